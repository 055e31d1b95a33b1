"""`uavmm tune`: fit the memory map's parameters and the size filter on an annotated set (PARAMS.json).

`uavmm boost/track --config PARAMS.json` and `uavmm agent --config PARAMS.json` (or --pipeline-config)
read the result.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from uavmm.cli import CliError, add_terrain_options, require_new_output, require_out_parent, terrain_from_args

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``tune`` subcommand."""
    p = sub.add_parser(
        "tune", help="fit the memory-map parameters and the size filter on an annotated set (PARAMS.json)",
        description="Fit the distance-size filter from the ground truth (its classes over the built-in priors, "
                    "or over the --config file's filter), then search the memory map's evidence per second, "
                    "forgetting half-life, Gaussian radius and boost weight for the best AP50 (pycocotools), "
                    "starting from the defaults. Every choice must beat its own noise: a gain of at least 2 "
                    "standard deviations of a bootstrap over 2-s time blocks (at least 8 of them), made again on "
                    "half of the videos (or the first half of one long video) and carried over to the other half, "
                    "or 3 standard deviations where nothing can be held out; a choice that does not stands down "
                    "and the start is written (docs/memory-map.md). Writes PARAMS.json for boost, track and agent "
                    "(--config). With --dem every run (the size filter's fits, the search, the held-out check) "
                    "georeferences on the terrain; PARAMS.json does not keep the DEM: give --dem to boost, track "
                    "and agent too.",
    )
    p.add_argument("--frames", type=Path, required=True, help="IMAGES.json with annotations and meta")
    p.add_argument("--candidates", type=Path, required=True, help="PRE_NMS.json (COCO result list)")
    p.add_argument("--camera", type=Path, required=True, help="CAMERA.json or a camera preset's name")
    p.add_argument("--out", type=Path, required=True, help="PARAMS.json to write")
    p.add_argument("--config", dest="start_config", type=Path, default=None,
                   help="start from this pipeline config or PARAMS.json (its settings and its size filter) instead "
                        "of the defaults")
    p.add_argument("--no-size-filter-fit", action="store_true",
                   help="keep the starting size filter (the built-in priors, or the --config file's)")
    p.add_argument("--no-holdout", action="store_true",
                   help="skip the held-out check (halves the run time; a choice then needs 3 sd in sample)")
    p.add_argument("--min-gain", type=float, default=0.2,
                   help="AP50 points any move must gain at least, beside beating its noise (0.2)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_terrain_options(p)
    p.set_defaults(handler=_run_tune)


def _run_tune(args: argparse.Namespace) -> int:
    from agent.boost import load_params
    from agent.tune import tune
    from shared.files import write_chunks_atomic

    require_out_parent(args.out)  # found before the work, not when writing after it
    require_new_output(args.out, args.frames, args.candidates, args.camera, args.start_config, args.dem)
    if not (args.min_gain >= 0):
        raise CliError(f"--min-gain must be >= 0, got {args.min_gain}")
    base, start_filter = load_params(args.start_config)
    terrain = terrain_from_args(args)
    if terrain is not None:  # every run's ground (fit, search, held-out check); not a setting PARAMS.json keeps
        base = dataclasses.replace(base, terrain=terrain)

    def progress(line: str) -> None:
        sys.stderr.write(f"uavmm tune: {line}\n")

    result = tune(args.frames, args.candidates, args.camera, base=base, start_filter=start_filter,
                  fit_size_filter=not args.no_size_filter_fit, min_gain=args.min_gain, holdout=not args.no_holdout,
                  progress=None if args.quiet else progress)
    write_chunks_atomic(args.out, [json.dumps(result.params(), indent=1)])  # a new temporary, on disk, renamed
    r = result.report
    start = "start" if args.start_config else "defaults"
    print(f"AP50: no memory {r['AP50_no_memory']:.2f}, {start} {r['AP50_start']:.2f}, search's best "
          f"{r['AP50_searched']:.2f}, written {r['AP50_tuned']:.2f} ({r['videos']} videos, {r['boxes']} boxes, "
          f"{r['time_blocks']} blocks of {r['rule']['block_s']:g} s, {r['pipeline_runs']} runs)")
    print(f"size filter: {r['size_filter']['used']} ({r['size_filter']['decision']})")
    if "holdout" in r:
        h = r["holdout"]
        where = (f"held-out videos {h['scored_on_videos']}" if h["split"] == "videos" else f"held out {h['scored_on']}")
        tuned_on = h["tuned_on_videos"] if h["split"] == "videos" else h["tuned_on"]
        print(f"{where} ({h['held_boxes']} boxes, {h['held_blocks']} blocks): no memory {h['AP50_no_memory']:.2f}, "
              f"{start} {h['AP50_start']:.2f}, tuned on {tuned_on} {h['AP50_tuned']:.2f}")
    kept = "tuned" if r["settings_acted"] else f"{start} kept"
    print(f"settings: {kept} ({r['settings_decision']}): {json.dumps(r['settings'])}")
    print(f"wrote {args.out}")
    return 0

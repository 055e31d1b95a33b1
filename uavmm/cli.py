"""The `uavmm` command line: one entry point, a subcommand per job (DESIGN.md 5).

Argument parsing lives here; each handler imports its module lazily and calls a typed main().
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from shared.files import same_file
from uavmm._signals import SERVER_COMMANDS, Terminated, terminate_as_interrupt

log = logging.getLogger("uavmm")

Handler = Callable[[argparse.Namespace], int]


class CliError(Exception):
    """A user error: printed as one line on stderr, exit code 2."""


def require_out_parent(*paths: Path | None) -> None:
    """CliError naming the folder when an output file's folder does not exist: checked before the work, so a
    long run does not end in an OSError about a file (or a temporary file) the user never named."""
    for path in paths:
        if path is not None and not path.parent.is_dir():
            raise CliError(f"output directory {path.parent} does not exist (for {path})")


#: (flag, path) pairs of `require_outputs_apart`; a path of None (a flag not given) is skipped.
FlagPaths = Iterable[tuple[str, Path | str | None]]


def require_outputs_apart(outputs: FlagPaths, inputs: FlagPaths) -> None:
    """CliError naming both flags when an output file is one of the run's input files (`track --out PRE_NMS.json`,
    through a link or another spelling as well) or when two outputs name one file (the later would replace the
    earlier): called before the work, so nothing is written over what the run reads or wrote.

    outputs: (flag, file the run writes) pairs, one per file (a folder output gives one pair per file it writes);
    inputs: (flag, file the run reads) pairs (a dataset's images: `uavmm.dataset_inputs`). Paths that do not exist
    are never inputs; two outputs are one when their real paths are equal (or they are one existing file). Inputs
    are iterated and stat'ed once, and only when an output exists already (a new file is none of them): thousands
    of images are cheap.
    """
    given_outputs = [(flag, out) for flag, out in outputs if out is not None]
    input_ids: dict[tuple[int, int], tuple[str, Path | str]] = {}
    if any(_file_id(out) is not None for _, out in given_outputs):
        for in_flag, path in inputs:
            if path is not None and (key := _file_id(path)) is not None:
                input_ids.setdefault(key, (in_flag, path))
    seen: list[tuple[str, Path | str]] = []
    for out_flag, out in given_outputs:
        out_id = _file_id(out)
        if out_id is not None and out_id in input_ids:  # os.path.samefile's test (`same_file`), one stat a path
            in_flag, path = input_ids[out_id]
            raise CliError(f"{out_flag} {out} is the {in_flag} input {path}: give another output path")
        for other_flag, other in seen:
            if same_file(out, other) or os.path.realpath(out) == os.path.realpath(other):
                raise CliError(f"{other_flag} {other} and {out_flag} {out} are one file: give each its own path")
        seen.append((out_flag, out))


def _file_id(path: Path | str) -> tuple[int, int] | None:
    """The (device, inode) of the existing file ``path`` names (links followed), or None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def require_new_output(out: Path, *inputs: Path | str | None) -> None:
    """CliError when an output file's path is a folder or one of the run's input files: writing it would have
    failed after the work, or put the results over the input they came from (`boost --out PRE_NMS.json`)."""
    if out.is_dir():
        raise CliError(f"{out} is a directory: give the output file's path")
    for path in inputs:
        if path is not None and out.exists() and Path(path).exists() and out.samefile(path):
            raise CliError(f"{out} is an input of this run ({path}): give another output path")


# --------------------------------------------------------------------------------------------- sim

def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim", help="write a simulated dataset (SeaDronesSee layout)",
        description="Simulate UAV flights over people/swimmers and write images.json, camera.json, "
                    "pre_nms.json and truth.json to --out. `uavmm sim --list` lists the scenarios.",
    )
    p.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.add_argument("--out", type=Path,
                   help="output directory: new, empty, or holding an earlier uavmm sim dataset (not rendered), which "
                        "is replaced")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--frames", type=int, default=None, help="frames per video, 1..36000 (default: the scenario's)")
    p.add_argument("--noise-scale", type=float, default=1.0,
                   help="multiply the scenario's telemetry noise levels (default 1.0)")
    p.add_argument("--image-size", metavar="WxH", default=None,
                   help="image size of the simulated camera, e.g. 1920x1080: even numbers, 16..8192 (default: the "
                        "scenario's, 3840x2160); boxes, candidates and camera.json follow it")
    p.add_argument("--render", action="store_true",
                   help="also draw the frames: the image files named in images.json (and with --video an MP4 "
                        "per video with SRT/CSV telemetry); --video implies it, and the rendering flags need one of "
                        "the two; not for terrain scenarios (hills, coop-slope); see uavmm render")
    from uavmm.render_args import add_render_options

    add_render_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_run_sim)


def _image_size(text: str) -> tuple[int, int]:
    """'1920x1080' -> (1920, 1080); CliError unless two even integers in 16..`sim.scenarios.MAX_IMAGE_SIDE_PX`."""
    from sim.scenarios import MAX_IMAGE_SIDE_PX

    parts = text.lower().split("x")
    try:
        width, height = (int(v) for v in parts)
    except ValueError:
        raise CliError(f"--image-size must look like 1920x1080, got {text!r}") from None
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise CliError(f"--image-size needs even numbers >= 16 (video encoders require it), got {text!r}")
    if max(width, height) > MAX_IMAGE_SIDE_PX:
        raise CliError(f"--image-size is at most {MAX_IMAGE_SIDE_PX} a side (the renderer's limit), got {text!r}")
    return width, height


def _run_sim(args: argparse.Namespace) -> int:
    from sim.scenarios import SCENARIOS, check_frames_per_video

    if args.list:
        for name, scenario in SCENARIOS.items():
            print(f"{name:10s} {scenario.description}")
        return 0
    if not args.scenario:
        raise CliError("give a SCENARIO (or --list)")
    if args.out is None:
        raise CliError("--out DIR is required")
    if args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    check_frames_per_video(args.frames, "--frames")
    from sim.scenarios import get_scenario
    from uavmm.render_args import print_render_summary, render_flags_given, render_kwargs

    scenario = get_scenario(args.scenario)
    render = args.render or args.video  # --video implies drawing the frames
    if not render and render_flags_given(args):
        raise CliError(f"{' '.join(render_flags_given(args))}: rendering flags, they go with --render or --video "
                       "(nothing is drawn without them)")
    if render and scenario.terrain is not None:
        raise CliError(f"--render: scenario {scenario.name} has a terrain and the renderer draws flat ground only "
                       "(simulate it without --render: the dataset needs no frames)")
    kwargs = render_kwargs(args) if render else None
    if args.image_size is not None:
        scenario = dataclasses.replace(scenario, image_size=_image_size(args.image_size))
    from sim.dataset import require_output_folder, write_dataset

    require_output_folder(args.out)  # before the work: nobody's files mixed in, no render left beside a new dataset
    summary = write_dataset(scenario, args.out, seed=args.seed, frames=args.frames,
                            noise_scale=args.noise_scale, progress=not args.quiet)
    print(f"wrote {args.out}: " + ", ".join(f"{k}={v}" for k, v in summary.items()))
    if kwargs is not None:
        from sim.render import render_dataset

        print_render_summary(render_dataset(args.out, progress=not args.quiet, **kwargs))
    return 0


# --------------------------------------------------------------------------------------------- boost

def _add_pipeline_options(p: argparse.ArgumentParser, *, config_flag: str = "--config",
                          joint_mode: bool = False) -> None:
    """The memory-map flags shared by boost, track and agent.

    config_flag: the pipeline JSON file's flag (networked processes keep --config for Zenoh); it is
    stored as `pipeline_config` either way. joint_mode: also offer --joint-mode (processes with a
    fusion server's joint map).
    """
    g = p.add_argument_group("memory map (defaults: the best measured; see docs/memory-map.md)")
    g.add_argument(config_flag, dest="pipeline_config", type=Path, default=None,
                   help="JSON file of pipeline/memory settings, or the PARAMS.json of `uavmm tune` (its "
                        "settings and fitted size filter); flags below override it")
    g.add_argument("--window-m", type=float, default=None, help="memory window edge, metres (300)")
    g.add_argument("--radius-m", type=float, default=None, help="Gaussian truncation radius, metres (4)")
    g.add_argument("--gain-per-s", type=float, default=None, help="evidence per second per unit confidence")
    g.add_argument("--half-life-s", type=float, default=None, help="forgetting half-life, seconds")
    g.add_argument("--boost-weight", type=float, default=None, help="c_hat = c + w * p (1)")
    g.add_argument("--anchor", choices=["auto", "center", "bottom"], default=None, help="box ground point")
    g.add_argument("--nms-iou", type=float, default=None, help="NMS IoU threshold (0.5)")
    g.add_argument("--max-detections", type=int, default=None, help="detections kept per frame (100)")
    g.add_argument("--size-filter", type=Path, default=None,
                   help="fitted size-filter file (uavmm fit-size-filter); default: built-in priors")
    g.add_argument("--size-filter-k", type=float, default=None, help="band half-width in std (3)")
    g.add_argument("--no-size-filter", action="store_true", help="do not filter boxes by size")
    add_terrain_options(p)
    if joint_mode:
        g.add_argument("--joint-mode", choices=["max", "local", "joint", "mean"], default=None,
                       help="how the joint map combines with the local one for boosting (max; local = ignore it)")
        g.add_argument("--no-joint-detections", action="store_true",
                       help="do not add detections for the other UAVs' evidence in view (docs/agent.md)")
        g.add_argument("--joint-min-value", type=float, default=None,
                       help="others' evidence a joint-map peak needs to become a detection (0.3)")
        g.add_argument("--joint-synth-factor", type=float, default=None,
                       help="score factor of boxes synthesised where no real candidate exists (default 0 = none)")
        g.add_argument("--joint-carry-s", type=float, default=None,
                       help="seconds this UAV's last sighting of an object the others see stands in for it "
                            "(0.5; 0 = off)")


def add_terrain_options(p: argparse.ArgumentParser) -> None:
    """--dem FILE and --takeoff-elevation-m METRES (read by `terrain_from_args`): every command that puts pixels on
    the ground (boost, track, agent, detect, anomaly, tune, fit-size-filter) takes the same two."""
    t = p.add_argument_group("terrain (docs/geometry.md, Terrain)")
    t.add_argument("--dem", type=Path, default=None, metavar="FILE",
                   help="georeference on this elevation model instead of flat ground: GeoTIFF or any raster GDAL "
                        "opens (needs the dem extra: rasterio), SRTM .hgt, or .npz (uavmm sim writes dem.npz)")
    t.add_argument("--takeoff-elevation-m", type=float, default=None, metavar="METRES",
                   help="--dem: elevation of the take-off point on the DEM's datum, the height the telemetry's "
                        "heights count from (0: heights above the datum, e.g. abs_alt above sea level; default: "
                        "the DEM's height under each video's first pose)")


def terrain_from_args(args: argparse.Namespace):
    """The Terrain --dem and --takeoff-elevation-m describe (`agent.dem.load_terrain`), or None without --dem;
    CliError for --takeoff-elevation-m alone, ValueError naming the file for a DEM that cannot be read."""
    if args.dem is not None:
        from agent.dem import load_terrain

        _klv_heights_on_the_dem(args)
        return load_terrain(args.dem, args.takeoff_elevation_m)
    if args.takeoff_elevation_m is not None:
        raise CliError("--takeoff-elevation-m needs --dem FILE")
    return None


def _klv_heights_on_the_dem(args: argparse.Namespace) -> None:
    """KLV telemetry with --dem: ST 0601 gives the sensor's altitude above sea level and the frame centre's, and
    without an offset the reader takes their difference, the height above the ground where the camera looks, which
    the DEM would then count from the take-off's elevation (13.7 m off on a 20 % slope in a probe). With neither
    --height-offset-m nor --takeoff-elevation-m the heights are the sensor's altitude above sea level and the
    take-off elevation 0 (the DEM's datum: sea level for SRTM and most GeoTIFFs), when the stream sends that altitude
    (tag 15; an ellipsoid height alone is metres off the geoid) and no --height-m is given; --takeoff-elevation-m
    alone gets a warning."""
    from shared.telemetry import KLV_FILE_SUFFIXES

    telemetry = getattr(args, "telemetry", None)
    if telemetry is None or getattr(args, "height_offset_m", "absent") == "absent":
        return
    klv = str(telemetry) == "klv" or Path(str(telemetry)).suffix.lower() in KLV_FILE_SUFFIXES
    if not klv or getattr(args, "height_m", None) is not None:  # --height-m: heights above the take-off, as given
        return
    if args.height_offset_m is None and args.takeoff_elevation_m is None:
        from agent.sources import resolve_video_telemetry
        from shared.telemetry import read_klv_report

        try:
            path = resolve_video_telemetry(telemetry, getattr(args, "video", None) or "")
            msl = any(s.sensor_alt_msl_m is not None for s in read_klv_report(path).samples)
        except (ValueError, OSError):
            return  # the video source names what is wrong with the file
        if not msl:  # the ellipsoid height alone is not on a DEM's (geoid) datum: left to the user
            return
        args.height_offset_m, args.takeoff_elevation_m = 0.0, 0.0
        log.info("KLV telemetry on the DEM %s: heights are the sensor's altitude above sea level (tag 15) and the "
                 "take-off elevation 0 (the DEM's datum; give --height-offset-m and --takeoff-elevation-m "
                 "otherwise)", args.dem)
    elif args.takeoff_elevation_m is not None and args.height_offset_m is None:
        log.warning("KLV telemetry on the DEM %s with --takeoff-elevation-m alone: the KLV's heights are above the "
                    "frame centre's ground unless --height-offset-m is given (0 with --takeoff-elevation-m 0: "
                    "altitudes above sea level on the DEM's datum)", args.dem)


def _add_clock_offset_flags(g: argparse._ArgumentGroup, *, fallback: str | None = None) -> None:
    """--clock-offset / --no-clock-offset (dest clock_offset: None = the configuration's, on by default).

    fallback: the flag that sets the offset used until it is measured, named in the help."""
    clock = g.add_mutually_exclusive_group()
    until = f"{fallback} is then its fallback" if fallback else "the telemetry as stamped until it is measured"
    clock.add_argument("--clock-offset", dest="clock_offset", action="store_true", default=None,
                       help="estimate the video/telemetry clock offset online from the detections and interpolate "
                            f"the telemetry at frame time + offset ({until}; the default, see docs/tracking.md)")
    clock.add_argument("--no-clock-offset", dest="clock_offset", action="store_false",
                       help="use the telemetry at its own stamps"
                            + (f" (turns are then compensated by {fallback} only)" if fallback else ""))


def _pipeline_from_args(args: argparse.Namespace, *, use_memory: bool):
    from agent.boost import load_params
    from agent.size_filter import SizeFilter

    overrides = {
        "window_m": args.window_m, "radius_m": args.radius_m, "gain_per_s": args.gain_per_s,
        "half_life_s": args.half_life_s, "boost_weight": args.boost_weight, "anchor": args.anchor,
        "nms_iou": args.nms_iou, "max_detections": args.max_detections,
        "joint_mode": getattr(args, "joint_mode", None),
        "joint_min_value": getattr(args, "joint_min_value", None),
        "joint_synth_factor": getattr(args, "joint_synth_factor", None),
        "joint_carry_s": getattr(args, "joint_carry_s", None),
    }
    cfg, tuned_filter = load_params(args.pipeline_config, overrides)
    cfg = dataclasses.replace(cfg, use_memory=use_memory and cfg.use_memory,
                              use_size_filter=cfg.use_size_filter and not args.no_size_filter,
                              joint_detections=cfg.joint_detections and not getattr(args, "no_joint_detections", False))
    # --size-filter FILE, else the one a `uavmm tune` parameters file carries, else the built-in priors
    size_filter = SizeFilter.load(args.size_filter) if args.size_filter else (tuned_filter or SizeFilter.builtin())
    if args.size_filter_k is not None:
        size_filter = dataclasses.replace(size_filter, k=args.size_filter_k)
    terrain = terrain_from_args(args)
    if terrain is not None:
        cfg = dataclasses.replace(cfg, terrain=terrain)
    return cfg, size_filter


def _add_boost(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "boost", help="memory-map boosting of pre-NMS detections (or the single-frame baseline)",
        description="Georeference each pre-NMS box, drop implausible sizes, boost its confidence by the "
                    "class's memory map at its ground cell, update the map, then NMS. Writes a COCO "
                    "result list. --no-memory gives the single-frame baseline (same filter and NMS).",
    )
    p.add_argument("--frames", type=Path, required=True, help="IMAGES.json (COCO with SeaDronesSee meta)")
    p.add_argument("--candidates", type=Path, required=True, help="PRE_NMS.json (COCO result list)")
    p.add_argument("--camera", type=Path, required=True,
                   help="CAMERA.json (width, height, fx, fy, cx, cy) or a camera preset's name")
    p.add_argument("--out", type=Path, required=True, help="RESULTS.json to write")
    p.add_argument("--no-memory", action="store_true", help="single-frame baseline: no boosting")
    p.add_argument("--corrections-out", type=Path, default=None, metavar="FILE.csv",
                   help="write the telemetry correction applied to each frame (east/north metres, measured or "
                        "held) and the clock offset the frame's pose was re-timed by, as CSV")
    _add_pipeline_options(p)
    _add_clock_offset_flags(p.add_argument_group("telemetry clock"))
    p.set_defaults(handler=_run_boost)


def _run_boost(args: argparse.Namespace) -> int:
    from agent.boost import StreamedResults, boost_dataset, write_corrections

    cfg, size_filter = _pipeline_from_args(args, use_memory=not args.no_memory)
    if args.clock_offset is not None:  # else the configuration's (on by default)
        cfg = dataclasses.replace(cfg, estimate_clock_offset=args.clock_offset)
    require_out_parent(args.out, args.corrections_out)
    inputs = (args.frames, args.candidates, args.camera, args.pipeline_config, args.size_filter, args.dem)
    for out in (args.out, args.corrections_out):
        if out is not None:
            require_new_output(out, *inputs)
    require_outputs_apart([("--out", args.out), ("--corrections-out", args.corrections_out)], [])
    corrections: list[tuple] | None = [] if args.corrections_out is not None else None
    spool = StreamedResults(args.out)  # written as the frames come; in place once the run ends well
    try:
        _, stats = boost_dataset(args.frames, args.candidates, args.camera, cfg, size_filter,
                                 corrections=corrections, sink=spool.extend)
    except BaseException:
        spool.abort()
        raise
    spool.close()
    if corrections is not None:
        write_corrections(corrections, args.corrections_out)
    print_run_summary(f"wrote {spool.count} detections to {args.out}", stats)
    if stats["candidates"] and stats["candidates"] - stats["size_filtered"] == stats["detections"]:
        print(f"  NMS removed none of the {stats['candidates']} candidates: they look like a detector's final output "
              "(post-NMS), not pre-NMS candidates; the memory map can only re-rank them (docs/memory-map.md, "
              "\"Pre-NMS candidates and a detector's final output\")")
    return 0


def print_run_summary(head: str, stats: dict) -> None:
    """A run's summary: the counters on one line, then the frames without pose by reason and what each
    adaptive stage did (agent.stage_report), one line each."""
    nested = ("stages", "frames_without_pose_by_reason")
    print(f"{head}: " + ", ".join(f"{k}={v}" for k, v in stats.items() if k not in nested))
    print_pose_and_stages(stats)


def print_pose_and_stages(stats: dict) -> None:
    """The frames without pose by reason and one line per adaptive stage, from a run's summary."""
    from agent.stage_report import stage_lines

    reasons = stats.get("frames_without_pose_by_reason") or {}
    if reasons:
        print(f"frames without pose: {sum(reasons.values())} (" + ", ".join(f"{k} {v}" for k, v in reasons.items())
              + ")")
    for line in stage_lines(stats.get("stages") or {}):
        print(f"  {line}")


def _add_fit_size_filter(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit-size-filter", help="fit the distance-size filter from a dataset with meta",
        description="Fit per class the metric box diameter (pixels x range / focal length) as a function "
                    "of the viewing depression from ground-truth boxes (range and depression to where each box's "
                    "ground point's ray meets the --dem terrain, when given), and save it for --size-filter. Each "
                    "class's spread is checked on its objects (track ids, else videos, or parts of a single "
                    "video) left out of the fit; a class with fewer than 20 boxes or 2 objects, or none of whose "
                    "objects can be left out and checked, gets no fitted band (a built-in class keeps its prior), "
                    "views without boxes are not judged, crowd and ignore regions are not fitted on, and the file "
                    "records the evidence (docs/memory-map.md).",
    )
    p.add_argument("--frames", type=Path, required=True, help="IMAGES.json with annotations and meta")
    p.add_argument("--camera", type=Path, required=True, help="CAMERA.json")
    p.add_argument("--out", type=Path, required=True, help="size-filter JSON to write")
    p.add_argument("--k", type=float, default=3.0, help="band half-width in standard deviations (3)")
    p.add_argument("--anchor", choices=["auto", "center", "bottom"], default="auto")
    add_terrain_options(p)
    p.set_defaults(handler=_run_fit_size_filter)


def _run_fit_size_filter(args: argparse.Namespace) -> int:
    from agent.size_filter import SizeFilter
    from agent.size_filter_fit import fit_from_dataset, left_out_text

    if not (args.k > 0 and args.k < float("inf")):
        raise CliError(f"--k must be a positive number, got {args.k}")
    terrain = terrain_from_args(args)
    require_out_parent(args.out)
    require_new_output(args.out, args.frames, args.camera, args.dem)
    left_out: dict[str, int] = {}
    sf, report = fit_from_dataset(args.frames, args.camera, k=args.k, anchor=args.anchor, terrain=terrain,
                                  left_out=left_out)
    skipped = [name for name, row in report.items() if not row["fitted"]]
    # every built-in class not fitted (no boxes, or too few objects) keeps its prior, as without a file and as
    # `uavmm tune` keeps them; at the file's k its spread is scaled to the width the built-in k gives
    builtin = SizeFilter.builtin()
    priors = sorted(set(builtin.bands) - set(sf.bands))
    for name in priors:
        band = builtin.bands[name]
        sf.bands[name] = dataclasses.replace(band, std_log=tuple(sd * (builtin.k / sf.k) for sd in band.std_log))
        if name in report:
            report[name]["band"] = "built-in prior (not fitted)"
    sf.save(args.out, evidence={"frames": str(args.frames), "camera": str(args.camera), "anchor": args.anchor,
                                "dem": None if args.dem is None else str(args.dem), "boxes_left_out": left_out,
                                "classes": report, "built_in_priors": priors})
    for name, row in report.items():
        print(f"{name}: " + ", ".join(f"{k}={v}" for k, v in row.items()))
    if any(left_out.values()):
        print(f"boxes not fitted on: {left_out_text(left_out)}")
    if kept := [name for name in skipped if name in priors]:
        print(f"not fitted, the built-in prior kept (as without a file): {', '.join(kept)}")
    if unfiltered := [name for name in skipped if name not in priors]:
        print(f"no band for {', '.join(unfiltered)}: with --size-filter {args.out} their boxes pass unfiltered")
    print(f"wrote {args.out}")
    return 0


# --------------------------------------------------------------------------------------------- bench

def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="run the performance benchmarks",
        description="Run benchmarks/ and print each figure beside a baseline measured in the same run.",
    )
    p.add_argument("names", nargs="*", help="benchmarks to run (default: all); see --list")
    p.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    p.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    p.set_defaults(handler=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    from benchmarks import BENCHMARK_MODULES, load_benchmark, run_benchmarks

    if args.list:
        for name in args.names or BENCHMARK_MODULES:  # an unknown name: ValueError, one line and exit 2
            print(f"{name:14s} {load_benchmark(name).DESCRIPTION}")
        return 0
    require_out_parent(args.json)  # before minutes of benchmarks, not after them
    try:  # unknown names and a --json path that cannot be written are refused before any benchmark runs
        rows = run_benchmarks(args.names or None, quick=args.quick, json_path=args.json,
                              progress=lambda line: print(line, file=sys.stderr, flush=True))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    from benchmarks import format_table

    print(format_table(rows))
    return 0


# --------------------------------------------------------------------------------------------- main

COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_sim, _add_boost, _add_fit_size_filter, _add_bench,
)
#: Modules that add their own subcommands: each has register(subparsers) and sets `handler`
#: (a function of the parsed Namespace returning an exit code) on its parser.
COMMAND_MODULES: tuple[str, ...] = ("uavmm.cmd_eval", "uavmm.cmd_fusion", "uavmm.cmd_agent", "uavmm.cmd_track",
                                     "uavmm.cmd_demo",
                                     "uavmm.cmd_secure", "uavmm.cmd_export", "uavmm.cmd_render", "uavmm.cmd_tune",
                                     "uavmm.cmd_detect", "uavmm.cmd_anomaly", "uavmm.cmd_gateway")


LOG_LEVELS = ["DEBUG", "INFO", "WARNING", "ERROR"]


def package_version() -> str:
    """The installed package's version (pyproject.toml), or "unknown" when run from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("uav-memory-maps")
    except PackageNotFoundError:
        return "unknown"


def _global_flags_everywhere(sub: argparse._SubParsersAction) -> None:
    """Accept the global flags after the subcommand too (``uavmm fusion --log-level INFO``, ``uavmm agent
    --version``).

    The copy's default is SUPPRESS, so a value given before the subcommand is kept when none is given after.
    """
    for parser in sub.choices.values():
        parser.add_argument("--log-level", choices=LOG_LEVELS, default=argparse.SUPPRESS,
                            help="logging level (stderr); also accepted before the subcommand")
        parser.add_argument("--version", action="version", version=f"uavmm {package_version()}",
                            help="print the version and exit")
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                _global_flags_everywhere(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavmm",
        description="uav-memory-maps: metadata-aware detection, tracking and cooperative mapping on drones.",
    )
    parser.add_argument("--log-level", default="WARNING", choices=LOG_LEVELS, help="logging level (stderr)")
    parser.add_argument("--version", action="version", version=f"uavmm {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(sub)
    _global_flags_everywhere(sub)
    return parser


def _innermost(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.ArgumentParser:
    """The deepest subcommand's parser that argv names (`uavmm secure init ...` -> init's)."""
    for token in argv:
        subs = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if subs is not None and token in subs.choices:
            parser = subs.choices[token]
    return parser


def _stdout_reader_left() -> bool:
    """Whether stdout is a pipe whose reader has gone (poll says error or hang-up); True where that cannot be asked
    (no poll, no file descriptor)."""
    try:
        import select

        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (AttributeError, ValueError, OSError):
        return True


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the (sub)subcommand's usage and one error line, not the top level's
        _innermost(parser, argv if argv is not None else sys.argv[1:]).error(
            f"unrecognized arguments: {' '.join(unknown)}")
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    if not getattr(args, "handler", None):
        parser.print_help(sys.stderr)
        return 2
    with terminate_as_interrupt():  # SIGTERM unwinds as Ctrl-C (uavmm._signals)
        try:
            return int(args.handler(args) or 0)
        except BrokenPipeError as exc:
            if _stdout_reader_left():  # `uavmm eval --list-domains | head`: nothing to say (Python's recipe)
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return 1
            print(f"uavmm {args.command}: error: {exc}", file=sys.stderr)  # another pipe (a child process's)
            return 2
        except (CliError, ValueError, OSError, ImportError) as exc:
            print(f"uavmm {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as exc:
            if isinstance(exc, Terminated):  # a server before its own handler (nothing open yet) stops as after it
                return 0 if args.command in SERVER_COMMANDS else 128 + signal.SIGTERM
            return 130


if __name__ == "__main__":
    # `python -m uavmm.cli`: run the imported module's main, whose CliError is the one the cmd_* modules raise (this
    # __main__ module's own class would not catch theirs: a traceback instead of one line and exit 2)
    from uavmm.cli import main as _main

    sys.exit(_main())

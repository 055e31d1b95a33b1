"""`uavmm eval`: the paper's tables on simulated data, the evaluation domains, the cooperative domains and a real
COCO file with meta, each beside its baselines (docs/simulator.md, docs/memory-map.md "Real data").

Registered through `uavmm.cli.COMMAND_MODULES`; argument parsing stays here, the work is in `sim`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from uavmm.cli import CliError, add_terrain_options, terrain_from_args
from uavmm.csv_args import csv_list


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `eval` subcommand to the `uavmm` parser."""
    p = sub.add_parser(
        "eval", help="the paper's tables on simulated data: baseline beside memory map",
        description="Simulate each scenario for each seed (cached under --out/data), run the single-frame "
                    "baseline and the memory map, score with pycocotools (AP50, AR@100), and write "
                    "report.json and report.md to --out. Progress goes to stderr.",
    )
    p.add_argument("--scenarios", default=None,
                   help="comma-separated scenarios (sea,grass; --tasks coop: the ones whose UAVs fly at once, "
                        "default coop, e.g. coop-slope)")
    p.add_argument("--seeds", default=None, help="comma-separated seeds (0,1,2)")
    p.add_argument("--frames", type=int, default=None, help="frames per video, 1..36000 (scenario default)")
    p.add_argument("--noise-scales", default=None, help="telemetry noise multipliers (1,2; --tasks coop: 1)")
    p.add_argument("--ablations", action="store_true", help="also sweep half-life, radius, gain, filter")
    p.add_argument("--tasks", default=None,
                   help="comma-separated: detection (AP50/AR), tracking (HOTA/MOTA/IDs/Frag vs norfair), "
                        "coop (two UAVs with a joint map), anomaly (rendered frames, docs/anomaly.md) "
                        "(default: detection; with --domains: detection,tracking)")
    p.add_argument("--domains", default=None,
                   help="comma-separated evaluation domains (sim.domains) or the groups all, tune, heldout (and "
                        "far: far, low views beyond the pipeline's range, for tracking): detection and tracking per "
                        "domain, held-out domains reported apart (seeds default 0,1,2; tasks detection,tracking). "
                        "With --tasks coop: the cooperative domains (sim.coop_domains; "
                        "the same groups), per UAV the detector, its own map and the joint map (first noise scale)")
    p.add_argument("--list-domains", action="store_true",
                   help="print the domains (with --tasks coop: the cooperative ones) as a table and exit")
    p.add_argument("--full", action="store_true", help="with --domains: 5x longer clips")
    real = p.add_argument_group("real data (docs/memory-map.md, Real data)")
    real.add_argument("--real", type=Path, default=None, metavar="IMAGES.json|DIR",
                      help="a real COCO file with meta (or a folder holding it, its detections and camera.json): "
                           "per class AP50/AR of the detector's own results, memory off, our defaults and the "
                           "paper's rule (report in --out/real)")
    real.add_argument("--detections", type=Path, default=None, metavar="RESULTS.json",
                      help="with --real: the detector's COCO results on it (default: the folder's detections*.json)")
    real.add_argument("--camera", default=None, metavar="CAMERA.json|PRESET",
                      help="with --real: the camera (default: the folder's camera.json)")
    real.add_argument("--config", dest="pipeline_config", type=Path, default=None, metavar="PARAMS.json",
                      help="with --real: our variant's settings (a pipeline config or `uavmm tune` parameters); "
                           "with --tasks coop: every variant's (e.g. a correction_anchor_s)")
    real.add_argument("--size-filter", type=Path, default=None, metavar="FILTER.json",
                      help="with --real: a fitted size filter (uavmm fit-size-filter) for our variant and memory off")
    add_terrain_options(p)  # with --real: every variant on the DEM's ground (the simulator has its own terrains)
    p.add_argument("--out", type=Path, default=Path("out/eval"), help="report directory (out/eval)")
    p.set_defaults(handler=_run_eval)


def _run_real_eval(args: argparse.Namespace) -> int:
    from agent.boost import load_params
    from sim.real_eval import real_files, run_real_eval

    images, detections, camera = real_files(args.real, args.detections, args.camera)
    out = args.out / "real"
    _require_out_dir(args.out)
    _require_out_dir(out)
    config, size_filter = load_params(args.pipeline_config)
    if args.size_filter is not None:
        from agent.size_filter import SizeFilter

        size_filter = SizeFilter.load(args.size_filter)
    report = run_real_eval(images, detections, camera, config=config, size_filter=size_filter, out_dir=out,
                           terrain=terrain_from_args(args))
    print((out / "report.md").read_text())
    print(f"reports: {out / 'report.md'}, {out / 'report.json'} ({report['seconds']} s)")
    return 0


def _csv_list(text: str, kind: type, flag: str) -> list:
    try:
        return csv_list(text, kind, flag)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _require_out_dir(out: Path) -> None:
    from uavmm.eval_domains import require_out_dir

    try:
        require_out_dir(out)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _run_eval(args: argparse.Namespace) -> int:
    from sim.evaluate import run_eval, stderr_progress
    from sim.scenarios import SCENARIOS, check_frames_per_video, get_scenario

    if args.real is not None:
        # the simulated evaluations' flags did nothing beside a real file, silently (`--real F --frames 30` ran all)
        unused = [flag for flag, value in (("--scenarios", args.scenarios), ("--seeds", args.seeds),
                                           ("--frames", args.frames), ("--noise-scales", args.noise_scales),
                                           ("--tasks", args.tasks), ("--domains", args.domains)) if value is not None]
        unused += [flag for flag, on in (("--ablations", args.ablations), ("--full", args.full),
                                         ("--list-domains", args.list_domains)) if on]
        if unused:
            raise CliError(f"{', '.join(unused)}: not used with --real (the file's frames are evaluated as they are)")
        return _run_real_eval(args)
    if any(v is not None for v in (args.detections, args.camera, args.size_filter, args.dem,
                                   args.takeoff_elevation_m)):
        raise CliError("--detections, --camera, --size-filter, --dem and --takeoff-elevation-m go with --real")
    if args.pipeline_config is not None and "coop" not in (args.tasks or "").split(","):
        raise CliError("--config goes with --real or --tasks coop")
    if args.full and args.domains is None and not args.list_domains:
        raise CliError("--full goes with --domains")
    if args.list_domains or args.domains is not None:
        from uavmm.eval_domains import run_domain_eval_command

        return run_domain_eval_command(args)

    scenarios = _csv_list(args.scenarios or "sea,grass", str, "--scenarios")
    for name in scenarios:
        get_scenario(name)  # unknown names fail before any work
    seeds = _csv_list(args.seeds if args.seeds is not None else "0,1,2", int, "--seeds")
    if any(s < 0 for s in seeds):
        raise CliError("--seeds must be >= 0")
    check_frames_per_video(args.frames, "--frames")
    from uavmm.eval_domains import noise_scales

    try:
        noise = tuple(noise_scales(args.noise_scales or "1,2"))
    except ValueError as exc:
        raise CliError(str(exc)) from None
    tasks = _csv_list(args.tasks or "detection", str, "--tasks")
    unknown = sorted(set(tasks) - {"detection", "tracking", "coop", "anomaly"})
    if unknown:
        raise CliError(f"--tasks: unknown task(s) {', '.join(unknown)}; valid: detection, tracking, coop, anomaly")
    coop_scenarios = ["coop"]
    if "coop" in tasks and args.scenarios is not None:  # the named scenarios whose UAVs fly at once
        coop_scenarios = [name for name in scenarios if get_scenario(name).simultaneous]
        if not coop_scenarios:
            raise CliError("--tasks coop: none of --scenarios flies its UAVs at once; valid: "
                           + ", ".join(sorted(n for n, sc in SCENARIOS.items() if sc.simultaneous)))
    _require_out_dir(args.out)
    if "detection" in tasks:
        report = run_eval(scenarios, seeds, frames=args.frames, noise_scales=noise, ablations=args.ablations,
                          out_dir=args.out, progress=stderr_progress)
        print((args.out / "report.md").read_text())
        print(f"reports: {args.out / 'report.md'}, {args.out / 'report.json'} ({report['seconds']} s)")
    if "tracking" in tasks:
        from sim.track_eval import run_track_eval

        out = args.out / "tracking"
        run_track_eval(scenarios, seeds, args.frames, out, stderr_progress)
        print((out / "report.md").read_text())
    if "coop" in tasks:
        from sim.coop_eval import run_coop_eval
        from uavmm.eval_domains import coop_params

        out = args.out / "coop"
        coop_config, coop_filter = coop_params(args.pipeline_config)
        run_coop_eval(seeds, frames=args.frames, out_dir=out, progress=stderr_progress,
                      scenarios=tuple(coop_scenarios), noise_scales=noise if args.noise_scales is not None else (1.0,),
                      config=coop_config, size_filter=coop_filter)
        print((out / "report.md").read_text())
    if "anomaly" in tasks:  # rendered frames; docs/anomaly.md
        from sim.anomaly_eval import run_anomaly_eval

        out = args.out / "anomaly"
        run_anomaly_eval(scenarios, seeds, frames=args.frames, out_dir=out, progress=stderr_progress)
        print((out / "report.md").read_text())
    return 0

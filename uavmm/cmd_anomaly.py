"""`uavmm anomaly` (regions of interest from anomaly heatmaps, per frame or through the ground memory layer)
and `uavmm anomaly-train` (the autoencoder). Registered through `uavmm.cli.COMMAND_MODULES`; docs/anomaly.md.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

from uavmm.cli import CliError, add_terrain_options, require_outputs_apart, terrain_from_args
from uavmm.cmd_detect import ProgressLine
from uavmm.dataset_inputs import DatasetImages


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `anomaly` and `anomaly-train` subcommands."""
    from agent.anomaly.registry import ANOMALY_METHODS, DEFAULT_METHOD

    p = sub.add_parser(
        "anomaly", help="regions of interest from anomaly heatmaps (COCO results, category anomaly)",
        description="Per-frame anomaly heatmaps (autoencoder, frame differencing after ego-motion compensation, "
                    "mean/median filter residual, MOG2) mapped below the horizon onto the ground grid, averaged "
                    "there with forgetting, read back into each frame; regions of interest are its connected "
                    "components above a threshold. Writes a COCO result list (category 'anomaly'). --no-memory "
                    "gives the per-frame baseline; --dem maps the heat onto the terrain instead of flat ground. See "
                    "docs/anomaly.md.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--frames", type=Path, help="IMAGES.json (image files relative to its folder)")
    src.add_argument("--video", type=Path, help="video file (with --telemetry)")
    p.add_argument("--telemetry", type=Path,
                   help="telemetry of --video: .srt (DJI), .csv, SeaDronesSee .json, MAVLink .tlog, PX4 .ulg, MISB "
                        "ST 0601 KLV (.ts/.m2ts/.mts video or raw .klv; the word 'klv' = the KLV inside the --video "
                        "transport stream)")
    p.add_argument("--telemetry-offset-s", type=float, default=None,
                   help="--video: telemetry time of the video's first frame, seconds on the telemetry's clock "
                        "(default: KLV in a transport stream tells it by its PTS; else where the log starts "
                        "recording, AirData's isVideo; else the first record's)")
    p.add_argument("--camera", required=True, help="CAMERA.json (or a camera preset's name)")
    p.add_argument("--out", type=Path, required=True, help="ROIS.json to write (COCO result list)")
    p.add_argument("--method", default=DEFAULT_METHOD,
                   help=f"heatmap method: {', '.join(sorted(ANOMALY_METHODS))} (default {DEFAULT_METHOD})")
    p.add_argument("--model", type=Path, default=None, help="ONNX autoencoder for --method autoencoder "
                                                            "(default: the shipped sea model)")
    p.add_argument("--no-memory", action="store_true", help="per-frame baseline: no ground aggregation")
    p.add_argument("--threshold", type=float, default=None, help="score a region needs (0.3)")
    p.add_argument("--half-life-s", type=float, default=None, help="forgetting half-life of the layer, s (0.75)")
    p.add_argument("--max-range-m", type=float, default=None, help="ground range mapped, m (120)")
    p.add_argument("--height-m", type=float, default=None, help="height above ground for telemetry without one")
    p.add_argument("--height-offset-m", type=float, default=None, metavar="METRES",
                   help="--video: metres added to every height the telemetry gives (e.g. minus the ground "
                        "elevation for DJI abs_alt or a KLV sensor altitude above sea level)")
    p.add_argument("--mavlink-system-id", type=int, default=None, metavar="N",
                   help="--video with a MAVLink .tlog: the vehicle's system id when the log carries several (default: "
                        "the one with the most positions; a warning names the others)")
    p.add_argument("--video-fps", type=float, default=None, metavar="FPS",
                   help="--video as a raw .h264/.h265 stream, which has no frame times: the rate it was recorded "
                        "at (default: the rate the stream states, else FFmpeg's guess of 25, with a warning)")
    p.add_argument("--telemetry-utc-offset-h", type=float, default=None, metavar="H",
                   help="--video with a DJI .srt: hours its date lines are ahead of UTC (DJI writes the drone's "
                        "local time; e.g. 2 for CEST; default: read as UTC)")
    p.add_argument("--pitch-deg", type=float, default=None, help="--video: fixed gimbal pitch if telemetry lacks it")
    p.add_argument("--heading-deg", type=float, default=None,
                   help="--video: fixed gimbal heading if telemetry lacks it")
    p.add_argument("--telemetry-as-written", action="store_true",
                   help="--video: keep GPS written with 3-5 decimals and altitude in whole or half metres as the "
                        "file has them (default: made continuous, docs/detect.md)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    add_terrain_options(p)
    p.set_defaults(handler=run_anomaly)

    t = sub.add_parser(
        "anomaly-train", help="train the anomaly autoencoder on rendered sea frames (needs the train extra)",
        description="Simulate and render sea scenes from fixed seeds (not used by the evaluation), train the "
                    "convolutional autoencoder on them and export ONNX. Needs PyTorch: pip install -e '.[train]'. "
                    "The defaults are the settings the shipped agent/anomaly/sea_autoencoder.onnx was trained with; "
                    "--out never names that file (write elsewhere, compare, copy deliberately).",
    )
    t.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    t.add_argument("--work-dir", type=Path, default=Path("out/anomaly-train"), help="rendered training scenes")
    t.add_argument("--seeds", default="100,101", help="simulator seeds of the training scenes (100,101)")
    t.add_argument("--frames", type=int, default=120, help="frames per video (120)")
    t.add_argument("--steps", type=int, default=1500, help="optimiser steps (1500)")
    t.add_argument("--quiet", action="store_true", help="no progress on stderr")
    t.set_defaults(handler=run_train)


def _config(args: argparse.Namespace):
    import dataclasses

    from agent.anomaly import AnomalyConfig, AnomalyMapConfig, make_method

    options = {"model": args.model} if args.model is not None else {}
    if args.model is not None and args.method != "autoencoder":
        raise ValueError(f"--model is for --method autoencoder, not {args.method}")
    method = make_method(args.method, **options)  # unknown names: one line listing the valid ones
    map_kw = {k: v for k, v in (("half_life_s", args.half_life_s), ("max_range_m", args.max_range_m)) if v is not None}
    cfg = AnomalyConfig(method=args.method, use_memory=not args.no_memory,
                        map=dataclasses.replace(AnomalyMapConfig(), **map_kw), terrain=terrain_from_args(args))
    if args.threshold is not None:
        cfg = dataclasses.replace(cfg, roi_threshold=args.threshold)
    return cfg, method


def run_anomaly(args: argparse.Namespace) -> int:
    """Handler of `uavmm anomaly`: returns the exit code; ValueError/OSError become one line and exit 2."""
    from agent.anomaly import ANOMALY_CLASS, AnomalyDetector
    from agent.anomaly.frames import VideoFrames, dataset_frames
    from agent.boost import StreamedResults
    from agent.telemetry_dequantize import describe_quanta
    from shared.geo import Camera

    if args.video is not None and args.telemetry is None:
        raise ValueError("--video needs --telemetry FILE")
    if args.frames is not None and args.telemetry is not None:
        raise ValueError("--telemetry goes with --video (--frames carries its telemetry in images.json meta)")
    for flag in ("height_m", "height_offset_m", "pitch_deg", "heading_deg", "mavlink_system_id",
                 "telemetry_utc_offset_h", "video_fps"):
        if args.frames is not None and getattr(args, flag) is not None:
            raise ValueError(f"--{flag.replace('_', '-')} goes with --video (--frames carries its telemetry in "
                             "images.json meta)")
    if args.frames is not None and args.telemetry_offset_s is not None:
        raise ValueError("--telemetry-offset-s goes with --video (--frames carries its times in images.json meta)")
    if args.frames is not None and args.telemetry_as_written:
        raise ValueError("--telemetry-as-written goes with --video (--frames takes each image's meta as written)")
    images = DatasetImages("--frames image", args.frames) if args.frames is not None else ()
    require_outputs_apart([("--out", args.out)], itertools.chain([
        ("--frames", args.frames), ("--video", args.video), ("--telemetry", args.telemetry), ("--camera", args.camera),
        ("--model", args.model), ("--dem", args.dem)], images))  # the images read only if --out exists
    # written as the frames come (an hour at 100 regions a frame held ~4 GiB until the end): a failed run leaves
    # nothing, Ctrl-C the regions of the frames done; a missing folder or a folder as --out is refused here
    spool = StreamedResults(args.out)
    cfg, method = _config(args)
    camera = Camera.from_spec(args.camera)
    video_frames = None if args.frames is not None else VideoFrames(
        args.video, args.telemetry, camera, height_m=args.height_m, telemetry_offset_s=args.telemetry_offset_s,
        height_offset_m=args.height_offset_m, pitch_deg=args.pitch_deg, heading_deg=args.heading_deg,
        system_id=args.mavlink_system_id, utc_offset_h=args.telemetry_utc_offset_h, video_fps=args.video_fps,
        dequantize=not args.telemetry_as_written)
    frames = dataset_frames(args.frames, camera) if video_frames is None else iter(video_frames)
    detector = AnomalyDetector(cfg, method)
    # as uavmm detect's: redrawn on a terminal, a line now and then in a pipe or file (it was "\r" redraws there)
    progress = ProgressLine("anomaly:", enabled=not args.quiet)
    video = None
    n = without_pose = 0
    started = time.perf_counter()
    try:
        for frame in frames:
            if frame.video != video:
                detector.reset()
                video = frame.video
            out = detector.process(frame.image, frame.pose, frame.t, frame.camera)
            spool.extend([{"image_id": frame.image_id, "category_id": 1, "category": ANOMALY_CLASS,
                           "bbox": [round(x0, 2), round(y0, 2), round(x1 - x0, 2), round(y1 - y0, 2)],
                           "score": round(float(score), 4)}
                          for (x0, y0, x1, y1), score in zip(out.boxes_xyxy.tolist(), out.roi_scores.tolist(),
                                                             strict=True)])
            n += 1
            without_pose += frame.pose is None
            progress(n, None)
    except KeyboardInterrupt:
        progress.close()
        spool.close()
        print(f"\nstopped: wrote {spool.count} regions of interest for the {n} frames done to {args.out}",
              file=sys.stderr)
        raise
    except BaseException:
        spool.abort()
        raise
    spool.close()
    progress.close()
    seconds = time.perf_counter() - started
    mode = ("per-frame" if args.no_memory else "memory map") + (f", terrain {args.dem.name}" if args.dem else "")
    # the telemetry file's GPS steps and holds
    made = describe_quanta(video_frames.quanta or {}, video_frames.holds) if video_frames is not None else ""
    continuous = f"; {made} made continuous" if made else ""
    print(f"wrote {spool.count} regions of interest for {n} frames to {args.out} ({args.method}, {mode}; "
          f"{without_pose} frames without telemetry{continuous}; {n / max(seconds, 1e-9):.1f} frames/s)")
    return 0


def run_train(args: argparse.Namespace) -> int:
    """Handler of `uavmm anomaly-train`: every flag, --out, --work-dir and PyTorch are checked (one line, exit 2)
    before the scenes are rendered; progress on stderr unless --quiet."""
    from sim.anomaly_train import check_paths, require_torch, train_autoencoder

    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise CliError(f"--seeds: expected comma-separated integers, got {args.seeds!r}") from None
    if not seeds or min(seeds) < 0:
        raise CliError(f"--seeds needs one or more integers >= 0, got {args.seeds!r}")
    for flag, value in (("--frames", args.frames), ("--steps", args.steps)):
        if value < 1:
            raise CliError(f"{flag} must be >= 1, got {value}")
    check_paths(args.out, args.work_dir)  # ValueError naming the path: one line, exit 2
    require_torch()  # ImportError naming the train extra: one line, exit 2
    if not args.quiet:
        print(f"anomaly-train: rendering {len(seeds)} sea scene(s) of {args.frames} frames a video into "
              f"{args.work_dir} (reused when complete), then {args.steps} training steps", file=sys.stderr)
    summary = train_autoencoder(args.out, work_dir=args.work_dir, seeds=seeds, frames=args.frames, steps=args.steps,
                                progress=not args.quiet, on_step=None if args.quiet else _StepProgress())
    print("trained: " + ", ".join(f"{k}={v}" for k, v in summary.items()))
    return 0


class _StepProgress:
    """Training steps on stderr: a bar redrawn in place on a terminal (at most 10 times a second), else a line
    per 10 %."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.started: float | None = None  # at the first step: rendering and loading are not steps
        self._last = -1.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if self.started is None:
            self.started = now
        mark = now if self.tty else float(10 * done // total)
        due = now - self._last >= 0.1 if self.tty else mark != self._last
        if not due and done != total:
            return
        self._last = mark
        left = f", {(total - done) * (now - self.started) / (done - 1):.0f} s left" if done > 1 else ""
        if self.tty:
            bar = "#" * (30 * done // total) + "." * (30 - 30 * done // total)
            end = "\n" if done == total else ""
            sys.stderr.write(f"\ranomaly-train [{bar}] {done}/{total} steps{left}\x1b[K{end}")
        else:
            sys.stderr.write(f"anomaly-train: step {done}/{total}{left}\n")
        sys.stderr.flush()

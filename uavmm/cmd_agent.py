"""`uavmm agent`: run one UAV's agent (source -> memory-map pipeline -> tracker -> Zenoh) until the source
ends, --duration passes or SIGINT/SIGTERM arrives; prints a ready line and a JSON summary on stdout.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from uavmm._signals import stop_on_signals
from uavmm._zenoh_args import add_zenoh_arguments, zenoh_options_from_args
from uavmm.cli import _add_pipeline_options, require_outputs_apart

log = logging.getLogger("uavmm.agent")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``agent`` subcommand."""
    p = sub.add_parser(
        "agent", help="run one UAV's agent: detect, boost with the memory map, track, publish over Zenoh",
        description="Play a simulator scenario, a dataset directory or a video with telemetry and an ONNX model; "
                    "run the memory-map pipeline (boosted by the joint map from the fusion server) and the GPS "
                    "tracker; publish the memory-map tiles, state and tracks over Zenoh. See docs/agent.md.",
    )
    p.add_argument("--uav-id", required=True, help="this UAV's id (one key chunk, e.g. uav1)")
    src = p.add_argument_group("source (exactly one of --sim, --dataset, --video)")
    choice = src.add_mutually_exclusive_group(required=True)
    choice.add_argument("--sim", metavar="SCENARIO", help="fly a simulator scenario (uavmm sim --list)")
    choice.add_argument("--dataset", metavar="DIR", type=Path,
                        help="play a dataset directory (images.json, pre_nms.json, camera.json)")
    choice.add_argument("--video", metavar="FILE", type=Path, help="play a video file (needs --telemetry --model "
                                                                   "--camera)")
    src.add_argument("--seed", type=int, default=0, help="--sim: random seed; agents of one scenario share it (0)")
    src.add_argument("--uav-index", type=int, default=0, help="--sim: which of the scenario's UAVs to fly (0)")
    src.add_argument("--frames", type=int, default=None, help="--sim: frames of the flight (scenario default)")
    src.add_argument("--noise-scale", type=float, default=1.0, help="--sim: telemetry noise multiplier (1)")
    src.add_argument("--video-id", default=None, metavar="ID|NAME",
                     help="--dataset: which video, by id or name (a SeaDronesSee v2 source.video; default: the first)")
    src.add_argument("--telemetry-as-stamped", action="store_true",
                     help="--dataset: each frame keeps the telemetry sample it carries, as a live feed gives it "
                          "(default: the recording is read as `uavmm track` reads it: time zone, telemetry at frame "
                          "time, clock offset, view cuts; the summary's stages say what acted)")
    src.add_argument("--telemetry", type=Path,
                     help="--video: telemetry file (.srt, .csv, SeaDronesSee .json, MAVLink .tlog, PX4 .ulg, MISB "
                          "ST 0601 KLV in .ts/.m2ts/.mts or raw .klv), 'klv' for the KLV inside the --video "
                          "transport stream, or a live MAVLink stream udp:HOST:PORT (docs/agent.md)")
    src.add_argument("--model", type=Path, help="--video: ONNX YOLO model with raw (pre-NMS) output")
    src.add_argument("--camera", type=Path,
                     help="--video: camera JSON (width, height, fx, fy, cx, cy) or a preset name (e.g. "
                          "dji-mavic2-pro); --dataset: instead of its camera.json")
    src.add_argument("--class-names", type=Path, default=None, help="--video: class names file (model's default)")
    src.add_argument("--conf-threshold", type=float, default=0.01, help="--video: lowest candidate score (0.01)")
    src.add_argument("--telemetry-offset-s", type=float, default=None,
                     help="--video: telemetry time of video time 0 (default: from the PTS for KLV in a transport "
                          "stream, else where the log starts recording, AirData's isVideo, else the first record's)")
    src.add_argument("--mavlink-system-id", type=int, default=None, metavar="N",
                     help="--video: " + "MAVLink telemetry (.tlog, udp:HOST:PORT): the vehicle's system id "
                          "when the log or link carries several (default: a .tlog's vehicle with the most positions, a "
                          "live link's first; a warning names the others)")
    src.add_argument("--video-fps", type=float, default=None, metavar="FPS",
                     help="--video as a raw .h264/.h265 stream, which has no frame times: the rate it was recorded "
                          "at (default: the rate the stream states, else FFmpeg's guess of 25, with a warning)")
    src.add_argument("--telemetry-utc-offset-h", type=float, default=None, metavar="H",
                     help="--video with a DJI .srt: hours its date lines are ahead of UTC (DJI writes the drone's "
                          "local time; e.g. 2 for CEST; default: read as UTC)")
    src.add_argument("--pitch-deg", type=float, default=None, help="--video: fixed gimbal pitch if telemetry lacks it")
    src.add_argument("--heading-deg", type=float, default=None,
                     help="--video: fixed gimbal heading if telemetry lacks it")
    src.add_argument("--height-m", type=float, default=None, metavar="METRES",
                     help="--video: height above the ground for telemetry records without one (some DJI SRT "
                          "firmware logs none)")
    src.add_argument("--height-offset-m", type=float, default=None, metavar="METRES",
                     help="--video: metres added to every logged height, e.g. -(ground elevation) when the "
                          "telemetry gives altitude above sea level (DJI abs_alt)")

    add_zenoh_arguments(p)
    net = p.add_argument_group("publishing")
    net.add_argument("--prefix", default="uavmm/v1", help="key prefix (uavmm/v1)")
    net.add_argument("--publish-hz", type=float, default=5.0, help="publish cycles a second (5)")
    net.add_argument("--refresh-s", type=float, default=1.0,
                     help="resend unchanged tiles this often; below the server's --ttl-s (1)")
    net.add_argument("--tile-min-value", type=float, default=0.05,
                     help="send cells below this value as 0 to save bandwidth (0.05; 0 = all)")
    net.add_argument("--tile-budget", type=float, default=70_000.0, metavar="BYTES_PER_S",
                     help="most tile bytes a second, stalest tiles first (70000; 0 = no limit)")
    net.add_argument("--joint-ttl-s", type=float, default=3.0, help="a joint tile boosts this long after arrival (3)")
    net.add_argument("--gid-gate-m", type=float, default=10.0,
                     help="a new local track adopts a global id within this distance, m (10)")
    net.add_argument("--grid-z", type=int, default=18, help="zoom of the shared tile grid (18)")
    net.add_argument("--grid-n", type=int, default=256, help="cells per tile edge of the shared grid (256)")
    run = p.add_argument_group("run")
    run.add_argument("--speed", type=float, default=1.0, help="playback speed, 1 = real time, 0 = as fast as possible")
    run.add_argument("--replay-sync-s", type=float, default=30.0, metavar="S",
                     help="a replay takes up another UAV's source clock when it leads by at most S seconds (it "
                          "started earlier), so recordings of one flight line up in the joint map; 0: off")
    run.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    run.add_argument("--loop", action="store_true", help="start the source again when it ends")
    run.add_argument("--tracks-out", type=Path, default=None, help="write the tracks (with global ids) as GeoJSON")
    run.add_argument("--detections-out", type=Path, default=None, metavar="FILE",
                     help="write the final detections (boosted, NMS'd, joint-aware) as a COCO result list: image "
                          "ids of --dataset, frame indices otherwise; score it like `uavmm boost` output")
    _add_pipeline_options(p, config_flag="--pipeline-config", joint_mode=True)
    p.add_argument("--no-memory", action="store_true", help="single-frame baseline: no boosting at all")
    p.add_argument("--anomaly", metavar="METHOD", default=None,
                   help="also run anomaly detection on the frames' pixels (autoencoder, diff, mean, median, mog2) "
                        "and publish its ground layer as tiles of class 'anomaly' (--video, or --dataset with "
                        "image files; on the --dem terrain when given; docs/anomaly.md)")
    p.set_defaults(handler=_run_agent)


def anomaly_from_args(args: argparse.Namespace, terrain=None):
    """The anomaly detector --anomaly asks for, or None; ValueError for an unknown method or a source without
    pixels. terrain: the pipeline's (--dem), whose surface the anomaly layer maps the heat onto as well."""
    if args.anomaly is None:
        return None
    if args.sim is not None:
        raise ValueError("--anomaly needs the frames' pixels: use --video or --dataset with rendered images")
    from agent.anomaly import AnomalyConfig, AnomalyDetector

    return AnomalyDetector(AnomalyConfig(method=args.anomaly, terrain=terrain))


#: The --video source's flags (default None), refused beside --sim / --dataset.
_VIDEO_ONLY = ("telemetry", "model", "class_names", "telemetry_offset_s", "mavlink_system_id", "video_fps",
               "telemetry_utc_offset_h", "pitch_deg", "heading_deg", "height_m", "height_offset_m")


def source_from_args(args: argparse.Namespace, *, dequantize: bool = True):
    """The frame source the flags describe; ValueError for missing companion flags or bad files. dequantize: a
    --video's telemetry file made continuous where it is quantised (`VideoSource`)."""
    from agent.dataset_source import DatasetSource
    from agent.sources import VideoSource

    if args.video is None:  # a --video flag beside --sim / --dataset did nothing, silently
        given = [f"--{name.replace('_', '-')}" for name in _VIDEO_ONLY if getattr(args, name, None) is not None]
        if given:
            raise ValueError(f"{', '.join(given)} go{'es' if len(given) == 1 else ''} with --video, not "
                             f"{'--sim' if args.sim is not None else '--dataset'}")
    if getattr(args, "telemetry_as_stamped", False) and args.dataset is None:
        raise ValueError("--telemetry-as-stamped goes with --dataset (--sim and --video read telemetry as it comes)")
    if args.sim is not None:
        from sim.source import SimSource  # the simulated source lives with the simulator (sim imports agent)

        return SimSource(args.sim, seed=args.seed, uav_index=args.uav_index, frames=args.frames,
                         noise_scale=args.noise_scale)
    if args.dataset is not None:
        return DatasetSource(args.dataset, video_id=args.video_id, camera=args.camera,
                             telemetry_as_stamped=args.telemetry_as_stamped)
    missing = [flag for flag, value in (("--telemetry", args.telemetry), ("--model", args.model),
                                        ("--camera", args.camera)) if value is None]
    if missing:
        from shared.camera import CAMERA_PRESETS

        what = {"--telemetry": "--telemetry FILE (.srt, .csv, .json, .tlog, .ulg, KLV, udp:HOST:PORT)",
                "--model": "--model M.onnx (a YOLO ONNX export with raw, pre-NMS output: docs/detect.md, Inputs)",
                "--camera": f"--camera C.json or a preset ({', '.join(sorted(CAMERA_PRESETS))})"}
        raise ValueError(f"--video needs {'; '.join(what[flag] for flag in missing)}")
    return VideoSource(args.video, args.telemetry, args.model, args.camera,
                       telemetry_offset_s=args.telemetry_offset_s, class_names=args.class_names,
                       conf_threshold=args.conf_threshold, pitch_deg=args.pitch_deg, heading_deg=args.heading_deg,
                       height_m=args.height_m, height_offset_m=args.height_offset_m,
                       system_id=args.mavlink_system_id, utc_offset_h=args.telemetry_utc_offset_h,
                       video_fps=args.video_fps, dequantize=dequantize)


def settings_from_args(args: argparse.Namespace):
    """AgentSettings from parsed flags; ValueError on bad values."""
    from agent.node import AgentSettings

    zenoh_options = zenoh_options_from_args(args)
    return AgentSettings(
        uav_id=args.uav_id, zenoh=zenoh_options, prefix=args.prefix, publish_hz=args.publish_hz,
        refresh_s=args.refresh_s, tile_min_value=args.tile_min_value,
        tile_budget_bytes_per_s=args.tile_budget if args.tile_budget > 0 else None, joint_ttl_s=args.joint_ttl_s,
        speed=args.speed, replay_sync_s=args.replay_sync_s, duration_s=args.duration, loop=args.loop,
        gid_gate_m=args.gid_gate_m,
        grid_z=args.grid_z, grid_n=args.grid_n, tracks_out=args.tracks_out, detections_out=args.detections_out,
    )


def pipeline_from_args(args: argparse.Namespace):
    """(PipelineConfig, SizeFilter) from the pipeline flags (as `uavmm boost` reads them)."""
    from uavmm.cli import _pipeline_from_args

    return _pipeline_from_args(args, use_memory=not args.no_memory)


def params_from_config_flag(args: argparse.Namespace) -> None:
    """Let ``--config`` name a `uavmm tune` parameters file (DESIGN.md section 5) as well as a Zenoh config.

    A parameters file (JSON with ``"format": "uavmm-params"``) moves to ``--pipeline-config``; anything
    else stays the Zenoh config. ValueError when a parameters file comes twice.
    """
    from agent.params_file import is_params

    if args.config is None:
        return
    try:
        data = json.loads(Path(args.config).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return  # JSON5 or unreadable: Zenoh reads it (and names the problem)
    if not is_params(data):
        return
    if args.pipeline_config is not None:
        raise ValueError(f"--config {args.config} is a parameters file and --pipeline-config "
                         f"{args.pipeline_config} gives another: give one")
    args.pipeline_config, args.config = args.config, None


def input_files(args: argparse.Namespace) -> list[tuple[str, Path | str | None]]:
    """(flag, path) of every file the run reads (a --dataset folder's images, candidates and camera files), for
    `require_outputs_apart`; a flag not given has None."""
    files: list[tuple[str, Path | str | None]] = [
        ("--video", args.video), ("--telemetry", args.telemetry), ("--model", args.model), ("--camera", args.camera),
        ("--class-names", args.class_names), ("--pipeline-config", args.pipeline_config),
        ("--size-filter", args.size_filter), ("--dem", args.dem), ("--config", args.config)]
    if args.dataset is not None and args.dataset.is_dir():
        from agent.dataset import dataset_files

        try:
            files += [("--dataset", path) for path in dataset_files(args.dataset, camera=args.camera)]
        except ValueError:
            pass  # the source names what is missing
    return files


def _run_agent(args: argparse.Namespace) -> int:
    from agent.node import AgentNode

    params_from_config_flag(args)
    for flag, path in (("--tracks-out", args.tracks_out), ("--detections-out", args.detections_out)):
        if path is not None and not path.parent.is_dir():  # before the flight, not after it
            raise ValueError(f"{flag}: output directory {path.parent} does not exist (for {path})")
    require_outputs_apart([("--tracks-out", args.tracks_out), ("--detections-out", args.detections_out)],
                          input_files(args))
    settings = settings_from_args(args)
    from agent.zenoh_config import agent_zenoh_config, identity_problem
    from transport.certificates import check_certificates

    conf = agent_zenoh_config(settings.zenoh)
    problem = identity_problem(conf, settings.uav_id)
    if problem is not None:
        raise ValueError(problem)
    check_certificates(conf, log)
    pipeline_config, size_filter = pipeline_from_args(args)
    anomaly = anomaly_from_args(args, pipeline_config.terrain)
    source = source_from_args(args, dequantize=pipeline_config.dequantize_telemetry)
    stop = stop_on_signals(log)

    def on_ready(node: AgentNode) -> None:
        from agent.zenoh_config import AGENT_DEFAULT_MODE

        options = settings.zenoh
        mode = options.mode or ("mode from config" if options.config_file else AGENT_DEFAULT_MODE)
        where = ", ".join(options.connect or options.listen or ("endpoints from config/scouting",))
        sys.stdout.write(f"uavmm agent: {settings.uav_id} up: {source.name}, zenoh {mode} {where}\n")
        sys.stdout.flush()

    node = AgentNode(settings, source, pipeline_config, size_filter, on_ready=on_ready, anomaly=anomaly)
    summary = node.run(stop)
    sys.stdout.write("uavmm agent: summary " + json.dumps(summary, sort_keys=True) + "\n")
    sys.stdout.flush()
    return 0

"""`uavmm detect`: a recorded flight (video + telemetry) through the agent's detector, memory map and tracker,
offline, into COCO, MOTChallenge, GeoJSON, KML and optionally an annotated MP4 (docs/detect.md).

Argument parsing and the progress line live here; the work is in `agent.offline`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from uavmm.cli import CliError, _add_pipeline_options, _pipeline_from_args, print_pose_and_stages, require_outputs_apart


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `detect` subcommand."""
    p = sub.add_parser(
        "detect", help="offline: video + telemetry + ONNX model -> COCO, MOT, GeoJSON, KML (+ annotated MP4)",
        description="Run the agent's chain over a recorded flight without a network: the ONNX detector's pre-NMS "
                    "candidates, georeferenced with the telemetry, size filter, memory-map boosting, NMS and the "
                    "GPS tracker. Writes into --out: detections.json (COCO results) with images.json (the frames "
                    "and their telemetry as SeaDronesSee meta), tracks.txt (MOTChallenge), tracks.geojson, "
                    "objects.geojson, tracks.kml, summary.json and with --render-video annotated.mp4. "
                    "See docs/detect.md.",
    )
    p.add_argument("video", type=Path, help="video file (anything OpenCV opens)")
    p.add_argument("--telemetry", required=True,
                   help="telemetry: .srt (DJI), .csv, SeaDronesSee .json, MAVLink .tlog, PX4 .ulg, MISB ST 0601 KLV "
                        "(.ts/.m2ts/.mts video or raw .klv; the word 'klv' = the KLV inside VIDEO), or a live "
                        "MAVLink stream udp:HOST:PORT / udpin:HOST:PORT (docs/agent.md, Telemetry)")
    p.add_argument("--model", type=Path, required=True, help="ONNX YOLO model with raw (pre-NMS) output")
    p.add_argument("--camera", type=Path, required=True,
                   help="camera JSON (width, height, fx, fy, cx, cy) or a preset name (e.g. dji-mavic2-pro); "
                        "fitted to the video's frame size when they differ (a warning says so)")
    p.add_argument("--out", type=Path, required=True, help="output directory (created if missing)")
    p.add_argument("--render-video", action="store_true",
                   help="also write annotated.mp4: boxes, track ids, trails on the ground, memory-map inset")
    p.add_argument("--trail-s", type=float, default=2.0, help="--render-video: trail length, seconds (2)")
    p.add_argument("--no-inset", action="store_true", help="--render-video: no memory-map inset")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--dataset-files", action="store_true",
                   help="also write pre_nms.json (every frame's pre-NMS candidates) and camera.json: --out is then a "
                        "dataset directory (with images.json) that boost, track and agent --dataset read without "
                        "running the detector again (tune and eval --real too, once ground truth is added)")
    p.add_argument("--one-pass", action="store_true",
                   help="run each frame as it comes, as the live agent does (default: read the recording as a file, "
                        "in two passes: the detector over the whole video, then the clock-offset estimate, view cuts "
                        "hidden by sparse telemetry and the adaptive stages on all of it, then memory map and "
                        "tracker; the candidates wait in a temporary file in --out, ~28 bytes each)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    det = p.add_argument_group("detector")
    det.add_argument("--providers", default="CPUExecutionProvider",
                     help="onnxruntime execution providers in order of preference, comma-separated; full names "
                          "or cpu, cuda, tensorrt, openvino, ... (CPUExecutionProvider)")
    det.add_argument("--slices", metavar="CxR", default=None,
                     help="sliced inference: run the model on C x R overlapping tiles of each frame (e.g. 2x2 for "
                          "small objects in 4K frames) plus the whole frame; candidates merged before the memory map")
    det.add_argument("--slice-overlap", type=float, default=0.2, help="--slices: tile overlap, fraction (0.2)")
    det.add_argument("--no-full-frame", action="store_true",
                     help="--slices: tiles only (objects larger than the overlap may be cut)")
    det.add_argument("--class-names", type=Path, default=None, help="class names file (default: the model's)")
    det.add_argument("--conf-threshold", type=float, default=0.01, help="lowest candidate score kept (0.01)")
    tel = p.add_argument_group("telemetry")
    tel.add_argument("--telemetry-offset-s", type=float, default=None,
                     help="telemetry time of video time 0 (the first frame's, unless a stream starts mid-GOP), "
                          "seconds on the telemetry's clock "
                          "(default: KLV in a transport stream tells it by its PTS; else where the log starts "
                          "recording, AirData's isVideo; else the first record's)")
    tel.add_argument("--telemetry-timeout-s", type=float, default=10.0,
                     help="udp:HOST:PORT: seconds to wait for the first MAVLink position (10)")
    tel.add_argument("--mavlink-system-id", type=int, default=None, metavar="N",
                     help="MAVLink telemetry (.tlog, udp:HOST:PORT): the vehicle's system id "
                          "when the log or link carries several (default: a .tlog's vehicle with the most positions, a "
                          "live link's first; a warning names the others)")
    tel.add_argument("--video-fps", type=float, default=None, metavar="FPS",
                     help="the video as a raw .h264/.h265 stream, which has no frame times: the rate it was recorded "
                          "at (default: the rate the stream states, else FFmpeg's guess of 25, with a warning)")
    tel.add_argument("--telemetry-utc-offset-h", type=float, default=None, metavar="H",
                     help="a DJI .srt: hours its date lines are ahead of UTC (DJI writes the drone's local time; "
                          "e.g. 2 for CEST; default: read as UTC)")
    tel.add_argument("--pitch-deg", type=float, default=None, help="fixed gimbal pitch if telemetry lacks it")
    tel.add_argument("--heading-deg", type=float, default=None, help="fixed gimbal heading if telemetry lacks it")
    tel.add_argument("--height-m", type=float, default=None, metavar="METRES",
                     help="height above the ground for records without one")
    tel.add_argument("--height-offset-m", type=float, default=None, metavar="METRES",
                     help="metres added to every logged height (e.g. -(ground elevation) for altitude above sea)")
    g = p.add_argument_group("tracker")
    g.add_argument("--tracker-config", type=Path, default=None, help="JSON file of TrackerConfig settings")
    _add_pipeline_options(p)
    p.add_argument("--no-memory", action="store_true", help="single-frame baseline: no boosting")
    p.set_defaults(handler=run)


class ProgressLine:
    """Progress on stderr: a bar redrawn in place on a terminal; otherwise a line per 10 % (or per 500 frames
    when the total is unknown), so logs stay short."""

    def __init__(self, label: str, enabled: bool = True, first_pass: str = "") -> None:
        """first_pass: added to the label until the count starts again (the second pass of `uavmm detect`)."""
        self.base_label = label
        self.label = label + first_pass
        self._last_done = 0
        self._last_call = time.monotonic()
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.started = time.monotonic()
        self._last_draw = 0.0
        self._last_step = -1

    def __call__(self, done: int, total: int | None) -> None:
        if not self.enabled:
            return
        if done < self._last_done:  # the count started again: the second pass (memory map and tracker)
            self.close()
            self.label = f"{self.base_label} (pass 2: memory map, tracker)"
            self.started = self._last_call  # from the end of pass one: the stages between count in its first frame
            self._last_step = -1
        self._last_done = done
        if done == 0:  # the announcement of a pass (run_detect's before pass two): nothing done to show yet
            return
        self._last_call = time.monotonic()
        elapsed = max(time.monotonic() - self.started, 1e-9)
        rate = done / elapsed
        if self.tty:
            now = time.monotonic()
            if now - self._last_draw < 0.1 and done != total:
                return
            self._last_draw = now
            if total:
                filled = int(30 * done / total)
                eta = (total - done) / max(rate, 1e-9)
                text = f"[{'#' * filled}{'.' * (30 - filled)}] {done}/{total} frames, {rate:.1f}/s, {eta:.0f} s left"
            else:
                text = f"{done} frames, {rate:.1f}/s"
            sys.stderr.write(f"\r{self.label} {text}\x1b[K")
        else:
            step = int(10 * done / total) if total else done // 500
            if step == self._last_step and done != total:
                return
            self._last_step = step
            of = f"/{total}" if total else ""
            sys.stderr.write(f"{self.label} {done}{of} frames, {rate:.1f}/s\n")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            sys.stderr.write("\n")
            sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    """Handler of `uavmm detect`: validate, build the source, run, print where the files are."""
    from agent.offline import DetectOptions, prepare_out_dir, run_detect
    from agent.offline.outputs import OPTIONAL_OUTPUTS, OUTPUT_FILES
    from agent.offline.two_pass import can_look_ahead
    from agent.slicing import SliceGrid
    from agent.sources import VideoSource
    from agent.tracking_io import load_tracker_config

    # the files it writes into --out have fixed names: none may be one the run reads (VIDEO as annotated.mp4 there)
    asked = {"--render-video": args.render_video, "--dataset-files": args.dataset_files}
    written = [name for kind, name in OUTPUT_FILES.items()
               if kind not in OPTIONAL_OUTPUTS or asked[OPTIONAL_OUTPUTS[kind]]]
    require_outputs_apart([("--out", args.out / name) for name in written], [
        ("VIDEO", args.video), ("--telemetry", args.telemetry), ("--model", args.model), ("--camera", args.camera),
        ("--class-names", args.class_names), ("--tracker-config", args.tracker_config),
        ("--config", args.pipeline_config), ("--size-filter", args.size_filter), ("--dem", args.dem)])
    options = DetectOptions(render_video=args.render_video, trail_s=args.trail_s,
                            inset_fraction=0.0 if args.no_inset else 0.28, max_frames=args.max_frames,
                            two_pass=not args.one_pass, dataset_files=args.dataset_files)
    slices = SliceGrid.parse(args.slices, args.slice_overlap) if args.slices else None
    if args.slices is None and (args.no_full_frame or args.slice_overlap != 0.2):
        raise CliError("--slice-overlap and --no-full-frame need --slices")
    providers = [p for p in args.providers.split(",") if p.strip()]
    pipeline_config, size_filter = _pipeline_from_args(args, use_memory=not args.no_memory)
    tracker_config = load_tracker_config(args.tracker_config)
    prepare_out_dir(args.out)  # a bad --out fails before the model loads
    source = VideoSource(args.video, args.telemetry, args.model, args.camera,
                         telemetry_offset_s=args.telemetry_offset_s, class_names=args.class_names,
                         conf_threshold=args.conf_threshold, pitch_deg=args.pitch_deg, heading_deg=args.heading_deg,
                         height_m=args.height_m, height_offset_m=args.height_offset_m, providers=providers,
                         slices=slices, slice_full_frame=not args.no_full_frame,
                         telemetry_timeout_s=args.telemetry_timeout_s, system_id=args.mavlink_system_id,
                         utc_offset_h=args.telemetry_utc_offset_h, video_fps=args.video_fps,
                         dequantize=pipeline_config.dequantize_telemetry)
    two_passes = not args.one_pass and can_look_ahead(source) is None  # as run_detect decides
    progress = ProgressLine(f"detect {args.video.name}", enabled=not args.quiet,
                            first_pass=" (pass 1: detector)" if two_passes else "")
    try:
        summary = run_detect(source, args.out, pipeline_config, size_filter, tracker_config, options=options,
                             progress=progress)
    finally:
        progress.close()
    print(f"uavmm detect: {summary['frames']} frames ({summary['frames_without_pose']} without telemetry), "
          f"{summary['detections']} detections, {summary['tracks']} tracks in {summary['seconds']} s")
    print_pose_and_stages(summary)
    for kind, path in summary["files"].items():
        print(f"  {kind:16s} {path}")
    return 0

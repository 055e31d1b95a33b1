"""`uavmm track`: memory-map pipeline plus GPS tracker over a dataset, MOTChallenge (and GeoJSON) out.

Registered through `uavmm.cli.COMMAND_MODULES`; argument parsing stays here, the work is in
`agent.tracking_io.track_dataset`.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from pathlib import Path

from uavmm.cli import (
    CliError,
    _add_clock_offset_flags,
    _add_pipeline_options,
    _pipeline_from_args,
    print_pose_and_stages,
    require_outputs_apart,
)
from uavmm.dataset_inputs import DatasetImages


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `track` subcommand to the `uavmm` parser."""
    p = sub.add_parser(
        "track", help="GPS-space multi-object tracking with long-term re-ID (MOTChallenge output)",
        description="Run the memory-map pipeline on pre-NMS detections, then track the boosted detections "
                    "on the ground (constant-velocity Kalman filter in metres, Mahalanobis gating, optimal "
                    "assignment, re-identification of objects that left the view). Writes MOTChallenge rows "
                    "frame,id,x,y,w,h,score,-1,-1,-1 (frame = frame_index + 1). --out: a file for one video "
                    "(--video-id, or a dataset with one video); with several videos one file per video beside "
                    "it (<stem>_<video name>.txt); a directory (existing, or ending in /) gets "
                    "<video name>.txt per video. See docs/tracking.md.",
    )
    p.add_argument("--frames", type=Path, required=True, help="IMAGES.json (COCO with SeaDronesSee meta)")
    p.add_argument("--candidates", type=Path, required=True, help="PRE_NMS.json (COCO result list)")
    p.add_argument("--camera", type=Path, required=True, help="CAMERA.json (width, height, fx, fy, cx, cy)")
    # a str, not a Path: a trailing slash (a directory to create) must survive
    p.add_argument("--out", type=str, required=True, help="TRACKS.txt, or a directory (see above)")
    p.add_argument("--video-id", default=None, metavar="ID|NAME",
                   help="track only this video, by id or name (a SeaDronesSee v2 source.video; default: all)")
    p.add_argument("--geojson", type=Path, default=None,
                   help="also write the tracks as GeoJSON (a LineString per track and video, with times)")
    p.add_argument("--image-dir", type=Path, default=None,
                   help="where the images' file_name are (default: beside --frames); frames whose image file "
                        "exists get colour-histogram appearance descriptors for re-ID, others are tracked without")
    p.add_argument("--no-images", action="store_true",
                   help="do not read images (motion and the candidates' descriptors only)")
    p.add_argument("--no-memory", action="store_true",
                   help="baseline: our tracker on single-frame detections (no boosting)")
    g = p.add_argument_group("tracker (defaults: the best measured; see docs/tracking.md)")
    g.add_argument("--tracker-config", type=Path, default=None, help="JSON file of TrackerConfig settings")
    g.add_argument("--reid-horizon-s", type=float, default=None, help="how long lost tracks are remembered (30)")
    g.add_argument("--max-coast-s", type=float, default=None, help="unmatched time before a track is lost (1)")
    g.add_argument("--birth-score", type=float, default=None, help="detector score that starts a track (0.5)")
    g.add_argument("--report-quality", type=float, default=None,
                   help="minimum running detector score of a reported track (0.4)")
    g.add_argument("--telemetry-latency-s", type=float, default=None,
                   help="how much older the telemetry is than its stamp (0.05)")
    _add_clock_offset_flags(g, fallback="--telemetry-latency-s")
    p.add_argument("--clock-offsets-out", type=Path, default=None, metavar="FILE.csv",
                   help="write the clock offset applied to each frame (image_id, "
                        "video_id, frame_index, offset_s, measured)")
    p.add_argument("--registrations-out", type=Path, default=None, metavar="FILE.csv",
                   help="write the pose correction the tracker's image registration applied to each frame "
                        "(image_id, video_id, frame_index, east_m, north_m, heading_deg, pitch_deg, registered, "
                        "carried)")
    _add_pipeline_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Handler of `uavmm track`: validate, run, print a summary; returns the exit code."""
    from agent.tracking_io import load_tracker_config, track_dataset

    inputs = [("--frames", args.frames), ("--candidates", args.candidates), ("--camera", args.camera),
              ("--config", args.pipeline_config), ("--size-filter", args.size_filter), ("--dem", args.dem),
              ("--tracker-config", args.tracker_config)]
    extras = [("--geojson", args.geojson), ("--clock-offsets-out", args.clock_offsets_out),
              ("--registrations-out", args.registrations_out)]
    # the image files read for appearance (thousands: images.json read and each stat'ed only if an output exists)
    images = (() if args.no_images else
              DatasetImages("--image-dir image" if args.image_dir is not None else "--frames image", args.frames,
                            args.image_dir))
    require_outputs_apart([("--out", args.out), *extras], itertools.chain(inputs, images))  # each video's file later

    def check_mot_paths(paths: dict[int, Path]) -> None:
        require_outputs_apart([*((f"--out (video {v})", p) for v, p in paths.items()), *extras],
                              itertools.chain(inputs, images))

    pipeline_config, size_filter = _pipeline_from_args(args, use_memory=not args.no_memory)
    if args.clock_offset is not None:  # else the configuration's (on by default)
        pipeline_config = dataclasses.replace(pipeline_config, estimate_clock_offset=args.clock_offset)
    if pipeline_config.estimate_clock_offset and args.telemetry_latency_s is not None:
        if not abs(args.telemetry_latency_s) <= pipeline_config.clock_offset_search_s:
            raise CliError(f"--telemetry-latency-s must be within +-{pipeline_config.clock_offset_search_s} s, "
                           f"got {args.telemetry_latency_s}")
        pipeline_config = dataclasses.replace(pipeline_config, clock_offset_fallback_s=args.telemetry_latency_s)
    tracker_config = load_tracker_config(args.tracker_config, {
        "reid_horizon_s": args.reid_horizon_s, "max_coast_s": args.max_coast_s, "birth_score": args.birth_score,
        "report_quality": args.report_quality, "telemetry_latency_s": args.telemetry_latency_s,
    })
    summary = track_dataset(args.frames, args.candidates, args.camera, args.out, pipeline_config, tracker_config,
                            size_filter, video_id=args.video_id, geojson_path=args.geojson,
                            image_dir=args.image_dir, use_images=not args.no_images,
                            clock_offsets_path=args.clock_offsets_out,
                            registrations_path=args.registrations_out, check_outputs=check_mot_paths)
    for video_id, path in summary["files"].items():
        print(f"video {video_id}: {summary['tracks'][video_id]} tracks -> {path}")
    if "clock_offset_median_s" in summary:
        print(f"clock offset: median {summary['clock_offset_median_s']} s, measured on "
              f"{summary['clock_offset_frames_measured']} frames"
              + (f" -> {summary['clock_offsets']}" if "clock_offsets" in summary else ""))
    if "geojson" in summary:
        print(f"geojson: {summary['geojson_features']} features -> {summary['geojson']}")
    if "registrations" in summary:
        print(f"registrations: {summary['frames_registered']} of {summary['frames']} frames "
              f"({summary['frames_carried']} carried) -> {summary['registrations']}")
    keys = ("rows", "frames", "frames_without_pose", "frames_registered", "frames_carried", "reidentified",
            "pipeline_ms_per_frame", "tracker_ms_per_frame",
            "images_read", "images_missing", "appearance_ms_per_image", "seconds")
    print(", ".join(f"{k}={summary[k]}" for k in keys))
    print_pose_and_stages(summary)
    return 0

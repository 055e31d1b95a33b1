"""`uavmm detect`: the agent's whole per-frame chain (detector, memory-map pipeline, GPS tracker) over one video
with its telemetry, offline (no Zenoh), collecting what `agent.offline.outputs` writes.

The same pieces as the live agent (`agent.node.AgentNode.step`), minus the joint map and the network: a frame
from `agent.sources.VideoSource` (telemetry interpolated to the frame, camera fitted to the frame size) ->
`DetectionPipeline.process` -> appearance descriptors -> `GpsTracker.update`. By default the recording is read
as a file, in two passes (`agent.offline.two_pass`: the detector over the whole video, then the clock offset,
the view cuts and the adaptive stages on all of it, then the chain); `DetectOptions(two_pass=False)` runs each
frame as it comes.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent.boost import StreamedResults, candidates_to_coco, results_to_coco
from agent.offline.annotate import VideoAnnotator
from agent.offline.outputs import OUTPUT_FILES, StreamedImages, image_entry, write_outputs, write_text_atomic
from agent.offline.two_pass import FilePasses, can_look_ahead
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.sources import FrameSource
from agent.stage_report import StageSummary
from agent.track_rows import TrackRowLog
from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking.appearance import with_image_descriptors
from agent.tracking_io import memory_evidence

__all__ = ["DetectOptions", "prepare_out_dir", "run_detect"]

log = logging.getLogger(__name__)

#: progress(frames done, frames expected or None); in two passes the count starts again for pass two, announced by
#: progress(0, its frames)
Progress = Callable[[int, int | None], None]


@dataclass(frozen=True, slots=True)
class DetectOptions:
    """What `run_detect` writes besides the files every run gets.

    render_video: also write the annotated MP4; trail_s: trail length in it, seconds; inset_fraction: edge of
    the memory-map inset over the frame's shorter side (0 = none); max_frames: stop after this many frames.
    two_pass: read the recording as a file (`agent.offline.two_pass`: the detector over the whole video first,
    then the clock offset, view cuts and the adaptive stages on all of it); False, or a source that cannot be
    read twice (a live telemetry stream): one pass, each frame as it comes, as the live agent runs.
    dataset_files: also write pre_nms.json (every frame's pre-NMS candidates, a COCO result list) and camera.json
    (the camera as fitted to the frames): with images.json --out is then a dataset directory that `uavmm boost`,
    `track`, `tune`, `eval --real` and `agent --dataset` read, without the detector again.
    """

    render_video: bool = False
    trail_s: float = 2.0
    inset_fraction: float = 0.28
    max_frames: int | None = None
    two_pass: bool = True
    dataset_files: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.trail_s) and self.trail_s >= 0):
            raise ValueError(f"trail length must be >= 0 s, got {self.trail_s!r}")
        if not 0 <= self.inset_fraction <= 0.5:
            raise ValueError(f"inset fraction must be in 0..0.5, got {self.inset_fraction!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"--max-frames must be >= 1, got {self.max_frames}")


def prepare_out_dir(out_dir: str | Path) -> Path:
    """Create the output directory (and parents) if needed; OSError naming it when it cannot be written."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".uavmm-write-test-", dir=out)  # a new name: never through a planted link
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OSError(f"output directory {out} is not writable: {exc.strerror or exc}") from None
    return out


def _remove_stale_dataset_files(out: Path) -> list[str]:
    """An earlier `--dataset-files` run's pre_nms.json and camera.json in ``out``, removed (with a warning) now that
    images.json describes other frames: beside it they made a dataset whose candidates belong to another run (`uavmm
    track` refused it for unknown image ids, or, the frame count equal, mixed them in silently). Returns their names."""
    removed = []
    for kind in ("candidates", "camera"):
        path = out / OUTPUT_FILES[kind]
        if path.is_file() or path.is_symlink():
            path.unlink()
            removed.append(path.name)
    if removed:
        log.warning("removed %s of an earlier run from %s: they belonged to its images.json, not this one's (keep them "
                    "with --dataset-files)", " and ".join(removed), out)
    return removed


def run_detect(source: FrameSource, out_dir: str | Path, pipeline_config: PipelineConfig | None = None,
               size_filter: SizeFilter | None = None, tracker_config: TrackerConfig | None = None, *,
               options: DetectOptions | None = None, progress: Progress | None = None) -> dict[str, Any]:
    """Run the detector, memory map and tracker over every frame of `source`; write the outputs into out_dir.

    Parameters
    ----------
    source : FrameSource
        Usually `agent.sources.VideoSource` (its ``fps``, ``frame_count`` and ``video_path`` are used when
        present); frames must carry their image for ``render_video``.
    out_dir : path
        Created if missing. Files: see `agent.offline.outputs.OUTPUT_FILES` (docs/detect.md).
    pipeline_config, size_filter, tracker_config : optional
        As for `uavmm boost` / `uavmm track` (no joint map offline).
    options : DetectOptions, optional
    progress : callable, optional
        Called after each frame with (frames done, frames expected or None), in two passes for each pass.

    Returns
    -------
    dict
        Summary: counts (frames, frames_without_pose, candidates, detections, tracks, track_rows), timing
        (ms per frame of detector+decoding, pipeline, tracker, drawing) and the written files.

    The source is closed at the end. A failing frame stops the run (no partial output files: every file is
    written at the end, atomically; the video's temporary file is removed).
    """
    options = options or DetectOptions()
    out = prepare_out_dir(out_dir)
    config = pipeline_config or PipelineConfig()
    pipe = DetectionPipeline(source.camera, source.class_names, config, size_filter=size_filter)
    why_one_pass = "--one-pass" if not options.two_pass else can_look_ahead(source)
    passes = None if why_one_pass is not None else FilePasses(source, config, out)
    tracker = GpsTracker(tracker_config, source.class_names, evidence_at=memory_evidence(pipe))
    video_path = getattr(source, "video_path", None)
    video_name = Path(video_path).stem if video_path is not None else source.name
    total = getattr(source, "frame_count", None)
    if options.max_frames is not None:
        total = options.max_frames if total is None else min(total, options.max_frames)
    annotator: VideoAnnotator | None = None
    # the detections and the frames go to their files as they come (held to the end, they were ~9 KB a frame:
    # ~0.3 GB an hour at 10 frames/s); the files are put in place at the end, removed when the run fails
    detections = StreamedResults(out / OUTPUT_FILES["detections"])
    candidates = StreamedResults(out / OUTPUT_FILES["candidates"]) if options.dataset_files else None
    images = StreamedImages(out / OUTPUT_FILES["images"])
    streamed: list[StreamedResults | StreamedImages] = [s for s in (detections, candidates, images) if s is not None]
    hfovs: list[float] = []  # each frame's field of view, written when the lens zoomed (below)
    zoomed = False
    rows = TrackRowLog()  # 104 B a row (as objects ~665 B: ~840 MB an hour of 30 fps video with ~20 people)
    counts = {"frames": 0, "frames_without_pose": 0, "candidates": 0, "size_filtered": 0, "detections": 0}
    seconds = {"source": 0.0, "pipeline": 0.0, "tracker": 0.0, "draw": 0.0}
    t_prev = -math.inf
    started = time.perf_counter()
    try:
        if passes is not None:  # pass one: the detector over the whole video, then the file stages
            passes.detect(pipe, options.max_frames, progress, total)
            seconds["source"] += passes.detector_s
            total = len(passes)
            if progress is not None and total:
                progress(0, total)  # pass two begins (a one-frame video's count would not go back)
        frames = iter(source.frames() if passes is None else passes.frames())
        while options.max_frames is None or counts["frames"] < options.max_frames:
            t0 = time.perf_counter()
            frame = next(frames, None)
            t1 = time.perf_counter()
            if frame is None:
                break
            seconds["source"] += t1 - t0
            if pipe.camera != frame.camera:
                pipe.camera = frame.camera
            result = pipe.process(frame.boxes_xyxy, frame.scores, frame.class_ids, frame.pose, frame.t,
                                  frame.embeddings)
            if frame.image is not None:
                result = with_image_descriptors(result, frame.image)
            t2 = time.perf_counter()
            t = max(frame.t, t_prev)
            t_prev = t
            tracks = tracker.update(result, frame.pose, t, frame.camera, pose_t=frame.pose_t,
                                    pose_retimed=frame.pose_retimed, terrain=pipe.terrain_for(frame.pose))
            reported = tracker.report(tracks)
            t3 = time.perf_counter()
            seconds["pipeline"] += t2 - t1
            seconds["tracker"] += t3 - t2
            rows.extend(frame.index, t, reported)
            detections.extend(results_to_coco(frame.index, result))
            if candidates is not None:
                candidates.extend(candidates_to_coco(frame.index, frame.boxes_xyxy, frame.scores, frame.class_ids))
            images.add(image_entry(frame.index, t, frame.camera.width, frame.camera.height, frame.pose,
                                   frame.pose_t))
            hfovs.append(frame.camera.hfov_deg)
            base = getattr(source, "camera", None)
            zoomed |= base is not None and frame.camera is not base and frame.camera.fx != base.fx
            counts["frames"] += 1
            counts["frames_without_pose"] += frame.pose is None
            counts["candidates"] += result.n_candidates
            counts["size_filtered"] += result.n_size_filtered
            counts["detections"] += len(result)
            if options.render_video:
                if frame.image is None:
                    raise ValueError(f"{source.name} gives no images: --render-video needs a video source")
                if annotator is None:
                    annotator = VideoAnnotator(out / OUTPUT_FILES["video"], float(getattr(source, "fps", 30.0)),
                                               frame.image.shape[1], frame.image.shape[0], source.class_names,
                                               trail_s=options.trail_s, inset_fraction=options.inset_fraction,
                                               range_m=config.range_limit_m)
                annotator.write(frame.image, t, frame.camera, frame.pose, result, reported, pipe.memory)
                seconds["draw"] += time.perf_counter() - t3
            if progress is not None:
                progress(counts["frames"], total)
    except BaseException:
        if annotator is not None:
            annotator.abort()
        for stream in streamed:
            stream.abort()
        raise
    finally:
        if passes is not None:
            passes.close()
        source.close()
    if annotator is not None:
        annotator.close()
    try:
        if candidates is not None:  # first: a failure here leaves the dataset's other files where they were
            write_text_atomic(out / OUTPUT_FILES["camera"], json.dumps(source.camera.to_dict(), indent=1))
        # a zoom lens: every frame with a pose carries its field of view (`hfov_deg`, read back by the dataset
        # reader), its unzoomed ones too: one left out would take its neighbours' when read as telemetry
        images.close(source.class_names, video_name, source=str(video_path or source.name),
                     hfovs=hfovs if zoomed else None)
        detections.close()
        if candidates is not None:
            candidates.close()
    except BaseException:
        for stream in streamed:
            stream.abort()
        raise
    files = write_outputs(out, detections=None, images=None, rows=rows, class_names=source.class_names,
                          video_name=video_name, source=str(video_path or source.name))
    if annotator is not None:
        files["video"] = str(annotator.path)
    if candidates is not None:
        files["candidates"] = str(candidates.path)
        files["camera"] = str(out / OUTPUT_FILES["camera"])
    stale = [] if candidates is not None else _remove_stale_dataset_files(out)
    n = max(counts["frames"], 1)
    summary: dict[str, Any] = {
        **counts,
        "tracks": rows.track_ids(), "track_rows": len(rows),
        "reidentified": tracker.n_reidentified,
        "source_ms_per_frame": round(1000 * seconds["source"] / n, 2),
        "pipeline_ms_per_frame": round(1000 * seconds["pipeline"] / n, 3),
        "tracker_ms_per_frame": round(1000 * seconds["tracker"] / n, 3),
        "draw_ms_per_frame": round(1000 * seconds["draw"] / n, 2) if annotator is not None else None,
        "seconds": round(time.perf_counter() - started, 3),
        "files": files,
    }
    stages = StageSummary()
    source_reports = getattr(source, "stage_reports", None)  # its telemetry file's (VideoSource: dequantisation)
    for report in [*(source_reports() if callable(source_reports) else []),
                   *(passes.reports if passes is not None else []), *pipe.stage_reports(),
                   *tracker.stage_reports()]:
        stages.add(report)
    summary["two_pass"] = passes is not None
    if stale:
        summary["removed_stale"] = stale
    if passes is not None and passes.missing_images:
        summary["frames_without_image"] = passes.missing_images
    if why_one_pass is not None:
        summary["one_pass_because"] = why_one_pass
    summary["stages"] = stages.as_dict()
    problems = getattr(source, "problems", 0)
    if isinstance(problems, int) and problems:
        summary["frames_with_unusable_telemetry"] = problems
    summary_path = out / OUTPUT_FILES["summary"]
    write_text_atomic(summary_path, json.dumps(summary, indent=1))
    summary["files"]["summary"] = str(summary_path)
    log.info("detect %s: %s", video_name, {k: v for k, v in summary.items() if k != "files"})
    return summary

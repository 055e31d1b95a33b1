"""`uavmm boost`: run the memory-map pipeline (or the single-frame baseline) over a dataset.

Reads IMAGES.json + PRE_NMS.json + CAMERA.json, writes a COCO result list.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.clock_offset import ClockOffset
from agent.dataset import Candidates, Dataset, PoseProblem, VideoTelemetry, count_reasons, read_json
from agent.file_frames import prepared_frames, telemetry_reports
from agent.frame_result import FrameResult
from agent.memory_map import MemoryMapConfig
from agent.params_file import is_params, split_params
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig, refuse_huge_int
from agent.size_filter import SizeFilter
from agent.stage_report import StageSummary
from shared.files import PendingFile, write_chunks_atomic
from shared.geo import Camera

log = logging.getLogger(__name__)


def config_from_dict(d: dict[str, Any], base: PipelineConfig | None = None) -> PipelineConfig:
    """A PipelineConfig from a flat or nested mapping ({"memory": {...}, "nms_iou": ...}).

    Unknown keys raise ValueError listing the valid ones.
    """
    base = base or PipelineConfig()
    if not isinstance(d, dict):
        raise ValueError(f"config must be a JSON object, got {type(d).__name__}")
    mem_fields = {f.name for f in dataclasses.fields(MemoryMapConfig)}
    pipe_fields = {f.name for f in dataclasses.fields(PipelineConfig)} - {"memory", "terrain"}  # terrain: --dem
    mem_kw: dict[str, Any] = {}
    pipe_kw: dict[str, Any] = {}
    for key, value in d.items():
        refuse_huge_int(key, value)
        if key == "memory":
            if not isinstance(value, dict):
                raise ValueError("config 'memory' must be an object")
            for k2, v2 in value.items():
                if k2 not in mem_fields:
                    raise ValueError(f"unknown memory setting {k2!r}; valid: {', '.join(sorted(mem_fields))}")
                refuse_huge_int(f"memory.{k2}", v2)
                mem_kw[k2] = v2
        elif key in mem_fields:
            mem_kw[key] = value
        elif key in pipe_fields:
            pipe_kw[key] = value
        else:
            valid = ", ".join(sorted(pipe_fields | mem_fields))
            raise ValueError(f"unknown setting {key!r}; valid: {valid}")
    memory = dataclasses.replace(base.memory, **mem_kw)
    return dataclasses.replace(base, memory=memory, **pipe_kw)


def load_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> PipelineConfig:
    """Config file (JSON) then command-line overrides (None values ignored).

    The file is a pipeline config or a parameters file of `uavmm tune` (its ``pipeline`` part; the size
    filter it carries comes from `load_params`).
    """
    return load_params(path, overrides)[0]


def load_params(path: str | Path | None,
                overrides: dict[str, Any] | None = None) -> tuple[PipelineConfig, SizeFilter | None]:
    """(config, the fitted size filter a `uavmm tune` parameters file carries, else None).

    The file (a pipeline config or a parameters file, agent.params_file) then the command-line
    overrides (None values ignored). ValueError naming the file and the setting on bad content.
    """
    cfg = PipelineConfig()
    size_filter = None
    if path is not None:
        data = read_json(path, "config")
        if is_params(data):
            data, size_filter = split_params(data, str(path))
        try:
            cfg = config_from_dict(data, cfg)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"config {path}: {exc}") from None
    if overrides:
        cfg = config_from_dict({k: v for k, v in overrides.items() if v is not None}, cfg)
    return cfg, size_filter


def run_pipeline(dataset: Dataset, candidates: Candidates, camera: Camera, config: PipelineConfig,
                 size_filter: SizeFilter | None = None, *, video_ids: list[int] | None = None,
                 on_frame=None, clock_offsets: dict[int, ClockOffset] | None = None) -> dict[str, Any]:
    """Run the pipeline over every video; on_frame(frame, result) is called per frame.

    With config.estimate_clock_offset (the default) each video's poses are first re-timed by the online
    video/telemetry clock-offset estimate (agent.clock_offset.video_frames), as `uavmm track` does, so the
    boxes are stamped and boosted where the camera looked when the frame was taken.

    Returns counts: frames, frames_without_pose, candidates, size_filtered, detections, seconds, the
    telemetry correction's: frames_corrected (frames whose offset was measured) and correction_median_m
    (median length of the applied offsets; per frame in FrameResult.correction and the DEBUG log), and,
    when the clock offset is estimated, clock_offset_median_s and clock_offset_frames_measured (per frame
    in ``clock_offsets``: a dict image id -> ClockOffset, filled when given).
    """
    stats: dict[str, Any] = {"frames": 0, "frames_without_pose": 0, "candidates": 0, "size_filtered": 0,
                             "detections": 0}
    problems: list[PoseProblem] = []
    stages = StageSummary()
    t0 = time.perf_counter()
    pipeline_time = 0.0
    corrections: list[float] = []
    offsets = clock_offsets if clock_offsets is not None else {}
    settings = config.clock_offset_settings()
    for video_id in video_ids if video_ids is not None else list(dataset.videos):
        if video_id not in dataset.videos:
            raise ValueError(f"unknown video_id {video_id}; known: {sorted(dataset.videos)}")
        pipe = DetectionPipeline(camera, dataset.categories, config, size_filter=size_filter)
        telemetry = VideoTelemetry()
        retimed = prepared_frames(dataset, camera, video_id, candidates, config, pipe, problems=problems,
                                  report=telemetry)
        for report in telemetry_reports(telemetry, settings):
            stages.add(report)
        for frame, offset in retimed:
            if offset is not None:
                offsets[frame.image.id] = offset
            if pipe.camera != frame.camera:
                pipe.camera = frame.camera
            boxes, scores, cids = candidates.get(frame.image.id)
            t1 = time.perf_counter()
            result = pipe.process(boxes, scores, cids, frame.pose, frame.t)
            pipeline_time += time.perf_counter() - t1
            stats["frames"] += 1
            stats["frames_without_pose"] += frame.pose is None
            stats["candidates"] += result.n_candidates
            stats["size_filtered"] += result.n_size_filtered
            stats["detections"] += len(result)
            if result.correction is not None:
                stats["frames_corrected"] = stats.get("frames_corrected", 0) + result.correction.measured
                corrections.append(math.hypot(result.correction.east_m, result.correction.north_m))
            if on_frame is not None:
                on_frame(frame, result)
        for report in pipe.stage_reports():
            stages.add(report)
    reasons = count_reasons(problems)
    if problems:  # frames without meta are normal (passed through); unusable meta is worth a warning
        unusable = [p for p in problems if p.reason != "no meta"]
        log.log(logging.WARNING if unusable else logging.INFO,
                "%d frame(s) have no pose and were not boosted (%s); first: %s", len(problems),
                ", ".join(f"{k} {v}" for k, v in reasons.items()), (unusable or problems)[0])
    stats["frames_with_bad_meta"] = sum(v for k, v in reasons.items() if k != "no meta")
    stats["frames_without_pose_by_reason"] = reasons
    if corrections:
        stats["correction_median_m"] = round(statistics.median(corrections), 3)
    if offsets:
        stats["clock_offset_median_s"] = round(statistics.median(o.offset_s for o in offsets.values()), 3)
        stats["clock_offset_frames_measured"] = sum(o.measured for o in offsets.values())
    stats["stages"] = stages.as_dict()
    stats["seconds"] = round(time.perf_counter() - t0, 3)
    stats["pipeline_ms_per_frame"] = round(1000 * pipeline_time / max(stats["frames"], 1), 3)
    return stats


def results_to_coco(image_id: int, result: FrameResult) -> list[dict[str, Any]]:
    """One frame's detections as COCO result entries (bbox [x, y, w, h])."""
    return candidates_to_coco(image_id, result.boxes_xyxy, result.scores, result.class_ids, score_digits=5)


def candidates_to_coco(image_id: int, boxes_xyxy, scores, class_ids, *, score_digits: int = 6) -> list[dict[str, Any]]:
    """Boxes (N, 4 xyxy), scores and class ids as COCO result entries (bbox [x, y, w, h]; a PRE_NMS.json's rows for
    a frame's pre-NMS candidates)."""
    return [
        {"image_id": image_id, "category_id": int(c),
         "bbox": [round(float(x1), 2), round(float(y1), 2), round(float(x2 - x1), 2), round(float(y2 - y1), 2)],
         "score": round(float(s), score_digits)}
        for (x1, y1, x2, y2), s, c in zip(boxes_xyxy, scores, class_ids, strict=True)
    ]


#: Columns of `uavmm boost --corrections-out`: the telemetry correction applied to each frame.
CORRECTION_COLUMNS = ("image_id", "video_id", "frame_index", "east_m", "north_m", "measured", "points", "support",
                      "clock_offset_s")


def boost_dataset(images_path: str | Path, candidates_path: str | Path, camera_path: str | Path,
                  config: PipelineConfig, size_filter: SizeFilter | None = None, *,
                  corrections: list[tuple] | None = None,
                  sink: Callable[[list[dict[str, Any]]], None] | None = None) -> tuple[list[dict], dict]:
    """Load the three files, run, and return (COCO results, stats).

    sink: when given, each frame's results go to it as they come (e.g. `StreamedResults.extend`: an hour's
    results as dicts are several times the file) and the returned list is empty.

    corrections: when a list, one row per frame is appended (CORRECTION_COLUMNS; a frame without pose
    or correction gets zeros and measured False; clock_offset_s: the video/telemetry clock offset its pose
    was re-timed by, empty when the estimate is off or the frame has no pose).
    """
    dataset = Dataset.load(images_path)
    candidates = Candidates.load(candidates_path, dataset)
    camera = Camera.from_spec(camera_path)
    results: list[dict[str, Any]] = []
    offsets: dict[int, ClockOffset] = {}

    add = results.extend if sink is None else sink

    def on_frame(frame, res: FrameResult) -> None:
        add(results_to_coco(frame.image.id, res))
        if corrections is not None:
            c = res.correction
            offset = offsets.get(frame.image.id)
            corrections.append((frame.image.id, frame.image.video_id, frame.image.frame_index,
                                round(c.east_m, 3) if c else 0.0, round(c.north_m, 3) if c else 0.0,
                                bool(c and c.measured), c.points if c else 0, round(c.support, 4) if c else 0.0,
                                round(offset.offset_s, 4) if offset is not None else ""))

    stats = run_pipeline(dataset, candidates, camera, config, size_filter, on_frame=on_frame,
                         clock_offsets=offsets)
    stats["skipped_candidates"] = candidates.skipped
    return results, stats


def write_corrections(rows: list[tuple], out_path: str | Path) -> None:
    """The per-frame telemetry corrections as CSV (CORRECTION_COLUMNS), written atomically
    (`shared.files.write_chunks_atomic`: a new temporary beside the file, on disk before the rename)."""
    import csv
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(CORRECTION_COLUMNS)
    writer.writerows(rows)
    write_chunks_atomic(Path(out_path), [buffer.getvalue()])


class StreamedResults:
    """A COCO results file written as the results come (`uavmm agent --detections-out`): an hour of a live flight
    held ~0.7 M result dicts in memory until the end (~0.4 GB at 10 frames/s and 20 detections a frame). Entries go
    to a new hidden temporary beside ``out`` as they are added (`shared.files.PendingFile`, created with the first:
    never a file or link already there, never another run's); `close` ends the JSON array, puts it on disk and
    renames it to ``out`` (a run that dies leaves the temporary, never a truncated results file). FileNotFoundError
    when the folder does not exist, IsADirectoryError when ``out`` is a folder (found at the start, not after the
    run)."""

    def __init__(self, out_path: str | Path) -> None:
        self.path = Path(out_path)
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"output directory {self.path.parent} does not exist (for {self.path})")
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path} is a directory: give the results file's path")
        self._file: PendingFile | None = None
        self.count = 0
        self.closed = False

    @property
    def spool_path(self) -> Path | None:
        """The temporary being written, None before the first results and after `close` / `abort`."""
        return None if self._file is None or self.closed else self._file.tmp

    def extend(self, results: list[dict[str, Any]]) -> None:
        if not results:
            return
        if self._file is None:
            self._file = PendingFile(self.path)
            self._file.write("[")
        # one write: a Ctrl-C lands before or after a frame's results, never inside them
        self._file.write((", " if self.count else "") + ", ".join(json.dumps(result) for result in results))
        self.count += len(results)

    def abort(self) -> None:
        """Drop what was written (a failed run leaves no temporary behind); idempotent."""
        if self._file is not None:
            self._file.discard()
        self.closed = True

    def close(self) -> None:
        """End the array, put it on disk and in place (idempotent)."""
        if self.closed:
            return
        self.closed = True
        if self._file is None:
            self._file = PendingFile(self.path)
            self._file.write("[]")
        else:
            self._file.write("]")
        self._file.commit()

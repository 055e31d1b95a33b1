"""Benchmark of the view cuts (`agent.view_cuts`) on a 1 Hz telemetry log: their cost per frame against the
per-frame pipeline the frames feed.

A 30 s clip at 30 fps of a hovering camera (30 m, 35 deg pitch, a 4K frame) over ~300 static people all around,
whose gimbal jumps 60 deg every 3 s; the telemetry is sampled at 1 Hz and interpolated at the frames' times, as
a flight log gives it. Cases: the view cuts over the whole clip (every jump searched and cut), the same clip
hovering without jumps (no interval turns: nothing searched), and the baseline, DetectionPipeline.process over
the clip's frames (georeference, size filter, boost, map update, NMS), measured in the same run (the three in
turns, one sample of each a round; each ratio the median of the per-round ratios). Memory: the
peak of what each allocates over the clip (tracemalloc, numpy's buffers included), the clip's frames and
detections already in memory.
"""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.clock_offset import ClockOffset
from agent.dataset import Frame, ImageRecord
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.telemetry_clock import TelemetryTrack
from agent.view_cuts import ViewCutReport, place_view_cuts
from benchmarks.timing import interleaved_samples_s, paired_ratio
from shared.geo import Camera, Pose, local_to_pixel

DESCRIPTION = "ms per frame of the view cuts on a 1 Hz log with 60 deg jumps vs the per-frame pipeline"

_FPS = 30.0
_HEIGHT_M, _PITCH_DEG = 30.0, 35.0


_Boxes = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]  # boxes_xyxy, scores, class ids


def _clip(seconds: float, jumps: bool) -> tuple[list[tuple[Frame, ClockOffset | None]], dict[int, _Boxes]]:
    """Frames with 1 Hz interpolated poses and the detections (people 20 x 50 px, score 0.9, plus 20 false
    positives at random) of the static field seen with the true heading."""
    rng = np.random.default_rng(0)
    camera = Camera.from_preset("dji-mavic2-pro", 3840, 2160)
    ang, dist = rng.uniform(0.0, 360.0, 300), rng.uniform(25.0, 80.0, 300)
    east, north = dist * np.sin(np.radians(ang)), dist * np.cos(np.radians(ang))

    def heading(t: float) -> float:
        return 10.0 + (60.0 * (math.floor(t / 3.0) % 2) if jumps else 0.0)

    stamps = np.arange(0.0, seconds + 1e-9, 1.0)
    values = np.array([[0.0, 0.0, _HEIGHT_M, heading(t), _PITCH_DEG] for t in stamps])
    track = TelemetryTrack(stamps, values)
    frames: list[tuple[Frame, ClockOffset | None]] = []
    dets: dict[int, _Boxes] = {}
    for i in range(int(seconds * _FPS)):
        t = i / _FPS
        _, _, h, head, pitch = track.at(t)[0]
        uv, ok = local_to_pixel(east, north, camera, Pose(0.0, 0.0, _HEIGHT_M, _PITCH_DEG, heading(t)))
        ok &= (uv[:, 0] > 10) & (uv[:, 0] < camera.width - 10) & (uv[:, 1] > 50) & (uv[:, 1] < camera.height)
        uv = np.vstack([uv[ok], rng.uniform([0, 700], [camera.width, camera.height], (20, 2))])
        boxes = np.column_stack([uv[:, 0] - 10, uv[:, 1] - 50, uv[:, 0] + 10, uv[:, 1]]).astype(np.float32)
        scores = np.concatenate([np.full(int(ok.sum()), 0.9), rng.uniform(0.05, 0.6, 20)]).astype(np.float32)
        dets[i] = (boxes, scores, np.ones(len(boxes), np.int64))
        frames.append((Frame(ImageRecord(i, camera.width, camera.height, 1, i, None, None),
                             Pose(0.0, 0.0, h, pitch, head), t, camera, t, pose_retimed=True, track=track), None))
    return frames, dets


def _peak_mib(fn: Callable[[], object]) -> float:
    """The peak of the memory fn allocates above what is traced already (tracemalloc), MiB. An outer
    tracemalloc session is left running (its peak is reset)."""
    outer = tracemalloc.is_tracing()
    if not outer:
        tracemalloc.start()
    tracemalloc.reset_peak()
    before = tracemalloc.get_traced_memory()[0]
    try:
        fn()
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        if not outer:
            tracemalloc.stop()
    return peak / 2**20


def run(quick: bool = False) -> list[dict[str, Any]]:
    seconds = 9.0 if quick else 30.0
    repeat = 3 if quick else 5
    rows: list[dict[str, Any]] = []
    frames, dets = _clip(seconds, jumps=True)
    n = len(frames)
    camera = frames[0][0].camera

    def pipeline() -> None:
        pipe = DetectionPipeline(camera, {1: "person"}, PipelineConfig())
        for frame, _ in frames:
            pipe.process(*dets[frame.image.id], frame.pose, frame.t)

    still, still_dets = _clip(seconds, jumps=False)
    report = ViewCutReport()
    place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    times = interleaved_samples_s({
        "pipeline": pipeline,
        "jumps": lambda: place_view_cuts(frames, lambda f: dets[f.image.id]),
        "still": lambda: place_view_cuts(still, lambda f: still_dets[f.image.id])}, repeat=repeat, min_time_s=0.0)
    base = float(np.median(times["pipeline"])) / n
    rows.append({"case": f"pipeline per frame ({n} frames, ~45 people in view)", "value": base * 1e3,
                 "unit": "ms/frame"})
    rows.append({"case": f"view cuts, 1 Hz log, {report.cuts} of {report.intervals} jumps cut",
                 "value": float(np.median(times["jumps"])) / n * 1e3, "unit": "ms/frame", "baseline_name": "pipeline",
                 "ratio": paired_ratio(times["jumps"], times["pipeline"])})
    base_mib = _peak_mib(pipeline)
    rows.append({"case": "pipeline over the clip, peak allocated", "value": base_mib, "unit": "MiB"})
    cuts_mib = _peak_mib(lambda: place_view_cuts(frames, lambda f: dets[f.image.id]))
    rows.append({"case": "view cuts over the clip, peak allocated", "value": cuts_mib, "unit": "MiB",
                 "baseline_name": "pipeline", "ratio": cuts_mib / base_mib})
    rows.append({"case": "view cuts, 1 Hz log, hovering (nothing to search)",
                 "value": float(np.median(times["still"])) / n * 1e3, "unit": "ms/frame", "baseline_name": "pipeline",
                 "ratio": paired_ratio(times["still"], times["pipeline"])})
    return rows

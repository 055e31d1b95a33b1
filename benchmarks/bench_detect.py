"""`uavmm detect` in two passes (`agent.offline.two_pass`) against one pass: what reading a recording as a file costs.

A clip of a turning camera over a textured ground (MJPG, 1280x720, 10 frames/s, a 10 Hz telemetry CSV) through a
random-weight ONNX model with YOLOv8n's architecture and cost (`benchmarks.yolo_model`, run by onnxruntime on this
CPU; its score threshold set to keep ~300 candidates a frame, a realistic pre-NMS load). Cases, measured in the
same run in turns (each ratio the median of the per-round ratios): `run_detect` in one pass (the baseline, as the
live agent runs) and in two passes (the detector over the whole clip with the candidates in the spool, then the
clock offset, view cuts and the adaptive stages, then the second decode, memory map and tracker). Also the spool's
bytes per frame (on disk, not in memory) and the peak Python-allocated memory of each run (tracemalloc, numpy's
buffers included).

--quick: 20 frames at a 320 input (the full run: 60 frames at 640).
"""

from __future__ import annotations

import json
import tempfile
import tracemalloc
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks.timing import interleaved_samples_s, paired_ratio

DESCRIPTION = "uavmm detect: two passes (a recording read as a file) vs one pass, time and memory"

_W, _H, _FPS = 1280, 720, 10.0
#: pre-NMS candidates a frame (about; a trained YOLOv8n at 0.01 on a busy 4K frame gives a few hundred)
_CANDIDATES = 300


def _clip(folder: Path, frames: int) -> tuple[Path, Path, Path]:
    rng = np.random.default_rng(0)
    ground = cv2.GaussianBlur(rng.integers(0, 256, (_H * 2, _W * 2, 3), dtype=np.uint8), (0, 0), 3)
    video = folder / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), _FPS, (_W, _H))
    for i in range(frames):  # the view pans across the ground as the camera turns
        x = int(i * 8) % _W
        writer.write(np.ascontiguousarray(ground[_H // 2:_H // 2 + _H, x:x + _W]))
    writer.release()
    telemetry = folder / "clip.csv"
    rows = ["time_s,lat,lon,height_m,pitch_deg,heading_deg"]
    rows += [f"{t:.2f},48.53,9.06,40,50,{(15.0 * t) % 360:.2f}" for t in np.arange(0, frames / _FPS + 0.5, 0.1)]
    telemetry.write_text("\n".join(rows) + "\n")
    camera = folder / "camera.json"
    camera.write_text(json.dumps({"width": _W, "height": _H, "fx": 1000.0}))
    return video, telemetry, camera


def _threshold_for(model: Path, video: Path, count: int) -> float:
    """The score threshold that keeps about `count` candidates of the clip's first frame: the random weights score
    every anchor low (~4e-4), so the usual 0.01 would keep none."""
    from agent.detector import OnnxYoloDetector

    capture = cv2.VideoCapture(str(video))
    try:
        image = capture.read()[1]
    finally:
        capture.release()
    scores = np.sort(OnnxYoloDetector(model, conf_threshold=1e-9)(image).scores)[::-1]
    return float(scores[min(count, len(scores)) - 1])


def run(quick: bool = False) -> list[dict[str, Any]]:
    from agent.offline.run import DetectOptions, run_detect
    from agent.sources import VideoSource
    from benchmarks.yolo_model import build_yolov8n_like_onnx

    frames = 20 if quick else 60
    size = 320 if quick else 640
    repeat = 3 if quick else 5
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        video, telemetry, camera = _clip(folder, frames)
        model = folder / "model.onnx"
        build_yolov8n_like_onnx(model, input_size=size, num_classes=80)
        threshold = _threshold_for(model, video, _CANDIDATES)
        summaries: dict[str, dict[str, Any]] = {}

        def detect(two_pass: bool) -> None:
            source = VideoSource(video, telemetry, model, camera, conf_threshold=threshold)
            name = "two" if two_pass else "one"
            summaries[name] = run_detect(source, folder / name, options=DetectOptions(two_pass=two_pass))

        times = interleaved_samples_s({"one": lambda: detect(False), "two": lambda: detect(True)}, repeat=repeat,
                                      min_time_s=0.0)
        one_s, two_s = float(np.median(times["one"])), float(np.median(times["two"]))
        candidates = summaries["two"]["candidates"]
        rows.append({"case": f"one pass ({frames} frames, {size} input, {candidates / frames:.0f} candidates a frame)",
                     "value": frames / one_s, "unit": "frames/s"})
        rows.append({"case": "two passes", "value": frames / two_s, "unit": "frames/s", "baseline_name": "one pass",
                     "ratio": paired_ratio(times["two"], times["one"])})
        rows.append({"case": "two passes: candidate spool on disk", "value": 28.0 * candidates / frames / 1024,
                     "unit": "KiB/frame"})
        peaks = {}
        for name, two_pass in (("one", False), ("two", True)):
            tracemalloc.start()
            try:
                detect(two_pass)
                peaks[name] = tracemalloc.get_traced_memory()[1] / 2 ** 20
            finally:
                tracemalloc.stop()
        rows.append({"case": "one pass: peak allocated", "value": peaks["one"], "unit": "MiB"})
        rows.append({"case": "two passes: peak allocated", "value": peaks["two"], "unit": "MiB",
                     "baseline_name": "one pass", "ratio": peaks["two"] / peaks["one"]})
    return rows

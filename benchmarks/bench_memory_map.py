"""Per-frame cost of the memory-map pipeline vs a YOLOv8n-sized detector's inference.

Pipeline = georeference + size filter + boost + map update + NMS, on clustered pre-NMS candidates
(objects with dense clusters plus uniform background, as detectors emit them). Baselines measured in
the same run: onnxruntime inference of a YOLOv8n-sized model at 640x640 (2 threads), and the
single-frame pipeline (same filter and NMS, no memory); and the memory map boosting every box (the
paper; fragment_iou 0) for the cost of finding the parts that a higher-ranked box overlaps.

Both are wall times, as a UAV's per-frame latency budget counts them: the detector's 2 intra-op
threads run in parallel, the pipeline in one thread. Other load on the machine slows both, so each
row alternates detector and pipeline samples (ROUNDS rounds) and its ratio is the median of the
per-round ratios: a load change between two rows no longer shows up as a change of ratio. cpu_ms
is the pipeline's thread CPU time (time.thread_time), which load does not inflate.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose

DESCRIPTION = "memory-map pipeline ms/frame at 1k/5k/20k candidates vs YOLOv8n-sized ONNX inference"


def clustered_candidates(n: int, camera: Camera, rng: np.random.Generator, *, objects: int = 40,
                         background_fraction: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 4) xyxy boxes, scores, class ids: clusters around `objects` centres + uniform background."""
    n_bg = int(n * background_fraction)
    n_obj = n - n_bg
    centres = np.column_stack([rng.uniform(50, camera.width - 50, objects),
                               rng.uniform(camera.height * 0.3, camera.height - 50, objects)])
    sizes = rng.uniform(15, 60, objects)
    which = rng.integers(0, objects, n_obj)
    c = centres[which] + rng.normal(0, 3, (n_obj, 2))
    s = sizes[which, None] * rng.uniform(0.8, 1.2, (n_obj, 2)) * [0.5, 1.0]
    bg_c = np.column_stack([rng.uniform(0, camera.width, n_bg), rng.uniform(camera.height * 0.3, camera.height, n_bg)])
    bg_s = rng.uniform(8, 120, (n_bg, 2))
    centre = np.vstack([c, bg_c])
    size = np.vstack([s, bg_s])
    boxes = np.column_stack([centre - size / 2, centre + size / 2]).astype(np.float32)
    scores = np.concatenate([rng.uniform(0.05, 0.9, n_obj), rng.uniform(0.01, 0.3, n_bg)]).astype(np.float32)
    cids = np.concatenate([np.ones(n_obj, np.int64), rng.integers(1, 3, n_bg)])
    return boxes, scores, cids


#: Alternations of detector and pipeline samples per row.
ROUNDS = 5


def _yolo_session() -> tuple[Callable[[], Any] | None, str]:
    """A function running one inference of a YOLOv8n-sized model (640x640, 2 threads), and its name."""
    try:
        import onnxruntime as ort

        from benchmarks.yolo_model import build_yolov8n_like_onnx
    except ImportError as exc:  # onnx is a test/bench extra
        return None, f"unavailable ({exc.name} not installed)"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "yolov8n_like.onnx"
        build_yolov8n_like_onnx(path, input_size=640)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 2
        opts.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    blob = np.random.default_rng(0).random((1, 3, 640, 640), dtype=np.float32)
    return (lambda: sess.run(None, {name: blob})), "yolov8n-640"


def _wall_and_cpu_s(fn: Callable[[], Any], min_time_s: float) -> tuple[float, float]:
    """One sample: mean wall and thread-CPU seconds per fn() over a batch of at least min_time_s."""
    loops, batch_wall, batch_cpu = 0, 0.0, 0.0
    while loops == 0 or batch_wall < min_time_s:
        w0, c0 = time.perf_counter(), time.thread_time()
        fn()
        batch_cpu += time.thread_time() - c0
        batch_wall += time.perf_counter() - w0
        loops += 1
    return batch_wall / loops, batch_cpu / loops


def run(quick: bool = False) -> list[dict[str, Any]]:
    rng = np.random.default_rng(0)
    camera = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    classes = {1: "person", 2: "swimmer"}
    yolo, yolo_name = _yolo_session()
    yolo_samples: list[float] = []
    if yolo is not None:
        yolo()  # warm-up
    rows: list[dict[str, Any]] = []
    sizes = (1000, 5000) if quick else (1000, 5000, 20000)
    for n in sizes:
        frames = [clustered_candidates(n, camera, rng) for _ in range(8)]
        # the UAV drifts and turns a little each frame, so the window and kernel paths run; poses
        # are built outside the timed step, like the candidates (telemetry parsing is not the pipeline)
        poses = [Pose(lat=47.67 + k * 1e-6, lon=9.27, height_m=40.0, pitch_deg=45.0,
                      heading_deg=(140.0 + 0.5 * k) % 360) for k in range(720)]
        variants = (("single-frame (filter + NMS)", PipelineConfig(use_memory=False)),
                    ("memory map", PipelineConfig()),
                    # the paper boosts every box: the cost of finding the parts that overlap a higher-ranked box
                    ("memory map, every box boosted (fragment_iou 0)", PipelineConfig(fragment_iou=0.0)))
        for label, config in variants:
            pipe = DetectionPipeline(camera, classes, config)
            state = {"k": 0}

            def step(pipe=pipe, frames=frames, poses=poses, state=state) -> None:
                k = state["k"]
                state["k"] = k + 1
                pipe.process(*frames[k % len(frames)], poses[k % len(poses)], k / 30.0)

            for _ in range(8):  # warm-up: the map fills, caches settle
                step()
            walls, cpus, ratios = [], [], []
            for _ in range(ROUNDS):
                if yolo is not None:
                    yolo_s = float(np.median([_wall_and_cpu_s(yolo, 0.0)[0] for _ in range(3)]))
                    yolo_samples.append(yolo_s)
                wall, cpu = _wall_and_cpu_s(step, 0.05)
                walls.append(wall)
                cpus.append(cpu)
                if yolo is not None:
                    ratios.append(wall / yolo_s)
            row = {"case": f"{label}, {n} candidates", "value": float(np.median(walls)) * 1e3,
                   "unit": "ms/frame", "cpu_ms": float(np.median(cpus)) * 1e3}
            if yolo is not None:
                row.update(baseline_name=yolo_name, ratio=float(np.median(ratios)))
            rows.append(row)
    if yolo is not None:
        rows.insert(0, {"case": "ONNX YOLOv8n-sized 640x640, 2 threads", "value": float(np.median(yolo_samples)) * 1e3,
                        "unit": "ms"})
    return rows

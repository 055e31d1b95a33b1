"""Anomaly detection speed: the heatmap -> ground projection and the whole pipeline per method.

Measured in the same run on rendered sea frames (`sim.render`):
- projecting a 4K (3840x2160) heatmap onto the ground layer (`agent.anomaly.ground.AnomalyMap.update`: cut,
  resample to 4 pixels a cell, mean over each cell's footprint, one warpPerspective, add) in ms, beside the
  per-pixel baseline (every pixel's ground point with `shared.geo.pixel_to_local`, then `np.bincount` into the
  grid) and the projection of the methods' own working-size heatmap (640x360, what the pipeline projects);
- the whole pipeline at 1080p per method (`AnomalyDetector.process`: heatmap, projection, read-back, regions)
  in frames/s against the 10 fps target, beside the heatmap method alone (--no-memory).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.timing import median_time_s

DESCRIPTION = "anomaly: 4K heatmap -> ground grid (vs per-pixel bincount), pipeline frames/s at 1080p per method"
TARGET_FPS = 10.0


def _frames(width: int, height: int, n: int) -> tuple[list[np.ndarray], list[Any], Any]:
    """n rendered sea frames (BGR) with their telemetry poses and the camera."""
    from agent.dataset import Dataset, iter_video_frames
    from shared.geo import Camera
    from sim.dataset import write_dataset
    from sim.render import SimulatedDataset, WorldRenderer, exposure_for
    from sim.scenarios import get_scenario

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "sea"
        scenario = get_scenario("sea")
        write_dataset(dataclasses.replace(scenario, image_size=(width, height), flights=scenario.flights[:1]), d,
                      seed=0, frames=n, progress=False)
        sds = SimulatedDataset(d)
        renderer = WorldRenderer(sds, sds.worlds[sorted(sds.worlds)[0]])
        video = renderer.videos[0]
        images = [renderer.render(f, exposure_for(sds, video)) for f in sds.frames(video)]
        camera = Camera.from_file(d / "camera.json")
        ds = Dataset.load(d / "images.json")
        poses = [(f.pose, f.t) for f in iter_video_frames(ds, camera, next(iter(ds.videos)))]
    return images, poses, camera


def _bincount_baseline(heat: np.ndarray, camera: Any, pose: Any, cell_m: float, size: int) -> np.ndarray:
    """Per-pixel projection: every pixel's ground point, summed into a size x size grid with np.bincount."""
    from shared.geo import pixel_to_local

    h, w = heat.shape
    v, u = np.mgrid[0:h, 0:w]
    uv = np.column_stack([(u.ravel() + 0.5) * camera.width / w, (v.ravel() + 0.5) * camera.height / h])
    east, north, valid = pixel_to_local(uv, camera, pose)
    col = np.floor(east / cell_m + size / 2)
    row = np.floor(-north / cell_m + size / 2)
    ok = valid & (col >= 0) & (col < size) & (row >= 0) & (row < size)
    idx = (row[ok] * size + col[ok]).astype(np.int64)
    return np.bincount(idx, weights=heat.ravel()[ok], minlength=size * size).reshape(size, size)


def run(quick: bool = False) -> list[dict[str, Any]]:
    from agent.anomaly import ANOMALY_METHODS, AnomalyConfig, AnomalyDetector, AnomalyMap

    rows: list[dict[str, Any]] = []
    n = 8 if quick else 30
    # ---- projection of a 4K heatmap
    images, poses, camera = _frames(3840, 2160, 4)
    rng = np.random.default_rng(0)
    heat4k = rng.random((2160, 3840), dtype=np.float32) ** 8
    pose, t = poses[1]
    layer = AnomalyMap()
    layer.update(heat4k, camera, pose, t)
    tick = [t]

    def project(heat: np.ndarray) -> None:
        tick[0] += 1 / 30
        layer.update(heat, camera, pose, tick[0])

    proj_4k = median_time_s(lambda: project(heat4k), repeat=5)
    size = layer.size_cells
    base = median_time_s(lambda: _bincount_baseline(heat4k, camera, pose, 0.4, size), repeat=3, min_time_s=0.0)
    rows.append({"case": "4K heatmap -> ground layer (warpPerspective), ms", "value": proj_4k * 1e3, "unit": "ms",
                 "baseline_name": "per-pixel rays + bincount", "ratio": proj_4k / base})
    heat_work = np.ascontiguousarray(heat4k[::6, ::6])
    proj_work = median_time_s(lambda: project(heat_work), repeat=5)
    rows.append({"case": f"{heat_work.shape[1]}x{heat_work.shape[0]} heatmap (4K frame) -> ground layer, ms",
                 "value": proj_work * 1e3, "unit": "ms", "baseline_name": "4K heatmap", "ratio": proj_work / proj_4k})
    # ---- whole pipeline at 1080p
    images, poses, camera = _frames(1920, 1080, n)
    for name in sorted(ANOMALY_METHODS):
        per_mode = {}
        for use_memory in (False, True):
            det = AnomalyDetector(AnomalyConfig(method=name, use_memory=use_memory))
            det.process(images[0], poses[0][0], poses[0][1], camera)  # warm-up
            det.reset()
            t0 = time.perf_counter()
            for image, (p, t) in zip(images, poses, strict=True):
                det.process(image, p, t, camera)
            per_mode[use_memory] = len(images) / (time.perf_counter() - t0)
        rows.append({"case": f"1080p pipeline {name} + memory map, frames/s", "value": per_mode[True],
                     "unit": "frames/s", "baseline_name": f"target {TARGET_FPS:g} fps",
                     "ratio": per_mode[True] / TARGET_FPS})
        rows.append({"case": f"1080p pipeline {name} per frame (no memory), frames/s", "value": per_mode[False],
                     "unit": "frames/s", "baseline_name": "with memory map", "ratio": per_mode[False] / per_mode[True]})
    return rows

"""Anomaly detection speed: the heatmap -> ground projection and the whole pipeline per method.

Measured in the same run on rendered sea frames (`sim.render`):
- projecting a 4K (3840x2160) heatmap onto the ground layer (`agent.anomaly.ground.AnomalyMap.update`: cut,
  resample to 4 pixels a cell, mean over each cell's footprint, one warpPerspective, add) in ms, beside the
  per-pixel baseline (every pixel's ground point with `shared.geo.pixel_to_local`, then `np.bincount` into the
  grid) and the projection of the methods' own working-size heatmap (640x360, what the pipeline projects);
- the whole pipeline at 1080p per method (`AnomalyDetector.process`: heatmap, projection, read-back, regions)
  in frames/s against the 10 fps target, beside the heatmap method alone (--no-memory; the modes take turns
  frame by frame);
- the same on a terrain (`--dem`: the `hills` scenario's 1 m DEM, 12 m of relief, under the sea flight; each
  frame's cells lifted onto the DEM, projected, the hidden ones left out, `agent.anomaly.terrain_view`), beside
  flat ground, the two taking turns frame by frame: the projection of a full-resolution 1080p and 4K heatmap,
  the working heatmap's projection and read-back per frame at both sizes (each frame at the flight's next pose,
  so no view is reused), and the 1080p pipeline per method.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.timing import median_time_s

DESCRIPTION = ("anomaly: 4K heatmap -> ground grid (vs per-pixel bincount), pipeline frames/s at 1080p per method; "
               "the same on a 1 m DEM vs flat")
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


def _hills_terrain() -> Any:
    """The `hills` scenario's DEM (seed 0) about the sea world's origin, heights above the take-off there."""
    from sim.scenarios import get_scenario

    spec = get_scenario("hills").terrain
    world = get_scenario("sea").world
    assert spec is not None
    return spec.build(np.random.default_rng(0), world.origin_lat, world.origin_lon).terrain


def _per_frame_ms(heat: np.ndarray, camera: Any, poses: list[Any], terrain: Any, read_back: bool,
                  frames: int) -> tuple[float, float]:
    """Median ms of one frame's layer update (and read-back at the working size) over flat ground and on the
    terrain, the two taking turns frame by frame (a change of the machine's load falls on both), each frame at the
    next of the poses (so no view is reused)."""
    import time

    from agent.anomaly import AnomalyMap

    layers = {"flat": AnomalyMap(), "dem": AnomalyMap()}
    times: dict[str, list[float]] = {"flat": [], "dem": []}
    for k in range(frames + 2):  # the first two warm up
        pose = poses[k % len(poses)][0]
        for name, layer in layers.items():
            ground = terrain if name == "dem" else None
            t0 = time.perf_counter()
            layer.update(heat, camera, pose, k / 30, terrain=ground)
            if read_back:
                layer.image_scores(camera, pose, (360, 640), terrain=ground)
            if k >= 2:
                times[name].append(time.perf_counter() - t0)
    return float(np.median(times["flat"])) * 1e3, float(np.median(times["dem"])) * 1e3


def _terrain_rows(poses4k: list[Any], camera4k: Any, poses1080: list[Any], camera1080: Any, terrain: Any,
                  frames: int) -> list[dict[str, Any]]:
    """Projection (full-resolution heatmaps) and projection + read-back (working heatmaps) on the DEM vs flat."""
    rows: list[dict[str, Any]] = []
    rng = np.random.default_rng(1)
    for label, camera, poses in (("1080p", camera1080, poses1080), ("4K", camera4k, poses4k)):
        full = rng.random((camera.height, camera.width), dtype=np.float32) ** 8
        work = np.ascontiguousarray(full[::camera.height // 360, ::camera.width // 640][:360, :640])
        for heat, what, read_back in ((full, f"{label} heatmap -> ground layer", False),
                                      (work, f"640x360 heatmap ({label} frame) -> layer + read-back", True)):
            flat, dem = _per_frame_ms(heat, camera, poses, terrain, read_back, frames)
            rows.append({"case": f"{what}, flat, ms", "value": flat, "unit": "ms"})
            rows.append({"case": f"{what}, hills DEM 1 m, ms", "value": dem, "unit": "ms", "baseline_name": "flat",
                         "ratio": dem / flat})
    return rows


def run(quick: bool = False) -> list[dict[str, Any]]:
    from agent.anomaly import ANOMALY_METHODS, AnomalyConfig, AnomalyDetector, AnomalyMap

    rows: list[dict[str, Any]] = []
    n = 8 if quick else 30
    # ---- projection of a 4K heatmap
    images, poses, camera = _frames(3840, 2160, 8)
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
    poses4k, camera4k = poses, camera
    # ---- whole pipeline at 1080p
    images, poses, camera = _frames(1920, 1080, n)
    terrain = _hills_terrain()
    rows.extend(_terrain_rows(poses4k, camera4k, poses, camera, terrain, n))
    modes: tuple[object, ...] = (False, True, "dem")
    for name in sorted(ANOMALY_METHODS):
        detectors = {mode: AnomalyDetector(AnomalyConfig(method=name, use_memory=bool(mode),
                                                         terrain=terrain if mode == "dem" else None))
                     for mode in modes}
        spent = dict.fromkeys(modes, 0.0)
        for det in detectors.values():
            det.process(images[0], poses[0][0], poses[0][1], camera)  # warm-up
            det.reset()
        # the modes take turns frame by frame, so a change of the machine's load falls on all of them alike
        for image, (p, t) in zip(images, poses, strict=True):
            for mode, det in detectors.items():
                t0 = time.perf_counter()
                det.process(image, p, t, camera)
                spent[mode] += time.perf_counter() - t0
        per_mode = {mode: len(images) / spent[mode] for mode in modes}
        rows.append({"case": f"1080p pipeline {name} + memory map, frames/s", "value": per_mode[True],
                     "unit": "frames/s", "baseline_name": f"target {TARGET_FPS:g} fps",
                     "ratio": per_mode[True] / TARGET_FPS})
        rows.append({"case": f"1080p pipeline {name} per frame (no memory), frames/s", "value": per_mode[False],
                     "unit": "frames/s", "baseline_name": "with memory map", "ratio": per_mode[False] / per_mode[True]})
        rows.append({"case": f"1080p pipeline {name} + memory map on the hills DEM, frames/s", "value": per_mode["dem"],
                     "unit": "frames/s", "baseline_name": "flat ground", "ratio": per_mode["dem"] / per_mode[True]})
    return rows

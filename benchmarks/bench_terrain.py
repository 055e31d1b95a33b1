"""Benchmark of georeferencing on a terrain (`--dem`): per-frame cost at 1k and 5k boxes against flat ground.

Cases: the boxes' anchor pixels to ground points (shared.geo.pixel_to_local without and with terrain=) on the
`hills` scenario's 1 m DEM (hills and hollows up to ~12 m) and on a flat DEM, and the whole per-frame pipeline
(DetectionPipeline.process: georeference, size filter, boost, map update, NMS) over flat ground (the compiled
kernel) and with the DEM (the ray marching), also with a telemetry correction applied (over the DEM the map's cells
are marched again from the moved UAV). The baseline of each is the flat-ground figure measured in the same run: the
cases compared are timed in turns (one sample of each a round) and each ratio is the median of the per-round
ratios, so a change of the machine's load between samples does not show up as a ratio.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from benchmarks.timing import interleaved_samples_s, paired_ratio
from shared.geo import Camera, Pose, local_to_latlon, pixel_to_local
from shared.terrain import ElevationGrid, Terrain
from sim.scenarios import get_scenario

DESCRIPTION = "ms per frame to georeference 1k / 5k boxes on a 1 m DEM vs flat ground (and the whole pipeline)"


def _frame(n: int, rng: np.random.Generator, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n pre-NMS boxes in the lower two thirds of a 4K frame (people seen from 30 m: 15-60 px)."""
    w = rng.uniform(8, 30, n)
    h = w * rng.uniform(1.5, 2.5, n)
    x = rng.uniform(0, camera.width - w)
    y = rng.uniform(camera.height / 3, camera.height - h)
    return np.column_stack([x, y, x + w, y + h]).astype(np.float32), rng.uniform(0.01, 1, n).astype(np.float32), \
        np.ones(n, dtype=np.int64)


def run(quick: bool = False) -> list[dict[str, Any]]:
    rng = np.random.default_rng(0)
    scenario = get_scenario("hills")
    camera = Camera.from_preset("dji-mavic2-pro", 3840, 2160)
    world = scenario.world
    assert scenario.terrain is not None
    hills = scenario.terrain.build(np.random.default_rng(0), world.origin_lat, world.origin_lon)
    lat, lon = local_to_latlon(-40.0, -45.0, world.origin_lat, world.origin_lon)
    pose = Pose(lat=float(lat), lon=float(lon), height_m=30.0, pitch_deg=35.0, heading_deg=30.0)
    flat_grid = ElevationGrid(np.full(hills.grid.shape, hills.takeoff_elevation_m), hills.grid.lat0_deg,
                              hills.grid.lon0_deg, hills.grid.lat_step_deg, hills.grid.lon_step_deg)
    terrains = {"hills DEM 1 m": hills.terrain, "flat DEM 1 m": Terrain(flat_grid, hills.takeoff_elevation_m)}
    rows: list[dict[str, Any]] = []
    repeat = 3 if quick else 7
    for n in (1000, 5000):
        boxes, scores, cids = _frame(n, rng, camera)
        uv = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, boxes[:, 3]]).astype(np.float64)
        anchors = interleaved_samples_s({
            "flat": functools.partial(pixel_to_local, uv, camera, pose, max_range_m=150.0),
            **{name: functools.partial(pixel_to_local, uv, camera, pose, max_range_m=150.0, terrain=terrain)
               for name, terrain in terrains.items()}}, repeat=repeat)
        rows.append({"case": f"anchors -> ground, flat, {n} boxes", "value": _ms(anchors["flat"]),
                     "unit": "ms/frame"})
        for name in terrains:
            rows.append({"case": f"anchors -> ground, {name}, {n} boxes", "value": _ms(anchors[name]),
                         "unit": "ms/frame", "baseline_name": "flat", "ratio": paired_ratio(anchors[name],
                                                                                            anchors["flat"])})
        steps = {}
        for name, dem, stamp, probe in (("flat", None, "shrink", 0.3),
                                        ("hills DEM 1 m", hills.terrain, "shrink", 0.3),
                                        ("fixed stamp", hills.terrain, "off", 0.3),
                                        ("no edge probe", hills.terrain, "shrink", 0.0)):
            config = PipelineConfig(terrain=dem, edge_probe=probe)
            config = dataclasses.replace(config, memory=dataclasses.replace(config.memory, terrain_stamp=stamp))
            pipe = DetectionPipeline(camera, {1: "person"}, config)
            steps[name] = _frames(pipe, boxes, scores, cids, pose, _clock())
        times = interleaved_samples_s(steps, repeat=repeat)
        on_dem = times["hills DEM 1 m"]
        rows.append({"case": f"pipeline frame, flat (compiled), {n} boxes", "value": _ms(times["flat"]),
                     "unit": "ms/frame"})
        rows.append({"case": f"pipeline frame, hills DEM 1 m, {n} boxes", "value": _ms(on_dem),
                     "unit": "ms/frame", "baseline_name": "flat", "ratio": paired_ratio(on_dem, times["flat"])})
        # the stamp radius following the terrain's footprint (MemoryMapConfig.terrain_stamp) against a fixed one
        rows.append({"case": f"pipeline frame, hills DEM 1 m, stamp by footprint, {n} boxes",
                     "value": _ms(on_dem), "unit": "ms/frame", "baseline_name": "fixed stamp",
                     "ratio": paired_ratio(on_dem, times["fixed stamp"])})
        # the kept boxes' second ground points past a terrain edge (PipelineConfig.edge_probe) against none
        rows.append({"case": f"pipeline frame, hills DEM 1 m, edge probe, {n} boxes",
                     "value": _ms(on_dem), "unit": "ms/frame", "baseline_name": "no edge probe",
                     "ratio": paired_ratio(on_dem, times["no edge probe"])})
        # with a telemetry correction applied: over the DEM the map's cells are marched again from the moved UAV
        moved = _with_correction(camera, pose, hills.terrain, boxes, scores, cids, repeat)
        rows.append({"case": f"pipeline frame, hills DEM 1 m, correction applied, {n} boxes",
                     "value": _ms(moved["applied"]), "unit": "ms/frame", "baseline_name": "correction off",
                     "ratio": paired_ratio(moved["applied"], moved["off"])})
    return rows


def _ms(samples_s: list[float]) -> float:
    return float(np.median(samples_s)) * 1e3


def _with_correction(camera: Camera, pose: Pose, terrain: Terrain, boxes: np.ndarray, scores: np.ndarray,
                     cids: np.ndarray, repeat: int) -> dict[str, list[float]]:
    """Seconds per frame (interleaved_samples_s) of the pipeline on the DEM after a 3 m GPS step, once the correction
    has measured it (the same boxes every frame: the map knows where they are; "applied"), and with the correction
    switched off ("off")."""
    lat, lon = local_to_latlon(3.0, 0.0, pose.lat, pose.lon)
    stepped = dataclasses.replace(pose, lat=float(lat), lon=float(lon))
    steps = {}
    for name, correct in (("off", False), ("applied", True)):
        pipe = DetectionPipeline(camera, {1: "person"}, PipelineConfig(terrain=terrain, correct_telemetry=correct))
        clock = _clock()
        for _ in range(30):
            pipe.process(boxes, scores, cids, pose, float(next(clock)))
        result = pipe.process(boxes, scores, cids, stepped, float(next(clock)))
        if correct and (result.correction is None or not result.correction.measured):
            raise RuntimeError(f"bench terrain: the correction did not measure the GPS step ({name})")
        steps[name] = _frames(pipe, boxes, scores, cids, stepped, clock)
    return interleaved_samples_s(steps, repeat=repeat)


def _clock() -> Iterator[float]:
    """Frame times at 30 fps from 0 s."""
    return (float(t) for t in np.arange(0.0, 1e6, 1.0 / 30.0))


def _frames(pipe: DetectionPipeline, boxes: np.ndarray, scores: np.ndarray, cids: np.ndarray, pose: Pose,
            clock: Iterator[float]) -> Callable[[], object]:
    """A pipeline frame of these boxes per call, at the clock's next time."""
    return lambda: pipe.process(boxes, scores, cids, pose, next(clock))

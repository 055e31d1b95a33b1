"""The pipeline's second ground points past a terrain edge (PipelineConfig.edge_probe, FrameResult.alt_latlon): a box
at a bank's lip gets the other level's point, boxes elsewhere and runs without a terrain get none; bad settings are
named."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_local, local_to_latlon, local_to_pixel
from shared.terrain import ElevationGrid, Terrain

LAT, LON = 48.0, 9.0
CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
CLASSES = {1: "person"}
POSE = Pose(lat=LAT, lon=LON, height_m=40.0, pitch_deg=40.0, heading_deg=0.0)  # looking north
AXIS = np.arange(-200.0, 201.0, 1.0)
EAST, NORTH = np.meshgrid(AXIS, AXIS[::-1])
#: The upper level under the UAV falls 5 m between 40 and 41 m north (away from the camera).
BANK = Terrain(ElevationGrid.from_local(np.where(NORTH <= 40.0, 200.0, 195.0), LAT, LON, west_m=-200.0,
                                        north_m=200.0, cell_m=1.0), 200.0)
FLAT = Terrain(ElevationGrid.from_local(np.full_like(NORTH, 200.0), LAT, LON, west_m=-200.0, north_m=200.0,
                                        cell_m=1.0), 200.0)


def lip_v() -> float:
    uv, ok = local_to_pixel(np.array([0.0]), np.array([40.0]), CAM, POSE, terrain=BANK)
    assert ok[0]
    return float(uv[0, 1])


def process(terrain: Terrain | None, bottoms_v: list[float], **settings):
    """One frame of 40 px tall boxes standing at bottoms_v (image rows) in the middle column, anchored at the
    bottom; returns the FrameResult."""
    cfg = PipelineConfig(use_size_filter=False, correct_telemetry=False, anchor="bottom", terrain=terrain,
                         **settings)
    boxes = np.array([[CAM.cx - 8, v - 40.0, CAM.cx + 8, v] for v in bottoms_v], np.float32)
    n = len(boxes)
    return DetectionPipeline(CAM, CLASSES, cfg).process(boxes, np.linspace(0.9, 0.8, n).astype(np.float32),
                                                        np.ones(n, np.int64), POSE, 0.0)


def north_of(lat, lon) -> np.ndarray:
    return np.asarray(latlon_to_local(lat, lon, LAT, LON)[1])


def test_a_box_at_the_lip_gets_the_other_levels_point_and_boxes_elsewhere_none():
    v = lip_v()
    res = process(BANK, [v + 3.0, v + 200.0])  # probes of 0.3 x 40 = 12 px: only the first reaches the lip
    assert res.alt_latlon is not None and res.alt_latlon.shape == (2, 2)
    order = np.argsort(res.boxes_xyxy[:, 3])  # the lip's box is the higher one in the image
    at_lip, below = order
    assert 38.0 < north_of(res.lat[at_lip], res.lon[at_lip]) <= 40.0
    assert north_of(*res.alt_latlon[at_lip]) > 41.0
    assert np.isnan(res.alt_latlon[below]).all()
    # past the lip the box lands on the lower level, with the lip's near side as its alternative
    res = process(BANK, [v - 3.0])
    assert north_of(res.lat[0], res.lon[0]) > 41.0 and 38.0 < north_of(*res.alt_latlon[0]) <= 40.0


def test_without_a_terrain_or_with_the_probe_off_there_are_none_and_a_flat_dem_has_no_edges():
    v = lip_v()
    assert process(None, [v + 3.0]).alt_latlon is None
    assert process(BANK, [v + 3.0], edge_probe=0.0).alt_latlon is None
    flat = process(FLAT, [v + 3.0, v + 100.0, v - 150.0])
    assert flat.alt_latlon is not None and np.isnan(flat.alt_latlon).all()


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), float("inf"), True, "0.3", None])
def test_a_bad_edge_probe_is_named(bad):
    with pytest.raises(ValueError, match="edge_probe"):
        PipelineConfig(edge_probe=bad)



def test_the_alternatives_move_with_the_telemetry_correction_as_the_boxes_points_do():
    # five people on the upper level and one at the lip, seen for a second; then the GPS steps 3 m east: the
    # correction measures the step and moves every box's point back, and each alternative by the same amount
    v = lip_v()
    people_v = [v + 3.0, v + 150.0, v + 250.0, v + 350.0, v + 420.0]
    us = [CAM.cx, CAM.cx - 300.0, CAM.cx + 250.0, CAM.cx - 120.0, CAM.cx + 400.0]
    boxes = np.array([[u - 8, b - 40.0, u + 8, b] for u, b in zip(us, people_v, strict=True)], np.float32)
    scores = np.full(len(boxes), 0.9, np.float32)
    cids = np.ones(len(boxes), np.int64)
    lat, lon = local_to_latlon(3.0, 0.0, LAT, LON)
    stepped = dataclasses.replace(POSE, lat=float(lat), lon=float(lon))
    out = {}
    for correct in (True, False):
        pipe = DetectionPipeline(CAM, CLASSES, PipelineConfig(use_size_filter=False, correct_telemetry=correct,
                                                              anchor="bottom", terrain=BANK))
        for k in range(30):
            pipe.process(boxes, scores, cids, POSE, k / 30.0)
        out[correct] = pipe.process(boxes, scores, cids, stepped, 1.0)
    moved, raw = out[True], out[False]
    assert moved.correction is not None and moved.correction.measured
    assert abs(moved.correction.east_m + 3.0) < 1.0  # the step, measured back
    # the rows in the same order (the boosted scores, and with them the order, differ)
    order = [int(np.flatnonzero((raw.boxes_xyxy == b).all(axis=1))[0]) for b in moved.boxes_xyxy]
    raw_ll, raw_alt = np.column_stack([raw.lat, raw.lon])[order], raw.alt_latlon[order]
    lip = np.flatnonzero(np.isfinite(raw_alt[:, 0]))
    assert len(lip) == 1 and np.isfinite(moved.alt_latlon[lip, 0]).all()
    shift = np.column_stack([moved.lat, moved.lon]) - raw_ll
    assert np.abs(shift[:, 1]).max() > 1e-5  # the points did move (3 m east ~ 4e-5 deg)
    np.testing.assert_allclose(moved.alt_latlon[lip] - raw_alt[lip], shift[lip], atol=1e-12)

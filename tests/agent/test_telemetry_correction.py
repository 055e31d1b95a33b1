"""Telemetry self-correction: a common-mode ground offset of the whole frame is found by registering its
confident detections to the memory map, within 0.3 m, and applied to the frame's ground points."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.telemetry_correction import CorrectionSettings, GroundOffsetEstimator, register_offset
from shared.geo import Camera, Pose, latlon_to_local, latlon_to_pixel, local_to_latlon, local_to_pixel

CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
LAT0, LON0 = 48.53, 9.06
# objects (east, north) metres, irregular and >= 12 m apart
OBJECTS = np.array([[0.0, 30.0], [-14.0, 38.0], [13.0, 44.0], [4.0, 56.0], [-9.0, 22.0], [16.0, 26.0]])


def _pose(east_m: float = 0.0, north_m: float = 0.0) -> Pose:
    lat, lon = local_to_latlon(east_m, north_m, LAT0, LON0)
    return Pose(float(lat), float(lon), 30.0, 50.0, 0.0)


def _frame_boxes(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of the objects as the TRUE pose sees them (20 px, 1 px jitter), confident, plus weak clutter."""
    lat, lon = local_to_latlon(OBJECTS[:, 0], OBJECTS[:, 1], LAT0, LON0)
    uv, valid = latlon_to_pixel(lat, lon, CAM, _pose())
    assert valid.all()
    uv = uv + rng.normal(0.0, 1.0, uv.shape)
    boxes = np.column_stack([uv[:, 0] - 10, uv[:, 1] - 10, uv[:, 0] + 10, uv[:, 1] + 10])
    scores = rng.uniform(0.7, 0.95, len(boxes))
    fp = rng.uniform([0, 600, 0, 0], [1900, 1060, 0, 0], (5, 4))
    fp[:, 2:] = fp[:, :2] + 20
    return (np.vstack([boxes, fp]).astype(np.float32), np.concatenate([scores, rng.uniform(0.05, 0.2, 5)]),
            np.ones(len(boxes) + 5, dtype=np.int64))


@pytest.mark.parametrize("offset_en", [(4.0, -3.0), (-5.5, 2.0), (0.0, 6.0)])
def test_common_mode_offset_recovered_within_30_cm(offset_en: tuple[float, float]) -> None:
    cfg = dataclasses.replace(PipelineConfig(), use_size_filter=False)
    pipe = DetectionPipeline(CAM, {1: "person"}, cfg)
    rng = np.random.default_rng(0)
    t = 0.0
    for _ in range(30):  # one second with true telemetry: the map learns where the objects are
        result = pipe.process(*_frame_boxes(rng), _pose(), t)
        t += 1 / 30
    # Now the GPS is off: every ground point moves by offset_en; the correction must undo it.
    for _ in range(3):
        result = pipe.process(*_frame_boxes(rng), _pose(*offset_en), t)
        t += 1 / 30
        assert result.correction is not None and result.correction.measured
        assert result.correction.east_m == pytest.approx(-offset_en[0], abs=0.3)
        assert result.correction.north_m == pytest.approx(-offset_en[1], abs=0.3)
    # The kept detections' ground points are back on the objects.
    strong = result.raw_scores >= 0.5
    e, n = latlon_to_local(result.lat[strong], result.lon[strong], LAT0, LON0)
    d = np.hypot(e[:, None] - OBJECTS[None, :, 0], n[:, None] - OBJECTS[None, :, 1]).min(axis=1)
    assert np.median(d) < 1.0


def test_without_memory_or_switched_off_no_correction_is_applied() -> None:
    rng = np.random.default_rng(1)
    for cfg in (dataclasses.replace(PipelineConfig(), use_memory=False),
                dataclasses.replace(PipelineConfig(), correct_telemetry=False)):
        pipe = DetectionPipeline(CAM, {1: "person"}, dataclasses.replace(cfg, use_size_filter=False))
        result = pipe.process(*_frame_boxes(rng), _pose(3.0, 0.0), 0.0)
        assert result.correction is None


def test_too_few_confident_boxes_fall_back_to_raw_telemetry() -> None:
    est = GroundOffsetEstimator(CorrectionSettings(hold_s=0.5))
    assert est.update(0.0, (2.0, -1.0), 5, 0.9).east_m == 2.0
    held = est.update(0.3, None)
    assert not held.measured and held.east_m == 2.0  # held ...
    later = est.update(5.0, None)
    assert abs(later.east_m) < 0.01 and abs(later.north_m) < 0.01  # ... then back to the raw telemetry


def test_register_offset_finds_the_centre_of_a_clipped_plateau() -> None:
    r = 10
    ys, xs = np.mgrid[-r:r + 1, -r:r + 1]
    blob = np.clip(2.0 * np.exp(-((xs - 3) ** 2 + (ys + 2) ** 2) / 8.0), 0.0, 1.0).astype(np.float32)
    dx, dy, support = register_offset(np.stack([blob, blob]), np.array([1.0, 0.5]))
    assert dx == pytest.approx(3.0, abs=0.05) and dy == pytest.approx(-2.0, abs=0.05)
    assert support == pytest.approx(1.0, abs=0.01)
    assert register_offset(np.zeros((2, 3, 3), np.float32), np.ones(2)) == (0.0, 0.0, 0.0)


def test_register_offset_keeps_to_the_current_correction_over_an_alias() -> None:
    """Two blobs: the true offset near the current correction (support 0.8) and an alias 9 cells away that
    scores higher in this frame (1.0): searched near the current one first, the alias is not taken unless
    nothing near it reaches the support asked for."""
    r = 12
    ys, xs = np.mgrid[-r:r + 1, -r:r + 1]

    def blob(cx: float, cy: float, peak: float) -> np.ndarray:
        return (peak * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / 2.0)).astype(np.float32)

    patches = np.stack([blob(1, 0, 0.8) + blob(-8, 4, 1.0)])
    dx, dy, support = register_offset(patches, np.ones(1))
    assert (dx, dy) == pytest.approx((-8.0, 4.0), abs=0.3)  # the whole window: the alias wins
    dx, dy, support = register_offset(patches, np.ones(1), near=(0.5, 0.0, 3.0), near_support=0.5)
    assert (dx, dy) == pytest.approx((1.0, 0.0), abs=0.3) and support == pytest.approx(0.8, abs=0.02)
    # nothing near the current correction reaches the support: a step, the whole window is searched
    dx, dy, _ = register_offset(patches, np.ones(1), near=(0.5, 0.0, 3.0), near_support=0.9)
    assert (dx, dy) == pytest.approx((-8.0, 4.0), abs=0.3)
    # a disc outside the window is ignored
    dx, dy, _ = register_offset(patches, np.ones(1), near=(40.0, 0.0, 3.0), near_support=0.5)
    assert (dx, dy) == pytest.approx((-8.0, 4.0), abs=0.3)


@pytest.mark.parametrize(("anchor_s", "drifts"), [(0.0, True), (3.0, False), (None, False)])
def test_an_anchored_correction_does_not_walk_away_with_the_walkers(anchor_s: float | None, drifts: bool) -> None:
    """Regression (coop-slope): exact telemetry, six people standing and two walking east. The map trails the
    walkers, so every frame measures a small offset westwards; measured against a map that holds the earlier
    corrections, an unanchored correction adds them up (2.5 m in 10 s). Anchored to the telemetry it stays
    within a few decimetres and the standing people's points stay on them. None: the default (anchored)."""
    cfg = dataclasses.replace(PipelineConfig(), use_size_filter=False)
    if anchor_s is not None:
        cfg = dataclasses.replace(cfg, correction_anchor_s=anchor_s)
    pipe = DetectionPipeline(CAM, {1: "person"}, cfg)
    rng = np.random.default_rng(0)
    walkers = np.array([[-12.0, 33.0], [-6.0, 47.0]])
    for frame in range(300):
        t = frame / 30
        points = np.vstack([OBJECTS, walkers + [1.4 * t, 0.0]])
        lat, lon = local_to_latlon(points[:, 0], points[:, 1], LAT0, LON0)
        uv, valid = latlon_to_pixel(lat, lon, CAM, _pose())
        assert valid.all()
        uv = uv + rng.normal(0.0, 1.0, uv.shape)
        boxes = np.column_stack([uv[:, 0] - 10, uv[:, 1] - 10, uv[:, 0] + 10, uv[:, 1] + 10]).astype(np.float32)
        result = pipe.process(boxes, rng.uniform(0.7, 0.95, len(boxes)), np.ones(len(boxes), np.int64), _pose(), t)
    assert result.correction is not None and result.correction.measured
    offset = float(np.hypot(result.correction.east_m, result.correction.north_m))
    e, n = latlon_to_local(result.lat, result.lon, LAT0, LON0)  # the kept boxes, highest score first
    error = float(np.median(np.hypot(e[None, :] - OBJECTS[:, :1], n[None, :] - OBJECTS[:, 1:]).min(axis=1)))
    if drifts:
        assert offset > 1.5 and error > 1.5
    else:
        assert offset < 0.5 and error < 0.5


def test_settings_reject_bad_values() -> None:
    with pytest.raises(ValueError, match="anchor_s"):
        PipelineConfig(correction_anchor_s=-1.0)
    with pytest.raises(ValueError, match="search_m"):
        CorrectionSettings(search_m=-1.0)
    with pytest.raises(ValueError, match="local_m"):
        PipelineConfig(correction_local_m=float("nan"))
    with pytest.raises(ValueError, match="min_points"):
        PipelineConfig(correction_min_points=0)


def test_a_lasting_gps_step_is_corrected_at_first_and_handed_back_to_the_telemetry() -> None:
    """With the default anchor (10 s), a GPS step that lasts is corrected at once and given back to the telemetry
    over about the anchor time: the map then follows the telemetry to where it puts the objects."""
    cfg = dataclasses.replace(PipelineConfig(), use_size_filter=False)
    assert cfg.correction_anchor_s > 0
    pipe = DetectionPipeline(CAM, {1: "person"}, cfg)
    rng = np.random.default_rng(1)
    step = (4.0, -3.0)
    corrections = {}
    for frame in range(30 * 60):
        t = frame / 30
        pose = _pose() if t < 2.0 else _pose(*step)
        result = pipe.process(*_frame_boxes(rng), pose, t)
        if frame in (2 * 30 + 3, 60 * 30 - 1):
            assert result.correction is not None
            corrections[frame // 30] = (result.correction.east_m, result.correction.north_m)
    assert corrections[2] == pytest.approx((-step[0], -step[1]), abs=0.3)  # just after the step: undone
    assert np.hypot(*corrections[59]) < 0.5  # a minute later: the telemetry's own
    strong = result.raw_scores >= 0.5
    e, n = latlon_to_local(result.lat[strong], result.lon[strong], LAT0, LON0)
    d = np.hypot(e[:, None] - (OBJECTS[None, :, 0] + step[0]), n[:, None] - (OBJECTS[None, :, 1] + step[1])).min(axis=1)
    assert np.median(d) < 0.5  # the points where the stepped telemetry puts the objects


def test_over_a_terrain_the_correction_moves_the_uav_and_marches_the_rays_again() -> None:
    """A GPS step over a bank: the correction found on the level ground is applied to the memory map by moving the
    UAV and marching the rays again, so the people on the bank keep reading and stamping the evidence where they
    stand; moving their ground points by the correction instead would put them 1.2-2.2 m off, where the map holds
    far less (the bank faces the camera: 4 m of the UAV move their hits by less). The returned points stay the
    telemetry's own moved by the correction (the tracker takes them back)."""
    from shared.terrain import ElevationGrid, Terrain

    north = np.arange(120.0, -21.0, -1.0)  # rows from 120 m north down to 20 m south
    bank = 6.0 / (1.0 + np.exp(-(north - 50.0) / 0.8))  # level up to ~46 m north, a 6 m bank by ~54 m
    grid = ElevationGrid.from_local(np.tile(bank[:, None], (1, 101)), LAT0, LON0, west_m=-50.0, north_m=120.0,
                                    cell_m=1.0)
    terrain = Terrain(grid, 0.0)  # heights above take-off; the take-off is on the level ground at 0 m
    level = np.vstack([OBJECTS[OBJECTS[:, 1] < 45.0], [[-22.0, 31.0], [7.0, 35.0], [-3.0, 15.0]]])
    people = np.vstack([level, [[2.0, 50.0], [-6.0, 51.0]]])  # and two on the bank's face
    up = terrain.up_m(people[:, 0], people[:, 1], _pose())
    assert (up[-2:] > 2.0).all() and (up[:-2] < 0.1).all()
    uv_true, ok = local_to_pixel(people[:, 0], people[:, 1], CAM, _pose(), terrain=terrain)
    assert ok.all()

    def boxes(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        uv = uv_true + rng.normal(0.0, 0.5, uv_true.shape)  # the anchor is the box's bottom centre
        b = np.column_stack([uv[:, 0] - 8, uv[:, 1] - 30, uv[:, 0] + 8, uv[:, 1]])
        return b.astype(np.float32), rng.uniform(0.7, 0.95, len(b)), np.ones(len(b), dtype=np.int64)

    cfg = dataclasses.replace(PipelineConfig(), use_size_filter=False, anchor="bottom", terrain=terrain)
    pipe = DetectionPipeline(CAM, {1: "person"}, cfg)
    rng = np.random.default_rng(1)
    t = 0.0
    for _ in range(30):  # one second with true telemetry: the map learns where they are
        result = pipe.process(*boxes(rng), _pose(), t)
        t += 1 / 30
    before = result.scores.min()
    step = (0.0, 4.0)  # the GPS jumps 4 m north, towards the bank (which faces the camera)
    for _ in range(15):  # half a second: the map's evidence is then mostly this stretch's stamps
        b, s, c = boxes(rng)
        result = pipe.process(b, s, c, _pose(*step), t)
        t += 1 / 30
        assert result.correction is not None and result.correction.measured
    assert -step[1] - 0.6 < result.correction.north_m < -step[1] + 1.0  # the bank's raw points pull it short
    # every person, those on the bank too, still reads its evidence: boosted as before the step
    assert len(result) == len(people) and result.scores.min() >= before - 0.02

    def evidence(east: np.ndarray, north_m: np.ndarray) -> np.ndarray:
        lat, lon = local_to_latlon(east, north_m, LAT0, LON0)
        gx, gy = pipe.grid.latlon_to_cell(lat, lon)
        return pipe.memory.values_at("person", np.round(gx), np.round(gy))

    assert evidence(people[-2:, 0], people[-2:, 1]).min() > 0.3  # stamped where they stand
    # the telemetry's own points moved by the correction: metres off on the bank, where the map has nothing
    er, nr, _, _ = pipe.ground_points(b, _pose(*step))
    e_s, n_s = er[-2:] + result.correction.east_m, nr[-2:] + step[1] + result.correction.north_m
    assert np.hypot(e_s - people[-2:, 0], n_s - people[-2:, 1]).min() > 1.2
    ratio = evidence(e_s, n_s) / evidence(people[-2:, 0], people[-2:, 1])  # about 1 on the previous code
    assert ratio.max() < 0.8 and ratio.mean() < 0.7
    # the returned points are those (the tracker undoes the correction to get the telemetry's own back)
    e, n = latlon_to_local(result.lat, result.lon, LAT0, LON0)
    assert np.hypot(e[:, None] - e_s[None], n[:, None] - n_s[None]).min(axis=0).max() < 1e-3

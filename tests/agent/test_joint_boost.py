"""Boosting with the partners' evidence where the joint registration puts it (agent.joint_boost)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.joint_boost import registered_joint_evidence
from agent.memory_map import JointLayer, MemoryMap
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon

CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
POSE = Pose(lat=48.53, lon=9.05, height_m=30.0, pitch_deg=40.0, heading_deg=0.0)
CLASSES = {1: "person"}
T = 100.0
#: where the people stand (east, north m of POSE) and how far north the partner's map puts them
PEOPLE = np.array([[-8.0, 40.0], [-4.0, 46.0], [0.0, 42.0], [4.0, 48.0], [8.0, 41.0]])
SHIFT_N = 3.0
#: scores as given (no calibration to a reference temperature), so the boosts can be read off exactly
BASE = dataclasses.replace(PipelineConfig(), calibrate_scores=False)
#: the partner's footprint: a square around everything in view
AREA = np.array([[-60.0, 10.0], [60.0, 10.0], [60.0, 120.0], [-60.0, 120.0]])


def put_blobs(joint: JointLayer, blobs: list[tuple[np.ndarray, float]], t: float = T) -> None:
    """The partner's evidence: Gaussian blobs (sigma 4 cells, clipped at 1) of the given peaks at east/north
    points of POSE, (points (K, 2), peak) per group; the tiles they touch are replaced."""
    grid = joint.grid
    n = grid.n
    tiles: dict[tuple[int, int], np.ndarray] = {}
    for centres_en, peak in blobs:
        for east, north in centres_en:
            lat, lon = local_to_latlon(np.array([east]), np.array([north]), POSE.lat, POSE.lon)
            gx, gy = (int(v[0]) for v in grid.latlon_to_cell_index(lat, lon))
            for dy in range(-16, 17):
                for dx in range(-16, 17):
                    x, y = gx + dx, gy + dy
                    tile = tiles.setdefault((x // n, y // n), np.zeros((n, n), np.float32))
                    value = min(1.0, peak * math.exp(-(dx * dx + dy * dy) / 32.0))
                    tile[y % n, x % n] = max(tile[y % n, x % n], value)
    for (tx, ty), values in tiles.items():
        joint.update("person", tx, ty, values, t)


def boxes_at(points_en: np.ndarray, height_px: float = 60.0) -> np.ndarray:
    """Upright boxes whose ground point (the bottom middle at this pitch) is each east/north point."""
    lat, lon = local_to_latlon(points_en[:, 0], points_en[:, 1], POSE.lat, POSE.lon)
    uv, ok = latlon_to_pixel(lat, lon, CAM, POSE)
    assert ok.all()
    w = 0.4 * height_px
    return np.column_stack([uv[:, 0] - w / 2, uv[:, 1] - height_px, uv[:, 0] + w / 2, uv[:, 1]]).astype(np.float32)


def registered_pipeline(config: PipelineConfig) -> tuple[DetectionPipeline, float]:
    """A pipeline whose joint registration has locked onto the partner's map SHIFT_N m north of its own
    detections (several frames of confident boxes on PEOPLE, the partner's blobs beside them); returns it and the
    next frame's time."""
    joint = JointLayer(ttl_s=5.0)
    put_blobs(joint, [(PEOPLE + [0.0, SHIFT_N], 0.9)])
    joint.put_footprint("uav2", np.column_stack(local_to_latlon(AREA[:, 0], AREA[:, 1], POSE.lat, POSE.lon)), T)
    pipe = DetectionPipeline(CAM, CLASSES, config, joint=joint)
    boxes = boxes_at(PEOPLE)
    t = T
    for _ in range(12):
        pipe.process(boxes, np.full(len(boxes), 0.95, np.float32), np.ones(len(boxes), np.int64), POSE, t)
        t += 0.1
    offset = pipe.joint_registration_offset_px()
    assert offset is not None and offset[1] < -20.0  # the partner's evidence lies up the image (further north)
    return pipe, t


def test_the_evidence_read_where_the_partner_holds_it():
    joint = JointLayer(ttl_s=5.0)
    memory = MemoryMap()
    memory.advance(T, POSE.lat, POSE.lon)
    put_blobs(joint, [(np.array([[0.0, 40.0]]), 0.4)])
    lat, lon = local_to_latlon(np.array([0.0, 20.0, 0.0]), np.array([40.0, 40.0, 40.0]), POSE.lat, POSE.lon)
    gx, gy = joint.grid.latlon_to_cell(lat, lon)
    own = np.array([0.6, 0.6, 0.0], np.float32)
    # without a partner's footprint one partner is assumed: its evidence (2 x 0.4 - 0) beside this UAV's own
    evidence, absent = registered_joint_evidence(joint, memory, "person", own, gx, gy, T, cover_uavs=2,
                                                 absent_value=0.05)
    assert evidence[0] == pytest.approx((0.6 + 0.8) / 2, abs=0.02) and evidence[2] == pytest.approx(0.4, abs=0.01)
    assert evidence[1] == pytest.approx(0.3) and not absent.any()  # nothing known of where the partner looks
    # with the partner's footprint over the first two spots only: the second is covered and empty, the third not
    # covered (this UAV's own evidence stands alone there)
    east, north = np.array([-5.0, 25.0, 25.0, -5.0]), np.array([20.0, 20.0, 33.0, 33.0])
    joint.put_footprint("uav2", np.column_stack(local_to_latlon(east, north, POSE.lat, POSE.lon)), T)
    lat, lon = local_to_latlon(np.array([0.0, 20.0, 0.0]), np.array([26.0, 26.0, 40.0]), POSE.lat, POSE.lon)
    gx, gy = joint.grid.latlon_to_cell(lat, lon)
    evidence, absent = registered_joint_evidence(joint, memory, "person", own, gx, gy, T, cover_uavs=2,
                                                 absent_value=0.05)
    assert absent.tolist() == [True, True, False]
    np.testing.assert_allclose(evidence, [0.3, 0.3, 0.0], atol=1e-6)
    assert registered_joint_evidence(joint, memory, "person", own[:0], gx[:0], gy[:0], T, cover_uavs=2,
                                     absent_value=0.05)[0].shape == (0,)


@settings(max_examples=40, deadline=None)
@given(own=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=6), peak=st.floats(0.0, 1.0),
       cover_uavs=st.integers(1, 4))
def test_the_registered_evidence_stays_between_zero_and_one(own, peak, cover_uavs):
    joint = JointLayer(ttl_s=5.0)
    memory = MemoryMap()
    memory.advance(T, POSE.lat, POSE.lon)
    put_blobs(joint, [(np.array([[0.0, 40.0]]), peak)])
    k = len(own)
    lat, lon = local_to_latlon(np.linspace(-3, 3, k), np.full(k, 40.0), POSE.lat, POSE.lon)
    gx, gy = joint.grid.latlon_to_cell(lat, lon)
    evidence, absent = registered_joint_evidence(joint, memory, "person", np.array(own, np.float32), gx, gy, T,
                                                 cover_uavs=cover_uavs, absent_value=0.05)
    assert evidence.dtype == np.float32 and ((evidence >= 0) & (evidence <= 1)).all()
    # without footprints cover_uavs - 1 partners are assumed: the own evidence counts for 1 / cover_uavs of the
    # mean at least, and nothing is marked absent (nothing tells where a partner looks)
    assert (evidence >= np.array(own, np.float32) / max(cover_uavs, 1) - 1e-6).all() and not absent.any()


def test_a_weak_box_is_boosted_by_the_partners_evidence_where_the_registration_puts_it():
    # a sixth person, seen weakly here; the partner's evidence of it 3 m north, too weak for a joint detection
    # (the others' share, 2 x 0.12, below joint_min_value), so only the boost can lift it
    sixth = np.array([[12.0, 44.0]])
    scores = {}
    for on in (True, False):
        cfg = dataclasses.replace(BASE, joint_register_boost=on)
        pipe, t = registered_pipeline(cfg)
        assert pipe.joint is not None
        put_blobs(pipe.joint, [(PEOPLE + [0.0, SHIFT_N], 0.9), (sixth + [0.0, SHIFT_N], 0.12)], t)
        boxes = np.vstack([boxes_at(PEOPLE), boxes_at(sixth)])
        conf = np.array([0.95] * len(PEOPLE) + [0.2], np.float32)
        result = pipe.process(boxes, conf, np.ones(len(boxes), np.int64), POSE, t)
        weak = [(s, j) for b, s, j in zip(result.boxes_xyxy, result.scores, result.from_joint, strict=True)
                if np.allclose(b, boxes[-1], atol=0.5)]
        assert len(weak) == 1 and not weak[0][1]  # not a joint detection: the boost alone
        scores[on] = float(weak[0][0])
    # read at the box the blob 3 m away gives little (its flank); where the registration puts it, the partner's
    # 2 x 0.12 beside this UAV's 0, halved: logit(0.2) + 6 x 0.12 -> 0.34 at the blob's middle
    assert scores[False] < 0.25
    assert 0.3 < scores[True] < 0.345


def test_a_box_where_the_partner_looks_and_sees_nothing_loses_log_odds():
    stray = np.array([[-14.0, 50.0]])  # in the partner's footprint, no evidence of the partner near it
    logits = {}
    for on, absent_logit in ((True, 2.0), (True, 0.0), (False, 2.0)):
        cfg = dataclasses.replace(BASE, joint_register_boost=on, joint_absent_logit=absent_logit)
        pipe, t = registered_pipeline(cfg)
        boxes = np.vstack([boxes_at(PEOPLE), boxes_at(stray)])
        conf = np.array([0.95] * len(PEOPLE) + [0.6], np.float32)
        result = pipe.process(boxes, conf, np.ones(len(boxes), np.int64), POSE, t)
        s = [s for b, s in zip(result.boxes_xyxy, result.scores, strict=True) if np.allclose(b, boxes[-1], atol=0.5)]
        logits[(on, absent_logit)] = math.log(s[0] / (1 - s[0]))
        # the people the partner sees are not lowered
        assert (result.scores[:len(PEOPLE)] > 0.95).all()
    assert logits[(True, 2.0)] == pytest.approx(logits[(True, 0.0)] - 2.0, abs=1e-3)
    assert logits[(False, 2.0)] == pytest.approx(logits[(True, 0.0)], abs=1e-3)


@pytest.mark.parametrize("field, value", [("joint_absent_value", -0.1), ("joint_absent_value", 1.5),
                                          ("joint_absent_logit", -1.0), ("joint_absent_logit", math.inf),
                                          ("joint_register_boost", 1), ("joint_register_boost", "yes")])
def test_bad_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(PipelineConfig(), **{field: value})


def test_another_video_starts_without_the_previous_ones_registration():
    pipe, _ = registered_pipeline(dataclasses.replace(BASE, joint_register_boost=True))
    pipe.reset()
    assert pipe.joint_registration_offset_px() is None


@pytest.mark.parametrize("change", [{"joint_detections": False}, {"joint_mode": "local"}])
def test_the_option_says_when_it_cannot_act(change, caplog):
    cfg = dataclasses.replace(BASE, joint_register_boost=True, **change)
    with caplog.at_level("WARNING", logger="agent.pipeline"):
        DetectionPipeline(CAM, CLASSES, cfg, joint=JointLayer(ttl_s=5.0))
    assert "joint_register_boost does nothing here" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="agent.pipeline"):
        DetectionPipeline(CAM, CLASSES, dataclasses.replace(BASE, joint_register_boost=True), joint=JointLayer())
        DetectionPipeline(CAM, CLASSES, cfg)  # no joint layer: nothing to say
    assert "joint_register_boost" not in caplog.text


def test_over_a_terrain_the_registered_spots_are_marched_from_the_uav_the_correction_moves():
    """With a DEM and a telemetry correction, the registered spots come from the rays marched again from the UAV
    moved by the correction, as the candidates' own cells do (agent.pipeline._boost_and_update); on a slope that
    faces the camera that is metres from the raw hits moved by the correction (the previous code's spots)."""
    from agent.telemetry_correction import GroundCorrection
    from shared.terrain import ElevationGrid, Terrain

    north = np.arange(120.0, -21.0, -1.0)
    slope = np.clip(north - 20.0, 0.0, None) * 0.3  # level to 20 m north, then rising 0.3 m per metre
    grid = ElevationGrid.from_local(np.tile(slope[:, None], (1, 121)), POSE.lat, POSE.lon, west_m=-60.0,
                                    north_m=120.0, cell_m=1.0)
    terrain = Terrain(grid, 0.0)
    pipe, _ = registered_pipeline(dataclasses.replace(BASE, joint_register_boost=True, terrain=terrain))
    offset = pipe.joint_registration_offset_px()
    assert offset is not None
    boxes = boxes_at(PEOPLE)
    idx = np.arange(len(boxes))
    shifted = boxes + np.array([offset[0], offset[1], offset[0], offset[1]], np.float32)
    correction = GroundCorrection(east_m=1.0, north_m=-4.0, measured=True)
    spots = pipe._registered_cells(boxes, idx, POSE, correction)
    assert spots is not None
    moved = correction.moved(POSE)
    east, north_m, _, ok = pipe.ground_points(shifted, moved)
    assert ok.all()
    want = pipe.grid.latlon_to_cell(*local_to_latlon(east, north_m, moved.lat, moved.lon))
    np.testing.assert_allclose(np.column_stack(spots), np.column_stack(want), atol=1e-6)
    # the raw hits moved by the correction lie well off on this slope (4 m of the UAV move a hit by ~2.5 m)
    er, nr, _, _ = pipe.ground_points(shifted, POSE)
    old = pipe.grid.latlon_to_cell(*local_to_latlon(er + 1.0, nr - 4.0, POSE.lat, POSE.lon))
    assert (np.hypot(old[0] - want[0], old[1] - want[1]) * pipe.memory.cell_m).min() > 1.0
    # without a terrain (flat ground) the spots are the raw points moved by the correction, as before
    flat, _ = registered_pipeline(dataclasses.replace(BASE, joint_register_boost=True))
    fo = flat.joint_registration_offset_px()
    assert fo is not None
    fshift = boxes + np.array([fo[0], fo[1], fo[0], fo[1]], np.float32)
    fe, fn, _, _ = flat.ground_points(fshift, POSE)
    fspots = flat._registered_cells(boxes, idx, POSE, correction)
    assert fspots is not None
    np.testing.assert_allclose(np.column_stack(fspots), np.column_stack(
        flat.grid.latlon_to_cell(*local_to_latlon(fe + 1.0, fn - 4.0, POSE.lat, POSE.lon))), atol=1e-9)

"""Joint detections: the other UAVs' evidence in view, projected back into this UAV's image."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import agent.joint_detections as jd
from agent.boxes import box_anchor_points, box_iou
from agent.joint_detections import JointRegistration, joint_score, others_evidence
from agent.memory_map import JointLayer
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.size_filter import BUILTIN_PRIORS
from shared.geo import Camera, Pose, latlon_to_local, latlon_to_pixel, local_to_latlon, pixel_to_latlon

CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
POSE = Pose(lat=48.53, lon=9.05, height_m=30.0, pitch_deg=40.0, heading_deg=0.0)
CLASSES = {1: "person"}
T = 100.0
#: synthesised boxes are off by default (joint_synth_factor 0); the tests of synthesis turn them on
SYNTH = dataclasses.replace(PipelineConfig(), joint_synth_factor=0.25)


def joint_with_blob(east_m: float, north_m: float, peak: float = 0.6) -> tuple[JointLayer, float, float]:
    """A joint layer with one Gaussian blob (sigma 1.5 cells) centred on the cell at east/north of POSE, clipped at
    1 as the maps are (a peak above 1 makes a plateau).

    Returns the layer and the lat/lon of the blob's centre cell.
    """
    joint, ((lat, lon),) = joint_with_blobs([(east_m, north_m, peak)])
    return joint, lat, lon


def joint_with_blobs(blobs: list[tuple[float, float, float]]) -> tuple[JointLayer, list[tuple[float, float]]]:
    """A joint layer with Gaussian blobs (east_m, north_m, peak) as `joint_with_blob` makes one (the larger value
    where they meet); returns it and each blob's centre cell's lat/lon."""
    joint = JointLayer(ttl_s=3.0)
    grid = joint.grid
    n = grid.n
    tiles: dict[tuple[int, int], np.ndarray] = {}
    centres = []
    for east_m, north_m, peak in blobs:
        lat, lon = local_to_latlon(np.array([east_m]), np.array([north_m]), POSE.lat, POSE.lon)
        gx, gy = grid.latlon_to_cell_index(lat, lon)
        gx, gy = int(gx[0]), int(gy[0])
        for dy in range(-8, 9):
            for dx in range(-8, 9):
                x, y = gx + dx, gy + dy
                tile = tiles.setdefault((x // n, y // n), np.zeros((n, n), np.float32))
                value = min(1.0, peak * math.exp(-(dx * dx + dy * dy) / (2 * 1.5**2)))
                tile[y % n, x % n] = max(tile[y % n, x % n], value)
        clat, clon = grid.cell_to_latlon(gx + 0.5, gy + 0.5)
        centres.append((float(clat), float(clon)))
    for (tx, ty), values in tiles.items():
        joint.update("person", tx, ty, values, T)
    return joint, centres


def run(pipe: DetectionPipeline, boxes=None, scores=None, pose: Pose | None = POSE):
    boxes = np.zeros((0, 4), np.float32) if boxes is None else np.asarray(boxes, np.float32)
    scores = np.zeros(0, np.float32) if scores is None else np.asarray(scores, np.float32)
    return pipe.process(boxes, scores, np.ones(len(scores), np.int64), pose, T)


def test_a_peak_in_view_with_no_detection_becomes_one_box_at_its_pixel_with_the_prior_size():
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    assert len(run(DetectionPipeline(CAM, CLASSES, joint=joint))) == 0  # by default nothing is synthesised
    pipe = DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint)
    result = run(pipe)
    assert len(result) == 1
    assert result.from_joint is not None and result.from_joint.tolist() == [True]
    assert result.raw_scores[0] == 0.0
    uv, valid = latlon_to_pixel(np.array([lat]), np.array([lon]), CAM, POSE)
    assert valid[0]
    anchor = box_anchor_points(result.boxes_xyxy.astype(np.float64), "auto", POSE.pitch_deg)[0]
    assert np.hypot(*(anchor - uv[0])) < 3.0
    # size: the built-in prior's diagonal at the peak's range and depression
    east, north = latlon_to_local(lat, lon, POSE.lat, POSE.lon)
    slant = math.sqrt(float(east) ** 2 + float(north) ** 2 + POSE.height_m**2)
    depression = math.degrees(math.asin(POSE.height_m / slant))
    diag_m = math.exp(float(BUILTIN_PRIORS["person"].mean_std(depression)[0]))
    x1, y1, x2, y2 = result.boxes_xyxy[0]
    assert math.hypot(x2 - x1, y2 - y1) == pytest.approx(diag_m * CAM.fx / slant, rel=0.02)
    assert y2 - y1 > x2 - x1  # an upright person
    # the score: others' evidence 2 * 0.6 - 0 = 1 (clipped), boosted prior, times the synthesis factor
    cfg = pipe.config
    expected = joint_score(np.array([1.0]), cfg.joint_prior_score, cfg.boost_mode, cfg.boost_weight,
                           cfg.logodds_scale)[0] * cfg.joint_synth_factor
    assert result.scores[0] == pytest.approx(expected, rel=0.05)


@pytest.mark.parametrize("peak", [50.0, 200.0])
def test_a_plateau_gives_one_box_at_its_middle(peak):
    """A steadily seen object is a plateau of the clipped map (a blob 50 and 200 times over the clip): its inner
    cells tie as maxima under the 0.25 m peak kernel, and the peak kept is the middle one, not the first in row
    order (0.4 and 0.8 m off)."""
    joint, lat, lon = joint_with_blob(2.0, 40.0, peak=peak)
    result = run(DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint))
    assert len(result) == 1
    anchor = box_anchor_points(result.boxes_xyxy.astype(np.float64), "auto", POSE.pitch_deg)
    (a_lat,), (a_lon,), _ = pixel_to_latlon(anchor, CAM, POSE)
    east, north = latlon_to_local(a_lat, a_lon, lat, lon)
    assert math.hypot(float(east), float(north)) < 0.3  # within a cell (0.4 m) of the blob's centre


@pytest.mark.parametrize("east_m, north_m", [(0.0, -20.0), (60.0, 40.0), (0.0, 400.0)],
                         ids=["behind", "beside the view", "beyond the range and horizon"])
def test_a_peak_outside_the_view_gives_nothing(east_m, north_m):
    joint, _, _ = joint_with_blob(east_m, north_m)
    result = run(DetectionPipeline(CAM, CLASSES, joint=joint))
    assert len(result) == 0
    assert result.from_joint is not None and len(result.from_joint) == 0


def _box_at(lat: float, lon: float, w: float = 20.0, h: float = 60.0) -> list[list[float]]:
    uv, _ = latlon_to_pixel(np.array([lat]), np.array([lon]), CAM, POSE)
    frac = float(box_anchor_points(np.array([[0.0, 0.0, 0.0, 1.0]]), "auto", POSE.pitch_deg)[0, 1])
    u, v = uv[0]
    return [[u - w / 2, v - frac * h, u + w / 2, v + (1 - frac) * h]]


def test_a_peak_explained_by_a_confident_kept_box_adds_nothing():
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    # confident: its boost by the joint value (0.6) ranks above the peak's score (prior 0.5, the others'
    # evidence 1): logit(0.95) + 6 * 0.6 > logit(0.5) + 6 * 1
    result = run(DetectionPipeline(CAM, CLASSES, joint=joint), _box_at(lat, lon), [0.95])
    assert len(result) == 1
    assert result.from_joint is not None and not result.from_joint.any()
    assert result.raw_scores[0] == pytest.approx(0.95)


def test_a_weak_real_candidate_at_the_peak_is_promoted_instead_of_synthesising_a_box():
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    box = _box_at(lat, lon)
    pipe = DetectionPipeline(CAM, CLASSES, dataclasses.replace(PipelineConfig(), joint_mode="local"), joint=joint)
    assert run(pipe, box, [0.01]).from_joint is None  # "local" ignores the joint map altogether
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    result = run(pipe, box, [0.01])
    assert len(result) == 1
    assert result.from_joint is not None and result.from_joint.tolist() == [True]
    np.testing.assert_allclose(result.boxes_xyxy[0], np.asarray(box[0], np.float32))
    cfg = pipe.config
    assert result.scores[0] == pytest.approx(
        joint_score(np.array([1.0]), cfg.joint_prior_score, cfg.boost_mode, cfg.boost_weight, cfg.logodds_scale)[0],
        rel=0.05)


def test_without_a_joint_layer_or_with_the_option_off_results_are_unchanged():
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 300], [1800, 1000], (40, 2))
    boxes = np.column_stack([xy, xy + rng.uniform(10, 60, (40, 2))]).astype(np.float32)
    scores = rng.uniform(0.01, 0.9, 40).astype(np.float32)
    joint, _, _ = joint_with_blob(2.0, 40.0)
    off = dataclasses.replace(PipelineConfig(), joint_detections=False)
    plain = [run(DetectionPipeline(CAM, CLASSES), boxes, scores) for _ in range(1)][0]
    for pipe in (DetectionPipeline(CAM, CLASSES, joint=joint, config=off), DetectionPipeline(CAM, CLASSES)):
        result = run(pipe, boxes, scores)
        assert result.from_joint is None
        np.testing.assert_array_equal(result.boxes_xyxy, plain.boxes_xyxy)
    # a frame without a pose: nothing from the joint map
    assert run(DetectionPipeline(CAM, CLASSES, joint=joint), pose=None).from_joint is None


def test_others_evidence_takes_the_own_contribution_out_of_the_mean():
    joint = np.array([0.5, 0.5, 0.3, 0.8], np.float32)
    own = np.array([0.0, 0.5, 0.6, 0.0], np.float32)
    np.testing.assert_allclose(others_evidence(joint, own, 2), [1.0, 0.5, 0.0, 1.0])
    np.testing.assert_allclose(others_evidence(joint, own, 3), [0.75, 0.5, 0.15, 1.0], atol=1e-6)
    np.testing.assert_allclose(others_evidence(joint, own, 1), joint)


def test_others_evidence_uses_the_partners_coverage_where_it_is_known():
    joint = np.array([0.5, 0.5, 0.6, 0.6], np.float32)
    own = np.array([0.0, 0.5, 0.6, 0.3], np.float32)
    # no partner covers cells 0 and 2: the joint value there is this UAV's own (or stale) evidence
    np.testing.assert_allclose(others_evidence(joint, own, 2, others_cover=np.array([0, 1, 0, 2])),
                               [0.0, 0.5, 0.0, 0.75], atol=1e-6)


def test_own_evidence_where_no_partner_looks_is_not_taken_for_the_partners():
    joint, lat, lon = joint_with_blob(2.0, 40.0)  # the joint value the mean of this UAV's own tile alone
    # before any partner footprint is known, cover_uavs = 2 is assumed everywhere: a joint detection
    assert run(DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint)).from_joint.tolist() == [True]
    east = np.array([-60.0, -20.0, -20.0, -60.0])
    north = np.array([0.0, 0.0, 80.0, 80.0])  # the partner looks 20-60 m west of the blob
    joint.put_footprint("uav2", np.column_stack(local_to_latlon(east, north, POSE.lat, POSE.lon)), T)
    assert len(run(DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint))) == 0
    joint.put_footprint("uav2", np.column_stack(local_to_latlon(east + 40.0, north, POSE.lat, POSE.lon)), T)
    assert run(DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint)).from_joint.tolist() == [True]


def _grid_people(rng: np.random.Generator, n: int = 8) -> np.ndarray:
    return np.column_stack([rng.uniform(-20, 20, n), rng.uniform(30, 60, n)])


def test_registration_finds_the_image_offset_most_peaks_share():
    reg = JointRegistration(radius_m=8.0, window_s=10.0, min_pairs=3)
    assert reg.offset() == (0.0, 0.0)
    rng = np.random.default_rng(1)
    true = np.array([0.05, -0.01])  # focal lengths: ~3 deg sideways
    for k in range(20):
        own_en = _grid_people(rng)
        own_xy = own_en / 50.0  # any image positions will do: the offset is what is measured
        peak_en = own_en[:6] + rng.normal(0, 0.5, (6, 2))  # the partner sees 6 of the 8, with jitter
        peak_xy = own_xy[:6] + true + rng.normal(0, 0.006, (6, 2))
        # and 3 people this UAV misses (resting behind a tree) beside one it sees: their pairs with it
        # fall on one sharp wrong offset frame after frame, a higher histogram maximum than the spread one
        group = own_en[6] + np.array([[1.5, 0.0], [0.0, 1.5], [-1.5, 0.0]])
        group_xy = np.repeat(own_xy[6:7] + [0.02, 0.0], 3, axis=0)
        reg.update(float(k) / 5, np.vstack([peak_en, group]), own_en, np.vstack([peak_xy, group_xy]), own_xy)
    dx, dy = reg.offset()
    assert (dx, dy) == pytest.approx(tuple(true), abs=0.002)


def test_registration_ignores_far_pairs_and_forgets_old_ones():
    reg = JointRegistration(radius_m=8.0, window_s=10.0, min_pairs=3)
    own_en = np.array([[0.0, 40.0], [10.0, 40.0], [20.0, 45.0]])
    for k in range(3):
        reg.update(float(k), own_en + [1.0, 0.0], own_en, own_en / 50 + [0.01, 0.0], own_en / 50)
    assert reg.offset() == pytest.approx((0.01, 0.0), abs=1e-3)
    reg.update(30.0, own_en + [50.0, 0.0], own_en, own_en / 50 + [0.01, 0.0], own_en / 50)  # too far to pair
    assert reg.offset() == (0.0, 0.0)  # and the old pairs have aged out
    reg.update(31.0, own_en, own_en, own_en / 50 + [0.5, 0.0], own_en / 50)  # beyond max_rad: no attitude bias
    assert reg.offset() == (0.0, 0.0)


def _frame(pipe: DetectionPipeline, boxes, scores, t: float):
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    return pipe.process(boxes, np.asarray(scores, np.float32), np.ones(len(boxes), np.int64), POSE, t)


def _peak_score(cfg: PipelineConfig) -> float:
    return float(joint_score(np.array([1.0]), cfg.joint_prior_score, cfg.boost_mode, cfg.boost_weight,
                             cfg.logodds_scale)[0])


def test_a_peak_keeps_the_box_where_this_uav_last_saw_it():
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    hidden = np.asarray(_box_at(lat, lon)[0]) + [25.0, 0.0, 25.0, 0.0]  # seen 25 px beside the peak
    pipe = DetectionPipeline(CAM, CLASSES, SYNTH, joint=joint)
    # frames 1 and 2: a weak candidate of the hidden person is promoted
    for k in range(SYNTH.joint_carry_min_sightings):
        first = _frame(pipe, hidden, [0.02], T + k / 30)
        assert first.from_joint is not None and first.from_joint.sum() == 1
        np.testing.assert_allclose(first.boxes_xyxy[0], hidden, atol=0.01)
    # next frame: no candidate; the box of the last sighting stands for the person, not one at the peak
    t = T + SYNTH.joint_carry_min_sightings / 30
    second = _frame(pipe, np.zeros((0, 4)), [], t)
    assert second.from_joint is not None and second.from_joint.sum() == 1
    np.testing.assert_allclose(second.boxes_xyxy[0], hidden, atol=0.01)
    cfg = pipe.config
    assert second.scores[0] == pytest.approx(_peak_score(cfg) * cfg.joint_carry_factor, rel=0.05)
    # long after the last sighting, the box is synthesised at the peak again (scored as such)
    late = _frame(pipe, np.zeros((0, 4)), [], t + 2 * cfg.joint_carry_s)
    assert late.from_joint is not None and late.from_joint.sum() == 1
    assert late.scores[0] == pytest.approx(_peak_score(cfg) * cfg.joint_synth_factor, rel=0.05)
    assert abs(float(late.boxes_xyxy[0, 0]) - float(hidden[0])) > 20.0


def test_a_single_sighting_is_not_carried():
    """One weak box near a peak is as often a background false positive or a neighbour: it is promoted
    in its frame, but only a place seen again stands for the object in frames without a box."""
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    hidden = np.asarray(_box_at(lat, lon)[0]) + [25.0, 0.0, 25.0, 0.0]
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    first = _frame(pipe, hidden, [0.02], T)
    assert first.from_joint is not None and first.from_joint.sum() == 1
    second = _frame(pipe, np.zeros((0, 4)), [], T + 1 / 30)
    assert len(second) == 0
    # seen twice (the boxes overlap), the place is carried
    _frame(pipe, hidden, [0.02], T + 2 / 30)
    _frame(pipe, hidden + 1.0, [0.02], T + 3 / 30)
    third = _frame(pipe, np.zeros((0, 4)), [], T + 4 / 30)
    assert third.from_joint is not None and third.from_joint.sum() == 1


#: a far, grazing view (the occluded UAV on `coop`): 27 m up, 20 deg down
GRAZING = Pose(lat=POSE.lat, lon=POSE.lon, height_m=27.0, pitch_deg=20.0, heading_deg=0.0)


@pytest.mark.parametrize("down_px, promoted", [(22.0, True), (40.0, False)])
def test_the_gate_around_a_peak_is_an_angle_in_the_image(down_px, promoted):
    """At 80 m and 20 deg a pixel down the image is ~0.2 m on the ground: a weak box 22 px below the
    peak's pixel lies ~4 m beyond the 3 m ground gate, yet within the peak's angular error."""
    joint, lat, lon = joint_with_blob(0.0, 80.0)
    uv, valid = latlon_to_pixel(np.array([lat]), np.array([lon]), CAM, GRAZING)
    assert valid[0]
    frac = float(box_anchor_points(np.array([[0.0, 0.0, 0.0, 1.0]]), "auto", GRAZING.pitch_deg)[0, 1])
    u, v = uv[0, 0], uv[0, 1] + down_px
    box = np.array([[u - 7.0, v - frac * 40.0, u + 7.0, v + (1 - frac) * 40.0]], np.float32)
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    out = pipe.process(box, np.array([0.02], np.float32), np.ones(1, np.int64), GRAZING, T)
    assert len(out) == 1
    east, north = latlon_to_local(out.lat[:1], out.lon[:1], lat, lon)
    assert float(np.hypot(east, north)[0]) > pipe.config.joint_gate_m  # outside the ground gate
    assert out.from_joint is not None and bool(out.from_joint[0]) is promoted
    assert (float(out.scores[0]) > 0.5) is promoted


def test_a_carried_box_keeps_the_drift_of_its_sightings():
    """A sweeping camera (or a walker) moves the object's boxes steadily: the carried box goes on moving."""
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    start = np.asarray(_box_at(lat, lon)[0]) - [20.0, 0.0, 20.0, 0.0]
    step = np.array([2.0, 0.0, 2.0, 0.0])  # 2 px per frame, 60 px/s
    rng = np.random.default_rng(1)
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    n = 20
    for k in range(n):
        jitter = np.tile(rng.normal(0.0, 0.5, 2), 2)
        out = _frame(pipe, start + k * step + jitter, [0.02], T + k / 30)
        assert out.from_joint is not None and out.from_joint.sum() == 1
    gone = 6  # frames without a candidate
    late = _frame(pipe, np.zeros((0, 4)), [], T + (n - 1 + gone) / 30)
    assert late.from_joint is not None and late.from_joint.sum() == 1
    expected = start + (n - 1 + gone) * step
    last_seen = start + (n - 1) * step
    err = np.abs(late.boxes_xyxy[0] - expected).max()
    assert err < 4.0 < np.abs(late.boxes_xyxy[0] - last_seen).max()


def test_weak_boxes_on_the_remembered_spot_are_promoted_first_even_beyond_the_gate():
    """At long range a few pixels are metres on the ground: the object's next weak box may land outside
    the gate; where this UAV last saw it decides, not the nearest weak box to the peak."""
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    slat, slon = local_to_latlon(np.array([2.0]), np.array([37.5]), POSE.lat, POSE.lon)  # 2.5 m short
    seen = np.asarray(_box_at(float(slat[0]), float(slon[0]))[0])
    other = np.asarray(_box_at(lat, lon)[0]) - [60.0, 0.0, 60.0, 0.0]  # another weak box within the gate
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    first = _frame(pipe, seen, [0.02], T)
    assert first.from_joint is not None and first.from_joint.sum() == 1
    lower = seen + [0.0, 25.0, 0.0, 25.0]  # the same person's next box, 25 px lower
    second = _frame(pipe, np.vstack([other, lower]), [0.05, 0.02], T + 1 / 30)
    assert second.from_joint is not None
    promoted = np.flatnonzero(second.from_joint)
    assert len(promoted) == 1
    np.testing.assert_allclose(second.boxes_xyxy[promoted[0]], lower, atol=0.01)
    east, north = latlon_to_local(second.lat[promoted], second.lon[promoted], lat, lon)
    assert float(np.hypot(east, north)[0]) > pipe.config.joint_gate_m  # outside the ground gate


def test_time_going_back_does_not_move_remembered_boxes():
    carry = jd.JointCarry(carry_s=0.5)
    carry.advance(T, POSE)
    lat, lon = local_to_latlon(np.array([2.0]), np.array([40.0]), POSE.lat, POSE.lon)
    box = np.array([100.0, 100.0, 120.0, 160.0])
    carry.observe(1, box, float(lat[0]), float(lon[0]), T, 3.0)
    carry.anchors[0].velocity[:] = [30.0, 0.0]
    carry.advance(T + 0.1, POSE)
    np.testing.assert_allclose(carry.anchors[0].box, box + [3.0, 0.0, 3.0, 0.0])
    carry.advance(T + 0.05, POSE)  # an older frame: nothing moves
    np.testing.assert_allclose(carry.anchors[0].box, box + [3.0, 0.0, 3.0, 0.0])
    carry.advance(T + 0.7, POSE)  # beyond carry_s since the sighting: forgotten
    assert carry.anchors == []


def test_carry_off_synthesises_at_the_peak():
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    hidden = np.asarray(_box_at(lat, lon)[0]) + [40.0, 0.0, 40.0, 0.0]  # seen 40 px beside the peak
    pipe = DetectionPipeline(CAM, CLASSES, dataclasses.replace(SYNTH, joint_carry_s=0.0), joint=joint)
    _frame(pipe, hidden, [0.02], T)
    _frame(pipe, hidden, [0.02], T + 1 / 30)
    second = _frame(pipe, np.zeros((0, 4)), [], T + 2 / 30)
    assert second.from_joint is not None and second.from_joint.sum() == 1
    assert abs(float(second.boxes_xyxy[0, 0]) - float(hidden[0])) > 20.0


@pytest.mark.parametrize("field, value", [("joint_carry_s", -1.0), ("joint_carry_s", math.nan),
                                          ("joint_carry_factor", 1.5), ("joint_carry_factor", -0.1),
                                          ("joint_peak_smoothing_m", 0.0), ("joint_peak_gate_across_rad", -0.01),
                                          ("joint_peak_gate_down_rad", math.inf), ("joint_register_score", -1.0),
                                          ("joint_register_radius_m", 0.0), ("joint_register_window_s", -1.0),
                                          ("joint_register_min_pairs", 0), ("joint_register_min_pairs", 2.5),
                                          ("joint_register_bin_rad", 0.0), ("joint_register_match_rad", math.nan),
                                          ("joint_register_candidates", 0), ("joint_register_max_rad", 0.0),
                                          ("joint_carry_gate", -1.0), ("joint_carry_min_sightings", 0),
                                          ("joint_carry_min_sightings", True), ("joint_carry_match_iou", 1.5),
                                          ("joint_carry_blend", -0.1), ("joint_carry_velocity_gain", 2.0)])
def test_bad_joint_settings_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(PipelineConfig(), **{field: value})


def test_registration_and_carry_take_their_settings_from_the_pipeline_config():
    cfg = dataclasses.replace(PipelineConfig(), joint_register_radius_m=5.0, joint_register_min_pairs=7,
                              joint_register_bin_rad=0.002, joint_carry_s=0.25, joint_carry_match_iou=0.4,
                              joint_carry_blend=0.6, joint_carry_velocity_gain=0.2)
    reg = JointRegistration.from_config(cfg)
    assert (reg.radius_m, reg.min_pairs, reg.bin_rad) == (5.0, 7, 0.002)
    carry = jd.JointCarry.from_config(cfg)
    assert (carry.carry_s, carry.match_iou, carry.blend, carry.velocity_gain) == (0.25, 0.4, 0.6, 0.2)
    # the constructors' defaults are the config's
    default, plain = JointRegistration.from_config(PipelineConfig()), JointRegistration()
    assert vars(default).keys() == vars(plain).keys()
    assert all(np.all(vars(default)[k] == vars(plain)[k]) for k in vars(plain) if not k.startswith("_"))
    assert vars(jd.JointCarry.from_config(PipelineConfig())) == vars(jd.JointCarry())


def test_joint_detections_score_on_the_boost_scale_unless_set():
    assert PipelineConfig().joint_scale == PipelineConfig().logodds_scale
    assert PipelineConfig(logodds_scale=3.0).joint_scale == 3.0
    assert PipelineConfig(joint_logodds_scale=4.0).joint_scale == 4.0
    with pytest.raises(ValueError, match="joint_logodds_scale"):
        PipelineConfig(joint_logodds_scale=0.0)


def test_kept_points_in_the_maps_frame_are_the_ones_matched_and_remembered():
    """Over a terrain the pipeline's returned points are moved by its correction, while the maps hold points marched
    again from the moved UAV (the pipeline passes those as on_map): the joint detections gate and remember a kept
    box at its point in the maps' frame, not at its returned one."""
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    pipe = DetectionPipeline(CAM, CLASSES, joint=joint)
    kept = run(pipe, _box_at(lat, lon), [0.95])
    assert len(kept) == 1 and kept.from_joint is not None and not kept.from_joint.any()
    far_lat, far_lon = local_to_latlon(np.array([9.0]), np.array([40.0]), POSE.lat, POSE.lon)  # 7 m east
    moved = dataclasses.replace(kept, lat=far_lat, lon=far_lon, from_joint=None)
    parts = dict(config=pipe.config, joint=joint, memory=pipe.memory, camera=CAM, class_names=CLASSES,
                 size_filter=pipe.active_size_filter)
    for on_map, where in ((None, (far_lat, far_lon)), ((kept.lat, kept.lon), (kept.lat, kept.lon))):
        carry = jd.JointCarry.from_config(pipe.config)
        result = jd.add_joint_detections(moved, POSE, T, carry=carry, on_map=on_map, **parts)
        assert len(result) == 1 and result.lat[0] == far_lat[0]  # the returned point is left as it was
        (anchor,) = carry.anchors  # the kept box explains the peak (in the image) and is remembered ...
        east, north = latlon_to_local(*where, *carry.origin)
        assert (anchor.east, anchor.north) == pytest.approx((east[0], north[0]), abs=0.01)  # ... at this point


def test_a_fragment_of_a_promoted_box_is_not_promoted_by_a_second_peak():
    """Two peaks 4.5 m apart along the view (a partner's double of one person, or two people), the farther one
    weaker; a weak box at the nearer one and a weaker box overlapping it (IoU ~0.2) whose anchor sits on the
    farther one. The nearer peak promotes the first box; the farther one promotes the second, which is a fragment
    of the first (fragment_iou 0.1), so the promotion is taken back: it keeps its own score. With the fragment
    rule off both are promoted."""
    joint, ((lat_a, lon_a), (lat_b, lon_b)) = joint_with_blobs([(2.0, 40.0, 0.6), (2.0, 44.5, 0.4)])
    near, far = _box_at(lat_a, lon_a, h=100.0)[0], _box_at(lat_b, lon_b, h=60.0)[0]
    iou = float(box_iou(np.array([near]), np.array([far]))[0, 0])
    assert 0.1 < iou < 0.5  # a fragment by the rule, and NMS keeps both
    scores = {}
    for frag in (0.1, 0.0):
        pipe = DetectionPipeline(CAM, CLASSES, dataclasses.replace(PipelineConfig(), fragment_iou=frag), joint=joint)
        result = run(pipe, [near, far], [0.3, 0.2])
        assert len(result) == 2 and result.from_joint is not None
        by_box = {tuple(np.round(b, 1)): (float(s), bool(j))
                  for b, s, j in zip(result.boxes_xyxy, result.scores, result.from_joint, strict=True)}
        scores[frag] = (by_box[tuple(np.round(np.float32(near), 1))], by_box[tuple(np.round(np.float32(far), 1))])
    (near_s, near_j), (far_s, far_j) = scores[0.1]
    assert near_j and near_s > 0.99  # promoted by the nearer peak
    assert not far_j and far_s < 0.5  # the fragment keeps its own (unboosted) score
    (near_s0, near_j0), (far_s0, far_j0) = scores[0.0]
    assert near_j0 and far_j0 and far_s0 > 0.98  # without the rule the farther peak promotes the fragment


def test_a_carried_box_that_a_stronger_box_overlaps_is_dropped():
    """The carried sighting of `test_a_peak_keeps_the_box_where_this_uav_last_saw_it`, in a frame whose only box
    is a confident one around it (IoU ~0.15: a fragment by the rule, not on the sighting's spot, its ground point
    beyond the peak's gate): the carried box is a piece of that box's object and goes; with the rule off it
    stays."""
    joint, lat, lon = joint_with_blob(2.0, 40.0)
    hidden = np.asarray(_box_at(lat, lon)[0]) + [25.0, 0.0, 25.0, 0.0]
    big = hidden + [-20.0, 0.0, 20.0, 70.0]  # 60 x 130 px holding the hidden box, its foot 70 px lower (nearer)
    iou = float(box_iou(hidden[None], big[None])[0, 0])
    assert 0.1 < iou < SYNTH.joint_carry_match_iou
    kept = {}
    for frag in (0.1, 0.0):
        pipe = DetectionPipeline(CAM, CLASSES, dataclasses.replace(SYNTH, fragment_iou=frag), joint=joint)
        for k in range(SYNTH.joint_carry_min_sightings):
            _frame(pipe, hidden, [0.02], T + k / 30)
        result = _frame(pipe, big, [0.95], T + SYNTH.joint_carry_min_sightings / 30)
        assert result.from_joint is not None and len(result.from_joint) == len(result)
        kept[frag] = [(np.asarray(b), bool(j)) for b, j in zip(result.boxes_xyxy, result.from_joint, strict=True)]
        assert any(np.allclose(b, big, atol=0.01) and not j for b, j in kept[frag])  # the confident box, as is
    assert len(kept[0.1]) == 1
    assert len(kept[0.0]) == 2 and any(np.allclose(b, hidden, atol=0.01) and j for b, j in kept[0.0])

"""The tracker's registration to its predicted tracks: a common offset of all detections is found; a
crowd, too few pairs or disagreeing pairs give none. The tracker applies it before gating."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.boxes import box_iou
from agent.tracking.registration import (
    anchored_offset,
    correction_jacobian,
    fit_pose_correction,
    image_pairs,
    point_heights,
    track_offset,
)
from shared.geo import Pose
from shared.terrain import ElevationGrid, Terrain

TRACKS = np.array([[0.0, 0.0], [12.0, 3.0], [-9.0, 14.0], [20.0, -11.0], [-15.0, -8.0]])


@settings(max_examples=40, deadline=None)
@given(st.floats(-2.5, 2.5), st.floats(-2.5, 2.5), st.integers(0, 2**31))
def test_a_common_offset_is_recovered(dx: float, dy: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    dets = TRACKS - np.array([dx, dy]) + rng.normal(0.0, 0.1, TRACKS.shape)
    off = track_offset(dets, TRACKS, gate_m=4.0, min_pairs=3)
    assert off is not None
    assert off[0] == pytest.approx(dx, abs=0.2) and off[1] == pytest.approx(dy, abs=0.2)


def test_too_few_pairs_or_no_agreement_give_none() -> None:
    assert track_offset(TRACKS[:2] + 1.0, TRACKS[:2], gate_m=4.0, min_pairs=3) is None
    rng = np.random.default_rng(0)
    scattered = TRACKS + rng.uniform(-3.5, 3.5, TRACKS.shape) * np.array([[1, 1], [-1, 1], [1, -1], [-1, -1], [0, 1]])
    off = track_offset(scattered, TRACKS, gate_m=4.0, min_pairs=3, inlier_m=0.5)
    assert off is None
    assert track_offset(np.zeros((0, 2)), TRACKS, gate_m=4.0, min_pairs=3) is None


def test_the_tracker_removes_a_per_frame_common_offset_before_gating() -> None:
    from agent.tracking import GpsTracker, TrackerConfig
    from tests.agent.test_tracker import CAM, CLASSES, FPS, observe, pose_at

    people = [(-8.0, 25.0), (0.0, 30.0), (7.0, 26.0), (-3.0, 38.0), (9.0, 40.0)]
    east, north = (np.array(v) for v in zip(*people, strict=True))
    pose = pose_at()
    rng = np.random.default_rng(5)
    tracker = GpsTracker(TrackerConfig(register_tracks=True), CLASSES)  # off by default
    ids: list[set[int]] = [set() for _ in people]
    residual = []
    for k in range(90):
        jitter = rng.normal(0.0, 1.2, 2)  # the whole frame moves: GPS/gimbal jitter
        result = observe(east + jitter[0], north + jitter[1], pose, noise_m=0.05, rng=rng)
        assert len(result) == len(people)
        outs = tracker.update(result, pose, 1.7e9 + k / FPS, CAM)
        if k < 10:
            continue
        # the tracks keep the frame they were born in: offset + jitter is that frame's constant
        assert tracker.last_offset_en is not None
        residual.append(np.add(tracker.last_offset_en, jitter))
        boxes = {tr.id: tr.box_xyxy for tr in outs if tr.confirmed and tr.matched}
        for i, box in enumerate(result.boxes_xyxy):
            ids[i].update(tid for tid, b in boxes.items() if np.allclose(b, box))
    assert np.std(np.array(residual), axis=0).max() < 0.2
    assert all(len(s) == 1 for s in ids), ids  # every person keeps one id


# --------------------------------------------------------------------------- pairs made in the image
BOXES = np.array([[100.0, 100.0, 130.0, 160.0], [400.0, 120.0, 430.0, 180.0], [800.0, 600.0, 840.0, 680.0],
                  [1500.0, 900.0, 1530.0, 960.0]])
CLS = np.ones(len(BOXES), np.int64)


@settings(max_examples=40, deadline=None)
@given(st.floats(-12.0, 12.0), st.floats(-12.0, 12.0), st.integers(0, 2**31))
def test_image_pairs_recover_an_offset_larger_than_any_ground_gate(dx: float, dy: float, seed: int) -> None:
    """A 4-decimal GPS step moves every ground point by 7-11 m; the boxes stay where they were."""
    rng = np.random.default_rng(seed)
    tracks_xy = TRACKS[: len(BOXES)]
    dets_xy = tracks_xy - np.array([dx, dy]) + rng.normal(0.0, 0.1, tracks_xy.shape)
    found = anchored_offset(BOXES, CLS, tracks_xy, BOXES + rng.normal(0.0, 2.0, BOXES.shape), CLS, dets_xy,
                            iou_min=0.5, min_pairs=2, inlier_m=2.0)
    assert found is not None
    (ox, oy), n = found
    assert n == len(BOXES)
    assert ox == pytest.approx(dx, abs=0.2) and oy == pytest.approx(dy, abs=0.2)


def test_image_pairs_need_overlap_the_same_class_and_agreement() -> None:
    xy = TRACKS[: len(BOXES)]
    moved = BOXES + np.array([60.0, 0.0, 60.0, 0.0])  # the camera turned: no box overlaps its track
    assert anchored_offset(BOXES, CLS, xy, moved, CLS, xy - 5.0, 0.5, 2, 2.0) is None
    assert anchored_offset(BOXES, CLS, xy, BOXES, CLS + 1, xy - 5.0, 0.5, 2, 2.0) is None  # other class
    scattered = xy + np.array([[6.0, 0.0], [-6.0, 0.0], [0.0, 6.0], [0.0, -6.0]])  # no common offset
    assert anchored_offset(BOXES, CLS, xy, BOXES, CLS, scattered, 0.5, 2, 2.0) is None
    assert anchored_offset(BOXES[:1], CLS[:1], xy[:1], BOXES[:1], CLS[:1], xy[:1], 0.5, 2, 2.0) is None
    # one wrong pair among four: the three that agree give the offset
    one_off = xy - 3.0
    one_off[2] += np.array([5.0, -4.0])
    found = anchored_offset(BOXES, CLS, xy, BOXES, CLS, one_off, 0.5, 2, 2.0)
    assert found is not None and found[1] == 3
    assert found[0] == pytest.approx((3.0, 3.0))


def test_the_tracker_keeps_every_id_through_a_gps_step() -> None:
    """Old DJI SRT files round GPS to 4 decimals: the UAV position jumps by 7.4 m east at once. Without
    image pairs every track of the frame fails its gate and is replaced by a new one."""
    from agent.tracking import GpsTracker, TrackerConfig
    from tests.agent.test_tracker import CAM, CLASSES, FPS, observe, pose_at

    people = [(-8.0, 25.0), (0.0, 30.0), (7.0, 26.0), (-3.0, 38.0), (9.0, 40.0)]
    east, north = (np.array(v) for v in zip(*people, strict=True))
    rng = np.random.default_rng(3)

    def run(config: TrackerConfig) -> tuple[set[int], list]:
        tracker = GpsTracker(config, CLASSES)
        seen: set[int] = set()
        offsets = []
        for k in range(90):
            step = 7.4 if k >= 20 else 0.0  # the reported position steps east; the drone did not move
            reported = pose_at(east_m=step)
            # the same pixels, projected with the reported pose: every ground point moves 7.4 m east
            result = observe(east + step, north, reported, noise_m=0.05, rng=rng)
            outs = tracker.update(result, reported, 1.7e9 + k / FPS, CAM)
            if k >= 10:
                seen |= {tr.id for tr in tracker.report(outs)}
            offsets.append(tracker.last_offset_en)
        return seen, offsets

    seen, offsets = run(TrackerConfig(image_register=True))
    assert len(seen) == len(people), seen
    assert offsets[20] is not None and offsets[20][0] == pytest.approx(-7.4, abs=0.3)
    # the tracks follow the telemetry's frame within a few track_follow_s: later frames need little offset
    assert abs(offsets[-1][0]) < 0.3
    seen_without, _ = run(TrackerConfig(image_register=False))
    assert len(seen_without) > len(people)


def test_a_pose_correction_separates_a_turn_from_a_shift() -> None:
    """Pairs spread in range and bearing: a heading error turns them about the UAV, a GPS error shifts
    them; the fit tells the two apart and lays the detections back onto the tracks."""
    rng = np.random.default_rng(1)
    tracks = rng.uniform([-30.0, 20.0], [30.0, 70.0], (12, 2))  # relative to the UAV, metres
    true = np.array([1.5, -0.8, np.radians(1.2), np.radians(-0.4)])
    dets = tracks - correction_jacobian(tracks, 40.0) @ true + rng.normal(0.0, 0.05, tracks.shape)
    S = np.repeat(0.05**2 * np.eye(2)[None], len(tracks), axis=0)
    prior = np.array([10.0, 10.0, np.radians(1.0), np.radians(0.5)])
    fit = fit_pose_correction(dets, tracks - dets, S, 40.0, prior, gate_chi2=9.21, min_pairs=2)
    assert fit is not None
    p, cov, inliers, _ = fit
    assert inliers.all()
    assert p[:2] == pytest.approx(true[:2], abs=0.2)
    assert np.degrees(p[2:]) == pytest.approx(np.degrees(true[2:]), abs=0.1)
    moved = dets + correction_jacobian(dets, 40.0) @ p
    assert np.hypot(*(moved - tracks).T).max() < 0.3
    # a wrong pair is left out and does not pull the fit
    bad = dets.copy()
    bad[0] += np.array([6.0, -5.0])
    p2, _, inl2, _ = fit_pose_correction(bad, tracks - bad, S, 40.0, prior, gate_chi2=9.21, min_pairs=2)
    assert not inl2[0] and inl2[1:].all()
    assert p2 == pytest.approx(p, abs=0.05)
    # too few pairs
    assert fit_pose_correction(dets[:1], (tracks - dets)[:1], S[:1], 40.0, prior, 9.21, 2) is None


def test_a_lone_object_keeps_its_id_through_a_gps_step() -> None:
    """One object gives no two pairs to register: by default its own pair registers the frame
    (image_register_alone), and the image-first round (off by default) would pair its box with its track
    as well; without either, a 7.4 m GPS step gives it a new track."""
    from agent.tracking import GpsTracker, TrackerConfig
    from tests.agent.test_tracker import CAM, CLASSES, FPS, observe, pose_at

    def ids(config: TrackerConfig) -> set[int]:
        rng = np.random.default_rng(4)
        tracker = GpsTracker(config, CLASSES)
        seen: set[int] = set()
        for k in range(60):
            step = 7.4 if k >= 20 else 0.0
            reported = pose_at(east_m=step)
            outs = tracker.update(observe(np.array([3.0 + step]), np.array([30.0]), reported, noise_m=0.05, rng=rng),
                                  reported, 1.7e9 + k / FPS, CAM)
            if k >= 10:
                seen |= {tr.id for tr in tracker.report(outs)}
        return seen

    assert len(ids(TrackerConfig())) == 1
    assert len(ids(TrackerConfig(image_register_alone=False, image_first_iou=0.3))) == 1
    assert len(ids(TrackerConfig(image_register_alone=False))) > 1


def test_a_frame_the_image_cannot_register_keeps_the_pending_correction() -> None:
    """Two people a GPS step apart; the reported position steps 7.4 m east, then one of them is missed for a
    while. With one pair of two the frame cannot be registered: raw telemetry would lay the other person's
    detection onto the missed one's track (the tracks have followed only part of the step yet). The
    tracker carries what the tracks have not followed of the last correction instead."""
    from agent.tracking import GpsTracker, TrackerConfig
    from tests.agent.test_tracker import CAM, CLASSES, FPS, observe, pose_at

    east, north = np.array([0.0, 7.4]), np.array([30.0, 30.0])

    def run(config: TrackerConfig) -> tuple[list[set[int]], list[bool], list]:
        tracker = GpsTracker(config, CLASSES)
        ids: list[set[int]] = [set(), set()]
        carried, corrections = [], []
        for k in range(80):
            step = 7.4 if k >= 20 else 0.0
            reported = pose_at(east_m=step)
            seen = [0] if 30 <= k < 42 else [0, 1]  # B missed for 0.4 s
            result = observe(east[seen] + step, north[seen], reported)
            outs = tracker.update(result, reported, 1.7e9 + k / FPS, CAM)
            carried.append(tracker.last_correction_carried)
            corrections.append(tracker.last_correction)
            boxes = {tr.id: tr.box_xyxy for tr in outs if tr.confirmed and tr.matched}
            for i, box in zip(seen, result.boxes_xyxy, strict=True):
                ids[i].update(tid for tid, b in boxes.items() if np.allclose(b, box))
        return ids, carried, corrections

    ids, carried, corrections = run(TrackerConfig())
    assert all(len(s) == 1 for s in ids) and ids[0] != ids[1], ids
    # carried while the missed track is still expected in the image; then its one pair registers alone
    assert not any(carried[:30]) and all(carried[30:34]) and not any(carried[43:])
    # the carried part shrinks as the tracks follow the telemetry's frame (track_follow_s)
    east_parts = [c[0] for c in corrections[30:42]]
    assert -7.4 < east_parts[0] < 0 and all(b > a for a, b in zip(east_parts, east_parts[1:], strict=False))
    ids_raw, carried_raw, _ = run(TrackerConfig(carry_correction=False))
    assert not any(carried_raw)
    # from raw telemetry both confirmed tracks miss the frame and are replaced by new ids
    assert all(len(s) > 1 for s in ids_raw), ids_raw


def _dense_image_pairs(tb: np.ndarray, tc: np.ndarray, db: np.ndarray, dc: np.ndarray,
                       iou_min: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference: mutual argmax over the dense IoU matrix (what image_pairs computed before it went sparse)."""
    iou = box_iou(tb, db)
    iou[tc[:, None] != dc[None, :]] = 0.0
    best_det, best_track = iou.argmax(axis=1), iou.argmax(axis=0)
    rows = np.arange(len(tb))
    ti = np.flatnonzero((best_track[best_det] == rows) & (iou[rows, best_det] >= iou_min))
    return ti, best_det[ti]


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 40), st.integers(0, 40), st.floats(0.05, 0.9), st.integers(0, 2**31), st.booleans())
def test_sparse_image_pairs_equal_the_dense_mutual_best_overlaps(m: int, n: int, iou_min: float, seed: int,
                                                                 snap: bool) -> None:
    """Random boxes of two classes in a small image (many overlaps; with snap, on a coarse grid so that equal
    IoUs tie): the k-d tree version pairs exactly what the dense matrix's mutual argmax pairs."""
    rng = np.random.default_rng(seed)

    def boxes(k: int) -> np.ndarray:
        xy = rng.uniform(0, 300, (k, 2))
        wh = rng.uniform(5, 80, (k, 2))
        if snap:
            xy, wh = np.round(xy / 20) * 20, np.round(wh / 20) * 20 + 20
        return np.column_stack([xy, xy + wh])

    tb, db = boxes(m), boxes(n)
    tc, dc = rng.integers(0, 2, m), rng.integers(0, 2, n)
    got = image_pairs(tb, tc, db, dc, iou_min)
    want = _dense_image_pairs(tb, tc, db, dc, iou_min) if m and n else (np.zeros(0), np.zeros(0))
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_point_heights_are_the_poses_over_flat_ground_and_the_distance_to_the_slope_over_a_terrain() -> None:
    """The flat error model's height for the tracks' share of a pose correction: over a plane rising 1 in 5 to the
    east it is the camera's distance from the plane (40 / sqrt(1.04) m) at every point on it, the pose's off the
    DEM and without one."""
    pose = Pose(lat=47.67, lon=9.27, height_m=40.0, pitch_deg=35.0, heading_deg=0.0)
    rel = np.array([[0.0, 30.0], [-20.0, 60.0], [45.0, -10.0], [500.0, 0.0]])
    assert point_heights(rel, pose, None) == 40.0
    east = np.arange(-150.0, 151.0)
    grid = ElevationGrid.from_local(np.tile(100.0 + 0.2 * east, (301, 1)), 47.67, 9.27, west_m=-150.0,
                                    north_m=150.0, cell_m=1.0)
    h = np.asarray(point_heights(rel, pose, Terrain(grid, 100.0)))
    assert h[:3] == pytest.approx(40.0 / np.sqrt(1.04), rel=1e-6)
    assert h[3] == 40.0
    flat = ElevationGrid.from_local(np.full((301, 301), 100.0), 47.67, 9.27, west_m=-150.0, north_m=150.0, cell_m=1.0)
    assert np.asarray(point_heights(rel, pose, Terrain(flat, 100.0))) == pytest.approx(40.0)


def test_the_tracks_follow_a_pose_correction_with_their_height_on_the_terrain() -> None:
    """GpsTracker's tracks and re-ID memory follow a pose correction (here at once: track_follow_s 0) by its
    Jacobian at each point's effective height on the DEM (a plane rising 4 in 5: 40 / sqrt(1.64) m), as the
    detections are corrected, not at the pose's 40 m."""
    from agent.tracking import GpsTracker, TrackerConfig

    pose = Pose(lat=47.67, lon=9.27, height_m=40.0, pitch_deg=35.0, heading_deg=0.0)
    east = np.arange(-150.0, 151.0)
    grid = ElevationGrid.from_local(np.tile(100.0 + 0.8 * east, (301, 1)), 47.67, 9.27, west_m=-150.0,
                                    north_m=150.0, cell_m=1.0)
    rel = np.array([[0.0, 30.0], [-20.0, 60.0], [45.0, -10.0]])
    p = np.array([0.3, -0.2, np.radians(0.5), np.radians(1.0)])
    tracker = GpsTracker(TrackerConfig(track_follow_s=0.0), {1: "person"})
    state = tracker._state
    state.origin = (pose.lat, pose.lon)
    for table, key in ((state.active, "x"), (state.lost, "pos")):
        table.cols = {k: np.zeros((3, *shape), dtype) for k, (shape, dtype) in table.fields.items()}
        table.cols[key][:, :2] = rel
    tracker._uav_en, tracker._correction = (0.0, 0.0), p.copy()
    tracker._ground = (pose, Terrain(grid, 100.0))
    tracker._follow_telemetry(0.1)
    from agent.tracking.registration import correction_offset

    expected = rel - correction_jacobian(rel, 40.0 / np.sqrt(1.64)) @ p
    assert expected == pytest.approx(rel + correction_offset(rel, 40.0 / np.sqrt(1.64), -p), abs=1e-9)
    assert state.active["x"][:, :2] == pytest.approx(expected, abs=1e-9)
    assert state.lost["pos"] == pytest.approx(expected, abs=1e-9)
    flat = rel - correction_jacobian(rel, 40.0) @ p
    assert np.abs(flat - expected).max() > 0.1  # the pose's height would put them elsewhere


@settings(max_examples=200, deadline=None)
@given(east=st.floats(-3e4, 3e4), north=st.floats(-3e4, 3e4), h=st.floats(2.0, 500.0),
       d_beta=st.floats(-0.05, 0.05), d_theta=st.floats(-0.05, 0.05))
def test_a_correction_moves_points_as_the_jacobian_within_the_horizon_and_never_past_it(east, north, h, d_beta,
                                                                                        d_theta):
    from agent.tracking.registration import correction_jacobian, correction_offset
    from shared.geo import horizon_distance_m

    rel = np.array([[east, north]])
    p = np.array([0.5, -0.3, d_theta, d_beta])
    step = correction_offset(rel, h, p)[0]
    r = float(np.hypot(east, north))
    limit = max(r, horizon_distance_m(h))
    assert np.isfinite(step).all()
    assert float(np.hypot(*(rel[0] + step))) <= limit * (1 + abs(d_theta)) + 1.0
    if abs(r - (r * r + h * h) / h * d_beta) <= limit:  # the linear move stays within: it is the move
        assert step == pytest.approx((correction_jacobian(rel, h) @ p)[0], rel=1e-9, abs=1e-9)


def test_a_correction_applied_frame_after_frame_stays_bounded():
    # the tracker's _follow_telemetry moves its tracks by the pending correction every frame: near a level gimbal
    # the linear pitch term grew them superexponentially (1e4 -> 1e292 m in 11 frames at 30 m up)
    from agent.tracking.registration import correction_offset
    from shared.geo import horizon_distance_m

    pts = np.array([[10_000.0, 11_000.0]])
    for _ in range(200):
        pts = pts + correction_offset(pts, 30.0, np.array([0.0, 0.0, 0.0, -0.004]))
    assert np.hypot(*pts[0]) <= max(np.hypot(10_000.0, 11_000.0), horizon_distance_m(30.0)) + 1e-6

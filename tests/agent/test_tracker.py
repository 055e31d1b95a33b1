"""GpsTracker on synthetic scenes made with the real camera geometry (shared.geo), no mocks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment

from agent.boxes import box_iou
from agent.frame_result import FrameResult
from agent.tracking import ClassMotion, GpsTracker, TrackerConfig
from agent.tracking.assignment import near_pairs, sparse_assignment
from agent.tracking.association import duplicate_mask
from agent.tracking.lifecycle import at_image_border
from agent.tracking.model import ground_measurement_cov
from shared.geo import Camera, Pose, latlon_to_local, local_to_latlon, local_to_pixel

CAM = Camera(width=3840, height=2160, fx=2985.0, fy=2985.0, cx=1920.0, cy=1080.0)
LAT0, LON0 = 48.53, 9.06
FPS = 30.0
CLASSES = {1: "person"}


def pose_at(heading_deg: float = 0.0, *, height_m: float = 30.0, pitch_deg: float = 40.0,
            east_m: float = 0.0, north_m: float = 0.0) -> Pose:
    lat, lon = local_to_latlon(east_m, north_m, LAT0, LON0)
    return Pose(lat=float(lat), lon=float(lon), height_m=height_m, pitch_deg=pitch_deg, heading_deg=heading_deg)


def observe(east_m, north_m, pose: Pose, *, score: float = 0.9, noise_m: float = 0.0,
            rng: np.random.Generator | None = None, raw: float | None = None) -> FrameResult:
    """Detections of ground points (metres around LAT0/LON0) that the camera sees: a 20 x 50 px box
    standing on each point, its lat/lon the point's (plus noise), as DetectionPipeline reports them."""
    e = np.atleast_1d(np.asarray(east_m, dtype=np.float64))
    n = np.atleast_1d(np.asarray(north_m, dtype=np.float64))
    uav_e, uav_n = latlon_to_local(pose.lat, pose.lon, LAT0, LON0)
    uv, ok = local_to_pixel(e - uav_e, n - uav_n, CAM, pose)
    ok &= (uv[:, 0] > 20) & (uv[:, 0] < CAM.width - 20) & (uv[:, 1] > 60) & (uv[:, 1] < CAM.height)
    e, n, uv = e[ok], n[ok], uv[ok]
    if noise_m and rng is not None:
        e = e + rng.normal(0, noise_m, len(e))
        n = n + rng.normal(0, noise_m, len(n))
    lat, lon = local_to_latlon(e, n, LAT0, LON0)
    boxes = np.column_stack([uv[:, 0] - 10, uv[:, 1] - 50, uv[:, 0] + 10, uv[:, 1]]).astype(np.float32)
    k = len(e)
    scores = np.full(k, score, np.float32)
    raws = np.full(k, score if raw is None else raw, np.float32)
    return FrameResult(boxes, scores, raws, np.ones(k, np.int64), np.atleast_1d(lat), np.atleast_1d(lon), k, 0, k)


def empty_result() -> FrameResult:
    z = np.zeros(0)
    return FrameResult(np.zeros((0, 4), np.float32), z.astype(np.float32), z.astype(np.float32),
                       np.zeros(0, np.int64), z, z, 0, 0, 0)


def run(tracker: GpsTracker, frames, t0: float = 1.7e9):
    """frames: iterable of (FrameResult, Pose | None); returns the per-frame outputs."""
    outs = []
    for k, (result, pose) in enumerate(frames):
        outs.append(tracker.update(result, pose, t0 + k / FPS, CAM))
    return outs


def ids_near(outputs, east_m: float, north_m: float, radius_m: float = 3.0) -> set[int]:
    """Ids of matched, confirmed tracks within radius of a ground point."""
    found = set()
    for tr in outputs:
        e, n = latlon_to_local(tr.lat, tr.lon, LAT0, LON0)
        if tr.confirmed and tr.matched and math.hypot(float(e) - east_m, float(n) - north_m) <= radius_m:
            found.add(tr.id)
    return found


# --------------------------------------------------------------------------------------------- geometry

def test_measurement_error_sideways_grows_with_range_times_heading_error():
    cov = ground_measurement_cov(np.array([0.0, 0.0]), np.array([20.0, 100.0]), 30.0, 3000.0,
                                 position_sigma_m=1e-6, heading_sigma_deg=1.0, pitch_sigma_deg=0.0,
                                 height_sigma_m=0.0, pixel_sigma_px=0.0)
    # points due north: sideways is east
    assert math.sqrt(cov[0, 0, 0]) == pytest.approx(20.0 * math.radians(1.0), rel=1e-6)
    assert math.sqrt(cov[1, 0, 0]) == pytest.approx(100.0 * math.radians(1.0), rel=1e-6)
    assert cov[:, 1, 1] == pytest.approx([0.0, 0.0], abs=1e-9)


def test_measurement_error_along_ray_grows_with_range_squared_over_height():
    r, h = 80.0, 20.0
    cov = ground_measurement_cov(np.array([r]), np.array([0.0]), h, 3000.0, position_sigma_m=1e-6,
                                 heading_sigma_deg=0.0, pitch_sigma_deg=0.5, height_sigma_m=0.0, pixel_sigma_px=0.0)
    expected = (r * r + h * h) / h * math.radians(0.5)
    assert math.sqrt(cov[0, 0, 0]) == pytest.approx(expected, rel=1e-6)  # the ray points east
    # and it is what a real pitch error does to the projection
    e_lo = h / math.tan(math.atan2(h, r) + math.radians(0.5))
    assert r - e_lo == pytest.approx(expected, rel=0.05)


@settings(max_examples=60, deadline=None)
@given(e=st.floats(-500, 500), n=st.floats(-500, 500), h=st.floats(1, 200),
       sd=st.tuples(st.floats(0, 5), st.floats(0, 5), st.floats(0, 5), st.floats(0, 20)))
def test_measurement_covariance_is_symmetric_positive_definite(e, n, h, sd):
    cov = ground_measurement_cov(np.array([e]), np.array([n]), h, 3000.0, position_sigma_m=0.1,
                                 heading_sigma_deg=sd[0], pitch_sigma_deg=sd[1], height_sigma_m=sd[2],
                                 pixel_sigma_px=sd[3], max_sigma_m=50.0)[0]
    assert cov[0, 1] == cov[1, 0]
    eig = np.linalg.eigvalsh(cov)
    assert eig.min() > 0 and eig.max() <= 0.01 + 2 * 50.0**2 + 1e-6


# --------------------------------------------------------------------------------------------- assignment

@settings(max_examples=80, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.floats(0.1, 0.9), st.integers(0, 10_000))
def test_sparse_assignment_equals_dense_gated_assignment(n_rows, n_cols, density, seed):
    rng = np.random.default_rng(seed)
    allowed = rng.random((n_rows, n_cols)) < density
    cost = rng.random((n_rows, n_cols)) * 10
    rows, cols = np.nonzero(allowed)
    r, c = sparse_assignment(rows, cols, cost[rows, cols])
    dense = np.where(allowed, cost, 1e9)
    rd, cd = linear_sum_assignment(dense)
    ok = allowed[rd, cd]
    assert len(r) == int(ok.sum())  # as many pairs as possible
    assert cost[r, c].sum() == pytest.approx(cost[rd[ok], cd[ok]].sum())  # at the same cost
    assert len(set(r.tolist())) == len(r) and len(set(c.tolist())) == len(c)
    assert allowed[r, c].all()


@pytest.mark.parametrize("unassigned", [None, 3.0])
@pytest.mark.parametrize("seed", range(5))
def test_large_sparse_problems_are_solved_group_by_group_to_the_same_optimum(seed, unassigned):
    rng = np.random.default_rng(seed)
    n = 120  # beyond the dense shortcut: groups of nearby tracks are solved one by one
    pos_r, pos_c = rng.uniform(0, 300, (n, 2)), rng.uniform(0, 300, (n, 2))
    rows, cols = near_pairs(pos_r, np.full(n, 6.0), pos_c, np.full(n, 6.0))
    cost = rng.random(len(rows)) * 5
    r, c = sparse_assignment(rows, cols, cost, unassigned_cost=unassigned)
    if unassigned is None:
        dense = np.full((n, n), 1e9)
        dense[rows, cols] = cost
    else:  # the textbook augmentation: dummies at cost 0, pair costs shifted by the unassigned cost
        dense = np.zeros((2 * n, 2 * n))
        dense[:n, :n] = 1e9
        keep = cost < unassigned
        dense[rows[keep], cols[keep]] = cost[keep] - unassigned
    rd, cd = linear_sum_assignment(dense)
    ok = (rd < n) & (cd < n) & (dense[rd, np.minimum(cd, 2 * n - 1)] < 1e8)
    lookup = dict(zip(zip(rows.tolist(), cols.tolist(), strict=True), cost.tolist(), strict=True))
    assert len(r) == int(ok.sum())
    assert sum(lookup[p] for p in zip(r.tolist(), c.tolist(), strict=True)) == pytest.approx(
        sum(lookup[p] for p in zip(rd[ok].tolist(), cd[ok].tolist(), strict=True)))


def test_an_unassigned_option_stops_trading_one_good_pair_for_two_poor_ones():
    # track 0 is close to detection 0 only; track 1 (a duplicate) is closer to it and far from detection 1
    rows, cols, cost = np.array([0, 1, 1]), np.array([0, 0, 1]), np.array([2.0, 1.0, 16.0])
    r, c = sparse_assignment(rows, cols, cost)
    assert sorted(zip(r.tolist(), c.tolist(), strict=True)) == [(0, 0), (1, 1)]  # largest size first
    r, c = sparse_assignment(rows, cols, cost, unassigned_cost=10.0)
    assert list(zip(r.tolist(), c.tolist(), strict=True)) == [(1, 0)]
    r, c = sparse_assignment(rows, cols, cost, unassigned_cost=0.5)  # nothing is worth it
    assert len(r) == 0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 30), st.integers(0, 30), st.integers(0, 10_000))
def test_near_pairs_finds_exactly_the_pairs_within_the_summed_radii(n_a, n_b, seed):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, 50, (n_a, 2)), rng.uniform(0, 50, (n_b, 2))
    ra, rb = rng.uniform(0, 5, n_a), rng.uniform(0, 5, n_b)
    i, j = near_pairs(a, ra, b, rb)
    dist = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    expected = set(zip(*np.nonzero(dist <= ra[:, None] + rb[None, :]), strict=True))
    assert set(zip(i.tolist(), j.tolist(), strict=True)) == {(int(x), int(y)) for x, y in expected}


def test_duplicate_mask_keeps_the_strongest_box_of_a_cluster_and_separate_objects():
    boxes = np.array([[100, 100, 140, 200], [104, 96, 142, 190], [100, 150, 140, 200],  # one object, 3 boxes
                      [300, 100, 340, 200]], np.float32)  # another object
    scores = np.array([0.9, 0.5, 0.3, 0.8])
    dup = duplicate_mask(boxes, scores, np.ones(4), 0.25, 0.5)
    assert dup.tolist() == [False, True, True, False]
    # another class at the same place is not a duplicate
    assert not duplicate_mask(boxes[:2], scores[:2], np.array([1, 2]), 0.25, 0.5).any()


# --------------------------------------------------------------------------------------------- gating

def _track_then(offset_e: float, *, north_m: float, height_m: float = 30.0, pitch_deg: float = 40.0):
    """A person tracked for 1 s at (0, north_m), then seen offset_e metres east of there."""
    pose = pose_at(height_m=height_m, pitch_deg=pitch_deg)
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    frames = [(observe(0.0, north_m, pose), pose) for _ in range(30)]
    frames.append((observe(offset_e, north_m, pose), pose))
    outs = run(tracker, frames)
    return outs[-2], outs[-1]


def test_gate_accepts_a_detection_next_to_the_track():
    before, after = _track_then(0.6, north_m=25.0)
    assert len(before) == 1 and before[0].confirmed
    assert [(tr.id, tr.matched) for tr in after] == [(before[0].id, True)]


def test_gate_rejects_a_far_detection():
    before, after = _track_then(12.0, north_m=25.0)
    old = [tr for tr in after if tr.id == before[0].id]
    assert old and not old[0].matched  # the track coasts; the far detection is someone else
    assert any(tr.id != before[0].id and tr.matched for tr in after)


def test_gate_grows_with_range():
    # 3 m sideways is far at 25 m range (heading error 1 deg ~ 0.4 m) but within the error at 150 m
    near_before, near_after = _track_then(3.0, north_m=25.0)
    far_before, far_after = _track_then(3.0, north_m=150.0, height_m=60.0, pitch_deg=20.0)
    assert not [tr for tr in near_after if tr.id == near_before[0].id][0].matched
    assert [tr for tr in far_after if tr.id == far_before[0].id][0].matched


def test_two_close_people_keep_their_ids_when_one_is_missed():
    pose = pose_at()
    rng = np.random.default_rng(3)
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    frames = []
    for k in range(90):
        people = [(0.0, 25.0), (2.0, 25.0)] if k % 5 else [(2.0, 25.0)]  # the first is missed every 5th frame
        e, n = zip(*people, strict=True)
        frames.append((observe(e, n, pose, noise_m=0.3, rng=rng), pose))
    outs = run(tracker, frames)
    assert ids_near(outs[-1], 0.0, 25.0, 0.9) | ids_near(outs[-1], 2.0, 25.0, 0.9) == {1, 2}
    assert all(tr.id in (1, 2) for out in outs for tr in out if tr.confirmed)


def _at_border(result: FrameResult) -> FrameResult:
    """The same detections with their boxes moved against the left image border."""
    boxes = result.boxes_xyxy.copy()
    boxes[:, 2] -= boxes[:, 0]
    boxes[:, 0] = 0.0
    return dataclasses.replace(result, boxes_xyxy=boxes)


def test_at_image_border_flags_boxes_within_the_margin():
    boxes = np.array([[0, 500, 30, 560], [3, 500, 30, 560], [10, 500, 40, 560], [3800, 10, 3838, 60],
                      [100, 2100, 140, 2158], [np.nan] * 4])
    assert at_image_border(boxes, 3840, 2160, 4.0).tolist() == [True, True, False, True, True, False]


@pytest.mark.parametrize("exit_margin_px", [4.0, -1.0])
def test_a_track_that_left_through_the_image_border_is_lost_at_once(exit_margin_px):
    # A person seen at the left border, then not any more: with the exit rule it goes to the re-ID
    # memory in the next frame, without it it coasts for max_coast_s.
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(exit_margin_px=exit_margin_px), CLASSES)
    run(tracker, [(_at_border(observe(-5.0, 25.0, pose)), pose) for _ in range(10)])
    assert [tr.id for tr in tracker.tracks if tr.confirmed] == [1]
    tracker.update(empty_result(), pose, 1.7e9 + 10 / FPS, CAM)
    lost = [tr.id for tr in tracker.lost_tracks]
    assert lost == ([1] if exit_margin_px >= 0 else [])


def test_a_track_away_from_the_border_still_coasts_through_a_missed_frame():
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    outs = run(tracker, [(observe(0.0, 25.0, pose), pose) for _ in range(10)]
               + [(empty_result(), pose)] + [(observe(0.0, 25.0, pose), pose) for _ in range(3)])
    assert not tracker.lost_tracks
    assert ids_near(outs[-1], 0.0, 25.0) == {1}


@pytest.mark.parametrize("exit_margin_px", [4.0, -1.0])
def test_a_track_leaving_the_view_does_not_take_its_neighbours_detection(exit_margin_px):
    # Two people 3 m apart; the western one leaves through the left border while the telemetry
    # places the eastern one's next detections 2 m west (a turn the telemetry has not caught up
    # with). Without the exit rule (margin < 0) the coasting track of the one who left takes them.
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(exit_margin_px=exit_margin_px), CLASSES)
    frames = []
    for _ in range(15):
        west = _at_border(observe(-3.0, 25.0, pose))
        east = observe(0.0, 25.0, pose)
        frames.append((concat_results(west, east), pose))
    frames.append((observe(0.0, 25.0, pose), pose))  # the western person has left
    for _ in range(3):
        frames.append((observe(-2.0, 25.0, pose), pose))  # the eastern person, its ground point 2 m off
    outs = run(tracker, frames)
    before = {tr.id: tr for tr in outs[14] if tr.confirmed}
    east_id = min(before, key=lambda i: abs(float(latlon_to_local(before[i].lat, before[i].lon, LAT0, LON0)[0])))
    taken_by = [tr.id for tr in outs[-1] if tr.matched]
    assert taken_by == [east_id] if exit_margin_px >= 0 else taken_by != [east_id]


def concat_results(a: FrameResult, b: FrameResult) -> FrameResult:
    """Two frames' detections as one."""
    k = len(a.scores) + len(b.scores)
    return FrameResult(np.vstack([a.boxes_xyxy, b.boxes_xyxy]), np.concatenate([a.scores, b.scores]),
                       np.concatenate([a.raw_scores, b.raw_scores]), np.concatenate([a.class_ids, b.class_ids]),
                       np.concatenate([a.lat, b.lat]), np.concatenate([a.lon, b.lon]), k, 0, k)


# --------------------------------------------------------------------------------------------- re-ID

def _leave_and_return(gap_s: float, *, horizon_s: float = 30.0):
    """A person seen for 2 s, then not at all for gap_s (the UAV looks away), then again a bit
    further on (walking east at 0.5 m/s all along)."""
    tracker = GpsTracker(TrackerConfig(reid_horizon_s=horizon_s), CLASSES)
    pose = pose_at()
    frames = []
    for k in range(60):
        frames.append((observe(k / FPS * 0.5, 25.0, pose), pose))
    away = pose_at(heading_deg=180.0)
    frames += [(empty_result(), away) for _ in range(int(gap_s * FPS))]
    t_back = (60 + int(gap_s * FPS)) / FPS
    for k in range(30):
        frames.append((observe((t_back + k / FPS) * 0.5, 25.0, pose), pose))
    outs = run(tracker, frames)
    return tracker, outs[59], outs[-1]


def test_reid_within_the_horizon_gives_the_old_id_back():
    tracker, before, after = _leave_and_return(10.0)
    assert len(before) == 1
    assert [tr.id for tr in after if tr.matched and tr.confirmed] == [before[0].id]
    assert tracker.n_reidentified == 1


def test_reid_beyond_the_horizon_gives_a_new_id():
    tracker, before, after = _leave_and_return(12.0, horizon_s=8.0)
    ids = [tr.id for tr in after if tr.matched and tr.confirmed]
    assert ids and before[0].id not in ids
    assert tracker.n_reidentified == 0


def test_lost_tracks_are_listed_until_the_horizon():
    tracker = GpsTracker(TrackerConfig(reid_horizon_s=5.0), CLASSES)
    pose = pose_at()
    run(tracker, [(observe(0.0, 25.0, pose), pose)] * 30)
    tracker.update(empty_result(), pose, 1.7e9 + 3.0, CAM)
    assert [tr.id for tr in tracker.lost_tracks] == [1] and tracker.tracks == []
    assert tracker.lost_tracks[0].time_since_update_s == pytest.approx(3.0 - 29 / FPS)
    tracker.update(empty_result(), pose, 1.7e9 + 6.0, CAM)
    assert tracker.lost_tracks == []


def test_a_180_degree_turn_keeps_ids():
    """People in front and behind a hovering UAV; it turns to look behind and back again: everyone
    keeps the id they had, both after the first turn (behind: new ids, kept on the second look) and
    after the second (in front: the old ids, re-identified)."""
    front = [(-4.0, 25.0), (3.0, 30.0), (8.0, 22.0)]
    behind = [(-3.0, -26.0), (5.0, -30.0)]
    people = front + behind
    e0 = np.array([p[0] for p in people])
    n0 = np.array([p[1] for p in people])
    vel = np.array([[0.3, 0.0], [0.0, -0.2], [-0.2, 0.1], [0.2, 0.2], [-0.3, 0.0]])
    headings = ([0.0] * 60 + list(np.linspace(0, 180, 45)) + [180.0] * 90 + list(np.linspace(180, 360, 45))
                + [0.0] * 60 + list(np.linspace(0, 180, 45)) + [180.0] * 60)
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    rng = np.random.default_rng(0)
    seen: dict[int, set[int]] = {i: set() for i in range(len(people))}
    for k, heading in enumerate(headings):
        t = k / FPS
        e, n = e0 + vel[:, 0] * t, n0 + vel[:, 1] * t
        pose = pose_at(heading % 360.0)
        out = tracker.update(observe(e, n, pose, noise_m=0.2, rng=rng), pose, 1.7e9 + t, CAM)
        for i in range(len(people)):
            seen[i] |= ids_near(out, float(e[i]), float(n[i]), 1.5)
    assert all(len(ids) == 1 for ids in seen.values()), seen
    assert len(set().union(*seen.values())) == len(people)
    assert tracker.n_reidentified >= len(people)


def test_reid_after_the_object_walked_a_curved_path_out_of_view():
    """Walking east, the person turns north while the UAV looks away for 6 s and comes back 6-7 m
    from where a straight line would have put them: still inside the growing re-ID gate."""
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)

    def position(t: float) -> tuple[float, float]:
        if t <= 3.0:  # east at 1.3 m/s until 1 s after the UAV looked away, then north
            return -3.0 + 1.3 * t, 25.0
        return -3.0 + 1.3 * 3.0, 25.0 + 1.3 * (t - 3.0)

    frames = []
    for k in range(int(9.5 * FPS)):
        t = k / FPS
        looking = pose if t < 2.0 or t >= 8.0 else away
        frames.append((observe(*position(t), looking), looking))
    outs = run(tracker, frames)
    first = ids_near(outs[int(1.9 * FPS)], *position(1.9))
    last = ids_near(outs[-1], *position((len(frames) - 1) / FPS))
    assert first == last == {1}
    assert tracker.n_reidentified == 1


def test_a_false_positive_does_not_take_or_move_a_lost_id():
    """While the person is out of view a single-frame false positive appears 6 m away, inside the
    re-ID gate: it revives the lost track only on probation, is never reported, and the memory
    entry comes back unchanged, so the person returning at the old spot gets the old id."""
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    outs = run(tracker, [(observe(0.0, 25.0, pose), pose)] * 60
               + [(empty_result(), away)] * 90
               + [(observe(6.0, 25.0, pose), pose)]
               + [(empty_result(), pose)] * 30
               + [(observe(0.0, 25.0, pose), pose)] * 20)
    assert ids_near(outs[59], 0.0, 25.0) == {1}
    assert all(not tr.confirmed for out in outs[150:181] for tr in out)  # the false positive: never reported
    assert ids_near(outs[-1], 0.0, 25.0) == {1}
    assert tracker.n_reidentified == 1


RED, BLUE = np.array([[1.0, 0.0]], np.float32), np.array([[0.0, 1.0]], np.float32)


def _looking(look: np.ndarray, pose: Pose, east_m: float = 0.0) -> FrameResult:
    return dataclasses.replace(observe(east_m, 25.0, pose), embeddings=look)


def _return_after_a_partial_box(config: TrackerConfig) -> tuple[GpsTracker, list]:
    """A person (red) is followed for 2 s, out of view for 3 s, then back at the same spot: the
    first box back is partial, its descriptor unlike the memory (blue: no revival, a new track is
    born), the next ones red again."""
    tracker = GpsTracker(config, CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    # the view is back 5 frames before the person (past the view-jump guard, TrackerConfig.jump_settle_s)
    outs = run(tracker, [(_looking(RED, pose), pose)] * 60 + [(empty_result(), away)] * 85
               + [(empty_result(), pose)] * 5 + [(_looking(BLUE, pose), pose)] + [(_looking(RED, pose), pose)] * 20)
    return tracker, outs


def test_a_young_unreported_track_takes_the_lost_id_its_detections_match():
    tracker, outs = _return_after_a_partial_box(TrackerConfig())
    assert ids_near(outs[59], 0.0, 25.0) == {1}
    assert ids_near(outs[-1], 0.0, 25.0) == {1}
    # The young track's own id (2) was never reported: no frame shows it.
    assert all(tr.id != 2 for out in outs for tr in tracker.report(out))
    assert tracker.n_reidentified == 1 and tracker.lost_tracks == []
    # Without it the new track keeps its new id.
    tracker, outs = _return_after_a_partial_box(TrackerConfig(reid_unreported_s=0.0))
    assert ids_near(outs[-1], 0.0, 25.0) == {2}


def test_a_reported_track_keeps_its_id_even_when_it_comes_to_look_like_a_lost_one():
    """A new person (blue) appears where a red one was lost and is reported under a new id; when
    its boxes later look red, the id it has shown stays."""
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    outs = run(tracker, [(_looking(RED, pose), pose)] * 60 + [(empty_result(), away)] * 90
               + [(_looking(BLUE, pose), pose)] * 15 + [(_looking(RED, pose), pose)] * 15)
    assert ids_near(outs[164], 0.0, 25.0) == {2} and any(tr.id == 2 for tr in tracker.report(outs[164]))
    assert ids_near(outs[-1], 0.0, 25.0) == {2}
    assert tracker.n_reidentified == 0 and [tr.id for tr in tracker.lost_tracks] == [1]


def _fading_false_positive_then_return(back_look: np.ndarray, config: TrackerConfig) -> tuple[GpsTracker, list]:
    """A person (red) is followed for 2 s and out of view for 3 s; back in view, a false positive
    (blue) 1 m beside the person's spot is reported for 0.5 s under a new id, then fades (detector
    confidence 0.1, no descriptor: the track's quality falls below report_quality, its id is no
    longer reported), then the person returns, looking back_look, and that young track takes the
    detections."""
    tracker = GpsTracker(config, CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    faint = dataclasses.replace(observe(1.0, 25.0, pose, raw=0.1), embeddings=np.full((1, 2), np.nan, np.float32))
    outs = run(tracker, [(_looking(RED, pose), pose)] * 60 + [(empty_result(), away)] * 90
               + [(_looking(BLUE, pose, east_m=1.0), pose)] * 15 + [(faint, pose)] * 15
               + [(_looking(back_look, pose), pose)] * 20)
    return tracker, outs


def test_a_young_track_no_longer_reported_gives_its_id_up_for_a_lost_one_it_looks_less_like():
    tracker, outs = _fading_false_positive_then_return(RED, TrackerConfig())
    assert any(tr.id == 2 for tr in tracker.report(outs[164]))  # the false positive was reported
    assert not tracker.report(outs[179])  # then no longer
    assert ids_near(outs[-1], 0.0, 25.0) == {1} and tracker.n_reidentified == 1
    tracker, outs = _fading_false_positive_then_return(RED, TrackerConfig(reid_unreported_s=0.0))
    assert ids_near(outs[-1], 0.0, 25.0) == {2}


def test_a_young_track_no_longer_reported_keeps_its_id_when_its_detection_looks_like_itself():
    """The same, but the returning boxes look more like the track (blue) than like the lost person
    (cosine distance 0.2 against 0.4, both within the re-ID appearance gate of 0.5): no evidence
    that the track changed objects."""
    tracker, outs = _fading_false_positive_then_return(np.array([[0.6, 0.8]], np.float32), TrackerConfig())
    assert ids_near(outs[-1], 0.0, 25.0) == {2} and tracker.n_reidentified == 0


def test_two_neighbours_coasting_out_of_view_are_not_merged():
    """Two people 2.5 m apart: when the UAV looks away both tracks coast side by side (their
    covariances growing) until they are lost; that is no evidence of one track shadowing the other,
    so both reach the re-ID memory and both come back with their ids (a 3 s coast lets the
    covariances grow far beyond the 2.5 m between them)."""
    tracker = GpsTracker(TrackerConfig(max_coast_s=3.0), CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    e, n = [0.0, 2.5], [25.0, 25.0]
    outs = run(tracker, [(observe(e, n, pose), pose)] * 60 + [(empty_result(), away)] * 120)
    assert sorted(tr.id for tr in tracker.lost_tracks) == [1, 2]
    t0 = 1.7e9 + len(outs) / FPS
    for k in range(15):
        out = tracker.update(observe(e, n, pose), pose, t0 + k / FPS, CAM)
    east = {tr.id: float(latlon_to_local(tr.lat, tr.lon, LAT0, LON0)[0]) for tr in out if tr.confirmed and tr.matched}
    assert set(east) == {1, 2} and east[1] < east[2]  # (the instant 180-degree turn shifts both a little)


# --------------------------------------------------------------------------------------------- no pose

def test_a_frame_without_pose_does_not_break_tracks():
    pose = pose_at()
    people_e, people_n = [-3.0, 4.0], [25.0, 28.0]
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    run(tracker, [(observe(people_e, people_n, pose), pose)] * 20)
    ids = {tr.id for tr in tracker.tracks}
    lat_before = {tr.id: tr.lat for tr in tracker.tracks}
    # Without meta the pipeline cannot georeference: lat/lon are NaN, the boxes are still there.
    seen = observe(people_e, people_n, pose)
    blind = FrameResult(seen.boxes_xyxy, seen.scores, seen.raw_scores, seen.class_ids,
                        np.full(2, np.nan), np.full(2, np.nan), 2, 0, 0)
    out = tracker.update(blind, None, 1.7e9 + 20 / FPS, CAM)
    assert {tr.id for tr in out} == ids
    assert all(tr.matched and tr.confirmed for tr in out)
    assert all(tr.lat == pytest.approx(lat_before[tr.id], abs=1e-6) for tr in out)  # coasted, not moved
    out = tracker.update(observe(people_e, people_n, pose), pose, 1.7e9 + 21 / FPS, CAM)
    assert {tr.id for tr in out if tr.matched} == ids


def test_frames_without_pose_from_the_start_start_no_tracks():
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    seen = observe([0.0], [25.0], pose_at())
    for k in range(5):
        assert tracker.update(seen, None, 1.7e9 + k / FPS, CAM) == []
    assert tracker.origin is None


# --------------------------------------------------------------------------------------------- memory-map leftovers

def test_boosted_leftovers_around_an_object_do_not_start_tracks():
    """The memory map lifts every box near a remembered object: weak boxes around the person
    (raw 0.05, boosted 1.05) must neither start tracks nor take the person's id."""
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    rng = np.random.default_rng(1)
    for k in range(60):
        main = observe(0.0, 25.0, pose, score=1.9, raw=0.9)
        ring = rng.uniform(0, 2 * np.pi, 3)
        left = observe(2.5 * np.cos(ring), 25.0 + 2.5 * np.sin(ring), pose, score=1.05, raw=0.05)
        merged = FrameResult(*(np.concatenate([getattr(main, f), getattr(left, f)]) for f in
                               ("boxes_xyxy", "scores", "raw_scores", "class_ids", "lat", "lon")), 4, 0, 4)
        out = tracker.update(merged, pose, 1.7e9 + k / FPS, CAM)
    assert [tr.id for tr in out if tr.confirmed] == [1]


def test_persistent_weak_clutter_is_followed_but_not_reported():
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    out = []
    for k in range(90):
        # a rock the detector reports in half of the frames with confidence 0.5
        result = observe(0.0, 25.0, pose, score=0.5) if k % 2 else empty_result()
        out = tracker.update(result, pose, 1.7e9 + k / FPS, CAM)
    assert any(tr.confirmed for tr in out)
    assert tracker.report(out) == []


# --------------------------------------------------------------------------------------------- robustness

def test_reanchoring_keeps_ground_positions():
    tracker = GpsTracker(TrackerConfig(reanchor_m=50.0), CLASSES)
    person = (0.0, 25.0)
    for k in range(40):
        pose = pose_at(north_m=-5.0 * k / 10)  # the UAV backs away 20 m ... then jumps 100 m
        tracker.update(observe(*person, pose), pose, 1.7e9 + k / FPS, CAM)
    origin = tracker.origin
    far = pose_at(north_m=-80.0, pitch_deg=20.0, height_m=40.0)
    out = tracker.update(observe(*person, far), far, 1.7e9 + 40 / FPS, CAM)
    assert tracker.origin != origin
    e, n = latlon_to_local(out[0].lat, out[0].lon, LAT0, LON0)
    assert (float(e), float(n)) == pytest.approx(person, abs=0.5)


def test_time_going_backwards_is_treated_as_the_same_time():
    pose = pose_at()
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    run(tracker, [(observe(0.0, 25.0, pose), pose)] * 10)
    out = tracker.update(observe(0.0, 25.0, pose), pose, 1.7e9 - 5.0, CAM)
    assert [tr.id for tr in out] == [1]
    with pytest.raises(ValueError, match="finite"):
        tracker.update(empty_result(), pose, math.nan, CAM)


@pytest.mark.parametrize(("field", "value", "message"), [
    ("gate_chi2", 0.0, "gate_chi2"), ("max_coast_s", -1.0, "max_coast_s"), ("confirm_hits", 0, "confirm_hits"),
    ("duplicate_iou", 1.5, "duplicate_iou"), ("low_score", 0.9, "low_score"), ("reid_horizon_s", math.inf, "finite"),
])
def test_bad_config_values_raise_naming_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        TrackerConfig(**{field: value})


def test_bad_class_motion_raises():
    with pytest.raises(ValueError, match="max_speed_mps"):
        ClassMotion(max_speed_mps=0.0)
    with pytest.raises(ValueError, match="class_motion"):
        TrackerConfig(class_motion=(("person", 3.0),))  # type: ignore[arg-type]
    assert TrackerConfig().motion_for("swimmer").max_speed_mps < TrackerConfig().motion_for("boat").max_speed_mps


def test_box_iou_of_identical_and_disjoint_boxes():
    a = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], np.float64)
    assert box_iou(a, a) == pytest.approx(np.eye(2))


@pytest.mark.parametrize("retimed", [False, True])
def test_a_retimed_pose_is_not_turned_again_by_the_telemetry_latency(retimed):
    # The gimbal turns at 60 deg/s over a still object. A stamped pose is turned by rate * latency (the
    # telemetry lags); one the clock-offset estimate already interpolated at the frame's time is not.
    cfg = TrackerConfig(telemetry_latency_s=0.1, image_register=False)
    tracker = GpsTracker(cfg, CLASSES)
    t0 = 1.7e9
    out = []
    for k in range(2):
        pose = pose_at(2.0 * k)
        out = tracker.update(observe(0.0, 30.0, pose), pose, t0 + k / FPS, CAM, pose_t=t0 + k / FPS,
                             pose_retimed=retimed)
    (track,) = [o for o in out if o.matched]
    e, n = latlon_to_local(track.lat, track.lon, LAT0, LON0)
    shift = math.hypot(float(e), float(n) - 30.0)
    if retimed:
        assert shift < 0.05  # the detection's own point
    else:
        assert shift > 0.2  # the point turned by 60 deg/s * 0.1 s = 6 deg about the UAV (3 m at 30 m) pulls the track


def _blurred_sweep(config: TrackerConfig) -> tuple[GpsTracker, list]:
    """Two people seen sharp (raw 0.9) for 1 s, then blurred (raw 0.2, as in a fast sweep) for 1 s."""
    tracker = GpsTracker(config, CLASSES)
    pose = pose_at()
    sharp, blurred = observe([0.0, 4.0], [25.0, 25.0], pose, raw=0.9), observe([0.0, 4.0], [25.0, 25.0], pose, raw=0.2)
    return tracker, run(tracker, [(sharp, pose)] * 30 + [(blurred, pose)] * 30)


def test_report_level_keeps_objects_reported_while_every_score_drops() -> None:
    """A blur that lowers every score: with a fixed report_quality both matched tracks fall out of the report;
    scaled by the detector's running score level (report_level_ref) they stay, with their ids."""
    fixed, outs = _blurred_sweep(TrackerConfig())
    assert len(fixed.report(outs[29])) == 2 and not fixed.report(outs[-1])
    scaled, outs = _blurred_sweep(TrackerConfig(report_level_ref=0.9))
    assert {tr.id for tr in scaled.report(outs[-1])} == {tr.id for tr in scaled.report(outs[29])} == {1, 2}
    assert scaled.report_threshold < 0.15 and fixed.report_threshold == 0.4


def test_report_level_still_hides_clutter_weaker_than_the_objects() -> None:
    """Objects stay sharp (raw 0.9) while a false positive born strong fades to raw 0.1: the level stays high,
    the clutter's quality falls below the threshold and it is no longer reported."""
    tracker = GpsTracker(TrackerConfig(report_level_ref=0.9), CLASSES)
    pose = pose_at()
    objects = observe([0.0, 4.0], [25.0, 25.0], pose, raw=0.9)
    frames = [(concat_results(objects, observe(-4.0, 25.0, pose, raw=r)), pose) for r in [0.9] * 30 + [0.1] * 40]
    outs = run(tracker, frames)
    assert ids_near(tracker.report(outs[29]), -4.0, 25.0)
    assert not ids_near(tracker.report(outs[-1]), -4.0, 25.0) and len(tracker.report(outs[-1])) == 2
    assert tracker.report_threshold > 0.25  # (0.9 + 0.9 + 0.1) / 3 of 0.9: scaled by 0.7


@pytest.mark.parametrize("bad", [{"report_level_top_k": 0}, {"report_level_top_k": 2.5}, {"report_level_ref": -0.1},
                                 {"report_level_ref": float("nan")}])
def test_report_level_settings_are_checked(bad) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        TrackerConfig(**bad)


def _sweep_out_of_view(exit_expected: bool) -> tuple[GpsTracker, list]:
    """The gimbal turns 1 deg a frame (boxes stream left ~45 px a frame); the western person, last seen
    124 px inside the left border, is not detected from frame 20 on (it left the view)."""
    tracker = GpsTracker(TrackerConfig(exit_expected=exit_expected), CLASSES)
    frames = []
    for k in range(26):
        pose = pose_at(heading_deg=float(k))
        frames.append((observe([-13.0, 6.0] if k < 20 else [6.0], [25.0, 25.0] if k < 20 else [25.0], pose), pose))
    return tracker, run(tracker, frames)


def test_a_track_whose_expected_box_streamed_out_of_view_is_lost_at_once() -> None:
    tracker, outs = _sweep_out_of_view(True)
    assert min(tr.box_xyxy[0] for tr in outs[19] if tr.matched) > 100.0  # not at the border when last seen
    assert {tr.id for tr in outs[19] if tr.matched} == {1, 2}
    assert 1 not in {tr.id for tr in outs[22]} and [tr.id for tr in tracker.lost_tracks] == [1]
    assert {tr.id for tr in outs[-1] if tr.matched} == {2}
    # with the last box only, the track coasts on (for max_coast_s), free to take the next box at the border
    tracker, outs = _sweep_out_of_view(False)
    assert 1 in {tr.id for tr in outs[-1] if not tr.matched} and not tracker.lost_tracks


def test_report_level_ignores_a_nan_score() -> None:
    """A detector output with a NaN score among the frame's detections does not poison the running level: a
    blur after it still lowers the threshold (a NaN level would stay NaN and switch the scaling off for the
    rest of the flight)."""
    tracker = GpsTracker(TrackerConfig(report_level_ref=0.9), CLASSES)
    pose = pose_at()
    good = observe([0.0, 4.0], [25.0, 25.0], pose, raw=0.9)
    bad = dataclasses.replace(good, raw_scores=np.array([np.nan, 0.9], np.float32))
    blurred = observe([0.0, 4.0], [25.0, 25.0], pose, raw=0.2)
    outs = run(tracker, [(good, pose)] * 20 + [(bad, pose)] + [(blurred, pose)] * 30)
    assert tracker.report_threshold < 0.15 and len(tracker.report(outs[-1])) == 2


def test_over_a_terrain_the_in_view_test_projects_the_tracks_terrain_point():
    # a rock on an 18 m plateau 15 m ahead, reported in half of the frames at 0.5: on the terrain it is in view
    # (38.7 deg down, the frame spans 20-60 deg at 40 deg pitch), so the frames that miss it lower its quality and
    # it is not reported; flat earth would put it 63 deg down, out of view, and keep reporting it
    from shared.terrain import ElevationGrid, Terrain

    axis = np.arange(-60.0, 61.0, 1.0)
    east, north = np.meshgrid(axis, axis[::-1])
    heights = np.where((np.abs(east) <= 10.0) & (np.abs(north - 15.0) <= 8.0), 118.0, 100.0)
    terrain = Terrain(ElevationGrid.from_local(heights, LAT0, LON0, west_m=-60.0, north_m=60.0, cell_m=1.0), 100.0)
    pose = pose_at()
    uv, ok = local_to_pixel(np.array([0.0]), np.array([15.0]), CAM, pose, terrain=terrain)
    assert ok[0] and 0 < uv[0, 1] < CAM.height
    assert not local_to_pixel(np.array([0.0]), np.array([15.0]), CAM, pose)[1][0] or \
        local_to_pixel(np.array([0.0]), np.array([15.0]), CAM, pose)[0][0, 1] > CAM.height
    lat, lon = local_to_latlon(0.0, 15.0, LAT0, LON0)
    seen = FrameResult(np.array([[uv[0, 0] - 10, uv[0, 1] - 50, uv[0, 0] + 10, uv[0, 1]]], np.float32),
                       np.array([0.5], np.float32), np.array([0.5], np.float32), np.ones(1, np.int64),
                       np.atleast_1d(lat), np.atleast_1d(lon), 1, 0, 1)
    reported = {}
    for label, ground in (("terrain", terrain), ("flat", None)):
        tracker = GpsTracker(TrackerConfig(), CLASSES)
        out = []
        for k in range(90):
            out = tracker.update(seen if k % 2 else empty_result(), pose, 1.7e9 + k / FPS, CAM, terrain=ground)
        assert any(tr.confirmed for tr in out)
        reported[label] = len(tracker.report(out))
    assert reported == {"terrain": 0, "flat": 1}


def test_a_person_at_a_banks_lip_keeps_one_id_when_the_alternative_ground_point_is_given():
    # the box's ray meets the upper level at the lip in some frames and passes over it to the lower level 9 m
    # farther in others (FrameResult.alt_latlon: the other side); four people stand still elsewhere (their points
    # steady: no telemetry error explains the jump). Without the alternative two tracks take turns
    pose = pose_at()
    rng = np.random.default_rng(3)
    near, far = local_to_latlon(0.0, 40.0, LAT0, LON0), local_to_latlon(0.0, 49.0, LAT0, LON0)
    base = observe([0.0, -15.0, 12.0, 20.0, -8.0], [40.0, 30.0, 35.0, 25.0, 22.0], pose)
    assert len(base) == 5
    frames = []
    for k in range(90):
        here, other = (far, near) if rng.uniform() < 0.4 and k > 2 else (near, far)
        alt = np.full((5, 2), np.nan)
        alt[0] = other
        frames.append(dataclasses.replace(base, lat=np.r_[here[0], base.lat[1:]], lon=np.r_[here[1], base.lon[1:]],
                                          alt_latlon=alt))
    ids = {}
    for label, use_alt in (("alternative", True), ("without", False)):
        tracker = GpsTracker(TrackerConfig(), CLASSES)
        outs = run(tracker, [(f if use_alt else dataclasses.replace(f, alt_latlon=None), pose) for f in frames])
        ids[label] = set().union(*(ids_near(o, 0.0, 40.0, 4.0) | ids_near(o, 0.0, 49.0, 4.0) for o in outs))
        if use_alt:  # the one track stays with the side it started on
            assert ids_near(outs[-1], 0.0, 40.0, 1.0) == ids[label]
    assert len(ids["alternative"]) == 1 and len(ids["without"]) >= 2


@pytest.mark.parametrize("missed_first", [False, True], ids=["seen", "missed in the newcomer's first frame"])
@pytest.mark.parametrize("other_north_m", [52.0, 55.0, 58.0, 60.0])
def test_another_persons_track_beyond_the_lip_does_not_pull_a_newcomer_across(other_north_m, missed_first):
    # one person followed alone beyond the bank; then a second appears at its lip, its point at 40 m in every frame
    # and its alternative 9 m farther, 1-11 m from the first person's track (whose own detection is there, or missed
    # in the newcomer's first frame): the newcomer's track is born and stays at the lip
    pose = pose_at()
    far, near = local_to_latlon(0.0, 49.0, LAT0, LON0), local_to_latlon(0.0, 40.0, LAT0, LON0)
    both = observe([0.0, 0.0], [40.0, other_north_m], pose)
    assert len(both) == 2
    alt = np.full((2, 2), np.nan)
    at = int(np.argmin(np.abs(both.lat - near[0])))
    alt[at] = far
    with_alt = dataclasses.replace(both, alt_latlon=alt)
    first = with_alt
    if missed_first:
        one = observe([0.0], [40.0], pose)
        first = dataclasses.replace(one, alt_latlon=np.array([[far[0], far[1]]]))
    frames = [(observe([0.0], [other_north_m], pose), pose)] * 30 + [(first, pose)] + [(with_alt, pose)] * 60
    outs = run(GpsTracker(TrackerConfig(), CLASSES), frames)
    at_lip, other = ids_near(outs[-1], 0.0, 40.0, 1.0), ids_near(outs[-1], 0.0, other_north_m, 1.0)
    assert len(at_lip) == 1 and len(other) == 1 and at_lip != other
    assert not ids_near(outs[-1], 0.0, 49.0, 2.0)


def _walker_passes_a_standing_person(config: TrackerConfig) -> tuple[set[int], set[int], set[int], set[int]]:
    """A walker at 1.2 m/s passes 0.3 m from a person standing still; while they are within 1.5 m of each other
    the image shows one box a frame, the walker's (convincing) or the half-hidden person's (raw 0.15, boosted to
    0.5), in turn. Returns the ids at the standing person and at the walker before and after the crossing."""
    pose = pose_at()
    tracker = GpsTracker(config, CLASSES)
    frames = []
    for k in range(int(12 * FPS)):
        walker_e = -7.0 + 1.2 * k / FPS
        if k < 15:  # the walker is seen from the 16th frame: its track has fewer hits than the person's
            frames.append((observe([0.0], [25.3], pose), pose))
        elif abs(walker_e) >= 1.5:
            frames.append((observe([0.0, walker_e], [25.3, 25.0], pose), pose))
        elif k % 2:
            frames.append((observe([0.0], [25.3], pose, score=0.5, raw=0.15), pose))
        else:
            frames.append((observe([walker_e], [25.0], pose), pose))
    outs = run(tracker, frames)
    before = int(4 * FPS)  # walker at -2.2 m
    return (ids_near(outs[before], 0.0, 25.3, 0.8), ids_near(outs[before], -7.0 + 1.2 * before / FPS, 25.0, 0.8),
            ids_near(outs[-1], 0.0, 25.3, 0.8), ids_near(outs[-1], -7.0 + 1.2 * (len(outs) - 1) / FPS, 25.0, 1.0))


def test_a_walker_passing_a_standing_person_keeps_both_ids():
    # the two tracks take turns on the one box the image shows while they overlap; their velocities (0 and 1.2 m/s,
    # each known to ~0.2 m/s) tell two objects apart, so neither is merged into the other
    stand0, walk0, stand1, walk1 = _walker_passes_a_standing_person(TrackerConfig())
    assert len(stand0) == len(walk0) == 1 and stand0 != walk0
    assert stand1 == stand0 and walk1 == walk0
    # by position alone (the velocity check off) one of them is dropped as the other's duplicate
    stand0, walk0, stand1, walk1 = _walker_passes_a_standing_person(TrackerConfig(merge_velocity_chi2=0.0))
    assert stand1 != stand0 or walk1 != walk0


def _confirmed_at_the_end_with_and_without_merging(frames) -> dict[str, set[int]]:
    """The confirmed ids after the frames, with the default tracker and with merging off (merge_max_m tiny); both
    runs must have two confirmed tracks after the 40th frame (a duplicate was born)."""
    kept = {}
    for label, config in (("default", TrackerConfig()), ("no merging", TrackerConfig(merge_max_m=0.01))):
        outs = run(GpsTracker(config, CLASSES), frames)
        assert {tr.id for tr in outs[40] if tr.confirmed} == {1, 2}
        kept[label] = {tr.id for tr in outs[-1] if tr.confirmed}
    return kept


def test_a_duplicate_track_on_one_person_is_still_merged():
    # a second track born on one standing person (a second box 1 m beside it for 10 frames), then the two tracks
    # taking turns on its one box, which jumps between the two places: both still, so the newer track is merged
    # (with merging off, merge_max_m tiny, both would stay)
    pose = pose_at()
    turns = [(observe([1.0 * (k % 2)], [25.0], pose), pose) for k in range(60)]
    frames = [(observe([0.0], [25.0], pose), pose)] * 30 + [(observe([0.0, 1.0], [25.0, 25.0], pose), pose)] * 10
    frames += turns
    assert _confirmed_at_the_end_with_and_without_merging(frames) == {"default": {1}, "no merging": {1, 2}}


def test_a_duplicate_track_on_a_walker_is_merged_too():
    # the velocity check's premise: a young duplicate's velocity is uncertain. A walker at 1.2 m/s with a second box
    # 1 m beside it for 10 frames (a second track born, standing still at first), then the two tracks taking turns on
    # its one box: the duplicate's velocity is still far less certain than the gap to the walker's, so it is merged
    pose = pose_at()
    frames = []
    for k in range(100):
        e = -6.0 + 1.2 * k / FPS
        if 30 <= k < 40:
            frames.append((observe([e, e], [25.0, 26.0], pose), pose))
        else:
            frames.append((observe([e], [25.0 + (k % 2 if k >= 40 else 0)], pose), pose))
    assert _confirmed_at_the_end_with_and_without_merging(frames) == {"default": {1}, "no merging": {1, 2}}
    # the velocity check ran on the pair and let it merge: with a near-zero threshold the duplicate stays
    outs = run(GpsTracker(TrackerConfig(merge_velocity_chi2=1e-6), CLASSES), frames)
    assert {tr.id for tr in outs[-1] if tr.confirmed} == {1, 2}


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_two_tracks_of_one_person_at_a_lip_are_merged_by_the_boxes_that_place_them_on_both_sides(seed):
    # as above, but one frame in ten carries no alternative (its probe did not reach the lip): a second track is born
    # on the far side, and both are fed in turn, 9 m apart (the position test of a merge fails). The boxes whose two
    # points fall in the two tracks' gates say they are one person: merged (merge_edge_twins), not without
    pose = pose_at()
    rng = np.random.default_rng(seed)
    near, far = local_to_latlon(0.0, 40.0, LAT0, LON0), local_to_latlon(0.0, 49.0, LAT0, LON0)
    base = observe([0.0, -15.0, 12.0, 20.0, -8.0], [40.0, 30.0, 35.0, 25.0, 22.0], pose)
    frames = []
    for k in range(150):
        here, other = (far, near) if rng.uniform() < 0.4 and k > 2 else (near, far)
        alt = np.full((5, 2), np.nan)
        if rng.uniform() >= 0.1:
            alt[0] = other
        frames.append((dataclasses.replace(base, lat=np.r_[here[0], base.lat[1:]], lon=np.r_[here[1], base.lon[1:]],
                                           alt_latlon=alt), pose))
    ids = {}
    for label, config in (("twins", TrackerConfig()), ("without", TrackerConfig(merge_edge_twins=0))):
        outs = run(GpsTracker(config, CLASSES), frames)
        ids[label] = {tr.id for tr in outs[-1] if tr.confirmed} - set().union(
            *(ids_near(outs[-1], e, n, 2.0) for e, n in ((-15.0, 30.0), (12.0, 35.0), (20.0, 25.0), (-8.0, 22.0))))
    assert len(ids["twins"]) == 1 and len(ids["without"]) == 2


def test_a_person_standing_where_the_lips_alternative_lands_is_not_merged_with_the_one_at_the_lip():
    # one person at the lip (its alternative 9 m farther) and another standing exactly there, detected in every frame
    # but one in eight: the lip person's boxes fall in both tracks' gates, but two detections in one frame are two
    # people, and that is remembered when the second is missed
    pose = pose_at()
    far = local_to_latlon(0.0, 49.0, LAT0, LON0)
    both = observe([0.0, 0.0], [40.0, 49.0], pose)
    assert len(both) == 2
    lip = int(np.argmin(np.abs(both.lat - local_to_latlon(0.0, 40.0, LAT0, LON0)[0])))
    alt = np.full((2, 2), np.nan)
    alt[lip] = far
    frame = dataclasses.replace(both, alt_latlon=alt)
    alone = observe([0.0], [40.0], pose)
    alone = dataclasses.replace(alone, alt_latlon=np.array([[far[0], far[1]]]))
    outs = run(GpsTracker(TrackerConfig(), CLASSES), [(alone if k % 8 == 7 else frame, pose) for k in range(121)])
    at_lip, beyond = ids_near(outs[-1], 0.0, 40.0, 1.0), ids_near(outs[-1], 0.0, 49.0, 1.0)
    assert len(at_lip) == 1 and len(beyond) == 1 and at_lip != beyond


@pytest.mark.parametrize("bad", [{"merge_edge_twins": -1}, {"merge_edge_twins": 2.5}, {"merge_edge_twins": True},
                                 {"merge_velocity_chi2": -1.0}, {"merge_velocity_chi2": float("nan")}])
def test_merge_settings_are_checked(bad) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        TrackerConfig(**bad)

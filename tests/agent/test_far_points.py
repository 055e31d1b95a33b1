"""agent.tracking.far_points: boxes beyond the pipeline's range get the tracker's own ground point where its error
model reaches, and nothing else changes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.frame_result import FrameResult
from agent.telemetry_correction import GroundCorrection
from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking.association import frame_detections
from agent.tracking.far_points import far_reach_m, fill_far_points
from shared.geo import Camera, Pose, latlon_to_local, local_to_pixel

CAMERA = Camera.from_preset("dji-mavic3pro-tele", 3840, 2160)


def _result(boxes: np.ndarray, lat: np.ndarray, lon: np.ndarray, correction=None) -> FrameResult:
    n = len(boxes)
    return FrameResult(boxes_xyxy=boxes.astype(np.float32), scores=np.full(n, 0.9, np.float32),
                       raw_scores=np.full(n, 0.9, np.float32), class_ids=np.ones(n, np.int64), lat=lat, lon=lon,
                       n_candidates=n, n_size_filtered=0, n_georeferenced=int(np.isfinite(lat).sum()),
                       correction=correction)


def _boxes_at(pose: Pose, east_north: list[tuple[float, float]]) -> np.ndarray:
    """20 x 40 px boxes whose bottom-centre (the "bottom" anchor; "auto" is close to it at grazing views) is each
    ground point."""
    uv, _ = local_to_pixel(np.array([e for e, _ in east_north]), np.array([n for _, n in east_north]), CAMERA, pose)
    return np.array([[u - 10.0, v - 40.0, u + 10.0, v] for u, v in uv])


@given(height=st.floats(5.0, 150.0), sigma=st.floats(1.0, 100.0), pitch_sigma=st.floats(0.05, 2.0))
def test_the_reach_is_where_the_along_ray_error_meets_the_sigma(height, sigma, pitch_sigma):
    config = TrackerConfig(far_reach_sigma_m=sigma, pitch_sigma_deg=pitch_sigma)
    reach = far_reach_m(config, height)
    along = (reach ** 2 + height ** 2) / height * math.radians(pitch_sigma)
    if reach > 0:
        assert along == pytest.approx(sigma, rel=1e-9)
    else:  # so high that even the point below is looser than the sigma
        assert height * math.radians(pitch_sigma) >= sigma * (1 - 1e-9)
    assert far_reach_m(TrackerConfig(far_reach_sigma_m=0.0), height) == 0.0


@settings(max_examples=40, deadline=None)
@given(height=st.floats(15.0, 60.0), pitch=st.floats(4.0, 12.0), heading=st.floats(0.0, 360.0),
       corr=st.tuples(st.floats(-3, 3), st.floats(-3, 3)))
def test_boxes_without_a_point_get_theirs_within_the_reach_and_the_others_are_untouched(height, pitch, heading, corr):
    pose = Pose(lat=47.6, lon=9.3, height_m=height, pitch_deg=pitch, heading_deg=heading)
    config = TrackerConfig(far_anchor="bottom", far_loose_gate=0.0)  # the boxes' bottom centres are the ground points
    reach = far_reach_m(config, height)
    ahead = height / math.tan(math.radians(pitch))  # the image centre's ground range
    ranges = [0.6 * ahead, 0.97 * reach, 1.05 * reach]
    h = math.radians(heading)
    points = [(r * math.sin(h), r * math.cos(h)) for r in ranges]
    boxes = _boxes_at(pose, points)
    inside = (boxes[:, 0] >= 0) & (boxes[:, 2] <= CAMERA.width) & (boxes[:, 1] >= 0) & (boxes[:, 3] <= CAMERA.height)
    lat = np.array([47.61, np.nan, np.nan])
    lon = np.array([9.31, np.nan, np.nan])
    result = _result(boxes, lat.copy(), lon.copy(), GroundCorrection(*corr))
    dets = frame_detections(result, config)
    filled = fill_far_points(dets, pose, CAMERA, result.correction, config)
    assert not filled[0] and dets.lat[0] == 47.61  # the pipeline's own point stays
    assert np.isnan(result.lat[1:]).all()  # the FrameResult is not written
    assert not filled[2] and np.isnan(dets.lat[2])  # beyond the reach: none without loose points
    assert dets.loose is None
    # far_loose_gate on: a loose point beyond the reach; far_image_sigma_m: followed in the image beyond its own reach
    loose_config = TrackerConfig(far_anchor="bottom", far_image_sigma_m=20.0)
    loose = frame_detections(result, loose_config)
    loose_filled = fill_far_points(loose, pose, CAMERA, result.correction, loose_config)
    assert loose.loose is not None and loose.unplaced is not None and not (loose.loose[0] or loose.unplaced[0])
    image_reach = far_reach_m(loose_config, height, loose_config.far_image_sigma_m)
    if inside[2]:
        assert loose_filled[2] and loose.loose[2] and loose.unplaced[2]
        e, n = latlon_to_local(loose.lat[2], loose.lon[2], pose.lat, pose.lon)
        assert float(e) == pytest.approx(points[2][0] + corr[0], abs=0.05 + 1e-4 * ranges[2])
    if inside[1]:  # within the reach: placed, and followed in the image beyond the image reach (far_image_sigma_m)
        assert loose_filled[1] and not loose.unplaced[1] and loose.lat[1] == pytest.approx(dets.lat[1], abs=1e-12)
        assert bool(loose.loose[1]) is (ranges[1] > image_reach * (1 + 1e-6))
    if inside[1]:
        assert filled[1]
        e, n = latlon_to_local(dets.lat[1], dets.lon[1], pose.lat, pose.lon)
        # where the box's bottom centre meets flat ground, moved by the pipeline's correction
        assert float(e) == pytest.approx(points[1][0] + corr[0], abs=0.05 + 1e-4 * ranges[1])
        assert float(n) == pytest.approx(points[1][1] + corr[1], abs=0.05 + 1e-4 * ranges[1])


def test_boxes_at_or_above_the_horizon_get_no_point():
    pose = Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=0.5, heading_deg=0.0)  # the horizon mid-image
    boxes = np.array([[1900.0, 100.0, 1940.0, 140.0], [1900.0, 1000.0, 1940.0, 1060.0]])  # sky; just below
    result = _result(boxes, np.full(2, np.nan), np.full(2, np.nan))
    dets = frame_detections(result, TrackerConfig(far_reach_sigma_m=1e6))
    filled = fill_far_points(dets, pose, CAMERA, None, TrackerConfig(far_reach_sigma_m=1e6))
    assert filled.tolist() == [False, True] and np.isnan(dets.lat[0])


def test_the_tracker_starts_tracks_on_far_boxes_and_not_with_the_reach_off():
    # probe: a view whose boxes all lay beyond the pipeline's range started no track (an empty MOT file)
    pose = Pose(lat=47.6, lon=9.3, height_m=25.0, pitch_deg=7.0, heading_deg=0.0)
    boxes = _boxes_at(pose, [(0.0, 200.0), (8.0, 215.0)])
    for config, tracked in ((TrackerConfig(), True), (TrackerConfig(far_reach_sigma_m=0.0), False)):
        tracker = GpsTracker(config, {1: "swimmer"})
        for k in range(10):
            tracks = tracker.update(_result(boxes, np.full(2, np.nan), np.full(2, np.nan)), pose, 100.0 + k / 10,
                                    CAMERA)
        confirmed = [tr for tr in tracks if tr.confirmed]
        assert (len(confirmed) == 2) is tracked and tracker.n_far_points == (20 if tracked else 0)
        assert tracker.last_grounded is not None and bool(tracker.last_grounded.all()) is tracked
        if tracked:
            e, n = latlon_to_local(np.array([tr.lat for tr in confirmed]), np.array([tr.lon for tr in confirmed]),
                                   pose.lat, pose.lon)
            assert sorted(np.round(n, 0).tolist()) == [200.0, 215.0]


def test_the_far_anchor_and_the_loose_gate_are_checked():
    with pytest.raises(ValueError, match="far_anchor"):
        TrackerConfig(far_anchor="top")
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="far_loose_gate"):
            TrackerConfig(far_loose_gate=bad)


def _far_view() -> tuple[Pose, float]:
    pose = Pose(lat=47.6, lon=9.3, height_m=25.0, pitch_deg=5.0, heading_deg=0.0)
    return pose, far_reach_m(TrackerConfig(), pose.height_m)


def _small_boxes(pose: Pose, east_north: list[tuple[float, float]], size: float, jitter: np.ndarray) -> np.ndarray:
    """size x size px boxes whose bottom centres are the ground points, moved by jitter (N, 2) pixels."""
    uv, _ = local_to_pixel(np.array([e for e, _ in east_north]), np.array([n for _, n in east_north]), CAMERA, pose)
    uv = uv + jitter
    return np.array([[u - size / 2, v - size, u + size / 2, v] for u, v in uv])


def test_boxes_beyond_the_reach_start_loose_tracks_followed_in_the_image():
    """Two swimmers beyond the reach: tracks start and keep their ids while the boxes, 6 px wide, jitter by up to
    4 px (IoU down to ~0.2); their positions are loose, so the agent does not report them to the fusion server.
    Probe: with far_loose_gate 0 no track starts (the tracker had nothing to place them by)."""
    from agent.node import publishable_tracks

    pose, reach = _far_view()
    points = [(-20.0, 1.3 * reach), (25.0, 1.4 * reach)]
    rng = np.random.default_rng(3)
    for config, tracked in ((TrackerConfig(), True), (TrackerConfig(far_loose_gate=0.0), False)):
        tracker = GpsTracker(config, {1: "swimmer"})
        seen: dict[int, set[int]] = {0: set(), 1: set()}
        for k in range(40):
            boxes = _small_boxes(pose, points, 6.0, rng.uniform(-2.0, 2.0, (2, 2)))
            tracks = tracker.update(_result(boxes, np.full(2, np.nan), np.full(2, np.nan)), pose, 100.0 + k / 10,
                                    CAMERA)
            for tr in tracks:
                if tr.confirmed and tr.matched:
                    seen[int(np.argmin(np.abs(boxes[:, 0] - tr.box_xyxy[0])))].add(tr.id)
        if not tracked:
            assert seen == {0: set(), 1: set()}
            continue
        assert [len(ids) for ids in seen.values()] == [1, 1] and seen[0] != seen[1]
        confirmed = [tr for tr in tracks if tr.confirmed]
        assert len(confirmed) == 2 and all(tr.loose for tr in confirmed)
        assert publishable_tracks(tracks) == []
        # no position: a loose point is as far off as a few pixels of pitch make it at that range
        assert all(math.isnan(tr.lat) and math.isnan(tr.lon) for tr in confirmed)


def test_a_loose_track_taking_a_point_within_the_reach_stops_being_loose():
    pose, reach = _far_view()
    tracker = GpsTracker(TrackerConfig(), {1: "swimmer"})
    far = np.zeros((1, 2))
    for k in range(5):  # beyond the reach
        boxes = _small_boxes(pose, [(0.0, 1.1 * reach)], 8.0, far)
        tracks = tracker.update(_result(boxes, np.full(1, np.nan), np.full(1, np.nan)), pose, 100.0 + k / 10, CAMERA)
    assert len(tracks) == 1 and tracks[0].loose
    for k in range(5, 40):  # the object comes within the reach, its box moving 2 px a frame
        d = 1.1 * reach - (k - 4) * 0.004 * reach
        boxes = _small_boxes(pose, [(0.0, d)], 8.0, far)
        tracks = tracker.update(_result(boxes, np.full(1, np.nan), np.full(1, np.nan)), pose, 100.0 + k / 10, CAMERA)
    assert [tr.id for tr in tracks if tr.matched] == [1]
    assert not tracks[0].loose and tracks[0].confirmed
    e, n = latlon_to_local(tracks[0].lat, tracks[0].lon, pose.lat, pose.lon)  # a position again, where it is
    assert abs(float(n) - (1.1 - 35 * 0.004) * reach) < 0.05 * reach and abs(float(e)) < 0.01 * reach


def test_boxes_without_any_point_follow_by_iou_whatever_the_loose_gate():
    """Review finding: the loose gate had also matched boxes without any ground point (far points off, over a DEM, at
    the horizon) by box centres. A 40 px box jumping 36 px a frame (IoU ~0.05) after losing its ground point is not
    followed, with the loose gate on or off."""
    camera = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
    pose = Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=45.0, heading_deg=0.0)
    for gate in (1.0, 0.0):
        tracker = GpsTracker(TrackerConfig(far_reach_sigma_m=0.0, far_loose_gate=gate), {1: "person"})
        matched = []
        for k in range(10):
            x = 900.0 + max(k - 4, 0) * 36.0
            box = np.array([[x, 500.0, x + 40.0, 540.0]])
            if k < 5:
                lat, lon = latlon_at(camera, pose, box)
            else:
                lat, lon = np.full(1, np.nan), np.full(1, np.nan)
            tracks = tracker.update(_result(box, lat, lon), pose, 100.0 + k / 10, camera)
            matched.append([tr.matched for tr in tracks if tr.id == 1])
        assert matched[4] == [True] and all(m in ([False], []) for m in matched[5:]), (gate, matched)


def latlon_at(camera: Camera, pose: Pose, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from shared.geo import pixel_to_latlon

    uv = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, boxes[:, 3]])
    lat, lon, _ = pixel_to_latlon(uv, camera, pose)
    return np.asarray(lat, float), np.asarray(lon, float)


@pytest.mark.parametrize("delay", [0.0, 0.3])
def test_a_loose_far_point_takes_no_lost_id(delay):
    """Review finding: a young track born from a loose point took a lost track's id by the loose point's ground
    position (tens to hundreds of metres off). An object lost within the reach and back just beyond it gets a new
    id, at once or deferred (reid_delay_s)."""
    pose, reach = _far_view()
    tracker = GpsTracker(TrackerConfig(reid_delay_s=delay), {1: "swimmer"})
    t = 100.0

    def frame(d):
        nonlocal t
        boxes = np.zeros((0, 4)) if d is None else _small_boxes(pose, [(0.0, d)], 8.0, np.zeros((1, 2)))
        tracks = tracker.update(_result(boxes, np.full(len(boxes), np.nan), np.full(len(boxes), np.nan)), pose, t,
                                CAMERA)
        t += 0.1
        return tracks

    for _ in range(10):
        tracks = frame(0.99 * reach)
    assert [(tr.id, tr.confirmed, tr.loose) for tr in tracks] == [(1, True, False)]
    for _ in range(15):
        frame(None)
    for _ in range(8):
        tracks = frame(1.01 * reach)
    assert [tr.id for tr in tracks if tr.matched] == [2] and tracker.n_reidentified == 0


def _swept_far_view(config: TrackerConfig, frames: int = 60, seed: int = 5, at: float = 1.3
                    ) -> tuple[dict[int, set[int]], list]:
    """Four swimmers at about `at` times the reach, 6 px boxes 40-60 px apart (at 1.3), under a tele camera that
    sweeps 0.1 deg (13 px, two box sizes) a frame for a second, holds, and sways up and down by up to 8 px a
    frame, with 1 px of box jitter; two large boxes (clutter) stay put in the image. Returns the ids seen on each
    swimmer (confirmed, matched) and the last frame's tracks."""
    pose0, reach = _far_view()
    points = [(-6.0, at * reach), (-2.0, (at + 0.02) * reach), (2.0, (at - 0.02) * reach), (6.0, (at + 0.01) * reach)]
    rng = np.random.default_rng(seed)
    tracker = GpsTracker(config, {1: "swimmer"})
    seen: dict[int, set[int]] = {k: set() for k in range(len(points))}
    heading, sway = 0.0, 0.0
    tracks: list = []
    for k in range(frames):
        heading += 0.1 if 5 <= k < 35 else 0.0
        sway = 0.6 * sway + rng.uniform(-8.0, 8.0)
        pose = Pose(lat=pose0.lat, lon=pose0.lon, height_m=pose0.height_m, pitch_deg=pose0.pitch_deg,
                    heading_deg=heading)
        jitter = rng.uniform(-1.0, 1.0, (len(points), 2)) + np.array([0.0, sway])
        boxes = np.vstack([_small_boxes(pose, points, 6.0, jitter),
                           [[300.0, 1500.0, 400.0, 1600.0], [3300.0, 1400.0, 3380.0, 1500.0]]])
        tracks = tracker.update(_result(boxes, np.full(len(boxes), np.nan), np.full(len(boxes), np.nan)), pose,
                                100.0 + k / 30, CAMERA)
        for tr in tracks:
            if tr.confirmed and tr.matched and tr.box_xyxy[2] - tr.box_xyxy[0] < 20:
                centre = 0.5 * (tr.box_xyxy[0] + tr.box_xyxy[2])
                seen[int(np.argmin(np.abs(0.5 * (boxes[:4, 0] + boxes[:4, 2]) - centre)))].add(tr.id)
    return seen, tracks


def test_far_objects_swept_across_the_image_keep_their_ids():
    """A tele camera's sweep moves every far box two box sizes a frame, its sway up to a size more: each swimmer's
    track expects its box where the image's common motion took it (`image_motion`, `far_shift_radius`) and keeps
    its id through the sweep. Probe: expected at its last box centre (far_shift_radius 0, far_loose_gate 1, as
    before 30 Nov 2026) the boxes leave every track's gate in the sweep and the swimmers change ids."""
    seen, tracks = _swept_far_view(TrackerConfig())
    assert [len(ids) for ids in seen.values()] == [1, 1, 1, 1] and len(set().union(*seen.values())) == 4
    assert sum(tr.confirmed and tr.matched for tr in tracks) == 6  # the swimmers and the two clutter boxes
    before, _ = _swept_far_view(TrackerConfig(far_shift_radius=0.0, far_loose_gate=1.0))
    assert sum(len(ids) for ids in before.values()) > 4


def test_points_beyond_the_image_reach_are_followed_in_the_image_and_keep_their_positions():
    """With far_image_sigma_m, points within the reach but beyond the shorter image reach are followed in the image
    (as loose ones are: through the sweep, one id each) and their tracks still report positions, where the
    swimmers are."""
    pose, reach = _far_view()
    config = TrackerConfig(far_image_sigma_m=20.0)
    assert far_reach_m(config, pose.height_m, 20.0) < 0.75 * reach
    seen, tracks = _swept_far_view(config, at=0.8)
    assert [len(ids) for ids in seen.values()] == [1, 1, 1, 1]
    swimmers = [tr for tr in tracks if tr.confirmed and tr.box_xyxy[2] - tr.box_xyxy[0] < 20]
    assert len(swimmers) == 4 and not any(tr.loose for tr in swimmers)
    e, n = latlon_to_local(np.array([tr.lat for tr in swimmers]), np.array([tr.lon for tr in swimmers]),
                           pose.lat, pose.lon)
    assert np.all(np.abs(np.hypot(e, n) - 0.8 * reach) < 0.1 * reach)


@pytest.mark.parametrize("delay", [0.0, 0.3])
def test_a_point_followed_in_the_image_within_the_reach_takes_its_lost_id_back(delay):
    """far_image_sigma_m follows points within the reach in the image, but their ground points still re-identify:
    a person behind trees comes back where the ground says (grass-far-tele lost its revivals with the option on).
    An object lost beyond the image reach, within the reach, gets its id back, at once or deferred."""
    pose, reach = _far_view()
    config = TrackerConfig(far_image_sigma_m=20.0, reid_delay_s=delay)
    assert far_reach_m(config, pose.height_m, 20.0) < 0.75 * reach
    tracker = GpsTracker(config, {1: "swimmer"})
    t = 100.0

    def frame(d):
        nonlocal t
        boxes = np.zeros((0, 4)) if d is None else _small_boxes(pose, [(0.0, d)], 8.0, np.zeros((1, 2)))
        tracks = tracker.update(_result(boxes, np.full(len(boxes), np.nan), np.full(len(boxes), np.nan)), pose, t,
                                CAMERA)
        t += 0.1
        return tracks

    for _ in range(10):
        tracks = frame(0.8 * reach)
    assert [(tr.id, tr.confirmed, tr.loose) for tr in tracks] == [(1, True, False)]
    for _ in range(15):
        frame(None)
    for _ in range(8):
        tracks = frame(0.8 * reach)
    assert [tr.id for tr in tracks if tr.matched] == [1] and tracker.n_reidentified == 1


def test_a_point_followed_in_the_image_within_the_reach_starts_no_track_beside_one_on_the_ground():
    """A second box a few sizes above a track's box (a part, or the object's other detection), whose ground point
    lies within the track's birth gate, starts no track when both are within the reach, followed in the image or
    not (far_image_sigma_m); beyond the reach (loose points) it does, as before."""
    pose, reach = _far_view()
    for at, sigma, born in ((0.8, 0.0, False), (0.8, 20.0, False), (1.3, 0.0, True)):
        tracker = GpsTracker(TrackerConfig(far_image_sigma_m=sigma), {1: "swimmer"})
        for k in range(12):
            boxes = _small_boxes(pose, [(0.0, at * reach)], 8.0, np.zeros((1, 2)))
            if k >= 6:
                boxes = np.vstack([boxes, boxes + np.array([0.0, -30.0, 0.0, -30.0])])
            tracks = tracker.update(_result(boxes, np.full(len(boxes), np.nan), np.full(len(boxes), np.nan)), pose,
                                    100.0 + k / 10, CAMERA)
        assert (max(tr.id for tr in tracks) > 1) == born, (at, sigma, [(tr.id, tr.box_xyxy) for tr in tracks])

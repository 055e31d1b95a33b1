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
    config = TrackerConfig(far_anchor="bottom")  # the boxes' bottom centres are the ground points
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
    assert not filled[2] and np.isnan(dets.lat[2])  # beyond the reach: none
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


def test_the_far_anchor_is_checked():
    with pytest.raises(ValueError, match="far_anchor"):
        TrackerConfig(far_anchor="top")

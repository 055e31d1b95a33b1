"""The tracker at the frame rates real files have: a detector's output every 15th video frame (2 fps)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking.config import FRAME_FLOORS
from tests.agent.test_tracker import CAM, CLASSES, observe, pose_at


def test_every_object_gets_one_confirmed_track_at_two_frames_a_second():
    # regression: tentative_coast_s 0.25 s deleted every tentative track before its second frame at 2 fps
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose = pose_at()
    out = []
    for k in range(12):
        out = tracker.update(observe([0.0, 8.0], [25.0, 30.0], pose), pose, 1.7e9 + 0.5 * k, CAM)
    confirmed = [tr for tr in out if tr.confirmed and tr.matched]
    assert sorted(tr.id for tr in confirmed) == [1, 2]
    assert tracker.config.tentative_coast_s == pytest.approx(0.75)
    assert tracker.base_config.tentative_coast_s == 0.25  # what was asked, kept


def test_a_missed_frame_at_two_fps_does_not_end_a_confirmed_track():
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose = pose_at()
    for k in range(8):
        seen = observe([0.0], [25.0], pose) if k != 5 else observe([], [], pose)
        out = tracker.update(seen, pose, 1.7e9 + 0.5 * k, CAM)
    assert [tr.id for tr in out if tr.confirmed and tr.matched] == [1]


@settings(max_examples=50, deadline=None)
@given(fps=st.floats(0.5, 120.0))
def test_property_windows_are_floored_to_frame_intervals_and_fast_video_is_untouched(fps):
    base = TrackerConfig()
    cfg = base.at_frame_interval(1.0 / fps)
    for name, k in FRAME_FLOORS.items():
        assert getattr(cfg, name) == pytest.approx(max(getattr(base, name), k / fps))
    assert cfg.confirm_window_s == pytest.approx(max(base.confirm_window_s, (base.confirm_hits - 0.5) / fps))
    if fps >= 24.0:
        assert cfg is base
    assert base.at_frame_interval(float("nan")) is base and base.at_frame_interval(0.0) is base

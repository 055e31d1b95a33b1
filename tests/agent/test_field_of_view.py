"""A zoom lens's field of view from the telemetry (agent.field_of_view): when it is applied, how it is read between
samples, and the warnings when it is not."""

from __future__ import annotations

import logging

import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.field_of_view import LINEAR_WITHIN_S, FieldOfView, field_of_view_track, zoomed_hfov_deg
from shared.geo import Camera
from shared.telemetry import Telemetry

CAMERA = Camera(width=320, height=180, fx=250.0, fy=250.0, cx=160.0, cy=90.0)  # 65.2 deg


def _records(hfovs, dt=0.1):
    return [Telemetry(t=100.0 + dt * i, lat=48.53, lon=9.06, height_m=40.0, pitch_deg=45.0, heading_deg=10.0,
                      hfov_deg=h) for i, h in enumerate(hfovs)]


def test_a_zoom_during_the_flight_is_applied_and_said(caplog):
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        track = field_of_view_track("f.ts", _records([30.0, 25.0, 20.0, None, 15.0]), CAMERA)
    assert track is not None
    assert [r.getMessage() for r in caplog.records] == [
        "telemetry f.ts: the horizontal field of view changes during the flight (15.0 .. 30.0 deg, a zoom lens; the "
        "camera file's is 65.2 deg): each frame's focal length follows it"]
    assert track.camera_at(100.1).hfov_deg == pytest.approx(25.0, abs=1e-3)
    assert track.camera_at(100.3).hfov_deg == pytest.approx(17.5, abs=1e-3)  # across the record without one
    assert track.camera_at(99.0).hfov_deg == pytest.approx(30.0, abs=1e-3)  # before the first: the first
    assert track.camera_at(200.0).hfov_deg == pytest.approx(15.0, abs=1e-3)  # after the last: held
    zoomed = track.camera_at(100.1)
    assert (zoomed.cx, zoomed.cy, zoomed.width, zoomed.height) == (160.0, 90.0, 320, 180)
    assert track.camera_at(100.1) is zoomed  # the same camera while the zoom stands (the pipeline compares)


@pytest.mark.parametrize(("hfovs", "said"), [
    ([65.0] * 5, None),
    ([None] * 5, None),
    ([70.0, 71.0, 72.0], None),  # within 5 %: no zoom; within 15 % of the camera's
    ([8.0] * 5, "the horizontal field of view it sends is 8.0 deg, constant over the flight, where the camera's is "
                "65.2 deg"),
])
def test_a_constant_field_of_view_is_not_applied(caplog, hfovs, said):
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        assert field_of_view_track("f.ts", _records(hfovs), CAMERA) is None
    messages = [r.getMessage() for r in caplog.records]
    assert (messages[0].split(": ", 1)[1].startswith(said) and len(messages) == 1) if said else not messages


def test_samples_far_apart_hold_the_earlier_until_the_next():
    """An encoder that sends the field of view only when it changes: the zoom stood at the earlier value until the
    later sample, it did not move gradually between them."""
    track = FieldOfView([0.0, 0.5, 10.0], [40.0, 30.0, 10.0], CAMERA)
    assert track.at(0.25) == pytest.approx(35.0)
    assert track.at(0.5 + LINEAR_WITHIN_S + 1.0) == pytest.approx(30.0)
    assert track.at(9.99) == pytest.approx(30.0)
    assert track.at(10.0) == pytest.approx(10.0)
    with pytest.raises(ValueError, match="at least one sample"):
        FieldOfView([], [], CAMERA)


@given(st.lists(st.tuples(st.floats(0.0, 100.0), st.floats(1.0, 120.0)), min_size=1, max_size=20),
       st.floats(-10.0, 110.0))
def test_the_field_of_view_at_any_time_lies_within_the_samples(samples, t):
    track = FieldOfView([s[0] for s in samples], [s[1] for s in samples], CAMERA)
    lo, hi = min(s[1] for s in samples), max(s[1] for s in samples)
    assert lo - 1e-9 <= track.at(t) <= hi + 1e-9
    assert track.camera_at(t).hfov_deg == pytest.approx(round(track.at(t), 3), abs=1e-6)


def test_on_a_live_link_the_camera_file_stands_until_the_lens_zooms(caplog):
    from agent.field_of_view import LiveFieldOfView

    live = LiveFieldOfView("udp:127.0.0.1:14550")
    steady = _records([8.0, 8.0, 8.0])  # constant, far from the camera file's: never applied (as for a file)
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        assert live.camera_at(100.1, steady, CAMERA) is CAMERA
        assert live.camera_at(100.1, _records([None, None]), CAMERA) is CAMERA
        zoom = _records([8.0, 8.0, 8.0, 12.0])
        assert live.camera_at(100.3, zoom, CAMERA).hfov_deg == pytest.approx(12.0, abs=1e-3)
        assert live.camera_at(100.1, zoom, CAMERA).hfov_deg == pytest.approx(8.0, abs=1e-3)  # from now on
        assert live.camera_at(100.1, _records([None]), CAMERA) is CAMERA  # no field of view around: the file's
    assert [r.getMessage() for r in caplog.records] == [
        "telemetry udp:127.0.0.1:14550: the horizontal field of view changed (8.0 .. 12.0 deg so far, a zoom lens; "
        "the camera file's is 65.2 deg): from now on each frame's focal length follows it"]


def _zoom_records(ratios, dt=0.1):
    return [Telemetry(t=100.0 + dt * i, lat=48.53, lon=9.06, height_m=40.0, pitch_deg=45.0, heading_deg=10.0,
                      zoom_ratio=z) for i, z in enumerate(ratios)]


def test_a_digital_zoom_that_changes_narrows_the_camera_files_view(caplog):
    """A DJI SRT's dzoom_ratio on a fixed lens: 2x is the centre half of the image, so the focal length doubles (the
    field of view's half-angle tangent halves) and a box 80 px off centre is half as far off on the ground."""
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        track = field_of_view_track("clip.SRT", _zoom_records([1.0, 1.0, 2.0, 2.0]), CAMERA)
    assert track is not None
    assert track.camera_at(100.0).fx == pytest.approx(CAMERA.fx, rel=1e-4)
    assert track.camera_at(100.3).fx == pytest.approx(2.0 * CAMERA.fx, rel=1e-4)
    assert CAMERA.fx < track.camera_at(100.15).fx < 2.0 * CAMERA.fx  # between the samples: in between
    (said,) = [r.getMessage() for r in caplog.records]
    assert "the digital zoom's field of view changes during the flight (35.5 .. 65.2 deg, a digital zoom" in said


def test_a_constant_digital_zoom_is_named_not_applied(caplog):
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        assert field_of_view_track("clip.SRT", _zoom_records([1.0] * 4), CAMERA) is None
        assert not caplog.records
        assert field_of_view_track("clip.SRT", _zoom_records([2.0] * 4), CAMERA) is None
    assert "digital zoom's field of view it sends is 35.5 deg, constant" in caplog.records[0].getMessage()


def test_a_field_of_view_sent_beside_a_digital_zoom_wins():
    records = [Telemetry(t=100.0 + i, lat=48.53, lon=9.06, height_m=40.0, pitch_deg=45.0, heading_deg=10.0,
                         hfov_deg=h, zoom_ratio=4.0) for i, h in enumerate([30.0, 20.0])]
    track = field_of_view_track("f.ts", records, CAMERA)
    assert track is not None and track.at(100.0) == pytest.approx(30.0)


@given(st.floats(1.0, 1000.0), st.floats(1.0, 170.0))
def test_a_digital_zoom_scales_the_focal_length(zoom, hfov):
    narrowed = zoomed_hfov_deg(hfov, zoom)
    assert 0.0 < narrowed <= hfov + 1e-9
    camera = CAMERA.with_hfov(hfov)
    assert camera.with_hfov(narrowed).fx == pytest.approx(zoom * camera.fx, rel=1e-6)

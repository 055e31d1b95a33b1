"""The video source's start on a flight controller's log (agent.sources): where the log says the camera started
recording, the video starts there; without it, at the log's first record, with one warning."""

from __future__ import annotations

import pytest

from agent.sources import video_start_time, video_telemetry
from shared.telemetry import Telemetry
from tests.shared.mavlink_writer import flight_packets, write_tlog

pytest.importorskip("pymavlink")
T0 = 1_685_613_600.0


def _tlog(tmp_path, extra=()):
    flight = [Telemetry(t=T0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06, height_m=30.0, pitch_deg=45.0,
                        heading_deg=10.0, vel_en_mps=(0.0, 2.0)) for i in range(60)]
    return write_tlog(tmp_path / "flight.tlog", sorted(flight_packets(flight) + list(extra), key=lambda p: p[0]))


def test_the_video_starts_where_the_tlog_says_the_camera_started_recording(tmp_path, caplog):
    """Before, the video went at the log's first record: 3.5 s early here (QGC logs from connection)."""
    from pymavlink.dialects.v20 import ardupilotmega

    camera = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=100)
    extra = [(T0 + k, camera.camera_capture_status_encode(0, 0, int(k >= 4), 0, int(max(0, (k - 3.5) * 1e3)) if k >= 4
                                                                else 0, 1000.0).pack(camera)) for k in range(7)]
    path = _tlog(tmp_path, extra)
    records, start = video_telemetry(path, need_angles=True)
    with caplog.at_level("INFO"):
        t0 = video_start_time(records, path, video_start_t=start)
    assert t0 == pytest.approx(T0 + 3.5 - 0.02, abs=1e-3)
    assert "the log's camera recording start" in caplog.text and "WARNING" not in caplog.text


def test_a_tlog_without_a_recording_start_places_the_video_at_its_first_record_with_one_warning(tmp_path, caplog):
    """Before, silently."""
    path = _tlog(tmp_path)
    records, start = video_telemetry(path, need_angles=True)
    with caplog.at_level("WARNING"):
        t0 = video_start_time(records, path, video_start_t=start)
    assert start is None and t0 == records[0].t
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "no recording start in the log" in warnings[0]
    assert "--telemetry-offset-s" in warnings[0] and "already moves" in warnings[0]

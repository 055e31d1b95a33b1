"""When a flight controller's log says its camera recorded (shared.telemetry.recording): MAVLink's
CAMERA_CAPTURE_STATUS and video start/stop commands in a .tlog, PX4's vehicle_command in a .ulg; a marker that
does not say when recording started is not used."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry import Telemetry, read_tlog_report, read_ulog_report, recording_start
from shared.telemetry.recording import from_commands, from_status
from tests.shared.mavlink_writer import euler_to_quaternion, flight_packets, ulog_bytes, write_tlog

T0 = 1_685_613_600.0


def _flight(n: int = 60) -> list[Telemetry]:
    return [Telemetry(t=T0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06, height_m=30.0, pitch_deg=45.0,
                      heading_deg=10.0, vel_en_mps=(0.0, 1.0)) for i in range(n)]


def _mav(compid: int = 100, sysid: int = 1):
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def _status(t: float, video: int, elapsed_ms: int) -> tuple[float, bytes]:
    link = _mav()
    return t, link.camera_capture_status_encode(0, 0, video, 0, elapsed_ms, 1000.0).pack(link)


def _with(extra: list[tuple[float, bytes]], tmp_path, name="f.tlog"):
    pytest.importorskip("pymavlink")
    packets = sorted(flight_packets(_flight()) + extra, key=lambda item: item[0])
    return read_tlog_report(write_tlog(tmp_path / name, packets))


def test_camera_capture_status_with_its_elapsed_time_gives_the_start(tmp_path):
    """Status at 1 Hz, recording from T0 + 2.35 s (between two messages): the elapsed time places it; the records
    say recording from then on, as AirData's isVideo does. Before, the video went at the log's first record."""
    start = T0 + 2.35
    extra = [_status(T0 + k + 0.5, int(T0 + k + 0.5 >= start), max(0, round((T0 + k + 0.5 - start) * 1e3)))
             for k in range(6)]
    report = _with(extra, tmp_path)
    # the status is placed at its receive time less the link's latency (20 ms in flight_packets' log)
    assert report.recording.start_t == pytest.approx(start - 0.02, abs=1e-3)
    assert report.recording.precise
    assert recording_start(report.records)[0] == pytest.approx(T0 + 2.4)
    assert [r.recording for r in report.records] == [r.t >= start for r in report.records]


def test_a_status_that_records_from_first_to_last_without_an_elapsed_time_is_not_used(tmp_path, caplog):
    with caplog.at_level("WARNING"):
        report = _with([_status(T0 + k + 0.5, 1, 0) for k in range(6)], tmp_path)
    assert report.recording.start_t is None and all(r.recording is None for r in report.records)
    assert "does not say when that recording started" in caplog.text


def test_an_accepted_video_start_command_gives_the_start_and_a_refused_one_does_not(tmp_path, caplog):
    gcs = _mav(190, 255)
    command = gcs.command_long_encode(1, 100, 2500, 0, 0, 0, 0, 0, 0, 0, 0).pack(gcs)
    camera = _mav()
    accepted = camera.command_ack_encode(2500, 0).pack(camera)
    refused = camera.command_ack_encode(2500, 4).pack(camera)
    report = _with([(T0 + 3.0, command), (T0 + 3.05, accepted)], tmp_path)
    assert report.recording.start_t == pytest.approx(T0 + 3.05 - 0.02, abs=1e-3)
    with caplog.at_level("WARNING"):
        report = _with([(T0 + 3.0, command), (T0 + 3.05, refused)], tmp_path, "refused.tlog")
    assert report.recording.start_t is None and "was not accepted" in caplog.text


def test_ulog_vehicle_command_video_start_gives_the_start(tmp_path):
    pytest.importorskip("pyulog")
    boot0 = 20_000_000
    times = [boot0 + 100_000 * i for i in range(30)]
    topics: dict = {
        "vehicle_global_position": ([("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon")],
                                    [(t, 48.53, 9.06) for t in times]),
        "vehicle_attitude": ([("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)],
                             [(t, *euler_to_quaternion(0, 0, 10.0)) for t in times]),
        "vehicle_gps_position": ([("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")],
                                 [(t, int(round(T0 * 1e6)) + t - boot0) for t in times]),
        "vehicle_command": ([("uint64_t", "timestamp"), ("uint32_t", "command")],
                            [(boot0 + 1_234_000, 2500), (boot0 + 2_500_000, 2501)]),
    }
    path = tmp_path / "f.ulg"
    path.write_bytes(ulog_bytes(topics))
    report = read_ulog_report(path)
    ((begin, end),) = report.recording.spans
    assert (begin, end) == pytest.approx((T0 + 1.234, T0 + 2.5))
    assert [r.recording for r in report.records] == [1.234 <= r.t - T0 < 2.5 for r in report.records]


@settings(max_examples=100, deadline=None)
@given(start=st.floats(0.0, 30.0), period=st.floats(0.2, 3.0), first=st.floats(0.0, 3.0),
       latency=st.floats(0.0, 0.3))
def test_status_recordings_start_where_the_camera_started(start, period, first, latency):
    """A status every `period` s received `latency` late: the start is the elapsed-time estimate (within the
    latency); without the elapsed time, within one period of it, and never before the last idle status."""
    sent = np.arange(first, 40.0, period)
    on = sent >= start
    t = sent + latency
    elapsed = np.where(on, (sent - start) * 1e3, 0.0)
    got = from_status(t, on.astype(float), elapsed)
    if not on.any():
        assert got.start_t is None
        return
    if on.sum() >= 2 and not on[0]:
        assert got.start_t == pytest.approx(start + latency, abs=1e-6) and got.precise
    coarse = from_status(t, on.astype(float), np.zeros(len(t)))
    if on[0]:
        assert coarse.start_t is None and "does not say" in coarse.note
    else:
        assert t[~on][-1] <= coarse.start_t <= t[on][0] and abs(coarse.start_t - start - latency) <= period


def test_commands_pair_starts_and_stops():
    assert from_commands([1.0, 1.5, 5.0], [3.0], "x").spans == ((1.0, 3.0), (5.0, math.inf))
    assert from_commands([], [3.0], "x").spans == ()


def test_without_a_start_the_warning_says_how_long_before_the_vehicle_moves():
    from shared.telemetry.recording import no_start_placement

    parked = [Telemetry(t=T0 + i, lat=48.53, lon=9.06, height_m=0.0 if i < 42 else 5.0, pitch_deg=45.0,
                        heading_deg=0.0, speed_mps=0.0) for i in range(50)]
    assert "42.0 s before the vehicle first moves or climbs" in no_start_placement(parked)
    assert "never moves" in no_start_placement(parked[:10])

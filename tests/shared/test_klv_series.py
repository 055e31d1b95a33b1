"""ST 0601 samples in time (shared.telemetry.klv_series, through klv's reader): time stamps an encoder repeats
(sample-and-hold) are timed by the packets' PTS or spread between the stamps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.telemetry import parse_klv_report, read_klv_report
from shared.telemetry.klv_series import sample_times
from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts

T0 = 1_717_236_000.0
VIDEO0 = 900_000  # the video's first PTS


def _panning(t_true: float, stamp: float) -> bytes:
    """A packet stamped `stamp` whose gimbal pans 10 deg/s: its azimuth tells the time it was sampled."""
    return packet(stamp, {**FULL_FIELDS, "platform_heading_deg": 0.0,
                          "sensor_rel_azimuth_deg": (10.0 * (t_true - T0)) % 360.0})


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(hold_hz=st.sampled_from([1, 2, 5]), rate_hz=st.sampled_from([25, 30]), phase_s=st.floats(0.0, 0.99))
def test_held_time_stamps_are_timed_by_the_pts_of_their_packets(tmp_path, hold_hz, rate_hz, phase_s):
    # regression: a stamp held at 1 Hz put video_start_t 0.48 s early and every packet under one stamp at the
    # stamp's time (the first of them won in interpolation: angles lagged by up to a second)
    t_true = [T0 + phase_s + i / rate_hz for i in range(4 * rate_hz)]
    stamps = [math.floor(t * hold_hz) / hold_hz for t in t_true]  # the stream may begin while a stamp is held
    pts = [VIDEO0 + round(i * 90_000 / rate_hz) for i in range(len(t_true))]
    path = tmp_path / "held.ts"
    path.write_bytes(write_ts([(p, _panning(t, s)) for p, t, s in zip(pts, t_true, stamps, strict=True)],
                              video_pts=[VIDEO0], klv_stream_type=0x06))
    report = read_klv_report(path)
    assert report.times_from == "pts" and report.repeated_stamps > 0
    t = np.array([r.t for r in report.records])
    assert (np.diff(t) > 0).all()
    # a new stamp is seen at the first packet after it changed: up to one packet interval late
    assert np.abs(t - np.array(t_true)).max() <= 1.0 / rate_hz + 1e-6
    assert report.video_start_t == pytest.approx(T0 + phase_s, abs=1.0 / rate_hz + 1e-6)
    off_deg = [abs((r.heading_deg - 10.0 * (r.t - T0) + 180.0) % 360.0 - 180.0) for r in report.records
               if r.heading_deg is not None]
    assert len(off_deg) == len(t) and max(off_deg) <= 10.0 / rate_hz + 0.01  # the angles sampled at that time


def test_fresh_stamps_keep_their_values_whatever_the_pts(tmp_path):
    jitter = [0, 700, -400, 1_500, 0, 2_000]  # an encoder's PTS wobble around its stamps
    klv = [(VIDEO0 + 9_000 * i + j, packet(T0 + 0.1 * i, FULL_FIELDS)) for i, j in enumerate(jitter)]
    path = tmp_path / "fresh.ts"
    path.write_bytes(write_ts(klv, video_pts=[VIDEO0]))
    report = read_klv_report(path)
    assert (report.times_from, report.repeated_stamps) == ("stamps", 0)
    assert [r.t for r in report.records] == [T0 + 0.1 * i for i in range(6)]


@pytest.mark.parametrize(("hold_hz", "expected"), [
    (1, [T0 + 0.1 * i for i in range(20)]),  # whole seconds: ten packets a second, spread over it
    (5, [T0 + 0.1 * i for i in range(20)]),  # stamps 0.2 s apart, two packets each: up to the next stamp
])
def test_raw_klv_repeated_stamps_are_spread_between_the_stamps(hold_hz, expected):
    # regression: without PTS, packets under one stamp all had its time
    data = b"".join(packet(math.floor((0.1 * i + 1e-9) * hold_hz) / hold_hz + T0, FULL_FIELDS) for i in range(20))
    report = parse_klv_report(data)
    assert (report.times_from, report.repeated_stamps) == ("spread", 20 - 2 * hold_hz)
    assert [r.t for r in report.records] == pytest.approx(expected, abs=1e-6)


def test_sample_times_checks_its_lengths_and_takes_the_next_offset_for_a_stale_first_stamp():
    with pytest.raises(ValueError, match="2 stamps but 1 PTS"):
        sample_times([0.0, 1.0], [None])
    # stamps 10, 10, 10, 11, 11 at PTS 0.4 .. 1.2 s: the stamp 11 is new at PTS 1.0, so the clocks differ by 10 s
    times = sample_times([10.0, 10.0, 10.0, 11.0, 11.0], [0.4, 0.6, 0.8, 1.0, 1.2])
    assert times.method == "pts" and times.repeated == 3
    assert times.t == pytest.approx([10.4, 10.6, 10.8, 11.0, 11.2])

"""ST 0601 samples in time (shared.telemetry.klv_series, through klv's reader): time stamps an encoder repeats
(sample-and-hold) are timed by the packets' PTS or spread between the stamps; a sensor position sent less often
than the angles is interpolated between the packets that sent it, a GPS outage gives no records."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from shared.telemetry import parse_klv_report, read_klv_report
from shared.telemetry.klv_series import positions_in_time, sample_times
from tests.shared.klv_writer import FULL_FIELDS, packet, resolution, write_ts

T0 = 1_717_236_000.0
VIDEO0 = 900_000  # the video's first PTS


def _panning(t_true: float, stamp: float) -> bytes:
    """A packet stamped `stamp` whose gimbal pans 10 deg/s: its azimuth tells the time it was sampled."""
    return packet(stamp, {**FULL_FIELDS, "platform_heading_deg": 0.0,
                          "sensor_rel_azimuth_deg": (10.0 * (t_true - T0)) % 360.0})


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(hold_hz=st.sampled_from([1, 2, 5]), rate_hz=st.sampled_from([25, 30]), phase_s=st.floats(0.0, 0.99))
@example(hold_hz=5, rate_hz=30, phase_s=1 / 3)  # frames on the stamps' boundaries
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


# ---- positions in time ----------------------------------------------------------------------------------------
M_PER_DEG = 111_320.0
ANGLES = {"platform_heading_deg": 0.0, "sensor_rel_azimuth_deg": 0.0, "sensor_rel_elevation_deg": -60.0,
          "frame_center_elevation_m": 500.0}


def _truth(dt: float, north_mps: float, east_mps: float, climb_mps: float) -> dict[str, float]:
    return {"sensor_lat": 48.5 + north_mps * dt / M_PER_DEG,
            "sensor_lon": 9.0 + east_mps * dt / (M_PER_DEG * math.cos(math.radians(48.5))),
            "sensor_alt_msl_m": 600.0 + climb_mps * dt}


@settings(max_examples=40, deadline=None)
@given(rate_hz=st.sampled_from([10, 25, 30]), position_hz=st.sampled_from([0.5, 1.0, 2.0, 5.0]),
       phase=st.integers(0, 100), north_mps=st.floats(-30, 30), east_mps=st.floats(-30, 30),
       climb_mps=st.floats(-5, 5))
def test_a_position_sent_less_often_than_the_angles_is_interpolated_between_the_packets_that_sent_it(
        rate_hz, position_hz, phase, north_mps, east_mps, climb_mps):
    # regression: the position was held from packet to packet, stepping once a second (19 m off at 20 m/s)
    every = round(rate_hz / position_hz)
    n = 4 * rate_hz
    packets = [packet(T0 + i / rate_hz, {**ANGLES, **(_truth(i / rate_hz, north_mps, east_mps, climb_mps)
                                                     if (i + phase) % every == 0 else {})}) for i in range(n)]
    report = parse_klv_report(b"".join(packets))
    senders = [i for i in range(n) if (i + phase) % every == 0]
    # kept after the last sender: the stream's own interval between positions (at least 0.5 s, at most 3 s)
    tail_s = min(max((senders[1] - senders[0]) / rate_hz if len(senders) > 1 else 0.0, 0.5), 3.0)
    hold = max(k for k in range(n - senders[-1]) if k / rate_hz <= tail_s + 1e-9)
    expected = list(range(senders[0], senders[-1] + hold + 1))
    assert [round((r.t - T0) * rate_hz) for r in report.records] == expected
    assert report.no_recent_position == n - len(expected) - senders[0] and report.no_position == senders[0]
    for r in report.records:
        i = round((r.t - T0) * rate_hz)
        at = min(i, senders[-1])  # after the last sender: its position, held
        truth = _truth(at / rate_hz, north_mps, east_mps, climb_mps)
        assert r.lat == pytest.approx(truth["sensor_lat"], abs=resolution("sensor_lat"))
        assert r.lon == pytest.approx(truth["sensor_lon"], abs=resolution("sensor_lon"))
        assert r.height_m == pytest.approx(truth["sensor_alt_msl_m"] - 500.0, abs=resolution("sensor_alt_msl_m"))


def test_a_gps_outage_gives_no_records_after_a_short_hold_and_is_counted():
    # regression: 4 s without tags 13-15 while the angles went on gave records frozen where the fix was lost
    packets = [packet(T0 + i / 10, {**ANGLES, **({} if 20 <= i < 60 else _truth(i / 10, 20.0, 0.0, 0.0))})
               for i in range(80)]
    report = parse_klv_report(b"".join(packets))
    kept = [round((r.t - T0) * 10) for r in report.records]
    assert kept == [*range(25), *range(60, 80)]  # 2.0 .. 2.4 s keep the fix of 1.9 s; 2.5 .. 5.9 s none
    assert report.records[24].lat == pytest.approx(_truth(1.9, 20.0, 0.0, 0.0)["sensor_lat"], abs=1e-7)
    assert report.problems() == {"no_recent_position": 35}
    assert report.samples[30].sensor_lat is None and report.samples[30].platform_heading_deg == 0.0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(0.001, 0.3), st.floats(-1e-3, 1e-3), st.floats(0, 300)), min_size=1, max_size=15))
def test_a_stream_with_every_item_in_every_packet_gives_each_packets_own_record(steps):
    t, packets = T0, []
    for dt, dlat, alt in steps:
        t += dt
        packets.append(packet(t, {**FULL_FIELDS, "sensor_lat": 48.53 + dlat, "sensor_alt_msl_m": 480.0 + alt}))
    alone = [rec for p in packets for rec in parse_klv_report(p).records]
    assert parse_klv_report(b"".join(packets)).records == sorted(alone, key=lambda r: r.t)


def test_positions_in_time_cross_the_antimeridian_and_do_not_bridge_unknown():
    t = np.array([0.0, 0.5, 1.0, 1.5])
    lon = np.array([179.9, 179.9, -179.9, np.nan])  # sample 3: the decoder has none (sent as unknown)
    sent = np.array([True, False, True, False])
    out = positions_in_time(t, {"sensor_lat": [1.0, 1.0, 2.0, np.nan], "sensor_lon": lon},
                            {"sensor_lat": sent, "sensor_lon": sent})
    assert abs(out["sensor_lon"][1]) == pytest.approx(180.0) and out["sensor_lat"][1] == pytest.approx(1.5)
    assert np.isnan(out["sensor_lon"][3]) and out["sensor_lon"][2] == -179.9


def test_an_altitude_sent_every_few_seconds_is_kept_between_its_packets():
    """An encoder sends tag 15 on change or every 3 s beside a 10 Hz position: the altitude's 0.5 s hold dropped
    the height of most records (the run was refused for want of one)."""
    packets = []
    for i in range(100):
        truth = _truth(i / 10, 5.0, 0.0, 1.0)
        if i % 30:
            truth = {k: v for k, v in truth.items() if k != "sensor_alt_msl_m"}
        packets.append(packet(T0 + i / 10, {**ANGLES, **truth}))
    report = parse_klv_report(b"".join(packets))
    assert len(report.records) == 100 and report.problems() == {}
    heights = [r.height_m for r in report.records]
    assert all(h is not None for h in heights[:91])  # between the packets that sent it: interpolated
    assert heights[45] == pytest.approx(_truth(4.5, 5.0, 0.0, 1.0)["sensor_alt_msl_m"] - 500.0, abs=0.5)


def test_a_first_stamp_sharing_the_next_ones_pes_keeps_its_time():
    """Three packets in one PES share its PTS; one later stamp repeats: the first packet (fresh) was moved to the
    second's time."""
    stamps = [T0, T0 + 1 / 30, T0 + 2 / 30, T0 + 2 / 30, T0 + 4 / 30, T0 + 5 / 30]
    times = sample_times(stamps, [10.0, 10.0, 10.0, 10.1, 10.1, 10.1])
    assert times.method == "pts" and times.t[0] == T0 and times.t[1] == pytest.approx(T0 + 1 / 30)
    assert (np.diff(times.t) >= 0).all() and times.t[3] <= stamps[4]
    jump = sample_times(stamps, [10.0, 10.0, 10.0, 19.0, 19.1, 19.2])  # a PTS discontinuity under a held stamp
    assert jump.t[3] < stamps[4] and (np.diff(jump.t) > 0).all()

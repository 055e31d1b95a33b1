"""Flight controllers' logs (.tlog, .ulg) after the walk-through of their readers: the gimbal interpolated between
its readings and never carried far beyond them, a .tlog's receive clock taken at the fastest packets, and a .ulg's
positions without a valid height dropped rather than refusing the run."""

from __future__ import annotations

import math

import pytest

from shared.telemetry import Telemetry, read_telemetry
from shared.telemetry.tlog import parse_tlog
from tests.shared.mavlink_writer import euler_to_quaternion, flight_packets, ulog_bytes

pytest.importorskip("pymavlink")

T0 = 1_685_613_600.0  # 2023-06-01 10:00 UTC
_GIMBAL = {"GIMBAL_DEVICE_ATTITUDE_STATUS", "MOUNT_ORIENTATION", "MOUNT_STATUS"}


def _flight(n: int) -> list[Telemetry]:
    """10 Hz positions; the gimbal tilts 1 deg and pans 3 deg per record (through north)."""
    return [Telemetry(t=T0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06 - 2e-5 * i, height_m=30.0 + 0.1 * i,
                      pitch_deg=40.0 + i, heading_deg=(350.0 + 3 * i) % 360, vel_en_mps=(-1.5, 1.1))
            for i in range(n)]


def _type(packet: bytes) -> str:
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None).decode(bytearray(packet)).get_type()


def _tlog(packets) -> bytes:
    import struct

    return b"".join(struct.pack(">Q", int(round(t * 1e6))) + p for t, p in packets)


def _gimbal_at(flight, keep, **kw) -> list[tuple[float, bytes]]:
    """flight_packets with the gimbal's messages only at the records whose index `keep` accepts."""
    out, k = [], 0
    for t, packet in flight_packets(flight, **kw):
        kind = _type(packet)
        if kind not in _GIMBAL or keep(k):
            out.append((t, packet))
        k += kind == "GLOBAL_POSITION_INT"
    return out


@pytest.mark.parametrize("gimbal", ["device-earth", "device-vehicle", "mount-status", "mount-orientation"])
def test_a_1hz_gimbal_is_interpolated_to_each_position(gimbal):
    """Before, each position held the latest reading: 1 Hz readings beside 10 Hz positions were up to 9 deg of
    pitch and 27 deg of heading behind."""
    flight = _flight(31)
    records = parse_tlog(_tlog(_gimbal_at(flight, lambda k: k % 10 == 0, gimbal=gimbal)))
    assert [r.pitch_deg for r in records] == pytest.approx([f.pitch_deg for f in flight], abs=0.02)
    for got, want in zip(records, flight, strict=True):
        assert math.cos(math.radians(got.heading_deg - want.heading_deg)) == pytest.approx(1.0, abs=1e-6)


def test_a_gimbal_that_stops_reporting_is_not_held_for_the_rest_of_the_flight(caplog):
    """The gimbal reports for the first second (10 Hz) of 4 s: its last reading is carried max(1 s, 3 intervals);
    the positions after get no gimbal pitch and the vehicle's yaw as heading, and one warning counts them. Before,
    its last reading was held to the end with no word."""
    flight = _flight(40)
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(_gimbal_at(flight, lambda k: k <= 10)))
    assert [r.pitch_deg for r in records[:11]] == pytest.approx([f.pitch_deg for f in flight[:11]], abs=0.02)
    assert [r.pitch_deg for r in records[11:21]] == pytest.approx([flight[10].pitch_deg] * 10, abs=0.02)
    assert all(r.pitch_deg is None for r in records[21:])
    vehicle_yaw = [(f.heading_deg + 20.0) % 360 for f in flight]  # flight_packets' vehicle heads 20 deg off
    assert [r.heading_deg for r in records[21:]] == pytest.approx(vehicle_yaw[21:], abs=1e-3)
    warnings = [r.getMessage() for r in caplog.records if "gimbal's readings" in r.getMessage()]
    assert len(warnings) == 1 and "19 of 40 positions" in warnings[0] and "from 2.1 s to 3.9 s" in warnings[0]


@pytest.mark.parametrize("spread_s", [0.2, 0.5, 1.0])
def test_without_system_time_the_log_clock_is_taken_at_the_fastest_packets(spread_s):
    """Receive time = send time + a link latency of 20 ms + up to spread_s (a radio), one packet stamped 2 s early
    (a ground station's clock step): the records lag the flight by about the smallest latency. Before, the median
    of receive - boot time carried the median latency (spread_s / 2 late: 0.5 s at 1 s)."""
    flight = _flight(40)
    packets = [(t + spread_s * ((k * 7919) % 100) / 100.0, p)
               for k, (t, p) in enumerate(flight_packets(flight, system_time=False))]
    packets[50] = (packets[50][0] - 2.0, packets[50][1])
    records = parse_tlog(_tlog(sorted(packets, key=lambda item: item[0])))
    assert [r.t for r in records] == pytest.approx([f.t + 0.02 for f in flight], abs=0.03 * spread_s + 2e-3)


# ---- PX4 ULog -------------------------------------------------------------------------------------------------

def _ulog(tmp_path, *, gimbal_window=None, z_nan_until=None, z_valid_from=None, n: int = 50):
    """10 Hz positions over n / 10 s; the gimbal at 20 Hz within gimbal_window (s after the first position);
    local z NaN before z_nan_until, z_valid false before z_valid_from (s)."""
    pytest.importorskip("pyulog")
    boot0 = 20_000_000
    flight = _flight(n)
    times = [boot0 + 100_000 * i for i in range(n)]
    local_t = [boot0 + 20_000 * i for i in range(5 * n)]

    def z(t_us: int) -> float:
        if z_nan_until is not None and (t_us - boot0) / 1e6 < z_nan_until:
            return math.nan
        return -(30.0 + (t_us - boot0) / 1e6)

    topics: dict = {
        "vehicle_global_position": ([("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon")],
                                    [(t, f.lat, f.lon) for t, f in zip(times, flight, strict=True)]),
        "vehicle_local_position": ([("uint64_t", "timestamp"), ("float", "z"), ("bool", "z_valid")],
                                   [(t, z(t), z_valid_from is None or (t - boot0) / 1e6 >= z_valid_from)
                                    for t in local_t]),
        "vehicle_attitude": ([("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)],
                             [(t, *euler_to_quaternion(0, 0, 200.0)) for t in local_t]),
        "vehicle_gps_position": ([("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")],
                                 [(t, int(round(T0 * 1e6)) + t - boot0) for t in times]),
    }
    rows = []
    for k in range(2 * n):
        s = 0.05 * k
        if gimbal_window is None or gimbal_window[0] <= s <= gimbal_window[1]:
            rows.append((boot0 + 50_000 * k, *euler_to_quaternion(0, -(40.0 + 10 * s), 100.0 + 30 * s), 16 | 64))
    topics["gimbal_device_attitude_status"] = (
        [("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)] + [("uint32_t", "device_flags")], rows)
    path = tmp_path / "flight.ulg"
    path.write_bytes(ulog_bytes(topics))
    return path


def test_ulog_gimbal_that_starts_late_and_ends_early_is_not_carried_outside(tmp_path, caplog):
    """Readings from 2.0 s to 2.5 s of 5 s: carried 1 s either side (20 Hz: max(1 s, 3 intervals)), no further.
    Before, np.interp held the first and last reading over the whole log."""
    with caplog.at_level("WARNING"):
        records = read_telemetry(_ulog(tmp_path, gimbal_window=(2.0, 2.5)))
    offsets = [round(r.t - T0, 3) for r in records]
    inside = [o for o, r in zip(offsets, records, strict=True) if r.pitch_deg is not None]
    assert inside[0] == pytest.approx(1.0) and inside[-1] == pytest.approx(3.5)
    for o, r in zip(offsets, records, strict=True):
        if r.pitch_deg is None:
            assert r.heading_deg == pytest.approx(200.0, abs=1e-3)  # the vehicle's yaw
        elif 2.0 <= o <= 2.5:
            assert r.pitch_deg == pytest.approx(40.0 + 10 * o, abs=0.01)
            assert r.heading_deg == pytest.approx(100.0 + 30 * o, abs=0.01)
    warnings = [r.getMessage() for r in caplog.records if "gimbal's samples" in r.getMessage()]
    assert len(warnings) == 1 and "24 of 50 positions" in warnings[0]


@pytest.mark.parametrize("kind", ["z NaN", "z_valid false"])
def test_ulog_positions_without_a_valid_height_are_dropped_not_the_run(tmp_path, caplog, kind):
    """The estimate's height is NaN (or flagged invalid) for the first second: those positions are dropped with one
    warning; before, they had no height and the video source refused the run (pass --height-m)."""
    kw = {"z_nan_until": 1.0} if kind == "z NaN" else {"z_valid_from": 1.0}
    with caplog.at_level("WARNING"):
        records = read_telemetry(_ulog(tmp_path, **kw))
    assert len(records) == 40 and all(r.height_m is not None for r in records)
    assert records[0].t - T0 == pytest.approx(1.0)
    assert [r.height_m for r in records] == pytest.approx([30.0 + r.t - T0 for r in records], abs=1e-3)
    warnings = [r.getMessage() for r in caplog.records if "no valid height" in r.getMessage()]
    assert len(warnings) == 1 and "10 of 50 positions" in warnings[0]


def test_ulog_with_almost_no_valid_height_keeps_its_positions_without_heights(tmp_path):
    """Valid at 2 of 50 positions: nothing is dropped, the others have no height (the run asks for --height-m)."""
    records = read_telemetry(_ulog(tmp_path, z_nan_until=4.8))
    assert len(records) == 50 and sum(r.height_m is None for r in records) == 48

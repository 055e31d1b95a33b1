"""MAVLink (.tlog, written by pymavlink's own encoder) and PX4 ULog telemetry: the same records as the other
readers, gimbal frames and clocks as MAVLink/PX4 define them (shared.telemetry.mavlink, shared.telemetry.ulog)."""

from __future__ import annotations

import io
import math
import re
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.telemetry import Telemetry, read_telemetry
from shared.telemetry.mavlink import quaternion_to_euler_deg
from shared.telemetry.tlog import parse_tlog
from tests.shared.mavlink_writer import BOOT_MS0, euler_to_quaternion, flight_packets, ulog_bytes, write_tlog

pytest.importorskip("pymavlink")

T0 = 1_685_613_600.0  # 2023-06-01 10:00 UTC


def _flight(n: int = 12) -> list[Telemetry]:
    return [Telemetry(t=T0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06 - 2e-5 * i, height_m=30.0 + 0.5 * i,
                      pitch_deg=45.0 + i, heading_deg=(350.0 + 3 * i) % 360, roll_deg=0.0, vel_en_mps=(-1.5, 1.1))
            for i in range(n)]


def _same(got: list[Telemetry], want: list[Telemetry], *, angles: bool = True) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.t == pytest.approx(w.t, abs=2e-3)
        assert (g.lat, g.lon) == pytest.approx((w.lat, w.lon), abs=2e-7)  # 1e-7 deg integers
        assert g.height_m == pytest.approx(w.height_m, abs=1e-3)
        assert g.vel_en_mps == pytest.approx(w.vel_en_mps, abs=0.01)
        if angles:
            assert g.pitch_deg == pytest.approx(w.pitch_deg, abs=0.02)
            assert math.cos(math.radians(g.heading_deg - w.heading_deg)) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("gimbal", ["device-earth", "device-vehicle", "mount-orientation", "mount-orientation-relative",
                                    "mount-status"])
def test_tlog_gives_the_records_the_flight_logged(tmp_path, gimbal):
    flight = _flight()
    path = write_tlog(tmp_path / "flight.tlog", flight_packets(flight, gimbal=gimbal))
    _same(read_telemetry(path), flight)


def test_camera_fov_status_gives_each_record_the_zoom_lens_field_of_view(tmp_path):
    """A gimbal camera with a zoom (ArduPilot's mount camera, MAVLink's camera protocol) sends CAMERA_FOV_STATUS:
    each position takes the latest horizontal field of view of the first camera (NaN: unknown; another camera's,
    an IR beside the EO, ignored)."""
    flight = _flight()
    packets = []
    for t, p in flight_packets(flight):
        if _type(p) == "GLOBAL_POSITION_INT":
            k = sum(1 for _, q in packets if _type(q) == "GLOBAL_POSITION_INT")
            hfov = math.nan if k == 3 else 60.0 - 4.0 * k
            eo = _mav(1, 100).camera_fov_status_encode(0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0], hfov, hfov * 0.56, 1)
            ir = _mav(1, 100).camera_fov_status_encode(0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0], 9.0, 7.0, 2)
            packets += [(t, eo.pack(_mav(1, 100))), (t, ir.pack(_mav(1, 100)))]
        packets.append((t, p))
    records = read_telemetry(write_tlog(tmp_path / "zoom.tlog", packets))
    _same(records, flight)
    assert [r.hfov_deg for r in records] == pytest.approx(
        [None if k == 3 else 60.0 - 4.0 * k for k in range(len(flight))], abs=1e-4)


def test_mount_orientation_prefers_the_absolute_yaw_to_the_vehicle_relative_one():
    from shared.telemetry.mavlink import MavlinkAssembler

    position = {"time_boot_ms": 1000, "lat": 485300000, "lon": 90600000, "relative_alt": 30000, "vx": 0, "vy": 0,
                "hdg": 65535}
    assembler = MavlinkAssembler()
    assembler.add("ATTITUDE", {"yaw": math.radians(100.0)}, 1)
    assembler.add("MOUNT_ORIENTATION", {"roll": 0.0, "pitch": -45.0, "yaw": 20.0, "yaw_absolute": 250.0}, 1)
    sample = assembler.add("GLOBAL_POSITION_INT", position, 1)
    assert sample.heading_deg == pytest.approx(250.0) and sample.pitch_deg == pytest.approx(45.0)
    for unknown in (math.nan, 0.0):  # NaN (MAVLink: unknown) or 0 (the field's default in older firmware)
        assembler.add("MOUNT_ORIENTATION", {"roll": 0.0, "pitch": -45.0, "yaw": 20.0, "yaw_absolute": unknown}, 1)
        assert assembler.add("GLOBAL_POSITION_INT", position, 1).heading_deg == pytest.approx(120.0)


def test_without_a_gimbal_the_camera_heads_where_the_vehicle_does_and_needs_a_pitch(tmp_path):
    flight = _flight()
    records = read_telemetry(write_tlog(tmp_path / "f.tlog", flight_packets(flight, gimbal="none")))
    _same(records, flight, angles=False)
    assert all(r.pitch_deg is None for r in records)
    assert [r.heading_deg for r in records] == pytest.approx([f.heading_deg for f in flight], abs=1e-4)
    assert records[3].to_pose(pitch_deg=60.0).pitch_deg == 60.0


def test_tlog_without_system_time_is_stamped_by_the_logs_receive_times(tmp_path):
    flight = _flight()
    packets = [(t + 0.25, p) for t, p in flight_packets(flight, system_time=False)]  # received 0.27 s late
    records = read_telemetry(write_tlog(tmp_path / "f.tlog", packets))
    assert [r.t for r in records] == pytest.approx([f.t + 0.27 for f in flight], abs=2e-3)


def test_tlog_skips_noise_other_systems_and_repeats(tmp_path):
    flight = _flight()
    packets = flight_packets(flight)
    other = flight_packets([Telemetry(t=f.t, lat=10.0, lon=10.0, height_m=5.0, pitch_deg=10.0, heading_deg=0.0)
                            for f in flight], system_id=7)
    noisy = b"".join(struct.pack(">Q", int(t * 1e6)) + p for t, p in packets[:5])
    noisy += b"\xfd\x09garbage\xfe\x01" + b"".join(struct.pack(">Q", int(t * 1e6)) + p for t, p in packets[5:])
    noisy += b"".join(struct.pack(">Q", int(t * 1e6)) + p for t, p in other + packets[-6:])  # another drone; repeats
    _same(parse_tlog(noisy), flight)


def test_tlog_without_positions_is_refused_naming_the_file(tmp_path):
    path = write_tlog(tmp_path / "empty.tlog", [(t, p) for t, p in flight_packets(_flight(3)) if p[7] != 33])
    with pytest.raises(ValueError, match=r"empty.tlog: no vehicle position \(GLOBAL_POSITION_INT\)"):
        read_telemetry(path)


@settings(max_examples=200, deadline=None)
@given(roll=st.floats(-60, 60), pitch=st.floats(-89, 89), yaw=st.floats(-179.9, 179.9))
def test_quaternion_to_euler_inverts_euler_to_quaternion(roll, pitch, yaw):
    got = quaternion_to_euler_deg(tuple(euler_to_quaternion(roll, pitch, yaw)))
    assert got[1] == pytest.approx(pitch, abs=1e-6)
    assert math.cos(math.radians(got[2] - yaw)) == pytest.approx(1.0, abs=1e-9)
    assert math.cos(math.radians(got[0] - roll)) == pytest.approx(1.0, abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(pitch=st.one_of(st.sampled_from([-90.0, 90.0, -89.99, 89.99, -89.9]), st.floats(-90, 90)),
       yaw=st.floats(-179.9, 179.9), float32=st.booleans())
def test_a_camera_looking_straight_down_keeps_its_heading(pitch, yaw, float32):
    """A nadir gimbal (mapping, or at its end stop) sends a quaternion at gimbal lock, rounded to float32 on the
    wire: its heading is the turn about the vertical (it came out 0, or the vehicle's yaw), its roll 0."""
    q = euler_to_quaternion(0.0, pitch, yaw)
    if float32:
        q = [float(np.float32(v)) for v in q]
    roll, got_pitch, got_yaw = quaternion_to_euler_deg(tuple(q))
    assert got_pitch == pytest.approx(pitch, abs=0.01)
    assert math.cos(math.radians(got_yaw - yaw)) == pytest.approx(1.0, abs=2e-6)  # within ~0.1 deg
    assert abs(roll) < 0.1


# ---- the vehicle's clock, reboots, several vehicles and gimbals, attitude at the position's time --------------

def _mav(sysid: int = 1, compid: int = 1):
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def _type(packet: bytes) -> str:
    return _mav().decode(bytearray(packet)).get_type()


def _tlog(packets) -> bytes:
    return b"".join(struct.pack(">Q", int(round(t * 1e6))) + p for t, p in packets)


def _moved(records: list[Telemetry], **change) -> list[Telemetry]:
    """The records with fields shifted: t=+300.0 adds 300 s to every t."""
    return [Telemetry(**{name: getattr(r, name) + change.get(name, 0) if name in change else getattr(r, name)
                         for name in ("t", "lat", "lon", "height_m", "pitch_deg", "heading_deg", "roll_deg",
                                      "vel_en_mps")}) for r in records]


@settings(max_examples=25, deadline=None)
@given(sender=st.sampled_from([(255, 190), (254, 1), (1, 240)]), uptime_ms=st.integers(0, 10**7),
       clock_error_s=st.floats(-3600, 3600), vehicle_system_time=st.booleans())
def test_a_ground_stations_system_time_never_sets_the_vehicles_clock(sender, uptime_ms, clock_error_s,
                                                                     vehicle_system_time):
    """A GCS (or a companion computer on the vehicle's system id) logs its own SYSTEM_TIME, its UNIX time and its
    own uptime, before the vehicle's streams start: every record came out off by the difference of the uptimes."""
    flight = _flight()
    gcs = _mav(*sender).system_time_encode(int((T0 - 3.0 + clock_error_s) * 1e6), uptime_ms).pack(_mav(*sender))
    records = parse_tlog(_tlog([(T0 - 3.0, gcs), *flight_packets(flight, system_time=vehicle_system_time)]))
    lag = 0.0 if vehicle_system_time else 0.02  # without the vehicle's SYSTEM_TIME: the log's receive times
    assert [r.t for r in records] == pytest.approx([f.t + lag for f in flight], abs=2e-3)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(steps=st.lists(st.floats(-600, 600).filter(lambda s: abs(s) > 1.5), min_size=1, max_size=2),
       at=st.integers(1, 10))
def test_the_clock_after_its_last_jump_times_the_log_and_one_warning_gives_the_jumps(caplog, steps, at):
    """PX4 / ArduPilot set their UNIX clock from the ground station's, then from GPS: the clock steps by `steps[j]`
    at record `at + j`. The first SYSTEM_TIME's offset was used for the whole log, silently."""
    flight = _flight()
    packets, k = [], 0
    for t, p in flight_packets(flight):
        if _type(p) == "SYSTEM_TIME":
            error_s = -sum(step for j, step in enumerate(steps) if at + j > k)  # 0 after the last step
            p = _mav().system_time_encode(int(round((flight[k].t + error_s) * 1e6)), BOOT_MS0 + 100 * k).pack(_mav())
            k += 1
        packets.append((t, p))
    caplog.clear()
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(packets))
    _same(records, flight)
    jumped = [r.getMessage() for r in caplog.records if "jumped" in r.getMessage()]
    assert len(jumped) == 1
    # the steps as measured from the microsecond stamps: 2.0555 reads +2.055 (hypothesis found the rounding edge)
    said = [float(v) for v in re.findall(r"by ([+-]\d+\.\d+) s", jumped[0])]
    assert said == pytest.approx(list(steps), abs=2e-3)


@pytest.mark.parametrize("second_boot_ms", [BOOT_MS0 - 3_000, BOOT_MS0 - 5_037])  # on the first's 100 ms grid or not
@pytest.mark.parametrize("second_system_time", [True, False])
def test_a_reboot_mid_log_gives_each_boot_its_own_clock(caplog, second_boot_ms, second_system_time):
    """A battery swap between two flights of one ground-station session restarts time_boot_ms: the two flights came
    out interleaved, or the second's positions were dropped as repeats of the first's boot times."""
    first, second = _flight(), _moved(_flight(), t=300.0, lon=0.0135)
    packets = flight_packets(first) + flight_packets(second, boot_ms0=second_boot_ms, system_time=second_system_time)
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(packets))
    _same(records, first + (second if second_system_time else _moved(second, t=0.02)))  # else: receive times
    assert sum("rebooted 1 time" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("by", ["gimbal_device_id", "component"])
def test_of_two_gimbals_the_first_is_used_and_the_other_named(caplog, by):
    """An autopilot with two mounts (a mapping camera and a forward one) sends both gimbals' attitude, by device id
    (MAVLink 2 since 2022) or as two components (id 0, older senders): pitch and heading flipped between them."""
    flight = _flight()
    other_q = euler_to_quaternion(0.0, -10.0, 123.0)
    packets, n = [], 0
    for t, p in flight_packets(flight, gimbal="device-earth"):
        if _type(p) != "GIMBAL_DEVICE_ATTITUDE_STATUS":
            packets.append((t, p))
            continue
        if by == "gimbal_device_id":  # the autopilot speaks for both gimbals
            q = list(_mav().decode(bytearray(p)).q)
            pair = [_mav().gimbal_device_attitude_status_encode(0, 0, 0, 16 | 64, q, 0, 0, 0, 0, 0, 0, 1).pack(_mav()),
                    _mav().gimbal_device_attitude_status_encode(0, 0, 0, 16 | 64, other_q, 0, 0, 0, 0, 0, 0, 2)
                    .pack(_mav())]
        else:  # two gimbal devices of their own
            pair = [p, _mav(1, 155).gimbal_device_attitude_status_encode(0, 0, 0, 16 | 64, other_q, 0, 0, 0, 0)
                    .pack(_mav(1, 155))]
        packets.extend((t, q) for q in (pair if n % 2 == 0 else pair[::-1]))  # the camera's gimbal first, then by turns
        n += 1
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(packets))
    _same(records, flight)
    warned = [r.getMessage() for r in caplog.records if "gimbals" in r.getMessage()]
    ignored = "gimbal_device_id 2" if by == "gimbal_device_id" else "gimbal component 155"
    assert len(warned) == 1 and f"ignoring {ignored} ({len(flight)} messages)" in warned[0]


def test_of_several_vehicles_the_one_with_the_most_positions_is_read_and_all_named(caplog):
    """QGroundControl logs every vehicle on its links: the first to send a position was read, silently."""
    flight, other = _flight(), _moved(_flight(6), t=-1.0, lat=0.02)  # the other drone's stream started first
    packets = sorted(flight_packets(flight) + flight_packets(other, system_id=2), key=lambda tp: tp[0])
    with caplog.at_level("WARNING"):
        _same(parse_tlog(_tlog(packets)), flight)
    warned = [r.getMessage() for r in caplog.records if "vehicles" in r.getMessage()]
    assert len(warned) == 1
    assert "system 1 (12 positions)" in warned[0] and "system 2 (6 positions)" in warned[0]
    assert "reading system 1" in warned[0]
    _same(parse_tlog(_tlog(packets), system_id=2), other)
    with pytest.raises(ValueError, match=r"of system 9 .*system 2 \(6 positions\), system 1 \(12 positions\)"):
        parse_tlog(_tlog(packets), system_id=9)


@settings(max_examples=40, deadline=None)
@given(yaw0=st.floats(0, 360), rate_dps=st.floats(-120, 120), every=st.integers(2, 5),
       gimbal=st.sampled_from(["none", "device-vehicle", "mount-status"]))
def test_the_vehicle_yaw_is_interpolated_to_each_positions_time(yaw0, rate_dps, every, gimbal):
    """ATTITUDE streams slower than GLOBAL_POSITION_INT (Mission Planner over a radio: 2 Hz and 5 Hz): each position
    took the latest ATTITUDE, up to rate x interval off. Bracketed positions now get the yaw at their time (on the
    circle: the flight turns through north); after the last ATTITUDE it is held."""
    flight = [Telemetry(t=T0 + 0.1 * i, lat=48.53, lon=9.06, height_m=30.0, pitch_deg=45.0,
                        heading_deg=(yaw0 + rate_dps * 0.1 * i) % 360, vel_en_mps=(0.0, 0.0)) for i in range(12)]
    packets, k = [], 0
    for t, p in flight_packets(flight, gimbal=gimbal):
        if _type(p) == "ATTITUDE":
            k += 1
            if (k - 1) % every:
                continue
        packets.append((t, p))
    records = parse_tlog(_tlog(packets))
    last = (len(flight) - 1) // every * every  # the last record with an ATTITUDE
    want = [f.heading_deg for f in flight[:last + 1]] + [flight[last].heading_deg] * (len(flight) - 1 - last)
    for got, expected in zip(records, want, strict=True):
        assert math.cos(math.radians(got.heading_deg - expected)) == pytest.approx(1.0, abs=1e-6)


# ---- PX4 ULog -------------------------------------------------------------------------------------------------

def _ulog_flight(tmp_path, *, gimbal_flags: int | None = 16 | 64, gps: bool = True, gps_receivers=(), n: int = 12,
                 sync_every: int = 0):
    """The flight of `_flight` as a .ulg; gps_receivers: (topic, multi_id, has UTC) of more GPS instances;
    sync_every: a sync message before every sync_every-th data message (0: none)."""
    pytest.importorskip("pyulog")
    boot0 = 20_000_000
    flight = _flight(n)
    times = [boot0 + int(round((f.t - T0) * 1e6)) for f in flight]
    topics: dict = {
        "vehicle_global_position": ([("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"),
                                     ("float", "alt")],
                                    [(t, f.lat, f.lon, 400.0 + f.height_m)
                                     for t, f in zip(times, flight, strict=True)]),
        "vehicle_local_position": ([("uint64_t", "timestamp"), ("float", "z"), ("float", "vx"), ("float", "vy")],
                                   [(t + 500, -f.height_m, f.vel_en_mps[1], f.vel_en_mps[0])
                                    for t, f in zip(times, flight, strict=True)]),
        "vehicle_attitude": ([("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)],
                             [(t, *euler_to_quaternion(0, 0, f.heading_deg + 20)) for t, f in zip(times, flight,
                                                                                                   strict=True)]),
    }
    if gimbal_flags is not None:
        earth = gimbal_flags & 64
        topics["gimbal_device_attitude_status"] = (
            [("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)] + [("uint32_t", "device_flags")],
            [(t, *euler_to_quaternion(0, -f.pitch_deg, f.heading_deg if earth else -20.0), gimbal_flags)
             for t, f in zip(times, flight, strict=True)])
    if gps:
        topics["vehicle_gps_position"] = ([("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")],
                                          [(t, int(round(T0 * 1e6)) + t - boot0) for t in times])
    for name, multi_id, has_utc in gps_receivers:
        topics[(name, multi_id)] = ([("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")],
                                    [(t, int(round(T0 * 1e6)) + t - boot0 if has_utc else 0) for t in times])
    path = tmp_path / "flight.ulg"
    path.write_bytes(ulog_bytes(topics, sync_every=sync_every))
    return path, flight


@pytest.mark.parametrize("flags", [16 | 64, 32])
def test_ulog_gives_the_records_the_flight_logged(tmp_path, flags):
    path, flight = _ulog_flight(tmp_path, gimbal_flags=flags)
    records = read_telemetry(path)
    assert len(records) == len(flight)
    for g, w in zip(records, flight, strict=True):
        assert g.t == pytest.approx(w.t, abs=1e-5)
        assert (g.lat, g.lon) == pytest.approx((w.lat, w.lon), abs=1e-9)
        # the local position is logged 0.5 ms after each global one: interpolated at 5 m/s climb, <= 2.5 mm less
        assert g.height_m == pytest.approx(w.height_m, abs=3e-3)
        assert g.pitch_deg == pytest.approx(w.pitch_deg, abs=1e-3)
        assert math.cos(math.radians(g.heading_deg - w.heading_deg)) == pytest.approx(1.0, abs=1e-6)
        assert g.vel_en_mps == pytest.approx(w.vel_en_mps, abs=1e-4)


def test_ulog_written_back_by_pyulog_reads_the_same(tmp_path):
    from pyulog import ULog

    path, _ = _ulog_flight(tmp_path)
    buffer = io.BytesIO()
    ULog(str(path)).write_ulog(buffer)  # pyulog's own writer, from the log it parsed
    (tmp_path / "again.ulg").write_bytes(buffer.getvalue())
    first, again = read_telemetry(path), read_telemetry(tmp_path / "again.ulg")
    assert np.allclose([(r.t, r.lat, r.lon, r.height_m, r.heading_deg) for r in first],
                       [(r.t, r.lat, r.lon, r.height_m, r.heading_deg) for r in again])


def test_ulog_without_gimbal_or_utc_is_a_fixed_camera_on_the_boot_clock(tmp_path):
    path, flight = _ulog_flight(tmp_path, gimbal_flags=None, gps=False)
    records = read_telemetry(path, height_offset_m=-2.0)
    assert records[0].t == pytest.approx(BOOT_MS0 / 1000, abs=1e-6)  # seconds since boot
    assert all(r.pitch_deg is None for r in records)
    assert records[4].heading_deg == pytest.approx((flight[4].heading_deg + 20) % 360, abs=1e-3)
    assert records[4].height_m == pytest.approx(flight[4].height_m - 2.0025, abs=1e-4)


def test_ulog_errors_name_the_file(tmp_path):
    pytest.importorskip("pyulog")
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"not a ulog at all")
    with pytest.raises(ValueError, match="bad.ulg: not a readable ULog file"):
        read_telemetry(bad)
    empty = tmp_path / "empty.ulg"
    empty.write_bytes(ulog_bytes({"vehicle_attitude": ([("uint64_t", "timestamp"), ("float", "q[0]")], [(1, 1.0)])}))
    with pytest.raises(ValueError, match="empty.ulg: no vehicle_global_position"):
        read_telemetry(empty)


def _ulog_gimbal_switching(tmp_path, flags: list[int], vehicle_yaw: list[float], camera_heading: list[float]):
    """A .ulg whose gimbal reports, per sample, `device_flags` and its yaw in the frame those flags name."""
    pytest.importorskip("pyulog")
    times = [20_000_000 + 200_000 * i for i in range(len(flags))]
    gimbal_rows = []
    for t, f, v, c in zip(times, flags, vehicle_yaw, camera_heading, strict=True):
        earth = f & 64 or (not f & 32 and f & 16)
        gimbal_rows.append((t, *euler_to_quaternion(0, -60.0, c if earth else c - v), f))
    topics = {
        "vehicle_global_position": ([("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon")],
                                    [(t, 48.53 + 1e-5 * i, 9.06) for i, t in enumerate(times)]),
        "vehicle_attitude": ([("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)],
                             [(t, *euler_to_quaternion(0, 0, v)) for t, v in zip(times, vehicle_yaw, strict=True)]),
        "gimbal_device_attitude_status": (
            [("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)] + [("uint32_t", "device_flags")],
            gimbal_rows),
    }
    path = tmp_path / "switching.ulg"
    path.write_bytes(ulog_bytes(topics))
    return path


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_ulog_gimbal_flags_count_per_sample_when_the_pilot_switches_follow_and_lock(tmp_path_factory, data):
    """Follow (yaw in the vehicle frame) and lock (earth frame) switched mid-flight: each sample's own flags say
    how to read its yaw (the last sample's flags were used for the whole log: headings off by the vehicle's yaw)."""
    n = data.draw(st.integers(2, 12))
    flags = data.draw(st.lists(st.sampled_from([16 | 64, 64, 32, 16 | 32, 16, 0]), min_size=n, max_size=n))
    vehicle_yaw = data.draw(st.lists(st.floats(-179, 179), min_size=n, max_size=n))
    camera = data.draw(st.lists(st.floats(-179, 179), min_size=n, max_size=n))
    records = read_telemetry(_ulog_gimbal_switching(tmp_path_factory.mktemp("ulg"), flags, vehicle_yaw, camera))
    for got, want in zip(records, camera, strict=True):
        assert math.cos(math.radians(got.heading_deg - want)) == pytest.approx(1.0, abs=1e-6)


def test_ulog_gimbal_switch_between_samples_keeps_the_heading(tmp_path):
    """Positions between a follow sample and a lock sample: the yaws are brought into one frame before
    interpolating (the camera holds 30 deg, the vehicle heads 100 deg; positions 0.1 s after each gimbal sample)."""
    path = _ulog_gimbal_switching(tmp_path, [32] * 5 + [16 | 64] * 5, [100.0] * 10, [30.0] * 10)
    from pyulog import ULog

    ulog = ULog(str(path))
    buffer = io.BytesIO()
    for dataset in ulog.data_list:
        if dataset.name == "vehicle_global_position":
            dataset.data["timestamp"] = dataset.data["timestamp"] + 100_000
    ulog.write_ulog(buffer)
    (tmp_path / "shifted.ulg").write_bytes(buffer.getvalue())
    assert [round(r.heading_deg, 3) for r in read_telemetry(tmp_path / "shifted.ulg")] == [30.0] * 10


_HOME = [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt"), ("float", "x"),
         ("float", "y"), ("float", "z"), ("uint8_t", "valid_lpos")]


def _ulog_heights(tmp_path, local_z: list[float], homes: list[tuple[int, float, int]] | None):
    """A .ulg with positions every 0.2 s (local z logged at the same times) and `homes` as (time us, z, valid)."""
    pytest.importorskip("pyulog")
    times = [20_000_000 + 200_000 * i for i in range(len(local_z))]
    topics = {
        "vehicle_global_position": ([("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon")],
                                    [(t, 48.53 + 1e-5 * i, 9.06) for i, t in enumerate(times)]),
        "vehicle_local_position": ([("uint64_t", "timestamp"), ("float", "z")],
                                   [(t, z) for t, z in zip(times, local_z, strict=True)]),
    }
    if homes is not None:
        topics["home_position"] = (_HOME, [(t, 48.53, 9.06, 412.0, 0.0, 0.0, z, valid) for t, z, valid in homes])
    path = tmp_path / "heights.ulg"
    path.write_bytes(ulog_bytes(topics))
    return path, times


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_ulog_height_is_above_the_home_in_effect_not_the_ekf_origin(tmp_path_factory, data):
    """PX4 powered on away from the launch spot (or the baro drifted on the ground): the EKF origin is not the
    take-off point, home_position.z says where home is in the same frame (the reader gave -z: 52 m for 40 m).
    Home may be reset in flight: the latest before each position counts, the first one before it is set."""
    n = data.draw(st.integers(2, 10))
    above_home = data.draw(st.lists(st.floats(0, 120, width=32), min_size=n, max_size=n))
    home_times = sorted(data.draw(st.lists(st.integers(19_000_000, 20_000_000 + 200_000 * n), min_size=1,
                                           max_size=3, unique=True)))
    home_z = data.draw(st.lists(st.floats(-30, 30, width=32), min_size=len(home_times), max_size=len(home_times)))
    times = [20_000_000 + 200_000 * i for i in range(n)]
    in_effect = [home_z[max(0, sum(h <= t for h in home_times) - 1)] for t in times]
    local_z = [z - h for z, h in zip(in_effect, above_home, strict=True)]
    path, _ = _ulog_heights(tmp_path_factory.mktemp("ulg"), local_z,
                            [(t, z, 1) for t, z in zip(home_times, home_z, strict=True)])
    assert [r.height_m for r in read_telemetry(path)] == pytest.approx(above_home, abs=1e-4)


def test_ulog_height_ignores_a_home_without_a_valid_local_position(tmp_path, caplog):
    path, _ = _ulog_heights(tmp_path, [-52.0, -52.0], [(19_000_000, 99.0, 0), (19_000_001, -12.0, 1)])
    assert [r.height_m for r in read_telemetry(path)] == pytest.approx([40.0, 40.0])
    path, _ = _ulog_heights(tmp_path, [-52.0, -52.0], [(19_000_000, 99.0, 0)])
    with caplog.at_level("WARNING"):
        assert [r.height_m for r in read_telemetry(path)] == pytest.approx([52.0, 52.0])
    assert "no home_position" in caplog.text and "EKF origin" in caplog.text


def test_ulog_without_home_position_gives_the_height_above_the_ekf_origin_and_says_so(tmp_path, caplog):
    path, _ = _ulog_heights(tmp_path, [-52.0, -53.0], None)
    with caplog.at_level("WARNING"):
        assert [r.height_m for r in read_telemetry(path)] == pytest.approx([52.0, 53.0])
    assert "heights.ulg: no home_position" in caplog.text


@pytest.mark.parametrize("receivers", [
    [("vehicle_gps_position", 0, False), ("vehicle_gps_position", 1, True)],  # receiver 0 without time output
    [("vehicle_gps_position", 1, True)],  # only instance 1 logged
    [("vehicle_gps_position", 0, False), ("sensor_gps", 1, True)],  # newer PX4: the receivers in sensor_gps
])
def test_ulog_takes_utc_from_any_gps_instance_that_has_it(tmp_path, receivers):
    """Only vehicle_gps_position instance 0 was read: with its time_utc_usec 0 the records fell back to seconds
    since boot without a word, and a UNIX --telemetry-offset-s left every frame without a pose."""
    path, flight = _ulog_flight(tmp_path, gps=False, gps_receivers=receivers)
    assert [r.t for r in read_telemetry(path)] == pytest.approx([f.t for f in flight], abs=1e-5)


def test_ulog_without_gps_utc_warns_that_the_records_are_on_the_boot_clock(tmp_path, caplog):
    path, _ = _ulog_flight(tmp_path, gps=False)
    with caplog.at_level("WARNING"):
        records = read_telemetry(path)
    assert records[0].t == pytest.approx(BOOT_MS0 / 1000, abs=1e-6)
    assert "flight.ulg: no GPS UTC time" in caplog.text and "seconds since boot" in caplog.text


def _damaged(path, at: float, garbage: bytes = bytes(range(7, 40))):
    """The log with `garbage` (a corrupt SD sector) inserted at the fraction `at` of its length."""
    data = path.read_bytes()
    cut = int(len(data) * at)
    damaged = path.with_name("damaged.ulg")
    damaged.write_bytes(data[:cut] + garbage + data[cut:])
    return damaged


def test_ulog_with_garbage_mid_file_and_no_sync_marker_warns_that_the_records_stop_early(tmp_path, caplog):
    """pyulog trusts the garbage's message length, drops the rest of the file and reports no corruption: the
    reader gave 13 of 30 records without a word. It cannot resync without a sync marker; the reader says so."""
    path, flight = _ulog_flight(tmp_path, n=30)
    with caplog.at_level("WARNING"):
        records = read_telemetry(_damaged(path, 0.5))
    assert len(records) < len(flight)
    assert "damaged.ulg: pyulog stopped reading" in caplog.text
    assert f"the records end at {records[-1].t - T0 + BOOT_MS0 / 1000:.1f} s after boot" in caplog.text


def test_ulog_with_sync_markers_recovers_past_garbage_and_warns(tmp_path, caplog):
    """PX4's sync messages let pyulog skip corrupt data: the records after it are read, and the skip is reported."""
    path, flight = _ulog_flight(tmp_path, n=40, sync_every=5)
    with caplog.at_level("WARNING"):
        records = read_telemetry(_damaged(path, 0.5))
    assert len(records) >= len(flight) - 3 and records[-1].t == pytest.approx(flight[-1].t, abs=1e-5)
    assert "damaged.ulg: pyulog found corrupt data" in caplog.text


def test_ulog_cut_mid_message_keeps_the_records_before_and_says_so(tmp_path, caplog):
    path, flight = _ulog_flight(tmp_path)
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(path.read_bytes()[:-7])
    with caplog.at_level("WARNING"):
        records = read_telemetry(cut)
    assert len(records) == len(flight)
    assert "cut.ulg: pyulog stopped reading" in caplog.text


def test_ulog_positions_ending_long_before_the_log_are_reported(tmp_path, caplog):
    path, flight = _ulog_flight(tmp_path)
    from pyulog import ULog

    ulog = ULog(str(path))
    position = next(d for d in ulog.data_list if d.name == "vehicle_global_position")
    position.data = {k: v[:4] for k, v in position.data.items()}  # GPS lost after 0.3 s; the attitude runs to 6.1 s
    for dataset in ulog.data_list:
        if dataset.name == "vehicle_attitude":
            dataset.data["timestamp"][-1] += 5_000_000
    buffer = io.BytesIO()
    ulog.write_ulog(buffer)
    (tmp_path / "early.ulg").write_bytes(buffer.getvalue())
    with caplog.at_level("WARNING"):
        assert len(read_telemetry(tmp_path / "early.ulg")) == 4
    assert "the positions (vehicle_global_position) end at 20.3 s after boot, 5.8 s before" in caplog.text


def test_a_clean_ulog_reads_without_damage_warnings(tmp_path, caplog):
    path, _ = _ulog_flight(tmp_path, sync_every=3)
    with caplog.at_level("WARNING"):
        read_telemetry(path)
    assert "pyulog" not in caplog.text and "positions (vehicle_global_position) end" not in caplog.text


def test_ulog_pyulogs_own_warnings_go_to_the_log_not_stdout(tmp_path, caplog, capsys):
    """pyulog prints what it finds to stdout, where a CLI writes its results: the reader logs it instead."""
    path, flight = _ulog_flight(tmp_path)
    unknown_id = struct.pack("<HBH", 5, ord("D"), 99) + b"abc"  # a data message of a topic never subscribed
    with caplog.at_level("WARNING"):
        assert len(read_telemetry(_damaged(path, 1.0, unknown_id))) == len(flight)  # at a message boundary
    assert capsys.readouterr().out == ""
    assert "damaged.ulg: pyulog: Warning: no subscription found for message id 99" in caplog.text
    assert "damaged.ulg: pyulog found corrupt data" in caplog.text

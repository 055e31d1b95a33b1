"""Flight-controller logs as real autopilots write them (shared.telemetry.mavlink, shared.telemetry.ulog): another
drone's gimbal heard before the vehicle's first position, a companion computer's ATTITUDE on its own boot clock,
NaN fields MAVLink calls invalid, PX4's own servo gimbal whose flags say "yaw lock" over vehicle-relative angles.
Each failed before (a helper's audit, proof scripts in the commit's note)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.telemetry import read_telemetry
from shared.telemetry.mavlink import MavlinkAssembler
from tests.shared.mavlink_writer import euler_to_quaternion, ulog_bytes, write_tlog

pytest.importorskip("pymavlink")
T0 = 1_700_000_000.0


def _link(system: int = 1, component: int = 1):
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None, srcSystem=system, srcComponent=component)


def _position(mav, boot_ms: int, lat: float = 47.0, heading: float = 30.0):
    return mav.global_position_int_encode(boot_ms, int(lat * 1e7), int(8.0 * 1e7), 450_000, 50_000, 0, 0, 0,
                                          int(heading * 100) % 36000)


def test_another_drones_gimbal_heard_before_the_vehicles_first_position_is_not_the_vehicles():
    """Live, without --mavlink-system-id: drone 2's gimbal (30 deg down) came first and stood for drone 1's (nadir)
    the whole flight, drone 1's own one ignored as 'a second gimbal'."""
    assembler = MavlinkAssembler()
    down30 = {"flags": 4 | 8 | 32, "q": euler_to_quaternion(0, -30, 0), "gimbal_device_id": 1}
    nadir = {"flags": 4 | 8 | 32, "q": euler_to_quaternion(0, -90, 0), "gimbal_device_id": 0}
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", down30, 2, 1)
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", nadir, 1, 154)  # the vehicle's own, before its first position
    position = {"time_boot_ms": 60_000, "lat": 470000000, "lon": 80000000, "relative_alt": 50_000, "vx": 0, "vy": 0,
                "hdg": 3000}
    first = assembler.add("GLOBAL_POSITION_INT", position, 1, 1)
    assert first is not None and first.pitch_deg == pytest.approx(90.0)  # replayed: its own gimbal from the start
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", down30, 2, 1)
    later = assembler.add("GLOBAL_POSITION_INT", {**position, "time_boot_ms": 60_100}, 1, 1)
    assert later.pitch_deg == pytest.approx(90.0) and assembler.gimbal_used == "gimbal component 154"
    assert assembler.gimbals_ignored == {}


def test_a_companion_computers_attitude_on_its_own_clock_does_not_steer_the_heading(tmp_path):
    """The log starts before the GPS fix; component 191 sends ATTITUDE stamped with its own boot clock: it was taken
    while the autopilot component was unknown, and 600 of 900 headings read 282 deg where all are 30."""
    autopilot, companion = _link(1, 1), _link(1, 191)
    packets = []
    for i in range(300):
        boot, t = 10_000 + i * 100, T0 + 0.1 * i
        packets.append((t, autopilot.attitude_encode(boot, 0, 0, math.radians(30), 0, 0, 0).pack(autopilot)))
        packets.append((t, companion.attitude_encode(boot + 9_050, 0, 0, math.radians(-150), 0, 0, 0).pack(companion)))
        if i >= 100:  # the GPS fix
            packets.append((t, _position(autopilot, boot + 30, lat=47 + i * 1e-6).pack(autopilot)))
    records = read_telemetry(write_tlog(tmp_path / "fix_late.tlog", packets))
    assert len(records) == 200
    assert max(abs((r.heading_deg - 30.0 + 180.0) % 360.0 - 180.0) for r in records) < 1e-3


@pytest.mark.parametrize(("roll", "yaw", "yaw_absolute"), [(math.nan, 10.0, 40.0), (0.0, math.nan, math.nan)])
def test_mount_orientation_fields_marked_invalid_do_not_abort_the_log(tmp_path, roll, yaw, yaw_absolute):
    """ardupilotmega.xml: NaN for invalid. One such message made read_tlog raise 'roll_deg must be finite'."""
    mav = _link()
    packets = []
    for i in range(20):
        boot, t = 60_000 + i * 200, T0 + 0.2 * i
        bad = i == 10
        packets += [(t, mav.system_time_encode(int(t * 1e6), boot).pack(mav)),
                    (t, mav.attitude_encode(boot, 0, 0, math.radians(30), 0, 0, 0).pack(mav)),
                    (t, mav.mount_orientation_encode(boot, roll if bad else 0.0, -60.0, yaw if bad else 10.0,
                                                     yaw_absolute if bad else 40.0).pack(mav)),
                    (t, _position(mav, boot + 10, lat=47 + i * 1e-5).pack(mav))]
    records = read_telemetry(write_tlog(tmp_path / "mount.tlog", packets))
    assert len(records) == 20
    assert all(r.pitch_deg == pytest.approx(60.0) and r.heading_deg == pytest.approx(40.0) for r in records)


_POSITION = [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt")]
_ATTITUDE = [("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)]


def _ulog(path: Path, gimbal_rows: list[tuple], fields: list[tuple[str, str]], vehicle_yaw: float) -> Path:
    positions = [(10_000_000 + i * 100_000, 47.0 + i * 1e-5, 8.0, 500.0) for i in range(len(gimbal_rows))]
    attitudes = [(t, *euler_to_quaternion(0, 0, vehicle_yaw)) for t, *_ in positions]
    path.write_bytes(ulog_bytes({"vehicle_global_position": (_POSITION, positions),
                                 "vehicle_attitude": (_ATTITUDE, attitudes),
                                 "gimbal_device_attitude_status": (fields, gimbal_rows)}))
    return path


def test_a_nan_gimbal_quaternion_in_a_ulog_is_no_reading(tmp_path):
    """PX4 copies a MAVLink gimbal's status into the topic; one NaN quaternion made read_ulog raise."""
    fields = [("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)] + [("uint32_t", "device_flags")]
    rows = [(10_000_005 + i * 100_000, *([math.nan] * 4 if i == 25 else euler_to_quaternion(0, -60, 10)), 32)
            for i in range(50)]
    records = read_telemetry(_ulog(tmp_path / "nan.ulg", rows, fields, vehicle_yaw=30.0))
    assert len(records) == 50
    assert all(r.pitch_deg == pytest.approx(60.0, abs=1e-3) for r in records)
    assert all(r.heading_deg == pytest.approx(40.0, abs=1e-3) for r in records)  # 30 + 10 in the vehicle frame


def test_px4s_own_servo_gimbal_is_read_relative_to_the_vehicle(tmp_path):
    """PX4's gimbal module publishes a servo (RC/AUX) gimbal with flags NEUTRAL | ROLL | PITCH | YAW lock (30)
    whatever its mode and the servo outputs' angles, relative to the vehicle (gimbal/output_rc.cpp): read as earth-
    frame, a camera looking forward on a vehicle flying east headed north."""
    fields = ([("uint64_t", "timestamp")] + [("float", f"q[{i}]") for i in range(4)]
              + [("uint32_t", "device_flags"), ("uint8_t", "received_from_mavlink")])
    servo = [(10_000_005 + i * 100_000, *euler_to_quaternion(0, -45, 0), 30, 0) for i in range(50)]
    records = read_telemetry(_ulog(tmp_path / "servo.ulg", servo, fields, vehicle_yaw=90.0))
    assert {round(r.heading_deg, 3) for r in records} == {90.0}
    assert {round(r.pitch_deg, 3) for r in records} == {45.0}
    # a MAVLink gimbal device's status (received_from_mavlink) with yaw lock stays in the earth frame
    device = [(t, *q, 30, 1) for t, *q, _flags, _from in servo]
    assert {round(r.heading_deg, 3) for r in read_telemetry(_ulog(tmp_path / "dev.ulg", device, fields, 90.0))} == {0.0}


def test_px4s_servo_gimbal_status_sent_by_the_autopilot_is_vehicle_relative_in_a_tlog_too():
    assembler = MavlinkAssembler(1, component_id=1)
    assembler.add("ATTITUDE", {"time_boot_ms": 999, "yaw": math.radians(90.0)}, 1, 1)
    status = {"flags": 30, "q": euler_to_quaternion(0, -45, 0), "gimbal_device_id": 0}
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", status, 1, 1)  # from the autopilot itself: PX4's servo output
    position = {"time_boot_ms": 1000, "lat": 470000000, "lon": 80000000, "relative_alt": 50_000, "vx": 0, "vy": 0,
                "hdg": 9000}
    assert assembler.add("GLOBAL_POSITION_INT", position, 1, 1).heading_deg == pytest.approx(90.0)
    device = MavlinkAssembler(1, component_id=1)  # a gimbal device of its own (component 154): its flags stand
    device.add("GIMBAL_DEVICE_ATTITUDE_STATUS", status, 1, 154)
    assert device.add("GLOBAL_POSITION_INT", position, 1, 1).heading_deg == pytest.approx(0.0)


def test_the_vehicles_early_gimbal_and_field_of_view_outlast_a_burst_of_attitudes():
    """Kept as the last 32 messages of any kind, a gimbal status and a CAMERA_FOV_STATUS were pushed out by 0.7 s of
    50 Hz ATTITUDE before the first position (the third read): the latest of each kind and sender now."""
    assembler = MavlinkAssembler()
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", {"flags": 4 | 8 | 32, "q": euler_to_quaternion(0, -60, 0),
                                                     "gimbal_device_id": 0}, 1, 154)
    assembler.add("CAMERA_FOV_STATUS", {"hfov": 60.0, "camera_device_id": 0}, 1, 100)
    for k in range(35):
        assembler.add("ATTITUDE", {"time_boot_ms": 59_300 + 20 * k, "yaw": math.radians(30.0)}, 1, 1)
    position = {"time_boot_ms": 60_000, "lat": 470000000, "lon": 80000000, "relative_alt": 50_000, "vx": 0, "vy": 0,
                "hdg": 3000}
    sample = assembler.add("GLOBAL_POSITION_INT", position, 1, 1)
    assert sample.pitch_deg == pytest.approx(60.0) and sample.hfov_deg == pytest.approx(60.0)
    assert sample.heading_deg == pytest.approx(30.0)


def test_live_a_gimbal_that_stops_reporting_is_not_carried_on():
    """Live (the assembler without keep_attitudes, as agent.mavlink_feed runs it): a gimbal silent after 2 s was held
    for the rest of the flight (a log read whole interpolates and bounds it: shared.telemetry.gimbal_track)."""
    assembler = MavlinkAssembler(1, component_id=1)
    down45 = {"flags": 16 | 64, "q": euler_to_quaternion(0, -45, 100), "gimbal_device_id": 0}
    out = []
    for i in range(60):  # 10 Hz for 6 s; the gimbal reports for the first 2 s only
        rx, boot = T0 + 0.1 * i, 60_000 + 100 * i
        assembler.add("ATTITUDE", {"time_boot_ms": boot, "roll": 0.0, "pitch": 0.0, "yaw": math.radians(30)}, 1, 1, rx)
        if i < 20:
            assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", down45, 1, 154, rx)
        position = {"time_boot_ms": boot, "lat": 470000000, "lon": 80000000, "relative_alt": 50_000, "vx": 0,
                    "vy": 0, "hdg": 3000}
        out.append(assembler.add("GLOBAL_POSITION_INT", position, 1, 1, rx))
    # carried 1 s (3 intervals of 0.1 s, at least 1 s) past the last reading at 1.9 s, then not
    assert all(s.pitch_deg == pytest.approx(45.0) and s.heading_deg == pytest.approx(100.0) for s in out[:30])
    assert all(s.pitch_deg is None and s.heading_deg == pytest.approx(30.0) for s in out[30:])
    assert assembler.gimbal_stale == 30
    # it reports again: taken again at once
    assembler.add("GIMBAL_DEVICE_ATTITUDE_STATUS", down45, 1, 154, T0 + 6.0)
    again = assembler.add("GLOBAL_POSITION_INT", {**position, "time_boot_ms": 66_000}, 1, 1, T0 + 6.0)
    assert again is not None and again.pitch_deg == pytest.approx(45.0)
    # without receive times, or with fewer than 3 readings to judge the interval by, it stands down
    quiet = MavlinkAssembler(1, component_id=1)
    quiet.add("GIMBAL_DEVICE_ATTITUDE_STATUS", down45, 1, 154, T0)
    late = quiet.add("GLOBAL_POSITION_INT", position, 1, 1, T0 + 10.0)
    assert late is not None and late.pitch_deg == pytest.approx(45.0) and quiet.gimbal_stale == 0


_LOCAL = [("uint64_t", "timestamp"), ("float", "z"), ("float", "vx"), ("float", "vy")]
_GPS = [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from([("vehicle_global_position", f) for _, f in _POSITION]
                       + [("vehicle_local_position", f) for _, f in _LOCAL]
                       + [("vehicle_attitude", f) for _, f in _ATTITUDE]
                       + [("gimbal_device_attitude_status", f) for _, f in _ATTITUDE]
                       + [("vehicle_gps_position", f) for _, f in _GPS]))
def test_a_ulog_field_name_damaged_in_its_format_is_refused_or_not_used_never_a_key_error(tmp_path, caplog,
                                                                                         topic_field):
    """Fuzzing (1 Dec 2026): a byte flipped in a topic's format definition ('timgstamp', 'lPt', 'q[1\\0') renamed the
    field, and read_ulog raised KeyError (a traceback from --telemetry F.ulg). Now the position topic without lat,
    lon or timestamp is a ValueError naming the field, any other topic is not used, with a warning. A topic without
    its timestamp makes pyulog stop reading without a word (11 of 12 positions lost): now a warning says so."""
    topic, field = topic_field
    rows = [(10_000_000 + i * 100_000, 47.0 + i * 1e-5, 8.0, 500.0) for i in range(12)]
    topics = {"vehicle_global_position": (_POSITION, rows),
              "vehicle_local_position": (_LOCAL, [(t + 50, -30.0, 0.0, 0.0) for t, *_ in rows]),
              "vehicle_attitude": (_ATTITUDE, [(t, *euler_to_quaternion(0, 0, 30)) for t, *_ in rows]),
              "gimbal_device_attitude_status": (_ATTITUDE, [(t, *euler_to_quaternion(0, -60, 10)) for t, *_ in rows]),
              "vehicle_gps_position": (_GPS, [(t, int(T0 * 1e6) + t) for t, *_ in rows])}
    definition = f"{topic}:".encode() + b"".join(f"{t} {f};".encode() for t, f in topics[topic][0])
    data = ulog_bytes(topics)
    assert data.count(definition) == 1
    damaged = definition.replace(f" {field};".encode(), f" {field[:-1]}\x01;".encode())
    path = tmp_path / "damaged.ulg"
    path.write_bytes(data.replace(definition, damaged))
    if topic == "vehicle_global_position" and field != "alt":
        with pytest.raises(ValueError, match=f"vehicle_global_position has no field '{re.escape(field)}'"):
            read_telemetry(path)
    else:  # pyulog itself stops at a data message of a topic without its timestamp: the records before it, said
        caplog.clear()
        records = read_telemetry(path)
        assert len(records) == 12 or (records and "pyulog stopped reading" in caplog.text)

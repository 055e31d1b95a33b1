"""MISB ST 0601 KLV telemetry (shared.telemetry.klv, klv_packets, klv_sample, mpegts): packets written by the
test's own encoder from the standard round-trip within the mappings' resolution, malformed packets are counted
and skipped, transport streams (our multiplexer and FFmpeg's via PyAV) give the samples their video time."""

from __future__ import annotations

import io
import math
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.geo import Pose
from shared.telemetry import (
    KlvSample,
    camera_angles_deg,
    interpolate,
    parse_klv_report,
    read_klv_report,
    read_telemetry,
)
from shared.telemetry.klv_packets import TruncatedKlv, checksum16, read_ber_length, read_ber_oid
from shared.telemetry.mpegts import TsStats, iter_metadata_units, mpeg_crc32, strip_au_cells
from tests.shared.klv_writer import (
    FULL_FIELDS,
    KEY,
    SPEC,
    au_cells,
    ber_length,
    ber_oid,
    crc32_mpeg,
    item,
    packet,
    resolution,
    standard_checksum,
    write_ts,
    write_ts_with_pyav,
)

T0 = 1_717_236_000.0  # 2024-06-01 10:00 UTC
FULL = FULL_FIELDS  # heading 350 + 20, 45 deg down, 512 m above MSL over ground at 472 m


def _flight(n: int, dt: float = 0.1) -> list[bytes]:
    return [packet(T0 + dt * i, {**FULL, "sensor_lat": 48.53 + 1e-5 * i}) for i in range(n)]


# ---- BER, checksum ---------------------------------------------------------------------------------------
@given(st.integers(0, 2**40))
def test_ber_length_round_trips_short_and_long_forms(n):
    encoded = ber_length(n) + b"rest"
    assert read_ber_length(encoded, 0) == (n, len(encoded) - 4)
    with pytest.raises(TruncatedKlv):
        read_ber_length(encoded[:len(encoded) - 5], 0)


def test_ber_length_rejects_the_indefinite_form_and_overlong_fields():
    with pytest.raises(ValueError, match="not a definite length"):
        read_ber_length(b"\x80\x00", 0)
    with pytest.raises(ValueError, match="not a definite length"):
        read_ber_length(b"\x89" + bytes(9), 0)


@given(st.integers(1, 2**28 - 1))
def test_ber_oid_round_trips(tag):
    encoded = ber_oid(tag)
    assert read_ber_oid(encoded + b"\x00", 0) == (tag, len(encoded))
    if len(encoded) > 1:
        with pytest.raises(TruncatedKlv):
            read_ber_oid(encoded[:-1], 0)


@given(st.binary(max_size=600))
def test_checksum_equals_the_standards_loop(data):
    assert checksum16(data) == standard_checksum(data)


# ---- decoding ----------------------------------------------------------------------------------------------
def test_published_example_values_decode_as_the_standard_states():
    # ST 0601's conversion examples: heading 0x71C2, latitude 0x5595B66D, longitude 0x5B5360C4, altitude 0xC221,
    # relative elevation 0x87F84B86, full-range pitch / roll 0xFF62E2F2 / 0x04D804DF
    raw = {5: "71C2", 13: "5595B66D", 14: "5B5360C4", 15: "C221", 19: "87F84B86", 90: "FF62E2F2", 91: "04D804DF"}
    extra = b"".join(item(tag, bytes.fromhex(value)) for tag, value in raw.items())
    (sample,) = parse_klv_report(packet(T0, extra=extra)).samples
    assert sample.platform_heading_deg == pytest.approx(159.9744, abs=1e-4)
    assert sample.sensor_lat == pytest.approx(60.1768229669783, abs=1e-9)
    assert sample.sensor_lon == pytest.approx(128.426759042045, abs=1e-9)
    assert sample.sensor_alt_msl_m == pytest.approx(14190.72, abs=0.01)
    assert sample.sensor_rel_elevation_deg == pytest.approx(-168.792324833941, abs=1e-9)
    assert sample.platform_pitch_deg == pytest.approx(-0.43152510208614414, abs=1e-12)
    assert sample.platform_roll_deg == pytest.approx(3.4058139815022304, abs=1e-12)
    # the short items' examples (0xFD3D -> -0.4315251, 0x08B8 -> 3.405814) were printed with 2**16 - 1 as the
    # divisor; the formula (40 / 65534, 100 / 65534) gives -0.4315317 and 3.4058657: within half a step of them
    short = parse_klv_report(packet(T0, extra=item(6, bytes.fromhex("FD3D")) + item(7, bytes.fromhex("08B8"))))
    assert short.samples[0].platform_pitch_deg == pytest.approx(-707 * 40 / 65534, abs=1e-12)
    assert short.samples[0].platform_pitch_deg == pytest.approx(-0.4315251, abs=resolution("platform_pitch_deg") / 2)
    assert short.samples[0].platform_roll_deg == pytest.approx(3.405814, abs=resolution("platform_roll_deg") / 2)


_VALUES = {name: st.floats(lo, hi) for name, (_tag, _size, lo, hi, _signed) in SPEC.items()
           if not name.endswith("_full_deg")}


@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(t=st.floats(0.0, 4e9), values=st.fixed_dictionaries({}, optional=_VALUES), long_length=st.booleans())
def test_values_round_trip_within_the_mapping_resolution(t, values, long_length):
    report = parse_klv_report(packet(t, values, long_length=long_length))
    assert (report.packets, report.decoded, report.skipped_bytes) == (1, 1, 0)
    (sample,) = report.samples
    assert sample.t == pytest.approx(t, abs=1e-6)
    for name, value in values.items():
        assert getattr(sample, name) == pytest.approx(value, abs=resolution(name) / 2 + 1e-9), name
    absent = set(_VALUES) - set(values)
    assert all(getattr(sample, name) is None for name in absent)


@given(pitch=st.floats(-90, 90), roll=st.floats(-90, 90))
def test_full_range_platform_pitch_and_roll_win_over_the_short_items(pitch, roll):
    (sample,) = parse_klv_report(packet(T0, {"platform_pitch_deg": 1.0, "platform_roll_deg": 2.0,
                                             "platform_pitch_full_deg": pitch, "platform_roll_full_deg": roll})).samples
    assert sample.platform_pitch_deg == pytest.approx(pitch, abs=resolution("platform_pitch_full_deg"))
    assert sample.platform_roll_deg == pytest.approx(roll, abs=resolution("platform_roll_full_deg"))


def test_records_carry_position_camera_angles_height_and_velocity():
    data = packet(T0, {**FULL, "vel_north_mps": 3.0, "vel_east_mps": -4.0})
    report = parse_klv_report(data)
    (rec,) = report.records
    assert rec.t == pytest.approx(T0, abs=1e-6)
    assert (rec.lat, rec.lon) == pytest.approx((48.53, 9.06), abs=1e-7)
    assert rec.heading_deg == pytest.approx(10.0, abs=0.01)  # 350 + 20; the heading's step is 0.0055 deg
    assert rec.pitch_deg == pytest.approx(45.0, abs=1e-6)
    assert rec.height_m == pytest.approx(40.0, abs=0.31)  # 512 - 472, each to 0.3 m
    assert rec.vel_en_mps == pytest.approx((-4.0, 3.0), abs=0.01) and rec.speed_mps == pytest.approx(5.0, abs=0.01)
    assert report.samples[0].hfov_deg == pytest.approx(60.0, abs=0.003)
    assert rec.hfov_deg == pytest.approx(60.0, abs=0.003)  # a zoom lens's focal length (agent.field_of_view)


@pytest.mark.parametrize("hfov", [0.0, 180.0])
def test_a_field_of_view_no_pinhole_camera_has_is_left_out(hfov):
    (rec,) = parse_klv_report(packet(T0, {**FULL, "hfov_deg": hfov})).records
    assert rec.hfov_deg is None and rec.pitch_deg == pytest.approx(45.0, abs=1e-6)


def test_height_needs_the_frame_centre_or_an_offset_and_falls_back_to_ellipsoid_heights():
    no_ground = {k: v for k, v in FULL.items() if k != "frame_center_elevation_m"}
    report = parse_klv_report(packet(T0, no_ground))
    assert report.records[0].height_m is None
    assert (report.heights_missing, report.heights_above_sea_level_only) == (1, 1)
    offset = parse_klv_report(packet(T0, no_ground), height_offset_m=-480.0)
    assert offset.records[0].height_m == pytest.approx(32.0, abs=0.31)
    ellipsoid = parse_klv_report(packet(T0, {**no_ground, "sensor_hae_m": 560.0, "frame_center_hae_m": 530.0}))
    assert ellipsoid.records[0].height_m == pytest.approx(30.0, abs=0.61)


def test_an_ellipsoid_height_only_stream_takes_the_height_offset():
    """A stream with the sensor's height above the ellipsoid (tag 75) and no altitude above MSL (tag 15):
    --height-offset-m was ignored and the run refused for want of a height."""
    hae_only = {k: v for k, v in FULL.items() if k not in ("sensor_alt_msl_m", "frame_center_elevation_m")}
    report = parse_klv_report(packet(T0, {**hae_only, "sensor_hae_m": 560.0}), height_offset_m=-520.0)
    assert report.records[0].height_m == pytest.approx(40.0, abs=0.31)


@pytest.mark.parametrize("which", ["platform_pitch_deg", "platform_roll_deg"])
def test_a_platform_attitude_out_of_range_gives_no_camera_angles_not_a_level_platform(which):
    """A 60 deg bank or a 25 deg dive: tags 6 / 7 carry "out of range" (0x8000). It was read as 0 (level): the
    camera 60 deg off, silently. Now the record has no angles, counted; a full-range tag 90 / 91, sent in the packet
    or held from a recent one, still stands."""
    report = parse_klv_report(packet(T0, {**FULL, which: None}))
    (rec,) = report.records
    assert rec.pitch_deg is None and rec.heading_deg is None
    assert report.problems() == {"attitude_out_of_range": 1}
    full = which.replace("_deg", "_full_deg")
    held = parse_klv_report(packet(T0, {**FULL, full: 35.0}) + packet(T0 + 0.1, {**FULL, which: None}))
    assert [r.pitch_deg is not None for r in held.records] == [True, True]
    assert getattr(held.samples[1], which) == pytest.approx(35.0, abs=1e-3)
    assert held.problems() == {}


# ---- malformed input: counted and skipped ------------------------------------------------------------------
def test_bad_checksum_packet_is_counted_and_skipped():
    good = _flight(3)
    bad = bytearray(good[1])
    bad[25] ^= 0x01
    report = parse_klv_report(good[0] + bytes(bad) + good[2])
    assert (report.packets, report.decoded, report.bad_checksum) == (3, 2, 1)
    assert [round(r.t - T0, 3) for r in report.records] == [0.0, 0.2]
    assert report.skipped_bytes == len(bad)


def _without_key_checksum(data: bytes) -> bytes:
    """The packet with its checksum summed from the length on, the key left out (an encoder's known bug)."""
    return data[:-2] + standard_checksum(data[len(KEY):-2]).to_bytes(2, "big")


@pytest.mark.parametrize("long_length", [False, True])
def test_a_checksum_that_leaves_out_the_key_is_read_and_said(tmp_path, caplog, long_length):
    """Some encoders sum from the length on: every packet was rejected as a bad checksum and the file refused. The
    sum still checks the rest of each packet, so such packets are read, counted, and said at info level; a byte
    changed in one of them is still caught."""
    packets = [_without_key_checksum(packet(T0 + 0.1 * i, FULL, long_length=long_length)) for i in range(4)]
    broken = bytearray(packets[2])
    broken[25] ^= 0x01
    path = tmp_path / "encoder.klv"
    path.write_bytes(packets[0] + packets[1] + bytes(broken) + packets[3])
    with caplog.at_level("INFO", logger="shared.telemetry.klv"):
        report = read_klv_report(path)
    assert (report.decoded, report.checksum_without_key, report.bad_checksum) == (3, 3, 1)
    assert [round(r.t - T0, 3) for r in report.records] == [0.0, 0.1, 0.3]
    assert "3 of 3 packets' checksums leave out the 16-byte key" in caplog.text
    assert parse_klv_report(b"".join(_flight(3))).checksum_without_key == 0  # standard packets: not counted


def test_truncated_packets_are_counted_in_the_middle_and_at_the_end():
    good = _flight(3)
    report = parse_klv_report(good[0] + good[1][:40] + good[2] + good[1][:30])
    assert (report.packets, report.decoded, report.truncated, report.bad_checksum) == (4, 2, 2, 0)
    assert [round(r.t - T0, 3) for r in report.records] == [0.0, 0.2]


def test_missing_checksum_and_missing_time_are_counted():
    report = parse_klv_report(packet(T0, FULL, checksum=False) + packet(None, FULL) + packet(T0 + 1, FULL))
    assert (report.missing_checksum, report.no_time, report.decoded, len(report.records)) == (1, 1, 2, 1)


def test_unknown_tags_are_counted_and_the_rest_decoded():
    """Items the standard defines and this reader does not use (mission id 3, slant range 21, target width 22) are
    not reported on every run; a security set (48) and tags it does not know are."""
    extra = (item(3, b"MISSION-7") + item(21, b"\x00\x00\x10\x00") + item(22, b"\x00\x10") + item(200, b"\x01\x02\x03")
             + item(48, item(1, b"\x01")))  # 200: 2-byte BER-OID
    report = parse_klv_report(packet(T0, FULL, extra=extra))
    assert report.unknown_tags == {48: 1, 200: 1}
    assert report.records[0].pitch_deg == pytest.approx(45.0, abs=1e-6)


def test_wrong_item_size_and_broken_lengths_inside_a_checked_packet_are_counted():
    no_heading = {k: v for k, v in FULL.items() if k != "platform_heading_deg"}
    report = parse_klv_report(packet(T0, no_heading, extra=item(5, b"\x00\x01\x02")))  # heading is 2 bytes
    assert report.bad_items == 1 and report.records[0].heading_deg is None
    assert report.records[0].pitch_deg == pytest.approx(45.0, abs=1e-6)  # the rest of the packet is used
    overrun = packet(T0, FULL, extra=b"\x05\x7f\x00")  # an item claiming 127 bytes runs past the checksum
    assert (parse_klv_report(overrun).malformed, parse_klv_report(overrun).decoded) == (1, 0)


@settings(max_examples=40)
@given(garbage=st.lists(st.binary(max_size=80).filter(lambda g: KEY[:4] not in g), min_size=4, max_size=4))
def test_garbage_between_packets_is_skipped(garbage):
    good = _flight(3)
    data = garbage[0] + good[0] + garbage[1] + good[1] + garbage[2] + good[2] + garbage[3]
    report = parse_klv_report(data)
    assert (report.decoded, len(report.records)) == (3, 3)
    assert report.skipped_bytes == sum(map(len, garbage))


@settings(max_examples=60)
@given(st.binary(max_size=400), st.integers(0, 3))
def test_arbitrary_bytes_never_crash_the_decoder(noise, where):
    good = _flight(2)
    parts = [good[0], noise, good[1]]
    parts.insert(where % 3, KEY + noise[:5])  # a key followed by anything
    report = parse_klv_report(b"".join(parts))
    assert report.decoded >= 2 and report.packets >= 3


def test_items_left_out_are_held_for_a_while_and_dropped_when_sent_as_unknown():
    def position(i: int) -> dict[str, float | None]:
        return {"sensor_lat": 48.53 + 1e-3 * i, "sensor_lon": 9.06}

    data = (packet(T0, FULL)
            + packet(T0 + 1.0, position(1))  # only the position changed
            + packet(T0 + 7.0, {**position(2), "sensor_rel_elevation_deg": -30.0})  # 7 s on: past the 5 s hold
            + packet(T0 + 7.5, {**position(3), "sensor_rel_elevation_deg": None})  # the gimbal reports "unknown"
            + packet(T0 + 8.0, position(4)))
    first, held, stale, unknown, after = parse_klv_report(data).samples
    assert held.platform_heading_deg == pytest.approx(350.0, abs=0.01) and held.sensor_lat == pytest.approx(48.531)
    assert stale.platform_heading_deg is None and stale.sensor_lat == pytest.approx(48.532)
    assert stale.sensor_rel_elevation_deg == pytest.approx(-30.0)
    assert unknown.sensor_rel_elevation_deg is None and after.sensor_rel_elevation_deg is None
    no_hold = parse_klv_report(data, max_hold_s=0.0).samples
    assert no_hold[1].platform_heading_deg is None
    with pytest.raises(ValueError, match="max_hold_s"):
        parse_klv_report(data, max_hold_s=-1.0)


def test_error_value_position_gives_no_record():
    report = parse_klv_report(packet(T0, {**FULL, "sensor_lat": None}) + packet(T0 + 0.1, FULL))
    assert report.no_position == 1 and len(report.records) == 1


# ---- camera angles -------------------------------------------------------------------------------------------
@given(heading=st.floats(0, 360), azimuth=st.floats(0, 360), elevation=st.floats(-90, 0))
def test_level_platform_gives_heading_plus_azimuth_and_minus_elevation(heading, azimuth, elevation):
    cam_heading, depression, roll = camera_angles_deg(heading, 0.0, 0.0, azimuth, elevation)
    assert depression == pytest.approx(-elevation, abs=1e-9)
    if depression < 89.999:
        assert math.cos(math.radians(cam_heading - heading - azimuth)) == pytest.approx(1.0, abs=1e-9)
        assert roll == pytest.approx(0.0, abs=1e-7)


def test_bank_and_pitch_move_the_line_of_sight():
    # right wing down 30 deg, camera looking right along the wing: 30 deg below the horizon, to the east
    heading, depression, _ = camera_angles_deg(0.0, 0.0, 30.0, 90.0, 0.0)
    assert (heading, depression) == pytest.approx((90.0, 30.0))
    # nose 10 deg up, camera 40 deg down from the nose: 30 deg below the horizon
    assert camera_angles_deg(0.0, 10.0, 0.0, 0.0, -40.0)[1] == pytest.approx(30.0)
    # straight down from the belly: nose up swings the view forward, nose down past nadir (top still forward)
    assert camera_angles_deg(45.0, 0.5, 0.0, 0.0, -90.0) == pytest.approx((45.0, 89.5, 0.0), abs=1e-9)
    heading, depression, roll = camera_angles_deg(45.0, -0.5, 0.0, 0.0, -90.0)
    assert (heading, depression, roll) == pytest.approx((45.0, 90.5, 0.0), abs=1e-9)
    (rec,) = parse_klv_report(packet(T0, {**FULL, "platform_heading_deg": 45.0, "sensor_rel_azimuth_deg": 0.0,
                                          "platform_pitch_deg": -0.5, "sensor_rel_elevation_deg": -90.0})).records
    assert (rec.pitch_deg, rec.heading_deg, rec.roll_deg) == pytest.approx((90.0, 45.0, 0.0), abs=0.01)  # clamped


def test_camera_looking_up_has_no_pitch_and_is_counted():
    report = parse_klv_report(packet(T0, {**FULL, "sensor_rel_elevation_deg": 20.0}))
    assert report.records[0].pitch_deg is None and report.no_pitch == 1


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


@settings(max_examples=80)
@given(st.tuples(st.floats(0, 360), st.floats(-20, 20), st.floats(-50, 50), st.floats(0, 360), st.floats(-120, 10),
                 st.floats(-30, 30)))
def test_composed_angles_give_the_pose_the_aircraft_and_gimbal_define(angles):
    heading, pitch, roll, azimuth, elevation, sensor_roll = angles
    cam_heading, depression, cam_roll = camera_angles_deg(heading, pitch, roll, azimuth, elevation, sensor_roll)
    if not (0.0 <= depression <= 90.0 and abs(cam_roll) <= 90.0):
        return  # not a pose shared.geo can hold (looking up, or past nadir): callers clamp or drop those
    # body axes (forward, right, down) in north-east-down: yaw about down, pitch about right, roll about forward
    platform = _rot(2, heading) @ _rot(1, pitch) @ _rot(0, roll)
    body = platform @ _rot(2, azimuth) @ _rot(1, elevation) @ _rot(0, sensor_roll)
    ned_to_enu = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    want = ned_to_enu @ body  # columns: forward, right, down in east-north-up
    pose = Pose(lat=48.5, lon=9.0, height_m=30.0, pitch_deg=depression, heading_deg=cam_heading, roll_deg=cam_roll)
    got = pose.R_world_from_cam  # columns: right, down, forward
    np.testing.assert_allclose(got, want[:, [1, 2, 0]], atol=1e-6)


# ---- transport streams -----------------------------------------------------------------------------------------
def test_crc32_mpeg_matches_a_bitwise_implementation():
    data = bytes(range(256)) * 3
    assert mpeg_crc32(data) == crc32_mpeg(data)
    assert mpeg_crc32(data + crc32_mpeg(data).to_bytes(4, "big")) == 0


def test_synchronous_metadata_with_au_cells_gets_video_time_from_the_pts(tmp_path):
    video0 = 900_000
    klv = [(video0 + 9_000 * i + 1_800, p) for i, p in enumerate(_flight(6))]  # 20 ms after each 0.1 s frame
    path = tmp_path / "flight.ts"
    path.write_bytes(write_ts(klv, video_pts=[video0 + 3_600, video0, video0 + 7_200]))  # B-frame order
    report = read_klv_report(path)
    assert report.ts is not None and report.ts.metadata_pids == [0x101] and report.ts.video_pid == 0x100
    assert report.ts.video_start_pts == video0
    assert [s.video_time_s for s in report.samples] == pytest.approx([0.02 + 0.1 * i for i in range(6)])
    assert report.video_start_t == pytest.approx(T0 - 0.02, abs=1e-6)
    assert (report.decoded, report.skipped_bytes, report.ts.pes, report.ts.pes_cut) == (6, 0, 6, 0)
    assert read_telemetry(path) == report.records


def test_strip_au_cells_keeps_payloads_without_cells_and_inconsistent_ones():
    packets = _flight(2)
    assert strip_au_cells(au_cells(packets)) == b"".join(packets)
    assert strip_au_cells(packets[0]) == packets[0]  # FFmpeg writes 0x15 streams without cells
    assert strip_au_cells(b"\x00\x01\xdf\x00\x50abc") == b"\x00\x01\xdf\x00\x50abc"


@pytest.mark.parametrize("kind", ["async-0x06", "sync-no-cells", "m2ts", "pts-wrap"])
def test_transport_stream_variants(tmp_path, kind):
    base = (1 << 33) - 18_000 if kind == "pts-wrap" else 0  # PTS wrap 0.2 s into the flight
    klv = [(base + 9_000 * i, p) for i, p in enumerate(_flight(5))]
    data = write_ts(klv, video_pts=[base], klv_stream_type=0x06 if kind == "async-0x06" else 0x15,
                    cells=kind != "sync-no-cells", m2ts=kind == "m2ts")
    path = tmp_path / ("f.m2ts" if kind == "m2ts" else "f.ts")
    path.write_bytes(data)
    report = read_klv_report(path)
    assert report.decoded == 5
    assert [s.video_time_s for s in report.samples] == pytest.approx([0.1 * i for i in range(5)])
    assert report.ts is not None and report.ts.packet_bytes == (192 if kind == "m2ts" else 188)


def test_large_packets_span_ts_packets_and_reading_in_small_chunks_gives_the_same(tmp_path):
    big = [packet(T0 + 0.1 * i, FULL, extra=item(3, bytes(400))) for i in range(150)]  # 3 TS packets each, 85 kB
    data = write_ts([(9_000 * i, p) for i, p in enumerate(big)], video_pts=[0])
    units = {}
    for chunk in (1 << 20, 377, 190):
        stats = TsStats()
        units[chunk] = list(iter_metadata_units(io.BytesIO(data), stats, chunk_bytes=chunk))
        assert stats.packets == len(data) // 188 and stats.sync_losses == 0
    assert units[1 << 20] == units[377] == units[190]
    assert [u.payload for u in units[190]] == big


def test_lost_ts_packets_and_sync_garbage_are_counted_and_skipped(tmp_path):
    klv = _flight(8)
    klv[5] = packet(T0 + 0.5, FULL, extra=item(3, bytes(400)))  # a PES over 3 TS packets
    data = write_ts([(9_000 * i, p) for i, p in enumerate(klv)], video_pts=[0])
    packets = [data[i:i + 188] for i in range(0, len(data), 188)]
    on_klv = [i for i, p in enumerate(packets) if ((p[1] & 0x1F) << 8 | p[2]) == 0x101]
    assert len(on_klv) == 10
    # packet 2 cut after 100 bytes: the reader takes 88 bytes of packet 3 as its end, then finds the sync again
    # 100 bytes on; the PES of KLV packets 2 and 3 are lost. The middle TS packet of KLV packet 5 is lost.
    packets[on_klv[2]] = packets[on_klv[2]][:100]
    del packets[on_klv[6]]
    path = tmp_path / "broken.ts"
    path.write_bytes(b"".join(packets))
    report = read_klv_report(path)
    assert report.ts is not None
    assert (report.ts.sync_losses, report.ts.skipped_bytes) == (1, 100)
    assert report.ts.continuity_errors == 2 and report.ts.pes_cut == 1
    assert (report.decoded, report.truncated) == (5, 1)
    assert [round(r.t - T0, 3) for r in report.records] == [0.0, 0.1, 0.4, 0.6, 0.7]


@pytest.mark.parametrize("chunk", [200, 377, 1 << 20])
def test_sync_search_longer_than_a_chunk_finishes(chunk):
    # regression: with small chunks, garbage longer than two packets after the first 64 kB (read at once to find
    # the packet size) kept the sync search from reading on: a hang
    big = [packet(T0 + 0.1 * i, FULL, extra=item(3, bytes(400))) for i in range(150)]
    data = write_ts([(9_000 * i, p) for i, p in enumerate(big)], video_pts=[0])
    cut = 188 * 400  # 75 kB in
    garbage = bytes(range(0x48, 0x48 + 100)) * 10  # 1000 bytes without a 0x47
    stats = TsStats()
    units = list(iter_metadata_units(io.BytesIO(data[:cut] + garbage + data[cut:]), stats, chunk_bytes=chunk))
    assert (stats.sync_losses, stats.skipped_bytes) == (1, 1000)
    assert parse_klv_report(b"".join(u.payload for u in units)).decoded == 150


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2_000), st.integers(0, 255)), max_size=30))
def test_corrupted_transport_streams_never_crash(flips):
    data = bytearray(write_ts([(9_000 * i, p) for i, p in enumerate(_flight(4))], video_pts=[0]))
    for at, value in flips:
        data[at % len(data)] = value
    stats = TsStats()
    try:
        units = list(iter_metadata_units(io.BytesIO(bytes(data)), stats))
    except ValueError as err:  # only when the start no longer looks like a transport stream
        assert "not an MPEG transport stream" in str(err)
        return
    report = parse_klv_report(b"".join(u.payload for u in units))
    assert report.decoded <= 4


def test_errors_name_the_file_and_the_reason(tmp_path):
    not_ts = tmp_path / "notes.ts"
    not_ts.write_bytes(b"hello" * 100)
    with pytest.raises(ValueError, match=r"notes\.ts: not an MPEG transport stream"):
        read_klv_report(not_ts)
    no_klv = tmp_path / "video-only.ts"
    from tests.shared.klv_writer import TsWriter, pes

    ts = TsWriter()
    ts.tables(klv_stream_type=0x06, klv_descriptor=struct.pack("BB4s", 0x05, 4, b"ID3 "))
    ts.unit(0x100, pes(0xE0, bytes(50), 0, bounded=False))
    no_klv.write_bytes(ts.bytes())
    with pytest.raises(ValueError, match=r"no KLV metadata stream in the transport stream \(stream types: "
                                         r"0x1b on PID 256, 0x06 on PID 257"):
        read_klv_report(no_klv)
    garbage = tmp_path / "g.klv"
    good = packet(T0, FULL)
    garbage.write_bytes(good[:-1] + bytes([good[-1] ^ 0xFF]))  # bad checksum only
    with pytest.raises(ValueError, match=r"g\.klv: no ST 0601 packet with a time stamp and a sensor position "
                                         r"\(1 UAS Datalink Local Set packets found: 1 bad checksum\)"):
        read_telemetry(garbage)
    with pytest.raises(ValueError, match="cannot read the file"):
        read_klv_report(tmp_path / "missing.klv")


def test_raw_klv_file_is_read_in_chunks(tmp_path, monkeypatch):
    import shared.telemetry.klv as klv_module

    monkeypatch.setattr(klv_module, "_CHUNK_BYTES", 50)  # every packet straddles chunks
    path = tmp_path / "flight.klv"
    path.write_bytes(b"\xff" * 7 + b"".join(_flight(10)) + b"junk")
    report = read_klv_report(path)
    assert (report.decoded, len(report.records), report.skipped_bytes) == (10, 10, 11)
    assert report.video_start_t is None and report.samples[0].video_time_s is None


# ---- a real muxer: FFmpeg through PyAV ---------------------------------------------------------------------
def test_ffmpeg_muxed_transport_stream_matches_pyavs_own_demuxer(tmp_path):
    av = pytest.importorskip("av")
    path = write_ts_with_pyav(tmp_path / "ffmpeg.ts", _flight(12), fps=10, klv_delay_frames=2)
    report = read_klv_report(path)
    assert report.ts is not None and report.ts.streams[report.ts.metadata_pids[0]] == 0x06  # KLVA, asynchronous
    assert (report.decoded, report.skipped_bytes) == (12, 0)
    with av.open(str(path)) as container:
        video, data = container.streams.video[0], container.streams.data[0]
        pts = [p.pts for p in container.demux(data) if p.size]
        start = video.start_time
    assert [s.video_time_s for s in report.samples] == pytest.approx([(p - start) / 90_000 for p in pts])
    assert [s.video_time_s for s in report.samples] == pytest.approx([0.1 * (i + 2) for i in range(12)], abs=1e-3)
    # packet i was stamped T0 + 0.1 i and shown with frame i + 2: the video starts 0.2 s before T0
    assert report.video_start_t == pytest.approx(T0 - 0.2, abs=1e-3)
    frames = interpolate(report.records, [report.video_start_t + 0.5])
    assert frames[0] is not None and frames[0].lat == pytest.approx(48.53 + 3e-5, abs=1e-7)


def test_klv_sample_validates_its_time():
    with pytest.raises(ValueError, match=r"KlvSample.t=nan must be a finite number of seconds"):
        KlvSample(t=math.nan)
    with pytest.raises(ValueError, match=r"KlvSample.video_time_s='1' must be a finite number"):
        KlvSample(t=0.0, video_time_s="1")  # type: ignore[arg-type]


# ---- several KLV streams in one transport stream --------------------------------------------------------
def _two_sensor_ts(order: list[bool], *, programs: bool = False) -> bytes:
    """EO (KLV PID 0x101, 45 deg down, 40 m up) and IR (PID 0x103, looking left, 20 deg down) packets, 30 each,
    written in `order` (True: the next EO packet). One program listing video 0x100, EO, video 0x102, IR; or
    (`programs`) program 1 with IR only, listed first, and program 2 with the video and EO."""
    from tests.shared.klv_writer import TsWriter, pes, section

    def stream(stream_type: int, pid: int, descriptor: bytes = b"") -> bytes:
        return bytes([stream_type, 0xE0 | (pid >> 8), pid & 0xFF, 0xF0, len(descriptor)]) + descriptor

    def pmt(program: int, *streams: bytes) -> bytes:
        return section(0x02, program, bytes([0xE1, 0x00, 0xF0, 0x00]) + b"".join(streams))

    klva = bytes([0x05, 4]) + b"KLVA"
    ts = TsWriter()
    if programs:
        ts.unit(0, section(0x00, 1, bytes([0, 1, 0xF0, 0x00, 0, 2, 0xF0, 0x01])), psi=True)
        ts.unit(0x1000, pmt(1, stream(0x06, 0x103, klva)), psi=True)
        ts.unit(0x1001, pmt(2, stream(0x1B, 0x100), stream(0x06, 0x101, klva)), psi=True)
    else:
        ts.unit(0, section(0x00, 1, bytes([0, 1, 0xF0, 0x00])), psi=True)
        ts.unit(0x1000, pmt(1, stream(0x1B, 0x100), stream(0x06, 0x101, klva), stream(0x1B, 0x102),
                            stream(0x06, 0x103, klva)), psi=True)
    ts.unit(0x100, pes(0xE0, bytes(300), 9_000, bounded=False))
    eo = iter(_flight(30))
    ir = iter(packet(T0 + 0.1 * i + 0.005, {**FULL, "sensor_rel_azimuth_deg": 270.0, "sensor_rel_elevation_deg": -20.0,
                                            "frame_center_elevation_m": 422.0}) for i in range(30))
    counts = [0, 0]
    for take_eo in order + [True] * 30 + [False] * 30:
        k = int(not take_eo)
        if counts[k] < 30:
            ts.unit(0x101 if take_eo else 0x103, pes(0xBD, next(eo if take_eo else ir), 9_000 * (1 + counts[k])))
            counts[k] += 1
    return ts.bytes()


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(order=st.lists(st.booleans(), max_size=60), programs=st.booleans())
def test_two_sensors_klv_streams_are_not_merged_the_first_videos_one_is_read(tmp_path, order, programs, caplog):
    # regression: both streams went into one decoder, so records alternated between the EO and the IR camera
    path = tmp_path / "eo-ir.ts"
    path.write_bytes(_two_sensor_ts(order, programs=programs))
    alone = parse_klv_report(b"".join(_flight(30)))
    caplog.clear()
    report = read_klv_report(path)
    assert report.records == alone.records  # EO only: heading 10, pitch 45, 40 m
    assert report.ignored_streams == {0x103: 30} and report.decoded == 30
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "reading PID 257 only, ignoring PID 259 (30 packets)" in warned[0]

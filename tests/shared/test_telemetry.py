"""Tests of shared.telemetry: DJI SRT variants, CSV, SeaDronesSee meta, pitch conversion, interpolation.

SRT samples are real blocks: DJI_SRT_Parser's samples (Mavic Pro, Matrice 300, Air 2S), blocks quoted in
public parsers' docs and tests (Mavic Mini, Phantom 4 RTK, Mavic 2), and a Matrice 30 block from a user's post.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from datetime import datetime, timezone
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from shared.telemetry import (
    PITCH_TOLERANCE_DEG,
    SEADRONESSEE_META_FIELDS,
    Telemetry,
    from_seadronessee_meta,
    interpolate,
    parse_csv,
    parse_datetime,
    parse_seadronessee_coco,
    parse_srt,
    parse_srt_report,
    pitch_from_dji,
    read_srt,
    read_srt_report,
    read_telemetry,
    to_seadronessee_meta,
)


def utc(*args: int) -> float:
    """Epoch seconds of a UTC date, computed independently of the parser."""
    return datetime(*args, tzinfo=timezone.utc).timestamp()


def circular_diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


# ---------------------------------------------------------------------------------------------
# Real SRT samples, one per variant
# ---------------------------------------------------------------------------------------------

# Mavic Pro (JuanIrache/DJI_SRT_Parser samples/sample2.SRT, blocks 7-8): GPS(lon, lat, satellites).
MAVIC_PRO_SRT = (
    "7\n"
    "00:00:07,000 --> 00:00:08,000\n"
    "HOME(131.1660,-25.2088) 2017.07.29 15:18:56\n"
    "GPS(131.1660,-25.2088,14) BAROMETER:0.5\n"
    "ISO:100 Shutter:60 EV: Fnum:2.2 \n"
    "\n"
    "8\n"
    "00:00:08,000 --> 00:00:09,000\n"
    "HOME(131.1660,-25.2088) 2017.07.29 15:18:57\n"
    "GPS(131.1660,-25.2088,14) BAROMETER:1.0\n"
    "ISO:100 Shutter:60 EV: Fnum:2.2 \n"
)

# Phantom 4 / Mavic Pro in Europe: both values under 90, so only the bare satellite count tells the order.
PHANTOM_4_EUROPE_SRT = (
    "1\n"
    "00:00:01,000 --> 00:00:02,000\n"
    "HOME(9.1830,47.6890) 2018.05.12 10:01:07\n"
    "GPS(9.1832,47.6893,17) BAROMETER:42.3\n"
    "ISO:100 Shutter:500 EV:-0.7 Fnum:2.8\n"
)

# Mavic Mini (quoted in a WebODM/ODM SRT parser): "GPS (lon, lat, sats)", H = height above home.
MAVIC_MINI_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:01,000\n"
    "F/2.8, SS 206.14, ISO 150, EV 0, GPS (-82.6669, 27.7716, 10), D 2.80m, H 12.40m, H.S 3.10m/s, "
    "V.S 0.00m/s \n"
)

# Phantom 4 RTK (same source): RTK fix tuple, aircraft F.PRY (ignored) and gimbal G.PRY (pitch, roll, yaw).
P4_RTK_SRT = (
    "36\n"
    "00:00:35,000 --> 00:00:36,000\n"
    "F/6.3, SS 60, ISO 100, EV 0, RTK (120.083799, 30.213635, 28), HOME (120.084146, 30.214243, "
    "103.55m), D 75.36m, H 76.19m, H.S 0.30m/s, V.S 0.00m/s, F.PRY (-5.3°, 2.1°, 28.3°), G.PRY "
    "(-40.0°, 0.0°, 28.2°)\n"
)

# Phantom 4 RTK in Argentina (DJI_SRT_Parser p4_rtk sample, first packet): both values within +-90.
P4_RTK_SOUTH_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:01,000\n"
    "F/5.6, SS 400, ISO 100, EV 0, GPS (-58.851745, -34.237922, 15), HOME (-58.847509, -34.232707, "
    "-57.98m), D 698.70m, H 85.80m, H.S 0.00m/s, V.S 0.00m/s, F.PRY (2.7°, -7.0°, 110.1°), G.PRY "
    "(-24.4°, 0.0°, 110.4°)\n"
)

# Matrice 300 (DJI_SRT_Parser samples/matrice_300.srt, blocks 59-60, with DJI's "00:00:60,000" quirk):
# GPS(lat, lon, altitude M) - latitude first.
MATRICE_300_SRT = (
    "59\n"
    "00:00:58,000 --> 00:00:59,000\n"
    "2022.06.21 16:07:15\n"
    "GPS(36.6153,-6.1130,0.0M) BAROMETER:83.3M\n"
    "\n"
    "60\n"
    "00:00:59,000 --> 00:00:60,000\n"
    "2022.06.21 16:07:16\n"
    "GPS(36.6153,-6.1130,0.0M) BAROMETER:83.8M\n"
)

# Mavic 2 (block quoted in a frame-geotagging script): FrameCnt, "ms,us" date, misspelt "longtitude",
# single "altitude" field.
MAVIC_2_SRT = (
    "107\n"
    "00:00:04,422 --> 00:00:04,463\n"
    '<font size="36">FrameCnt : 107, DiffTime : 41ms\n'
    "2023-06-23 11:26:03,972,307\n"
    "[iso : 100] [shutter : 1/3200.0] [fnum : 280] [ev : -0.7] [ct : 5502] [color_md : default] "
    "[focal_len : 280] [latitude : 38.904148] [longtitude : -92.281307] [altitude: 274.239014] "
    "</font>\n"
)

# Air 2S (DJI_SRT_Parser samples/air2s.srt, blocks 1-2): SrtCnt, "[latitude: ..] [longitude: ..]".
AIR_2S_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:00,033\n"
    '<font size="36">SrtCnt : 1, DiffTime : 33ms\n'
    "2022-08-07 13:40:40,774,808\n"
    "[iso : 100] [shutter : 1/80.0] [fnum : 280] [ev : 0] [ct : 5744] [color_md : default] "
    "[focal_len : 240] [latitude: 41.424724] [longitude: 2.234156] [altitude: 117.000000] </font>\n"
    "\n"
    "2\n"
    "00:00:00,033 --> 00:00:00,066\n"
    '<font size="36">SrtCnt : 2, DiffTime : 33ms\n'
    "2022-08-07 13:40:40,808,164\n"
    "[iso : 100] [shutter : 1/80.0] [fnum : 280] [ev : 0] [ct : 5744] [color_md : default] "
    "[focal_len : 240] [latitude: 41.424725] [longitude: 2.234147] [altitude: 117.000000] </font>\n"
)

# Mini 3 Pro style (quoted in a WebODM/ODM parser): rel_alt and abs_alt, no gimbal fields.
MINI_3_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:00,033\n"
    '<font size="28">SrtCnt : 1, DiffTime : 33ms\n'
    "2024-01-18 10:23:26.397\n"
    "[iso : 150] [shutter : 1/5000.0] [fnum : 170] [ev : 0] [ct : 5023] [color_md : default] "
    "[focal_len : 240] [dzoom_ratio: 10000, delta:0],[latitude: -22.724555] [longitude: -47.602414] "
    "[rel_alt: 30.300 abs_alt: 579.679] </font>\n"
)

# Matrice 30 / Mavic 3 Enterprise style (a user's posted SRT): FrameCnt, gimbal gb_yaw/gb_pitch/gb_roll.
MATRICE_30_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:00,198\n"
    '<font size="28">FrameCnt: 1, DiffTime: 198ms\n'
    "2025-04-09 09:15:02.655\n"
    "[iso: 170] [shutter: 1/99.77] [fnum: 4.4] [ev: 0] [color_md : default] [ae_meter_md: 1] "
    "[focal_len: 284.80] [dzoom_ratio: 1.77], [latitude: 53.388452] [longitude: 5.361783] [rel_alt: "
    "55.774 abs_alt: 98.364] [gb_yaw: -83.6 gb_pitch: -9.1 gb_roll: 0.0] </font>\n"
    "\n"
    "2\n"
    "00:00:00,198 --> 00:00:00,396\n"
    '<font size="28">FrameCnt: 2, DiffTime: 198ms\n'
    "2025-04-09 09:15:02.837\n"
    "[iso: 170] [shutter: 1/99.77] [fnum: 4.4] [ev: 0] [color_md : default] [ae_meter_md: 1] "
    "[focal_len: 284.80] [dzoom_ratio: 1.77], [latitude: 53.388452] [longitude: 5.361783] [rel_alt: "
    "55.759 abs_alt: 98.349] [gb_yaw: -83.6 gb_pitch: -9.1 gb_roll: 0.0] </font>\n"
)


def test_mavic_pro_gps_tuple_is_lon_lat_with_barometer_height_and_home_line_date():
    first, second = parse_srt(MAVIC_PRO_SRT, source="mavic_pro.SRT")
    assert (first.lat, first.lon) == pytest.approx((-25.2088, 131.1660))
    assert (first.height_m, second.height_m) == pytest.approx((0.5, 1.0))
    assert first.t == utc(2017, 7, 29, 15, 18, 56)
    assert second.t - first.t == 1.0
    assert (first.frame, second.frame) == (7, 8)
    assert first.pitch_deg is None and first.heading_deg is None


def test_phantom_4_tuple_order_from_bare_satellite_count_when_values_cannot_tell():
    (rec,) = parse_srt(PHANTOM_4_EUROPE_SRT)
    assert (rec.lat, rec.lon, rec.height_m) == pytest.approx((47.6893, 9.1832, 42.3))


def test_mavic_mini_spaced_gps_tuple_height_and_speed_without_date_use_subtitle_time():
    (rec,) = parse_srt(MAVIC_MINI_SRT)
    assert (rec.lat, rec.lon) == pytest.approx((27.7716, -82.6669))
    assert rec.height_m == pytest.approx(12.4)
    assert rec.speed_mps == pytest.approx(3.1)
    assert rec.t == 0.0
    assert rec.frame == 1


def test_phantom_4_rtk_uses_gimbal_pry_not_aircraft_pry():
    (rec,) = parse_srt(P4_RTK_SRT)
    assert (rec.lat, rec.lon, rec.height_m) == pytest.approx((30.213635, 120.083799, 76.19))
    assert rec.pitch_deg == pytest.approx(40.0)
    assert rec.heading_deg == pytest.approx(28.2)  # F.PRY says 28.3: the aircraft, not the camera
    assert rec.roll_deg == 0.0
    assert rec.t == 35.0 and rec.frame == 36


def test_phantom_4_rtk_south_west_keeps_signs():
    (rec,) = parse_srt(P4_RTK_SOUTH_SRT)
    assert (rec.lat, rec.lon) == pytest.approx((-34.237922, -58.851745))
    assert rec.pitch_deg == pytest.approx(24.4)
    assert rec.heading_deg == pytest.approx(110.4)


def test_gimbal_pry_tolerates_mojibake_degree_signs():
    text = P4_RTK_SRT.replace("°", "Â°")
    (rec,) = parse_srt(text)
    assert rec.pitch_deg == pytest.approx(40.0)


def test_matrice_300_gps_tuple_is_lat_lon_and_tolerates_second_60():
    first, second = parse_srt(MATRICE_300_SRT)
    assert (first.lat, first.lon) == pytest.approx((36.6153, -6.1130))
    assert (first.height_m, second.height_m) == pytest.approx((83.3, 83.8))
    assert first.t == utc(2022, 6, 21, 16, 7, 15)
    assert second.frame == 60


def test_mavic_2_longtitude_typo_ms_us_date_and_frame_counter(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        (rec,) = parse_srt(MAVIC_2_SRT, source="DJI_0042.SRT")
    assert (rec.lat, rec.lon) == pytest.approx((38.904148, -92.281307))
    assert rec.t == pytest.approx(utc(2023, 6, 23, 11, 26, 3) + 0.972307, abs=1e-6)
    assert rec.frame == 107
    assert rec.height_m == pytest.approx(274.239014)
    assert "altitude" in caplog.text and "height_offset_m" in caplog.text


def test_height_offset_turns_altitude_above_sea_level_into_height_above_ground(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        (rec,) = parse_srt(MAVIC_2_SRT, height_offset_m=-244.0)
    assert rec.height_m == pytest.approx(30.239014)
    assert caplog.text == ""


def test_air_2s_srtcnt_and_plain_longitude():
    first, second = parse_srt(AIR_2S_SRT)
    assert (first.lat, first.lon) == pytest.approx((41.424724, 2.234156))
    assert second.t - first.t == pytest.approx(0.033356, abs=1e-6)
    assert (first.frame, second.frame) == (1, 2)


def test_mini_3_prefers_rel_alt_over_abs_alt_and_has_no_gimbal():
    (rec,) = parse_srt(MINI_3_SRT)
    assert (rec.lat, rec.lon, rec.height_m) == pytest.approx((-22.724555, -47.602414, 30.3))
    assert rec.t == pytest.approx(utc(2024, 1, 18, 10, 23, 26) + 0.397)
    assert rec.pitch_deg is None and rec.heading_deg is None


def test_matrice_30_gimbal_pitch_converted_and_yaw_normalised():
    first, second = parse_srt(MATRICE_30_SRT)
    assert first.pitch_deg == pytest.approx(9.1)
    assert first.heading_deg == pytest.approx(276.4)
    assert first.height_m == pytest.approx(55.774)
    assert second.t - first.t == pytest.approx(0.182)
    assert first.t == pytest.approx(utc(2025, 4, 9, 9, 15, 2) + 0.655)


@pytest.mark.parametrize(("text", "zoom", "focals"), [
    (MINI_3_SRT, None, None),  # dzoom_ratio 10000: 1x
    (MATRICE_30_SRT, (2, 1.77), None),  # the zoom camera at 1.77x digital zoom, the whole clip
    (MINI_3_SRT.replace("dzoom_ratio: 10000", "dzoom_ratio: 20000"), (1, 2.0), None),
    (MATRICE_30_SRT.replace("[focal_len: 284.80] [dzoom_ratio: 1.77]", "[focal_len: 113.0] [dzoom_ratio: 1.00]", 1),
     (1, 1.77), (113.0, 284.8)),  # zooming in during the clip
    (MINI_3_SRT.replace("dzoom_ratio: 10000", "dzoom_ratio: n/a").replace("focal_len : 240", "focal_len : ?"),
     None, None),  # not numbers: left out, the block kept
])
def test_a_zooming_dji_camera_is_named_and_its_records_kept(caplog, text, zoom, focals):
    """DJI's digital zoom crops the sensor: the frames' focal length is that many times the camera file's, and
    every point off the image centre lands that many times too far out. On a fixed lens each record carries its
    ratio (the video source applies it where it changes: agent.field_of_view); beside a focal length that changes
    (a hybrid zoom, the SRT's focal_len units vary by firmware) it is not applied, and said."""
    with caplog.at_level(logging.WARNING):
        report = parse_srt_report(text, source="clip.SRT")
    assert len(report.records) == text.count("-->")
    assert report.digital_zoom == (pytest.approx(zoom) if zoom else None)
    assert report.focal_lengths == (pytest.approx(focals) if focals else None)
    said = [r.getMessage() for r in caplog.records if "zooms" in r.getMessage()]
    assert len(said) == (1 if focals else 0)
    if focals:
        assert f"digital zoom in {zoom[0]} of {len(report.records)} records, up to {zoom[1]:.2f}x" in said[0]
        assert all(r.zoom_ratio is None for r in report.records)
    elif zoom:
        assert max(r.zoom_ratio for r in report.records) == pytest.approx(zoom[1])


@pytest.mark.parametrize(("written", "ratio"), [("DZOOM 1.000", 1.0), ("DZOOM 2.500", 2.5), ("DZOOM 0", None)])
def test_a_mini_2_digital_zoom_is_read(written, ratio):
    """The Mini 2 writes one line, ``F/2.8, SS 1667.11, ISO 100, EV 0, DZOOM 1.000, GPS (lon, lat, 26), ...``."""
    text = ("1\n00:00:00,000 --> 00:00:00,033\n"
            f"F/2.8, SS 1667.11, ISO 100, EV 0, {written}, GPS (120.3534, 23.1201, 26), D 499.16m, H 98.00m, "
            "H.S 4.81m/s, V.S 0.10m/s\n")
    (rec,) = parse_srt(text)
    assert (rec.lat, rec.lon, rec.height_m) == pytest.approx((23.1201, 120.3534, 98.0))
    assert rec.zoom_ratio == (pytest.approx(ratio) if ratio else None)


def test_utc_offset_shifts_the_naive_drone_clock():
    (rec,) = parse_srt(MINI_3_SRT, utc_offset_s=-3 * 3600.0)  # Brazil, UTC-3
    assert rec.t == pytest.approx(utc(2024, 1, 18, 13, 23, 26) + 0.397)


def test_crlf_bom_and_missing_final_newline_are_fine(tmp_path):
    path = tmp_path / "DJI_0001.SRT"
    path.write_bytes(("\ufeff" + MATRICE_30_SRT.strip()).replace("\n", "\r\n").encode("utf-8"))
    records = read_srt(path)
    assert [r.frame for r in records] == [1, 2]
    assert read_telemetry(path) == records


def test_srt_gimbal_without_pitch_gives_heading_only():
    text = MINI_3_SRT.replace("</font>", "[gb_yaw: 12.5] </font>")
    (rec,) = parse_srt(text)
    assert rec.heading_deg == pytest.approx(12.5) and rec.pitch_deg is None


@pytest.mark.parametrize(
    ("gb_pitch", "expected"),
    [("-90.3", 90.0), ("0.5", 0.0), ("-45.0", 45.0), ("-90.0", 90.0), ("0.0", 0.0), ("-17.5", 17.5)],
)
def test_srt_gimbal_pitch_clamps_small_overshoots(gb_pitch, expected):
    text = MATRICE_30_SRT.replace("gb_pitch: -9.1", f"gb_pitch: {gb_pitch}")
    assert parse_srt(text)[0].pitch_deg == expected


def test_gps_fix_missing_blocks_at_zero_zero_are_skipped_with_a_warning(caplog):
    no_fix = MATRICE_30_SRT.replace(
        "[latitude: 53.388452] [longitude: 5.361783]", "[latitude: 0.000000] [longitude: 0.000000]", 1
    )
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        records = parse_srt(no_fix)
    assert [r.frame for r in records] == [2]
    assert "no GPS fix" in caplog.text


# ---------------------------------------------------------------------------------------------
# Files that give no record at all: one clear ValueError naming the file
# ---------------------------------------------------------------------------------------------

# Early Mavic Air firmware: exposure settings only, no position in any block.
MAVIC_AIR_EXPOSURE_ONLY_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:00,033\n"
    '<font size="36">SrtCnt : 1, DiffTime : 33ms\n'
    "2018-04-14 15:07:32,126,452\n"
    "[iso : 100] [shutter : 1/1250.0] [fnum : 280] [ev : 0] [ct : 5526] [color_md : default] "
    "[focal_len : 240] </font>\n"
    "\n"
    "2\n"
    "00:00:00,033 --> 00:00:00,066\n"
    '<font size="36">SrtCnt : 2, DiffTime : 33ms\n'
    "2018-04-14 15:07:32,159,812\n"
    "[iso : 100] [shutter : 1/1250.0] [fnum : 280] [ev : 0] [ct : 5526] [color_md : default] "
    "[focal_len : 240] </font>\n"
)


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("", r"^flight\.srt: empty SRT file$"),
        ("  \n\n \r\n", r"^flight\.srt: empty SRT file$"),
        ("\ufeff\r\n", r"^flight\.srt: empty SRT file$"),
        ("hello drone\n", r"^flight\.srt: no subtitle blocks"),
        (MAVIC_AIR_EXPOSURE_ONLY_SRT, r"^flight\.srt: no block of 2 has a position .*logs no GPS"),
        (
            MATRICE_30_SRT.replace("53.388452", "0.0").replace("5.361783", "0.0"),
            r"^flight\.srt: no block has a GPS fix",
        ),
        (
            MAVIC_PRO_SRT.replace("GPS(131.1660,-25.2088,14)", "GPS(N/A,N/A,0)"),
            r"^flight\.srt: no block has a GPS fix",
        ),
        (
            P4_RTK_SRT.replace("G.PRY (-40.0°, 0.0°, 28.2°)", "G.PRY (-40.0°, 28.2°)"),
            r"^flight\.srt: no usable block among 1: line 3: G\.PRY .*needs pitch, roll, yaw$",
        ),
    ],
)
def test_srt_without_any_usable_block_raises_one_clear_line(text, pattern):
    with pytest.raises(ValueError, match=pattern) as err:
        parse_srt(text, source="flight.srt")
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------------------------------------
# Bad blocks are skipped, counted and named; the rest of the file loads
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "reason"),
    [
        (MATRICE_30_SRT.replace("[latitude: 53.388452] ", "", 1), 2, "block has no latitude"),
        (MATRICE_30_SRT.replace("[latitude: 53.388452]", "[latitude: 5x.388452]", 1), 5, "latitude value '5x.388452'"),
        (MATRICE_30_SRT.replace("[latitude: 53.388452]", "[latitude: ]", 1), 5, "latitude value '' is not a number"),
        (MATRICE_30_SRT.replace("2025-04-09 09:15:02.655", "2025-13-45 09:15:02.655"), 4, "invalid date-time"),
        (MATRICE_30_SRT.replace("2025-04-09 09:15:02.655", "2025-04-09 9h15"), 4, "date-time does not parse"),
        (
            MATRICE_30_SRT.replace("00:00:00,198 --> 00:00:00,396", "00:00:0x,198 --> 00:00:00,396"),
            8,
            "malformed subtitle timing line",
        ),
        (MATRICE_30_SRT.replace("FrameCnt: 2,", "FrameCnt: two,"), 9, "frame counter 'two'"),
        (MATRICE_30_SRT.replace("[latitude: 53.388452]", "[latitude: 95.1]", 1), 5, "latitude 95.1 is outside"),
        (MATRICE_30_SRT.replace("[latitude: 53.388452] [longitude: 5.361783]", "", 1), 2, "block has no position"),
        (MAVIC_PRO_SRT.replace("GPS(131.1660,-25.2088,14)", "GPS(131.1660)", 1), 4, "GPS tuple 'GPS(131.1660)'"),
        (MAVIC_PRO_SRT.replace("GPS(131.1660,-25.2088,14)", "GPS(131.1660,-25.20x8,14)", 1), 4, "GPS value"),
        ("garbage line\n" + MATRICE_30_SRT, 1, "text outside any subtitle block: 'garbage line'"),
    ],
)
def test_a_bad_block_is_skipped_counted_and_named_never_the_whole_file(text, line, reason, caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(text, source="flight.srt")
    assert len(report.skipped) == 1 and len(report.records) == report.blocks - 1 >= 1
    assert report.skipped[0][0] == line and reason in report.skipped[0][1]
    assert f"flight.srt: skipped 1 of {report.blocks} blocks: line {line}: " in caplog.text
    assert reason in caplog.text
    assert parse_srt(text) == report.records


def test_skipped_block_warning_names_the_first_three_lines_and_counts_the_rest(caplog):
    good = MATRICE_30_SRT.split("\n\n")[1]
    bad = MATRICE_30_SRT.split("\n\n")[0].replace("[latitude: 53.388452] [longitude: 5.361783]", "GPS(N/A,N/A,0)")
    text = "\n\n".join([bad] * 5 + [good]) + "\n"
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(text, source="flight.srt")
    assert len(report.records) == 1 and len(report.skipped) == 5
    assert [line for line, _ in report.skipped] == [5, 11, 17, 23, 29]
    assert all(reason == "no GPS fix: GPS(N/A,N/A,0)" for _, reason in report.skipped)
    message = next(r.getMessage() for r in caplog.records if "skipped" in r.getMessage())
    assert message.startswith("flight.srt: skipped 5 of 6 blocks: line 5: no GPS fix")
    assert "line 17: " in message and "line 23" not in message and message.endswith("(and 2 more)")


# ---------------------------------------------------------------------------------------------
# The variants of issue 21, each in the exact shape quoted there
# ---------------------------------------------------------------------------------------------

# Mavic 2-era firmware without timing lines: an index, a date-time line, then the fields.
NO_TIMING_LINE_SRT = (
    "1\n"
    "2017.08.05 14:11:51,393,525\n"
    "[iso : 110] [shutter : 1/200.0] [fnum : 220] [ev : 0.7] [ct : 5064] [color_md : default] "
    "[focal_len : 240] [latitude : 22.543096] [longtitude : 113.958321] \n"
    "\n"
    "2\n"
    "2017.08.05 14:11:51,426,891\n"
    "[iso : 110] [shutter : 1/200.0] [fnum : 220] [ev : 0.7] [ct : 5064] [color_md : default] "
    "[focal_len : 240] [latitude : 22.543101] [longtitude : 113.958330] \n"
)

# Mavic 2 Pro firmware that writes the position and no altitude at all.
MAVIC_2_PRO_NO_ALTITUDE_SRT = (
    "1\n"
    "00:00:00,000 --> 00:00:00,033\n"
    '<font size="36">SrtCnt : 1, DiffTime : 33ms\n'
    "2019-03-16 16:20:47,227,538\n"
    "[iso : 100] [shutter : 1/640.0] [fnum : 280] [ev : 0] [ct : 5500] [color_md : default] "
    "[focal_len : 280] [latitude : 38.887375] [longtitude : -77.034671] </font>\n"
    "\n"
    "2\n"
    "00:00:00,033 --> 00:00:00,066\n"
    '<font size="36">SrtCnt : 2, DiffTime : 33ms\n'
    "2019-03-16 16:20:47,260,904\n"
    "[iso : 100] [shutter : 1/640.0] [fnum : 280] [ev : 0] [ct : 5500] [color_md : default] "
    "[focal_len : 280] [latitude : 38.887381] [longtitude : -77.034665] </font>\n"
)

# The oldest format (Phantom 3 era): GPS(lon, lat, alt) with barometric (Hb) and sonar (Hs) heights.
OLD_HB_HS_SRT = (
    "1\n"
    "00:00:01,000 --> 00:00:02,000\n"
    "GPS(8.5417,47.3769,19) Hb:1.9 Hs:1.9\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.8\n"
    "\n"
    "2\n"
    "00:00:02,000 --> 00:00:03,000\n"
    "GPS(8.5418,47.3770,19) Hb:12.4 Hs:3.1\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.8\n"
)

# Mavic Pro blocks without a fix: GPS(N/A,N/A,...).
MAVIC_PRO_NO_FIX_SRT = (
    "1\n"
    "00:00:01,000 --> 00:00:02,000\n"
    "HOME(149.0251,-20.2532) 2017.08.05 14:11:51\n"
    "GPS(N/A,N/A,4) BAROMETER:0.0\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.2 \n"
    "\n"
    "2\n"
    "00:00:02,000 --> 00:00:03,000\n"
    "HOME(149.0251,-20.2532) 2017.08.05 14:11:52\n"
    "GPS(149.0251,-20.2533,9) BAROMETER:0.3\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.2 \n"
    "\n"
    "3\n"
    "00:00:03,000 --> 00:00:04,000\n"
    "HOME(149.0251,-20.2532) 2017.08.05 14:11:53\n"
    "GPS(N/A,N/A,6) BAROMETER:1.1\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.2 \n"
    "\n"
    "4\n"
    "00:00:04,000 --> 00:00:05,000\n"
    "HOME(149.0251,-20.2532) 2017.08.05 14:11:54\n"
    "GPS(149.0252,-20.2534,11) BAROMETER:2.4\n"
    "ISO:100 Shutter:60 EV:0 Fnum:2.2 \n"
)

# Blocks with neither a timing line nor a date: the frame counter and DiffTime give the clock.
COUNTER_ONLY_SRT = (
    "1\n"
    "FrameCnt : 1, DiffTime : 41ms\n"
    "[latitude : 22.543096] [longtitude : 113.958321] [altitude: 45.300000]\n"
    "\n"
    "2\n"
    "FrameCnt : 2, DiffTime : 42ms\n"
    "[latitude : 22.543097] [longtitude : 113.958322] [altitude: 45.400000]\n"
    "\n"
    "3\n"
    "FrameCnt : 3, DiffTime : 41ms\n"
    "[latitude : 22.543098] [longtitude : 113.958323] [altitude: 45.500000]\n"
)

# Mavic Mini recording (subtitle timing, no dates) followed by a Matrice 30 recording (dates).
MAVIC_MINI_2_BLOCKS_SRT = MAVIC_MINI_SRT + (
    "\n"
    "2\n"
    "00:00:01,000 --> 00:00:02,000\n"
    "F/2.8, SS 206.14, ISO 150, EV 0, GPS (-82.6670, 27.7717, 10), D 2.90m, H 13.10m, H.S 3.20m/s, "
    "V.S 0.00m/s \n"
)
CONCATENATED_SRT = MAVIC_MINI_2_BLOCKS_SRT + "\n" + MATRICE_30_SRT


def test_blocks_without_timing_line_use_their_date_time_line(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(NO_TIMING_LINE_SRT, source="DJI_0007.SRT")
    first, second = report.records
    assert (first.lat, first.lon) == pytest.approx((22.543096, 113.958321))
    assert first.t == pytest.approx(utc(2017, 8, 5, 14, 11, 51) + 0.393525, abs=1e-6)
    assert second.t - first.t == pytest.approx(0.033366, abs=1e-6)
    assert (first.frame, second.frame) == (1, 2)
    assert first.height_m is None and report.heights_missing == 2
    assert report.skipped == () and report.clock_notes == ()
    assert "2 of 2 records have no height above ground" in caplog.text


def test_mavic_2_pro_without_altitude_loads_with_the_height_missing(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(MAVIC_2_PRO_NO_ALTITUDE_SRT, source="DJI_0012.SRT")
    assert [(r.lat, r.lon) for r in report.records] == [(38.887375, -77.034671), (38.887381, -77.034665)]
    assert [r.height_m for r in report.records] == [None, None]
    assert report.heights_missing == 2 and report.heights_above_sea_level_only == 0
    assert "DJI_0012.SRT: 2 of 2 records have no height above ground (2 give no height at all)" in caplog.text
    with pytest.raises(ValueError, match=r"--height-m METRES .* or, if it logs altitude above sea level"):
        report.records[0].to_pose(45.0, 90.0)
    pose = report.records[0].to_pose(45.0, 90.0, height_m=40.0)
    assert pose.height_m == 40.0


@pytest.mark.parametrize("third", ["19", "412.5M"])
def test_oldest_format_gps_is_lon_lat_and_height_is_hb(third):
    first, second = parse_srt(OLD_HB_HS_SRT.replace(",19)", f",{third})"))
    assert (first.lat, first.lon) == pytest.approx((47.3769, 8.5417))
    assert (first.height_m, second.height_m) == pytest.approx((1.9, 12.4))
    assert (first.t, second.t) == (1.0, 2.0)


def test_oldest_format_uses_sonar_height_without_barometric():
    (first, _) = parse_srt(OLD_HB_HS_SRT.replace("Hb:1.9 ", ""))
    assert first.height_m == pytest.approx(1.9)


def test_mavic_pro_blocks_without_fix_are_skipped_and_counted(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(MAVIC_PRO_NO_FIX_SRT, source="DJI_0001.SRT")
    assert [r.frame for r in report.records] == [2, 4]
    assert report.records[0].lat == pytest.approx(-20.2533) and report.records[0].lon == pytest.approx(149.0251)
    assert report.skipped == ((4, "no GPS fix: GPS(N/A,N/A,4)"), (16, "no GPS fix: GPS(N/A,N/A,6)"))
    assert "DJI_0001.SRT: skipped 2 of 4 blocks: line 4: no GPS fix: GPS(N/A,N/A,4); line 16: " in caplog.text
    assert report.records[1].t - report.records[0].t == 2.0


def test_blocks_without_timing_or_date_use_frame_counter_and_diff_time():
    report = parse_srt_report(COUNTER_ONLY_SRT)
    assert [r.t for r in report.records] == pytest.approx([0.0, 0.042, 0.083])
    assert [r.frame for r in report.records] == [1, 2, 3]
    assert report.records[2].height_m == pytest.approx(45.5)


def test_concatenated_recordings_are_read_block_by_block_on_one_monotonic_clock(caplog):
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(CONCATENATED_SRT, source="both.SRT")
    records = report.records
    assert [r.frame for r in records] == [1, 2, 1, 2]
    assert (records[0].lat, records[0].lon) == pytest.approx((27.7716, -82.6669))  # Mini: GPS(lon, lat, sats)
    assert (records[2].lat, records[2].lon) == pytest.approx((53.388452, 5.361783))
    dated = utc(2025, 4, 9, 9, 15, 2) + 0.655
    assert records[2].t == pytest.approx(dated) and records[3].t == pytest.approx(dated + 0.182)
    # the undated Mini blocks keep their 1 s spacing and end before the dated recording starts
    assert records[1].t - records[0].t == pytest.approx(1.0)
    assert records[0].t < records[1].t < records[2].t
    assert report.gps_decimals_seen == {4: 2, 6: 2} and report.gps_decimals == 4
    assert report.gps_step_m == pytest.approx(11.132)
    assert len(report.clock_notes) == 1 and report.clock_notes[0].startswith("line 10: ")
    assert "both.SRT: the clock was made monotonic" in caplog.text


def test_a_block_without_date_among_dated_ones_continues_from_the_subtitle_timing(caplog):
    text = MATRICE_30_SRT.replace("2025-04-09 09:15:02.837\n", "")
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        first, second = parse_srt(text)
    assert second.t - first.t == pytest.approx(0.198)  # the timing step; the missing date said 0.182
    assert "line 8" in caplog.text and "monotonic" in caplog.text


def test_dates_that_go_back_are_made_monotonic_with_a_warning(caplog):
    later = AIR_2S_SRT.replace("2022-08-07 13:40:40,808,164", "2022-08-07 12:40:40,808,164")
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        first, second = parse_srt(later, source="jump.SRT")
    assert second.t - first.t == pytest.approx(0.033)
    assert "jump.SRT: the clock was made monotonic" in caplog.text and "goes back 3599.967 s" in caplog.text


def test_dates_that_jump_ahead_of_the_subtitle_timing_are_kept_with_a_warning(caplog):
    later = AIR_2S_SRT.replace("2022-08-07 13:40:40,808,164", "2022-08-07 14:40:40,808,164")
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        first, second = parse_srt(later)
    assert second.t - first.t == pytest.approx(3600.033356)
    assert "kept the dates" in caplog.text


def test_gps_quantisation_is_reported_per_file():
    assert parse_srt_report(MAVIC_PRO_SRT).gps_decimals == 4
    report = parse_srt_report(MATRICE_30_SRT)
    assert report.gps_decimals == 6 and report.gps_decimals_seen == {6: 2}
    assert report.gps_step_m == pytest.approx(0.11132)


def test_srt_resaved_as_utf_16_by_a_subtitle_editor_reads_the_same(tmp_path):
    path = tmp_path / "DJI_0004.SRT"
    path.write_bytes(MATRICE_30_SRT.replace("\n", "\r\n").encode("utf-16"))  # with a BOM, as editors write it
    assert read_srt(path) == parse_srt(MATRICE_30_SRT)


def test_read_srt_report_reads_a_latin_1_file_and_names_it(tmp_path):
    path = tmp_path / "DJI_0003.SRT"
    path.write_bytes(P4_RTK_SRT.encode("latin-1"))
    report = read_srt_report(path)
    assert report.source == str(path) and report.records == read_srt(path)
    assert report.records[0].pitch_deg == pytest.approx(40.0)




def test_abs_alt_only_works_with_height_offset():
    text = MINI_3_SRT.replace("rel_alt: 30.300 ", "")
    (rec,) = parse_srt(text, height_offset_m=-549.679)
    assert rec.height_m == pytest.approx(30.0)


def test_abs_alt_only_without_offset_loads_with_height_missing_and_says_which_flag(caplog):
    text = MINI_3_SRT.replace("rel_alt: 30.300 ", "")
    with caplog.at_level(logging.WARNING, logger="shared.telemetry"):
        report = parse_srt_report(text, source="DJI_0100.SRT")
    assert report.records[0].height_m is None
    assert report.heights_missing == 1 and report.heights_above_sea_level_only == 1
    assert "1 give only abs_alt, above sea level: pass height_offset_m=-(ground elevation in m)" in caplog.text


def test_mavic_mini_without_h_loads_with_height_missing():
    (rec,) = parse_srt(MAVIC_MINI_SRT.replace("H 12.40m, ", ""))
    assert rec.height_m is None and rec.lat == pytest.approx(27.7716)


def test_gps_order_override_that_contradicts_values_is_rejected():
    with pytest.raises(ValueError, match=r":4: gps_order='latlon'"):
        parse_srt(MAVIC_PRO_SRT, gps_order="latlon")
    assert parse_srt(MATRICE_300_SRT, gps_order="lonlat")[0].lat == pytest.approx(-6.1130)
    with pytest.raises(ValueError, match="gps_order"):
        parse_srt(MATRICE_300_SRT, gps_order="xy")


def test_gps_tuple_with_longitude_in_second_place_is_detected_from_values():
    text = MATRICE_300_SRT.replace("36.6153,-6.1130,0.0M", "36.6153,-116.1130,12")
    assert parse_srt(text)[0].lon == pytest.approx(-116.1130)


def test_bracket_latitude_beats_a_stray_gps_token():
    text = MATRICE_30_SRT.replace("[iso: 170]", "[GPS(7) ] [iso: 170]")
    assert parse_srt(text)[0].lat == pytest.approx(53.388452)


# ---------------------------------------------------------------------------------------------
# DJI pitch conversion, heading wrap, record validation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("gb_pitch", "depression"),
    [(-90.0, 90.0), (-90.3, 90.0), (-91.0, 90.0), (0.5, 0.0), (1.0, 0.0), (-0.0, 0.0), (-45.4, 45.4), (-1e-9, 1e-9)],
)
def test_pitch_from_dji(gb_pitch, depression):
    assert pitch_from_dji(gb_pitch) == pytest.approx(depression)
    assert math.copysign(1.0, pitch_from_dji(gb_pitch)) == 1.0


@pytest.mark.parametrize("gb_pitch", [-91.01, 1.01, 30.0, -120.0, float("nan"), float("inf")])
def test_pitch_from_dji_rejects_beyond_tolerance(gb_pitch):
    with pytest.raises(ValueError):
        pitch_from_dji(gb_pitch)


def test_pitch_tolerance_is_one_degree():
    assert PITCH_TOLERANCE_DEG == 1.0


@pytest.mark.parametrize(
    ("heading", "wrapped"), [(-90.0, 270.0), (360.0, 0.0), (725.0, 5.0), (-1e-20, 0.0), (359.9, 359.9)]
)
def test_heading_is_normalised_to_0_360(heading, wrapped):
    tel = Telemetry(t=0.0, lat=1.0, lon=2.0, height_m=10.0, pitch_deg=None, heading_deg=heading)
    assert tel.heading_deg == pytest.approx(wrapped)
    assert 0.0 <= tel.heading_deg < 360.0


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("lat", 90.5),
        ("lat", float("nan")),
        ("lon", -180.5),
        ("t", float("inf")),
        ("height_m", "30"),
        ("pitch_deg", 90.5),
        ("pitch_deg", -0.5),
        ("heading_deg", float("nan")),
        ("speed_mps", -1.0),
        ("vel_en_mps", (1.0,)),
        ("frame", -1),
        ("frame", True),
        ("frame", 1.5),
        ("roll_deg", None),
    ],
)
def test_telemetry_rejects_bad_values_naming_the_field(field, value):
    kwargs = dict(t=0.0, lat=1.0, lon=2.0, height_m=10.0, pitch_deg=45.0, heading_deg=10.0)
    kwargs[field] = value
    with pytest.raises(ValueError, match=field.split("_")[0]):
        Telemetry(**kwargs)


def test_telemetry_to_pose_supplies_and_overrides_gimbal_angles():
    tel = Telemetry(t=0.0, lat=47.67, lon=9.27, height_m=30.0, pitch_deg=None, heading_deg=None, roll_deg=2.0)
    with pytest.raises(ValueError, match="telemetry has no gimbal pitch: pass --pitch-deg"):
        tel.to_pose()
    with pytest.raises(ValueError, match="no gimbal heading"):
        tel.to_pose(pitch_deg=45.0)
    pose = tel.to_pose(pitch_deg=45.0, heading_deg=-20.0)
    assert (pose.lat, pose.lon, pose.height_m, pose.pitch_deg, pose.heading_deg, pose.roll_deg) == pytest.approx(
        (47.67, 9.27, 30.0, 45.0, 340.0, 2.0)
    )
    full = Telemetry(t=0.0, lat=47.67, lon=9.27, height_m=30.0, pitch_deg=60.0, heading_deg=90.0)
    assert full.to_pose().pitch_deg == 60.0
    assert full.to_pose(pitch_deg=30.0).pitch_deg == 30.0


# ---------------------------------------------------------------------------------------------
# SeaDronesSee meta
# ---------------------------------------------------------------------------------------------

SDS_META = {
    "date_time": "2020-08-24T15:45:20",
    "gps_latitude": 47.6715011,
    "gps_latitude_ref": "N",
    "gps_longitude": 9.2709444,
    "gps_longitude_ref": "E",
    "altitude": 29.9,
    "gimbal_pitch": 45.4,
    "compass_heading": 293.8,
    "gimbal_heading": 300.1,
    "speed": 1.2,
    "xspeed": 0.5,
    "yspeed": -1.1,
    "zspeed": 0.0,
}


def test_seadronessee_meta_uses_gimbal_heading_not_compass():
    tel = from_seadronessee_meta(SDS_META, frame=12)
    assert tel is not None
    assert (tel.lat, tel.lon, tel.height_m, tel.pitch_deg) == pytest.approx((47.6715011, 9.2709444, 29.9, 45.4))
    assert tel.heading_deg == pytest.approx(300.1)
    assert tel.t == utc(2020, 8, 24, 15, 45, 20)
    assert tel.speed_mps == pytest.approx(1.2)
    assert tel.vel_en_mps == pytest.approx((-1.1, 0.5))  # DJI: x north, y east
    assert tel.frame == 12


@pytest.mark.parametrize(
    ("lat_ref", "lon_ref", "signs"), [("S", "W", (-1, -1)), ("N", "W", (1, -1)), ("s", "e", (-1, 1))]
)
def test_seadronessee_refs_sign_the_coordinates(lat_ref, lon_ref, signs):
    meta = dict(SDS_META, gps_latitude_ref=lat_ref, gps_longitude_ref=lon_ref)
    tel = from_seadronessee_meta(meta)
    assert (tel.lat, tel.lon) == pytest.approx((signs[0] * 47.6715011, signs[1] * 9.2709444))


def test_seadronessee_null_meta_is_none_and_strings_are_numbers():
    assert from_seadronessee_meta(None) is None
    as_strings = {k: str(v) for k, v in SDS_META.items()}
    assert from_seadronessee_meta(as_strings) == from_seadronessee_meta(SDS_META)


def test_seadronessee_missing_gimbal_gives_none_angles():
    meta = {k: v for k, v in SDS_META.items() if k not in ("gimbal_pitch", "gimbal_heading", "xspeed")}
    tel = from_seadronessee_meta(meta)
    assert tel.pitch_deg is None and tel.heading_deg is None and tel.vel_en_mps is None


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"gps_latitude": None}, "gps_latitude"),
        ({"gps_latitude": "north-ish"}, "gps_latitude"),
        ({"gps_latitude_ref": None}, "gps_latitude_ref"),
        ({"gps_longitude_ref": "Q"}, "gps_longitude_ref"),
        ({"gps_longitude": 190.0}, "gps_longitude"),
        ({"gps_latitude": -47.0}, "gps_latitude"),  # negative with ref N contradicts
        ({"altitude": None}, "altitude"),
        ({"altitude": "nan"}, "altitude"),
        ({"altitude": True}, "altitude"),
        ({"gimbal_pitch": "down"}, "gimbal_pitch"),
        ({"gimbal_pitch": 120.0}, "gimbal_pitch"),
        ({"gimbal_heading": [1, 2]}, "gimbal_heading"),
        ({"speed": -3.0}, "speed"),
        ({"date_time": None}, "date_time"),
        ({"date_time": "yesterday"}, "date_time"),
        ({"date_time": "2020-02-30T10:00:00"}, "date_time"),
    ],
)
def test_seadronessee_bad_fields_raise_naming_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        from_seadronessee_meta(dict(SDS_META, **change))


def test_to_seadronessee_meta_writes_every_field_and_nulls_for_unknowns():
    tel = Telemetry(
        t=utc(2021, 3, 1, 12, 0, 0) + 0.25, lat=-33.9, lon=-70.1, height_m=50.0, pitch_deg=None, heading_deg=None
    )
    meta = to_seadronessee_meta(tel)
    assert set(meta) == set(SEADRONESSEE_META_FIELDS)
    assert meta["gps_latitude_ref"] == "S" and meta["gps_longitude_ref"] == "W"
    assert meta["gps_latitude"] == 33.9 and meta["gps_longitude"] == 70.1
    assert meta["date_time"] == "2021-03-01T12:00:00.250000"
    assert meta["gimbal_pitch"] is None and meta["zspeed"] is None and meta["compass_heading"] is None
    assert json.loads(json.dumps(meta)) == meta
    assert from_seadronessee_meta(meta) == tel


def test_a_zoom_lens_field_of_view_rides_in_the_meta_and_back():
    """`uavmm detect` writes a zooming camera's field of view per frame (meta hfov_deg, not SeaDronesSee's); the
    dataset reader reads it back; a bad one names the field."""
    tel = Telemetry(t=utc(2021, 3, 1, 12, 0, 0), lat=48.5, lon=9.0, height_m=40.0, pitch_deg=45.0, heading_deg=10.0,
                    hfov_deg=12.5)
    meta = to_seadronessee_meta(tel)
    assert set(meta) == set(SEADRONESSEE_META_FIELDS) | {"hfov_deg"} and meta["hfov_deg"] == 12.5
    assert from_seadronessee_meta(json.loads(json.dumps(meta))) == tel
    for bad in (0.0, 190.0, "wide"):
        with pytest.raises(ValueError, match="hfov_deg"):
            from_seadronessee_meta({**meta, "hfov_deg": bad})


def test_seadronessee_coco_json_ordered_by_frame_index_and_skips_null_meta(tmp_path):
    def image(i, frame, meta):
        return {"id": i, "file_name": f"{i}.jpg", "video_id": 3, "frame_index": frame, "meta": meta}

    metas = [dict(SDS_META, date_time=f"2020-08-24T15:45:{20 + k:02d}", altitude=20.0 + k) for k in range(3)]
    coco = {"images": [image(7, 2, metas[2]), image(5, 0, metas[0]), image(6, 1, None), image(8, 3, metas[1])]}
    path = tmp_path / "images.json"
    path.write_text(json.dumps(coco))
    records = read_telemetry(path)
    assert [r.frame for r in records] == [0, 2, 3]
    assert [r.height_m for r in records] == [20.0, 22.0, 21.0]


def test_seadronessee_coco_with_several_videos_needs_video_id():
    coco = {
        "images": [
            {"id": 1, "video_id": 1, "frame_index": 0, "meta": SDS_META},
            {"id": 2, "video_id": 2, "frame_index": 0, "meta": SDS_META},
        ]
    }
    with pytest.raises(ValueError, match="video_id"):
        parse_seadronessee_coco(coco)
    assert len(parse_seadronessee_coco(coco, video_id=2)) == 1
    bad = {"images": [{"id": 9, "video_id": 1, "frame_index": 0, "meta": dict(SDS_META, altitude="x")}]}
    with pytest.raises(ValueError, match=r"image id 9: .*altitude"):
        parse_seadronessee_coco(bad)


def test_read_telemetry_rejects_unknown_extension(tmp_path):
    with pytest.raises(ValueError, match=r"\.gpx"):
        read_telemetry(tmp_path / "track.gpx")


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------


def test_csv_with_aliases_case_insensitive():
    text = (
        "Time_S,Latitude,LNG,rel_alt,Gimbal_Pitch,Yaw,Roll,frame\n"
        "0.0,47.1,9.2,30.5,45,350.5,1.5,0\n"
        "0.5,47.2,9.3,31.0,,10,0,1\n"
    )
    first, second = parse_csv(text)
    assert (first.t, first.lat, first.lon, first.height_m, first.pitch_deg) == (0.0, 47.1, 9.2, 30.5, 45.0)
    assert (first.heading_deg, first.roll_deg, first.frame) == (350.5, 1.5, 0)
    assert second.pitch_deg is None  # empty optional cell
    assert second.frame == 1


def test_csv_negative_pitch_means_dji_convention():
    text = "t,lat,lon,height,pitch\n0,1,2,30,-45\n1,1,2,30,-90.4\n2,1,2,30,0\n"
    assert [r.pitch_deg for r in parse_csv(text)] == [45.0, 90.0, 0.0]


def test_csv_gb_pitch_column_is_dji_even_when_no_value_is_negative():
    text = "time,lat,lon,height_m,gb_pitch,gb_yaw\n0,1,2,30,0.4,-170\n"
    (rec,) = parse_csv(text)
    assert rec.pitch_deg == 0.0 and rec.heading_deg == pytest.approx(190.0)


def test_csv_airdata_export_units_and_gimbal_columns_beat_aircraft_ones():
    text = (
        "time(millisecond),datetime(utc),latitude,longitude,height_above_takeoff(feet),"
        "altitude_above_seaLevel(feet),compass_heading(degrees),pitch(degrees),roll(degrees),"
        "gimbal_heading(degrees),gimbal_pitch(degrees),gimbal_roll(degrees),speed(mph)\n"
        "0,2019-08-10 10:22:33,47.6712345,9.2701234,98.4,1450.3,120.5,-5.2,1.1,118.0,-45.0,0.0,11.2\n"
        "100,2019-08-10 10:22:33,47.6712400,9.2701300,98.7,1450.6,120.6,-5.1,1.0,118.2,-45.1,0.0,11.3\n"
        "1100,2019-08-10 10:22:34,47.6712900,9.2701800,99.0,1450.9,120.7,-5.0,0.9,118.4,-45.2,0.0,11.4\n"
    )
    records = parse_csv(text, source="airdata.csv")
    t0 = utc(2019, 8, 10, 10, 22, 33)
    assert [r.t for r in records] == pytest.approx([t0, t0 + 0.1, t0 + 1.1])
    first = records[0]
    assert first.height_m == pytest.approx(98.4 * 0.3048)
    assert (first.pitch_deg, first.heading_deg, first.roll_deg) == pytest.approx((45.0, 118.0, 0.0))
    assert first.speed_mps == pytest.approx(11.2 * 0.44704)


def test_csv_iso_timestamps_are_epoch_seconds():
    text = "timestamp,lat,lon,altitude\n2021-05-08T13:34:31.5Z,47,9,40\n2021-05-08T15:34:32+02:00,47,9,41\n"
    first, second = parse_csv(text)
    assert first.t == pytest.approx(utc(2021, 5, 8, 13, 34, 31) + 0.5)
    assert second.t == pytest.approx(utc(2021, 5, 8, 13, 34, 32))


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("", r"data\.csv: empty"),
        ("time,lat,lon\n0,1,2\n", r"missing required column 'height'"),
        ("time,latitude,height\n0,1,2\n", r"missing required column 'lon'"),
        ("lat,lon,height\n1,2,3\n", r"missing required column 'time'"),
        ("time,lat,lon,height\n", r"no data rows"),
        ("time,lat,lon,height\n0,1,2,30\n1,1,abc,30\n", r"data\.csv:3: column 'lon': 'abc' is not a number"),
        ("time,lat,lon,height\n0,1,2,30\n\n1,1,2\n", r"data\.csv:4: 3 cells"),
        ("time,lat,lon,height\n0,,2,30\n", r"data\.csv:2: column 'lat' is empty"),
        ("time,lat,lon,height\n0,95,2,30\n", r"data\.csv:2: Telemetry\.lat"),
        ("time,lat,lon,height,frame\n0,1,2,30,1.5\n", r"data\.csv:2: column 'frame'"),
        ("time(fortnight),lat,lon,height\n0,1,2,30\n", r"column 'time\(fortnight\)': unknown unit"),
        ("time,lat,Lat,lon,height\n0,1,1,2,30\n", r"same field"),
        ("time,lat,lon,height\nnan,1,2,30\n", r"data\.csv:2: column 'time'"),
        ("datetime,lat,lon,height\n2021-02-30 10:00:00,1,2,30\n", r"data\.csv:2: column 'datetime'"),
        ('time,lat,lon,height\n0,1,2,"30\n', r"data\.csv"),
    ],
)
def test_malformed_csv_raises_value_error_with_line_and_column(text, pattern):
    with pytest.raises(ValueError, match=pattern):
        parse_csv(text, source="data.csv")


def test_read_csv_by_extension(tmp_path):
    path = tmp_path / "log.CSV"
    path.write_text("time,lat,lon,height\n0,1,2,30\n")
    (rec,) = read_telemetry(path, height_offset_m=-5.0)
    assert rec.height_m == 25.0


# ---------------------------------------------------------------------------------------------
# Dates
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("2020-08-24T15:45:20", utc(2020, 8, 24, 15, 45, 20)),
        ("2020-08-24 15:45:20.25", utc(2020, 8, 24, 15, 45, 20) + 0.25),
        ("2020:08:24 15:45:20", utc(2020, 8, 24, 15, 45, 20)),
        ("2017.07.29 15:18:50", utc(2017, 7, 29, 15, 18, 50)),
        ("2022-08-07 13:40:40,774,808", utc(2022, 8, 7, 13, 40, 40) + 0.774808),
        ("2020-08-24T17:45:20+02:00", utc(2020, 8, 24, 15, 45, 20)),
        ("2020-08-24T15:45:20Z", utc(2020, 8, 24, 15, 45, 20)),
    ],
)
def test_parse_datetime_forms(text, expected):
    assert parse_datetime(text) == pytest.approx(expected, abs=1e-6)


# ---------------------------------------------------------------------------------------------
# Interpolation
# ---------------------------------------------------------------------------------------------


def rec(t, heading=0.0, lat=47.0, lon=9.0, height=30.0, pitch=45.0, frame=None, roll=0.0):
    return Telemetry(
        t=t, lat=lat, lon=lon, height_m=height, pitch_deg=pitch, heading_deg=heading, roll_deg=roll, frame=frame
    )


def test_interpolation_crosses_359_to_1_through_north():
    out = interpolate([rec(0.0, heading=359.0), rec(1.0, heading=1.0)], [0.25, 0.5, 0.75])
    assert [circular_diff_deg(o.heading_deg, e) for o, e in zip(out, [359.5, 0.0, 0.5], strict=True)] == pytest.approx(
        [0.0, 0.0, 0.0], abs=1e-9
    )


def test_interpolation_roll_and_longitude_take_the_short_way():
    out = interpolate([rec(0.0, lon=179.8, roll=-179.0), rec(2.0, lon=-179.8, roll=179.0)], [1.0])
    assert abs(out[0].lon) == pytest.approx(180.0)
    assert abs(out[0].roll_deg) == pytest.approx(180.0)


def test_interpolation_is_linear_and_none_outside_unless_tolerated():
    records = [rec(10.0, lat=47.0, height=30.0, pitch=40.0, frame=300), rec(12.0, lat=47.002, height=34.0, pitch=50.0)]
    before, a, mid, b, after = interpolate(records, np.array([9.9, 10.0, 11.0, 12.0, 12.1]))
    assert before is None and after is None
    assert (mid.lat, mid.height_m, mid.pitch_deg, mid.t) == pytest.approx((47.001, 32.0, 45.0, 11.0))
    assert a.frame == 300 and mid.frame is None
    held = interpolate(records, [9.9, 12.1], extrapolate_s=0.2)
    assert held[0].lat == 47.0 and held[0].t == 9.9
    assert held[1].height_m == 34.0


@settings(max_examples=200, deadline=None)
@given(steps=st.lists(st.floats(0.05, 12.0), min_size=1, max_size=12), max_gap=st.floats(0.0, 3.0),
       queries=st.lists(st.floats(-5.0, 80.0), min_size=1, max_size=20))
@example(steps=[1.0], max_gap=0.0, queries=[-3.9e-93])  # a hair before the first record, nothing held
def test_interpolation_leaves_frames_in_a_gap_of_the_log_without_a_pose(steps, max_gap, queries):
    """A radio dropout or a paused logger: a time farther than max_gap_s from both records around it gets None
    (a pose drawn straight across the gap is a guess); nearer, or without max_gap_s, the interpolation as before."""
    times = np.concatenate([[0.0], np.cumsum(steps)])
    records = [rec(float(t), lat=47.0 + 1e-5 * float(t)) for t in times]
    plain = interpolate(records, queries, extrapolate_s=max_gap)
    gapped = interpolate(records, queries, extrapolate_s=max_gap, max_gap_s=max_gap)
    for q, a, b in zip(queries, plain, gapped, strict=True):
        nearest = float(np.min(np.abs(times - q)))
        if not times[0] - max_gap <= q <= times[-1] + max_gap:  # beyond the ends: held up to max_gap only
            assert a is None and b is None
        elif nearest <= max_gap + 1e-9:  # float stamps: the tolerance interpolate allows inside the span
            assert a is not None and b is not None and b.lat == a.lat
        else:  # inside the span, in a gap
            assert a is not None and b is None
    with pytest.raises(ValueError, match="max_gap_s"):
        interpolate(records, queries, max_gap_s=-1.0)


def test_interpolation_missing_optional_field_gives_none():
    records = [rec(0.0, pitch=None), rec(1.0, pitch=30.0), rec(2.0, pitch=40.0)]
    out = interpolate(records, [0.5, 1.5])
    assert out[0].pitch_deg is None
    assert out[1].pitch_deg == pytest.approx(35.0)


def test_interpolation_carries_a_zoom_lens_field_of_view_linearly_and_none_where_a_record_lacks_it():
    records = [replace(rec(0.0), hfov_deg=None), replace(rec(1.0), hfov_deg=40.0), replace(rec(2.0), hfov_deg=20.0)]
    out = interpolate(records, [0.5, 1.0, 1.25])
    assert out[0].hfov_deg is None
    assert (out[1].hfov_deg, out[2].hfov_deg) == pytest.approx((40.0, 35.0))


@pytest.mark.parametrize("hfov", [0.0, 180.0, -5.0, float("nan"), "60"])
def test_a_field_of_view_outside_0_to_180_is_refused_naming_it(hfov):
    with pytest.raises(ValueError, match="hfov_deg"):
        Telemetry(t=0.0, lat=47.0, lon=9.0, height_m=30.0, pitch_deg=45.0, heading_deg=0.0, hfov_deg=hfov)


def test_interpolation_missing_height_gives_none_and_to_pose_asks_for_one():
    records = [rec(0.0, height=None), rec(1.0, height=20.0), rec(2.0, height=30.0)]
    out = interpolate(records, [0.5, 1.5])
    assert out[0].height_m is None and out[1].height_m == pytest.approx(25.0)
    with pytest.raises(ValueError, match="no height above ground: pass --height-m"):
        out[0].to_pose()
    assert out[0].to_pose(height_m=12.0).height_m == 12.0
    assert out[1].to_pose(height_m=12.0).height_m == pytest.approx(25.0)  # never replaces a logged height


def test_interpolation_rejects_unsorted_and_empty():
    with pytest.raises(ValueError, match="sorted"):
        interpolate([rec(1.0), rec(0.0)], [0.5])
    with pytest.raises(ValueError, match="at least one"):
        interpolate([], [0.5])
    with pytest.raises(ValueError, match="finite"):
        interpolate([rec(0.0)], [float("nan")])


def test_interpolation_of_real_srt_to_frame_times():
    records = parse_srt(MATRICE_30_SRT)
    mid = (records[0].t + records[1].t) / 2.0
    (out,) = interpolate(records, [mid])
    assert out.height_m == pytest.approx((55.774 + 55.759) / 2.0)
    assert out.heading_deg == pytest.approx(276.4)


# ---------------------------------------------------------------------------------------------
# Property tests
# ---------------------------------------------------------------------------------------------

LAT = st.floats(-89.9, 89.9).filter(lambda x: abs(x) > 1e-3)
LON = st.floats(-179.9, 179.9)


def srt_timing(start_s: float, end_s: float) -> str:
    def stamp(s: float) -> str:
        ms = round(s * 1000)
        return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"

    return f"{stamp(start_s)} --> {stamp(end_s)}"


samples_bracket = st.lists(
    st.tuples(
        LAT,
        LON,
        st.floats(0.1, 500.0),
        st.floats(-90.0, 0.0),
        st.floats(-180.0, 180.0),
        st.floats(-10.0, 10.0),
        st.integers(1, 2000),
    ),
    min_size=1,
    max_size=8,
)


@settings(max_examples=60, deadline=None)
@given(samples=samples_bracket, base_ms=st.integers(1_400_000_000_000, 1_900_000_000_000))
def test_property_bracket_srt_round_trip(samples, base_ms):
    blocks, t_ms = [], base_ms
    for i, (lat, lon, height, gb_pitch, gb_yaw, roll, step_ms) in enumerate(samples, start=1):
        t_ms += step_ms
        date = datetime.fromtimestamp(t_ms // 1000, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        blocks.append(
            f"{i}\n{srt_timing((t_ms - base_ms) / 1000, (t_ms - base_ms) / 1000 + 0.033)}\n"
            f'<font size="28">FrameCnt: {i}, DiffTime: 33ms\n{date}.{t_ms % 1000:03d}\n'
            f"[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [latitude: {lat:.6f}] [longitude: {lon:.6f}] "
            f"[rel_alt: {height:.3f} abs_alt: {height + 400:.3f}] "
            f"[gb_yaw: {gb_yaw:.1f} gb_pitch: {gb_pitch:.1f} gb_roll: {roll:.1f}] </font>\n"
        )
    records = parse_srt("\n".join(blocks))
    assert len(records) == len(samples)
    t_ms = base_ms
    for i, (record, (lat, lon, height, gb_pitch, gb_yaw, roll, step_ms)) in enumerate(
        zip(records, samples, strict=True), start=1
    ):
        t_ms += step_ms
        assert record.t == pytest.approx(t_ms / 1000, abs=1e-6)
        assert (record.lat, record.lon, record.height_m) == pytest.approx((lat, lon, height), abs=6e-4)
        assert record.pitch_deg == pytest.approx(-round(gb_pitch, 1) + 0.0, abs=1e-9)
        assert circular_diff_deg(record.heading_deg, round(gb_yaw, 1)) < 1e-9
        assert record.roll_deg == pytest.approx(round(roll, 1), abs=1e-9)
        assert record.frame == i


@settings(max_examples=60, deadline=None)
@given(
    samples=st.lists(st.tuples(LAT, LON, st.floats(0.0, 500.0), st.integers(6, 25)), min_size=1, max_size=8),
    base_s=st.integers(1_400_000_000, 1_900_000_000),
)
def test_property_mavic_pro_tuple_srt_round_trip(samples, base_s):
    blocks = []
    for i, (lat, lon, height, sats) in enumerate(samples):
        date = datetime.fromtimestamp(base_s + i, tz=timezone.utc).strftime("%Y.%m.%d %H:%M:%S")
        blocks.append(
            f"{i + 1}\n{srt_timing(i + 1.0, i + 2.0)}\nHOME({lon:.4f},{lat:.4f}) {date}\n"
            f"GPS({lon:.4f},{lat:.4f},{sats}) BAROMETER:{height:.1f}\nISO:100 Shutter:60 EV: Fnum:2.2 \n"
        )
    text = "\n".join(blocks)
    assume(any(round(lat, 4) != 0.0 or round(lon, 4) != 0.0 for lat, lon, _, _ in samples))
    records = parse_srt(text)
    kept = [s for s in samples if round(s[0], 4) != 0.0 or round(s[1], 4) != 0.0]
    assert len(records) == len(kept)
    for record, (lat, lon, height, _) in zip(records, kept, strict=True):
        assert (record.lat, record.lon) == pytest.approx((round(lat, 4), round(lon, 4)), abs=1e-9)
        assert record.height_m == pytest.approx(round(height, 1), abs=1e-9)


telemetry_records = st.builds(
    Telemetry,
    t=st.floats(0.0, 2e9),
    lat=st.floats(-90.0, 90.0),
    lon=st.floats(-180.0, 180.0),
    height_m=st.floats(-10.0, 1000.0),
    pitch_deg=st.none() | st.floats(0.0, 90.0),
    heading_deg=st.none() | st.floats(0.0, 359.999),
    roll_deg=st.floats(-180.0, 179.999),
    speed_mps=st.none() | st.floats(0.0, 40.0),
    vel_en_mps=st.none(),
    frame=st.none() | st.integers(0, 10**6),
)


@settings(max_examples=80, deadline=None)
@given(st.lists(telemetry_records.filter(lambda r: (r.lat, r.lon) != (0.0, 0.0)), min_size=1, max_size=10,
                unique_by=lambda r: r.t))
def test_property_csv_round_trip_is_exact(records):
    # distinct stamps (repeated whole-second stamps are spread over their second) and a GPS fix (0, 0 is a
    # logger's "no fix": test_csv_rows_without_a_fix_or_cut_short_are_skipped_and_counted)
    header = "time_s,latitude,longitude,height_m,pitch_deg,heading_deg,roll_deg,speed_mps,frame"

    def cell(value):
        return "" if value is None else repr(value)

    lines = [header] + [
        ",".join(
            cell(v)
            for v in (r.t, r.lat, r.lon, r.height_m, r.pitch_deg, r.heading_deg, r.roll_deg, r.speed_mps, r.frame)
        )
        for r in records
    ]
    assert parse_csv("\n".join(lines) + "\n") == records


@settings(max_examples=80, deadline=None)
@given(
    telemetry_records.filter(lambda r: r.height_m is not None),
    st.none() | st.tuples(st.floats(-30.0, 30.0), st.floats(-30.0, 30.0)),
)
def test_property_seadronessee_meta_round_trip(record, vel):
    assume((record.lat, record.lon) != (0.0, 0.0))  # (0, 0) is no GPS fix: no record (tested apart)
    tel = Telemetry(
        t=record.t,
        lat=record.lat,
        lon=record.lon,
        height_m=record.height_m,
        pitch_deg=record.pitch_deg,
        heading_deg=record.heading_deg,
        speed_mps=record.speed_mps,
        vel_en_mps=vel,
    )
    back = from_seadronessee_meta(json.loads(json.dumps(to_seadronessee_meta(tel))))
    assert back.t == pytest.approx(tel.t, abs=1e-5)
    assert (back.lat, back.lon, back.height_m) == (tel.lat, tel.lon, tel.height_m)
    assert (back.pitch_deg, back.heading_deg, back.speed_mps) == (tel.pitch_deg, tel.heading_deg, tel.speed_mps)
    assert back.vel_en_mps == tel.vel_en_mps


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.01, 10.0), st.floats(0.0, 359.999), st.floats(0.0, 90.0)), min_size=2, max_size=8),
    st.floats(0.0, 1.0),
)
def test_property_interpolation_hits_records_and_stays_on_the_short_arc(steps, fraction):
    records, t = [], 0.0
    for dt, heading, pitch in steps:
        t += dt
        records.append(rec(t, heading=heading, pitch=pitch))
    at_records = interpolate(records, [r.t for r in records])
    for got, want in zip(at_records, records, strict=True):
        assert circular_diff_deg(got.heading_deg, want.heading_deg) < 1e-9
        assert got.pitch_deg == pytest.approx(want.pitch_deg)
    for a, b in pairwise(records):
        (mid,) = interpolate(records, [a.t + fraction * (b.t - a.t)])
        arc = circular_diff_deg(a.heading_deg, b.heading_deg)
        if arc > 179.0:  # near 180 both ways are about equally short
            continue
        assert circular_diff_deg(mid.heading_deg, a.heading_deg) == pytest.approx(fraction * arc, abs=1e-6)
        assert circular_diff_deg(mid.heading_deg, b.heading_deg) == pytest.approx((1 - fraction) * arc, abs=1e-6)
        assert min(a.pitch_deg, b.pitch_deg) - 1e-9 <= mid.pitch_deg <= max(a.pitch_deg, b.pitch_deg) + 1e-9


# Every variant's first block (or a skipped one) with the position it must give, None = skipped.
SRT_BLOCK_CATALOGUE = [
    (MAVIC_PRO_SRT.split("\n\n")[0], (-25.2088, 131.1660)),
    (PHANTOM_4_EUROPE_SRT, (47.6893, 9.1832)),
    (MAVIC_MINI_SRT, (27.7716, -82.6669)),
    (P4_RTK_SRT, (30.213635, 120.083799)),
    (MATRICE_300_SRT.split("\n\n")[0], (36.6153, -6.1130)),
    (MAVIC_2_SRT, (38.904148, -92.281307)),
    (AIR_2S_SRT.split("\n\n")[0], (41.424724, 2.234156)),
    (MINI_3_SRT, (-22.724555, -47.602414)),
    (MATRICE_30_SRT.split("\n\n")[1], (53.388452, 5.361783)),
    (NO_TIMING_LINE_SRT.split("\n\n")[0], (22.543096, 113.958321)),
    (MAVIC_2_PRO_NO_ALTITUDE_SRT.split("\n\n")[0], (38.887375, -77.034671)),
    (OLD_HB_HS_SRT.split("\n\n")[1], (47.3770, 8.5418)),
    (COUNTER_ONLY_SRT.split("\n\n")[2], (22.543098, 113.958323)),
    (MAVIC_PRO_NO_FIX_SRT.split("\n\n")[0], None),
    (MAVIC_AIR_EXPOSURE_ONLY_SRT.split("\n\n")[0], None),
]

_SPACE = st.sampled_from(["", " ", "  ", "\t"])


@st.composite
def shuffled_srt_files(draw):
    """A file of catalogue blocks in any order, with DJI-like whitespace: CRLF/CR/LF, BOM, padding, blank lines."""
    picks = draw(st.lists(st.integers(0, len(SRT_BLOCK_CATALOGUE) - 1), min_size=1, max_size=10))
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    chunks = []
    for pick in picks:
        lines = SRT_BLOCK_CATALOGUE[pick][0].strip("\n").split("\n")
        chunks.append(newline.join(draw(_SPACE) + line + draw(_SPACE) for line in lines))
    separators = [newline + newline.join(draw(_SPACE) for _ in range(draw(st.integers(1, 3)))) + newline
                  for _ in picks[1:]]
    text = chunks[0] + "".join(sep + chunk for sep, chunk in zip(separators, chunks[1:], strict=True))
    text = newline * draw(st.integers(0, 2)) + text + newline * draw(st.integers(0, 2))
    if draw(st.booleans()):
        text = "\ufeff" + text
    return text, [SRT_BLOCK_CATALOGUE[pick][1] for pick in picks]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(shuffled_srt_files())
def test_property_any_order_and_whitespace_of_variant_blocks_loads_block_by_block(case):
    text, expected = case
    positions = [p for p in expected if p is not None]
    if not positions:
        with pytest.raises(ValueError, match=r"^flight\.srt: no block"):
            parse_srt(text, source="flight.srt")
        return
    report = parse_srt_report(text, source="flight.srt")
    assert [c for r in report.records for c in (r.lat, r.lon)] == pytest.approx([c for p in positions for c in p])
    assert len(report.skipped) == len(expected) - len(positions)
    assert report.blocks == len(expected)
    times = [r.t for r in report.records]
    assert all(b >= a for a, b in pairwise(times))
    assert report.gps_decimals in (4, 6)


SRT_TOKENS = [
    "1",
    "2",
    "17",
    "00:00:00,000 --> 00:00:01,000",
    "00:00:01,000 --> 00:00:02,000",
    "00:00:0x,000 --> 1",
    "-->",
    "[latitude: 47.1]",
    "[longitude: 9.2]",
    "[longtitude : -92.2]",
    "[latitude: 0.0] [longitude: 0.0]",
    "[rel_alt: 30.1 abs_alt: 450.2]",
    "[abs_alt: 450.2]",
    "[altitude: 117.0]",
    "GPS(9.1,47.2,12)",
    "GPS(36.6,-6.1,0.0M)",
    "GPS(200,200,1)",
    "GPS()",
    "RTK (120.1, 30.2, 28)",
    "BAROMETER:3.0",
    "BAROMETER:x",
    "H 30.00m",
    "H.S 2.0m/s",
    "[gb_yaw: 10 gb_pitch: -45 gb_roll: 0]",
    "[gb_pitch: 40]",
    "[gb_pitch: ]",
    "G.PRY (-45.0°, 0.0°, 10.0°)",
    "G.PRY (a, b, c)",
    "F.PRY (1°, 2°, 3°)",
    "FrameCnt: 3, DiffTime: 33ms",
    "SrtCnt : x",
    "2021-05-08 13:34:31.123",
    "2017.07.29 15:18:50",
    "2021-99-99 99:99:99",
    "2021-05-08 1x",
    '<font size="28">',
    "</font>",
    "",
    " ",
    "[latitude: 1e999]",
    "[latitude: 99999999999999999999]",
    "99999999999999999999:00:00,000 --> 00:00:01,000",
    "[latitude: -]",
    "HOME(1,2)",
    "GPS(8.5417,47.3769,19) Hb:1.9 Hs:1.9",
    "Hb:x Hs:",
    "GPS(N/A,N/A,4) BAROMETER:0.0",
    "GPS(n/a,1,2)",
    "2017.08.05 14:11:51,393,525",
    "[latitude : 22.543096] [longtitude : 113.958321]",
    "FrameCnt : 2, DiffTime : 42ms",
    "DiffTime : xms",
]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.sampled_from(SRT_TOKENS) | st.text(max_size=12), max_size=30).map("\n".join))
def test_property_junk_srt_raises_only_value_error(text):
    try:
        records = parse_srt(text)
    except ValueError:
        return
    assert records and all(isinstance(r, Telemetry) for r in records)
    assert all(b.t >= a.t for a, b in pairwise(records))


@settings(max_examples=200, deadline=None)
@given(st.text())
def test_property_random_text_raises_only_value_error(text):
    for parser in (parse_srt, parse_csv):
        try:
            parser(text)
        except ValueError:
            pass


CSV_CELLS = [
    "0",
    "1.5",
    "-45",
    "95",
    "",
    "abc",
    "nan",
    "inf",
    "1e400",
    "2021-05-08T13:34:31Z",
    "2021-02-30 1:00:00",
    '"',
    '"1,2"',
    "-0",
    "360",
]
CSV_HEADERS = [
    "time",
    "t",
    "datetime",
    "lat",
    "latitude",
    "lon",
    "lng",
    "height",
    "rel_alt",
    "pitch",
    "gb_pitch",
    "yaw",
    "roll",
    "speed(mph)",
    "frame",
    "time(ms)",
    "time(parsec)",
    "Lat",
    "x",
]


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.sampled_from(CSV_HEADERS), min_size=1, max_size=8),
    st.lists(st.lists(st.sampled_from(CSV_CELLS), min_size=1, max_size=9), max_size=5),
)
def test_property_junk_csv_raises_only_value_error(header, rows):
    text = "\n".join([",".join(header)] + [",".join(row) for row in rows])
    try:
        records = parse_csv(text)
    except ValueError:
        return
    assert len(records) == len(rows)


@pytest.mark.parametrize("gb_pitch", ["12.0", "-93.0"])
def test_srt_camera_tilted_up_or_past_nadir_gives_no_pitch_for_that_sample_only(gb_pitch, caplog):
    records = parse_srt(MATRICE_30_SRT.replace("gb_pitch: -9.1", f"gb_pitch: {gb_pitch}", 1), source="flight.srt")
    assert records[0].pitch_deg is None
    assert all(r.pitch_deg is not None for r in records[1:])
    assert "flight.srt:5" in caplog.text
    with pytest.raises(ValueError, match="no gimbal pitch"):
        records[0].to_pose()


def test_csv_camera_tilted_up_gives_no_pitch_for_that_row():
    text = "time,lat,lon,height_m,gb_pitch,heading\n0,47.0,9.0,30,-45,10\n1,47.0,9.0,30,15,10\n"
    records = parse_csv(text)
    assert records[0].pitch_deg == pytest.approx(45.0) and records[1].pitch_deg is None


# ---------------------------------------------------------------------------------------------
# CSV quirks of real logs (a helper's probe, 29 Nov 2026): units the header does not say, whole-second stamps,
# rows before the GPS fix, a logger killed mid-line, two drones in one file
# ---------------------------------------------------------------------------------------------

_ROW = "48.53,9.06,30,45,{h}"


def _csv(times: list[str], header: str = "time", heading_step: float = 1.0) -> str:
    return f"{header},lat,lon,height_m,pitch_deg,heading_deg\n" + "".join(
        f"{t}," + _ROW.format(h=100 + heading_step * i) + "\n" for i, t in enumerate(times))


def test_a_unitless_time_column_in_milliseconds_is_read_as_milliseconds(caplog):
    # relative milliseconds (a 30 Hz log: steps of 33-34) and milliseconds since 1970
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.csv_table"):
        relative = parse_csv(_csv(["0", "33", "67", "100", "133"]))
    assert [r.t for r in relative] == pytest.approx([0.0, 0.033, 0.067, 0.1, 0.133])
    assert any("'time' read as milliseconds" in r.getMessage() for r in caplog.records)
    epoch = parse_csv(_csv(["1685613600000", "1685613600100", "1685613600200"], header="timestamp"))
    assert [r.t for r in epoch] == pytest.approx([1685613600.0, 1685613600.1, 1685613600.2])
    # beside a date column the milliseconds space the rows from the first date
    text = "datetime,timestamp,lat,lon,height_m\n" + "".join(
        f"2023-06-01 10:00:00,{1685613600000 + 100 * i},48.53,9.06,30\n" for i in range(3))
    assert [r.t for r in parse_csv(text)] == pytest.approx([utc(2023, 6, 1, 10, 0, 0) + 0.1 * i for i in range(3)])
    # seconds stay seconds: a 10 Hz log, a 1 Hz one, and a column that names its unit
    assert [r.t for r in parse_csv(_csv(["0", "0.1", "0.2"]))] == pytest.approx([0.0, 0.1, 0.2])
    assert [r.t for r in parse_csv(_csv(["100", "101", "102"]))] == pytest.approx([100.0, 101.0, 102.0])
    assert [r.t for r in parse_csv(_csv(["0", "20", "40"], header="time_s"))] == pytest.approx([0.0, 20.0, 40.0])


@pytest.mark.parametrize("stamps", [
    ["2023-06-01 10:00:00"] * 3 + ["2023-06-01 10:00:01"] * 3,  # ISO date-times in the time column
    ["1685613600"] * 3 + ["1685613601"] * 3,  # integer epoch seconds
])
def test_whole_second_stamps_in_the_time_column_are_spread_over_their_second(stamps):
    records = parse_csv(_csv(stamps))
    t = np.array([r.t for r in records]) - records[0].t
    assert t == pytest.approx([0.0, 1 / 3, 2 / 3, 1.0, 4 / 3, 5 / 3])
    # so every sample keeps its own pose at the frames: none is dropped as a duplicate stamp
    frames = interpolate(records, records[0].t + np.array([0.0, 0.34, 0.67, 1.34]))
    assert [f.heading_deg for f in frames] == pytest.approx([100.0, 101.02, 102.01, 104.02], abs=0.05)


def test_csv_rows_without_a_fix_or_cut_short_are_counted_and_the_clock_kept(caplog):
    text = ("time_s,lat,lon,height_m,pitch_deg,heading_deg,isVideo\n"
            "0,0.0,0.0,0,45,100,1\n0.1,0,0,0,45,100,1\n"  # recording before the GPS fix (AirData writes 0, 0)
            + "".join(f"{0.2 + 0.1 * i:.1f},48.53,9.06,30,45,100,1\n" for i in range(8))
            + "1.0,48.53,-200,30,45,100,1\n"  # a value out of range
            + "1.1,48.53,9.0")  # the logger killed mid-line
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.csv_table"):
        records = parse_csv(text, source="f.csv")
    # the rows before the fix stay: the log's clock (its first time, where recording starts) is the video's
    assert len(records) == 10 and records[0].t == 0.0 and records[0].recording
    message = " ".join(r.getMessage() for r in caplog.records)
    assert ("f.csv: 4 of 12 rows: 2 unreadable rows skipped, 2 without a GPS fix (0, 0) give no pose; first "
            "skipped: f.csv:12: Telemetry.lon") in message
    # the frames of those rows get no pose; the first fix's holds up to the extrapolation limit
    poses = interpolate(records, [0.0, 0.05, 0.15, 0.25], extrapolate_s=0.06)
    assert [p is None for p in poses] == [True, True, False, False]
    assert poses[2].lat == 48.53
    # a file of bad rows is the file's fault: the first problem is named
    with pytest.raises(ValueError, match=r"f\.csv:3: column 'lat': 'x' is not a number"):
        parse_csv("time_s,lat,lon,height_m\n0,48,9,30\n1,x,9,30\n2,y,9,30\n", source="f.csv")
    # and nothing but "no fix" gives no pose anywhere
    only = parse_csv("time_s,lat,lon,height_m\n0,0,0,30\n1,0,0,30\n", source="f.csv")
    assert interpolate(only, [0.0, 0.5]) == [None, None]


@pytest.mark.parametrize("row", ["2.0,48.53,9.06,30,abc,100", "2.0,48.53,9.06,30,45,100,7", "2.0,48.53,9.06,-,45,100"])
def test_one_bad_row_of_any_column_is_skipped_alike(row):
    # a bad pitch cell, a row with a cell too many, a bad height: each costs its row, not the file
    text = "time_s,lat,lon,height_m,pitch_deg,heading_deg\n" + "".join(
        f"{0.1 * i:.1f},48.53,9.06,30,45,100\n" for i in range(6)) + row + "\n"
    assert len(parse_csv(text)) == 6


def test_a_pitch_past_nadir_keeps_its_row_without_a_pitch_and_says_so_once(caplog):
    text = "time_s,lat,lon,height_m,pitch_deg,heading_deg\n" + "".join(
        f"{0.1 * i:.1f},48.53,9.06,30,{95 if i == 3 else 45},100\n" for i in range(6))
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.record"):
        records = parse_csv(text)
    assert [r.pitch_deg for r in records] == [45.0, 45.0, 45.0, None, 45.0, 45.0]
    assert sum("no pose for this sample" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("times, seconds", [
    (["0", "10", "20", "30"], True),  # a sparse log at 0.1 Hz, in seconds
    (["1700000000", "1700000015", "1700000030"], True),  # epoch seconds every 15 s
    (["0", "20", "40", "60"], False),  # 50 Hz in milliseconds
])
def test_the_millisecond_guess_leaves_sparse_seconds_alone(times, seconds):
    records = parse_csv(_csv(times))
    scale = 1.0 if seconds else 1e-3
    assert [r.t for r in records] == pytest.approx([float(t) * scale for t in times])


def test_the_millisecond_warning_is_said_once(caplog):
    text = "timestamp,lat,lon,height_m\n" + "".join(f"{1685613600000 + 100 * i},48.5,9.0,30\n" for i in range(50))
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.csv_table"):
        parse_csv(text, source="x.csv")
    assert sum("read as milliseconds" in r.getMessage() for r in caplog.records) == 1


def test_a_csv_of_two_drones_is_refused_by_name():
    text = "time_s,uav_id,lat,lon,height_m\n0,alpha,48.53,9.06,30\n0,bravo,48.60,9.10,50\n0.1,alpha,48.53,9.06,30\n"
    with pytest.raises(ValueError, match=r"f\.csv: column 'uav_id' names 2 drones \('alpha', 'bravo'\)"):
        parse_csv(text, source="f.csv")
    # one drone named in every row is fine
    assert len(parse_csv(text.replace("bravo", "alpha").replace("0,alpha,48.60", "0.05,alpha,48.60"))) == 3


def test_whole_second_srt_dates_under_finer_subtitle_timing_keep_the_timing():
    # Phantom 4 era: a block per frame (33 ms subtitle timing) but date lines at whole seconds; as stamps the
    # blocks of one second were one sample and every frame of that second took the first block's height
    blocks = []
    for i in range(45):
        start, end = round(i * 1000 / 30), round((i + 1) * 1000 / 30)
        second = (i * 1000 // 30 + 400) // 1000  # the recording began 0.4 s into 10:00:00
        blocks.append(f"{i + 1}\n00:00:{start // 1000:02d},{start % 1000:03d} --> 00:00:{end // 1000:02d},"
                      f"{end % 1000:03d}\nHOME(9.0592,48.5326) 2023.06.01 10:00:{second:02d}\n"
                      f"GPS(9.0582,48.5316,16) BAROMETER:{27.0 + 0.02 * i:.2f}M\nISO:100 Shutter:1000 EV:0 "
                      "Fnum:F2.8 \n")
    records = parse_srt("\n".join(blocks))
    t = np.array([r.t for r in records])
    assert np.all(np.diff(t) > 0)
    assert np.diff(t) == pytest.approx(1 / 30, abs=1e-3)
    # each block's time lies in the second its date line names (dates truncated to the second)
    seconds = np.array([(i * 1000 // 30 + 400) // 1000 for i in range(45)])
    assert np.all(np.floor(t - utc(2023, 6, 1, 10, 0, 0)) == seconds)
    # so the frames between blocks get their own heights, not the second's first
    heights = [r.height_m for r in interpolate(records, t[[5, 20, 40]])]
    assert heights == pytest.approx([27.1, 27.4, 27.8], abs=1e-6)


def test_a_bare_pitch_column_near_the_horizon_is_flagged_as_maybe_the_airframes(caplog):
    # AirData's pitch(degrees) is the airframe's (a few degrees, either sign); read as the camera's it looks at the
    # horizon (and nose-up rows, above the horizon, have no pitch at all)
    text = ("time_s,latitude,longitude,height_m,pitch(degrees),yaw(degrees)\n"
            "0,48.5,9.05,30,-3.1,120\n1,48.5,9.05,30,-2.0,121\n2,48.5,9.05,30,4.0,121\n")
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.csv_table"):
        records = parse_csv(text, source="air.csv")
    assert [r.pitch_deg for r in records] == pytest.approx([3.1, 2.0, None])
    assert any("air.csv: column 'pitch(degrees)' stays within 10 deg of the horizon" in r.getMessage()
               for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.csv_table"):
        parse_csv(text.replace("-3.1", "-45").replace("-2.0", "-44").replace(",4.0,", ",-46,"), source="air.csv")
    assert not caplog.records  # a gimbal's pitch


@pytest.mark.parametrize("sep, said", [(";", "';'"), ("\t", "tabs")])
def test_a_csv_separated_otherwise_is_named_in_the_error(sep, said):
    text = sep.join(["time_s", "lat", "lon", "height_m"]) + "\n" + sep.join(["0", "48,53", "9,06", "30"]) + "\n"
    with pytest.raises(ValueError, match=rf"f\.csv: missing required column 'lat' .*separated by {said}, not commas"):
        parse_csv(text, source="f.csv")


def test_whole_second_dates_keep_going_forward_when_the_timing_steps_back():
    from shared.telemetry.srt_clock import BlockTimes, monotonic_times

    # one second's blocks whose subtitle timing steps back once (a re-encoded file): the dates are kept as they are
    starts = [0.0, 0.033, 0.067, 0.050, 0.100]
    blocks = [BlockTimes(line=1 + 5 * i, epoch_s=1000.0, start_s=s, counter=None, diff_time_s=None)
              for i, s in enumerate(starts)]
    times, _ = monotonic_times(blocks)
    assert all(b >= a for a, b in pairwise(times))


@settings(max_examples=150, deadline=None)
@given(rows=st.lists(st.tuples(st.integers(0, 3), st.booleans(), st.floats(0.0, 359.0)), min_size=2, max_size=30),
       start=st.integers(1_600_000_000, 1_800_000_000))
def test_property_csv_whole_second_stamps_and_no_fix_rows(rows, start):
    # a log stamped at whole seconds (0-3 s steps, repeats), some rows before the GPS fix (0, 0)
    stamps, t = [], start
    for step, _, _ in rows:
        t += step
        stamps.append(t)
    assume(any(not no_fix for _, no_fix, _ in rows))
    text = "time,lat,lon,height_m,pitch_deg,heading_deg\n" + "".join(
        f"{s},{0 if no_fix else 48.5},{0 if no_fix else 9.05},30,45,{h}\n"
        for s, (_, no_fix, h) in zip(stamps, rows, strict=True))
    records = parse_csv(text)
    assert len(records) == len(rows)  # nothing is dropped: no-fix rows keep the log's clock
    times = [r.t for r in records]
    assert all(b > a for a, b in pairwise(times))  # repeated stamps are spread, none is dropped as a duplicate
    # each record stays within the second its stamp names
    assert all(s <= r < s + 1.0 for s, r in zip(stamps, times, strict=True))
    # interpolation never takes a (0, 0) sample for a position
    poses = interpolate(records, np.array(times), extrapolate_s=0.5)
    assert all(p is None or (p.lat, p.lon) == (48.5, 9.05) for p in poses)


def _joined_srt(restart_timing: bool = False) -> str:
    """Two 10 s clips at 10 blocks a second joined, their dates 30 minutes apart; the subtitle timing goes on across
    the join (or starts again at 0 with `restart_timing`)."""
    def ts(sec: float) -> str:
        ms = int(round(sec * 1000))
        return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"

    blocks, n = [], 0
    for clip, (minute, lat0) in enumerate(((0, 47.0), (30, 47.01))):
        for i in range(100):
            n += 1
            start = (0 if restart_timing else 10 * clip) + i / 10
            blocks.append(f"{n}\n{ts(start)} --> {ts(start + 0.1)}\nFrameCnt: {n}, DiffTime: 100ms\n"
                          f"2024-05-01 10:{minute + i // 600:02d}:{(i // 10) % 60:02d}.{(i % 10) * 100:03d}\n"
                          f"[latitude: {lat0 + i * 1e-6:.6f}] [longitude: 9.000000] [rel_alt: 30.000 abs_alt: 450.000] "
                          "[gb_yaw: 0.0 gb_pitch: -90.0 gb_roll: 0.0]\n")
    return "\n".join(blocks)


def test_joined_clips_are_put_on_the_videos_clock_by_their_subtitle_timing(caplog):
    """Kept on their dates, the second clip's records lay 30 minutes past the joined video's end: its frames had no
    pose (and the first second of it the first clip's last one)."""
    from shared.telemetry import interpolate

    with caplog.at_level(logging.WARNING):
        report = parse_srt_report(_joined_srt(), source="joined.srt")
        records = report.on_video_clock()
    assert report.records[-1].t - report.video_start_t > 1000  # the dates, as the report keeps them
    (pose,) = interpolate(records, [report.video_start_t + 15.0], max_gap_s=1.0)
    assert pose is not None and pose.lat == pytest.approx(47.01 + 50e-6, abs=2e-6)
    assert ("from record 101 on (subtitle time 10.000 s) its dates are 1790.0 s off the subtitle timing (two "
            "recordings joined, or a drifting clock?)") in caplog.text
    single = parse_srt_report(MATRICE_30_SRT, source="one.srt")
    assert single.on_video_clock() == single.records  # a consistent file: as it is
    restarted = parse_srt_report(_joined_srt(restart_timing=True), source="restart.srt")
    assert restarted.on_video_clock() == restarted.records  # a timing that starts again is no video clock

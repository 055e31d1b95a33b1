"""Telemetry CSV files as other tools write them (shared.telemetry.csv_table): whole-second dates beside a fine
clock, a first second cut short, a clock that starts again, a single reading above the horizon, missing values as
NaN / NA, yes/no as True / False, several drones under other column names. Each case failed before (a helper's audit,
proof scripts in the commit's note)."""

from __future__ import annotations

import datetime as dt
import logging
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry.csv_table import parse_csv

START = dt.datetime(2024, 5, 1, 10, 0, 0, tzinfo=dt.timezone.utc)
AIRDATA = ("time(millisecond),datetime(utc),latitude,longitude,height_above_takeoff(feet),gimbal_heading(degrees),"
           "gimbal_pitch(degrees),isVideo")


def _stamp(seconds: float) -> str:
    return (START + dt.timedelta(seconds=seconds)).strftime("%Y-%m-%d %H:%M:%S")  # truncated to the second


@settings(max_examples=50, deadline=None)
@given(st.floats(0.0, 0.999), st.integers(20, 200))
def test_whole_second_dates_beside_a_fine_clock_place_the_flight_to_a_sample(phase, rows):
    """AirData: datetime(utc) at whole seconds, time(millisecond) fine. The first row's date alone put a flight
    starting at .9 s 0.9 s early; every row's date bounds the start to one 10 Hz sample."""
    text = "\n".join([AIRDATA] + [f"{100 * i},{_stamp(phase + 0.1 * i)},47.0,9.0,100,0,-90,1" for i in range(rows)])
    records = parse_csv(text)
    truth = START.timestamp() + phase
    assert records[0].t == pytest.approx(truth, abs=0.1)
    assert [r.t - records[0].t for r in records] == pytest.approx([0.1 * i for i in range(rows)], abs=1e-6)


@settings(max_examples=50, deadline=None)
@given(st.floats(0.0, 0.999), st.integers(25, 80))
def test_a_first_second_cut_short_holds_the_end_of_that_second(phase, rows):
    """Only whole-second dates, 10 rows a second, the log starting at .7 s: the first second's 3 rows are .7, .8, .9
    (spread over the whole second they were .0, .33, .67, and every later frame's pose came 0.7 s early)."""
    text = "\n".join(["datetime(utc),latitude,longitude,height_above_takeoff(meter),gimbal_pitch(degrees)"]
                     + [f"{_stamp(phase + 0.1 * i)},47.0,9.0,30,-90" for i in range(rows)])
    records = parse_csv(text)
    truth = [START.timestamp() + phase + 0.1 * i for i in range(rows)]
    assert max(abs(r.t - t) for r, t in zip(records, truth, strict=True)) < 0.1 + 1e-6


def test_a_time_column_that_starts_again_is_placed_by_its_dates(caplog):
    """Two logs joined: time(millisecond) back to 0 ten minutes later while datetime(utc) goes on. The second part
    was laid over the first part's times (sorted by time, the pose jumped 1.1 km every sample)."""
    rows = [AIRDATA]
    for part, t0 in enumerate((0.0, 600.0)):
        rows += [f"{100 * i},{_stamp(t0 + 0.1 * i)},{47 + 0.01 * part:.4f},9.0,100,0,-90,1" for i in range(50)]
    with caplog.at_level(logging.WARNING):
        records = parse_csv("\n".join(rows), source="joined.csv")
    assert records[50].t - records[0].t == pytest.approx(600.0, abs=0.1)
    assert all(b.t > a.t for a, b in zip(records, records[1:], strict=False))
    assert "joined.csv: column 'time(millisecond)' starts again 1 time(s) (first at line 52)" in caplog.text


def test_one_reading_above_the_horizon_does_not_flip_the_pitch_convention(caplog):
    """Positive below the horizon, one row at -3 (the camera tilted up): that row has no pitch; before, the one
    negative value made the whole column DJI's (negative down) and every other row lost its pitch."""
    text = "\n".join(["time_s,lat,lon,height_m,gimbal_pitch"]
                     + [f"{i},47.0,9.0,30,{p}" for i, p in enumerate([40, 30, 20, 10, 5, -3, 10, 20])])
    with caplog.at_level(logging.WARNING):
        records = parse_csv(text)
    assert [r.pitch_deg for r in records] == [40, 30, 20, 10, 5, None, 10, 20]
    dji = parse_csv(text.replace(",40\n", ",-40\n").replace(",30\n", ",-30\n").replace(",20\n", ",-20\n")
                    .replace(",10\n", ",-10\n").replace(",5\n", ",-5\n").replace(",20", ",-20"))
    assert [r.pitch_deg for r in dji][:3] == [40, 30, 20]  # mostly negative: DJI's sign


@pytest.mark.parametrize("missing", ["NaN", "nan", "NA", "null", "n/a"])
def test_missing_values_written_as_words_are_empty_cells(missing):
    text = "\n".join(["time_s,lat,lon,height_m,pitch_deg,speed_mps"]
                     + [f"{i},47.0,9.0,30,60,{missing if i % 3 else 4.5}" for i in range(9)])
    records = parse_csv(text)
    assert len(records) == 9
    assert [r.speed_mps for r in records] == [4.5 if i % 3 == 0 else None for i in range(9)]


def test_a_yes_no_column_written_as_true_false_is_read():
    text = "\n".join(["time_s,lat,lon,height_m,pitch_deg,isVideo"]
                     + [f"{i},47.0,9.0,30,60,{'True' if i >= 2 else 'False'}" for i in range(5)])
    assert [r.recording for r in parse_csv(text)] == [False, False, True, True, True]
    with pytest.raises(ValueError, match="'True' is not a number"):  # a yes/no word in a number column stays wrong
        parse_csv(text.replace(",60,", ",True,"))


@pytest.mark.parametrize("column", ["uas_id", "serial_number", "drone_name", "aircraft_name", "aircraft_sn"])
def test_a_column_naming_several_drones_is_refused_under_its_other_names(column):
    text = "\n".join([f"time_s,{column},lat,lon,height_m,pitch_deg"]
                     + [f"{0.05 * i},{'A' if i % 2 else 'B'},{47.0 + 0.01 * (i % 2)},9.0,30,60" for i in range(10)])
    with pytest.raises(ValueError, match=f"column '{column}' names 2 drones"):
        parse_csv(text)


def test_rows_further_apart_than_a_drone_flies_are_named(caplog):
    """Two drones 1.1 km apart interleaved under an unnamed column (or GPS glitches): said, with the first line."""
    text = "\n".join(["time_s,lat,lon,height_m,pitch_deg"]
                     + [f"{0.1 * i},{47.0 + 0.01 * (i % 2)},9.0,30,60" for i in range(10)])
    with caplog.at_level(logging.WARNING):
        records = parse_csv(text, source="mixed.csv")
    assert len(records) == 10
    assert "mixed.csv: the position jumps faster than 150 m/s between 9 pairs of rows (first at line 3)" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # 15 m/s: a drone
        parse_csv("\n".join(["time_s,lat,lon,height_m,pitch_deg"]
                            + [f"{0.1 * i},{47.0 + 1.5 * i / 111_320.0:.8f},9.0,30,60" for i in range(10)]))
    assert "jumps" not in caplog.text
    assert math.isfinite(records[0].t)


def test_a_start_date_on_every_row_beside_elapsed_seconds_stays_exact():
    """date_time the log's start on every row, time_s the seconds since: date + time, exactly (the second read found
    the truncation rule moving such a flight by half its length)."""
    text = "\n".join(["time_s,date_time,lat,lon,height_m,pitch_deg"]
                     + [f"{i},{_stamp(0.0)},47.0,9.0,30,60" for i in range(600)])
    records = parse_csv(text)
    assert records[0].t == pytest.approx(START.timestamp()) and records[-1].t == pytest.approx(START.timestamp() + 599)


@settings(max_examples=60, deadline=None)
@given(gps_every=st.integers(2, 20), phase=st.integers(0, 19), east=st.booleans(), feet=st.booleans())
def test_a_gps_slower_than_the_rows_is_filled_between_its_fixes(gps_every, phase, east, feet):
    # a 10 Hz log of the gimbal whose position cells are written only in the rows where a fix arrived (merged
    # exports): each row a record with its own heading, the position linear between the fixes (until 1 Dec 2026
    # refused: "column 'latitude' is empty"); rows before the first fix and after the last are skipped and counted
    phase %= gps_every
    lon0 = 179.9999 if east else 9.06  # across the antimeridian, the short way round
    unit = 0.3048 if feet else 1.0
    header = f"time_s,latitude,longitude,{'height(feet)' if feet else 'height_m'},gimbal_pitch,gimbal_heading"
    rows = [header]
    for k in range(200):
        t = k / 10.0
        fix = k % gps_every == phase
        lon = (lon0 + 5.7e-5 * t + 180.0) % 360.0 - 180.0
        cells = (f"{48.53 + 3.8e-5 * t:.8f}", f"{lon:.8f}", f"{(40.0 + 0.5 * t) / unit:.3f}") if fix else ("", "", "")
        rows.append(f"{t:.1f},{cells[0]},{cells[1]},{cells[2]},-30.0,{k % 360}")
    records = parse_csv("\n".join(rows) + "\n", source="sparse.csv")
    fixes = [k for k in range(200) if k % gps_every == phase]
    assert [round(r.t * 10) for r in records] == list(range(fixes[0], fixes[-1] + 1))
    assert [r.heading_deg for r in records] == [float(k % 360) for k in range(fixes[0], fixes[-1] + 1)]
    for r in records:
        assert r.lat == pytest.approx(48.53 + 3.8e-5 * r.t, abs=1e-8)
        assert math.remainder(r.lon - (lon0 + 5.7e-5 * r.t), 360.0) == pytest.approx(0.0, abs=1e-8)
        assert -180.0 <= r.lon < 180.0
        assert r.height_m == pytest.approx(40.0 + 0.5 * r.t, abs=2e-3)


def test_sparse_positions_are_not_filled_across_a_long_gap_a_no_fix_row_or_one_missing_cell(caplog):
    # 10 Hz rows with fixes at 0, 1, 2 and 3 s; then a row a second with no fix until 12 s (9 s: too long to
    # fill); then a fix on every row
    times = [k / 10.0 for k in range(30)] + [3.0 + k for k in range(10)] + [12.0 + k / 10.0 for k in range(1, 61)]
    rows = ["time_s,latitude,longitude,height_m,gimbal_pitch"]
    for k, t in enumerate(times):
        if k in (0, 10, 20, 30, 39) or k > 39:
            rows.append(f"{t},{48.5 + 1e-5 * t},{9.0 + 1e-5 * t},40,-30")
        elif k == 15:
            rows.append(f"{t},0,0,40,-30")  # no fix: kept, and no end of an interval (10 to 20 is filled)
        elif k == 5:
            rows.append(f"{t},48.5,,40,-30")  # latitude without longitude: a bad row, not filled
        else:
            rows.append(f"{t},,,40,-30")
    with caplog.at_level(logging.INFO):
        records = parse_csv("\n".join(rows) + "\n", source="gaps.csv")
    kept = [r.t for r in records]
    assert kept == pytest.approx([t for k, t in enumerate(times) if k != 5 and not 30 < k < 39])
    assert [r.has_fix for r in records].count(False) == 1
    assert records[3].lat == pytest.approx(48.5 + 3e-6) and records[13].lon == pytest.approx(9.0 + 1.4e-5)
    assert "25 of 100 rows lack a value other rows hold" in caplog.text
    assert "9 unreadable rows skipped" in caplog.text and "gaps.csv:7: column 'longitude' is empty" in caplog.text


def test_a_merged_export_unsorted_with_bad_cells_and_whole_second_stamps_is_filled():
    # a merged-topics export (a helper's review, 1 Dec 2026): GPS rows at 1 Hz without the gimbal cells, written
    # just before the gimbal row of 0.05 s earlier (not in time order), gimbal rows at 10 Hz without a position;
    # one unreadable latitude cell and one unreadable time (each used to stop the fill for the whole file); the
    # positions linear between the fixes, the attitude between the gimbal rows
    rows = ["time_s,latitude,longitude,height_m,gimbal_pitch,gimbal_heading"]
    for k in range(200):
        t = k / 10
        if k % 10 == 0:
            tg = t + 0.05
            rows.append(f"{tg:.2f},{48.53 + 3.8e-5 * tg:.8f},{9.06 + 5.7e-5 * tg:.8f},40,,")
        rows.append(f"{'' if k == 77 else f'{t:.2f}'},{'ERR' if k == 55 else ''},,,-30,{(k * 0.5) % 360:.1f}")
    records = sorted(parse_csv("\n".join(rows) + "\n", source="merged.csv"), key=lambda r: r.t)
    assert len(records) == 20 + 200 - 2 - 10  # the rows after the last fix (19.1-19.9) and the two bad rows skipped
    for r in records:
        assert r.lat == pytest.approx(48.53 + 3.8e-5 * r.t, abs=1e-9) and r.height_m == 40.0
        assert r.pitch_deg is not None and r.heading_deg is not None
    gimbal = [r for r in records if round(r.t * 100) % 10 == 5]
    assert len(gimbal) == 20 and all(r.heading_deg == pytest.approx((r.t - 0.05) * 5.0 + 0.25, abs=1e-6)
                                     for r in gimbal[:-1])
    # whole-second stamps, 10 rows a second, a fix at .3 of each second and none for 8 s: the filled rows get the
    # times their records get (each second spread over all its rows, also those skipped): exact positions
    start = dt.datetime(2026, 5, 1, 12, 0, 0)
    rows = ["datetime(utc),latitude,longitude,height_m,gimbal_pitch"]
    for k in range(600):
        fix = k % 10 == 3 and not 200 < k < 280
        stamp = (start + dt.timedelta(seconds=k // 10)).strftime("%Y-%m-%d %H:%M:%S")
        rows.append(f"{stamp},{f'{48.53 + 5e-5 * k / 10:.8f}' if fix else ''},{'9.06' if fix else ''},40,-30")
    t0 = start.replace(tzinfo=dt.timezone.utc).timestamp()
    records = parse_csv("\n".join(rows) + "\n", source="ws.csv")
    assert len(records) == 600 - 89 - 6 - 3
    assert max(abs(r.lat - 48.53 - 5e-5 * (r.t - t0)) for r in records) < 1e-9


def test_radians_knots_and_a_speed_in_an_unknown_unit(caplog):
    # pitch and heading in radians are read as such; a knots speed is one; a speed in a unit we do not know leaves
    # that column out with a warning naming it (it refused the whole file, though no pose needs a speed)
    text = ("time,lat,lon,height,gimbal_pitch(rad),gimbal_heading [radians],speed(knots),xspeed(ft/s)\n"
            "0,48.5,9.1,40,-0.5,1.0,10,3\n1,48.5,9.1,40,-0.5,1.0,10,3\n")
    with caplog.at_level(logging.WARNING):
        records = parse_csv(text, source="log.csv")
    assert records[0].pitch_deg == pytest.approx(math.degrees(0.5))
    assert records[0].heading_deg == pytest.approx(math.degrees(1.0))
    assert records[0].speed_mps == pytest.approx(5.1444, abs=1e-4)
    assert records[0].vel_en_mps is None
    assert "'xspeed(ft/s)': unknown unit 'ft/s'" in caplog.text and "left out" in caplog.text
    with pytest.raises(ValueError, match=r"'gimbal_pitch\(gradians\)': unknown unit"):
        parse_csv("time,lat,lon,height,gimbal_pitch(gradians)\n0,48.5,9.1,40,-50\n", source="log.csv")


def _litchi(rows: int = 30) -> str:
    # Litchi's flight log (a subset of its columns, in its order): the aircraft's pitch(deg)/yaw(deg) beside the
    # gimbal's raw angles in tenths of a degree, isTakingVideo, datetime(utc) beside a 12-hour datetime(local)
    head = ("latitude,longitude,altitude(m),speed(mps),time(millisecond),datetime(utc),datetime(local),pitch(deg),"
            "roll(deg),yaw(deg),isTakingVideo,pitchRaw,yawRaw,gimbalPitchRaw,gimbalRollRaw,gimbalYawRaw")
    out = [head]
    start = dt.datetime(2024, 5, 1, 10, 1, 53, tzinfo=dt.timezone.utc)
    for k in range(rows):
        t = start + dt.timedelta(milliseconds=100 * k)
        local = t.astimezone(dt.timezone(dt.timedelta(hours=2)))
        out.append(f"{47.67 + 1e-6 * k:.8f},9.27,{40 + 0.1 * k:.1f},3.0,{100 * k},{t:%Y-%m-%d %H:%M:%S}.{k % 10}00,"
                   f"{local:%Y-%m-%d %I:%M:%S}.{k % 10}00 {local:%p},-4.2,0.3,10.0,{int(k >= 10)},-42,100,"
                   f"{-450 - k},0,{300 + 2 * k}")
    return "\n".join(out) + "\n"


def test_a_litchi_log_reads_the_gimbal_and_the_recording_flag():
    # the telemetry walk-through (1 Dec 2026): refused for datetime(local)'s unit; without that column, the
    # aircraft's yaw (31 deg off) and pitch (63 deg off) were read and isTakingVideo ignored (video 20 s early)
    records = parse_csv(_litchi(), source="litchi.csv")
    assert len(records) == 30
    r = records[12]
    assert r.t == pytest.approx(dt.datetime(2024, 5, 1, 10, 1, 54, 200000, tzinfo=dt.timezone.utc).timestamp())
    assert r.pitch_deg == pytest.approx(46.2) and r.heading_deg == pytest.approx(32.4)
    assert r.height_m == pytest.approx(41.2)
    assert [rec.recording for rec in records[9:11]] == [False, True]
    # with only the local column, its 12-hour clock is read (in the zone the caller gives)
    only_local = "\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != 5)
                           for line in _litchi().splitlines())
    local = parse_csv(only_local, source="litchi.csv", utc_offset_s=7200.0)
    assert local[12].t == pytest.approx(r.t)


def test_a_converted_dji_log_reads_osd_and_gimbal_columns():
    # DJI logs converted by TXTlogToCSVtool / Flight Reader: refused ("missing required column 'lat'")
    head = ("CUSTOM.date [local],CUSTOM.updateTime [local],OSD.flyTime [s],OSD.latitude,OSD.longitude,OSD.height [ft],"
            "OSD.height [m],OSD.hSpeed [MPH],OSD.pitch,OSD.yaw,GIMBAL.pitch,GIMBAL.roll,GIMBAL.yaw,GIMBAL.yaw [360],"
            "CAMERA.isVideo,CUSTOM.isVideo")
    lines = [head]
    for k in range(20):
        rec = k >= 5
        lines.append(f"5/1/2024,12:01:5{k % 10}.00 PM,{0.1 * k:.1f},{47.67 + 1e-6 * k:.8f},9.27,{131.2 + k:.1f},"
                     f"{(131.2 + k) * 0.3048:.3f},6.7,-4.2,10.0,-45.0,0.0,-150.0,210.0,{'TRUE' if rec else 'FALSE'},"
                     f"{'Recording' if rec else ''}")
    records = parse_csv("\n".join(lines) + "\n", source="fly.csv")
    assert len(records) == 20
    assert records[3].t == pytest.approx(0.3) and records[3].height_m == pytest.approx(40.904)  # the [m] column
    assert records[3].pitch_deg == pytest.approx(45.0) and records[3].heading_deg == pytest.approx(210.0)
    assert records[3].speed_mps == pytest.approx(6.7 * 0.44704)
    assert [r.recording for r in records[4:6]] == [False, True]
    # the flag written only as "Recording" or empty (no CAMERA.isVideo)
    custom = "\n".join(line.rsplit(",", 2)[0] + "," + line.rsplit(",", 1)[1] for line in lines)
    from shared.telemetry.record import recording_start

    assert recording_start(parse_csv(custom + "\n", source="fly.csv")) == (pytest.approx(0.5), 1)


def test_one_name_in_two_units_takes_the_preferred_and_the_same_unit_twice_is_refused():
    text = "time,lat,lon,height [ft],height [m]\n0,48.5,9.1,131.2,40.0\n"
    assert parse_csv(text, source="a.csv")[0].height_m == pytest.approx(40.0)
    with pytest.raises(ValueError, match="are the same field"):
        parse_csv("time,lat,lon,height [m],height(m)\n0,48.5,9.1,40,40\n", source="a.csv")


@settings(max_examples=80, deadline=None)
@given(st.datetimes(min_value=dt.datetime(1990, 1, 1), max_value=dt.datetime(2090, 1, 1)))
def test_a_twelve_hour_clock_reads_as_the_twenty_four_hour_one(when):
    from shared.telemetry.dates import parse_datetime

    frac = f"{when.microsecond // 1000:03d}"
    assert parse_datetime(f"{when:%Y-%m-%d %I:%M:%S}.{frac} {when:%p}") == parse_datetime(
        f"{when:%Y-%m-%d %H:%M:%S}.{frac}")

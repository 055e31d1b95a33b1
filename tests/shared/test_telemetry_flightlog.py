"""The flight-log layout of SeaDronesSee meta (Object Detection v2, AirData names) and the layouts of other
drones found in the same files: read as they are, problems classified by reason."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry import parse_csv
from shared.telemetry.dates import parse_datetime
from shared.telemetry.seadronessee import (
    MetaProblem,
    from_seadronessee_meta,
    is_flight_log_meta,
    pitch_convention_of,
)

#: One frame's meta of the real file (instances_dev.json, image 3464), as it is.
REAL_META = {
    "compass_heading(degrees)": 116.5,
    "datetime(utc)": "2020-08-25 12:19:22",
    "gimbal_heading(degrees)": 99.3,
    "gimbal_pitch(degrees)": 13.7,
    "height_above_takeoff(meter)": 9.999512343797623,
    "image_name": "DJI_0032_merged.MP4_image5316.png",
    "latitude": 47.67209,
    "longitude": 9.267889,
    "speed(m/s)": 2.8019248457755923,
    "xspeed(m/s)": -0.09999731783638802,
    "yspeed(m/s)": -2.7999248994188646,
    "zspeed(m/s)": 0.0,
}


def test_the_real_flight_log_meta_is_read_as_it_is():
    assert is_flight_log_meta(REAL_META)
    tel = from_seadronessee_meta(REAL_META, frame=5415)
    assert tel is not None
    assert (tel.lat, tel.lon) == (47.67209, 9.267889)
    assert tel.height_m == pytest.approx(9.9995, abs=1e-4)
    assert tel.pitch_deg == pytest.approx(13.7) and tel.heading_deg == pytest.approx(99.3)  # gimbal, not compass
    assert tel.t == parse_datetime("2020-08-25T12:19:22Z")  # named (utc): UTC whatever the local offset
    assert from_seadronessee_meta(REAL_META, utc_offset_s=7200).t == tel.t
    assert tel.vel_en_mps == pytest.approx((-2.7999, -0.1), abs=1e-3)  # (east, north): y east, x north
    assert tel.speed_mps == pytest.approx(2.802, abs=1e-3) and tel.frame == 5415


def test_feet_and_mph_are_converted_and_dji_pitch_is_read_in_the_flight_log_layout():
    meta = {"latitude": -33.9, "longitude": 151.2, "height_above_takeoff(feet)": 100.0, "speed(mph)": 10.0,
            "gimbal_pitch(degrees)": -45.0, "gimbal_heading(degrees)": 270.0, "datetime(utc)": "2021-01-01 00:00:00"}
    tel = from_seadronessee_meta(meta)
    assert tel.height_m == pytest.approx(30.48) and tel.speed_mps == pytest.approx(4.4704)
    assert tel.pitch_deg == pytest.approx(45.0)  # negative down in the flight-log layout: DJI's convention
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta(meta, pitch_convention="depression")  # -45 as a depression: camera up
    assert err.value.reason == "pitch out of range"


def test_a_flight_log_meta_without_a_time_takes_the_frames_clock():
    meta = {k: v for k, v in REAL_META.items() if k != "datetime(utc)"}
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta(meta)
    assert err.value.reason == "no time"
    assert from_seadronessee_meta(meta, t_default=123.5).t == 123.5


@pytest.mark.parametrize("empty", [None, ""])
def test_a_flight_log_meta_with_a_null_time_takes_the_frames_clock_too(empty):
    # a null datetime(utc) (a log row written before the clock was set) is a missing time, not a bad one
    meta = {**REAL_META, "datetime(utc)": empty}
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta(meta)
    assert err.value.reason == "no time"
    assert from_seadronessee_meta(meta, t_default=123.5).t == 123.5


@pytest.mark.parametrize("drop, reason", [
    ("latitude", "no position"), ("height_above_takeoff(meter)", "no height"),
])
def test_missing_flight_log_fields_are_named_and_classified(drop, reason):
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta({k: v for k, v in REAL_META.items() if k != drop})
    assert err.value.reason == reason and "flight-log names" in str(err.value)


@pytest.mark.parametrize("change, reason", [
    ({"latitude": "north"}, "bad position"), ({"latitude": 95.0}, "bad position"),
    ({"longitude": math.inf}, "bad position"), ({"datetime(utc)": "yesterday"}, "bad time"),
    ({"height_above_takeoff(parsecs)": 3.0}, "bad unit"), ({"gimbal_pitch(degrees)": 120.0}, "pitch out of range"),
    ({"speed(m/s)": -1.0}, "bad speed"),
])
def test_bad_flight_log_values_are_classified(change, reason):
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta({**REAL_META, **change})
    assert err.value.reason == reason


def test_missing_gimbal_angles_give_none_not_an_error():
    meta = {k: v for k, v in REAL_META.items() if not k.startswith("gimbal")}
    tel = from_seadronessee_meta(meta)
    assert tel.pitch_deg is None and tel.heading_deg is None


def test_the_aircrafts_own_attitude_is_not_taken_for_the_cameras():
    meta = {k: v for k, v in REAL_META.items() if not k.startswith("gimbal")}
    meta.update({"pitch(degrees)": -3.0, "yaw(degrees)": 40.0})  # AirData's aircraft attitude columns
    tel = from_seadronessee_meta(meta)
    assert tel.pitch_deg is None and tel.heading_deg is None


def test_a_ref_field_holding_the_coordinate_is_read_as_the_coordinate():
    # other drones in the same public file: the ref holds the latitude as a number
    base = {"altitude": 80.0, "gimbal_pitch": 90.0, "gimbal_heading": 10.0, "date_time": "2020-08-24T15:45:20"}
    bare = {**base, "gps_latitude_ref": 53.72, "gps_longitude_ref": -7.16}
    tel = from_seadronessee_meta(bare)
    assert (tel.lat, tel.lon) == (53.72, -7.16)
    swapped = {**base, "gps_latitude": "S", "gps_latitude_ref": 33.9, "gps_longitude": "E", "gps_longitude_ref": 151.2}
    tel = from_seadronessee_meta(swapped)
    assert (tel.lat, tel.lon) == (-33.9, 151.2)
    agree = {**base, "gps_latitude": 53.72, "gps_latitude_ref": 53.72, "gps_longitude": 7.16, "gps_longitude_ref": "E"}
    assert from_seadronessee_meta(agree).lat == 53.72
    with pytest.raises(MetaProblem) as err:
        from_seadronessee_meta({**agree, "gps_latitude_ref": 12.0})
    assert err.value.reason == "bad position" and "two different coordinates" in str(err.value)


def test_the_seadronessee_layout_keeps_its_positive_down_pitch():
    meta = {"gps_latitude": 47.6, "gps_latitude_ref": "N", "gps_longitude": 9.3, "gps_longitude_ref": "E",
            "altitude": 30.0, "gimbal_pitch": -0.5, "gimbal_heading": 10.0, "date_time": "2020-08-24T15:45:20"}
    assert from_seadronessee_meta(meta).pitch_deg == 0.0  # a small overshoot above the horizon: clamped
    with pytest.raises(MetaProblem):
        from_seadronessee_meta({**meta, "gimbal_pitch": -30.0})  # camera up: no ground view
    assert from_seadronessee_meta({**meta, "gimbal_pitch": -30.0}, pitch_convention="dji").pitch_deg == 30.0


def test_a_video_s_pitch_convention_is_decided_by_its_majority():
    dji = [{**REAL_META, "gimbal_pitch(degrees)": v} for v in (-30.0, -45.0, 5.0)]
    sds = [{**REAL_META, "gimbal_pitch(degrees)": v} for v in (30.0, 45.0, -0.5)]
    assert pitch_convention_of(dji) == "dji"
    assert pitch_convention_of(sds) == "depression"
    assert pitch_convention_of([None, {"gimbal_pitch": "x"}]) == "depression"
    with pytest.raises(ValueError, match="pitch_convention"):
        from_seadronessee_meta(REAL_META, pitch_convention="up")


@settings(max_examples=80, deadline=None)
@given(lat=st.floats(-89.9, 89.9), lon=st.floats(-179.9, 179.9), height=st.floats(0.5, 500.0),
       pitch=st.floats(0.0, 90.0), heading=st.floats(0.0, 359.9), feet=st.booleans(),
       stamp=st.integers(1_500_000_000, 1_800_000_000))
def test_property_flight_log_values_round_trip(lat, lon, height, pitch, heading, feet, stamp):
    from datetime import datetime, timezone

    from hypothesis import assume

    assume((lat, lon) != (0.0, 0.0))  # (0, 0) is no GPS fix: no record (tested apart)

    text = datetime.fromtimestamp(stamp, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    unit, factor = ("feet", 0.3048) if feet else ("meter", 1.0)
    meta = {"latitude": lat, "longitude": lon, f"height_above_takeoff({unit})": height / factor,
            "gimbal_pitch(degrees)": pitch, "gimbal_heading(degrees)": heading, "datetime(utc)": text}
    tel = from_seadronessee_meta(meta)
    assert tel.lat == lat and tel.lon == lon and tel.t == stamp
    assert tel.height_m == pytest.approx(height, rel=1e-9)
    assert tel.pitch_deg == pytest.approx(pitch) and tel.heading_deg == pytest.approx(heading % 360.0)


def test_a_flight_log_csv_gives_velocities_and_its_utc_column_ignores_the_local_offset():
    text = ("datetime(utc),latitude,longitude,height_above_takeoff(meter),gimbal_pitch(degrees),"
            "gimbal_heading(degrees),xSpeed(mph),ySpeed(mph)\n"
            "2020-08-25 12:19:22,47.67209,9.267889,10.0,-13.7,99.3,1.0,-2.0\n")
    (tel,) = parse_csv(text, utc_offset_s=7200)
    assert tel.t == parse_datetime("2020-08-25T12:19:22Z")
    assert tel.vel_en_mps == pytest.approx((-2.0 * 0.44704, 1.0 * 0.44704))
    assert tel.pitch_deg == pytest.approx(13.7)  # a negative column: DJI's convention


def test_a_csv_stamped_at_whole_seconds_spreads_each_seconds_rows_over_it():
    header = ("datetime(utc),latitude,longitude,height_above_takeoff(meter),gimbal_pitch(degrees),"
              "gimbal_heading(degrees)")
    rows = [f"2020-08-25 12:19:{22 + k // 10:02d},47.6,9.3,30.0,-45.0,{k}.0" for k in range(25)]
    records = parse_csv("\n".join([header, *rows]) + "\n")
    t0 = parse_datetime("2020-08-25T12:19:22Z")
    # the last second holds 5 rows: the start of it at the file's 10 rows a second (spread whole, 0.2 s apart)
    assert [round(r.t - t0, 6) for r in records] == pytest.approx([0.1 * k for k in range(25)])


def test_an_airdata_log_says_where_its_video_starts():
    from shared.telemetry import recording_start

    header = "time(millisecond),datetime(utc),latitude,longitude,height_above_takeoff(feet),isVideo"
    flags = [0, 0, 1, 1, 1, 0, 1, 1]
    rows = [f"{100 * k},2020-08-25 12:19:22,47.6,9.3,100,{f}" for k, f in enumerate(flags)]
    records = parse_csv("\n".join([header, *rows]) + "\n")
    assert [r.recording for r in records] == [bool(f) for f in flags]
    start, starts = recording_start(records)
    assert starts == 2 and start == pytest.approx(parse_datetime("2020-08-25T12:19:22Z") + 0.2)
    assert recording_start(parse_csv("t,lat,lon,height\n0,47.6,9.3,30\n")) == (None, 0)
    with pytest.raises(ValueError, match="recording"):
        from shared.telemetry import Telemetry

        Telemetry(t=0.0, lat=0.0, lon=0.0, height_m=1.0, pitch_deg=None, heading_deg=None, recording="yes")


def _v2_image(i: int, frame_no: int, second: int, **meta_changes) -> dict:
    """An image of SeaDronesSee Object Detection v2: source.video / source.frame_no, flight-log meta at whole
    seconds (two images a second: every 15th frame at 30 fps)."""
    meta = {**REAL_META, "datetime(utc)": f"2020-08-25 12:19:{second:02d}", "latitude": 47.67209 + 1e-5 * i,
            **meta_changes}
    return {"id": 100 + i, "file_name": f"{i}.png", "source": {"drone": "mavic", "video": "DJI_0032.MP4",
                                                               "frame_no": frame_no}, "meta": meta}


def test_a_v2_coco_file_gives_one_video_s_telemetry_by_its_source_fields(caplog):
    import logging

    from shared.telemetry.seadronessee import parse_seadronessee_coco

    images = [_v2_image(i, 15 * i, 22 + i // 2) for i in range(8)]
    images[3]["meta"]["latitude"] = "north"  # one unusable meta: that frame has no telemetry, the others keep theirs
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.seadronessee"):
        records = parse_seadronessee_coco({"images": images}, source="v2.json")
    assert [r.frame for r in records] == [0, 15, 30, 60, 75, 90, 105]
    # whole-second stamps, two images a second: spread over their second in frame order
    t = [r.t - records[0].t for r in records]
    assert t == pytest.approx([0.0, 0.5, 1.0, 2.0, 2.5, 3.0, 3.5])
    assert any("v2.json: 1 image(s) with unusable meta carry no telemetry; first: image id 103" in r.getMessage()
               for r in caplog.records)
    # several videos: one must be chosen, by its name
    other = [{**_v2_image(9, 0, 30), "source": {"drone": "mavic", "video": "DJI_0033.MP4", "frame_no": 0}}]
    with pytest.raises(ValueError, match=r"v2\.json: holds 2 videos \('DJI_0032\.MP4', 'DJI_0033\.MP4'\)"):
        parse_seadronessee_coco({"images": images + other}, source="v2.json")
    assert len(parse_seadronessee_coco({"images": images + other}, video_id="DJI_0033.MP4")) == 1
    # nothing usable: the first problem is named
    with pytest.raises(ValueError, match=r"v2\.json: image id 103: "):
        parse_seadronessee_coco({"images": [images[3]]}, source="v2.json")


def test_a_coco_file_of_mostly_unusable_meta_is_refused_and_a_null_frame_no_falls_back():
    from shared.telemetry.seadronessee import parse_seadronessee_coco

    images = [_v2_image(i, 15 * i, 22 + i // 2) for i in range(4)]
    for image in images[:2]:
        image["meta"]["latitude"] = "north"
    with pytest.raises(ValueError, match=r"v2\.json: image id 100: "):  # half unusable: the file, not a frame
        parse_seadronessee_coco({"images": images}, source="v2.json")
    images = [_v2_image(i, 15 * i, 22) for i in range(2)]
    images[1]["source"]["frame_no"] = None
    images[1]["frame_index"] = 7
    assert [r.frame for r in parse_seadronessee_coco({"images": images})] == [0, 7]


@pytest.mark.parametrize("meta", [
    {"latitude": 0.0, "longitude": 0.0, "height_above_takeoff(meter)": 30.0, "gimbal_pitch(degrees)": 60.0,
     "gimbal_heading(degrees)": 10.0, "datetime(utc)": "2020-08-25 12:19:21"},
    {"gps_latitude": 0.0, "gps_latitude_ref": "N", "gps_longitude": 0.0, "gps_longitude_ref": "E", "altitude": 30.0,
     "gimbal_pitch": 60.0, "gimbal_heading": 10.0, "date_time": "2020-08-25T12:19:21"},
])
def test_a_position_at_0_0_is_no_gps_fix(meta):
    """DJI logs write (0, 0) before the fix; as a position it was 5,346 km off the flight, and the poses interpolated
    beside it up to 1,876 km (a helper's audit): no position, as every other reader takes it."""
    from shared.telemetry.seadronessee import MetaProblem, from_seadronessee_meta

    with pytest.raises(MetaProblem, match=r"position \(0, 0\): no GPS fix yet") as err:
        from_seadronessee_meta(meta)
    assert err.value.reason == "no position"

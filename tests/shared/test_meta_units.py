"""SeaDronesSee `gps_latitude`-layout meta fields that name their unit, as the flight-log layout's do
(`altitude(feet)`; a helper's walk-through, 1 Dec 2026: read as missing, every frame lost its pose)."""

from __future__ import annotations

import pytest

from shared.telemetry import from_seadronessee_meta
from shared.telemetry.seadronessee import MetaProblem, compass_heading_of

META = {"gps_latitude": 47.67, "gps_latitude_ref": "N", "gps_longitude": 9.27, "gps_longitude_ref": "E",
        "gimbal_pitch": 45.0, "gimbal_heading": 140.0, "date_time": "2020-08-24T15:45:20"}


@pytest.mark.parametrize(("key", "value", "metres"), [("altitude", 40.0, 40.0), ("altitude(feet)", 131.234, 40.0),
                                                      ("Altitude (ft)", "131.234", 40.0), ("altitude [m]", 40.0, 40.0),
                                                      ("altitude(meter)", 40.0, 40.0)])
def test_altitude_with_a_unit(key, value, metres):
    tel = from_seadronessee_meta({**META, key: value})
    assert tel is not None and tel.height_m == pytest.approx(metres, abs=1e-3)


def test_speeds_with_units_and_a_bad_unit():
    tel = from_seadronessee_meta({**META, "altitude": 40.0, "speed(km/h)": 36.0, "xspeed(mph)": 10.0,
                                  "yspeed(m/s)": 2.0})
    assert tel is not None and tel.speed_mps == pytest.approx(10.0) and tel.vel_en_mps == pytest.approx((2.0, 4.4704))
    with pytest.raises(MetaProblem, match=r"'altitude\(furlongs\)': unknown unit 'furlongs'"):
        from_seadronessee_meta({**META, "altitude(furlongs)": 1.0})
    with pytest.raises(MetaProblem, match="'altitude' is missing"):
        from_seadronessee_meta(META)


def test_compass_heading_in_either_layout():
    assert compass_heading_of({"compass_heading": -20.0}) == pytest.approx(340.0)
    assert compass_heading_of({"compass_heading(degrees)": "181.5"}) == pytest.approx(181.5)
    assert compass_heading_of({"compass_heading": "n/a"}) is None and compass_heading_of(None) is None
    assert compass_heading_of({"gimbal_heading": 10.0}) is None


def test_a_dji_pitch_naming_its_unit_sets_the_convention():
    # a helper's review: `gimbal_pitch(degrees)` negative (DJI) in the gps_latitude layout was judged "depression"
    # and every frame refused as out of range
    from shared.telemetry.seadronessee import pitch_convention_of, raw_pitch

    metas = [{**META, "altitude": 40.0, "gimbal_pitch(degrees)": -30.0} for _ in range(3)]
    for m in metas:
        del m["gimbal_pitch"]
    assert raw_pitch(metas[0]) == -30.0 and pitch_convention_of(metas) == "dji"
    tel = from_seadronessee_meta(metas[0], pitch_convention="dji")
    assert tel is not None and tel.pitch_deg == pytest.approx(30.0)
    # a null plain field beside one naming its unit: the one with a value
    tel = from_seadronessee_meta({**META, "altitude": None, "altitude(ft)": 131.234})
    assert tel is not None and tel.height_m == pytest.approx(40.0, abs=1e-3)


def test_radians_and_knots_are_units():
    # the dataset walk-through's left items: compass_heading(rad) was read as degrees (2.5 rad -> 2.5 deg), and
    # speed(knots) was an unknown unit that cost the frame its pose
    assert compass_heading_of({"compass_heading(rad)": 2.5}) == pytest.approx(143.2394, abs=1e-3)
    assert compass_heading_of({"compass_heading [radians]": -0.5}) == pytest.approx(331.3521, abs=1e-3)
    assert compass_heading_of({"compass_heading(gradians)": 100.0}) is None  # unknown: not read as degrees
    tel = from_seadronessee_meta({**META, "altitude": 40.0, "speed(knots)": 10.0, "gimbal_heading": None,
                                  "gimbal_heading(rad)": 1.0})
    assert tel is not None and tel.speed_mps == pytest.approx(5.1444, abs=1e-4)
    assert tel.heading_deg == pytest.approx(57.2958, abs=1e-4)


@pytest.mark.parametrize("layout", ["gps", "flight-log"])
def test_a_speed_in_an_unknown_unit_is_left_out_not_the_frame(layout):
    if layout == "gps":
        meta = {**META, "altitude": 40.0, "speed(furlongs/fortnight)": 3.0}
    else:
        meta = {"latitude": 47.67, "longitude": 9.27, "height_above_takeoff(meter)": 40.0, "gimbal_pitch": -45.0,
                "gimbal_heading": 140.0, "datetime(utc)": "2020-08-24 13:45:20", "xspeed(ft/s)": 3.0,
                "yspeed(ft/s)": 1.0, "speed(furlongs)": 1.0}
    tel = from_seadronessee_meta(meta)
    assert tel is not None and tel.speed_mps is None and tel.vel_en_mps is None
    assert tel.height_m == pytest.approx(40.0)
    # a pose field in an unknown unit still costs the frame, named
    with pytest.raises(MetaProblem, match="gradians"):
        from_seadronessee_meta({**meta, "gimbal_heading": None, "gimbal_heading(gradians)": 10.0})

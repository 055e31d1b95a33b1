"""Coordinates held between regular updates, taken linear between them (agent.telemetry_holds), alone and through
the dequantisation stage of a dataset's video and a telemetry file's records (agent.telemetry_dequantize)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Dataset, VideoTelemetry, iter_video_frames
from agent.file_frames import telemetry_reports
from agent.telemetry_dequantize import dequantize_records
from agent.telemetry_holds import changes, detect_hold, grid_unit, interpolate_holds, phase_locked_period, varied
from shared.geo import Camera
from shared.telemetry import Telemetry

CAMERA = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)


def _held(t: np.ndarray, truth, period: float, phase: float) -> np.ndarray:
    """truth(s) sampled at phase + k * period and held until the next update."""
    return truth(np.floor((t - phase) / period) * period + phase)


@settings(max_examples=80, deadline=None)
@given(speed=st.floats(0.5, 15.0), sign=st.sampled_from([-1.0, 1.0]), fps=st.sampled_from([10.0, 25.0, 30.0]),
       gps_hz=st.sampled_from([1.0, 2.0, 5.0]), phase=st.floats(0.0, 1.0), lat0=st.floats(-80.0, 80.0))
def test_a_held_coordinate_is_found_and_taken_nearly_exact_between_its_updates(
        speed: float, sign: float, fps: float, gps_hz: float, phase: float, lat0: float) -> None:
    # a latitude moving at `speed` m/s give or take 1 m/s (a swing of 1 m over 6 s: the steps differ, as a real
    # flight's do), written on every record (fps) and updated gps_hz times a second
    if fps / gps_hz < 2.0:
        return
    period = 1.0 / gps_hz
    t = np.arange(0.0, 20.0, 1.0 / fps)
    deg = 1.0 / 111_320.0
    omega = 2.0 * np.pi / 6.0

    def truth(s):
        return lat0 + sign * (speed * s + np.sin(omega * s) / omega) * deg

    written = _held(t, truth, period, phase * period)
    found = detect_hold(t, written)
    assert found is not None and abs(found - period) <= 0.25 / fps
    fixed = interpolate_holds(t, written, found)
    err, as_written = np.abs(fixed - truth(t)) / deg, np.abs(written - truth(t)) / deg
    last = np.arange(len(t)) >= np.flatnonzero(written[1:] != written[:-1])[-1] + 1  # from the last update on
    # between the updates off by at most the time an update is placed off (half a record; before the first, the
    # period's error too) plus the curve's bend over a period (acceleration * period^2 / 8), and never further than
    # the step the file makes next
    top, bend = speed + 1.0, omega * period ** 2 / 8.0
    assert err[~last].max() <= top * (0.75 / fps) + bend + 1e-6
    # after the last update: as written, or on at the last interval's speed (steady: within 30 % over three
    # intervals, as a swing of 1 m/s is at 8 m/s and more), off by the speed's change since (at most 2 periods
    # of acceleration, over at most a period) and the placements' error (a record's time at the top speed)
    if speed >= 8.0 and last.sum() > 1:
        assert not np.array_equal(fixed[last], written[last])
    if not np.array_equal(fixed[last], written[last]):
        assert err[last].max() <= top * (1.0 / fps) + 2.0 * omega * period ** 2 + 1e-6
    assert np.all(np.abs(fixed - written) / deg <= top * period + 1e-6)
    # (two records an update, the second at the update: each record is off by 0 or a half period as written, by a
    # quarter placed halfway between: no better on average)
    assert err.mean() <= as_written.mean() + 1e-9
    if fps / gps_hz >= 5.0:
        assert err.mean() < 0.5 * as_written.mean()


@settings(max_examples=60, deadline=None)
@given(stop=st.floats(4.0, 15.0), speed=st.floats(1.0, 12.0), fps=st.sampled_from([10.0, 30.0]),
       phase=st.floats(0.0, 1.0), back=st.booleans())
def test_a_stop_is_never_further_off_than_as_written(stop: float, speed: float, fps: float, phase: float,
                                                      back: bool) -> None:
    # fly, stop, and (back) fly on again after 10 s of hover: GPS held for 1 s, no noise (the values stop changing)
    t = np.arange(0.0, stop + 20.0, 1.0 / fps)

    def leg(s):  # at `speed` give or take a quarter (the steps differ, as a real flight's do)
        return speed * (s + 0.25 * np.sin(s))

    def truth(s):
        s = np.asarray(s, dtype=np.float64)
        moved = leg(np.minimum(s, stop))
        return moved + (leg(np.clip(s - stop - 10.0, 0.0, None)) if back else 0.0)

    written = _held(t, truth, 1.0, phase)
    found = detect_hold(t, written)
    if found is None:  # too few updates to judge: left as written
        return
    fixed = interpolate_holds(t, written, found)
    err, as_written = np.abs(fixed - truth(t)), np.abs(written - truth(t))
    hover = (t > stop + 1.0) & (t < stop + 9.0)
    assert np.all(err[hover] <= as_written[hover] + 1e-9)
    assert err.mean() <= as_written.mean() + 1e-9


def test_what_is_not_a_regular_hold_is_left_alone() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 30.0, 0.1)
    # a value that changes on every record (noise, full precision)
    assert detect_hold(t, 6.0 * t + rng.normal(0.0, 0.3, len(t))) is None
    # updates at random times (their intervals spread as widely as a Poisson process's), steps of several sizes
    moments = np.sort(rng.uniform(0.0, 30.0, 25))
    k = np.searchsorted(moments, t).astype(float)
    assert detect_hold(t, 6.0 * k + np.sin(k)) is None
    assert detect_hold(t, 6.0 * np.floor(t) + np.sin(np.floor(t))) == 1.0  # the same steps at whole seconds: held
    # a slow coordinate rounded to 6 decimals steps one last digit at a time at a regular pace: rounded, not held;
    # so does a climb written in whole feet or as a KLV altitude (a 16-bit count of 0.3037 m), and a latitude
    # stored as a 32-bit float (0.42 m apart at 48 N), grids of no decimal
    assert detect_hold(t, np.round(48.5 + 0.5 * t / 111_320.0, 6)) is None
    assert detect_hold(t, np.round((40.0 + 0.5 * t) / 0.3048) * 0.3048) is None
    assert detect_hold(t / 3.0, np.round((40.0 + 0.5 * t / 3.0) / 0.3037) * 0.3037) is None
    assert detect_hold(t, (48.5 + 0.3 * t / 111_320.0).astype(np.float32).astype(np.float64)) is None
    # a coarser grid written with more decimals steps a few written units at a time, never more than one apart,
    # at whatever period its grid / speed gives (a helper's review, 1 Dec 2026: 0.078 -> 0.152 m when read as a
    # hold): a KLV altitude (0.3037 m) written to 0.1 m and whole feet written in centimetres, climbing about
    # 1 m/s, a float32 latitude written with 6 decimals drifting 0.5 m/s
    tt = np.arange(0.0, 120.0, 1.0 / 30.0)
    climb = 40.0 + tt + 0.3 * np.sin(2.0 * np.pi * tt / 20.0)
    assert detect_hold(tt, np.round(np.round(climb / (19_900 / 65_535)) * (19_900 / 65_535), 1)) is None
    assert detect_hold(tt, np.round(np.round(climb / 0.3048) * 0.3048, 2)) is None
    drift = 48.53 + (0.5 * tt + 0.5 * np.sin(2.0 * np.pi * tt / 30.0)) / 111_320.0
    assert detect_hold(tt, np.round(drift.astype(np.float32).astype(np.float64), 6)) is None
    # a hold at exactly constant speed steps by one length every update: that length is the grid, as rounding's
    # one unit is, and it stands down
    assert detect_hold(t, 48.5 + 6.0 * np.floor(t) / 111_320.0) is None
    # too few updates (four) and one update a record are not enough to judge
    assert detect_hold(t, np.floor(t / 7.0) * 6.0) is None
    assert detect_hold(t[:10], np.floor(t[:10] / 0.1) * 6.0) is None
    # never changes, nan, mismatched lengths
    assert detect_hold(t, np.full(len(t), 3.0)) is None
    assert detect_hold(t, np.where(t > 5.0, np.nan, np.floor(t))) is None
    assert detect_hold(t, np.floor(t)[:-1]) is None
    # a barometer's height written to 0.1 m (after an offset) flipping between levels: the real flight
    # NorthSea_Sat_DJI_0122 of the SeaDronesSee dev set, one frame a second (held 1.5 s until 30 Nov 2026)
    flips = [0, 0, 0, 1, 1, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 2, 1, 2, 2, 3, 2, 2, 1, 2, 2]
    assert detect_hold(np.arange(26.0), 37.198 + 0.1 * np.array(flips)) is None
    # held for a second at full precision, the speed varying, is held
    assert detect_hold(t, 48.5 + (6.0 * np.floor(t) + np.sin(np.floor(t))) / 111_320.0) == 1.0


def _records(t, lat, lon, height=None) -> list[Telemetry]:
    return [Telemetry(t=float(ti), lat=float(la), lon=float(lo), height_m=None if height is None else float(height[i]),
                      pitch_deg=60.0, heading_deg=45.0) for i, (ti, la, lo) in enumerate(zip(t, lat, lon, strict=True))]


def test_records_with_held_gps_across_the_antimeridian_and_without_a_fix() -> None:
    t = np.arange(0.0, 20.0, 0.1)

    def east(s):  # east across +-180 at about 6 m/s
        return (6.0 * s + np.sin(s)) / 111_320.0

    held = np.floor(t)
    lon = (179.9995 + east(held) + 180.0) % 360.0 - 180.0
    records = _records(t, np.full(len(t), 0.5), lon, height=40.0 + 0.01 * np.arange(len(t)))
    records.insert(40, Telemetry(t=3.95, lat=0.0, lon=0.0, height_m=40.0, pitch_deg=60.0, heading_deg=45.0))
    out, quanta, holds = dequantize_records(records)
    assert quanta == {} and holds == {"lon": 1.0}  # latitude never changes, height on every record
    assert out[40] is records[40]  # no fix: untouched
    fixed = [r for r in out if r.has_fix]
    got = np.unwrap(np.array([r.lon for r in fixed]), period=360.0)
    # each update (at a whole second, on a record) placed halfway between that record and the one before: linear
    # between those points
    knots = np.arange(0.0, 20.0) - 0.05
    expected = 179.9995 + np.interp(t, knots, east(np.arange(0.0, 20.0)))
    inside = (t > 0.95) & (t < 18.95)  # from the last update on (t = 19): on at the last speed (not this line)
    assert np.abs(got - expected)[inside].max() < 1e-9
    assert np.abs(got - (179.9995 + east(t)))[inside].max() < np.abs(np.unwrap(lon, period=360.0)
                                                                     - (179.9995 + east(t)))[inside].max() / 5
    assert all(-180.0 <= r.lon < 180.0 for r in fixed)
    assert [r.height_m for r in fixed] == [r.height_m for r in records if r.has_fix]


def test_dataset_frames_with_gps_held_between_updates_and_the_stage_report() -> None:
    # a flight log written for every frame at 10 Hz whose GPS updates once a second while the gimbal heading moves on
    images = []

    def north(s):  # about 6 m/s
        return (6.0 * s + np.sin(s)) / 111_320.0

    for i in range(80):
        lat = 47.59983 + float(north(i // 10))
        images.append({"id": i + 1, "width": 1920, "height": 1080, "video_id": 1, "frame_index": i,
                       "meta": {"gps_latitude": lat, "gps_latitude_ref": "N", "gps_longitude": 9.3,
                                "gps_longitude_ref": "E", "altitude": 40.0, "gimbal_pitch": 45.0,
                                "gimbal_heading": 10.0 + 0.1 * i,
                                "date_time": f"2020-08-24T15:45:{20 + i * 0.1:09.6f}"}})
    ds = Dataset.from_dict({"images": images, "annotations": [], "categories": [{"id": 1, "name": "person"}]})
    report = VideoTelemetry()
    frames = list(iter_video_frames(ds, CAMERA, 1, dequantize=True, report=report))
    assert report.quanta == {} and report.holds == {"lat": 1.0}
    lats = np.array([f.pose.lat for f in frames if f.pose is not None])
    knots = np.arange(8.0) - 0.05  # each update placed halfway between its first record and the one before
    expected = 47.59983 + np.interp(np.arange(80) / 10.0, knots, north(np.arange(8.0)))
    assert np.abs(lats - expected)[10:70].max() < 1e-9
    stage = {r.stage: r for r in telemetry_reports(report, None)}["dequantize"]
    assert (stage.acted, stage.why) == (True, "lat held 1 s")
    # the frames' heading moves on every record: each frame is a sample (not a whole-record repeat)
    assert report.clock.held_frames == 0


def test_missed_updates_while_moving_are_linear_across_and_bad_input_is_refused() -> None:
    # 1 Hz GPS at about 8 m/s, a tenth of its updates missing (the reviewer's case): a step two periods' worth is
    # ramped over the time it takes at the neighbours' speed, not held for a period and then jumped
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 120.0, 1.0 / 30.0)
    fixes = np.arange(-1.0, 122.0) + 0.3
    fixes = fixes[(rng.random(len(fixes)) > 0.1) | (np.arange(len(fixes)) == 0)]

    def truth(s):
        return 8.0 * s + np.sin(s)

    written = truth(fixes[np.searchsorted(fixes, t, side="right") - 1])
    period = detect_hold(t, written)
    assert period is not None and abs(period - 1.0) < 0.01
    fixed = interpolate_holds(t, written, period)
    err, as_written = np.abs(fixed - truth(t)), np.abs(written - truth(t))
    before_last = t < fixes[-1]
    # 0.21 m; kept for a period and then ramped over one (the rule before the review): 0.72; as written 4.48
    assert err[before_last].mean() < 0.3 < 4.0 < as_written.mean()
    for bad_t, bad_x, period_s, match in ((t[:5], written[:4], 1.0, "one time per value"),
                                          (t[:5][::-1], written[:5], 1.0, "increasing times"),
                                          (np.zeros(5), written[:5], 1.0, "increasing times"),
                                          (t[:5], written[:5], 0.0, "period"),
                                          (t[:5], written[:5], float("nan"), "period")):
        with pytest.raises(ValueError, match=match):
            interpolate_holds(bad_t, bad_x, period_s)


def test_after_the_last_update_on_at_a_steady_speed_else_as_written() -> None:
    # a 1 Hz GPS at 30 records a second; the file ends 0.8 s after its last update (at 19.3 s)
    t = np.arange(0.0, 20.1, 1.0 / 30.0)
    fixes = np.arange(-1.0, 21.0) + 0.3

    def held(truth):
        return truth(fixes[np.searchsorted(fixes, t, side="right") - 1])

    tail = t > 19.3
    # steady at about 6 m/s (speeds within 30 % over the last three intervals): on at the last interval's speed,
    # as the update the file did not reach would have put it (0.6 m at most against 4.8 m as written)
    steady = lambda s: 6.0 * s + 0.3 * np.sin(s)  # noqa: E731
    written = held(steady)
    fixed = interpolate_holds(t, written, 1.0)
    err, as_written = np.abs(fixed - steady(t)), np.abs(written - steady(t))
    assert err[tail].max() < 0.6 < 4.0 < as_written[tail].max()
    # a hover's noise, a turn back, a slowing down by half (steps of one sign but not steady), a UAV that just
    # stopped (a hold longer than LONG_HOLD periods at the end): as written
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 0.3, len(fixes))
    cases = {"hover": lambda s: 0.0 * s, "turn": lambda s: 6.0 * np.minimum(s, 17.5) - 6.0 * np.maximum(s - 17.5, 0.0),
             "slowing": lambda s: 6.0 * s - np.maximum(s - 16.0, 0.0) ** 2}
    for name, truth in cases.items():
        written = held(truth) + (held(lambda s: np.interp(s, fixes, noise)) if name == "hover" else 0.0)
        assert detect_hold(t, written) is not None, name
        assert np.array_equal(interpolate_holds(t, written, 1.0)[tail], written[tail]), name
    stopped = np.where(t < 18.0, held(steady), steady(17.3))  # no update since 17.3 s: 2.8 s at the end
    assert np.array_equal(interpolate_holds(t, stopped, 1.0)[t > 17.3], stopped[t > 17.3])


def test_the_grid_is_the_values_own_not_the_smallest_step() -> None:
    # a smooth (RTK, filtered) position held for a second at a steady 6 m/s, written with 6 decimals: at heading 45
    # the latitude steps 38 and 39 millionths of a degree. Judged against the smallest step (until 1 Dec 2026) 83 %
    # of them were "one unit" and it stood down; on its grid of 1e-6 every step is 38 units or more: held
    t = np.arange(0.0, 30.0, 1.0 / 30.0)
    held = np.floor(t - 0.35) + 0.35
    lat = np.round(48.53 + 6.0 * np.cos(np.radians(45.0)) * held / 111_320.0, 6)
    steps = np.abs(np.diff(lat)[np.diff(lat) != 0])
    assert set(np.round(steps * 1e6).astype(int).tolist()) == {38, 39}
    assert grid_unit(steps, 1e-9 * 49.53) == pytest.approx(1e-6, rel=1e-6)
    assert detect_hold(t, lat) == pytest.approx(1.0, abs=1e-3)
    fixed = interpolate_holds(t, lat, 1.0)
    truth = 48.53 + 6.0 * np.cos(np.radians(45.0)) * t / 111_320.0
    inside = (t > 1.0) & (t < 29.0)
    assert np.abs(fixed - truth)[inside].max() * 111_320.0 < 0.1 < 2.0 < np.abs(lat - truth)[inside].mean() * 111_320.0
    # grids of no decimal and none at all
    assert grid_unit(np.array([3, 5, 2]) * 0.3048, 1e-9) == pytest.approx(0.3048)
    assert grid_unit(np.array([0.3037, 0.6074, 0.3037]), 1e-9) == pytest.approx(0.3037)
    # full precision: no grid, or one a few tolerances wide (Euclid's remainders stop at the tolerance), where every
    # step is hundreds of units
    assert grid_unit(np.random.default_rng(0).normal(5e-5, 1e-5, 50), 5e-8) < 5e-7
    assert grid_unit(np.array([1e-9, 5e-5]), 5e-8) == 0.0


def test_a_long_hover_does_not_hide_the_leg_after_it() -> None:
    # 90 s of hover, its 1 Hz fixes 0.1 m apart (one unit of 6 decimals, or none: the same value for seconds),
    # then a 15 s leg at 6 m/s: the hover's steps are one and two units at irregular intervals, which stood the
    # stage down for the whole file until 1 Dec 2026 (the leg's frames 2.9 m off as written)
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 105.0, 1.0 / 30.0)
    fixes = np.arange(-1.0, 106.0) + 0.35
    noise = rng.normal(0.0, 0.1, len(fixes))

    def north(s):
        return 6.0 * np.maximum(s - 90.0, 0.0)

    i = np.searchsorted(fixes, t, side="right") - 1
    lat = np.round(48.53 + (north(fixes[i]) + noise[i]) / 111_320.0, 6)
    period = detect_hold(t, lat)
    assert period == pytest.approx(1.0, abs=0.02)
    err = np.abs(interpolate_holds(t, lat, period) - 48.53 - north(t) / 111_320.0) * 111_320.0
    as_written = np.abs(lat - 48.53 - north(t) / 111_320.0) * 111_320.0
    leg = (t > 91.0) & (t < 104.0)
    assert err[leg].mean() < 0.3 < 2.5 < as_written[leg].mean()
    hover = t < 89.0
    assert err[hover].mean() <= as_written[hover].mean() + 0.01


def test_a_slow_coordinate_is_held_with_its_partner() -> None:
    # flying east at 6 m/s with a 1 Hz GPS, drifting north at about 0.2 m/s: the latitude steps 2 units of 6
    # decimals at most, at some updates none (no held steps of its own: left as written until 1 Dec 2026);
    # it changes where the longitude's updates are (and once where the longitude rounded to its value before), so
    # it is held with them
    t = np.arange(0.0, 20.0, 1.0 / 30.0)
    fixes = np.floor(t - 0.35) + 0.35
    north = 0.2 * fixes + 0.1 * np.sin(fixes)
    lat = np.round(48.53 + north / 111_320.0, 6)
    lon = np.round(9.06 + 6.0 * fixes / 73_800.0, 6)
    lon[(t > 5.35) & (t < 6.35)] = lon[np.searchsorted(t, 5.3)]  # one update the longitude does not show
    records = _records(t, lat, lon)
    assert detect_hold(t, lat) is None and detect_hold(t, lon) == pytest.approx(1.0, abs=0.01)
    out, quanta, holds = dequantize_records(records)
    assert quanta == {} and list(holds) == ["lat", "lon"] and holds["lat"] == holds["lon"]
    got = np.array([r.lat for r in out])
    truth = 48.53 + (0.2 * t + 0.1 * np.sin(t)) / 111_320.0
    inside = (t > 1.0) & (t < 19.3)
    # 0.09 m as written (the lag and the rounding), 0.02 m held with the longitude
    assert np.abs(got - truth)[inside].mean() < 0.5 * np.abs(lat - truth)[inside].mean()
    # a latitude that changes at records of its own (rounding as it crosses, not where the fix arrives): as written
    own = np.round(48.53 + (0.4 * t) / 111_320.0, 6)
    out, _, holds = dequantize_records(_records(t, own, lon))
    assert list(holds) == ["lon"] and [r.lat for r in out] == [r.lat for r in _records(t, own, lon)]
    with pytest.raises(ValueError, match="change where no update"):
        interpolate_holds(t, lat, 1.0, updates=np.array([40, 70]))
    with pytest.raises(ValueError, match="increasing sample indices"):
        interpolate_holds(t, lat, 1.0, updates=np.array([70, 40]))


def _flight(t: np.ndarray, speed: float, heading_deg: float, swing: float, decimals: int,
            gps_hz: float | None, phase: float = 0.35) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Truth and written latitude / longitude of a UAV at `speed` m/s give or take `swing` (over 17 s), written
    with `decimals` on every record, its fix updated gps_hz times a second (None: on every record)."""
    dist = speed * t + swing * 17.0 / (2.0 * np.pi) * np.sin(2.0 * np.pi * t / 17.0)
    lat = 48.53 + dist * np.cos(np.radians(heading_deg)) / 111_320.0
    lon = 9.06 + dist * np.sin(np.radians(heading_deg)) / (111_320.0 * np.cos(np.radians(48.53)))
    k = np.arange(len(t))
    if gps_hz is not None:
        k = np.clip(np.searchsorted(t, np.floor((t - phase) * gps_hz) / gps_hz + phase), 0, len(t) - 1)
    return lat, lon, np.round(lat[k], decimals), np.round(lon[k], decimals)


def _metres(lat_a, lon_a, lat_b, lon_b) -> np.ndarray:
    return np.hypot((lat_a - lat_b) * 111_320.0, (lon_a - lon_b) * 111_320.0 * np.cos(np.radians(48.53)))


@settings(max_examples=40, deadline=None)
@given(speed=st.floats(3.0, 14.0), heading=st.floats(0.0, 360.0), swing=st.floats(0.3, 1.5),
       fps=st.sampled_from([10.0, 30.0]), phase=st.floats(0.0, 1.0))
def test_quantised_gps_held_between_updates_goes_back_half_a_period(speed, heading, swing, fps, phase) -> None:
    # 4 decimals (11 m) written on every record from a fix updated once a second (the Mavic Mini's per-frame
    # subtitles): each step one quantum, seen at the update after the crossing, half a second late on average.
    # The steps' phase shows the hold: the quantum stage's curve goes half a period earlier (until 1 Dec 2026 it
    # kept the lag; 336 such flights: 5.10 m as written, 3.89 before, 2.36 now)
    t = np.arange(0.0, 60.0, 1.0 / fps)
    lat, lon, w_lat, w_lon = _flight(t, speed, heading, swing, 4, 1.0, phase)
    out, quanta, holds = dequantize_records(_records(t, w_lat, w_lon))
    assert set(holds) <= set(quanta) and all(v == 1.0 for v in holds.values())
    got = _metres(np.array([r.lat for r in out]), np.array([r.lon for r in out]), lat, lon)
    assert got.mean() < _metres(w_lat, w_lon, lat, lon).mean()


@pytest.mark.parametrize(("speed", "heading", "before"), [(3.0, 45.0, 1.41), (6.0, 30.0, 2.93), (10.0, 60.0, 4.92)])
def test_quantised_gps_held_acts_on_both_coordinates(speed: float, heading: float, before: float) -> None:
    t = np.arange(0.0, 60.0, 1.0 / 30.0)
    lat, lon, w_lat, w_lon = _flight(t, speed, heading, 0.5, 4, 1.0)
    out, quanta, holds = dequantize_records(_records(t, w_lat, w_lon))
    assert quanta == {"lat": 1e-4, "lon": 1e-4} and holds == {"lat": 1.0, "lon": 1.0}
    got = _metres(np.array([r.lat for r in out]), np.array([r.lon for r in out]), lat, lon)
    # the quantum stage alone (until 1 Dec 2026: `before`) stayed about half a second's flight off; now 0.78, 1.57,
    # 1.89 m (as written 3.77, 4.56, 6.02)
    assert got.mean() < 0.6 * before < before < _metres(w_lat, w_lon, lat, lon).mean()


@settings(max_examples=60, deadline=None)
@given(speed=st.floats(0.5, 14.0), heading=st.floats(0.0, 360.0), swing=st.sampled_from([0.0, 0.1, 1.0]),
       fps=st.sampled_from([10.0, 30.0]), decimals=st.sampled_from([4, 5]))
def test_quantised_gps_written_as_it_crosses_is_no_hold(speed, heading, swing, fps, decimals) -> None:
    # the same GPS written on every record at full rate: its steps come where the UAV crosses, at no one phase
    t = np.arange(0.0, 60.0, 1.0 / fps)
    *_, w_lat, w_lon = _flight(t, speed, heading, swing, decimals, None)
    assert dequantize_records(_records(t, w_lat, w_lon))[2] == {}


def test_steps_every_whole_period_at_one_speed_are_no_hold() -> None:
    # 5.566 m/s north in 4 decimals crosses every 2.000 s: locked to a 1 s period as a hold is, but one interval
    # only (a hold of a real flight, whose speed varies, steps after 1 or 2 periods): the stage cannot tell
    t = np.arange(0.0, 60.0, 1.0 / 30.0)
    lat = np.round(48.53 + 11.132 / 2.0 * t / 111_320.0, 4)
    assert len(changes(lat)) >= 25 and phase_locked_period(t, lat) is None and not varied(
        (t[changes(lat) - 1] + t[changes(lat)]) / 2.0, 1.0)
    held = np.round(48.53 + (5.566 * np.floor(t - 0.35) + 2.0 * np.sin(np.floor(t - 0.35) / 3.0)) / 111_320.0, 4)
    assert phase_locked_period(t, held) == 1.0

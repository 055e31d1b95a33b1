"""Quantised GPS / altitude made continuous (agent.telemetry_dequantize)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Dataset, VideoTelemetry, iter_video_frames
from agent.file_frames import telemetry_reports
from agent.telemetry_clock import TelemetryTrack
from agent.telemetry_dequantize import (
    AVERAGE_S,
    GPS_QUANTA_DEG,
    HEIGHT_QUANTA_M,
    dequantize,
    dequantize_records,
    dequantize_track,
    detect_quantum,
)
from shared.geo import Camera
from shared.telemetry import Telemetry

CAMERA = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)


def test_the_quantum_is_read_from_the_values() -> None:
    assert detect_quantum(np.array([47.5998, 47.5999, 47.6001]), (1e-4, 1e-5)) == 1e-4
    assert detect_quantum(np.array([9.29911, 9.29912, 9.2993]), (1e-4, 1e-5)) == 1e-5
    assert detect_quantum(np.array([9.299113, 9.299121]), (1e-4, 1e-5)) is None  # 6 decimals: left alone
    assert detect_quantum(np.array([47.5998, 47.5998]), (1e-4, 1e-5)) is None  # never steps: nothing to learn
    assert detect_quantum(np.array([47.5998, math.nan]), (1e-4, 1e-5)) is None
    assert detect_quantum(np.array([40.0, 41.0, 43.0]), (1.0, 0.5)) == 1.0
    assert detect_quantum(np.array([40.5, 41.0]), (1.0, 0.5)) == 0.5


@settings(max_examples=60, deadline=None)
@given(start=st.floats(-0.5, 0.5), speed=st.floats(0.3, 4.0), sign=st.sampled_from([-1.0, 1.0]),
       hz=st.sampled_from([10.0, 30.0]))
def test_a_steady_motion_is_recovered_far_better_than_the_rounded_values(start: float, speed: float, sign: float,
                                                                         hz: float) -> None:
    # a coordinate moving at `speed` quanta per second for 20 s, written rounded to whole quanta
    t = np.arange(0.0, 20.0, 1.0 / hz)
    truth = start + sign * speed * t
    written = np.round(truth)
    fixed = dequantize(t, written, 1.0)
    assert np.all(np.abs(fixed - written) <= 0.5 + 1e-9)  # never leaves the rounding interval
    rounded_rms = float(np.sqrt(np.mean((written - truth) ** 2)))
    fixed_rms = float(np.sqrt(np.mean((fixed - truth) ** 2)))
    assert fixed_rms < 0.5 * rounded_rms + 0.02, (fixed_rms, rounded_rms)


def test_a_value_that_never_steps_is_kept() -> None:
    t = np.arange(10.0)
    x = np.full(10, 3.0)
    assert np.array_equal(dequantize(t, x, 1.0), x)


def _track(lats: list[float], lons: list[float], heights: list[float]) -> TelemetryTrack:
    n = len(lats)
    values = np.column_stack([lats, lons, heights, np.full(n, 10.0), np.full(n, 45.0)])
    return TelemetryTrack(np.arange(n) / 10.0, values)


def test_tracks_with_4_decimal_gps_get_continuous_positions_and_others_are_untouched() -> None:
    n = 60
    true_lat = 47.59983 + 1.0e-5 * np.arange(n)  # 11 m/s north, sampled at 10 Hz: six steps in 6 s
    lats = [round(v, 4) for v in true_lat]
    lons = [9.3] * n
    heights = [40.0 + (i // 20) for i in range(n)]  # 1 m altitude steps
    track, quanta, holds = dequantize_track(_track(lats, lons, heights))
    assert quanta == {"lat": 1e-4, "height_m": 1.0} and holds == {}
    got = track.column("lat")
    assert np.abs(got - true_lat).max() < np.abs(np.array(lats) - true_lat).max()
    assert np.all(track.column("lon") == 9.3)  # never stepped: kept
    assert np.all(np.abs(got - np.array(lats)) <= 0.5e-4 + 1e-12)
    # six decimals: nothing to do, the very same track comes back
    fine = _track([47.599801 + 1e-6 * i for i in range(n)], lons, [40.123] * n)
    same, none, held = dequantize_track(fine)
    assert none == held == {} and same is fine


def test_a_track_of_one_sample_is_left_alone() -> None:
    one = _track([47.5998], [9.3], [40.0])
    same, quanta, holds = dequantize_track(one)
    assert same is one and quanta == holds == {}


def test_dataset_frames_get_dequantised_positions_between_the_samples() -> None:
    # 4-decimal GPS on a file: iter_video_frames(dequantize=True) interpolates the continuous track
    images = []
    for i in range(40):
        lat = round(47.59983 + 2.0e-5 * i, 4)
        images.append({"id": i + 1, "width": 1920, "height": 1080, "video_id": 1, "frame_index": i,
                       "meta": {"gps_latitude": lat, "gps_latitude_ref": "N", "gps_longitude": 9.3,
                                "gps_longitude_ref": "E", "altitude": 40.0, "gimbal_pitch": 45.0,
                                "gimbal_heading": 10.0, "date_time": f"2020-08-24T15:45:{20 + i * 0.1:09.6f}"}})
    ds = Dataset.from_dict({"images": images, "annotations": [], "categories": [{"id": 1, "name": "person"}]})
    report = VideoTelemetry()
    frames = list(iter_video_frames(ds, CAMERA, 1, dequantize=True, report=report))
    assert report.quanta == {"lat": 1e-4}
    lats = np.array([f.pose.lat for f in frames if f.pose is not None])
    truth = 47.59983 + 2.0e-5 * np.arange(40)
    assert np.abs(lats - truth)[5:-5].max() < 0.3e-4  # the rounded values err by up to 0.5e-4
    plain_report = VideoTelemetry()
    plain = list(iter_video_frames(ds, CAMERA, 1, report=plain_report))
    assert all(f.pose is not None and round(f.pose.lat, 4) == f.pose.lat for f in plain)
    # the stage reports say which: acted, or turned off (not "no quantised coordinate", as until 30 Nov 2026)
    stage = {r.stage: r for r in telemetry_reports(report, None)}["dequantize"]
    assert (stage.acted, stage.why) == (True, "lat 0.0001")
    stage = {r.stage: r for r in telemetry_reports(plain_report, None)}["dequantize"]
    assert (stage.acted, stage.why) == (False, "off (dequantize_telemetry false)")


# ------------------------------------------------------------------------------------------------------------------
# A video's telemetry file, record by record (dequantize_records: uavmm detect, agent --video, anomaly --video)
# ------------------------------------------------------------------------------------------------------------------

def _records(t, lat, lon, height=None) -> list[Telemetry]:
    return [Telemetry(t=float(ti), lat=float(la), lon=float(lo), height_m=None if height is None else float(height[i]),
                      pitch_deg=60.0, heading_deg=45.0) for i, (ti, la, lo) in enumerate(zip(t, lat, lon, strict=True))]


@settings(max_examples=60, deadline=None)
@given(lat0=st.floats(-60.0, 60.0), lon0=st.floats(-179.9, 179.9), v_north=st.floats(-12.0, 12.0),
       v_east=st.floats(-12.0, 12.0), hz=st.sampled_from([1.0, 10.0]), decimals=st.sampled_from([4, 5]))
def test_records_written_with_4_or_5_decimals_stay_within_half_a_step_and_land_nearer_the_truth(
        lat0: float, lon0: float, v_north: float, v_east: float, hz: float, decimals: int) -> None:
    t = np.arange(0.0, 30.0, 1.0 / hz)
    lat = lat0 + v_north * t / 111_320.0
    lon = (lon0 + v_east * t / (111_320.0 * math.cos(math.radians(lat0))) + 180.0) % 360.0 - 180.0
    records = _records(t, np.round(lat, decimals), np.round(lon, decimals))
    out, quanta, _ = dequantize_records(records)
    assert len(out) == len(records) and [r.t for r in out] == [r.t for r in records]
    # the written step, or a coarser one where every value written happens to sit on it (the file cannot tell)
    assert all(quanta[name] in (10.0 ** -decimals, 1e-4) for name in quanta)
    q = max(quanta.values(), default=0.0)
    for before, after in zip(records, out, strict=True):
        assert abs(after.lat - before.lat) <= q / 2 + 1e-12
        assert abs((after.lon - before.lon + 180.0) % 360.0 - 180.0) <= q / 2 + 1e-12  # also across +-180
        assert -180.0 <= after.lon < 180.0 and after.heading_deg == before.heading_deg and after.height_m is None
    if "lat" in quanta and 4 <= len({r.lat for r in records}) <= len(records) / 3:  # held and stepped: nearer truth
        got = np.array([r.lat for r in out])
        assert np.sqrt(np.mean((got - lat) ** 2)) < np.sqrt(np.mean((np.round(lat, decimals) - lat) ** 2))


def test_records_without_a_fix_repeated_times_and_six_decimals() -> None:
    t = np.arange(0.0, 10.0, 1.0)
    lat = np.round(48.5 + 6.0 * t / 111_320.0, 4)
    records = _records(t, lat, np.full(len(t), 9.06), height=np.round(40.0 + 0.7 * t))
    no_fix = Telemetry(t=2.5, lat=0.0, lon=0.0, height_m=40.0, pitch_deg=60.0, heading_deg=45.0)  # "no GPS fix"
    records.insert(3, no_fix)
    records.insert(6, replace(records[5], lat=records[5].lat))  # two records at one time
    out, quanta, holds = dequantize_records(records)
    assert quanta == {"lat": 1e-4, "height_m": 1.0} and holds == {}  # longitude never steps: left as written
    assert out[3] is records[3]  # no fix: untouched
    assert out[5].lat == out[6].lat and out[5].t == out[6].t
    assert all(r.lon == 9.06 for r in out if r.has_fix)
    # six decimals (0.11 m): nothing quantised, the very same list back
    fine = _records(t, 48.5 + 6.0 * t / 111_320.0, np.full(len(t), 9.06))
    assert dequantize_records(fine) == (fine, {}, {})
    # one record with a fix: nothing to judge
    assert dequantize_records(records[:1]) == (records[:1], {}, {})
    # out of time order: refused
    with pytest.raises(ValueError, match="time order"):
        dequantize_records(records[::-1])


@settings(max_examples=80, deadline=None)
@given(stop=st.floats(5.0, 60.0), speed=st.floats(0.5, 12.0), start=st.floats(0.0, 11.0),
       hz=st.sampled_from([1.0, 10.0]))
def test_a_uav_that_stops_is_never_put_further_off_in_its_hover_than_as_written(stop: float, speed: float,
                                                                               start: float, hz: float) -> None:
    # metres along one axis, written to 11.1 m steps (4 decimals of latitude); flies, then hovers for a minute
    t = np.arange(0.0, stop + 60.0, 1.0 / hz)
    truth = start + speed * np.minimum(t, stop)
    written = np.round(truth / 11.1) * 11.1
    fixed = dequantize(t, written, 11.1)
    hover = t > stop + 15.0 / speed + 1.0  # the last step's ramp is over
    assert np.all(np.abs(fixed - written) <= 5.55 + 1e-9)
    assert np.abs(fixed - truth)[hover].mean() <= np.abs(written - truth)[hover].mean() + 1e-9


def test_take_off_in_whole_metres_and_steps_over_several_levels_reach_their_levels() -> None:
    t = np.arange(0.0, 120.0, 1.0)
    height = np.clip(2.0 * (t - 10.0), 0.0, 40.0)  # on the pad, a climb of 2 m a sample (two levels), a hover
    fixed = dequantize(t, np.round(height), 1.0)
    # on the pad and in the hover the levels written (the average's ramp reaches 2 s into each), the climb linear
    assert np.all(fixed[t < 8] == 0.0) and np.all(fixed[t > 32] == 40.0)
    assert np.abs(fixed - height).max() <= 0.5 and np.abs(fixed - height)[(t > 10) & (t < 30)].max() <= 0.01
    # one step alone says no speed: a ramp as wide as the average (4 s) across it, the levels written beyond
    written = np.array([3.0] * 5 + [4.0] * 5)
    one = dequantize(np.arange(10.0), written, 1.0)
    assert list(one[:3]) == [3.0] * 3 and list(one[7:]) == [4.0] * 3 and np.all(np.diff(one[2:8]) > 0)


def test_the_quantum_is_judged_with_a_coarser_grid_and_an_offset() -> None:
    assert detect_quantum(np.array([47.599, 47.6, 47.601]), GPS_QUANTA_DEG) == 1e-3  # 3 decimals: 111 m steps
    assert detect_quantum(np.array([47.59, 47.6, 47.61]), GPS_QUANTA_DEG) is None  # 2 decimals: no position
    heights = np.array([40.0, 41.0, 43.0]) - 380.4  # whole metres above the sea, minus the ground's 380.4 m
    assert detect_quantum(heights, HEIGHT_QUANTA_M) is None
    assert detect_quantum(heights, HEIGHT_QUANTA_M, offset=True) == 1.0
    assert detect_quantum(np.array([30.0, 31.0, 31.0]), HEIGHT_QUANTA_M, offset=True) is None  # one step: a climb?
    # two values alone: only one step apart do they say the step (a 5-decimal hover that jumped 3e-4 says nothing)
    assert detect_quantum(np.array([48.5301, 48.5302, 48.5302]), GPS_QUANTA_DEG) == 1e-4
    assert detect_quantum(np.array([48.5301, 48.5304]), GPS_QUANTA_DEG) is None
    assert detect_quantum(np.array([48.5301, 48.5304, 48.5302]), GPS_QUANTA_DEG) == 1e-4


def test_a_latitude_made_continuous_stays_on_the_globe() -> None:
    t = np.arange(0.0, 30.0, 1.0)
    lat = np.round(np.minimum(89.999 + 6.0 * t / 111_320.0, 90.0), 4)  # flying north at 6 m/s to the pole, 4 decimals
    out, quanta, _ = dequantize_records(_records(t, lat, np.full(len(t), 9.06)))
    assert quanta == {"lat": 1e-4} and all(-90.0 <= r.lat <= 90.0 for r in out)


@settings(max_examples=80, deadline=None)
@given(stop=st.floats(5.0, 30.0), speed=st.floats(2.0, 12.0), start=st.floats(0.0, 11.0), back=st.booleans())
def test_a_hover_between_two_legs_is_no_further_off_than_as_written(stop: float, speed: float, start: float,
                                                                   back: bool) -> None:
    # metres on one axis at 10 Hz, 11.1 m steps: a leg, a 40 s hover, a leg on (or back)
    t = np.arange(0.0, stop + 40.0 + 20.0, 0.1)
    leg2 = np.clip(t - stop - 40.0, 0.0, None)
    truth = start + speed * np.minimum(t, stop) + (-1.0 if back else 1.0) * speed * leg2
    written = np.round(truth / 11.1) * 11.1
    fixed = dequantize(t, written, 11.1)
    hover = (t > stop + 15.0 / speed + 1.0) & (t < stop + 40.0 - 15.0 / speed - 1.0)
    assert np.abs(fixed - truth)[hover].mean() <= np.abs(written - truth)[hover].mean() + 1e-9
    legs = (t < stop) | (t > stop + 40.0)
    assert np.abs(fixed - truth)[legs].mean() < np.abs(written - truth)[legs].mean()


@settings(max_examples=60, deadline=None)
@given(where=st.floats(0.0, 1.0), sigma=st.floats(0.5, 3.0), hz=st.sampled_from([1.0, 10.0, 30.0]),
       seed=st.integers(0, 2**31))
def test_a_hover_with_gps_noise_is_no_further_off_than_as_written_and_nearer_where_it_flips(
        where: float, sigma: float, hz: float, seed: int) -> None:
    # the second review's case: noise flipping the written value about a level's edge was read as passes through
    # the level (a hover at its centre came out 1.8 m off against 0.06 m as written)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 1.0 / hz)
    truth = np.full(len(t), 5.55 * where)  # from the level's centre (0) to its edge (5.55)
    written = np.round((truth + rng.normal(0.0, sigma, len(t))) / 11.1) * 11.1
    fixed = dequantize(t, written, 11.1)
    assert np.abs(fixed - truth).mean() <= np.abs(written - truth).mean() + 0.3


@settings(max_examples=60, deadline=None)
@given(spacing=st.floats(8.0, 20.0), line_s=st.floats(10.0, 40.0), hz=st.sampled_from([1.0, 10.0]),
       offset=st.floats(0.0, 11.1))
def test_survey_line_changes_are_steps_then_holds_not_a_drift(spacing: float, line_s: float, hz: float,
                                                              offset: float) -> None:
    # the cross-track coordinate of a lawn-mower survey: a line, a 5 m/s move of `spacing` metres, the next line
    times, values, now, y = [0.0], [offset], 0.0, offset
    for _ in range(6):
        now += line_s
        times.append(now)
        values.append(y)
        now += spacing / 5.0
        y += spacing
        times.append(now)
        values.append(y)
    t = np.arange(0.0, now + line_s, 1.0 / hz)
    truth = np.interp(t, times, values)
    written = np.round(truth / 11.1) * 11.1
    fixed = dequantize(t, written, 11.1)
    # the holds keep their levels beyond the average's reach (AVERAGE_S / 2) of a move; overall no worse
    moving = t[np.abs(np.gradient(truth, t)) >= 0.05]
    held = np.abs(t[:, None] - moving[None, :]).min(axis=1) > AVERAGE_S / 2.0
    assert np.abs(fixed - truth)[held].mean() <= np.abs(written - truth)[held].mean() + 1e-9
    assert np.abs(fixed - truth).mean() <= np.abs(written - truth).mean() + 0.05

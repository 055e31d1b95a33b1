"""Coordinates held between regular updates, taken linear between them (agent.telemetry_holds), alone and through
the dequantisation stage of a dataset's video and a telemetry file's records (agent.telemetry_dequantize)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Dataset, VideoTelemetry, iter_video_frames
from agent.file_frames import telemetry_reports
from agent.telemetry_dequantize import dequantize_records
from agent.telemetry_holds import detect_hold, interpolate_holds, last_digit
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
    # a latitude moving at `speed` m/s, written on every record (fps) and updated gps_hz times a second
    if fps / gps_hz < 2.0:
        return
    period = 1.0 / gps_hz
    t = np.arange(0.0, 20.0, 1.0 / fps)
    deg = 1.0 / 111_320.0

    def truth(s):
        return lat0 + sign * speed * s * deg

    written = _held(t, truth, period, phase * period)
    found = detect_hold(t, written)
    assert found is not None and abs(found - period) <= 0.25 / fps
    fixed = interpolate_holds(t, written, found)
    err, as_written = np.abs(fixed - truth(t)) / deg, np.abs(written - truth(t)) / deg
    last = np.arange(len(t)) >= np.flatnonzero(written[1:] != written[:-1])[-1] + 1  # from the last update on
    assert np.array_equal(fixed[last], written[last])  # held as written: nothing is extrapolated
    # between the updates off by at most the time an update is placed off (half a record; before the first, the
    # period's error too), and never further than the step the file makes next
    assert err[~last].max() <= speed * (0.75 / fps) + 1e-6
    assert np.all(np.abs(fixed - written) / deg <= speed * period + 1e-6)
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

    def truth(s):
        s = np.asarray(s, dtype=np.float64)
        moved = speed * np.minimum(s, stop)
        return moved + (speed * np.clip(s - stop - 10.0, 0.0, None) if back else 0.0)

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
    # updates at random times (their intervals spread as widely as a Poisson process's)
    moments = np.sort(rng.uniform(0.0, 30.0, 25))
    assert detect_hold(t, np.searchsorted(moments, t).astype(float) * 6.0) is None
    # a slow coordinate rounded to 6 decimals steps one last digit at a time at a regular pace: rounded, not held
    assert detect_hold(t, np.round(48.5 + 0.5 * t / 111_320.0, 6)) is None
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
    # the same slow coordinate held for a second at full precision is held
    assert detect_hold(t, 48.5 + 6.0 * np.floor(t) / 111_320.0) == 1.0


def test_the_last_decimal_written() -> None:
    assert last_digit(np.array([47.67209, 47.672089])) == 1e-6
    assert last_digit(np.array([47.1234567, -122.123456789])) == 1e-9
    assert last_digit(np.array([40.0, 41.0])) == 1.0 and last_digit(np.array([40.5])) == 0.1
    assert last_digit(np.array([9.999512343797623])) == 0.0  # a binary float: no decimal grid


def _records(t, lat, lon, height=None) -> list[Telemetry]:
    return [Telemetry(t=float(ti), lat=float(la), lon=float(lo), height_m=None if height is None else float(height[i]),
                      pitch_deg=60.0, heading_deg=45.0) for i, (ti, la, lo) in enumerate(zip(t, lat, lon, strict=True))]


def test_records_with_held_gps_across_the_antimeridian_and_without_a_fix() -> None:
    t = np.arange(0.0, 20.0, 0.1)
    held = np.floor(t)
    lon = (179.9995 + 6.0 * held / 111_320.0 + 180.0) % 360.0 - 180.0  # east across +-180 at 6 m/s
    records = _records(t, np.full(len(t), 0.5), lon, height=40.0 + 0.01 * np.arange(len(t)))
    records.insert(40, Telemetry(t=3.95, lat=0.0, lon=0.0, height_m=40.0, pitch_deg=60.0, heading_deg=45.0))
    out, quanta, holds = dequantize_records(records)
    assert quanta == {} and holds == {"lon": 1.0}  # latitude never changes, height on every record
    assert out[40] is records[40]  # no fix: untouched
    fixed = [r for r in out if r.has_fix]
    # each update (at a whole second, on a record) placed halfway between that record and the one before
    truth = 179.9995 + 6.0 * (t + 0.05) / 111_320.0
    got = np.unwrap(np.array([r.lon for r in fixed]), period=360.0)
    inside = t < 18.95  # from the last update on (t = 19): held as written
    assert np.abs(got - truth)[inside].max() < 1e-9
    assert all(-180.0 <= r.lon < 180.0 for r in fixed)
    assert [r.height_m for r in fixed] == [r.height_m for r in records if r.has_fix]


def test_dataset_frames_with_gps_held_between_updates_and_the_stage_report() -> None:
    # a flight log written for every frame at 10 Hz whose GPS updates once a second while the gimbal heading moves on
    images = []
    for i in range(80):
        lat = 47.59983 + 6.0 * (i // 10) / 111_320.0
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
    truth = 47.59983 + 6.0 * (np.arange(80) / 10.0 + 0.05) / 111_320.0  # updates placed half a record early
    assert np.abs(lats - truth)[:70].max() < 1e-9
    stage = {r.stage: r for r in telemetry_reports(report, None)}["dequantize"]
    assert (stage.acted, stage.why) == (True, "lat held 1 s")
    # the frames' heading moves on every record: each frame is a sample (not a whole-record repeat)
    assert report.clock.held_frames == 0

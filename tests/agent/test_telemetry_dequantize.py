"""Quantised GPS / altitude made continuous (agent.telemetry_dequantize)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Frame, ImageRecord
from agent.telemetry_dequantize import dequantize, dequantize_frames, detect_quantum
from shared.geo import Camera, Pose

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


def _frames(lats: list[float], lons: list[float], heights: list[float]) -> list[Frame]:
    out = []
    for i, (lat, lon, h) in enumerate(zip(lats, lons, heights, strict=True)):
        image = ImageRecord(i, CAMERA.width, CAMERA.height, 1, i, None, None)
        out.append(Frame(image, Pose(lat, lon, h, 45.0, 10.0), i / 10.0, CAMERA, i / 10.0))
    return out


def test_frames_with_4_decimal_gps_get_continuous_positions_and_others_are_untouched() -> None:
    n = 60
    true_lat = 47.59983 + 1.0e-5 * np.arange(n)  # 11 m/s north, sampled at 10 Hz: six steps in 6 s
    lats = [round(v, 4) for v in true_lat]
    lons = [9.3] * n
    heights = [40.0 + (i // 20) for i in range(n)]  # 1 m altitude steps
    frames, quanta = dequantize_frames(_frames(lats, lons, heights))
    assert quanta == {"lat": 1e-4, "height_m": 1.0}
    got = np.array([f.pose.lat for f in frames if f.pose])
    assert np.abs(got - true_lat).max() < np.abs(np.array(lats) - true_lat).max()
    assert all(f.pose is not None and f.pose.lon == 9.3 for f in frames)  # never stepped: kept
    assert all(abs(f.pose.lat - lat) <= 0.5e-4 + 1e-12 for f, lat in zip(frames, lats, strict=True) if f.pose)
    # six decimals: nothing to do, the very same frames come back
    fine = _frames([47.599801 + 1e-6 * i for i in range(n)], lons, [40.123] * n)
    same, none = dequantize_frames(fine)
    assert none == {} and same == fine


def test_frames_without_pose_pass_through() -> None:
    frames = _frames([47.5998, 47.5999, 47.6000], [9.3] * 3, [40.0] * 3)
    frames[1] = Frame(frames[1].image, None, frames[1].t, CAMERA)
    out, quanta = dequantize_frames(frames)
    assert out[1].pose is None and quanta == {"lat": 1e-4}
    assert out[0].pose is not None and out[2].pose is not None and out[0].pose.lat < out[2].pose.lat

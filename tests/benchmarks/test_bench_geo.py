"""`uavmm bench geo` compares pixel_to_latlon with a homography only where both put the pixels on the same ground."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from benchmarks.bench_geo import _check_same_ground_points
from shared.geo import Camera, Pose, image_to_ground_homography

CAMERA = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
POSE = Pose(lat=47.67, lon=9.27, height_m=30.0, pitch_deg=45.0, heading_deg=140.0)


def _homography_points(uv: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(uv.reshape(-1, 1, 2), image_to_ground_homography(CAMERA, POSE)).reshape(-1, 2)


def test_the_homography_baseline_maps_the_benchmarks_pixels_where_pixel_to_local_does():
    uv = np.column_stack([np.linspace(0, 3840, 500), np.linspace(0, 2160, 500)])
    _check_same_ground_points(uv, CAMERA, POSE, _homography_points(uv))


def test_a_baseline_that_puts_the_pixels_elsewhere_is_refused():
    uv = np.array([[1920.0, 1500.0], [100.0, 2000.0]])
    with pytest.raises(RuntimeError, match="disagree"):
        _check_same_ground_points(uv, CAMERA, POSE, _homography_points(uv) + [0.0, 0.01])
    above_horizon = np.array([[1920.0, -5000.0]])
    with pytest.raises(RuntimeError, match="1 pixels without a ground point"):
        _check_same_ground_points(above_horizon, CAMERA, POSE, _homography_points(above_horizon))

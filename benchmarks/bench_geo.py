"""Benchmark of the geometry core: pixel -> lat/lon for many pixels.

Baseline in the same run: cv2.perspectiveTransform of the same pixels with the image->ground
homography (the cheapest possible per-pixel mapping, no lens model, no validity).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from benchmarks.timing import median_time_s
from shared.geo import Camera, Pose, image_to_ground_homography, latlon_to_pixel, pixel_to_latlon

DESCRIPTION = "pixel_to_latlon / latlon_to_pixel ns per point (1e6 points) vs cv2.perspectiveTransform"


def run(quick: bool = False) -> list[dict[str, Any]]:
    n = 100_000 if quick else 1_000_000
    rng = np.random.default_rng(0)
    cam = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    cam_dist = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0,
                      dist=(-0.1, 0.03, 0.0, 0.0, 0.0))
    pose = Pose(lat=47.67, lon=9.27, height_m=30.0, pitch_deg=45.0, heading_deg=140.0)
    uv = np.column_stack([rng.uniform(0, 3840, n), rng.uniform(0, 2160, n)])
    h = image_to_ground_homography(cam, pose)
    pts = uv.reshape(-1, 1, 2)
    base = median_time_s(lambda: cv2.perspectiveTransform(pts, h), repeat=5)
    t_fwd = median_time_s(lambda: pixel_to_latlon(uv, cam, pose), repeat=5)
    lat, lon, valid = pixel_to_latlon(uv, cam, pose)
    t_inv = median_time_s(lambda: latlon_to_pixel(lat[valid], lon[valid], cam, pose), repeat=5)
    t_dist = median_time_s(lambda: pixel_to_latlon(uv[: n // 10], cam_dist, pose), repeat=3)
    ns = 1e9 / n
    rows = [
        {"case": f"homography, {n} px", "value": base * ns, "unit": "ns/px"},
        {"case": f"pixel_to_latlon, {n} px", "value": t_fwd * ns, "unit": "ns/px",
         "baseline_name": "homography", "ratio": t_fwd / base},
        {"case": f"latlon_to_pixel, {int(valid.sum())} pts", "value": t_inv * 1e9 / valid.sum(),
         "unit": "ns/pt", "baseline_name": "homography", "ratio": (t_inv / valid.sum()) / (base / n)},
        {"case": f"pixel_to_latlon + undistort, {n // 10} px", "value": t_dist * 1e9 / (n // 10),
         "unit": "ns/px", "baseline_name": "homography", "ratio": (t_dist / (n // 10)) / (base / n)},
    ]
    return rows

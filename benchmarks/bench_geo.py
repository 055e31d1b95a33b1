"""Benchmark of the geometry core: pixel -> lat/lon for many pixels.

Baseline in the same run: cv2.perspectiveTransform of the same pixels with the image->ground
homography (the cheapest possible per-pixel mapping, no lens model, no validity); the two are checked to put
every pixel on the same ground point (to 1 mm) before they are timed. The cases are timed in turns (one sample of
each a round) and each ratio is the median of the per-round ratios.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from benchmarks.timing import interleaved_samples_s, paired_ratio
from shared.geo import Camera, Pose, image_to_ground_homography, latlon_to_pixel, pixel_to_latlon, pixel_to_local

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
    _check_same_ground_points(uv, cam, pose, cv2.perspectiveTransform(pts, h).reshape(-1, 2))
    lat, lon, valid = pixel_to_latlon(uv, cam, pose)
    lat_ok, lon_ok, n_ok = lat[valid], lon[valid], int(valid.sum())
    uv_dist = uv[: n // 10]
    # in turns, so a change of the machine's load falls on the baseline as well (the ratios are per round)
    samples = interleaved_samples_s({
        "homography": lambda: cv2.perspectiveTransform(pts, h),
        "forward": lambda: pixel_to_latlon(uv, cam, pose),
        "inverse": lambda: latlon_to_pixel(lat_ok, lon_ok, cam, pose),
        "undistort": lambda: pixel_to_latlon(uv_dist, cam_dist, pose),
    }, repeat=5)
    per_point = {"homography": n, "forward": n, "inverse": n_ok, "undistort": len(uv_dist)}
    ns = {name: [t * 1e9 / per_point[name] for t in times] for name, times in samples.items()}
    rows = [{"case": f"homography, {n} px", "value": float(np.median(ns["homography"])), "unit": "ns/px"}]
    for name, case, unit in (("forward", f"pixel_to_latlon, {n} px", "ns/px"),
                             ("inverse", f"latlon_to_pixel, {n_ok} pts", "ns/pt"),
                             ("undistort", f"pixel_to_latlon + undistort, {len(uv_dist)} px", "ns/px")):
        rows.append({"case": case, "value": float(np.median(ns[name])), "unit": unit, "baseline_name": "homography",
                     "ratio": paired_ratio(ns[name], ns["homography"])})
    return rows


def _check_same_ground_points(uv: np.ndarray, camera: Camera, pose: Pose, east_north: np.ndarray) -> None:
    """RuntimeError unless pixel_to_local puts the (N, 2) pixels uv where the homography put them (east_north, (N, 2)
    metres), to 1 mm: else the ratio would compare two different computations."""
    east, north, valid = pixel_to_local(uv, camera, pose)
    off_m = np.hypot(east - east_north[:, 0], north - east_north[:, 1])[valid]
    worst_m = float(off_m.max()) if off_m.size else 0.0
    if not valid.all() or not worst_m <= 1e-3:
        raise RuntimeError(f"bench geo: pixel_to_local and the homography disagree (up to {worst_m:.3g} m; "
                           f"{int((~valid).sum())} pixels without a ground point)")

"""Camera geometry the renderer needs beyond `shared.geo`: 3-D points, the texture-to-image homography, ranges, sun.

Everything here takes the TRUE pose of a frame. Points are east/north/up metres relative to the ground point
below the UAV (the local frame of `shared.geo`); the world's own frame (``world_en``) is east/north metres
around the world origin. Only undistorted cameras with roll 0 are rendered (the simulator's cameras and poses).
"""

from __future__ import annotations

import math
from datetime import datetime, timezone

import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose, ground_to_image_homography, horizon_row, latlon_to_local

FloatArray = NDArray[np.float64]


def check_renderable(camera: Camera, pose: Pose | None = None) -> None:
    """ValueError when the renderer cannot draw this camera (lens distortion) or pose (roll)."""
    if camera.dist is not None:
        raise ValueError("rendering needs an undistorted camera (camera.json has 'dist'); simulated cameras have none")
    if pose is not None and pose.roll_deg != 0.0:
        raise ValueError(f"rendering needs roll 0 (the simulator's gimbal), got roll_deg={pose.roll_deg!r}")


def uav_world_en(pose: Pose, origin_lat: float, origin_lon: float) -> tuple[float, float]:
    """East/north metres of the point below the UAV in the world frame around (origin_lat, origin_lon)."""
    east, north = latlon_to_local(pose.lat, pose.lon, origin_lat, origin_lon)
    return float(east), float(north)


def project_enu(points_enu: NDArray, camera: Camera, pose: Pose) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Project 3-D points into the image (pinhole, no distortion).

    points_enu: (N, 3) east/north/up metres relative to the ground point below the UAV. Returns uv (N, 2)
    float64 pixels (u right, v down, pixel centres at +0.5) and valid (N,) bool: False (uv NaN) for points
    at or behind the camera plane. For ground points (up = 0) in front of the camera and below the horizon
    this equals `shared.geo.local_to_pixel`.
    """
    pts = np.asarray(points_enu, dtype=np.float64).reshape(-1, 3)
    rel = pts - pose.camera_position_enu[None, :]
    cam = rel @ pose.R_world_from_cam  # rows: camera-frame coordinates (x right, y down, z forward)
    z = cam[:, 2]
    valid = z > 1e-6
    uv = np.full((len(pts), 2), np.nan)
    if valid.any():
        uv[valid, 0] = camera.fx * cam[valid, 0] / z[valid] + camera.cx
        uv[valid, 1] = camera.fy * cam[valid, 1] / z[valid] + camera.cy
    return uv, valid


def first_ground_row(camera: Camera, pose: Pose) -> int:
    """Index of the first image row whose pixel centres all see the ground (0..height).

    Rows above it are sky. With roll 0 the horizon is level, so `shared.geo.horizon_row` decides for every
    column; a pixel row r has its centre at v = r + 0.5.
    """
    row = horizon_row(camera, pose)
    if row == -math.inf:
        return 0
    if row == math.inf:
        return camera.height
    return int(min(max(math.floor(row - 0.5) + 1, 0), camera.height))


def texture_to_image_homography(camera: Camera, pose: Pose, uav_en: tuple[float, float],
                                texel_to_world: NDArray, first_row: int = 0) -> FloatArray:
    """(3, 3) homography for ``cv2.warpPerspective`` from texture indices to destination indices.

    texel_to_world: (3, 3) affine taking a texel's (column, row) index (cv2 coordinates: texel centres at
    integers) to world east/north metres. uav_en: the UAV's world east/north (`uav_world_en`). The
    destination is the image from row `first_row` down, in cv2 index coordinates (pixel (c, r) has its centre
    at u = c + 0.5, v = r + 0.5 + first_row).
    """
    to_local = np.array([[1.0, 0.0, -uav_en[0]], [0.0, 1.0, -uav_en[1]], [0.0, 0.0, 1.0]])
    to_index = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5 - first_row], [0.0, 0.0, 1.0]])
    h = to_index @ ground_to_image_homography(camera, pose) @ to_local @ np.asarray(texel_to_world, np.float64)
    return np.asarray(h / h[2, 2] if abs(h[2, 2]) > 1e-12 else h, dtype=np.float64)


def pixel_rays_grid(camera: Camera, pose: Pose, us: NDArray, vs: NDArray) -> FloatArray:
    """(len(vs), len(us), 3) unit ray directions (east, north, up) through the pixels us x vs."""
    x = (np.asarray(us, np.float64) - camera.cx) / camera.fx
    y = (np.asarray(vs, np.float64) - camera.cy) / camera.fy
    rays_cam = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((len(y), len(x)))), axis=-1)
    rays = rays_cam @ pose.R_world_from_cam.T
    return np.asarray(rays / np.linalg.norm(rays, axis=-1, keepdims=True), dtype=np.float64)


def slant_range_grid(camera: Camera, pose: Pose, us: NDArray, vs: NDArray) -> FloatArray:
    """(len(vs), len(us)) camera-to-ground distance in metres along each pixel's ray; inf where the ray
    does not go down (at or above the horizontal). Flat ground, as `shared.geo.pixel_slant_range_m`."""
    up = pixel_rays_grid(camera, pose, us, vs)[..., 2]
    with np.errstate(divide="ignore"):
        return np.where(up < -1e-9, pose.height_m / np.maximum(-up, 1e-12), np.inf)


def sun_position(lat_deg: float, lon_deg: float, t_unix_s: float) -> tuple[float, float]:
    """Sun azimuth (degrees clockwise from north) and elevation (degrees above the horizon).

    The NOAA low-accuracy formulas (declination and equation of time from the fractional year), good to
    about a degree: plenty for shadows and sun glint.
    """
    when = datetime.fromtimestamp(t_unix_s, tz=timezone.utc)
    day = when.timetuple().tm_yday
    hours = when.hour + when.minute / 60.0 + when.second / 3600.0
    g = 2.0 * math.pi / 365.0 * (day - 1 + (hours - 12.0) / 24.0)
    eqtime = 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                       - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))
    decl = (0.006918 - 0.399912 * math.cos(g) + 0.070257 * math.sin(g) - 0.006758 * math.cos(2 * g)
            + 0.000907 * math.sin(2 * g) - 0.002697 * math.cos(3 * g) + 0.00148 * math.sin(3 * g))
    true_solar_min = hours * 60.0 + eqtime + 4.0 * lon_deg
    hour_angle = math.radians(true_solar_min / 4.0 - 180.0)
    lat = math.radians(lat_deg)
    cos_zenith = math.sin(lat) * math.sin(decl) + math.cos(lat) * math.cos(decl) * math.cos(hour_angle)
    zenith = math.acos(min(max(cos_zenith, -1.0), 1.0))
    elevation = 90.0 - math.degrees(zenith)
    az = math.degrees(math.atan2(math.sin(hour_angle),
                                 math.cos(hour_angle) * math.sin(lat) - math.tan(decl) * math.cos(lat)))
    return (az + 180.0) % 360.0, elevation


def sun_vector(azimuth_deg: float, elevation_deg: float) -> FloatArray:
    """(3,) unit vector (east, north, up) pointing at the sun."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])

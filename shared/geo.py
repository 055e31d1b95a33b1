"""Pixel <-> ground geometry for a gimballed pinhole camera over flat ground, or over a terrain.

Pose value object, vectorised projections, horizon, footprint and ground homography; the camera's
intrinsics live in `shared.camera` (re-exported here).

Frames and conventions (DESIGN.md 2):
- Local ground frame: east, north, up in metres, origin on the ground below the UAV.
- Camera frame (OpenCV): x right, y down, z forward along the optical axis.
- pitch_deg: depression of the optical axis below the horizontal, 0..90 (90 = nadir).
- heading_deg: yaw of the optical axis, clockwise from true north.
- roll_deg: rotation about the optical axis; positive turns the image's right side down
  (the aircraft convention: right wing down), so the horizon appears rotated anticlockwise.
- Pixels: u right, v down, origin at the top-left corner of the top-left pixel, so a pixel's
  centre is at (col + 0.5, row + 0.5) and cx = width / 2 is the image centre.

A ray is valid (meets the ground) when its depression below the horizontal exceeds the dip of
the true horizon, acos(R / (R + h)), so flat-ground results stop where the curved earth's
horizon is; far pixels just below it are still noisy, which callers limit with max_range_m.

`terrain=` (a `GroundSurface`, e.g. `shared.terrain.Terrain`) replaces the flat plane by a surface whose
height `up` varies in the local frame (docs/geometry.md, Terrain); without it the flat results are exactly
those of the flat model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq

from shared.camera import CAMERA_PRESETS as CAMERA_PRESETS  # re-exported: the names callers import from here
from shared.camera import Camera as Camera
from shared.camera import _check_finite, _check_range

# WGS84 ellipsoid
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
EARTH_MEAN_RADIUS_M = 6371008.8

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


# ---------------------------------------------------------------------------------------------
# Value objects
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Pose:
    """Camera pose: UAV position, height above the ground below it, gimbal angles in degrees."""

    lat: float
    lon: float
    height_m: float
    pitch_deg: float
    heading_deg: float
    roll_deg: float = 0.0
    _rotation: FloatArray = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        _check_range("Pose.lat", self.lat, -90.0, 90.0)
        _check_range("Pose.lon", self.lon, -180.0, 180.0)
        _check_finite("Pose.height_m", self.height_m)
        if self.height_m <= 0:
            raise ValueError(f"Pose.height_m={self.height_m!r} must be > 0 metres above the ground")
        _check_range("Pose.pitch_deg", self.pitch_deg, 0.0, 90.0)
        _check_finite("Pose.heading_deg", self.heading_deg)
        _check_range("Pose.roll_deg", self.roll_deg, -90.0, 90.0)
        object.__setattr__(self, "_rotation", _camera_to_world(self.pitch_deg, self.heading_deg, self.roll_deg))

    @property
    def R_world_from_cam(self) -> FloatArray:  # noqa: N802
        """(3, 3) rotation taking camera-frame vectors to east/north/up vectors."""
        return self._rotation

    @property
    def camera_position_enu(self) -> FloatArray:
        """(3,) camera centre in the local ground frame: (0, 0, height_m)."""
        return np.array([0.0, 0.0, self.height_m])


def _camera_to_world(pitch_deg: float, heading_deg: float, roll_deg: float) -> FloatArray:
    """Columns are the camera's x (right), y (down) and z (forward) axes in east/north/up."""
    b, h, r = math.radians(pitch_deg), math.radians(heading_deg), math.radians(roll_deg)
    forward = np.array([math.sin(h) * math.cos(b), math.cos(h) * math.cos(b), -math.sin(b)])
    right0 = np.array([math.cos(h), -math.sin(h), 0.0])
    down0 = np.cross(forward, right0)
    right = math.cos(r) * right0 + math.sin(r) * down0
    down = math.cos(r) * down0 - math.sin(r) * right0
    return np.column_stack([right, down, forward])


class GroundSurface(Protocol):
    """Ground that is not the flat plane below the UAV (`shared.terrain.Terrain` is one).

    Heights are `up` metres in the pose's local frame: 0 is the plane the flat model uses, the one
    pose.height_m is measured from; the camera is at up = pose.height_m.
    """

    def intersect_rays(self, rays_enu: FloatArray, pose: Pose, max_range_m: float | None = None
                       ) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
        """(N, 3) unit rays from the camera -> east, north, up of the first hit, valid (N,); NaN where none."""
        ...

    def up_m(self, east_m: FloatArray, north_m: FloatArray, pose: Pose) -> FloatArray:
        """(N,) surface height at local points, metres; NaN where unknown."""
        ...


# ---------------------------------------------------------------------------------------------
# Earth model
# ---------------------------------------------------------------------------------------------

def meridian_radius_m(lat_deg: ArrayLike) -> FloatArray:
    """WGS84 meridian radius of curvature M at latitude lat_deg (degrees), metres."""
    s = np.sin(np.radians(np.asarray(lat_deg, dtype=np.float64)))
    return WGS84_A_M * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s) ** 1.5


def prime_vertical_radius_m(lat_deg: ArrayLike) -> FloatArray:
    """WGS84 prime-vertical radius of curvature N at latitude lat_deg (degrees), metres."""
    s = np.sin(np.radians(np.asarray(lat_deg, dtype=np.float64)))
    return WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * s * s)


def local_to_latlon(east_m: ArrayLike, north_m: ArrayLike, lat0: float, lon0: float) -> tuple[FloatArray, FloatArray]:
    """Local east/north offsets (metres) around (lat0, lon0) to lat/lon degrees (tangent plane); longitudes past the
    antimeridian wrap into [-180, 180) (a drone over Fiji: 180.0002 was refused in its state message)."""
    e = np.asarray(east_m, dtype=np.float64)
    n = np.asarray(north_m, dtype=np.float64)
    m = float(meridian_radius_m(lat0))
    p = float(prime_vertical_radius_m(lat0)) * math.cos(math.radians(lat0))
    lon = lon0 + np.degrees(e / p)
    if np.any(np.abs(lon) > 180.0):  # rare: only then the wrap's rounding (lon0 itself stays as given)
        lon = np.where(np.abs(lon) > 180.0, (lon + 180.0) % 360.0 - 180.0, lon)
    return lat0 + np.degrees(n / m), lon


def latlon_to_local(lat: ArrayLike, lon: ArrayLike, lat0: float, lon0: float) -> tuple[FloatArray, FloatArray]:
    """Lat/lon degrees to local east/north metres around (lat0, lon0); inverse of local_to_latlon."""
    la = np.asarray(lat, dtype=np.float64)
    lo = np.asarray(lon, dtype=np.float64)
    m = float(meridian_radius_m(lat0))
    p = float(prime_vertical_radius_m(lat0)) * math.cos(math.radians(lat0))
    dlon = (lo - lon0 + 180.0) % 360.0 - 180.0
    return np.radians(dlon) * p, np.radians(la - lat0) * m


def horizon_dip_deg(height_m: float) -> float:
    """Dip of the visible horizon below the horizontal for an eye height_m above a spherical earth."""
    return math.degrees(math.acos(EARTH_MEAN_RADIUS_M / (EARTH_MEAN_RADIUS_M + height_m)))


def horizon_distance_m(height_m: float) -> float:
    """Distance to the visible horizon, metres (~3.57 km * sqrt(h / 1 m))."""
    return math.sqrt(2.0 * EARTH_MEAN_RADIUS_M * height_m + height_m * height_m)


# ---------------------------------------------------------------------------------------------
# Rays
# ---------------------------------------------------------------------------------------------

def _as_uv(uv: ArrayLike) -> FloatArray:
    arr = np.asarray(uv, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 2:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"uv must have shape (N, 2), got {np.shape(uv)}")
    return arr


def normalized_coords(uv: ArrayLike, camera: Camera) -> FloatArray:
    """(N, 2) pixels -> (N, 2) undistorted normalised image coordinates (x/z, y/z)."""
    pts = _as_uv(uv)
    if camera.dist is None:
        return np.column_stack([(pts[:, 0] - camera.cx) / camera.fx, (pts[:, 1] - camera.cy) / camera.fy])
    if len(pts) == 0:
        return np.zeros((0, 2))
    # The default 5 iterations leave ~0.1 px errors at the corners of strongly distorted lenses.
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    # OpenCV 4 names the iterative variant undistortPointsIter; OpenCV 5 folds it into undistortPoints.
    undistort = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)
    eye = np.eye(3)  # R = P = I: normalised output (OpenCV 5 rejects P=None with criteria)
    und = undistort(pts.reshape(-1, 1, 2), camera.K, camera.dist_array, None, eye, eye, criteria)
    return und.reshape(-1, 2).astype(np.float64)


def _project_normalized(xy: FloatArray, camera: Camera) -> FloatArray:
    """(N, 2) normalised coordinates -> (N, 2) pixels, applying distortion."""
    if camera.dist is None or len(xy) == 0:
        return np.column_stack([xy[:, 0] * camera.fx + camera.cx, xy[:, 1] * camera.fy + camera.cy])
    obj = np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3)
    img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), camera.K, camera.dist_array)
    return img.reshape(-1, 2).astype(np.float64)


def pixel_rays_enu(uv: ArrayLike, camera: Camera, pose: Pose) -> FloatArray:
    """(N, 2) pixels -> (N, 3) unit ray directions in east/north/up."""
    xy = normalized_coords(uv, camera)
    rays_cam = np.column_stack([xy, np.ones(len(xy))])
    rays = rays_cam @ pose.R_world_from_cam.T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _min_depression_sin(pose: Pose) -> float:
    return math.sin(math.radians(horizon_dip_deg(pose.height_m)))


def pixel_to_local(
    uv: ArrayLike, camera: Camera, pose: Pose, *, max_range_m: float | None = None,
    terrain: GroundSurface | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Project pixels to the ground plane in local metres around the point below the UAV.

    uv: (N, 2) float pixel coordinates (u right, v down).
    max_range_m: optional horizontal distance beyond which points are marked invalid.
    terrain: intersect the rays with this surface instead (the first hit; its height: terrain.up_m).
    Returns east_m, north_m (N,) float64 and valid (N,) bool; NaN where invalid (the ray is at or
    above the horizon, or farther than max_range_m; with a terrain: no hit on it within range).
    """
    rays = pixel_rays_enu(uv, camera, pose)
    if terrain is not None:
        east, north, _, valid = terrain.intersect_rays(rays, pose, max_range_m)
        return east, north, valid
    valid = rays[:, 2] < -_min_depression_sin(pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(valid, -pose.height_m / rays[:, 2], np.nan)
    east = t * rays[:, 0]
    north = t * rays[:, 1]
    if max_range_m is not None:
        valid &= np.hypot(east, north) <= max_range_m
        east = np.where(valid, east, np.nan)
        north = np.where(valid, north, np.nan)
    return east, north, valid


def pixel_to_latlon(
    uv: ArrayLike, camera: Camera, pose: Pose, *, max_range_m: float | None = None,
    terrain: GroundSurface | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Project pixels to the ground plane (or to `terrain`'s surface, see pixel_to_local).

    uv: (N, 2) float pixel coordinates (u right, v down); lens distortion is removed first.
    Returns lat, lon in degrees, shape (N,), and valid (N,) bool: False where the ray does not
    meet the ground (at or above the horizon) or lies beyond max_range_m; lat/lon are NaN there.
    """
    east, north, valid = pixel_to_local(uv, camera, pose, max_range_m=max_range_m, terrain=terrain)
    lat, lon = local_to_latlon(east, north, pose.lat, pose.lon)
    return lat, lon, valid


def local_to_pixel(
    east_m: ArrayLike, north_m: ArrayLike, camera: Camera, pose: Pose, *, terrain: GroundSurface | None = None
) -> tuple[FloatArray, BoolArray]:
    """Project ground points (local metres, up = 0; with a terrain, up = terrain.up_m there) into the image.

    Returns uv (N, 2) float64 pixels and valid (N,) bool: False (uv NaN) for points behind the
    camera or beyond the horizon (with a terrain: behind the camera or off the terrain; points hidden
    behind a hill are not tested). Valid points may still fall outside the image bounds: compare
    with camera.width/height where that matters.
    """
    e = np.atleast_1d(np.asarray(east_m, dtype=np.float64))
    n = np.atleast_1d(np.asarray(north_m, dtype=np.float64))
    if e.shape != n.shape or e.ndim != 1:
        raise ValueError(f"east_m and north_m must be (N,) arrays of one shape, got {e.shape} and {n.shape}")
    up = None if terrain is None else terrain.up_m(e, n, pose)
    rel = np.column_stack([e, n, np.full(len(e), -pose.height_m) if up is None else up - pose.height_m])
    cam = rel @ pose.R_world_from_cam  # rows: camera-frame coordinates
    dist = np.linalg.norm(rel, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        if up is None:
            valid = (cam[:, 2] > 1e-9 * dist) & (pose.height_m / dist > _min_depression_sin(pose))
        else:  # a hillside above the camera is ground too
            valid = (cam[:, 2] > 1e-9 * dist) & np.isfinite(up)
        valid &= np.isfinite(e) & np.isfinite(n)
        xy = np.where(valid[:, None], cam[:, :2] / cam[:, 2:3], np.nan)
    uv = np.full((len(e), 2), np.nan)
    if valid.any():
        uv[valid] = _project_normalized(xy[valid], camera)
    return uv, valid


def latlon_to_pixel(
    lat: ArrayLike, lon: ArrayLike, camera: Camera, pose: Pose, *, terrain: GroundSurface | None = None
) -> tuple[FloatArray, BoolArray]:
    """Project ground points given in lat/lon degrees into the image (inverse of pixel_to_latlon).

    lat, lon: (N,) degrees; with a terrain, the points lie on its surface (local_to_pixel). Returns uv
    (N, 2) float64 pixels and valid (N,) bool: False (uv NaN) for points behind the camera or beyond
    the horizon. Valid points may lie outside the image.
    """
    east, north = latlon_to_local(lat, lon, pose.lat, pose.lon)
    return local_to_pixel(np.atleast_1d(east), np.atleast_1d(north), camera, pose, terrain=terrain)


def pixel_ground_distance_m(uv: ArrayLike, camera: Camera, pose: Pose) -> FloatArray:
    """Horizontal ground distance (metres) from the point below the UAV to each pixel's ground point.

    uv: (N, 2) pixels. Returns (N,) float64; NaN where the pixel does not see the ground.
    """
    east, north, _ = pixel_to_local(uv, camera, pose)
    return np.hypot(east, north)


def pixel_slant_range_m(uv: ArrayLike, camera: Camera, pose: Pose, *,
                        terrain: GroundSurface | None = None) -> FloatArray:
    """Camera-to-ground distance (metres) along each pixel's ray; NaN where there is no ground."""
    if terrain is not None:
        east, north, up, _ = terrain.intersect_rays(pixel_rays_enu(uv, camera, pose), pose)
        return np.sqrt(east * east + north * north + (pose.height_m - up) ** 2)
    east, north, _ = pixel_to_local(uv, camera, pose)
    return np.sqrt(east * east + north * north + pose.height_m * pose.height_m)


def metres_per_pixel(uv: ArrayLike, camera: Camera, pose: Pose, *,
                     terrain: GroundSurface | None = None) -> FloatArray:
    """Approximate ground sampling distance at each pixel: slant range / focal length, metres.

    This is the metric size of one pixel on a surface facing the camera (the form the size
    filter uses, independent of the camera's resolution). (N,) float64, NaN without ground.
    """
    return pixel_slant_range_m(uv, camera, pose, terrain=terrain) / math.sqrt(camera.fx * camera.fy)


# ---------------------------------------------------------------------------------------------
# Horizon, footprint, homography
# ---------------------------------------------------------------------------------------------

def horizon_row(camera: Camera, pose: Pose) -> float:
    """Image row of the horizon at the principal point's column (float, may lie outside the image).

    Rows greater than this (below it) see the ground; the returned row is where rays reach the
    dip of the true horizon. With roll the horizon is tilted: this is its row at u = cx.
    Returns -inf when the whole column sees the ground, +inf when none of it does.
    """
    r = pose.R_world_from_cam
    a, b = r[2, 1], r[2, 2]  # up-components of the camera's y (down) and z (forward) axes
    s = _min_depression_sin(pose)
    # Ray (0, y, 1) has up-component (a*y + b) / sqrt(1 + y^2); the horizon is where it equals -s.
    qa, qb, qc = a * a - s * s, 2.0 * a * b, b * b - s * s
    if abs(qa) < 1e-15:
        roots = np.array([-qc / qb]) if qb != 0 else np.array([])
    else:
        disc = qb * qb - 4.0 * qa * qc
        if disc < 0:
            return -math.inf if b < -s else math.inf
        sq = math.sqrt(disc)
        roots = np.array([(-qb - sq) / (2 * qa), (-qb + sq) / (2 * qa)])
    # Squaring admits spurious roots on the upward branch; keep those where the ray goes down.
    # a <= 0 for every allowed pose, so rows below the upper root see the ground.
    good = [y for y in roots if a * y + b < 0]
    if not good:
        return -math.inf if b < -s else math.inf
    y_n = min(good)
    row = float(_project_normalized(np.array([[0.0, y_n]]), camera)[0, 1])
    if camera.dist is None:
        return row
    # Tangential distortion bends the line x_n = 0 away from the column u = cx: refine on the pixel
    # column itself, bracketing the root around the undistorted estimate.
    def excess(v: float) -> float:
        return float(pixel_rays_enu(np.array([[camera.cx, v]]), camera, pose)[0, 2] + s)

    step = 1.0
    lo, hi = row - step, row + step
    while excess(lo) * excess(hi) > 0 and step < camera.height:
        step *= 2.0
        lo, hi = row - step, row + step
    if excess(lo) * excess(hi) > 0:
        return row
    return float(brentq(excess, lo, hi, xtol=1e-9))


def image_border(camera: Camera, samples_per_edge: int = 32) -> FloatArray:
    """(4 * samples_per_edge, 2) pixels along the image border, clockwise from the top-left corner."""
    w, h = float(camera.width), float(camera.height)
    t = np.linspace(0.0, 1.0, samples_per_edge, endpoint=False)
    top = np.column_stack([t * w, np.zeros_like(t)])
    right = np.column_stack([np.full_like(t, w), t * h])
    bottom = np.column_stack([w - t * w, np.full_like(t, h)])
    left = np.column_stack([np.zeros_like(t), h - t * h])
    return np.vstack([top, right, bottom, left])


def footprint_local(
    camera: Camera, pose: Pose, *, max_range_m: float = 500.0, samples_per_edge: int = 32,
    terrain: GroundSurface | None = None,
) -> FloatArray:
    """Ground footprint of the frame as a polygon in local east/north metres, (M, 2).

    The image border is cast onto the ground; rays that pass the horizon or land farther than
    max_range_m are cut to the point at max_range_m along their azimuth, so the polygon is the
    visible ground within that range.
    terrain: cast the border onto this surface instead (the first hit of each border ray); a border ray
    that meets no terrain within range (it passes every height in reach, or leaves the DEM first) keeps
    the flat footprint's point. The polygon is the outline: ground the terrain hides inside it is not cut
    out. Without a terrain the result is bit-identical to the flat footprint.
    """
    if max_range_m <= 0:
        raise ValueError(f"max_range_m must be > 0, got {max_range_m!r}")
    rays = pixel_rays_enu(image_border(camera, samples_per_edge), camera, pose)
    s = _min_depression_sin(pose)
    horiz = np.hypot(rays[:, 0], rays[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[:, 2] < -s, -pose.height_m / rays[:, 2], np.inf)
        reach = np.minimum(t * horiz, max_range_m)
        scale = np.where(horiz > 1e-12, reach / horiz, 0.0)
    polygon = np.column_stack([rays[:, 0] * scale, rays[:, 1] * scale])
    if terrain is not None:
        east, north, _, hit = terrain.intersect_rays(rays, pose, max_range_m)
        polygon[hit, 0] = east[hit]
        polygon[hit, 1] = north[hit]
    return polygon


def footprint_latlon(
    camera: Camera, pose: Pose, *, max_range_m: float = 500.0, samples_per_edge: int = 32,
    terrain: GroundSurface | None = None,
) -> FloatArray:
    """Ground footprint polygon as (M, 2) [lat, lon] degrees (see footprint_local)."""
    en = footprint_local(camera, pose, max_range_m=max_range_m, samples_per_edge=samples_per_edge, terrain=terrain)
    lat, lon = local_to_latlon(en[:, 0], en[:, 1], pose.lat, pose.lon)
    return np.column_stack([lat, lon])


def ground_to_image_homography(camera: Camera, pose: Pose) -> FloatArray:
    """(3, 3) homography H with [u, v, 1] ~ H [east_m, north_m, 1] for undistorted pixels.

    Only meaningful for ground points in front of the camera and below the horizon; invert it
    (np.linalg.inv) for image -> ground, or compose it with a grid's affine map for whole-heatmap
    warps with cv2.warpPerspective.
    """
    r_cw = pose.R_world_from_cam.T
    c = pose.camera_position_enu
    m = np.column_stack([r_cw[:, 0], r_cw[:, 1], -r_cw @ c])
    return camera.K @ m


def image_to_ground_homography(camera: Camera, pose: Pose) -> FloatArray:
    """(3, 3) homography with [east_m, north_m, 1] ~ H [u, v, 1] (inverse of the above)."""
    return np.asarray(np.linalg.inv(ground_to_image_homography(camera, pose)), dtype=np.float64)

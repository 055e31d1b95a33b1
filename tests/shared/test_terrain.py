"""Terrain (shared.terrain) against independent models: dense ray sampling over scipy's interpolator on a 1 m DEM,
analytic ray-plane intersections, and the flat model of shared.geo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter

from shared.geo import (
    Camera,
    Pose,
    footprint_latlon,
    footprint_local,
    image_border,
    latlon_to_local,
    latlon_to_pixel,
    local_to_latlon,
    local_to_pixel,
    metres_per_pixel,
    pixel_rays_enu,
    pixel_to_latlon,
    pixel_to_local,
)
from shared.terrain import ElevationGrid, Terrain, pixel_to_terrain
from tests.shared.test_geo import independent_rotation

CAM = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
ORIGIN = (47.67, 9.27)
HALF_M = 150  # the test DEMs span +-150 m around ORIGIN at 1 m


def local_grid(heights: np.ndarray, cell_m: float = 1.0) -> ElevationGrid:
    """A DEM centred on ORIGIN in local metres (rows north to south)."""
    rows, cols = heights.shape
    return ElevationGrid.from_local(heights, *ORIGIN, west_m=-(cols - 1) * cell_m / 2,
                                    north_m=(rows - 1) * cell_m / 2, cell_m=cell_m)


def random_dem(seed: int, relief_m: float, smooth_cells: float, rough_m: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 2 * HALF_M + 1
    field = gaussian_filter(rng.normal(0.0, 1.0, (n, n)), smooth_cells)
    field *= relief_m / max(float(np.ptp(field)), 1e-9)
    return 380.0 + field + rng.uniform(0.0, rough_m, (n, n))


def pose_at(east_m: float, north_m: float, **angles) -> Pose:
    lat, lon = local_to_latlon(east_m, north_m, *ORIGIN)
    return Pose(lat=float(lat), lon=float(lon), **angles)


def oracle_hits(heights: np.ndarray, pose: Pose, camera_elevation_m: float, uv: np.ndarray, max_range_m: float,
                step_m: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) east/north (pose frame) of each pixel's first terrain point and (N,) found: the ray sampled every
    step_m metres (rotation from elementary rotations, terrain from scipy's bilinear interpolator)."""
    n = heights.shape[0]
    axis = np.arange(n, dtype=float) - (n - 1) / 2
    terrain = RegularGridInterpolator((axis, axis), heights[::-1], bounds_error=False, fill_value=np.nan)
    pe0, pn0 = (float(v) for v in latlon_to_local(pose.lat, pose.lon, *ORIGIN))
    r = independent_rotation(pose.pitch_deg, pose.heading_deg, pose.roll_deg)
    rays = np.column_stack([(uv[:, 0] - CAM.cx) / CAM.fx, (uv[:, 1] - CAM.cy) / CAM.fy, np.ones(len(uv))]) @ r.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    out = np.full((len(uv), 2), np.nan)
    found = np.zeros(len(uv), dtype=bool)
    for k, (rx, ry, rz) in enumerate(rays):
        horiz = math.hypot(rx, ry)
        t_max = (max_range_m + 1.0) / horiz if horiz > 1e-9 else 1e4
        t = np.arange(0.0, min(t_max, 600.0), step_m)
        z = camera_elevation_m + rz * t
        ground = terrain(np.column_stack([pn0 + ry * t, pe0 + rx * t]))
        below = np.flatnonzero(z <= ground)
        if len(below) and math.hypot(rx * t[below[0]], ry * t[below[0]]) <= max_range_m:
            out[k] = rx * t[below[0]], ry * t[below[0]]
            found[k] = True
    return out, found


# ----------------------------------------------------------------------------- value objects

@pytest.mark.parametrize(("kwargs", "field"), [
    ({"heights_m": np.zeros(5)}, "heights_m"),
    ({"heights_m": np.zeros((1, 5))}, "heights_m"),
    ({"heights_m": np.full((3, 3), np.inf)}, "heights_m"),
    ({"heights_m": np.full((3, 3), np.nan)}, "heights_m"),
    ({"lat_step_deg": 0.0}, "lat_step_deg"),
    ({"lon_step_deg": -0.001}, "lon_step_deg"),
    ({"lat0_deg": float("nan")}, "lat0_deg"),
])
def test_elevation_grid_rejects_bad_field_naming_it(kwargs, field):
    base = {"heights_m": np.zeros((3, 3)), "lat0_deg": 47.0, "lat_step_deg": -0.001, "lon0_deg": 9.0,
            "lon_step_deg": 0.001}
    with pytest.raises(ValueError, match=field):
        ElevationGrid(**{**base, **kwargs})


def test_terrain_rejects_a_bad_takeoff_elevation():
    grid = local_grid(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="takeoff_elevation_m"):
        Terrain(grid, float("inf"))
    with pytest.raises(ValueError, match="grid"):
        Terrain(np.zeros((3, 3)))  # type: ignore[arg-type]


def test_heights_are_bilinear_between_samples_and_nan_off_the_grid():
    grid = ElevationGrid(np.array([[10.0, 20.0], [30.0, 44.0]]), lat0_deg=47.001, lon0_deg=9.0,
                         lat_step_deg=-0.001, lon_step_deg=0.001)
    assert grid.height_at(47.001, 9.0) == 10.0
    assert grid.height_at(47.0, 9.001) == pytest.approx(44.0)
    assert grid.height_at(47.0005, 9.0005) == pytest.approx((10 + 20 + 30 + 44) / 4)
    assert grid.height_at(47.001, 9.00025) == pytest.approx(12.5)
    assert np.isnan(grid.height_at(47.0015, 9.0005)) and np.isnan(grid.height_at(47.0005, 9.0011))
    assert grid.bounds() == pytest.approx((47.0, 47.001, 9.0, 9.001))


def test_the_reference_is_the_takeoff_elevation_or_the_ground_below():
    heights = 400.0 + np.add.outer(np.zeros(2 * HALF_M + 1), np.arange(2 * HALF_M + 1) * 0.1)  # rises east
    grid = local_grid(heights)
    pose = pose_at(20.0, 0.0, height_m=30.0, pitch_deg=90.0, heading_deg=0.0)
    below = Terrain(grid)
    assert below.base_elevation_m(pose) == pytest.approx(400.0 + 17.0)  # 170 m from the west edge
    east, north, up, valid = below.intersect_rays(np.array([[0.0, 0.0, -1.0]]), pose)
    assert valid[0] and up[0] == pytest.approx(0.0, abs=1e-9) and abs(east[0]) < 1e-9
    takeoff = below.with_takeoff_elevation(407.0)  # took off 100 m further west: the UAV is 10 m lower here
    east, north, up, valid = takeoff.intersect_rays(np.array([[0.0, 0.0, -1.0]]), pose)
    assert valid[0] and up[0] == pytest.approx(10.0)
    assert takeoff.up_m(np.array([-20.0]), np.array([0.0]), pose)[0] == pytest.approx(8.0)


# ----------------------------------------------------------------------------- against independent models

def test_a_flat_dem_at_the_reference_gives_the_flat_result():
    grid = local_grid(np.full((2 * HALF_M + 1, 2 * HALF_M + 1), 512.0))
    rng = np.random.default_rng(1)
    uv = np.column_stack([rng.uniform(0, CAM.width, 2000), rng.uniform(0, CAM.height, 2000)])
    for pose in (pose_at(5.0, -7.0, height_m=40.0, pitch_deg=35.0, heading_deg=200.0, roll_deg=3.0),
                 pose_at(0.0, 0.0, height_m=80.0, pitch_deg=90.0, heading_deg=10.0)):
        for terrain in (Terrain(grid, 512.0), Terrain(grid)):
            e0, n0, v0 = pixel_to_local(uv, CAM, pose, max_range_m=120.0)
            e1, n1, v1 = pixel_to_local(uv, CAM, pose, max_range_m=120.0, terrain=terrain)
            assert v0.any() and np.array_equal(v0, v1)
            np.testing.assert_allclose(e1[v1], e0[v0], atol=1e-8)
            np.testing.assert_allclose(n1[v1], n0[v0], atol=1e-8)
            lat0, lon0, _ = pixel_to_latlon(uv, CAM, pose, max_range_m=120.0)
            lat1, lon1, _ = pixel_to_latlon(uv, CAM, pose, max_range_m=120.0, terrain=terrain)
            np.testing.assert_allclose(lat1[v1], lat0[v0], atol=1e-12)
            uv0, ok0 = local_to_pixel(e0[v0], n0[v0], CAM, pose)
            uv1, ok1 = local_to_pixel(e0[v0], n0[v0], CAM, pose, terrain=terrain)
            assert ok0.all() and ok1.all()
            np.testing.assert_allclose(uv1, uv0, atol=1e-7)
            np.testing.assert_allclose(metres_per_pixel(uv[v0], CAM, pose, terrain=terrain),
                                       metres_per_pixel(uv[v0], CAM, pose), rtol=1e-10)


@settings(max_examples=40, deadline=None)
@given(gx=st.floats(-0.3, 0.3), gy=st.floats(-0.3, 0.3), offset=st.floats(-15.0, 15.0),
       height=st.floats(10.0, 120.0), pitch=st.floats(30.0, 90.0), heading=st.floats(0.0, 360.0),
       u=st.floats(0, 3840), v=st.floats(0, 2160))
def test_rays_meet_a_tilted_plane_where_the_analytic_intersection_is(gx, gy, offset, height, pitch, heading, u, v):
    """Bilinear interpolation reproduces a plane exactly, so the hit is the ray-plane intersection."""
    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    east, north = np.meshgrid(axis, axis[::-1])
    grid = local_grid(300.0 + gx * east + gy * north)
    pose = pose_at(0.0, 0.0, height_m=height, pitch_deg=pitch, heading_deg=heading)
    terrain = Terrain(grid, 300.0 + offset)  # the take-off lies offset metres above the plane under the UAV
    ray = pixel_rays_enu(np.array([[u, v]]), CAM, pose)[0]
    # camera at z = offset + height above the plane's value at the origin; plane z = gx e + gy n
    denom = ray[2] - gx * ray[0] - gy * ray[1]
    t = -(offset + height) / denom if denom < 0 else math.inf
    e, n, up, valid = terrain.intersect_rays(ray[None, :], pose)
    if offset + height <= 0:
        assert not valid[0]
        return
    if math.isfinite(t) and max(abs(t * ray[0]), abs(t * ray[1])) < HALF_M - 1:
        assert valid[0]
        assert e[0] == pytest.approx(t * ray[0], abs=1e-6) and n[0] == pytest.approx(t * ray[1], abs=1e-6)
        assert up[0] == pytest.approx(gx * e[0] + gy * n[0] - offset, abs=1e-6)
    elif not math.isfinite(t):
        assert not valid[0]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), relief=st.floats(0.0, 25.0), smooth=st.floats(1.5, 12.0),
       rough=st.floats(0.0, 0.5), height=st.floats(10.0, 100.0), pitch=st.floats(30.0, 90.0),
       heading=st.floats(0.0, 360.0), roll=st.floats(-5.0, 5.0), pe=st.floats(-20.0, 20.0),
       pn=st.floats(-20.0, 20.0))
def test_ground_points_within_half_a_metre_of_dense_ray_sampling_on_a_1m_dem(seed, relief, smooth, rough, height,
                                                                             pitch, heading, roll, pe, pn):
    heights = random_dem(seed, relief, smooth, rough)
    pose = pose_at(pe, pn, height_m=height, pitch_deg=pitch, heading_deg=heading, roll_deg=roll)
    terrain = Terrain(local_grid(heights))  # heights above the ground below the UAV
    rng = np.random.default_rng(seed)
    uv = np.column_stack([rng.uniform(0, CAM.width, 12), rng.uniform(0, CAM.height, 12)])
    max_range = 120.0
    e, n, valid = pixel_to_local(uv, CAM, pose, max_range_m=max_range, terrain=terrain)
    truth, found = oracle_hits(heights, pose, terrain.base_elevation_m(pose) + height, uv, max_range)
    reach = np.hypot(truth[:, 0], truth[:, 1])
    clear = ~found | (reach < max_range - 1.0)  # not at the range limit, where rounding may decide
    assert np.array_equal(valid[clear], found[clear])
    both = valid & found
    err = np.hypot(e[both] - truth[both, 0], n[both] - truth[both, 1])
    assert (err <= 0.5).all(), err.max()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), relief=st.floats(0.0, 25.0), height=st.floats(10.0, 120.0),
       pitch=st.floats(20.0, 90.0), heading=st.floats(0.0, 360.0), roll=st.floats(-10.0, 10.0),
       takeoff=st.floats(-20.0, 20.0))
def test_pixel_terrain_pixel_round_trip(seed, relief, height, pitch, heading, roll, takeoff):
    heights = random_dem(seed, relief, 4.0, 0.2)
    pose = pose_at(3.0, -4.0, height_m=height, pitch_deg=pitch, heading_deg=heading, roll_deg=roll)
    terrain = Terrain(local_grid(heights), float(heights[HALF_M, HALF_M]) + takeoff)
    uv = np.column_stack([np.linspace(0, CAM.width, 25), np.linspace(CAM.height, 0, 25)])
    lat, lon, valid = pixel_to_latlon(uv, CAM, pose, terrain=terrain)
    back, ok = latlon_to_pixel(lat[valid], lon[valid], CAM, pose, terrain=terrain)
    assert ok.all()
    # 1e-4 px: far along a grazing ray a ground point's float64 latitude/longitude rounding alone moves the
    # pixel by ~1e-5 px (seed 669, 20 deg pitch, 20 m above flat ground: 1.1e-5)
    np.testing.assert_allclose(back, uv[valid], atol=1e-4)
    assert np.isnan(lat[~valid]).all()


# ----------------------------------------------------------------------------- no hit, horizon, edges

def test_rays_above_every_height_in_reach_leaving_the_dem_or_the_range_see_nothing():
    grid = local_grid(random_dem(3, 10.0, 5.0, 0.1))
    pose = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=10.0, heading_deg=90.0)
    terrain = Terrain(grid)
    top = np.column_stack([np.linspace(0, CAM.width, 9), np.zeros(9)])  # above the horizon at 10 deg pitch
    e, n, up, valid = pixel_to_terrain(top, CAM, pose, terrain)
    assert not valid.any() and np.isnan(e).all() and np.isnan(up).all()
    # 6 deg down: meets the plane ~285 m east, this +-5 m terrain beyond 230 m, the DEM ends at 150 m
    near_horizon = np.array([[CAM.cx, CAM.cy - math.tan(math.radians(4.0)) * CAM.fy]])
    assert not pixel_to_local(near_horizon, CAM, pose, terrain=terrain)[2][0]  # past the DEM's edge
    assert pixel_to_local(near_horizon, CAM, pose)[2][0]  # the flat model's plane goes on
    steep = np.array([[CAM.cx, CAM.height]])
    assert pixel_to_local(steep, CAM, pose, terrain=terrain)[2][0]
    assert not pixel_to_local(steep, CAM, pose, terrain=terrain, max_range_m=5.0)[2][0]


def test_a_hillside_above_the_camera_is_hit_and_projects_back():
    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    east, _ = np.meshgrid(axis, axis)
    heights = 100.0 + np.clip(east - 40.0, 0.0, None) * 2.0  # a wall of rock 40 m east rising 2 m per metre
    pose = pose_at(0.0, 0.0, height_m=20.0, pitch_deg=0.0, heading_deg=90.0)  # looking east, level
    terrain = Terrain(local_grid(heights), 100.0)
    uv = np.array([[CAM.cx, CAM.cy - 200.0]])  # 3.9 deg above the horizontal
    e, n, up, valid = pixel_to_terrain(uv, CAM, pose, terrain)
    assert valid[0] and up[0] > pose.height_m and 50.0 < e[0] < 60.0
    assert not pixel_to_local(uv, CAM, pose)[2][0]  # the flat model: no ground there
    back, ok = local_to_pixel(e, n, CAM, pose, terrain=terrain)
    assert ok[0] and np.allclose(back, uv, atol=1e-6)


def test_a_camera_below_the_ground_and_holes_in_the_dem_see_nothing():
    heights = np.full((2 * HALF_M + 1, 2 * HALF_M + 1), 200.0)
    heights[HALF_M - 10:HALF_M + 10, HALF_M + 20:HALF_M + 40] = np.nan  # a hole 20..40 m east of the centre
    grid = local_grid(heights)
    pose = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=45.0, heading_deg=90.0)
    hole = np.array([[CAM.cx, CAM.cy]])  # meets the plane 30 m east: in the hole
    assert not pixel_to_local(hole, CAM, pose, terrain=Terrain(grid, 200.0))[2][0]
    aside = np.array([[CAM.cx, CAM.height]])  # steeper, lands ~14 m east of the UAV: on data
    assert pixel_to_local(aside, CAM, pose, terrain=Terrain(grid, 200.0))[2][0]
    underground = Terrain(grid, 160.0)  # took off 40 m lower: the camera is 10 m below this ground
    assert not pixel_to_local(aside, CAM, pose, terrain=underground)[2].any()
    off = local_to_pixel(np.array([30.0, 500.0]), np.array([0.0, 0.0]), CAM, pose, terrain=Terrain(grid, 200.0))[1]
    assert off.tolist() == [False, False]  # in the hole, off the DEM


def test_a_uav_outside_the_dem_sees_what_its_rays_meet_over_it():
    grid = local_grid(np.full((2 * HALF_M + 1, 2 * HALF_M + 1), 50.0))
    pose = pose_at(-HALF_M - 20.0, 0.0, height_m=40.0, pitch_deg=30.0, heading_deg=90.0)  # west of it, looking east
    terrain = Terrain(grid, 50.0)
    e, n, valid = pixel_to_local(np.array([[CAM.cx, CAM.cy]]), CAM, pose, terrain=terrain)
    assert valid[0] and e[0] == pytest.approx(40.0 / math.tan(math.radians(30.0)))
    assert not Terrain(grid).intersect_rays(np.array([[1.0, 0.0, -1.0]]) / math.sqrt(2), pose)[3][0]  # no reference


def test_effective_height_is_the_pose_height_on_flat_ground_and_shrinks_on_a_slope_facing_away():
    from shared.terrain import effective_height_m

    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    east, north = np.meshgrid(axis, axis[::-1])
    pose = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=35.0, heading_deg=0.0)  # looking north
    uv = np.array([[CAM.cx, CAM.cy], [CAM.cx + 300.0, CAM.cy + 200.0]])
    flat = Terrain(local_grid(np.full_like(east, 50.0)), 50.0)
    e, n, up, valid = pixel_to_terrain(uv, CAM, pose, flat)
    np.testing.assert_allclose(effective_height_m(e, n, up, pose, flat), 30.0)
    away = Terrain(local_grid(50.0 - 0.3 * north), 50.0)  # falls 0.3 m per metre northward, away from the camera
    e, n, up, valid = pixel_to_terrain(uv, CAM, pose, away)
    h = effective_height_m(e, n, up, pose, away)
    slant = np.sqrt(e**2 + n**2 + (30.0 - up) ** 2)
    ray = np.column_stack([e, n, up - 30.0]) / slant[:, None]
    normal = np.array([0.0, 0.3, 1.0]) / math.hypot(0.3, 1.0)
    np.testing.assert_allclose(h, slant * np.abs(ray @ normal), rtol=1e-9)  # slant x sin(ray, surface)
    assert (h < 30.0).all()
    east_slope = Terrain(local_grid(50.0 + 0.2 * east), 50.0)
    gx, gy = east_slope.gradient(np.array([3.3, -40.0]), np.array([7.1, 12.0]), pose)
    np.testing.assert_allclose(gx, 0.2, atol=1e-9)
    np.testing.assert_allclose(gy, 0.0, atol=1e-9)


def _area(points: np.ndarray) -> float:
    """Area spanned by the central differences (rows 1 - 2 and 3 - 4) of (5, 2) ground points."""
    du, dv = points[1] - points[2], points[3] - points[4]
    return abs(du[0] * dv[1] - du[1] * dv[0])


@settings(max_examples=40, deadline=None)
@given(gx=st.floats(-0.3, 0.3), gy=st.floats(-0.3, 0.3), offset=st.floats(-10.0, 10.0),
       height=st.floats(15.0, 120.0), pitch=st.floats(30.0, 90.0), heading=st.floats(0.0, 360.0),
       u=st.floats(200, 3640), v=st.floats(200, 1960))
def test_footprint_scale_is_the_ground_area_of_a_pixel_against_level_grounds(gx, gy, offset, height, pitch,
                                                                             heading, u, v):
    """On a tilted plane (exact under bilinear interpolation) the scale is the square root of the ratio of the
    horizontal areas that a pixel's neighbourhood covers on the terrain and on level ground at the height of the
    ground below the UAV, by central differences of the two projections (the level one: each ray cut analytically
    at that height)."""
    from shared.terrain import footprint_scale

    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    east, north = np.meshgrid(axis, axis[::-1])
    terrain = Terrain(local_grid(300.0 + gx * east + gy * north), 300.0 + offset)
    pose = pose_at(0.0, 0.0, height_m=height, pitch_deg=pitch, heading_deg=heading)
    step = 0.05
    uv = np.array([[u, v], [u + step, v], [u - step, v], [u, v + step], [u, v - step]])
    e, n, up, valid = pixel_to_terrain(uv, CAM, pose, terrain, max_range_m=140.0)
    below = height + offset  # the plane lies offset metres below the take-off under the UAV
    if not valid.all() or height - up[0] <= 1.0 or below <= 1.0:
        return
    rays = pixel_rays_enu(uv, CAM, pose)
    level = rays[:, :2] * (below / -rays[:, 2])[:, None]  # every ray down to the ground below the UAV
    scale = footprint_scale(e[:1], n[:1], up[:1], pose, terrain)[0]
    expected = math.sqrt(_area(np.column_stack([e, n])) / _area(level))
    assert scale == pytest.approx(expected, rel=1e-4)


def test_footprint_scale_is_one_on_level_ground_below_one_facing_the_camera_and_above_facing_away():
    from shared.terrain import footprint_scale

    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    east, north = np.meshgrid(axis, axis[::-1])
    pose = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=35.0, heading_deg=0.0)  # looking north
    uv = np.array([[CAM.cx, CAM.cy], [CAM.cx + 300.0, CAM.cy + 200.0]])
    scales = {}
    for name, heights in (("flat", np.full_like(east, 50.0)), ("facing", 50.0 + 0.2 * north),
                          ("away", 50.0 - 0.2 * north)):
        terrain = Terrain(local_grid(heights), 50.0)
        e, n, up, valid = pixel_to_terrain(uv, CAM, pose, terrain)
        assert valid.all()
        scales[name] = footprint_scale(e, n, up, pose, terrain)
    np.testing.assert_allclose(scales["flat"], 1.0, rtol=1e-12)
    assert (scales["facing"] < 0.9).all() and (scales["away"] > 1.1).all()
    # a rise ahead of the UAV: nearer than level ground below it, so smaller; the same plateau level with the UAV's
    # ground: 1
    step_up = Terrain(local_grid(np.where(north > 20.0, 55.0, 50.0)), 50.0)
    e, n, up, valid = pixel_to_terrain(uv, CAM, pose, step_up)
    assert valid.all() and (up > 4.9).all()
    np.testing.assert_allclose(footprint_scale(e, n, up, pose, step_up), 25.0 / 30.0, rtol=1e-9)
    # a UAV outside the DEM (a take-off elevation given): the slope alone, drop / |g.en + drop|
    rising = Terrain(local_grid(50.0 + 0.2 * north), 50.0)
    outside = pose_at(0.0, -HALF_M - 20.0, height_m=60.0, pitch_deg=35.0, heading_deg=0.0)
    e, n, up, valid = pixel_to_terrain(uv, CAM, outside, rising)
    assert valid.all()
    drop = 60.0 - up
    np.testing.assert_allclose(footprint_scale(e, n, up, outside, rising), np.sqrt(drop / (0.2 * n + drop)), rtol=1e-6)
    # level ground at any height, also heights above sea level (a take-off elevation of 0 on the DEM's datum)
    for reference, level_m in ((0.0, 50.0), (50.0, 62.0), (50.0, 41.0)):
        terrain = Terrain(local_grid(np.full_like(east, level_m)), reference)
        at = pose_at(0.0, 0.0, height_m=30.0 + level_m - reference, pitch_deg=35.0, heading_deg=0.0)
        e, n, up, valid = pixel_to_terrain(uv, CAM, at, terrain)
        assert valid.all()
        np.testing.assert_allclose(footprint_scale(e, n, up, at, terrain), 1.0, rtol=1e-12)
    # no point, or a point not below the camera (a hillside above it): not defined
    terrain = Terrain(local_grid(np.full_like(east, 50.0)), 50.0)
    out = footprint_scale(np.array([np.nan, 10.0]), np.array([np.nan, 10.0]), np.array([np.nan, 31.0]), pose,
                          terrain)
    assert np.isnan(out).all()


# ----------------------------------------------------------------------------- footprint

def test_the_footprint_on_a_flat_dem_is_the_flat_footprint():
    grid = local_grid(np.full((2 * HALF_M + 1, 2 * HALF_M + 1), 512.0))
    pose = pose_at(5.0, -7.0, height_m=40.0, pitch_deg=35.0, heading_deg=200.0, roll_deg=3.0)
    flat = footprint_local(CAM, pose, max_range_m=120.0, samples_per_edge=16)
    on_dem = footprint_local(CAM, pose, max_range_m=120.0, samples_per_edge=16, terrain=Terrain(grid, 512.0))
    np.testing.assert_allclose(on_dem, flat, atol=1e-6)
    np.testing.assert_allclose(footprint_latlon(CAM, pose, max_range_m=120.0, terrain=Terrain(grid, 512.0)),
                               footprint_latlon(CAM, pose, max_range_m=120.0), atol=1e-10)


def test_the_footprint_on_rising_ground_is_nearer_and_lies_on_the_border_rays():
    axis = np.arange(-HALF_M, HALF_M + 1, dtype=float)
    _, north = np.meshgrid(axis, axis[::-1])
    heights = 100.0 + 0.2 * north  # rises 20 m per 100 m to the north
    terrain = Terrain(local_grid(heights), 100.0)
    pose = pose_at(0.0, 0.0, height_m=40.0, pitch_deg=45.0, heading_deg=0.0)
    flat = footprint_local(CAM, pose, max_range_m=140.0, samples_per_edge=8)
    hilly = footprint_local(CAM, pose, max_range_m=140.0, samples_per_edge=8, terrain=terrain)
    # the far (top) edge meets the rising ground before the flat plane
    top = slice(0, 8)
    assert (hilly[top, 1] < flat[top, 1] - 5.0).all()
    # every vertex is where its border pixel's ray meets the terrain
    uv, ok = local_to_pixel(hilly[:, 0], hilly[:, 1], CAM, pose, terrain=terrain)
    assert ok.all()
    border = image_border(CAM, 8)
    np.testing.assert_allclose(uv, border, atol=1e-6)


def test_footprint_rays_that_miss_the_terrain_keep_the_flat_point():
    grid = local_grid(random_dem(3, 10.0, 5.0, 0.1))
    pose = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=10.0, heading_deg=90.0)
    flat = footprint_local(CAM, pose, max_range_m=400.0, samples_per_edge=8)
    hilly = footprint_local(CAM, pose, max_range_m=400.0, samples_per_edge=8, terrain=Terrain(grid))
    _, _, hit = pixel_to_local(image_border(CAM, 8), CAM, pose, max_range_m=400.0, terrain=Terrain(grid))
    assert hit.any() and not hit.all()  # the top edge passes the DEM's edge, the bottom meets the terrain
    np.testing.assert_array_equal(hilly[~hit], flat[~hit])
    assert np.isfinite(hilly).all()

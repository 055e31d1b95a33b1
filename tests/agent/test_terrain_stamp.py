"""The memory map's stamp over a terrain (MemoryMapConfig.terrain_stamp): per-box radii in MemoryMap.add and the
pipeline's factors from shared.terrain.footprint_scale."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.memory_map import MemoryMap, MemoryMapConfig
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon
from shared.terrain import ElevationGrid, Terrain
from shared.tiles import TileGrid

LAT, LON = 48.0, 9.0
GRID = TileGrid()
CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
CLASSES = {1: "person"}
POSE = Pose(lat=LAT, lon=LON, height_m=40.0, pitch_deg=40.0, heading_deg=0.0)  # looking north


def cell_of(east_m: float, north_m: float):
    return GRID.latlon_to_cell(*local_to_latlon(east_m, north_m, LAT, LON))


def placed_map(config: MemoryMapConfig | None = None) -> MemoryMap:
    mm = MemoryMap(config or MemoryMapConfig())
    mm.advance(0.0, LAT, LON)
    return mm


# ----------------------------------------------------------------------------- MemoryMap.add(radius_scale=)

def test_a_scale_of_one_is_the_plain_stamp_and_half_is_the_stamp_of_half_the_radius():
    gx, gy = cell_of([0.0, 20.0, -15.0], [5.0, 30.0, -10.0])
    amp = np.array([0.3, 0.7, 0.5])
    plain, ones, half, small = placed_map(), placed_map(), placed_map(), placed_map(MemoryMapConfig(radius_m=2.0))
    plain.add("person", gx, gy, amp)
    ones.add("person", gx, gy, amp, np.ones(3))
    half.add("person", gx, gy, amp, 0.5)
    small.add("person", gx, gy, amp)
    np.testing.assert_array_equal(ones.layer("person"), plain.layer("person"))
    np.testing.assert_allclose(half.layer("person"), small.layer("person"), atol=1e-7)
    assert np.count_nonzero(half.layer("person")) < np.count_nonzero(plain.layer("person")) / 3


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.5, 2.0), min_size=1, max_size=6), st.sampled_from(["max", "sum"]))
def test_each_box_stamps_the_gaussian_of_its_own_radius(scales, stamp):
    """Boxes far apart, each with its own factor: the map is the sum of the single stamps of their radii."""
    n = len(scales)
    gx, gy = cell_of(np.arange(n) * 25.0 - 60.0, np.zeros(n))
    amp = np.linspace(0.2, 0.8, n)
    mixed = placed_map(MemoryMapConfig(stamp=stamp))
    mixed.add("person", gx, gy, amp, scales)
    expected = np.zeros_like(mixed.layer("person"))
    base = round(4.0 / mixed.cell_m)  # the configured radius in cells
    for k, s in enumerate(scales):
        radius_cells = max(1, round(4.0 * s / mixed.cell_m))
        one = placed_map(MemoryMapConfig(stamp=stamp, radius_m=4.0 * radius_cells / base))
        one.add("person", gx[k:k + 1], gy[k:k + 1], amp[k:k + 1])
        expected += one.layer("person")
    np.testing.assert_allclose(mixed.layer("person"), expected, atol=1e-6)


@pytest.mark.parametrize("bad", [np.nan, 0.0, -1.0, np.inf, 0.4, 2.5, 1e9])
def test_a_bad_radius_scale_is_refused_and_the_map_kept(bad):
    mm = placed_map()
    gx, gy = cell_of([0.0, 10.0], [0.0, 10.0])
    mm.add("person", gx, gy, [0.5, 0.5])
    before = mm.layer("person").copy()
    with pytest.raises(ValueError, match="radius_scale"):
        mm.add("person", gx, gy, [0.5, 0.5], [1.0, bad])
    np.testing.assert_array_equal(mm.layer("person"), before)


@pytest.mark.parametrize("lon", [LON, 179.9995], ids=["here", "at the antimeridian"])
def test_with_max_stamping_a_cell_counts_once_across_radii(lon):
    """Two boxes in one cell whose radii differ: the strongest one alone is stamped, with its own radius."""
    gx, gy = (np.floor(c) for c in GRID.latlon_to_cell(*local_to_latlon(0.0, 0.0, LAT, lon)))
    inside = [gx + 0.1, gx + 0.9], [gy + 0.1, gy + 0.9]  # two corners of one cell
    both, strong = placed_map(), placed_map()
    for mm in (both, strong):
        mm.advance(0.0, LAT, lon)
    assert both.add("person", *inside, [0.3, 0.5], [0.7, 0.9]) == 2
    strong.add("person", [inside[0][1]], [inside[1][1]], [0.5], [0.9])
    np.testing.assert_array_equal(both.layer("person"), strong.layer("person"))
    assert both.values_at("person", [gx], [gy])[0] == pytest.approx(0.5, rel=1e-5)
    summed = placed_map(MemoryMapConfig(stamp="sum"))
    summed.advance(0.0, LAT, lon)
    summed.add("person", *inside, [0.3, 0.5], [0.7, 0.9])
    assert summed.values_at("person", [gx], [gy])[0] == pytest.approx(0.8, rel=1e-5)
    one = placed_map()  # a scalar point with a scale stamps as an array of one does
    one.advance(0.0, LAT, lon)
    one.add("person", inside[0][1], inside[1][1], 0.5, 0.9)
    np.testing.assert_array_equal(one.layer("person"), strong.layer("person"))


def test_the_scaled_kernels_stay_few_and_the_configured_one_is_kept_while_the_latitude_drifts():
    mm = placed_map()
    base, kernel = mm._kernel_for()
    for k in range(300):  # northward, the cells shrink a little every frame
        mm.advance(k * 0.1, LAT + k * 1e-4, LON)
        gx, gy = GRID.latlon_to_cell(*local_to_latlon(np.zeros(3), np.full(3, 10.0), LAT + k * 1e-4, LON))
        mm.add("person", gx, gy, [0.2, 0.2, 0.2], [0.5, 0.75, 1.0])
        if mm._kernel_for()[0] == base:
            assert mm._kernel_for()[1] is kernel
    assert len(mm._scaled_kernels) <= 2 * mm._kernel_for()[0] + 2


def test_stamp_scales_by_mode_and_bad_modes_named():
    footprint = np.array([0.2, 0.8, 1.0, 1.5, 3.0, np.nan])
    np.testing.assert_array_equal(MemoryMapConfig().stamp_scales(footprint), [0.5, 0.8, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(MemoryMapConfig(terrain_stamp="follow").stamp_scales(footprint),
                                  [0.5, 0.8, 1.0, 1.5, 2.0, 1.0])
    assert MemoryMapConfig(terrain_stamp="off").stamp_scales(footprint) is None
    with pytest.raises(ValueError, match="terrain_stamp"):
        MemoryMapConfig(terrain_stamp="grow")


# ----------------------------------------------------------------------------- pipeline over a terrain

def plane(rise_north: float, reference_m: float = 200.0) -> Terrain:
    """A plane through 200 m under the UAV rising rise_north metres per metre northward (toward the view); the
    pose's height above reference_m."""
    axis = np.arange(-200.0, 201.0, 2.0)
    east, north = np.meshgrid(axis, axis[::-1])
    grid = ElevationGrid.from_local(200.0 + rise_north * north, LAT, LON, west_m=-200.0, north_m=200.0, cell_m=2.0)
    return Terrain(grid, reference_m)


def stamped_cells(terrain: Terrain | None, mode: str) -> tuple[int, np.ndarray]:
    """Nonzero cells of the map after one frame with one confident person 40 m ahead on the terrain, and the map."""
    base = PipelineConfig(use_size_filter=False, correct_telemetry=False, terrain=terrain)
    cfg = dataclasses.replace(base, memory=dataclasses.replace(base.memory, terrain_stamp=mode))
    pipe = DetectionPipeline(CAM, CLASSES, cfg)
    up = 0.0 if terrain is None else float(terrain.up_m(np.array([0.0]), np.array([40.0]), POSE)[0])
    lat, lon = local_to_latlon(np.array([0.0]), np.array([40.0]), LAT, LON)
    (u, v), = latlon_to_pixel(lat, lon, CAM, POSE, terrain=terrain)[0]
    box = np.array([[u - 8, v - 45, u + 8, v]], np.float32)
    pipe.process(box, np.array([0.9], np.float32), np.array([1]), POSE, 0.0)
    layer = pipe.memory.layer("person")
    assert layer is not None and layer.max() > 0, up
    return int(np.count_nonzero(layer)), layer.copy()


def test_the_stamp_shrinks_on_a_slope_facing_the_camera_and_grows_only_when_following():
    facing, away = plane(0.25), plane(-0.25)
    off_facing, _ = stamped_cells(facing, "off")
    shrink_facing, _ = stamped_cells(facing, "shrink")
    assert shrink_facing < 0.85 * off_facing
    off_away, off_map = stamped_cells(away, "off")
    shrink_away, shrink_map = stamped_cells(away, "shrink")
    follow_away, _ = stamped_cells(away, "follow")
    np.testing.assert_array_equal(shrink_map, off_map)  # a larger footprint keeps the configured radius
    assert follow_away > 1.5 * off_away


@pytest.mark.parametrize("terrain", [None, plane(0.0), plane(0.0, 190.0)],
                         ids=["flat earth", "flat DEM", "flat DEM above the take-off"])
def test_flat_ground_stamps_the_configured_radius_in_every_mode(terrain):
    maps = [stamped_cells(terrain, mode)[1] for mode in ("off", "shrink", "follow")]
    np.testing.assert_array_equal(maps[1], maps[0])
    np.testing.assert_array_equal(maps[2], maps[0])

"""Tests of the global Web-Mercator tile grid: known values, round trips, windows and tile coverage."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from shared.tiles import (
    EARTH_RADIUS_M,
    MAX_LAT_DEG,
    CellWindow,
    TileGrid,
    fill_cell_polygons,
    latlon_to_tile_xy,
)

GRID = TileGrid()  # z = 18, n = 256
lats = st.floats(-85.0, 85.0, allow_nan=False)
lons = st.floats(-180.0, 180.0, allow_nan=False, exclude_max=True)
grids = st.builds(TileGrid, z=st.integers(0, 24), n=st.integers(1, 256))
small_grids = st.builds(TileGrid, z=st.integers(0, 24), n=st.sampled_from([1, 2, 3, 7, 16, 64, 256]))


def slippy_tile(lat: float, lon: float, z: int) -> tuple[int, int]:
    """The OSM wiki formula, written independently of the code under test."""
    lat_rad = math.radians(lat)
    side = 2**z
    x = int((lon + 180.0) / 360.0 * side)
    y = int((1.0 - math.log(math.tan(lat_rad) + 1.0 / math.cos(lat_rad)) / math.pi) / 2.0 * side)
    return x, y


def offset_latlon(lat: float, lon: float, east_m: float, north_m: float) -> tuple[float, float]:
    """Point east/north metres away on the sphere (the window's convention: north along the meridian).

    The latitude is clipped to the map limits, as the window is.
    """
    new_lat = min(max(lat + math.degrees(north_m / EARTH_RADIUS_M), -MAX_LAT_DEG), MAX_LAT_DEG)
    return new_lat, lon + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat))))


# ---- known values -----------------------------------------------------------------------------
def test_tile_of_48n_9e_matches_the_slippy_formula() -> None:
    expected = slippy_tile(48.0, 9.0, 18)
    assert expected == (137625, 91125)
    x, y = GRID.tile_of(48.0, 9.0)
    assert (int(x), int(y)) == expected
    assert tuple(int(v) for v in latlon_to_tile_xy(48.0, 9.0, 18)) == expected


def test_cell_size_is_0597_cos_lat_at_default_grid() -> None:
    assert float(GRID.cell_size_m(0.0)) == pytest.approx(0.597164, abs=1e-6)
    assert float(GRID.cell_size_m(48.0)) == pytest.approx(0.597164 * math.cos(math.radians(48.0)), rel=1e-6)
    assert float(GRID.cell_size_m(48.0)) == pytest.approx(0.3996, abs=1e-4)
    sizes = GRID.cell_size_m(np.array([[0.0, 60.0]]))
    assert sizes.shape == (1, 2) and sizes[0, 1] == pytest.approx(sizes[0, 0] / 2)


def test_world_corners() -> None:
    assert GRID.world_cells == 2**18 * 256
    assert TileGrid(z=0).tile_bounds(0, 0) == pytest.approx((-180.0, -MAX_LAT_DEG, 180.0, MAX_LAT_DEG))
    gx, gy = GRID.latlon_to_cell(0.0, 0.0)
    assert (float(gx), float(gy)) == (GRID.world_cells / 2, GRID.world_cells / 2)
    assert MAX_LAT_DEG == pytest.approx(85.0511287798)


@given(lat=lats, lon=lons, z=st.integers(0, 24))
def test_latlon_to_tile_xy_matches_the_slippy_formula(lat: float, lon: float, z: int) -> None:
    expected = slippy_tile(lat, lon, z)
    got = tuple(int(v) for v in latlon_to_tile_xy(lat, lon, z))
    # the two formulas may disagree by one tile only within float rounding of a tile edge
    if got != expected:
        x_f = (lon + 180.0) / 360.0 * 2**z
        y_f = (1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * 2**z
        assert min(abs(x_f - round(x_f)), abs(y_f - round(y_f))) < 1e-6
    grid = TileGrid(z=z, n=1)
    assert tuple(int(v) for v in grid.tile_of(lat, lon)) == got


def test_vectorised_shapes_and_dtypes() -> None:
    lat = np.full((3, 4), 48.0)
    lon = np.linspace(8.0, 10.0, 4)[None, :]
    gx, gy = GRID.latlon_to_cell(lat, lon)
    assert gx.shape == gy.shape == (3, 4) and gx.dtype == np.float64
    ix, iy = GRID.latlon_to_cell_index(lat, lon)
    assert ix.shape == (3, 4) and ix.dtype == np.int64
    tx, ty = GRID.tile_of(lat, lon)
    assert tx.dtype == np.int64 and np.all(tx == ix // 256)


# ---- round trips ------------------------------------------------------------------------------
@given(lat=lats, lon=lons, grid=grids)
def test_latlon_cell_round_trip(lat: float, lon: float, grid: TileGrid) -> None:
    gx, gy = grid.latlon_to_cell(lat, lon)
    lat2, lon2 = grid.cell_to_latlon(gx, gy)
    assert float(lat2) == pytest.approx(lat, abs=1e-9)
    assert (float(lon2) - lon + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-9)


@given(lat=lats, lon=lons, grid=grids)
def test_point_lies_in_its_tile_bounds_and_cell_centre_in_its_cell(lat: float, lon: float, grid: TileGrid) -> None:
    x, y = (int(v) for v in grid.tile_of(lat, lon))
    min_lon, min_lat, max_lon, max_lat = grid.tile_bounds(x, y)
    eps = 1e-9
    assert min_lat - eps <= lat <= max_lat + eps
    assert min_lon - eps <= lon <= max_lon + eps
    ix, iy = grid.latlon_to_cell_index(lat, lon)
    c_lat, c_lon = grid.cell_to_latlon(ix + 0.5, iy + 0.5)
    jx, jy = grid.latlon_to_cell_index(c_lat, c_lon)
    assert (int(jx), int(jy)) == (int(ix), int(iy))
    assert (int(ix) // grid.n, int(iy) // grid.n) == (x, y)


def test_tile_cell_centres_fall_in_their_cells() -> None:
    grid = TileGrid(z=10, n=8)
    lat, lon = grid.tile_cell_centres(5, 7)
    assert lat.shape == lon.shape == (8, 8)
    gx, gy = grid.latlon_to_cell_index(lat, lon)
    rows, cols = np.mgrid[0:8, 0:8]
    assert np.array_equal(gx, 5 * 8 + cols) and np.array_equal(gy, 7 * 8 + rows)
    assert np.all(np.diff(lat, axis=0) < 0)  # rows go south


def test_longitude_wraps_and_180_is_the_first_tile() -> None:
    x, _ = GRID.tile_of(0.0, 180.0)
    assert int(x) == 0
    gx1, _ = GRID.latlon_to_cell(10.0, 190.0)
    gx2, _ = GRID.latlon_to_cell(10.0, -170.0)
    assert float(gx1) == pytest.approx(float(gx2))
    gx, _ = GRID.latlon_to_cell(0.0, np.nextafter(180.0, 0.0))
    assert 0.0 <= float(gx) < GRID.world_cells


def test_map_limit_latitudes_are_clipped_into_the_first_and_last_tile() -> None:
    assert int(GRID.tile_of(MAX_LAT_DEG, 0.0)[1]) == 0
    assert int(GRID.tile_of(-MAX_LAT_DEG, 0.0)[1]) == 2**18 - 1


# ---- validation -------------------------------------------------------------------------------
@pytest.mark.parametrize("lat", [85.06, -85.06, 90.0, float("nan"), float("inf")])
def test_latitude_outside_web_mercator_raises(lat: float) -> None:
    for call in (GRID.latlon_to_cell, GRID.latlon_to_cell_index, GRID.tile_of):
        with pytest.raises(ValueError, match="lat"):
            call(lat, 0.0)
    with pytest.raises(ValueError, match="lat"):
        GRID.cell_size_m(lat)
    with pytest.raises(ValueError, match="lat"):
        GRID.window(lat, 0.0, 10.0)
    with pytest.raises(ValueError, match="lat"):
        latlon_to_tile_xy(np.array([0.0, lat]), 0.0, 5)


def test_non_finite_lon_and_gy_outside_the_world_raise() -> None:
    with pytest.raises(ValueError, match="lon"):
        GRID.latlon_to_cell(0.0, float("nan"))
    with pytest.raises(ValueError, match="gy"):
        GRID.cell_to_latlon(0.0, -1.0)
    with pytest.raises(ValueError, match="gy"):
        GRID.cell_to_latlon(0.0, GRID.world_cells + 1.0)


@pytest.mark.parametrize(("z", "n"), [(25, 256), (-1, 256), (18, 0), (18, 257), (True, 256), (18.0, 256), (18, "8")])
def test_bad_grid_parameters_raise(z: object, n: object) -> None:
    with pytest.raises(ValueError):
        TileGrid(z=z, n=n)  # type: ignore[arg-type]


@pytest.mark.parametrize(("x", "y"), [(-1, 0), (0, -1), (2**18, 0), (0, 2**18)])
def test_tile_bounds_outside_the_zoom_raise(x: int, y: int) -> None:
    with pytest.raises(ValueError):
        GRID.tile_bounds(x, y)


def test_non_power_of_two_n_is_allowed() -> None:
    grid = TileGrid(z=18, n=100)
    x, y = grid.tile_of(48.0, 9.0)
    assert (int(x), int(y)) == (137625, 91125)


# ---- windows and tiles_within -----------------------------------------------------------------
def test_default_window_at_48n_is_3_to_4_tiles_across() -> None:
    window = GRID.window(48.0, 9.0, 150.0)
    assert 300.0 / 0.3996 <= window.width <= 300.0 / 0.3996 + 2
    assert window.width == window.height
    tiles = GRID.tiles_within(48.0, 9.0, 150.0)
    assert tiles == window.tiles()
    xs = {x for x, _ in tiles}
    assert len(xs) in (3, 4) and len(tiles) == len(xs) * len({y for _, y in tiles})
    assert (137625, 91125) in tiles


@settings(max_examples=200, deadline=None)
@given(lat=st.floats(-84.0, 84.0), lon=lons, radius_tiles=st.floats(0.0, 6.0), grid=small_grids)
@example(lat=1e-14, lon=0.0, radius_tiles=1e-14, grid=TileGrid(z=7, n=1))  # regression: float-noise edge
@example(lat=0.0, lon=0.0, radius_tiles=0.0, grid=TileGrid(z=19, n=64))  # regression: point on a border
def test_tiles_within_covers_the_square_and_nothing_far(
    lat: float, lon: float, radius_tiles: float, grid: TileGrid
) -> None:
    radius_m = min(radius_tiles * grid.n * float(grid.cell_size_m(lat)), 3e6)
    tiles = grid.tiles_within(lat, lon, radius_m)
    assert len(tiles) == len(set(tiles))
    side = grid.tiles_per_side
    assert all(0 <= x < side and 0 <= y < side for x, y in tiles)
    # covers: points sampled on and inside the square land in listed tiles
    f = np.linspace(-0.999, 0.999, 9)
    for east in f * radius_m:
        for north in f * radius_m:
            p_lat, p_lon = offset_latlon(lat, lon, east, north)
            tx, ty = grid.tile_of(p_lat, p_lon)
            assert (int(tx), int(ty)) in tiles
    # nothing far: every tile's cell range overlaps the square's continuous cell extent
    gx, _ = grid.latlon_to_cell(lat, lon)
    hx = radius_m / float(grid.cell_size_m(lat))
    _, gy_n = grid.latlon_to_cell(*offset_latlon(lat, lon, 0.0, radius_m))
    _, gy_s = grid.latlon_to_cell(*offset_latlon(lat, lon, 0.0, -radius_m))
    cells = grid.world_cells
    for x, y in tiles:
        assert y * grid.n < float(gy_s) + 1e-6 and (y + 1) * grid.n > float(gy_n) - 1e-6
        # distance in cells from the centre column to the tile's column range, across the wrap
        lo, hi = x * grid.n, (x + 1) * grid.n
        d = min(abs(((float(gx) - c + cells / 2) % cells) - cells / 2) for c in (lo, hi))
        inside = lo <= float(gx) < hi
        assert inside or d < hx + 1e-6


def test_tiles_within_wraps_at_the_antimeridian() -> None:
    last = 2**18 - 1
    for lon in (179.9995, -179.9995):
        xs = {x for x, _ in GRID.tiles_within(0.0, lon, 200.0)}
        assert 0 in xs and last in xs
        assert xs <= {0, 1, 2, last - 2, last - 1, last}


def test_window_at_the_pole_is_clipped() -> None:
    window = GRID.window(85.05, 0.0, 1000.0)
    assert window.gy0 == 0 and window.height >= 1
    assert all(y >= 0 for _, y in window.tiles())
    south = GRID.window(-85.05, 0.0, 1000.0)
    assert south.gy0 + south.height == GRID.world_cells


def test_window_never_exceeds_the_world_width() -> None:
    grid = TileGrid(z=1, n=4)
    window = grid.window(0.0, 10.0, 3e7)
    assert window.width == grid.world_cells and window.gx0 == 0
    assert sorted(window.tiles()) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_zero_radius_window_is_the_cell_of_the_point() -> None:
    window = GRID.window(48.0, 9.0, 0.0)
    assert window.shape == (1, 1)
    gx, gy = GRID.latlon_to_cell_index(48.0, 9.0)
    assert (window.gx0, window.gy0) == (int(gx), int(gy))


@pytest.mark.parametrize("half_edge_m", [-1.0, float("nan"), float("inf")])
def test_bad_half_edge_raises(half_edge_m: float) -> None:
    with pytest.raises(ValueError, match="half_edge_m"):
        GRID.window(48.0, 9.0, half_edge_m)


# ---- CellWindow split / paste -----------------------------------------------------------------
windows = st.builds(
    lambda n, z, gx0, gy0, w, h: (n, z, gx0, gy0, w, h),
    st.sampled_from([1, 3, 4, 8]),
    st.integers(1, 5),
    st.integers(0, 10**6),
    st.integers(0, 10**6),
    st.integers(1, 40),
    st.integers(1, 40),
)


def make_window(params: tuple[int, int, int, int, int, int]) -> CellWindow:
    n, z, gx0, gy0, w, h = params
    grid = TileGrid(z=z, n=n)
    cells = grid.world_cells
    w = min(w, cells)
    gy0 = gy0 % cells
    h = min(h, cells - gy0)
    return CellWindow(gx0=gx0 % cells, gy0=gy0, width=w, height=h, grid=grid)


@settings(max_examples=200)
@given(params=windows, seed=st.integers(0, 2**32 - 1))
def test_split_then_paste_round_trips_across_tile_borders(params: tuple, seed: int) -> None:
    window = make_window(params)
    grid = window.grid
    values = np.random.default_rng(seed).random(window.shape).astype(np.float32) + 1.0
    pieces = window.split(values)
    assert [(x, y) for x, y, _ in pieces] == window.tiles()
    for x, y, tile in pieces:
        assert tile.shape == (grid.n, grid.n) and tile.dtype == np.float32
        # each tile cell holds the window value of the same global cell, or the fill value 0
        rows, cols = np.nonzero(tile)
        gx = x * grid.n + cols
        gy = y * grid.n + rows
        col, row = window.cell_to_local(gx, gy)
        assert np.all(window.contains(gx, gy))
        assert np.array_equal(tile[rows, cols], values[row.astype(int), col.astype(int)])
    # every window cell was copied exactly once
    assert sum(int(np.count_nonzero(tile)) for _, _, tile in pieces) == values.size
    assert np.array_equal(window.paste(pieces), values)


def test_split_and_paste_across_the_antimeridian() -> None:
    grid = TileGrid(z=2, n=4)
    window = CellWindow(gx0=14, gy0=3, width=5, height=2, grid=grid)  # columns 14, 15, 0, 1, 2
    values = np.arange(10, dtype=np.float64).reshape(2, 5) + 1
    pieces = {(x, y): tile for x, y, tile in window.split(values)}
    assert set(pieces) == {(3, 0), (3, 1), (0, 0), (0, 1)}
    assert pieces[(3, 0)][3, 2:4].tolist() == [1.0, 2.0]
    assert pieces[(0, 0)][3, 0:3].tolist() == [3.0, 4.0, 5.0]
    assert pieces[(0, 1)][0, 0:3].tolist() == [8.0, 9.0, 10.0]
    assert np.array_equal(window.paste(list(window.split(values)), dtype=np.float64), values)
    col, row = window.cell_to_local(np.array([15, 0, 2, 3]), np.array([3, 4, 4, 4]))
    assert col.tolist() == [1.0, 2.0, 4.0, 5.0]
    assert window.contains(np.array([15, 0, 2, 3, 13]), np.array([3, 4, 4, 4, 3])).tolist() == [
        True,
        True,
        True,
        False,
        False,
    ]
    gx, gy = window.local_to_cell(np.array([0, 4]), np.array([0, 1]))
    assert gx.tolist() == [14.0, 2.0] and gy.tolist() == [3.0, 4.0]


def test_full_width_unaligned_window_merges_the_split_tile() -> None:
    grid = TileGrid(z=1, n=4)
    window = CellWindow(gx0=2, gy0=0, width=8, height=1, grid=grid)
    values = np.arange(1, 9, dtype=np.float32)[None, :]
    pieces = window.split(values)
    assert sorted((x, y) for x, y, _ in pieces) == [(0, 0), (1, 0)]
    tile0 = dict(((x, y), t) for x, y, t in pieces)[(0, 0)]
    assert tile0[0].tolist() == [7.0, 8.0, 1.0, 2.0]
    assert np.array_equal(window.paste(pieces), values)


def test_paste_ignores_foreign_tiles_and_checks_shapes() -> None:
    grid = TileGrid(z=3, n=4)
    window = CellWindow(gx0=4, gy0=4, width=4, height=4, grid=grid)
    out = window.paste([(5, 5, np.ones((4, 4)))], fill=-1.0)
    assert np.all(out == -1.0)
    out = window.paste([(1, 1, np.full((4, 4), 2.0))], out=out)
    assert np.all(out == 2.0)
    with pytest.raises(ValueError, match="shape"):
        window.paste([(1, 1, np.ones((3, 4)))])
    with pytest.raises(ValueError, match="shape"):
        window.split(np.ones((4, 5)))


def test_window_latlon_helpers_agree_with_the_grid() -> None:
    window = GRID.window(48.0, 9.0, 20.0)
    lat, lon = window.centres_latlon()
    assert lat.shape == window.shape
    col, row = window.latlon_to_local(lat, lon)
    rows, cols = np.mgrid[0 : window.height, 0 : window.width]
    assert np.allclose(col, cols + 0.5, atol=1e-4) and np.allclose(row, rows + 0.5, atol=1e-4)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"gx0": -1, "gy0": 0, "width": 1, "height": 1},
        {"gx0": 0, "gy0": -1, "width": 1, "height": 1},
        {"gx0": 0, "gy0": 0, "width": 0, "height": 1},
        {"gx0": 0, "gy0": 0, "width": 1, "height": 0},
        {"gx0": 0, "gy0": 0, "width": 33, "height": 1},
        {"gx0": 0, "gy0": 30, "width": 1, "height": 3},
        {"gx0": 0.5, "gy0": 0, "width": 1, "height": 1},
    ],
)
def test_bad_cell_windows_raise(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        CellWindow(**kwargs, grid=TileGrid(z=3, n=4))


def test_split_tiles_are_independent_of_the_window_array() -> None:
    window = CellWindow(gx0=1, gy0=1, width=2, height=2, grid=TileGrid(z=2, n=4))
    values = np.ones(window.shape)
    ((_, _, tile),) = window.split(values)
    values[:] = 5.0
    assert tile.max() == 1.0


# ----------------------------------------------------------------------------- fill_cell_polygons
@settings(max_examples=200, deadline=None)
@given(x0=st.integers(-5, 20), y0=st.integers(-5, 20), w=st.integers(1, 12), h=st.integers(1, 12),
       gx0=st.integers(-3, 3), gy0=st.integers(-3, 3))
def test_fill_cell_polygons_fills_the_cells_whose_centres_are_inside(x0, y0, w, h, gx0, gy0):
    # a rectangle whose edges lie a quarter cell off the centres: no centre is on an edge
    rect = np.array([[x0 + 0.25, y0 + 0.25], [x0 + w + 0.25, y0 + 0.25], [x0 + w + 0.25, y0 + h + 0.25],
                     [x0 + 0.25, y0 + h + 0.25]])
    mask = fill_cell_polygons([rect], gx0, gy0, 16, 12)
    assert mask.shape == (12, 16) and mask.dtype == bool
    cx = gx0 + np.arange(16) + 0.5
    cy = gy0 + np.arange(12)[:, None] + 0.5
    def within(margin: float) -> np.ndarray:
        return ((cx > rect[0, 0] - margin) & (cx < rect[1, 0] + margin) & (cy > rect[0, 1] - margin)
                & (cy < rect[2, 1] + margin))

    assert not (within(0.0) & ~mask).any()  # every centre inside is filled
    assert not (mask & ~within(1.0)).any()  # and nothing beyond the cells the edges pass through


def test_fill_cell_polygons_joins_polygons_and_skips_degenerate_ones():
    a = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    b = a + [4.0, 0.0]
    mask = fill_cell_polygons([a, b, a[:2], np.zeros((4, 3))], 0, 0, 8, 4)
    assert mask[0:2, 0:2].all() and mask[0:2, 4:6].all()
    assert not mask[:, 7].any() and not mask[3].any()
    assert not fill_cell_polygons([a[:2]], 0, 0, 4, 4).any()
    assert fill_cell_polygons([a], 0, 0, 0, 5).shape == (5, 0)

"""Global Web-Mercator tile grid shared by all UAVs and the fusion server (DESIGN.md section 3).

Slippy-map tiles ``z/x/y`` (EPSG:3857 on the WGS84 sphere, R = 6378137 m) split into ``n x n`` cells;
a cell has global integer coordinates ``gx = x * n + col``, ``gy = y * n + row`` (row-major from the
tile's north-west corner, so ``gy`` grows southwards).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EARTH_CIRCUMFERENCE_M",
    "EARTH_RADIUS_M",
    "MAX_LAT_DEG",
    "MAX_N",
    "MAX_ZOOM",
    "CellWindow",
    "TileGrid",
    "TileOverlap",
    "fill_cell_polygons",
    "latlon_to_tile_xy",
]

#: WGS84 semi-major axis, the sphere radius of Web-Mercator (EPSG:3857), metres.
EARTH_RADIUS_M = 6378137.0
#: Equator length of that sphere, metres (40075016.686 m).
EARTH_CIRCUMFERENCE_M = 2.0 * math.pi * EARTH_RADIUS_M
#: Latitude limit of Web-Mercator, degrees: the square world map ends at +-85.0511287798 deg.
MAX_LAT_DEG = math.degrees(math.atan(math.sinh(math.pi)))
MAX_ZOOM = 24
#: Largest cells-per-tile edge: indices 0..n*n-1 must fit uint16.
MAX_N = 256


def _check_int(value: object, field: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{field} must be an int, got {type(value).__name__} {value!r}")
    if not low <= int(value) <= high:
        raise ValueError(f"{field} must be in {low}..{high}, got {value}")
    return int(value)


def _check_lat(lat: ArrayLike) -> NDArray[np.float64]:
    lat = np.asarray(lat, dtype=np.float64)
    if (np.abs(lat) <= MAX_LAT_DEG).all():  # False for NaN too
        return lat
    bad = ~(np.abs(lat) <= MAX_LAT_DEG)
    if np.any(bad):
        raise ValueError(
            f"lat must be finite and within +-{MAX_LAT_DEG:.7f} deg (Web-Mercator), got {lat[bad].flat[0]!r}"
        )
    return lat


def _check_lon(lon: ArrayLike) -> NDArray[np.float64]:
    lon = np.asarray(lon, dtype=np.float64)
    if np.isfinite(lon).all():
        return lon
    bad = ~np.isfinite(lon)
    if np.any(bad):
        raise ValueError(f"lon must be finite, got {lon[bad].flat[0]!r}")
    return lon


def _wrap_lon(lon: NDArray[np.float64]) -> NDArray[np.float64]:
    """Longitude wrapped to [-180, 180) degrees; values already inside are returned unchanged."""
    # wrapping an in-range lon through mod would round 180 - 3e-14 to -180 (the wrong tile)
    inside = (lon >= -180.0) & (lon < 180.0)
    if inside.all():  # the usual case: no wrapping to compute
        return lon
    return np.where(inside, lon, np.mod(lon + 180.0, 360.0) - 180.0)


def _lat_to_unit_y(lat: ArrayLike) -> NDArray[np.float64]:
    """Web-Mercator y in [0, 1] (0 = north edge of the world) of latitudes in degrees."""
    return 0.5 - np.arcsinh(np.tan(np.radians(np.asarray(lat, dtype=np.float64)))) / (2.0 * np.pi)


def _unit_y_to_lat(unit_y: ArrayLike) -> NDArray[np.float64]:
    """Latitude in degrees of Web-Mercator y in [0, 1]."""
    return np.degrees(np.arctan(np.sinh(np.pi * (1.0 - 2.0 * np.asarray(unit_y, dtype=np.float64)))))


def latlon_to_tile_xy(lat: ArrayLike, lon: ArrayLike, z: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Slippy-map tile containing each point at zoom ``z`` (OSM standard formulas).

    lat, lon: degrees, broadcastable arrays; lat within +-MAX_LAT_DEG (ValueError otherwise), any
    finite lon (wrapped, so lon = 180 is tile x = 0). Returns x, y as int64 arrays of the broadcast
    shape, each in 0..2**z - 1 (points exactly on the south/pole edge are clipped into the last tile).
    """
    z = _check_int(z, "z", 0, MAX_ZOOM)
    lat, lon = np.broadcast_arrays(_check_lat(lat), _wrap_lon(_check_lon(lon)))
    side = 1 << z
    x = np.floor((lon + 180.0) / 360.0 * side).astype(np.int64)
    y = np.floor(_lat_to_unit_y(lat) * side).astype(np.int64)
    return np.clip(x, 0, side - 1), np.clip(y, 0, side - 1)


class TileOverlap(NamedTuple):
    """Where one tile and one :class:`CellWindow` overlap.

    x, y: tile indices. ``window``: (row slice, col slice) into the window's (height, width) array;
    ``tile``: (row slice, col slice) into the tile's (n, n) array, same extent.
    """

    x: int
    y: int
    window: tuple[slice, slice]
    tile: tuple[slice, slice]


@dataclass(frozen=True, slots=True)
class TileGrid:
    """The global grid: zoom level ``z`` (0..24) and ``n`` (1..256) cells along each tile edge.

    All coordinate methods are vectorised over broadcastable numpy arrays and raise ValueError for
    latitudes outside +-MAX_LAT_DEG or non-finite input. Longitudes are wrapped to [-180, 180), so
    ``gx`` is always in [0, world_cells); near the antimeridian use :class:`CellWindow` helpers,
    which handle the wrap.
    """

    z: int = 18
    n: int = 256

    def __post_init__(self) -> None:
        _check_int(self.z, "z", 0, MAX_ZOOM)
        _check_int(self.n, "n", 1, MAX_N)

    @property
    def tiles_per_side(self) -> int:
        """Number of tiles along each axis of the world, 2**z."""
        return 1 << self.z

    @property
    def world_cells(self) -> int:
        """Number of cells along each axis of the world, 2**z * n (at most 2**32)."""
        return self.tiles_per_side * self.n

    # ---- points <-> cells ----------------------------------------------------------------------
    def latlon_to_cell(self, lat: ArrayLike, lon: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous global cell coordinates of points.

        lat, lon: degrees, broadcastable. Returns gx, gy float64 of the broadcast shape:
        ``floor`` gives the integer cell, the cell centre is at integer + 0.5. gx is in
        [0, world_cells) (lon wrapped), gy in [0, world_cells] (gy = world_cells only at the south
        limit of the map).
        """
        lat, lon = _check_lat(lat), _wrap_lon(_check_lon(lon))
        if lat.shape != lon.shape:
            lat, lon = np.broadcast_arrays(lat, lon)
        cells = float(self.world_cells)
        gx = (lon + 180.0) * (cells / 360.0)
        gy = _lat_to_unit_y(lat) * cells
        # rounding can push a lon just below 180 onto the east edge of the world; it belongs to the
        # last column (lon = 180 itself was wrapped to -180, i.e. gx = 0)
        gx = np.minimum(gx, np.nextafter(cells, 0.0))
        return gx, gy

    def polygon_cells(self, polygon_latlon: ArrayLike) -> NDArray[np.float64] | None:
        """A ground polygon ``[[lat, lon], ...]`` in continuous global cell coordinates: (M, 2) (gx, gy).

        None when it is not a polygon (fewer than 3 vertices, another shape, non-finite values); a
        latitude beyond +-MAX_LAT_DEG raises ValueError like latlon_to_cell. For fill_cell_polygons.
        """
        poly = np.asarray(polygon_latlon, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[0] < 3 or poly.shape[1] != 2 or not np.isfinite(poly).all():
            return None
        gx, gy = self.latlon_to_cell(poly[:, 0], poly[:, 1])
        return np.column_stack([gx, gy])

    def latlon_to_cell_index(self, lat: ArrayLike, lon: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Integer global cell (gx, gy) containing each point, int64 of the broadcast shape.

        Points on the map's north/south limits are clipped into the first/last cell row.
        """
        gx, gy = self.latlon_to_cell(lat, lon)
        last = self.world_cells - 1
        return np.floor(gx).astype(np.int64), np.clip(np.floor(gy).astype(np.int64), 0, last)

    def cell_to_latlon(self, gx: ArrayLike, gy: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latitude and longitude (degrees, float64) of continuous global cell coordinates.

        gx: any finite value (wrapped around the world); gy: in [0, world_cells], ValueError
        otherwise. Use ``gx + 0.5, gy + 0.5`` for cell centres. Longitudes are in [-180, 180).
        """
        gx, gy = np.broadcast_arrays(np.asarray(gx, dtype=np.float64), np.asarray(gy, dtype=np.float64))
        cells = float(self.world_cells)
        if not np.all(np.isfinite(gx)):
            raise ValueError("gx must be finite")
        bad = ~((gy >= 0.0) & (gy <= cells))
        if np.any(bad):
            raise ValueError(f"gy must be within 0..{self.world_cells}, got {gy[bad].flat[0]!r}")
        lon = _wrap_lon(gx * (360.0 / cells) - 180.0)
        lat = _unit_y_to_lat(gy / cells)
        return lat, lon

    # ---- tiles ------------------------------------------------------------------------------
    def tile_of(self, lat: ArrayLike, lon: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Tile (x, y) of this grid's zoom containing each point, int64 of the broadcast shape."""
        gx, gy = self.latlon_to_cell_index(lat, lon)
        return gx // self.n, gy // self.n

    def tile_bounds(self, x: int, y: int) -> tuple[float, float, float, float]:
        """Bounds of tile (x, y): (min_lon, min_lat, max_lon, max_lat) in degrees.

        Raises ValueError for x or y outside 0..2**z - 1.
        """
        side = self.tiles_per_side
        x = _check_int(x, "x", 0, side - 1)
        y = _check_int(y, "y", 0, side - 1)
        min_lon = x / side * 360.0 - 180.0
        max_lon = (x + 1) / side * 360.0 - 180.0
        max_lat = float(_unit_y_to_lat(y / side))
        min_lat = float(_unit_y_to_lat((y + 1) / side))
        return min_lon, min_lat, max_lon, max_lat

    def tile_cell_centres(self, x: int, y: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latitude and longitude (degrees) of the centres of tile (x, y)'s cells, each (n, n) float64."""
        side = self.tiles_per_side
        x = _check_int(x, "x", 0, side - 1)
        y = _check_int(y, "y", 0, side - 1)
        offsets = np.arange(self.n, dtype=np.float64) + 0.5
        lat, lon = self.cell_to_latlon((x * self.n + offsets)[None, :], (y * self.n + offsets)[:, None])
        return np.broadcast_to(lat, (self.n, self.n)).copy(), np.broadcast_to(lon, (self.n, self.n)).copy()

    def cell_size_m(self, lat: ArrayLike) -> NDArray[np.float64]:
        """Ground edge length of a cell at latitude ``lat`` (degrees), metres, float64 broadcast shape.

        ``40075016.686 * cos(lat) / 2**z / n``: 0.597 * cos(lat) m at z = 18, n = 256.
        """
        lat = _check_lat(lat)
        return EARTH_CIRCUMFERENCE_M * np.cos(np.radians(lat)) / self.world_cells

    def window(self, lat: float, lon: float, half_edge_m: float) -> CellWindow:
        """Smallest block of cells covering the ground square of half-edge ``half_edge_m`` around a point.

        lat, lon: scalar degrees; half_edge_m: metres >= 0. The square is axis-aligned with north:
        its north/south edges lie ``half_edge_m`` along the meridian on the sphere, its east/west
        edges ``half_edge_m`` along the point's parallel (Web-Mercator is conformal, so at UAV-window
        sizes this is a square on the ground to ~1e-5). Cells are included when they overlap the
        square with positive area; the window is clipped at the map's north/south limits and wraps
        at the antimeridian (its width is at most the world).
        """
        lat_f = float(_check_lat(lat))
        lon_f = float(_check_lon(lon))
        if not (math.isfinite(half_edge_m) and half_edge_m >= 0.0):
            raise ValueError(f"half_edge_m must be finite and >= 0, got {half_edge_m!r}")
        cells = self.world_cells
        gx, _ = self.latlon_to_cell(lat_f, lon_f)
        half_cells_x = half_edge_m / float(self.cell_size_m(lat_f))
        dlat = math.degrees(half_edge_m / EARTH_RADIUS_M)
        north = min(lat_f + dlat, MAX_LAT_DEG)
        south = max(lat_f - dlat, -MAX_LAT_DEG)
        gy_north = float(_lat_to_unit_y(north)) * cells
        gy_south = float(_lat_to_unit_y(south)) * cells

        # A square edge within float noise of a cell border includes the neighbour: a superset is
        # harmless, a missed cell is not (regression: a 3 nm square on the equator lost its south row).
        # The east/south edge includes the cell its point lies in (a point on a border belongs to the
        # cell east/south of it); a few ulps of tolerance absorb rounding in the projection.
        eps = 4.0 * math.ulp(max(1.0, float(gx), gy_south))
        gx0 = math.floor(float(gx) - half_cells_x - eps)
        width = max(math.floor(float(gx) + half_cells_x + eps) + 1 - gx0, 1)
        if width >= cells:
            gx0, width = 0, cells
        gy0 = min(max(math.floor(gy_north - eps), 0), cells - 1)
        gy1 = min(max(math.floor(gy_south + eps) + 1, gy0 + 1), cells)
        return CellWindow(gx0=gx0 % cells, gy0=gy0, width=width, height=gy1 - gy0, grid=self)

    def tiles_within(self, lat: float, lon: float, radius_m: float) -> list[tuple[int, int]]:
        """All tiles (x, y) that overlap the ground SQUARE of half-edge ``radius_m`` around a point.

        A square, not a disk: the result is a superset of the tiles within distance ``radius_m``.
        Same geometry as :meth:`window` (these are exactly ``window(...).tiles()``): x wraps at the
        antimeridian, y is clipped at the map limits. Ordered north to south, then west to east
        starting at the window's west edge; no duplicates.
        """
        return self.window(lat, lon, radius_m).tiles()


@dataclass(frozen=True, slots=True)
class CellWindow:
    """An axis-aligned block of global cells: columns gx0..gx0+width-1, rows gy0..gy0+height-1.

    gx0 is in [0, world_cells) and columns past the east edge of the world wrap to 0 (antimeridian);
    rows never wrap: 0 <= gy0 and gy0 + height <= world_cells. A window's dense array has shape
    (height, width), local row 0 / col 0 at the north-west cell (gy0, gx0).
    """

    gx0: int
    gy0: int
    width: int
    height: int
    grid: TileGrid = TileGrid()

    def __post_init__(self) -> None:
        if not isinstance(self.grid, TileGrid):
            raise ValueError(f"grid must be a TileGrid, got {type(self.grid).__name__}")
        cells = self.grid.world_cells
        _check_int(self.width, "width", 1, cells)
        _check_int(self.gx0, "gx0", 0, cells - 1)
        _check_int(self.gy0, "gy0", 0, cells - 1)
        _check_int(self.height, "height", 1, cells - int(self.gy0))

    @property
    def shape(self) -> tuple[int, int]:
        """Shape (height, width) of this window's dense arrays."""
        return (self.height, self.width)

    # ---- coordinates ------------------------------------------------------------------------
    def cell_to_local(self, gx: ArrayLike, gy: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Local (col, row) of global cell coordinates (int or continuous), float64 broadcast shape.

        col is taken modulo the world width, so it is in [0, world_cells); a point is inside the
        window when 0 <= col < width and 0 <= row < height (see :meth:`contains`).
        """
        gx = np.asarray(gx, dtype=np.float64)
        gy = np.asarray(gy, dtype=np.float64)
        return np.mod(gx - self.gx0, float(self.grid.world_cells)), gy - self.gy0

    def local_to_cell(self, col: ArrayLike, row: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Global (gx, gy) of local (col, row), float64 broadcast shape, gx wrapped into the world."""
        col = np.asarray(col, dtype=np.float64)
        row = np.asarray(row, dtype=np.float64)
        return np.mod(col + self.gx0, float(self.grid.world_cells)), row + self.gy0

    def latlon_to_local(self, lat: ArrayLike, lon: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous local (col, row) of points in degrees; ``floor`` gives the array index."""
        return self.cell_to_local(*self.grid.latlon_to_cell(lat, lon))

    def contains(self, gx: ArrayLike, gy: ArrayLike) -> NDArray[np.bool_]:
        """Whether global cell coordinates (int or continuous) fall inside the window, bool array."""
        col, row = self.cell_to_local(gx, gy)
        return (col < self.width) & (row >= 0) & (row < self.height)

    def centres_latlon(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latitude and longitude (degrees) of the window's cell centres, each (height, width)."""
        gx = self.gx0 + np.arange(self.width, dtype=np.float64) + 0.5
        gy = self.gy0 + np.arange(self.height, dtype=np.float64) + 0.5
        lat, lon = self.grid.cell_to_latlon(gx[None, :], gy[:, None])
        return np.broadcast_to(lat, self.shape).copy(), np.broadcast_to(lon, self.shape).copy()

    # ---- tiles ------------------------------------------------------------------------------
    def overlaps(self) -> list[TileOverlap]:
        """Every (tile, window) overlap, north to south then west to east.

        A tile appears twice only when the window spans the whole world width without being tile
        aligned (its two ends then cut the same tile).
        """
        n = self.grid.n
        side = self.grid.tiles_per_side
        result = []
        for ty in range(self.gy0 // n, (self.gy0 + self.height - 1) // n + 1):
            row0 = max(self.gy0, ty * n)
            row1 = min(self.gy0 + self.height, (ty + 1) * n)
            rows_win = slice(row0 - self.gy0, row1 - self.gy0)
            rows_tile = slice(row0 - ty * n, row1 - ty * n)
            # columns are unwrapped here (may pass the world's east edge) and wrapped into x below
            for tx in range(self.gx0 // n, (self.gx0 + self.width - 1) // n + 1):
                col0 = max(self.gx0, tx * n)
                col1 = min(self.gx0 + self.width, (tx + 1) * n)
                result.append(
                    TileOverlap(
                        x=tx % side,
                        y=ty,
                        window=(rows_win, slice(col0 - self.gx0, col1 - self.gx0)),
                        tile=(rows_tile, slice(col0 - tx * n, col1 - tx * n)),
                    )
                )
        return result

    def tiles(self) -> list[tuple[int, int]]:
        """Distinct tiles (x, y) overlapping the window, in :meth:`overlaps` order."""
        return list(dict.fromkeys((o.x, o.y) for o in self.overlaps()))

    def split(self, values: ArrayLike, fill: float = 0.0) -> list[tuple[int, int, np.ndarray]]:
        """Cut a dense window array into per-tile arrays.

        values: (height, width) array of any dtype. Returns one (x, y, tile) per distinct tile in
        :meth:`tiles` order, tile an (n, n) array of the same dtype holding the window's values
        where the window covers the tile and ``fill`` elsewhere. Raises ValueError on a wrong shape.
        """
        values = np.asarray(values)
        if values.shape != self.shape:
            raise ValueError(f"values must have shape {self.shape}, got {values.shape}")
        n = self.grid.n
        pieces: dict[tuple[int, int], np.ndarray] = {}
        for overlap in self.overlaps():
            tile = pieces.get((overlap.x, overlap.y))
            if tile is None:
                tile = pieces[(overlap.x, overlap.y)] = np.full((n, n), fill, dtype=values.dtype)
            tile[overlap.tile] = values[overlap.window]
        return [(x, y, tile) for (x, y), tile in pieces.items()]

    def paste(
        self,
        tiles: Iterable[tuple[int, int, ArrayLike]],
        out: np.ndarray | None = None,
        fill: float = 0.0,
        dtype: np.dtype | type = np.float32,
    ) -> np.ndarray:
        """Write the parts of tile arrays that fall inside the window into a window array.

        tiles: iterable of (x, y, tile) with tile an (n, n) array; tiles outside the window are
        ignored, later tiles overwrite earlier ones. out: (height, width) array written in place, or
        None for a new array of ``dtype`` filled with ``fill``. Returns the (height, width) array.
        """
        if out is None:
            out = np.full(self.shape, fill, dtype=dtype)
        elif out.shape != self.shape:
            raise ValueError(f"out must have shape {self.shape}, got {out.shape}")
        by_tile: dict[tuple[int, int], list[TileOverlap]] = {}
        for overlap in self.overlaps():
            by_tile.setdefault((overlap.x, overlap.y), []).append(overlap)
        n = self.grid.n
        for x, y, tile in tiles:
            tile = np.asarray(tile)
            if tile.shape != (n, n):
                raise ValueError(f"tile ({x}, {y}) must have shape {(n, n)}, got {tile.shape}")
            for overlap in by_tile.get((int(x), int(y)), ()):
                out[overlap.window] = tile[overlap.tile]
        return out


#: Sub-cell precision (bits) of fill_cell_polygons (cv2.fillPoly shift).
_POLY_SHIFT = 4


def fill_cell_polygons(polygons: Iterable[ArrayLike], gx0: int, gy0: int, width: int, height: int
                       ) -> NDArray[np.bool_]:
    """Cells of a block inside any of the polygons: (height, width) bool.

    Every cell whose centre lies inside is set, and so are cells the edges pass through (OpenCV's
    fillPoly draws the outline too): at most one cell beyond the polygon.

    polygons: (M, 2) vertices (M >= 3) in continuous global cell coordinates (gx, gy), as
    TileGrid.latlon_to_cell gives them; row r, column c of the block is the cell (gx0 + c, gy0 + r),
    whose centre is (gx0 + c + 0.5, gy0 + r + 0.5). Polygons with fewer than 3 vertices are skipped.
    """
    canvas = np.zeros((max(int(height), 0), max(int(width), 0)), dtype=np.uint8)
    if canvas.size == 0:
        return canvas.view(bool)
    for poly in polygons:
        cells = np.asarray(poly, dtype=np.float64)
        if cells.ndim != 2 or cells.shape[0] < 3 or cells.shape[1] != 2:
            continue
        pts = np.rint((cells - (gx0 + 0.5, gy0 + 0.5)) * (1 << _POLY_SHIFT)).astype(np.int32)
        cv2.fillPoly(canvas, [pts], 1, lineType=cv2.LINE_8, shift=_POLY_SHIFT)
    return canvas.view(bool)

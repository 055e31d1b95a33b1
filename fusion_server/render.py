"""Views of the joint map for the REST API: heatmap PNG tiles at any zoom and cell windows over a bbox.

The joint map lives at the grid's zoom (18 by default). Lower zooms are downsampled (per output
pixel the max or the mean of the cells it covers), higher zooms are cropped and upsampled with
nearest-neighbour so cells stay crisp. No I/O here besides PNG encoding in memory.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from fusion_server.joint_map import JointTile
from shared.tiles import MAX_LAT_DEG, MAX_ZOOM, CellWindow, TileGrid

__all__ = [
    "AGGREGATIONS",
    "COLORMAPS",
    "TILE_PX",
    "BBox",
    "heatmap_png",
    "parse_bbox",
    "tile_bytes",
    "window_bounds",
    "window_for_bbox",
]

TILE_PX = 256
AGGREGATIONS = ("max", "mean")
COLORMAPS: dict[str, int] = {
    "inferno": cv2.COLORMAP_INFERNO,
    "magma": cv2.COLORMAP_MAGMA,
    "plasma": cv2.COLORMAP_PLASMA,
    "viridis": cv2.COLORMAP_VIRIDIS,
    "turbo": cv2.COLORMAP_TURBO,
    "jet": cv2.COLORMAP_JET,
    "hot": cv2.COLORMAP_HOT,
}


@dataclass(frozen=True, slots=True)
class BBox:
    """A lon/lat box in degrees: min_lon < max_lon in [-180, 180], min_lat < max_lat within Web-Mercator."""

    min_lon: float
    min_lat: float
    max_lon: float
    max_lat: float

    def __post_init__(self) -> None:
        values = (self.min_lon, self.min_lat, self.max_lon, self.max_lat)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("bbox values must be finite numbers")
        if not (-180.0 <= self.min_lon < self.max_lon <= 180.0):
            raise ValueError(
                f"bbox needs -180 <= minlon < maxlon <= 180, got {self.min_lon}, {self.max_lon} "
                "(boxes across the antimeridian are not supported)"
            )
        if not (-MAX_LAT_DEG <= self.min_lat < self.max_lat <= MAX_LAT_DEG):
            raise ValueError(
                f"bbox needs -{MAX_LAT_DEG:.4f} <= minlat < maxlat <= {MAX_LAT_DEG:.4f}, "
                f"got {self.min_lat}, {self.max_lat}"
            )

    def contains(self, lat: NDArray[np.float64], lon: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether points (degrees, broadcastable) lie inside the box (edges included)."""
        return (lat >= self.min_lat) & (lat <= self.max_lat) & (lon >= self.min_lon) & (lon <= self.max_lon)


def parse_bbox(text: str) -> BBox:
    """``"minlon,minlat,maxlon,maxlat"`` (degrees) -> BBox; ValueError with a readable reason."""
    parts = text.split(",")
    if len(parts) != 4:
        raise ValueError(f"bbox must be minlon,minlat,maxlon,maxlat (4 numbers), got {text[:100]!r}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"bbox must hold 4 numbers, got {text[:100]!r}") from None
    return BBox(*values)


def window_for_bbox(grid: TileGrid, bbox: BBox) -> CellWindow:
    """The smallest cell window of ``grid`` covering ``bbox``."""
    west_gx, north_gy = grid.latlon_to_cell_index(bbox.max_lat, bbox.min_lon)
    gx0, gy0 = int(west_gx), int(north_gy)
    _, south_gy = grid.latlon_to_cell(bbox.min_lat, bbox.max_lon)
    # not latlon_to_cell's x: it wraps lon 180 to the world's west edge (a one-cell window)
    east_gx = (bbox.max_lon + 180.0) * (grid.world_cells / 360.0)
    # the east/south edges are exclusive: a box ending exactly on a cell edge does not take that cell
    gx1 = max(math.ceil(east_gx) - 1, gx0)
    gy1 = min(max(math.ceil(float(south_gy)) - 1, gy0), grid.world_cells - 1)
    return CellWindow(gx0=gx0, gy0=gy0, width=gx1 - gx0 + 1, height=gy1 - gy0 + 1, grid=grid)


def window_bounds(grid: TileGrid, window: CellWindow) -> tuple[float, float, float, float]:
    """Outer edges of a cell window in degrees: (west, south, east, north); east is 180 (not the
    wrapped -180) for a window that ends at the antimeridian."""
    north, west = (float(v) for v in grid.cell_to_latlon(window.gx0, window.gy0))
    south, east = (float(v) for v in grid.cell_to_latlon(window.gx0 + window.width, window.gy0 + window.height))
    if window.gx0 + window.width >= grid.world_cells and east <= west:
        east = 180.0
    return west, south, east, north


def _block_reduce(values: NDArray[np.uint8], size: int, agg: str) -> NDArray[np.float32]:
    """(n, n) uint8 -> (size, size) float32 in [0, 1], each output pixel the max/mean of its cells."""
    n = values.shape[0]
    if size >= n:  # upsample: nearest
        return cv2.resize(values, (size, size), interpolation=cv2.INTER_NEAREST).astype(np.float32) / 255.0
    if n % size == 0:
        blocks = values.reshape(size, n // size, size, n // size)
        out = blocks.max(axis=(1, 3)) if agg == "max" else blocks.mean(axis=(1, 3), dtype=np.float32)
        return out.astype(np.float32) / 255.0
    if agg == "max":  # grow every cell over its neighbours first so sampling cannot skip a peak
        k = math.ceil(n / size)
        grown = cv2.dilate(values, np.ones((k, k), np.uint8))
        return cv2.resize(grown, (size, size), interpolation=cv2.INTER_NEAREST).astype(np.float32) / 255.0
    area = np.asarray(cv2.resize(values.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA), np.float32)
    return area / 255.0


def tile_values(
    tiles_in_range,
    grid: TileGrid,
    cls: str,
    z: int,
    x: int,
    y: int,
    agg: str = "max",
    px: int = TILE_PX,
) -> NDArray[np.float32]:
    """(px, px) float32 values in [0, 1] of slippy tile z/x/y of the joint map of ``cls``.

    tiles_in_range: ``(cls, x0, x1, y0, y1) -> list[JointTile]`` at the grid's zoom (e.g.
    :meth:`JointMap.tiles_in_range`). agg: "max" or "mean" for zooms below the grid's.
    """
    zb, n = grid.z, grid.n
    out = np.zeros((px, px), dtype=np.float32)
    if z >= zb:
        k = 1 << (z - zb)
        found = tiles_in_range(cls, x // k, x // k, y // k, y // k)
        if not found:
            return out
        values = found[0].values
        # output pixel -> base cell: exact nearest neighbour for any n and zoom difference
        fine = np.arange(px, dtype=np.int64)
        rows = ((y % k) * px + fine) * n // (k * px)
        cols = ((x % k) * px + fine) * n // (k * px)
        return values[rows[:, None], cols[None, :]].astype(np.float32) / 255.0
    k = 1 << (zb - z)  # base tiles per output tile edge
    x0, y0 = x * k, y * k
    found = tiles_in_range(cls, x0, x0 + k - 1, y0, y0 + k - 1)
    if k <= px:
        size = px // k
        for tile in found:
            r, c = (tile.y - y0) * size, (tile.x - x0) * size
            out[r : r + size, c : c + size] = _block_reduce(tile.values, size, agg)
        return out
    per_px = k // px  # base tiles per output pixel edge
    if found:
        rows = np.array([(t.y - y0) // per_px for t in found])
        cols = np.array([(t.x - x0) // per_px for t in found])
        if agg == "max":
            np.maximum.at(out, (rows, cols), np.array([t.values.max() for t in found], dtype=np.float32) / 255.0)
        else:
            means = np.array([t.values.mean() for t in found], dtype=np.float32) / 255.0
            np.add.at(out, (rows, cols), means / np.float32(per_px * per_px))
    return out


def heatmap_png(values: NDArray[np.floating], cmap: str = "inferno") -> bytes:
    """RGBA PNG bytes of (h, w) values in [0, 1]: colormapped, transparent where the value is 0.

    Opacity grows with the value (from 40 % at the smallest non-zero value to 100 % at 1).
    """
    if cmap not in COLORMAPS:
        raise ValueError(f"unknown colormap {cmap!r}; valid: {', '.join(COLORMAPS)}")
    v = np.clip(np.asarray(values, dtype=np.float32), 0.0, 1.0)
    v8 = np.rint(v * 255.0).astype(np.uint8)
    bgr = cv2.applyColorMap(v8, COLORMAPS[cmap])
    alpha = np.where(v8 > 0, 100 + (v8.astype(np.uint16) * 155) // 255, 0).astype(np.uint8)
    ok, buf = cv2.imencode(".png", np.dstack([bgr, alpha]))
    if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 BGRA image
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def tile_bytes(
    tiles_in_range, grid: TileGrid, cls: str, z: int, x: int, y: int, agg: str = "max", cmap: str = "inferno"
) -> bytes:
    """PNG of slippy tile z/x/y (see :func:`tile_values` and :func:`heatmap_png`).

    Raises ValueError for z outside 0..24, x or y outside 0..2**z - 1, an unknown agg or cmap.
    """
    if not 0 <= z <= MAX_ZOOM:
        raise ValueError(f"z must be in 0..{MAX_ZOOM}, got {z}")
    side = 1 << z
    if not (0 <= x < side and 0 <= y < side):
        raise ValueError(f"x and y must be in 0..{side - 1} at z={z}, got x={x}, y={y}")
    if agg not in AGGREGATIONS:
        raise ValueError(f"agg must be one of {', '.join(AGGREGATIONS)}, got {agg!r}")
    return heatmap_png(tile_values(tiles_in_range, grid, cls, z, x, y, agg), cmap)


def paste_window(window: CellWindow, tiles: Iterable[JointTile]) -> NDArray[np.uint8]:
    """(height, width) uint8 window of the given joint tiles (0 where none covers)."""
    return window.paste(((t.x, t.y, t.values) for t in tiles), dtype=np.uint8, fill=0)

"""Fused object candidates: local maxima (peaks) of the joint map above a score.

A cell is a peak when it equals the maximum of its 3 x 3 neighbourhood (``cv2.dilate``), looking
across tile borders; a plateau of equal maxima is one peak at its centroid; peaks closer than
``min_distance_cells`` to a stronger one are suppressed. The antimeridian is a tile border like any other:
tile x = 2**z - 1 neighbours x = 0, and distances in x are taken around the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fusion_server.joint_map import JointTile
from fusion_server.render import BBox
from shared.tiles import TileGrid

__all__ = ["Peak", "find_peaks", "peaks_geojson"]

_KERNEL = np.ones((3, 3), np.uint8)


@dataclass(frozen=True, slots=True)
class Peak:
    """One object candidate: cls, position (degrees), score in [0, 1], global cell coordinates."""

    cls: str
    lat: float
    lon: float
    score: float
    gx: float
    gy: float


def _padded(tiles: dict[tuple[int, int], NDArray[np.uint8]], x: int, y: int, n: int, side: int
            ) -> NDArray[np.uint8]:
    """(n + 2, n + 2) tile (x, y) with a one-cell border taken from its 8 neighbours (0 where none); x wraps
    modulo ``side`` (tiles per world edge): across the antimeridian x = side - 1 and x = 0 are neighbours."""
    out = np.zeros((n + 2, n + 2), dtype=np.uint8)
    out[1:-1, 1:-1] = tiles[(x, y)]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == dy == 0:
                continue
            other = tiles.get(((x + dx) % side, y + dy))
            if other is None:
                continue
            rows_dst = slice(0, 1) if dy < 0 else slice(n + 1, n + 2) if dy > 0 else slice(1, n + 1)
            cols_dst = slice(0, 1) if dx < 0 else slice(n + 1, n + 2) if dx > 0 else slice(1, n + 1)
            rows_src = slice(n - 1, n) if dy < 0 else slice(0, 1) if dy > 0 else slice(0, n)
            cols_src = slice(n - 1, n) if dx < 0 else slice(0, 1) if dx > 0 else slice(0, n)
            out[rows_dst, cols_dst] = other[rows_src, cols_src]
    return out


def _tile_peaks(padded: NDArray[np.uint8], min_byte: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray]:
    """Plateau centroids (col, row inside the tile) and byte values of the peaks of one padded tile."""
    dilated = cv2.dilate(padded, _KERNEL)
    mask = ((padded == dilated) & (padded >= min_byte))[1:-1, 1:-1].astype(np.uint8)
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        empty = np.zeros(0)
        return empty, empty, empty
    cols = np.flatnonzero(mask.any(axis=0))
    # the components are labelled in the span of the maxima only: a tile's few objects usually lie close together,
    # and labelling 256 x 256 cells took ~0.5 ms a tile. OpenCV labels in 2 x 2 blocks from the corner, so the span
    # starts on an even row and column: the labels, and so the order of tied peaks, stay those of the whole tile
    r0, c0 = int(rows[0]) & ~1, int(cols[0]) & ~1
    mask = mask[r0:int(rows[-1]) + 1, c0:int(cols[-1]) + 1]
    count, labels, _, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    centroids = centroids + (c0, r0)
    inner = padded[1:-1, 1:-1][r0:r0 + mask.shape[0], c0:c0 + mask.shape[1]]
    # equal neighbours that are both maxima have the same value, so any cell of a component gives it
    first = np.full(count, -1, dtype=np.int64)
    flat = labels.ravel()
    order = np.flatnonzero(flat)
    first[flat[order[::-1]]] = order[::-1]
    scores = inner.ravel()[first[1:]]
    return centroids[1:, 0], centroids[1:, 1], scores


#: Peaks closer than this (m) are one object, whatever the latitude (2 cells at 48.5 deg, z 18, 256-cell tiles).
MIN_PEAK_DISTANCE_M = 0.8


def find_peaks(
    tiles: list[JointTile],
    grid: TileGrid,
    min_score: float = 0.5,
    *,
    bbox: BBox | None = None,
    min_distance_cells: float = 2.0,
    min_distance_m: float = MIN_PEAK_DISTANCE_M,
    limit: int = 1000,
) -> list[Peak]:
    """Peaks with score >= min_score of the joint tiles of one class, strongest first.

    tiles: joint tiles of one class at the grid's zoom (neighbours are looked up among them).
    bbox: keep only peaks inside it. At most ``limit`` peaks are returned. A weaker peak within
    ``min_distance_cells`` cells of a stronger one, or within ``min_distance_m`` metres (Web Mercator cells shrink
    with cos(latitude): 2 cells are 0.79 m at 48.5 deg but 0.23 m at 79 deg, where one person gave several objects),
    is suppressed.
    """
    if not tiles:
        return []
    cls = tiles[0].cls
    n = grid.n
    min_byte = max(1, math.ceil(min_score * 255.0 - 1e-6))
    by_xy = {(t.x, t.y): t.values for t in tiles}
    gxs, gys, scores = [], [], []
    for (x, y), values in by_xy.items():
        if int(values.max()) < min_byte:
            continue
        cols, rows, vals = _tile_peaks(_padded(by_xy, x, y, n, grid.tiles_per_side), min_byte)
        gxs.append(x * n + cols + 0.5)
        gys.append(y * n + rows + 0.5)
        scores.append(vals)
    if not gxs:
        return []
    gx = np.concatenate(gxs)
    gy = np.concatenate(gys)
    score = np.concatenate(scores).astype(np.float64) / 255.0
    lat, lon = grid.cell_to_latlon(gx, gy)
    if bbox is not None:
        inside = bbox.contains(lat, lon)
        gx, gy, score, lat, lon = gx[inside], gy[inside], score[inside], lat[inside], lon[inside]
    order = np.argsort(-score, kind="stable")
    radius = np.maximum(min_distance_cells, min_distance_m / np.maximum(grid.cell_size_m(lat), 1e-9))  # per peak
    keep = _suppress(gx[order], gy[order], radius[order], grid.world_cells)
    picked = order[keep][:limit]
    return [Peak(cls, float(lat[i]), float(lon[i]), float(score[i]), float(gx[i]), float(gy[i])) for i in picked]


def _suppress(gx: NDArray[np.float64], gy: NDArray[np.float64], radius: float | NDArray[np.float64],
              world_cells: int) -> NDArray[np.intp]:
    """Indices (into the score-sorted arrays) of peaks with no stronger kept peak within radius (cells; one, or one
    per peak: the kept peak's). gx, gy in [0, world_cells); gx is periodic (the antimeridian), gy is not."""
    radii = np.broadcast_to(np.asarray(radius, dtype=np.float64), gx.shape)
    if gx.size <= 1 or not np.any(radii > 0):
        return np.arange(gx.size)
    # a torus in x; in y a period of twice the world, which no radius spans (the poles are no neighbours)
    tree = cKDTree(np.column_stack([gx, gy]), boxsize=(float(world_cells), 2.0 * world_cells))
    suppressed = np.zeros(gx.size, dtype=bool)
    keep = []
    for i in range(gx.size):
        if suppressed[i]:
            continue
        keep.append(i)
        for j in tree.query_ball_point((gx[i], gy[i]), radii[i]):
            if j > i:
                suppressed[j] = True
    return np.array(keep, dtype=np.intp)


def peaks_geojson(peaks: list[Peak]) -> dict:
    """A GeoJSON FeatureCollection of Points with properties cls and score."""
    return {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [p.lon, p.lat]},
                "properties": {"cls": p.cls, "score": round(p.score, 4)},
            }
            for p in peaks
        ],
    }

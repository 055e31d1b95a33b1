"""The anomaly layer of the memory map: per-frame heatmaps warped onto the global ground grid below the
horizon, averaged over time with forgetting, and read back into any frame (paper section IV-C).

One `cv2.warpPerspective` per frame moves the whole heatmap into the block of cells the camera sees within
``max_range_m``; before it, each band of image rows is averaged over the footprint one grid cell has there
(`cell_mean`), so a cell holds the mean heat of its own ground area wherever it lies in the frame: near rows,
where a cell covers many pixels, are averaged over all of them (a one-pixel glint counts by its share of the
cell), far rows, where a pixel covers several cells, are sampled as they are.
The layer keeps two decaying sums per cell on a `agent.memory_map.MemoryMap` window (same grid, window,
recentring and forgetting as the detection maps): heat x observation time and observation time. Their
ratio is the cell's heat averaged over the recent frames that saw it; cells seen for less than
``prior_s`` are pulled towards 0, so one noisy glimpse does not count as much as a steady sighting.
With a terrain (`--dem`) the cells are lifted onto the DEM and projected one by one, the cells the terrain hides
are left out (`agent.anomaly.terrain_view`), each takes the mean of the heat over its own footprint box, and the
layer is read back by spreading each cell's value over that box (`footprint_means`, `spread_footprints`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.anomaly.terrain_view import TerrainCells, TerrainView, terrain_cut_row, terrain_view
from agent.memory_map import MemoryMap, MemoryMapConfig
from shared.geo import Camera, Pose, ground_to_image_homography, latlon_to_local, pixel_ground_distance_m
from shared.terrain import Terrain
from shared.tiles import CellWindow, TileGrid

#: Class name of the layer on the wire (tiles ``uav/{uav}/tiles/anomaly/...``) and in COCO results.
ANOMALY_CLASS = "anomaly"
_HEAT, _SEEN = "anomaly_heat", "anomaly_seen"
#: Heatmaps finer than _MAX_PX_PER_CELL pixels a grid cell (at their finest row: a full-resolution 4K heatmap) are
#: first resampled to _RESAMPLE_PX_PER_CELL; the working-size heatmaps (up to ~6 pixels a cell) are used as they are.
_MAX_PX_PER_CELL = 8.0
_RESAMPLE_PX_PER_CELL = 4.0


@dataclass(frozen=True, slots=True)
class AnomalyMapConfig:
    """Parameters of the anomaly layer, in metres and seconds.

    window_m: edge of the UAV-centric window (as the detection maps).
    half_life_s: time for unrefreshed heat to halve (the paper's forgetting factor phi per frame is
        0.5 ** (frame interval / half_life_s)). 0.75 s since 26 Nov 2026 (0.5 s before; docs/anomaly.md,
        sea-hard).
    prior_s: observation time a cell needs before its average counts fully (value = heat sum /
        (seen + prior_s)).
    max_range_m: pixels whose ground point is farther from the UAV are cut (the paper: far pixels are noise).
    horizon_margin_deg: pixels less than this below the horizon are cut as well.
    max_step_s: the longest frame interval one update counts as observation time.
    """

    window_m: float = 300.0
    half_life_s: float = 0.75
    prior_s: float = 0.1
    max_range_m: float = 120.0
    horizon_margin_deg: float = 3.0
    max_step_s: float = 0.2

    def __post_init__(self) -> None:
        for name in ("window_m", "half_life_s", "prior_s", "max_range_m", "max_step_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"AnomalyMapConfig.{name} must be a finite number > 0, got {value!r}")
        if not (math.isfinite(self.horizon_margin_deg) and 0 <= self.horizon_margin_deg < 45):
            raise ValueError(f"AnomalyMapConfig.horizon_margin_deg must be in [0, 45), got {self.horizon_margin_deg!r}")


class _SumLayers(MemoryMap):
    """A MemoryMap whose layers are decaying sums written a block at a time (no clipping)."""

    def add_block(self, cls: str, block: NDArray[np.float32], row0: int, col0: int) -> None:
        """Add a (h, w) block at window cell (row0, col0); parts outside the window are dropped."""
        s = self._size
        r0, c0 = max(row0, 0), max(col0, 0)
        r1, c1 = min(row0 + block.shape[0], s), min(col0 + block.shape[1], s)
        if r1 <= r0 or c1 <= c0:
            return
        m = self._maps.get(cls)
        if m is None:
            m = self._maps[cls] = np.zeros((s, s), dtype=np.float32)
        part = block[r0 - row0:r1 - row0, c0 - col0:c1 - col0]
        m[r0:r1, c0:c1] += part if self._scale == 1.0 else part * np.float32(1.0 / self._scale)

    def stored(self, cls: str) -> tuple[NDArray[np.float32] | None, float]:
        """The stored layer (a view) and the pending decay factor: true values = stored * factor."""
        return self._maps.get(cls), self._scale


def _translate(dx: float, dy: float) -> NDArray[np.float64]:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def cut_row(camera: Camera, pose: Pose, max_range_m: float, horizon_margin_deg: float) -> int:
    """First image row (full resolution) that is mapped to the ground: its ray on the centre column points
    at least horizon_margin_deg below the horizontal and meets the ground within max_range_m.
    camera.height when no row qualifies (camera looking too high).

    Closed form for the usual zero roll and no distortion (the row of the limiting depression); otherwise
    the rows' ground distances are computed.
    """
    min_dep = max(horizon_margin_deg, math.degrees(math.atan2(pose.height_m, max_range_m)))
    if pose.roll_deg == 0.0 and camera.dist is None:
        offset = min_dep - pose.pitch_deg  # the limiting ray's angle below the optical axis
        if offset <= -89.0:
            return 0
        if offset >= 89.0:
            return camera.height
        v = camera.cy + camera.fy * math.tan(math.radians(offset))
        return int(min(max(math.ceil(v - 0.5), 0), camera.height))
    rows = np.arange(camera.height, dtype=np.float64) + 0.5
    uv = np.column_stack([np.full_like(rows, camera.cx), rows])
    dist = pixel_ground_distance_m(uv, camera, pose)
    depression = pose.pitch_deg + np.degrees(np.arctan2(rows - camera.cy, camera.fy))
    ok = np.isfinite(dist) & (dist <= max_range_m) & (depression >= horizon_margin_deg)
    if not ok.any():
        return camera.height
    return int(np.argmax(ok))  # rows farther down are nearer: the first qualifying row starts the band


def _odd(k: NDArray[np.float64]) -> NDArray[np.int64]:
    """The odd kernel sizes nearest to k pixels (at least 1; 1 where k is not finite)."""
    k = np.where(np.isfinite(k), k, 1.0)
    return (2 * np.round(np.maximum(k - 1.0, 0.0) / 2.0) + 1).astype(np.int64)


def cell_footprint_px(cell_to_band: NDArray[np.float64], band_rows: NDArray[np.float64], centre_col: float
                      ) -> NDArray[np.float64]:
    """Width and height (band pixels) of the box around one grid cell's footprint at each band row.

    cell_to_band: (3, 3) homography from window cells (col, row) to band pixels; band_rows (N,) pixel rows,
    taken at the band column centre_col. Returns (N, 2) float64: (kx, ky), the sums of the absolute image steps
    of one cell east and one cell south (the bounding box of the cell's parallelogram); NaN where the row has no
    ground point.
    """
    pts = np.column_stack([np.full_like(band_rows, centre_col), band_rows])[None]
    cells = cv2.perspectiveTransform(pts, np.linalg.inv(cell_to_band))[0]
    corners = np.concatenate([cells, cells + [1.0, 0.0], cells + [0.0, 1.0]])[None]
    img = cv2.perspectiveTransform(corners, cell_to_band)[0].reshape(3, -1, 2)
    de, dn = np.abs(img[1] - img[0]), np.abs(img[2] - img[0])
    return de + dn


def cell_mean(band: NDArray[np.float32], cell_to_band: NDArray[np.float64], rows_step: int = 8
              ) -> NDArray[np.float32]:
    """The band averaged, row by row, over the footprint one grid cell has there (a box of odd size about the
    cell's bounding box, `cell_footprint_px`): sampling the result at a cell's centre gives about the mean heat
    of the cell's ground. Rows where a cell is smaller than a pixel are left as they are.

    band: (h, w) float32; cell_to_band: (3, 3) homography from window cells to band pixels. The footprint is
    taken every rows_step rows (centre column); runs of rows with the same box are filtered together
    (`cv2.blur` on the strip: the cost does not grow with the box). Returns a new (h, w) float32 array.
    """
    h, w = band.shape
    rows = np.arange(0, h, rows_step, dtype=np.float64)
    fp = cell_footprint_px(cell_to_band, rows + 0.5 * min(rows_step, h), 0.5 * w)
    sizes = list(zip(_odd(fp[:, 0]).tolist(), _odd(fp[:, 1]).tolist(), strict=True))
    out = band.copy()
    i = 0
    while i < len(sizes):
        j = i
        while j + 1 < len(sizes) and sizes[j + 1] == sizes[i]:
            j += 1
        kx, ky = sizes[i]
        if (kx, ky) != (1, 1):
            a, b = i * rows_step, min((j + 1) * rows_step, h)
            lo, hi = max(a - ky // 2, 0), min(b + ky // 2, h)
            out[a:b] = cv2.blur(band[lo:hi], (kx, ky), borderType=cv2.BORDER_REFLECT)[a - lo:b - lo]
        i = j + 1
    return out


def _box_edges(centre: NDArray[np.float64], size: NDArray[np.float64], limit: int, *, outward: bool = False
               ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Pixel edges [lo, hi) of boxes of the given sizes (at least one pixel; NaN: one) about real-valued centres
    (pixel i spans [i, i + 1)), rounded to the nearest edges (outward: to the edges that hold the whole box),
    clipped to [0, limit], never empty."""
    hi = np.fmax(size, 1.0)
    hi *= 0.5
    lo = centre - hi
    hi += centre
    if outward:
        np.floor(lo, out=lo)
        np.ceil(hi, out=hi)
    else:
        np.rint(lo, out=lo)
        np.rint(hi, out=hi)
    first = np.minimum(np.maximum(lo, 0.0, out=lo), limit - 1.0, out=lo).astype(np.int64)
    last = np.minimum(np.maximum(hi, 1.0, out=hi), float(limit), out=hi).astype(np.int64)
    return first, np.maximum(last, first + 1, out=last)


def footprint_means(image: NDArray[np.float32], u: NDArray[np.float64], v: NDArray[np.float64],
                    kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float32]:
    """(N,) float32 mean of image (h, w) float32 over the box of kx x ky pixels about each point (u, v) (pixel i
    spans [i, i + 1); float64 (N,) arrays), the terrain path's `cell_mean`: a summed-area table for boxes of two
    pixels or more, bilinear sampling (edges replicated) where the box is smaller (the flat path's odd box 1).
    NaN sizes count as small."""
    out = np.empty(len(u), np.float32)
    small = ~((kx >= 2.0) | (ky >= 2.0))
    if small.any():
        n = int(small.sum())
        rows = -(-n // 1024)  # OpenCV's maps are images of fewer than 32767 columns
        mx = np.zeros(rows * 1024, np.float32)
        my = np.zeros(rows * 1024, np.float32)
        mx[:n], my[:n] = u[small] - 0.5, v[small] - 0.5
        sampled = cv2.remap(image, mx.reshape(rows, 1024), my.reshape(rows, 1024), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        out[small] = sampled.reshape(-1)[:n]
    big = ~small
    if big.any():
        h, w = image.shape
        sat = np.asarray(cv2.integral(image, sdepth=cv2.CV_64F)).ravel()  # (h + 1, w + 1): image[:y, :x].sum()
        x0, x1 = _box_edges(u[big], kx[big], w)
        y0, y1 = _box_edges(v[big], ky[big], h)
        area = (x1 - x0) * (y1 - y0)
        y0 *= w + 1
        y1 *= w + 1
        total = sat.take(y1 + x1) - sat.take(y0 + x1) - sat.take(y1 + x0) + sat.take(y0 + x0)
        out[big] = total / area
    return out


def spread_footprints(shape: tuple[int, int], u: NDArray[np.float64], v: NDArray[np.float64],
                      kx: NDArray[np.float64], ky: NDArray[np.float64], values: NDArray[np.float32]
                      ) -> NDArray[np.float32]:
    """The read-back counterpart of `footprint_means`: an (h, w) float32 image where each pixel holds the mean of
    the values whose boxes (kx x ky pixels, at least one, about (u, v), rounded outward so that neighbouring cells'
    boxes leave no pixel between them) cover it, 0 where none does.

    The boxes are painted by their four corners into a difference image and integrated (a summed-area table),
    so the cost does not grow with their size."""
    h, w = shape
    x0, x1 = _box_edges(u, kx, w, outward=True)
    y0, y1 = _box_edges(v, ky, h, outward=True)
    stride = w + 1
    y0 *= stride
    y1 *= stride
    n = len(u)
    idx = np.empty(4 * n, np.int64)
    weights = np.empty(4 * n)
    for k, (row, col, sign) in enumerate(((y0, x0, 1.0), (y0, x1, -1.0), (y1, x0, -1.0), (y1, x1, 1.0))):
        np.add(row, col, out=idx[k * n:(k + 1) * n])
        weights[k * n:(k + 1) * n] = sign
    size = (h + 1) * stride

    def integrate(corner_weights: NDArray[np.float64]) -> NDArray[np.float64]:
        corners = np.bincount(idx, corner_weights, size).reshape(h + 1, stride)
        sat = np.asarray(cv2.integral(corners, sdepth=cv2.CV_64F), dtype=np.float64)
        return sat[1:h + 1, 1:w + 1]  # the inclusive 2-D cumulative sum

    count = integrate(weights)
    weights *= np.tile(values.astype(np.float64), 4)
    total = integrate(weights)
    # counts are whole numbers (exact); where no box covers a pixel its total is 0 but for rounding
    np.maximum(count, 1.0, out=count)
    out = (total / count).astype(np.float32)
    return np.maximum(out, 0.0, out=out)


class AnomalyMap:
    """The anomaly layer: `update` with each frame's heatmap, `image_scores` to read it back into a frame,
    `tiles` to publish it.

    Parameters
    ----------
    config : AnomalyMapConfig, optional
    grid : TileGrid, optional
        The shared tile grid (default z 18, 256 cells a tile).
    """

    def __init__(self, config: AnomalyMapConfig | None = None, grid: TileGrid | None = None) -> None:
        self.config = config or AnomalyMapConfig()
        self.grid = grid or TileGrid()
        self._sums = _SumLayers(MemoryMapConfig(window_m=self.config.window_m, half_life_s=self.config.half_life_s,
                                                max_step_s=self.config.max_step_s), self.grid)
        self._t_prev: float | None = None
        self._terrain_cells: TerrainCells | None = None
        self._view: tuple[tuple[object, ...], TerrainView | None] | None = None  # (key, the last view)

    def reset(self) -> None:
        """Forget everything (a new video)."""
        self._sums.reset()
        self._t_prev = None

    @property
    def size_cells(self) -> int:
        return self._sums.size_cells

    @property
    def origin(self) -> tuple[int, int]:
        return self._sums.origin

    # ------------------------------------------------------------------ geometry
    def _cell_to_local(self, pose: Pose) -> NDArray[np.float64]:
        """(3, 3) affine taking window (col, row) cell-corner coordinates to metres east/north of the UAV.

        Web Mercator is conformal: over a 300 m window the map from cells to local metres is affine to
        well under a centimetre, so three points fix it.
        """
        gx0, gy0 = self._sums.origin
        cols = np.array([0.0, self.size_cells, 0.0])
        rows = np.array([0.0, 0.0, self.size_cells])
        lat, lon = self.grid.cell_to_latlon(gx0 + cols, gy0 + rows)
        east, north = latlon_to_local(lat, lon, pose.lat, pose.lon)
        src = np.column_stack([cols, rows]).astype(np.float32)
        dst = np.column_stack([east, north]).astype(np.float32)
        a = cv2.getAffineTransform(src, dst).astype(np.float64)
        return np.vstack([a, [0.0, 0.0, 1.0]])

    def _cell_to_image(self, camera: Camera, pose: Pose, ground_to_image: NDArray[np.float64] | None = None
                       ) -> NDArray[np.float64]:
        """(3, 3) homography from window (col, row) cell coordinates to full-resolution image pixels."""
        g = ground_to_image_homography(camera, pose) if ground_to_image is None else ground_to_image
        return g @ self._cell_to_local(pose)

    # ------------------------------------------------------------------ write
    def _footprint(self, camera: Camera, pose: Pose, ground_to_image: NDArray[np.float64] | None
                   ) -> tuple[int, NDArray[np.float64], NDArray[np.float64], tuple[int, int, int, int]] | None:
        """The mapped band of a frame: (cut row, cell -> image homography, its corners in window cells (4, 2),
        block (c0, r0, c1, r1) of window cells it covers), or None when nothing of it lies in the window."""
        cfg = self.config
        row = cut_row(camera, pose, cfg.max_range_m, cfg.horizon_margin_deg)
        if row >= camera.height or self.size_cells == 0:
            return None
        c2i = self._cell_to_image(camera, pose, ground_to_image)
        corners = np.array([[[0.0, row], [camera.width, row], [camera.width, camera.height], [0.0, camera.height]]])
        cells = cv2.perspectiveTransform(corners, np.linalg.inv(c2i))[0]
        if not np.isfinite(cells).all():
            return None
        s = self.size_cells
        c0, r0 = (max(int(v), 0) for v in np.floor(cells.min(axis=0)))
        c1, r1 = (min(int(v) + 1, s) for v in np.ceil(cells.max(axis=0)))
        if c1 <= c0 or r1 <= r0:
            return None
        return row, c2i, cells, (c0, r0, c1, r1)

    def terrain_view(self, camera: Camera, pose: Pose, terrain: Terrain,
                     ground_to_image: NDArray[np.float64] | None = None) -> TerrainView | None:
        """The window cells the frame sees on the terrain and their pixels (`agent.anomaly.terrain_view`), None when
        it sees none; the last one is kept, so an update and the read-back of the same frame compute it once."""
        key = (camera, pose, terrain.grid, terrain.takeoff_elevation_m, self._sums.origin, self.size_cells,
               None if ground_to_image is None else ground_to_image.tobytes())
        if self._view is not None and self._view[0] == key:
            return self._view[1]
        cfg = self.config
        view = terrain_view(camera, pose, terrain, self._cells_of(terrain), self._cell_to_local(pose),
                            self.size_cells, self._step_m(pose, terrain), cfg.max_range_m, cfg.horizon_margin_deg,
                            ground_to_image)
        self._view = (key, view)
        return view

    def _cells_of(self, terrain: Terrain) -> TerrainCells:
        if self._terrain_cells is None or self._terrain_cells.grid is not terrain.grid:
            self._terrain_cells = TerrainCells(terrain.grid)
        return self._terrain_cells

    def terrain_cut_row(self, camera: Camera, pose: Pose, terrain: Terrain,
                        ground_to_image: NDArray[np.float64] | None = None) -> int:
        """First full-resolution row that shows a cell the layer maps on the terrain (`TerrainView.cut_row`; the
        camera's height when none): of this frame's view once the layer's window is placed, else on a lattice
        about the UAV (`agent.anomaly.terrain_view.terrain_cut_row`: the per-frame baseline has no window)."""
        if self.size_cells == 0:
            cfg = self.config
            return terrain_cut_row(camera, pose, terrain, self._cells_of(terrain), self._step_m(pose, terrain),
                                   cfg.max_range_m, cfg.horizon_margin_deg)
        view = self.terrain_view(camera, pose, terrain, ground_to_image)
        return camera.height if view is None else view.cut_row

    def _step_m(self, pose: Pose, terrain: Terrain) -> float:
        """The terrain path's lattice step: a grid cell, or the DEM's spacing where that is finer."""
        return min(float(self.grid.cell_size_m(pose.lat)), *terrain.grid.cell_size_m())

    def update(self, heat: NDArray[np.float32], camera: Camera, pose: Pose, t: float,
               ground_to_image: NDArray[np.float64] | None = None, terrain: Terrain | None = None) -> bool:
        """Add one frame's heatmap (h, w) float32 in [0, 1] (any scale of the camera's frame) seen at time t
        (seconds) with the camera pose. Returns False when no pixel of the frame maps to the ground.

        ground_to_image: the frame's (3, 3) homography from metres east/north of the pose's position to
        full-resolution pixels when known better than the pose's own (`agent.anomaly.registration`).
        terrain: map the heat onto this terrain's surface (`terrain_view`: cells hidden by the terrain are not
        seen); None: flat ground (one homography)."""
        cfg = self.config
        dt = 0.0 if self._t_prev is None else min(max(t - self._t_prev, 0.0), cfg.max_step_s)
        self._t_prev = t if self._t_prev is None else max(self._t_prev, t)
        self._sums.advance(t, pose.lat, pose.lon)
        amount = dt if dt > 0 else 1.0 / 30.0  # the first frame counts as one frame at 30 fps
        if terrain is not None:
            view = self.terrain_view(camera, pose, terrain, ground_to_image)
            if view is None:
                return False
            self._add_terrain_heat(heat, camera, view, amount)
            return True
        foot = self._footprint(camera, pose, ground_to_image)
        if foot is None:
            return False
        row, c2i, cells, (c0, r0, c1, r1) = foot
        hh, hw = heat.shape
        scale = hw / camera.width
        # only the band below the cut row is read (a view: no copy of the heatmap)
        first = min(hh - 1, int(row * hh / camera.height))
        band = heat[first:]
        # a large heatmap (a full-resolution 4K one) is first resampled to 4 pixels a cell at its finest row
        # (bilinear: the cost follows the output, not the 33 MB input; anything wider than a quarter of a cell
        # still reaches the cell's mean)
        bottom = np.array([[[camera.cx, camera.height - 0.5], [camera.cx + 1.0, camera.height - 0.5]]])
        step = np.diff(cv2.perspectiveTransform(bottom, np.linalg.inv(c2i))[0], axis=0)[0]  # cells a full pixel
        px_per_cell = scale / max(float(np.hypot(step[0], step[1])), 1e-9)
        if px_per_cell > _MAX_PX_PER_CELL:
            k = _RESAMPLE_PX_PER_CELL / px_per_cell
            band = np.asarray(cv2.resize(band, (max(1, int(round(band.shape[1] * k))),
                                                max(1, int(round(band.shape[0] * k)))),
                                         interpolation=cv2.INTER_LINEAR), dtype=np.float32)
        sx, sy = band.shape[1] / camera.width, band.shape[0] / ((hh - first) * camera.height / hh)
        y0 = first * camera.height / hh  # full-resolution row of the band's top edge
        cell_to_band = np.diag([sx, sy, 1.0]) @ _translate(0.0, -y0) @ c2i
        band = cell_mean(band, cell_to_band)
        # block index (x, y) -> cell centre -> image pixel -> band array index (pixel centres at integers)
        block_to_band = _translate(-0.5, -0.5) @ cell_to_band @ _translate(c0 + 0.5, r0 + 0.5)
        size = (c1 - c0, r1 - r0)
        warped = cv2.warpPerspective(band, block_to_band, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT)
        seen = np.zeros((size[1], size[0]), np.float32)
        poly = np.round((cells - [c0 + 0.5, r0 + 0.5]) * 16).astype(np.int32)
        cv2.fillPoly(seen, [poly], float(amount), lineType=cv2.LINE_8, shift=4)
        self._sums.add_block(_HEAT, np.asarray(cv2.multiply(warped, seen), dtype=np.float32), r0, c0)
        self._sums.add_block(_SEEN, seen, r0, c0)
        return True

    def _add_terrain_heat(self, heat: NDArray[np.float32], camera: Camera, view: TerrainView, amount: float) -> None:
        """The terrain path of `update`: each seen cell takes the mean heat of its footprint box about its pixel."""
        hh, hw = heat.shape
        first = min(hh - 1, int(view.cut_row * hh / camera.height))
        band = heat[first:]
        # as on flat ground: a heatmap finer than _MAX_PX_PER_CELL at its finest cell is resampled first
        px_per_cell = hw / camera.width * view.max_step_px
        if px_per_cell > _MAX_PX_PER_CELL:
            k = _RESAMPLE_PX_PER_CELL / px_per_cell
            band = np.asarray(cv2.resize(band, (max(1, int(round(band.shape[1] * k))),
                                                max(1, int(round(band.shape[0] * k)))),
                                         interpolation=cv2.INTER_LINEAR), dtype=np.float32)
        sx, sy = band.shape[1] / camera.width, band.shape[0] / ((hh - first) * camera.height / hh)
        y0 = first * camera.height / hh  # full-resolution row of the band's top edge
        means = footprint_means(np.ascontiguousarray(band), view.uv[:, 0] * sx, (view.uv[:, 1] - y0) * sy,
                                view.footprint[:, 0] * sx, view.footprint[:, 1] * sy)
        c0, r0, _, _ = view.block
        seen = view.valid.astype(np.float32) * np.float32(amount)
        warmed = np.zeros(view.valid.shape, np.float32)
        warmed[view.valid] = means * np.float32(amount)
        self._sums.add_block(_HEAT, warmed, r0, c0)
        self._sums.add_block(_SEEN, seen, r0, c0)

    # ------------------------------------------------------------------ read
    def layer(self, block: tuple[int, int, int, int] | None = None) -> NDArray[np.float32] | None:
        """The averaged heat, float32 in [0, 1]: the whole window (size, size), north-west cell first, or the
        block (c0, r0, c1, r1) of window cells; None before the first update."""
        heat, f_heat = self._sums.stored(_HEAT)
        seen, _ = self._sums.stored(_SEEN)
        if heat is None or seen is None:
            return None
        if block is not None:
            c0, r0, c1, r1 = block
            heat, seen = heat[r0:r1, c0:c1], seen[r0:r1, c0:c1]
        prior = np.float32(self.config.prior_s / f_heat)  # in stored units: both sums share the factor
        out = heat / (seen + prior)
        np.clip(out, 0.0, 1.0, out=out)
        return out

    def image_scores(self, camera: Camera, pose: Pose, shape: tuple[int, int],
                     ground_to_image: NDArray[np.float64] | None = None, terrain: Terrain | None = None
                     ) -> NDArray[np.float32]:
        """The layer seen from a frame: (h, w) float32 at an image scale of the camera (shape = (h, w)),
        0 above the cut row (horizon, range) and where the window holds nothing (ground_to_image and terrain as in
        update; with a terrain each seen cell's value is spread over its footprint box, `spread_footprints`)."""
        if terrain is not None:
            return self._terrain_scores(camera, pose, shape, ground_to_image, terrain)
        out = np.zeros(shape, dtype=np.float32)
        foot = self._footprint(camera, pose, ground_to_image)
        if foot is None:
            return out
        row, c2i, _, (c0, r0, c1, r1) = foot
        block = self.layer((c0, r0, c1, r1))
        if block is None:
            return out
        h, w = shape
        first = int(math.ceil(row * h / camera.height))
        if first >= h:
            return out
        # output pixel (x, y) -> image point -> window cell -> block array index; one inverse warp
        s = np.diag([w / camera.width, h / camera.height, 1.0])
        img_to_block = (_translate(-0.5 - c0, -0.5 - r0) @ np.linalg.inv(c2i) @ np.linalg.inv(s)
                        @ _translate(0.5, first + 0.5))
        out[first:] = cv2.warpPerspective(block, img_to_block, (w, h - first),
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                          borderMode=cv2.BORDER_CONSTANT)
        return out

    def _terrain_scores(self, camera: Camera, pose: Pose, shape: tuple[int, int],
                        ground_to_image: NDArray[np.float64] | None, terrain: Terrain) -> NDArray[np.float32]:
        view = self.terrain_view(camera, pose, terrain, ground_to_image)
        block = None if view is None else self.layer(view.block)
        if view is None or block is None:
            return np.zeros(shape, dtype=np.float32)
        h, w = shape
        sx, sy = w / camera.width, h / camera.height
        out = spread_footprints(shape, view.uv[:, 0] * sx, view.uv[:, 1] * sy, view.footprint[:, 0] * sx,
                                view.footprint[:, 1] * sy, block[view.valid])
        out[:int(math.ceil(view.cut_row * h / camera.height))] = 0.0
        return out

    @property
    def classes(self) -> list[str]:
        """The layer's class name, once it holds something (the interface `agent.tile_updates` reads)."""
        return [ANOMALY_CLASS] if self._sums.size_cells else []

    def tiles(self, cls: str = ANOMALY_CLASS, *, min_value: float = 0.0) -> list[tuple[int, int, NDArray[np.float32]]]:
        """The layer cut into grid tiles [(x, y, (n, n) float32)], cells outside the window 0, like
        `MemoryMap.tiles` (every overlapped tile, empty ones too, unless min_value > 0 drops tiles whose
        maximum is below it). Other class names give no tiles."""
        layer = self.layer()
        if cls != ANOMALY_CLASS or self.size_cells == 0:
            return []
        if layer is None:
            layer = np.zeros((self.size_cells, self.size_cells), np.float32)
        gx0, gy0 = self._sums.origin
        gy_lo = max(gy0, 0)
        gy_hi = min(gy0 + self.size_cells, self.grid.world_cells)
        window = CellWindow(gx0 % self.grid.world_cells, gy_lo, self.size_cells, gy_hi - gy_lo, self.grid)
        tiles = window.split(layer[gy_lo - gy0:gy_hi - gy0])
        return [t for t in tiles if min_value <= 0 or t[2].max() >= min_value]

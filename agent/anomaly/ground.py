"""The anomaly layer of the memory map: per-frame heatmaps warped onto the global ground grid below the
horizon, averaged over time with forgetting, and read back into any frame (paper section IV-C).

One `cv2.warpPerspective` per frame moves the whole heatmap (max-pooled and area-downscaled first so a grid
cell samples a heatmap pixel of about its own size holding the strongest heat inside it) into the block of
cells the camera sees within ``max_range_m``.
The layer keeps two decaying sums per cell on a `agent.memory_map.MemoryMap` window (same grid, window,
recentring and forgetting as the detection maps): heat x observation time and observation time. Their
ratio is the cell's heat averaged over the recent frames that saw it; cells seen for less than
``prior_s`` are pulled towards 0, so one noisy glimpse does not count as much as a steady sighting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.memory_map import MemoryMap, MemoryMapConfig
from shared.geo import Camera, Pose, ground_to_image_homography, latlon_to_local, pixel_ground_distance_m
from shared.tiles import CellWindow, TileGrid

#: Class name of the layer on the wire (tiles ``uav/{uav}/tiles/anomaly/...``) and in COCO results.
ANOMALY_CLASS = "anomaly"
_HEAT, _SEEN = "anomaly_heat", "anomaly_seen"


@dataclass(frozen=True, slots=True)
class AnomalyMapConfig:
    """Parameters of the anomaly layer, in metres and seconds.

    window_m: edge of the UAV-centric window (as the detection maps).
    half_life_s: time for unrefreshed heat to halve (the paper's forgetting factor phi per frame is
        0.5 ** (frame interval / half_life_s)).
    prior_s: observation time a cell needs before its average counts fully (value = heat sum /
        (seen + prior_s)).
    max_range_m: pixels whose ground point is farther from the UAV are cut (the paper: far pixels are noise).
    horizon_margin_deg: pixels less than this below the horizon are cut as well.
    max_step_s: the longest frame interval one update counts as observation time.
    """

    window_m: float = 300.0
    half_life_s: float = 0.5
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
    """First image row (full resolution) that is mapped to the ground: below the horizon by the margin and
    with ground points within max_range_m on the centre column. camera.height when no row qualifies."""
    rows = np.arange(camera.height, dtype=np.float64) + 0.5
    uv = np.column_stack([np.full_like(rows, camera.cx), rows])
    dist = pixel_ground_distance_m(uv, camera, pose)
    depression = pose.pitch_deg + np.degrees(np.arctan2(rows - camera.cy, camera.fy))
    ok = np.isfinite(dist) & (dist <= max_range_m) & (depression >= horizon_margin_deg)
    if not ok.any():
        return camera.height
    # rows farther down are nearer: the first qualifying row starts the mapped band
    return int(np.argmax(ok))


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
    def update(self, heat: NDArray[np.float32], camera: Camera, pose: Pose, t: float,
               ground_to_image: NDArray[np.float64] | None = None) -> bool:
        """Add one frame's heatmap (h, w) float32 in [0, 1] (any scale of the camera's frame) seen at time t
        (seconds) with the camera pose. Returns False when no pixel of the frame maps to the ground.

        ground_to_image: the frame's (3, 3) homography from metres east/north of the pose's position to
        full-resolution pixels when known better than the pose's own (`agent.anomaly.registration`)."""
        cfg = self.config
        dt = 0.0 if self._t_prev is None else min(max(t - self._t_prev, 0.0), cfg.max_step_s)
        self._t_prev = t if self._t_prev is None else max(self._t_prev, t)
        self._sums.advance(t, pose.lat, pose.lon)
        amount = dt if dt > 0 else 1.0 / 30.0  # the first frame counts as one frame at 30 fps
        row = cut_row(camera, pose, cfg.max_range_m, cfg.horizon_margin_deg)
        if row >= camera.height:
            return False
        hh, hw = heat.shape
        scale = hw / camera.width
        # footprint of the mapped band: its four corners on the ground (lines stay lines under a homography)
        c2i = self._cell_to_image(camera, pose, ground_to_image)
        i2c = np.linalg.inv(c2i)
        corners = np.array([[0.0, row], [camera.width, row], [camera.width, camera.height], [0.0, camera.height]])
        cells = cv2.perspectiveTransform(corners[None].astype(np.float64), i2c)[0]
        if not np.isfinite(cells).all():
            return False
        s = self.size_cells
        c0, r0 = np.floor(cells.min(axis=0)).astype(int)
        c1, r1 = np.ceil(cells.max(axis=0)).astype(int) + 1
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, s), min(r1, s)
        if c1 <= c0 or r1 <= r0:
            return False
        # area-downscale the heatmap so that its finest pixels (the image's bottom row) are about a cell
        bottom = np.array([[camera.cx, camera.height - 0.5], [camera.cx + 1.0, camera.height - 0.5]])
        step = np.diff(cv2.perspectiveTransform(bottom[None], i2c)[0], axis=0)[0]  # cells per full pixel
        heat_px_per_cell = scale / max(float(np.hypot(step[0], step[1])), 1e-9)
        k = 1.0 / heat_px_per_cell if heat_px_per_cell > 1.0 else 1.0
        band = heat.copy()
        band[:max(0, min(hh, int(math.ceil(row * scale)))), :] = 0.0
        if k < 1.0:
            # max-pool (dilate, then area-downscale): a cell holds the strongest heat it contains, so an
            # object smaller than a cell is not averaged away with the water around it
            side = int(math.ceil(1.0 / k))
            if side > 1:
                band = cv2.dilate(band, np.ones((side, side), np.uint8))
            band = cv2.resize(band, (max(1, int(round(hw * k))), max(1, int(round(hh * k)))),
                              interpolation=cv2.INTER_AREA)
        sx, sy = band.shape[1] / camera.width, band.shape[0] / camera.height
        # block index (x, y) -> cell centre -> image pixel -> band array index (pixel centres at integers)
        block_to_band = _translate(-0.5, -0.5) @ np.diag([sx, sy, 1.0]) @ c2i @ _translate(c0 + 0.5, r0 + 0.5)
        size = (c1 - c0, r1 - r0)
        warped = cv2.warpPerspective(band, block_to_band, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT)
        seen = np.zeros((size[1], size[0]), np.uint8)
        poly = np.round((cells - [c0 + 0.5, r0 + 0.5]) * 16).astype(np.int32)
        cv2.fillPoly(seen, [poly], 1, lineType=cv2.LINE_8, shift=4)
        seen_f = seen.astype(np.float32) * np.float32(amount)
        self._sums.add_block(_HEAT, warped * seen_f, r0, c0)
        self._sums.add_block(_SEEN, seen_f, r0, c0)
        return True

    # ------------------------------------------------------------------ read
    def layer(self) -> NDArray[np.float32] | None:
        """The whole window's averaged heat, (size, size) float32 in [0, 1] (north-west cell first), or None
        before the first update."""
        heat, f_heat = self._sums.stored(_HEAT)
        seen, f_seen = self._sums.stored(_SEEN)
        if heat is None or seen is None:
            return None
        prior = np.float32(self.config.prior_s / f_seen)  # in stored units: both sums share the factor
        out = heat / (seen + prior)
        np.clip(out, 0.0, 1.0, out=out)
        return out

    def image_scores(self, camera: Camera, pose: Pose, shape: tuple[int, int],
                     ground_to_image: NDArray[np.float64] | None = None) -> NDArray[np.float32]:
        """The layer seen from a frame: (h, w) float32 at an image scale of the camera (shape = (h, w)),
        0 above the cut row (horizon, range) and where the window holds nothing (ground_to_image as in update)."""
        out = np.zeros(shape, dtype=np.float32)
        layer = self.layer()
        if layer is None:
            return out
        row = cut_row(camera, pose, self.config.max_range_m, self.config.horizon_margin_deg)
        h, w = shape
        first = int(math.ceil(row * h / camera.height))
        if first >= h:
            return out
        # image pixel (u + 0.5)/s -> cell coordinates; warp with the inverse map of output pixels
        s = np.diag([w / camera.width, h / camera.height, 1.0])
        img_to_cell = _translate(-0.5, -0.5) @ np.linalg.inv(self._cell_to_image(camera, pose, ground_to_image)) @ \
            np.linalg.inv(s) @ _translate(0.5, first + 0.5)
        out[first:] = cv2.warpPerspective(layer, img_to_cell, (w, h - first),
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                          borderMode=cv2.BORDER_CONSTANT)
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

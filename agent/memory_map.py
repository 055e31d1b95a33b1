"""Class-wise memory maps on the global tile grid (paper section IV), plus the joint layer, and the boost
rule by which a map's evidence raises a candidate's confidence.

Arrays in, arrays out: no I/O. A map is a UAV-centric, north-aligned window of global Web-Mercator
cells (shared.tiles) holding, per class, evidence in [0, 1] that decays with time.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from agent._kernels import add_clipped, map_patches, map_values, stamp_impulses
from shared.tiles import TileGrid, fill_cell_polygons

FloatArray = NDArray[np.float64]
STAMP_MODES = ("sum", "max")
#: How a stamp's radius follows the terrain (MemoryMapConfig.terrain_stamp).
TERRAIN_STAMP_MODES = ("shrink", "follow", "off")
#: The stamp radius's range over a terrain, as factors of radius_m.
TERRAIN_STAMP_LIMITS = (0.5, 2.0)
#: Lazy decay folds into the stored maps once the pending factor drops below this (every ~20 s at
#: a 1 s half-life); stored values then reach at most 1 / _MIN_SCALE, far inside float32's range.
_MIN_SCALE = 1e-6


@dataclass(frozen=True, slots=True)
class MemoryMapConfig:
    """Memory-map parameters, in metres and seconds so they hold across cameras and frame rates.

    Defaults are the best measured on the simulator (docs/memory-map.md); the paper's own values
    are radius 6 m and stamp "sum".

    window_m: edge of the UAV-centric square window (paper: c = 300 m); evidence outside is forgotten.
    radius_m: truncation radius of the Gaussian each box stamps (paper: 6 m; 4 m measured better).
    sigma_m: standard deviation of that Gaussian (default radius / 2).
    gain_per_s: evidence added per second of observation per unit confidence (the paper's s per
        frame = gain_per_s * frame interval; frame-rate independent: at 30 fps and 1.0 /s, s = 0.033).
    half_life_s: time for unrefreshed evidence to halve (the paper's forgetting factor per frame is
        phi = 0.5 ** (frame interval / half_life_s); 0.5 s chosen on the tuning domains, issue 15: 1 s
        before).
    max_step_s: the longest frame interval one update counts as observation time (a gap after
        dropped frames decays the map for the whole gap but adds one normal update).
    recentre_m: how far the UAV may drift from the window centre before the window is moved.
    stamp: "sum" (the paper: every pre-NMS box adds its Gaussian, so a detector that emits 30 boxes
        per object adds 30x the evidence) or "max" (per cell and frame the strongest box counts once:
        the evidence no longer depends on how many candidates a detector emits per object).
    terrain_stamp: over a terrain (--dem), how a box's stamp radius and sigma follow the ground: "shrink" (default)
        scales them by the terrain's footprint of the box's pixel against level ground's at the UAV's ground level
        (shared.terrain.footprint_scale) where that is smaller (a slope facing the camera, a rise ahead), down to
        half; "follow" also where it is larger, up to twice; "off" keeps radius_m everywhere. A flat DEM is
        unchanged in every mode.
    forget_per_frame, gain_per_frame: the paper's literal per-frame constants (phi and s), kept as a
        baseline: when set, the map decays by forget_per_frame at every frame (whatever time passed) and
        each box adds gain_per_frame * confidence, so the evidence depends on the frame rate (None: the
        per-second half_life_s and gain_per_s).
    """

    window_m: float = 300.0
    radius_m: float = 4.0
    sigma_m: float | None = None
    gain_per_s: float = 1.0
    half_life_s: float = 0.5
    max_step_s: float = 0.2
    recentre_m: float = 10.0
    stamp: str = "max"
    forget_per_frame: float | None = None
    gain_per_frame: float | None = None
    terrain_stamp: str = "shrink"

    def __post_init__(self) -> None:
        if self.forget_per_frame is not None and not (0.0 < self.forget_per_frame <= 1.0):
            raise ValueError(f"MemoryMapConfig.forget_per_frame must be in (0, 1], got {self.forget_per_frame!r}")
        if self.gain_per_frame is not None and not (math.isfinite(self.gain_per_frame) and self.gain_per_frame > 0):
            raise ValueError(f"MemoryMapConfig.gain_per_frame must be > 0, got {self.gain_per_frame!r}")
        if self.stamp not in STAMP_MODES:
            raise ValueError(f"MemoryMapConfig.stamp must be one of {', '.join(STAMP_MODES)}, got {self.stamp!r}")
        if self.terrain_stamp not in TERRAIN_STAMP_MODES:
            raise ValueError(f"MemoryMapConfig.terrain_stamp must be one of {', '.join(TERRAIN_STAMP_MODES)}, "
                             f"got {self.terrain_stamp!r}")
        for name in ("window_m", "radius_m", "gain_per_s", "half_life_s", "max_step_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"MemoryMapConfig.{name} must be a finite number > 0, got {value!r}")
        if self.sigma_m is not None and not (math.isfinite(self.sigma_m) and self.sigma_m > 0):
            raise ValueError(f"MemoryMapConfig.sigma_m must be > 0, got {self.sigma_m!r}")
        if not (math.isfinite(self.recentre_m) and 0 <= self.recentre_m < self.window_m / 2):
            raise ValueError(f"MemoryMapConfig.recentre_m must be in [0, window_m / 2), got {self.recentre_m!r}")

    @property
    def sigma(self) -> float:
        return self.radius_m / 2.0 if self.sigma_m is None else self.sigma_m

    def stamp_scales(self, footprint: ArrayLike) -> NDArray[np.float64] | None:
        """Per-box factors of the stamp radius from shared.terrain.footprint_scale (NaN: 1) by terrain_stamp; None
        when "off"."""
        if self.terrain_stamp == "off":
            return None
        lo, hi = TERRAIN_STAMP_LIMITS
        f = np.asarray(footprint, dtype=np.float64)
        return np.where(np.isfinite(f), np.clip(f, lo, 1.0 if self.terrain_stamp == "shrink" else hi), 1.0)

    def phi(self, dt_s: float) -> float:
        """Forgetting factor for an elapsed time dt_s (seconds)."""
        return 0.5 ** (max(dt_s, 0.0) / self.half_life_s)


def _points(values: ArrayLike) -> NDArray[np.float64]:
    """Coordinates as a contiguous (N,) float64 array (no copy when they already are one)."""
    return np.ascontiguousarray(values, dtype=np.float64).reshape(-1)


def _broadcast(*arrays: NDArray) -> tuple[NDArray, ...]:
    """np.broadcast_arrays, skipped (~5 us a call) when the shapes already agree."""
    if all(a.shape == arrays[0].shape for a in arrays):
        return arrays
    return tuple(np.broadcast_arrays(*arrays))


def gaussian_kernel_1d(radius_cells: int, sigma_cells: float) -> NDArray[np.float32]:
    """(2 * radius_cells + 1,) float32 Gaussian with peak 1, truncated at radius_cells."""
    x = np.arange(-radius_cells, radius_cells + 1, dtype=np.float64)
    return np.exp(-0.5 * (x / sigma_cells) ** 2).astype(np.float32)


class MemoryMap:
    """Per-class evidence maps over one moving window of global cells.

    Use per frame: advance(t, lat, lon) (decay + move the window), values_at(...) to boost with
    the map from before this frame, then add(...) with the original confidences.
    """

    def __init__(self, config: MemoryMapConfig | None = None, grid: TileGrid | None = None) -> None:
        self.config = config or MemoryMapConfig()
        self.grid = grid or TileGrid()
        self._maps: dict[str, NDArray[np.float32]] = {}
        self._gx0 = 0  # global cell of the window's north-west corner
        self._gy0 = 0
        self._size = 0  # window edge in cells
        self._cell_m = 0.0
        self._t: float | None = None
        self._kernel: tuple[int, NDArray[np.float32]] | None = None
        self._kernel_sigma = 0.0
        self._scaled_kernels: dict[int, NDArray[np.float32]] = {}
        # Lazy decay: the maps store evidence / _scale and advance() only shrinks _scale, instead of
        # multiplying every cell of every class each frame; the maps are renormalised when _scale
        # falls below _MIN_SCALE (float32 keeps its relative precision at any magnitude) or when a
        # caller asks for a whole layer.
        self._scale = 1.0

    # ------------------------------------------------------------------ state
    @property
    def classes(self) -> list[str]:
        return list(self._maps)

    @property
    def t(self) -> float | None:
        """Time (s) of the last advance(), or None before the first."""
        return self._t

    @property
    def origin(self) -> tuple[int, int]:
        """Global cell (gx0, gy0) of the window's north-west corner."""
        return self._gx0, self._gy0

    @property
    def size_cells(self) -> int:
        return self._size

    @property
    def cell_m(self) -> float:
        return self._cell_m

    def layer(self, cls: str) -> NDArray[np.float32] | None:
        """The (size, size) float32 map of a class (a view: do not modify), or None."""
        self._renormalise()
        return self._maps.get(cls)

    def reset(self) -> None:
        """Forget everything (e.g. at the start of another video)."""
        self._maps.clear()
        self._t = None
        self._size = 0
        self._scale = 1.0

    def _renormalise(self) -> None:
        """Fold the pending decay into the stored maps (stored values become true values)."""
        if self._scale != 1.0:
            scale = np.float32(self._scale)
            for m in self._maps.values():
                m *= scale
                np.minimum(m, 1.0, out=m)  # stored <= 1 / scale may round a hair above 1
            self._scale = 1.0

    # ------------------------------------------------------------------ time and window
    def advance(self, t: float, lat: float, lon: float) -> float:
        """Move to time t (s) with the UAV at (lat, lon): decay by the elapsed time, recentre.

        Returns the elapsed time in seconds (0 at the first call). Time going backwards is
        treated as no elapsed time.
        """
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t!r}")
        dt = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t if self._t is None else max(self._t, t)
        if dt > 0 and self._maps:
            phi = self.config.forget_per_frame
            self._scale *= self.config.phi(dt) if phi is None else phi
            if self._scale < _MIN_SCALE:
                self._renormalise()
        self._place_window(lat, lon)
        return dt

    def _place_window(self, lat: float, lon: float) -> None:
        cell_m = float(self.grid.cell_size_m(lat))
        gx, gy = self.grid.latlon_to_cell(lat, lon)
        size = int(math.ceil(self.config.window_m / cell_m))
        if self._size == 0 or abs(size - self._size) > max(2, self._size // 50):
            self._size, self._cell_m = size, cell_m
            self._set_origin(int(math.floor(gx)) - size // 2, int(math.floor(gy)) - size // 2, reset=True)
            return
        self._cell_m = cell_m
        cx, cy = self._gx0 + self._size / 2, self._gy0 + self._size / 2
        dx = self._wrap(float(gx) - cx)
        if math.hypot(dx, float(gy) - cy) * cell_m > self.config.recentre_m:
            self._set_origin(int(math.floor(gx)) - self._size // 2, int(math.floor(gy)) - self._size // 2)

    def _wrap(self, dx: float | NDArray) -> float | NDArray:
        cells = self.grid.world_cells
        return (dx + cells / 2) % cells - cells / 2

    def _set_origin(self, gx0: int, gy0: int, reset: bool = False) -> None:
        shift_x = int(self._wrap(gx0 - self._gx0))
        shift_y = gy0 - self._gy0
        self._gx0, self._gy0 = gx0 % self.grid.world_cells, gy0
        s = self._size
        if reset:
            self._scale = 1.0
        for cls, old in list(self._maps.items()):
            new = np.zeros((s, s), dtype=np.float32)
            if not reset and abs(shift_x) < s and abs(shift_y) < s and old.shape == new.shape:
                # new[r, c] = old[r + shift_y, c + shift_x] where both exist; the rest is forgotten.
                r0, r1 = max(0, -shift_y), min(s, s - shift_y)
                c0, c1 = max(0, -shift_x), min(s, s - shift_x)
                new[r0:r1, c0:c1] = old[r0 + shift_y:r1 + shift_y, c0 + shift_x:c1 + shift_x]
            self._maps[cls] = new

    def local_indices(
        self, gx: ArrayLike, gy: ArrayLike
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
        """Global cell coordinates (continuous or integer) -> window (row, col) and inside mask."""
        col = np.floor(self._wrap(np.asarray(gx, dtype=np.float64) - self._gx0)).astype(np.int64)
        row = np.floor(np.asarray(gy, dtype=np.float64) - self._gy0).astype(np.int64)
        inside = (col >= 0) & (col < self._size) & (row >= 0) & (row < self._size)
        return row, col, inside

    # ------------------------------------------------------------------ read and write
    def values_at(self, cls: str, gx: ArrayLike, gy: ArrayLike) -> NDArray[np.float32]:
        """Map values at global cells (N,) -> (N,) float32; 0 outside the window or for unseen classes."""
        gx_arr, gy_arr = _broadcast(np.atleast_1d(np.asarray(gx, dtype=np.float64)),
                                    np.atleast_1d(np.asarray(gy, dtype=np.float64)))
        m = self._maps.get(cls)
        if m is None or gx_arr.size == 0:
            return np.zeros(gx_arr.shape, dtype=np.float32)
        out = map_values(m, _points(gx_arr), _points(gy_arr), self._gx0, self._gy0, float(self.grid.world_cells),
                         self._scale)  # agent._kernels: ~10x the numpy indexing at 5,000 points
        return out.reshape(gx_arr.shape)

    def patches(self, cls: str, gx: ArrayLike, gy: ArrayLike, radius_cells: int) -> NDArray[np.float32]:
        """Evidence around global cells: (N, 2r+1, 2r+1) float32, patch[i, r + dy, r + dx] = value at cell
        (floor(gx[i]) + dx, floor(gy[i]) + dy); 0 outside the window or for an unseen class.
        """
        gx_arr = _points(gx)
        gy_arr = _points(gy)
        r = int(radius_cells)
        m = self._maps.get(cls)
        if m is None or not len(gx_arr) or self._size == 0:
            return np.zeros((len(gx_arr), 2 * r + 1, 2 * r + 1), dtype=np.float32)
        return map_patches(m, gx_arr, gy_arr, self._gx0, self._gy0, float(self.grid.world_cells), r, self._scale)

    def _kernel_for(self, radius: int | None = None) -> tuple[int, NDArray[np.float32]]:
        """(radius cells, kernel) of the configured stamp (built when its radius in cells changes), or of a
        terrain-scaled one of `radius` cells with sigma in proportion (cached until the configured one changes)."""
        base = max(1, int(round(self.config.radius_m / self._cell_m)))
        if self._kernel is None or self._kernel[0] != base:
            sigma_cells = self.config.sigma / self._cell_m
            self._kernel = (base, gaussian_kernel_1d(base, sigma_cells))
            self._kernel_sigma = sigma_cells  # what the scaled ones scale
            self._scaled_kernels = {}
        if radius is None or radius == base:
            return self._kernel
        kernel = self._scaled_kernels.get(radius)
        if kernel is None:
            kernel = self._scaled_kernels[radius] = gaussian_kernel_1d(radius, self._kernel_sigma * radius / base)
        return radius, kernel

    def add(self, cls: str, gx: ArrayLike, gy: ArrayLike, amplitudes: ArrayLike,
            radius_scale: ArrayLike | None = None) -> int:
        """Stamp a truncated Gaussian of peak `amplitude` at each global cell, then clip at 1.

        gx, gy, amplitudes: (N,). Points outside the window are ignored. All stamps are written as
        an impulse image over their bounding region and spread with one separable filter
        (cv2.sepFilter2D), which costs the same for 10 or 10,000 boxes. radius_scale: (N,) factors of
        the stamp radius and sigma per box in TERRAIN_STAMP_LIMITS (MemoryMapConfig.stamp_scales; None:
        1), rounded to whole cells: one filter per distinct radius; with stamp "max" the strongest box of
        a cell counts once, with its radius (ties: the first). Returns the number stamped.
        """
        if self._size == 0:
            raise RuntimeError("MemoryMap.add before advance(): the window is not placed yet")
        gx_arr, gy_arr, amp = _broadcast(np.asarray(gx, dtype=np.float64), np.asarray(gy, dtype=np.float64),
                                         np.asarray(amplitudes, dtype=np.float32))
        if radius_scale is not None:
            gx_arr, gy_arr, amp = gx_arr.reshape(-1), gy_arr.reshape(-1), amp.reshape(-1)
            lo, hi = TERRAIN_STAMP_LIMITS
            scale = np.broadcast_to(np.asarray(radius_scale, dtype=np.float64), gx_arr.shape)
            if not np.all((scale >= lo) & (scale <= hi)):
                raise ValueError(f"MemoryMap.add: radius_scale must lie in [{lo:g}, {hi:g}] (finite)")
            cells = np.maximum(1, np.round(self.config.radius_m * scale / self._cell_m)).astype(np.int64)
            groups = np.unique(cells)
            if len(groups) > 1 or (len(groups) and groups[0] != self._kernel_for()[0]):
                return self._add_by_radius(cls, gx_arr, gy_arr, amp, cells)
        return self._stamp(cls, gx_arr, gy_arr, amp, *self._kernel_for())

    def _add_by_radius(self, cls: str, gx: NDArray, gy: NDArray, amp: NDArray, cells: NDArray[np.int64]) -> int:
        """add() with a radius (cells) per point: one filter per radius; with stamp "max" only the strongest point
        of each window cell (as one filter would take it), so that a cell counts once across radii too."""
        dropped = 0
        if self.config.stamp == "max":
            with np.errstate(invalid="ignore"):  # NaN points: outside
                row, col, inside = self.local_indices(gx, gy)
            ok = np.flatnonzero(inside & np.isfinite(amp) & (amp > 0))
            order = ok[np.argsort(-amp[ok], kind="stable")]
            _, first = np.unique(row[order] * self._size + col[order], return_index=True)
            keep = np.sort(order[first])
            dropped = len(ok) - len(keep)
            gx, gy, amp, cells = gx[keep], gy[keep], amp[keep], cells[keep]
        stamped = dropped
        for r in np.unique(cells).tolist():
            sel = cells == r
            stamped += self._stamp(cls, gx[sel], gy[sel], amp[sel], *self._kernel_for(r))
        return stamped

    def _stamp(self, cls: str, gx_arr: NDArray, gy_arr: NDArray, amp: NDArray, radius: int,
               kernel: NDArray[np.float32]) -> int:
        # the impulses in stored units (max stamping commutes with the scaling), from agent._kernels
        impulses, r0, c0, stamped = stamp_impulses(
            _points(gx_arr), _points(gy_arr), np.ascontiguousarray(amp).reshape(-1), self._gx0, self._gy0,
            float(self.grid.world_cells), self._size, radius, self.config.stamp == "max", self._scale)
        if not stamped:
            return 0
        m = self._maps.get(cls)
        if m is None:
            m = self._maps[cls] = np.zeros((self._size, self._size), dtype=np.float32)
        spread = cv2.sepFilter2D(impulses, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_CONSTANT)
        roi = m[r0:r0 + impulses.shape[0], c0:c0 + impulses.shape[1]]
        add_clipped(roi, spread, np.float32(1.0 / self._scale))  # true values clip at 1
        return int(stamped)

    # ------------------------------------------------------------------ tiles
    def tiles(self, cls: str, *, min_value: float = 0.0) -> list[tuple[int, int, NDArray[np.float32]]]:
        """The window of a class cut into grid tiles: [(x, y, (n, n) float32)], cells outside 0.

        Every tile the window overlaps is returned (empty ones too: "covered, nothing seen") unless
        min_value > 0, which drops tiles whose maximum is below it.
        """
        m = self._maps.get(cls)
        n = self.grid.n
        if self._size == 0:
            return []
        out = []
        tx0, ty0 = self._gx0 // n, self._gy0 // n
        tx1, ty1 = (self._gx0 + self._size - 1) // n, (self._gy0 + self._size - 1) // n
        side = self.grid.tiles_per_side
        for ty in range(max(ty0, 0), min(ty1, side - 1) + 1):
            for tx in range(tx0, tx1 + 1):
                tile = np.zeros((n, n), dtype=np.float32)
                if m is not None:
                    # overlap of tile cells [tx*n, tx*n+n) with window cells [gx0, gx0+size)
                    gxa, gya = max(tx * n, self._gx0), max(ty * n, self._gy0)
                    gxb = min(tx * n + n, self._gx0 + self._size)
                    gyb = min(ty * n + n, self._gy0 + self._size)
                    part = tile[gya - ty * n:gyb - ty * n, gxa - tx * n:gxb - tx * n]
                    part[...] = m[gya - self._gy0:gyb - self._gy0, gxa - self._gx0:gxb - self._gx0]
                    if self._scale != 1.0:
                        part *= np.float32(self._scale)
                        np.minimum(part, 1.0, out=part)
                if min_value > 0 and tile.max() < min_value:
                    continue
                out.append((tx % side, ty, tile))
        return out


#: Camera footprints kept per other UAV (JointLayer.put_footprint); at 5 Hz, 12 s of them.
MAX_FOOTPRINTS_PER_UAV = 64


class JointLayer:
    """Latest joint (fused) tiles received from the fusion server, per class, with their times.

    values_at() reads them like a memory map; tiles older than ttl_s count as absent (0).
    It also keeps the other UAVs' camera footprints (from their state messages, put_footprint): the
    fusion server averages a cell over the UAVs whose footprints of the last cover_ttl_s hold it
    (the server's --ttl-s, 2 s by default), and others_cover() counts them, so a UAV can tell the
    cells where the joint value is its own evidence alone.
    """

    def __init__(self, grid: TileGrid | None = None, ttl_s: float = 3.0, cover_ttl_s: float = 2.0,
                 max_tiles: int = 1024) -> None:
        if not (math.isfinite(ttl_s) and ttl_s > 0):
            raise ValueError(f"ttl_s must be > 0, got {ttl_s!r}")
        if not (math.isfinite(cover_ttl_s) and cover_ttl_s > 0):
            raise ValueError(f"cover_ttl_s must be > 0, got {cover_ttl_s!r}")
        self.grid = grid or TileGrid()
        self.ttl_s = ttl_s
        self.cover_ttl_s = cover_ttl_s
        self.max_tiles = int(max_tiles)
        # least recently updated first: beyond max_tiles the oldest update is forgotten
        self._tiles: OrderedDict[tuple[str, int, int], tuple[NDArray[np.float32], float]] = OrderedDict()
        # uav -> [(vertices in global cell coordinates (M, 2), time)], oldest first
        self._footprints: dict[str, list[tuple[NDArray[np.float64], float]]] = {}

    def put_footprint(self, uav: str, footprint_latlon: ArrayLike, t: float) -> bool:
        """Record another UAV's camera footprint, ``[[lat, lon], ...]`` (M >= 3), seen at time t.

        Returns False (and stores nothing) for fewer than 3 vertices, another shape, non-finite or
        out-of-range coordinates, or a non-finite t.
        """
        if not math.isfinite(t):
            return False
        try:
            cells = self.grid.polygon_cells(footprint_latlon)
        except ValueError:  # beyond the map's latitude range
            return False
        if cells is None:
            return False
        prints = self._footprints.setdefault(uav, [])
        prints.append((cells, float(t)))
        del prints[:-MAX_FOOTPRINTS_PER_UAV]
        return True

    def others_cover(self, gx0: int, gy0: int, width: int, height: int, now: float) -> NDArray[np.uint8] | None:
        """How many other UAVs cover each cell of a block: (height, width) uint8, row = gy - gy0.

        A UAV covers the cells inside its footprints put within cover_ttl_s before now. None when no
        UAV has a footprint that fresh (nothing known: the caller falls back to an assumption).
        """
        out = np.zeros((max(int(height), 0), max(int(width), 0)), dtype=np.uint8)
        known = False
        for uav in list(self._footprints):
            # forget what is too old for good; footprints stamped after now wait for their time
            kept = self._footprints[uav] = [p for p in self._footprints[uav] if now - p[1] <= self.cover_ttl_s]
            prints = [cells for cells, t in kept if t <= now]
            if not kept:
                del self._footprints[uav]
            if prints:
                known = True
                out += fill_cell_polygons(prints, gx0, gy0, out.shape[1], out.shape[0])
        return out if known else None

    def __len__(self) -> int:
        return len(self._tiles)

    def update(self, cls: str, x: int, y: int, values: NDArray[np.float32], t: float) -> None:
        """Store a joint tile (n, n) float32 in [0, 1] received at time t (seconds); beyond
        max_tiles the least recently updated tile is forgotten (memory: 256 KiB a tile)."""
        n = self.grid.n
        if values.shape != (n, n):
            raise ValueError(f"joint tile must be ({n}, {n}), got {values.shape}")
        key = (cls, int(x), int(y))
        self._tiles[key] = (values.astype(np.float32, copy=False), float(t))
        self._tiles.move_to_end(key)
        while len(self._tiles) > self.max_tiles:
            self._tiles.popitem(last=False)

    def prune(self, now: float) -> int:
        """Drop tiles older than ttl_s; returns how many were dropped."""
        old = [k for k, (_, t) in self._tiles.items() if now - t > self.ttl_s]
        for k in old:
            del self._tiles[k]
        return len(old)

    def values_at(self, cls: str, gx: ArrayLike, gy: ArrayLike, now: float) -> NDArray[np.float32]:
        """Joint values at global cells (N,) -> (N,) float32; 0 where no fresh tile exists."""
        gx_i = np.floor(np.atleast_1d(np.asarray(gx, dtype=np.float64))).astype(np.int64)
        gy_i = np.floor(np.atleast_1d(np.asarray(gy, dtype=np.float64))).astype(np.int64)
        out = np.zeros(gx_i.shape, dtype=np.float32)
        if not self._tiles or gx_i.size == 0:
            return out
        n = self.grid.n
        tx, ty = gx_i // n, gy_i // n
        keys = tx * (1 << 32) + ty
        for key in np.unique(keys):
            x, y = int(key >> 32), int(key & 0xFFFFFFFF)
            entry = self._tiles.get((cls, x, y))
            if entry is None or now - entry[1] > self.ttl_s:
                continue
            sel = keys == key
            out[sel] = entry[0][gy_i[sel] - y * n, gx_i[sel] - x * n]
        return out

    def window(self, cls: str, gx0: int, gy0: int, width: int, height: int, now: float) -> NDArray[np.float32]:
        """Joint values of a block of global cells: (height, width) float32, row = gy - gy0, col = gx - gx0.

        0 where no fresh tile of the class exists. The block is assembled from whole-tile slices, so it
        costs a copy of the block (used by agent.joint_detections to look for peaks in a view).
        """
        out = np.zeros((max(int(height), 0), max(int(width), 0)), dtype=np.float32)
        if out.size == 0 or not self._tiles:
            return out
        n = self.grid.n
        gx1, gy1 = gx0 + out.shape[1], gy0 + out.shape[0]
        for ty in range(gy0 // n, (gy1 - 1) // n + 1):
            for tx in range(gx0 // n, (gx1 - 1) // n + 1):
                entry = self._tiles.get((cls, tx, ty))
                if entry is None or now - entry[1] > self.ttl_s:
                    continue
                x_lo, x_hi = max(gx0, tx * n), min(gx1, (tx + 1) * n)
                y_lo, y_hi = max(gy0, ty * n), min(gy1, (ty + 1) * n)
                out[y_lo - gy0:y_hi - gy0, x_lo - gx0:x_hi - gx0] = \
                    entry[0][y_lo - ty * n:y_hi - ty * n, x_lo - tx * n:x_hi - tx * n]
        return out


def boost_scores(conf: NDArray, evidence: NDArray | np.floating, boost_mode: str, boost_weight: float,
                 logodds_scale: float) -> NDArray:
    """Boosted confidences of candidates with confidence `conf` at cells holding memory `evidence` (or one value).

    "add" (the paper): c + w p; "logodds": sigmoid(logit(c) + w * logodds_scale * p), c clipped to
    [1e-6, 1 - 1e-6]. Same dtype as the inputs.
    """
    if boost_mode == "add":
        return conf + boost_weight * evidence
    cc = np.clip(conf, 1e-6, 1 - 1e-6)
    logit = np.log(cc / (1 - cc)) + boost_weight * logodds_scale * evidence
    return 1.0 / (1.0 + np.exp(-logit))

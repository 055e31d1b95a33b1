"""Terrain under the camera: a DEM on a lat/lon grid, the elevation the UAV's heights are measured from, and
vectorised ray-terrain intersection (the `terrain=` of `shared.geo`'s projections; docs/geometry.md, Terrain).

Pure numpy, no file I/O: `agent.dem` reads GeoTIFF, SRTM .hgt and .npz files into an `ElevationGrid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.geo import Camera, Pose, meridian_radius_m, pixel_rays_enu, prime_vertical_radius_m

__all__ = ["BLOCK_CELLS", "ElevationGrid", "Terrain", "edge_alternatives", "effective_height_m", "footprint_scale",
           "pixel_to_terrain"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

#: Edge of the coarse blocks (grid cells) whose height extremes let rays skip the air above the terrain.
BLOCK_CELLS = 4
#: Steps (one grid cell each) of the first march block; later blocks take FOLLOW_STEPS.
FIRST_STEPS = 2
FOLLOW_STEPS = 8
#: Rays marched together (their working arrays, ~50 of CHUNK_RAYS x 3 x steps floats, stay in the caches).
CHUNK_RAYS = 1024


def _finite(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True, slots=True, eq=False)
class ElevationGrid:
    """Heights on a north-up lat/lon grid: a DEM, bilinear between the sample points.

    heights_m: (rows, cols) float64, >= 2 x 2, metres above the DEM's datum (SRTM: the EGM96 geoid); NaN =
        no data. Row r lies at latitude lat0_deg + r * lat_step_deg, column c at lon0_deg + c * lon_step_deg
        (sample points: the centres of a GeoTIFF's pixels, the corners of an SRTM tile's).
    lat_step_deg: non-zero (negative when row 0 is the northernmost); lon_step_deg > 0 (west to east).
    Compared by identity (eq=False): grids are large and shared, not values.
    """

    heights_m: FloatArray
    lat0_deg: float
    lon0_deg: float
    lat_step_deg: float
    lon_step_deg: float
    _block_max: FloatArray = field(init=False, repr=False)
    _block_min: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        try:
            heights = np.array(self.heights_m, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("ElevationGrid.heights_m must be a 2-D array of numbers") from None
        if heights.ndim != 2 or heights.shape[0] < 2 or heights.shape[1] < 2:
            raise ValueError(f"ElevationGrid.heights_m must be a 2-D array of at least 2 x 2, got shape "
                             f"{heights.shape}")
        if np.isinf(heights).any():
            raise ValueError("ElevationGrid.heights_m must be finite or NaN (no data), found inf")
        if np.isnan(heights).all():
            raise ValueError("ElevationGrid.heights_m holds no data (all NaN)")
        heights.setflags(write=False)
        object.__setattr__(self, "heights_m", heights)
        lat0 = _finite("ElevationGrid.lat0_deg", self.lat0_deg)
        lon0 = _finite("ElevationGrid.lon0_deg", self.lon0_deg)
        dlat = _finite("ElevationGrid.lat_step_deg", self.lat_step_deg)
        dlon = _finite("ElevationGrid.lon_step_deg", self.lon_step_deg)
        if dlat == 0:
            raise ValueError("ElevationGrid.lat_step_deg must be non-zero")
        if dlon <= 0:
            raise ValueError(f"ElevationGrid.lon_step_deg must be > 0 (columns west to east), got {dlon!r}")
        rows, cols = heights.shape
        for name, value in (("latitude", lat0), ("latitude", lat0 + (rows - 1) * dlat)):
            if not -90.0 <= value <= 90.0:
                raise ValueError(f"ElevationGrid rows reach {name} {value!r}, outside [-90, 90]")
        if not (-180.0 <= lon0 and lon0 + (cols - 1) * dlon <= 360.0):
            raise ValueError(f"ElevationGrid columns span longitudes {lon0!r}..{lon0 + (cols - 1) * dlon!r}")
        for name, value in (("lat0_deg", lat0), ("lon0_deg", lon0), ("lat_step_deg", dlat), ("lon_step_deg", dlon)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_block_max", _block_extreme(heights, np.fmax))
        object.__setattr__(self, "_block_min", _block_extreme(heights, np.fmin))

    def __repr__(self) -> str:
        rows, cols = self.heights_m.shape
        return (f"ElevationGrid({rows}x{cols}, lat0={self.lat0_deg:.6f}, lon0={self.lon0_deg:.6f}, "
                f"steps=({self.lat_step_deg:.3g}, {self.lon_step_deg:.3g}) deg, "
                f"{np.nanmin(self.heights_m):.1f}..{np.nanmax(self.heights_m):.1f} m)")

    @classmethod
    def from_local(cls, heights_m: ArrayLike, origin_lat: float, origin_lon: float, *, west_m: float,
                   north_m: float, cell_m: float) -> ElevationGrid:
        """A grid laid out in local metres around (origin_lat, origin_lon): row 0 at north_m, column 0 at
        west_m (east of the origin, metres; negative = west), square cells of cell_m metres, rows going
        south. Exact for `shared.geo.local_to_latlon` around the origin (the tangent plane is linear)."""
        cell = _finite("cell_m", cell_m)
        if cell <= 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m!r}")
        m = float(meridian_radius_m(origin_lat))
        p = float(prime_vertical_radius_m(origin_lat)) * math.cos(math.radians(origin_lat))
        return cls(np.asarray(heights_m, dtype=np.float64),
                   lat0_deg=origin_lat + math.degrees(_finite("north_m", north_m) / m),
                   lon0_deg=origin_lon + math.degrees(_finite("west_m", west_m) / p),
                   lat_step_deg=-math.degrees(cell / m), lon_step_deg=math.degrees(cell / p))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the sample points."""
        rows, cols = self.heights_m.shape
        return int(rows), int(cols)

    def bounds(self) -> tuple[float, float, float, float]:
        """(lat_min, lat_max, lon_min, lon_max) of the sample points, degrees."""
        rows, cols = self.shape
        lat1 = self.lat0_deg + (rows - 1) * self.lat_step_deg
        return (min(self.lat0_deg, lat1), max(self.lat0_deg, lat1), self.lon0_deg,
                self.lon0_deg + (cols - 1) * self.lon_step_deg)

    def cell_size_m(self) -> tuple[float, float]:
        """(east, north) spacing of the samples in metres at the grid's middle latitude."""
        lat = 0.5 * (self.bounds()[0] + self.bounds()[1])
        m = float(meridian_radius_m(lat))
        p = float(prime_vertical_radius_m(lat)) * math.cos(math.radians(lat))
        return math.radians(self.lon_step_deg) * p, math.radians(abs(self.lat_step_deg)) * m

    def height_at(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """Bilinear height (metres above the datum) at lat/lon degrees, any shape; NaN off the grid or where
        a neighbouring sample has no data."""
        la = np.asarray(lat, dtype=np.float64)
        lo = np.asarray(lon, dtype=np.float64)
        return self.at_grid((lo - self.lon0_deg) / self.lon_step_deg, (la - self.lat0_deg) / self.lat_step_deg)

    def at_grid(self, col: ArrayLike, row: ArrayLike) -> FloatArray:
        """Bilinear height at fractional grid coordinates (column, row of the sample points), any shape;
        NaN outside [0, cols - 1] x [0, rows - 1] or next to a sample without data."""
        c, r = np.broadcast_arrays(np.asarray(col, dtype=np.float64), np.asarray(row, dtype=np.float64))
        rows, cols = self.shape
        with np.errstate(invalid="ignore"):
            inside = (c >= 0) & (c <= cols - 1) & (r >= 0) & (r <= rows - 1)
        i = np.clip(np.floor(np.where(inside, c, 0.0)), 0, cols - 2).astype(np.int64)
        j = np.clip(np.floor(np.where(inside, r, 0.0)), 0, rows - 2).astype(np.int64)
        z00, z10, z01, z11 = _corners(self.heights_m, i, j)
        u, v = c - i, r - j
        z = z00 + (z10 - z00) * u + (z01 - z00) * v + (z00 - z10 - z01 + z11) * u * v
        return np.where(inside, z, np.nan)

    def extremes(self, col_lo: float, col_hi: float, row_lo: float, row_hi: float) -> tuple[float, float]:
        """(lowest, highest) height of the samples that grid coordinates [col_lo, col_hi] x [row_lo, row_hi]
        interpolate (from the block extremes, so possibly a block wider); NaN when none has data."""
        bmax, bmin = self._block_max, self._block_min
        b0 = max(0, int(math.floor(col_lo / BLOCK_CELLS)))
        b1 = min(bmax.shape[1] - 1, int(math.floor(col_hi / BLOCK_CELLS)))
        a0 = max(0, int(math.floor(row_lo / BLOCK_CELLS)))
        a1 = min(bmax.shape[0] - 1, int(math.floor(row_hi / BLOCK_CELLS)))
        if b1 < b0 or a1 < a0:
            return math.nan, math.nan
        hi = bmax[a0:a1 + 1, b0:b1 + 1]
        if np.isnan(hi).all():
            return math.nan, math.nan
        return float(np.nanmin(bmin[a0:a1 + 1, b0:b1 + 1])), float(np.nanmax(hi))


def _block_extreme(heights: FloatArray, op: np.ufunc) -> FloatArray:
    """Per block of BLOCK_CELLS x BLOCK_CELLS cells, the max (op=np.fmax) or min (np.fmin) of the samples it
    interpolates, its far edges included (so every bilinear patch inside lies within it); NaN: no data."""
    k = BLOCK_CELLS
    rows, cols = heights.shape
    nr, nc = -(-(rows - 1) // k), -(-(cols - 1) // k)
    padded = np.full((nr * k + 1, nc * k + 1), np.nan)
    padded[:rows, :cols] = heights
    along = op(op.reduceat(padded[:-1], np.arange(0, nr * k, k), axis=0), padded[k::k])
    return np.asarray(op(op.reduceat(along[:, :-1], np.arange(0, nc * k, k), axis=1), along[:, k::k]))


def _corners(heights: FloatArray, i: IntArray, j: IntArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Heights at (j, i), (j, i + 1), (j + 1, i), (j + 1, i + 1) for index arrays of any one shape."""
    cols = heights.shape[1]
    flat = heights.reshape(-1)
    k = j * cols + i
    return flat.take(k), flat.take(k + 1), flat.take(k + cols), flat.take(k + cols + 1)


@dataclass(frozen=True, slots=True, eq=False)
class Terrain:
    """A DEM and the elevation the pose heights are measured from: `shared.geo`'s `terrain=`.

    grid: the DEM (heights above its datum).
    takeoff_elevation_m: the DEM elevation of the take-off point, for telemetry heights above take-off (DJI
        rel_alt, SeaDronesSee altitude); 0 for heights above the datum (abs_alt above sea level). None: the
        heights are above the DEM's ground directly below the UAV, frame by frame.
    The camera is at elevation (takeoff_elevation_m or the DEM below the UAV) + pose.height_m; the local
    frame's up = 0 is that reference elevation, so a flat DEM at it gives the flat model's results.
    """

    grid: ElevationGrid
    takeoff_elevation_m: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.grid, ElevationGrid):
            raise ValueError(f"Terrain.grid must be an ElevationGrid, got {type(self.grid).__name__}")
        if self.takeoff_elevation_m is not None:
            object.__setattr__(self, "takeoff_elevation_m",
                               _finite("Terrain.takeoff_elevation_m", self.takeoff_elevation_m))

    def with_takeoff_elevation(self, elevation_m: float | None) -> Terrain:
        """The same DEM with another reference (see takeoff_elevation_m)."""
        return Terrain(self.grid, elevation_m)

    def height_at(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """DEM height (metres above its datum) at lat/lon degrees; NaN off the DEM."""
        return self.grid.height_at(lat, lon)

    def base_elevation_m(self, pose: Pose) -> float:
        """Elevation of the local frame's up = 0 for this pose: the take-off's, or the DEM's below the UAV
        (NaN when the UAV is off the DEM)."""
        if self.takeoff_elevation_m is not None:
            return self.takeoff_elevation_m
        return float(self.grid.height_at(pose.lat, pose.lon))

    def _affine(self, pose: Pose) -> tuple[float, float, float, float]:
        """(c0, ce, r0, rn): grid column = c0 + ce * east_m, row = r0 + rn * north_m in the pose's local
        frame (the radii `shared.geo.local_to_latlon` uses)."""
        g = self.grid
        m = float(meridian_radius_m(pose.lat))
        p = float(prime_vertical_radius_m(pose.lat)) * math.cos(math.radians(pose.lat))
        return ((pose.lon - g.lon0_deg) / g.lon_step_deg, math.degrees(1.0 / p) / g.lon_step_deg,
                (pose.lat - g.lat0_deg) / g.lat_step_deg, math.degrees(1.0 / m) / g.lat_step_deg)

    def up_m(self, east_m: ArrayLike, north_m: ArrayLike, pose: Pose) -> FloatArray:
        """(N,) terrain height above the pose's reference at local east/north metres; NaN off the DEM."""
        c0, ce, r0, rn = self._affine(pose)
        e = np.asarray(east_m, dtype=np.float64)
        n = np.asarray(north_m, dtype=np.float64)
        return self.grid.at_grid(c0 + ce * e, r0 + rn * n) - self.base_elevation_m(pose)

    def gradient(self, east_m: ArrayLike, north_m: ArrayLike, pose: Pose) -> tuple[FloatArray, FloatArray]:
        """(N,) slopes d up / d east and d up / d north (metres per metre) of the bilinear surface at local points
        of the pose's frame; NaN off the DEM."""
        c0, ce, r0, rn = self._affine(pose)
        rows, cols = self.grid.shape
        c = c0 + ce * np.asarray(east_m, dtype=np.float64)
        r = r0 + rn * np.asarray(north_m, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            inside = (c >= 0) & (c <= cols - 1) & (r >= 0) & (r <= rows - 1)
        i = np.clip(np.floor(np.where(inside, c, 0.0)), 0, cols - 2).astype(np.int64)
        j = np.clip(np.floor(np.where(inside, r, 0.0)), 0, rows - 2).astype(np.int64)
        z00, z10, z01, z11 = _corners(self.grid.heights_m, i, j)
        d = z00 - z10 - z01 + z11
        d_col = z10 - z00 + d * (r - j)
        d_row = z01 - z00 + d * (c - i)
        return np.where(inside, d_col * ce, np.nan), np.where(inside, d_row * rn, np.nan)

    def intersect_rays(self, rays_enu: ArrayLike, pose: Pose, max_range_m: float | None = None
                       ) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
        """First point where each ray from the camera meets the terrain (bilinear between DEM samples).

        rays_enu: (N, 3) unit directions in east/north/up (`shared.geo.pixel_rays_enu`).
        max_range_m: hits farther than this horizontally from the UAV do not count.
        Returns east_m, north_m, up_m (N,) float64 in the pose's local frame and valid (N,) bool. valid is
        False, and the coordinates NaN, where the ray meets no terrain: it points above every height in reach
        (the horizon), leaves the DEM or max_range_m first, crosses samples without data first, or the camera
        is below the ground. Exact to float rounding for the bilinear surface (each cell's part of a ray is
        solved as a quadratic); the earth's curvature is not modelled (8 cm drop at 1 km).
        """
        rays = np.asarray(rays_enu, dtype=np.float64).reshape(-1, 3)
        n = len(rays)
        out_t = np.full(n, np.nan)
        base = self.base_elevation_m(pose)
        reach = math.inf if max_range_m is None else float(max_range_m)
        rows, cols = self.grid.shape
        c0, ce, r0, rn = self._affine(pose)
        h = float(pose.height_m)
        if n and math.isfinite(base) and reach > 0:
            col_r, row_r = reach * abs(ce), reach * abs(rn)
            low, high = self.grid.extremes(max(c0 - col_r, 0.0), min(c0 + col_r, cols - 1.0),
                                           max(r0 - row_r, 0.0), min(r0 + row_r, rows - 1.0))
            below = float(self.grid.at_grid(c0, r0)) - base  # NaN when the UAV is off the DEM
            if math.isfinite(high) and not below >= h:  # a camera underground sees nothing
                marcher = _Marcher(self.grid, base, h, c0, ce, r0, rn)
                for k in range(0, n, CHUNK_RAYS):  # chunks whose working arrays stay in the CPU's caches
                    marcher.run(rays[k:k + CHUNK_RAYS], high - base, low - base, reach, out_t[k:k + CHUNK_RAYS])
        valid = np.isfinite(out_t)
        east, north, up = (rays[:, k] * out_t for k in range(3))
        up = up + h
        if max_range_m is not None:
            with np.errstate(invalid="ignore"):
                valid &= np.hypot(east, north) <= reach
            east, north, up = (np.where(valid, a, np.nan) for a in (east, north, up))
        return east, north, up, valid


class _Marcher:
    """Ray parameters t (metres along unit rays from the camera) of the first terrain hits, for one pose.

    The ray is marched cell by cell in grid coordinates: first over the coarse blocks (BLOCK_CELLS) to skip
    the air above every block's highest sample, then over the DEM's cells, where each piece of ray inside
    one cell meets the bilinear patch at the roots of a quadratic in t. Vectorised over rays, in blocks of
    steps (few at first: most rays are decided early); rays leave the working set once decided.
    """

    def __init__(self, grid: ElevationGrid, base: float, h: float, c0: float, ce: float, r0: float,
                 rn: float) -> None:
        self.grid, self.base, self.h = grid, base, h
        self.c0, self.ce, self.r0, self.rn = c0, ce, r0, rn

    def run(self, rays: FloatArray, z_high: float, z_low: float, reach: float, out_t: FloatArray) -> None:
        rows, cols = self.grid.shape
        h = self.h
        rx, ry, rz = rays[:, 0], rays[:, 1], rays[:, 2]
        dc, dr = self.ce * rx, self.rn * ry
        horiz = np.hypot(rx, ry)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # the part of each ray between the highest and the lowest height in reach ...
            t_lo = np.where(h > z_high, np.where(rz < 0, (z_high - h) / rz, np.inf), 0.0)
            # below z_low going down, above z_high going up, nothing is hit
            t_hi = np.where(rz < 0, (z_low - h) / rz, np.where(rz > 0, (z_high - h) / rz, np.inf))
            t_hi = np.minimum(t_hi, np.where(horiz > 0, reach / horiz, np.inf))
            # ... and over the DEM (outside it the ground is unknown: a ray that starts there sees nothing)
            t_in_c, t_out_c = _slab(self.c0, dc, cols - 1.0)
            t_in_r, t_out_r = _slab(self.r0, dr, rows - 1.0)
        t_hi = np.minimum(t_hi, np.minimum(t_out_c, t_out_r))
        t_in = np.maximum(t_in_c, t_in_r)
        live = np.isfinite(t_lo) & (t_lo <= t_hi) & (t_in <= t_lo + 1e-9 * (1.0 + np.abs(t_lo)))
        idx = np.flatnonzero(live)
        if not len(idx):
            return
        t_start = t_lo[idx]
        # spans of more than a block skip the air above the blocks first (on gentle terrain most are shorter)
        with np.errstate(invalid="ignore"):
            long = np.flatnonzero((t_hi[idx] - t_start) * np.maximum(np.abs(dc[idx]), np.abs(dr[idx])) > BLOCK_CELLS)
        if len(long):
            sel = idx[long]
            t_start[long] = self._skip_air(t_start[long], t_hi[sel], dc[sel], dr[sel], rz[sel])
        keep = np.isfinite(t_start)
        idx = idx[keep]
        self._march(idx, t_start[keep], t_hi[idx], dc[idx], dr[idx], rz[idx], out_t)

    def _skip_air(self, t0: FloatArray, t1: FloatArray, dc: FloatArray, dr: FloatArray,
                  rz: FloatArray) -> FloatArray:
        """Where each ray first enters a block whose highest sample reaches it (inf: it never does)."""
        k = float(BLOCK_CELLS)
        bmax = self.grid._block_max
        nbr, nbc = bmax.shape
        flat_max = bmax.reshape(-1)
        result = np.full(len(t0), np.inf)
        act = np.arange(len(t0))
        start = t0.copy()
        steps = 4
        while len(act):
            sa, sb, i, j = _segments(start[act], t1[act], self.c0 / k, dc[act] / k, self.r0 / k, dr[act] / k, steps)
            inside = (i >= 0) & (i < nbc) & (j >= 0) & (j < nbr)
            top = flat_max.take(np.where(inside, j * nbc + i, 0).astype(np.int64)) - self.base
            a_rz = rz[act, None]
            ray_low = self.h + a_rz * np.where(a_rz < 0, sb, sa)
            reached = ~inside | np.isnan(top) | (ray_low <= top + 1e-6)  # a margin for rounding: safe side
            first = np.argmax(reached, axis=1)
            rows_a = np.arange(len(act))
            found = reached[rows_a, first]
            result[act[found]] = sa[rows_a[found], first[found]]
            nxt = sb[:, -1]
            go = ~found & (nxt < t1[act])
            start[act[go]] = nxt[go]
            act = act[go]
            steps = 16
        return result

    def _march(self, idx: IntArray, t0: FloatArray, t1: FloatArray, dc: FloatArray, dr: FloatArray,
               rz: FloatArray, out_t: FloatArray) -> None:
        """Per ray, the first root of (ray height - terrain height) over [t0, t1] into out_t[idx] (NaN where
        the ray meets missing data or leaves the DEM first, or has no root)."""
        rows, cols = self.grid.shape
        flat = self.grid.heights_m.reshape(-1)
        act = np.arange(len(idx))
        start = t0.copy()
        steps = FIRST_STEPS
        while len(act):
            a_dc, a_dr, a_rz = dc[act], dr[act], rz[act]
            sa, sb, i, j = _segments(start[act], t1[act], self.c0, a_dc, self.r0, a_dr, steps)
            # a piece at the DEM's last row or column belongs to the cell before it (and one rounded just
            # outside the span's first cell to that cell: spans lie on the DEM)
            i = np.clip(i, 0.0, cols - 2.0, where=(i == -1.0) | (i == cols - 1.0), out=i)
            j = np.clip(j, 0.0, rows - 2.0, where=(j == -1.0) | (j == rows - 1.0), out=j)
            inside = (i >= 0) & (i <= cols - 2) & (j >= 0) & (j <= rows - 2)
            kk = np.where(inside, j * cols + i, 0.0).astype(np.int64)
            z00, z10, z01, z11 = flat.take(kk), flat.take(kk + 1), flat.take(kk + cols), flat.take(kk + cols + 1)
            # the cell's patch: z = a + b u + c v + d u v, u and v its fractional column and row
            b, c, d = z10 - z00, z01 - z00, z00 - z10 - z01 + z11
            du, dv = a_dc[:, None], a_dr[:, None]
            u0 = self.c0 + du * sa - i
            v0 = self.r0 + dv * sa - j
            a2 = -d * du * dv
            a1 = a_rz[:, None] - (b * du + c * dv + d * (u0 * dv + v0 * du))
            a0 = (self.h + self.base) + a_rz[:, None] * sa - (z00 + b * u0 + c * v0 + d * u0 * v0)
            tau = _first_root(a0, a1, a2, sb - sa)
            known = inside & np.isfinite(a0)
            event = ~known | np.isfinite(tau)
            first = np.argmax(event, axis=1)
            rows_a = np.arange(len(act))
            found = event[rows_a, first]
            hit = found & known[rows_a, first]
            out_t[idx[act[hit]]] = sa[rows_a[hit], first[hit]] + tau[rows_a[hit], first[hit]]
            nxt = sb[:, -1]
            go = ~found & (nxt < t1[act])
            start[act[go]] = nxt[go]
            act = act[go]
            steps = FOLLOW_STEPS


def _slab(p0: float, dp: FloatArray, hi: float) -> tuple[FloatArray, FloatArray]:
    """Ray parameters where p0 + dp * t enters and leaves [0, hi] ((-inf, inf) for dp = 0 inside it)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ta = (0.0 - p0) / dp
        tb = (hi - p0) / dp
    inside = (p0 >= 0.0) & (p0 <= hi)
    t_in = np.where(dp == 0, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    t_out = np.where(dp == 0, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return t_in, t_out


def _segments(t0: FloatArray, t1: FloatArray, c0: float, dc: FloatArray, r0: float, dr: FloatArray,
              steps: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The next `steps` steps of rays c = c0 + dc t, r = r0 + dr t over unit grid cells, cut where they cross
    a column or a row line, so each piece lies in one cell.

    t0, t1: (N,) start and end of each ray's span; a step advances one cell along the faster axis (the
    whole span for a vertical ray). Returns sa, sb (N, 3 * steps) pieces in order (empty ones past t1) and
    the cell of each piece, i (column) and j (row), (N, 3 * steps) whole floats.
    """
    n = len(t0)
    sa = np.empty((n, steps, 3))
    sb = np.empty((n, steps, 3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        step = 1.0 / np.maximum(np.abs(dc), np.abs(dr))
        k = np.arange(steps, dtype=np.float64)
        ta = t0[:, None] + np.where(k == 0, 0.0, k * step[:, None])
        np.minimum(ta, t1[:, None], out=ta)
        tb = np.minimum(ta + step[:, None], t1[:, None])
        cross = []
        for p0, dp in ((c0, dc[:, None]), (r0, dr[:, None])):
            pa = p0 + dp * ta
            line = np.where(dp > 0, np.floor(pa) + 1.0, np.ceil(pa) - 1.0)
            tc = (line - p0) / dp  # inf or NaN for dp = 0: no crossing
            cross.append(np.clip(np.where(tc < tb, tc, tb), ta, tb))
    np.minimum(cross[0], cross[1], out=sa[:, :, 1])
    np.maximum(cross[0], cross[1], out=sa[:, :, 2])
    sa[:, :, 0] = ta
    sb[:, :, :2] = sa[:, :, 1:]
    sb[:, :, 2] = tb
    sa2, sb2 = sa.reshape(n, -1), sb.reshape(n, -1)
    tm = 0.5 * (sa2 + sb2)
    big = 2.0**40  # far outside any grid
    i = np.clip(np.floor(c0 + dc[:, None] * tm), -big, big)
    j = np.clip(np.floor(r0 + dr[:, None] * tm), -big, big)
    return sa2, sb2, i, j


def _first_root(a0: FloatArray, a1: FloatArray, a2: FloatArray, length: FloatArray) -> FloatArray:
    """Smallest tau in [0, length] with a0 + a1 tau + a2 tau^2 = 0 (0 where a0 <= 0 already), else NaN."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        disc = a1 * a1 - 4.0 * a2 * a0
        sq = np.sqrt(np.maximum(disc, 0.0))
        q = -0.5 * (a1 + np.copysign(sq, a1))  # the cancellation-free pair of roots: a0 / q and q / a2
        r1 = a0 / q
        r2 = q / a2
        tol = 1e-12 * (1.0 + length)
        ok1 = (disc >= 0) & (r1 >= -tol) & (r1 <= length + tol)
        ok2 = (disc >= 0) & (r2 >= -tol) & (r2 <= length + tol)
        tau = np.minimum(np.where(ok1, r1, np.inf), np.where(ok2, r2, np.inf))
    tau = np.where(np.isfinite(tau), np.clip(tau, 0.0, length), np.nan)
    tau = np.where(a0 <= 0.0, 0.0, tau)
    return np.where(np.isfinite(tau) & np.isfinite(a0), tau, np.nan)


def pixel_to_terrain(uv: ArrayLike, camera: Camera, pose: Pose, terrain: Terrain, *,
                     max_range_m: float | None = None) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Pixels to their first terrain point: `shared.geo.pixel_to_local(..., terrain=)` with the height too.

    uv: (N, 2) pixels. Returns east_m, north_m, up_m (N,) float64 in the pose's local frame (up above the
    reference the pose's height is measured from, see Terrain) and valid (N,) bool; NaN where not valid.
    """
    return terrain.intersect_rays(pixel_rays_enu(uv, camera, pose), pose, max_range_m)


def _view_terms(east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike, pose: Pose, terrain: Terrain,
                gradient: tuple[FloatArray, FloatArray] | None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """drop (the camera's height above each point), |g_e east + g_n north + drop| (the camera's distance from the
    tangent plane times sqrt(1 + |g|^2)) and sqrt(1 + |g|^2), with the gradient g given or from the terrain."""
    e = np.asarray(east_m, dtype=np.float64)
    n = np.asarray(north_m, dtype=np.float64)
    drop = pose.height_m - np.asarray(up_m, dtype=np.float64)
    gx, gy = terrain.gradient(e, n, pose) if gradient is None else gradient
    return drop, np.abs(gx * e + gy * n + drop), np.sqrt(1.0 + gx * gx + gy * gy)


def effective_height_m(east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike, pose: Pose,
                       terrain: Terrain, gradient: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """(N,) the camera height above flat ground that gives the same along-ray sensitivity at each terrain point:
    slant range times the sine of the angle between the line of sight and the surface there, i.e. the camera's
    distance from the terrain's tangent plane at the point.

    A ray's ground point moves by slant / sin(that angle) per radian of pitch or pixel error; the flat model's
    slant^2 / h is that with h = slant sin(depression). Error models written for flat ground (the tracker's
    measurement covariance and pose-correction Jacobian) stay right on a terrain with h replaced by this:
    smaller where the ray grazes a slope facing away, larger on one facing the camera. NaN where not known.
    gradient: the terrain's (g_e, g_n) at the points when already known (Terrain.gradient).
    """
    # slant * |unit line of sight . unit surface normal|, the normal along (-gx, -gy, 1)
    _, plane, tilt = _view_terms(east_m, north_m, up_m, pose, terrain, gradient)
    return np.asarray(plane / tilt, dtype=np.float64)


def footprint_scale(east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike, pose: Pose,
                    terrain: Terrain, gradient: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """(N,) how much larger the map's footprint of a pixel is at each terrain point than the same ray's on level
    ground at the height of the ground below the UAV (the flat world of a UAV at its true height above the ground),
    as a length: the square root of the ratio of the horizontal areas that one small cone of rays covers there.
    Below 1 where the terrain turns toward the camera (a slope facing it, a rise ahead: a pixel covers less ground,
    and its errors move the point less), above 1 where it turns away or falls, 1 on a flat DEM at any height.
    Where the DEM has no height below the UAV, or the UAV is not above it, level ground through the point is the
    reference (the slope alone).
    NaN where not defined (no point, or not below the camera).

    A cone of solid angle w along the unit ray d at slant range R covers R^2 w / |n.d| of a surface with unit normal
    n, n_z of it on the horizontal map: R^3 w / |g_e east + g_n north + drop| with the gradient g and drop the
    camera's height above the point. On level ground a height h below the camera the same rays meet it at
    R_f = R h / drop and cover R_f^3 w / h, so the ratio is drop^3 / (h^2 |g_e east + g_n north + drop|).
    gradient: the terrain's (g_e, g_n) at the points when already known (Terrain.gradient).
    """
    drop, plane, _ = _view_terms(east_m, north_m, up_m, pose, terrain, gradient)
    below = pose.height_m - float(terrain.up_m(np.zeros(1), np.zeros(1), pose)[0])  # above the ground below the UAV
    with np.errstate(invalid="ignore", divide="ignore"):
        level = below if math.isfinite(below) and below > 0 else drop
        ratio = drop**3 / (level * level * plane)
        defined = (drop > 0) & (ratio > 0) & np.isfinite(ratio)  # a grazing ray (|g.en + drop| = 0): not
        return np.asarray(np.where(defined, np.sqrt(ratio), np.nan), dtype=np.float64)


def edge_alternatives(uv: ArrayLike, probe_px: ArrayLike, camera: Camera, pose: Pose, terrain: Terrain,
                      east_m: ArrayLike, north_m: ArrayLike, *, max_range_m: float | None = None, ratio: float = 3.0,
                      min_jump_m: float = 2.0) -> tuple[FloatArray, FloatArray]:
    """Second ground points of pixels whose ray passes an edge of the terrain (a bank's lip, a crest) within
    probe_px of them: east, north (N,) metres in the pose's local frame, NaN where there is none.

    uv (N, 2) pixels with their first terrain points east_m, north_m (pixel_to_terrain); probe_px (N,) or scalar
    pixels. The pixels probe_px above and below are marched too: on ground the ray meets smoothly both move the
    point about as far (their ratio is near 1 short of grazing angles); where one probe lands beyond an edge and
    the other does not, its jump is more than `ratio` times the other's and at least min_jump_m, and its point is
    the alternative (the same object a few pixels away lands there: a box's edge is that uncertain). A probe
    without a terrain point gives none.
    """
    pts = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    step = np.broadcast_to(np.asarray(probe_px, dtype=np.float64), (n,))
    probes = np.concatenate([pts - np.column_stack([np.zeros(n), step]), pts + np.column_stack([np.zeros(n), step])])
    pe, pn, _, ok = pixel_to_terrain(probes, camera, pose, terrain, max_range_m=max_range_m)
    e = np.asarray(east_m, dtype=np.float64).reshape(-1)
    nn = np.asarray(north_m, dtype=np.float64).reshape(-1)
    jump = np.hypot(pe - np.tile(e, 2), pn - np.tile(nn, 2)).reshape(2, n)
    both = ok.reshape(2, n).all(axis=0) & np.isfinite(e) & np.isfinite(nn)
    side = np.argmax(np.where(both, jump, 0.0), axis=0)  # 0: the probe above, 1: below
    big = np.take_along_axis(jump, side[None], axis=0)[0]
    small = np.take_along_axis(jump, 1 - side[None], axis=0)[0]
    with np.errstate(invalid="ignore"):
        edge = both & (big >= min_jump_m) & (big > ratio * small)
    rows = side * n + np.arange(n)
    return np.where(edge, pe[rows], np.nan), np.where(edge, pn[rows], np.nan)

"""Which ground cells a frame sees on a terrain, and where: the anomaly layer's geometry with a DEM (`--dem`).

Over flat ground one homography maps the grid to the image (`agent.anomaly.ground`). On a terrain each cell's
centre is lifted to the DEM's surface and projected: the flat homography of the cell plus its height times the
camera's up axis in the image (`shared.geo.local_to_pixel(..., terrain=)` without lens distortion, which the
flat homographies leave out as well). A cell is seen when nothing between the camera and it rises above the line
of sight (a radial viewshed on a polar grid about the UAV), it lies within the range limit and the horizon margin
below the horizontal, and it projects into the image. The DEM is resampled by OpenCV (bilinear, as
`shared.terrain`; weights in 1/32 of a DEM spacing: 5 mm on a 1 m DEM at a 30 % slope).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose, ground_to_image_homography, image_border, local_to_latlon, pixel_rays_enu
from shared.terrain import ElevationGrid, Terrain

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Cap on the viewshed's polar grid (azimuths x range steps): beyond it both spacings grow.
MAX_VIEWSHED_SAMPLES = 400_000


@dataclass(frozen=True, slots=True, eq=False)
class TerrainView:
    """The window cells one frame sees on a terrain.

    block: (c0, r0, c1, r1) window cells of the view (rows r0..r1-1, columns c0..c1-1).
    valid: (r1 - r0, c1 - c0) bool, the cells the frame sees: projected into the image, not hidden by the terrain,
        within the range limit and at least the horizon margin below the horizontal (both measured along the view's
        heading, as the flat cut row does), on the DEM. The arrays below hold the N seen cells in its order.
    uv: (N, 2) float64 full-resolution pixels of the seen cells' centres on the terrain.
    footprint: (N, 2) float64 width and height (full-resolution pixels) of the box about each seen cell's
        footprint in the image: the sums of the absolute image steps to its east and south neighbours (the
        bounding box of the parallelogram they span).
    max_step_px: the largest image step (full-resolution pixels) from a seen cell to its east neighbour: how fine
        the frame's finest cell is.
    cut_row: first full-resolution image row that shows a seen cell.
    """

    block: tuple[int, int, int, int]
    valid: BoolArray
    uv: FloatArray
    footprint: FloatArray
    max_step_px: float
    cut_row: int


class TerrainCells:
    """The DEM of a terrain prepared once for resampling by OpenCV (float32), with the affine map to its grid.

    Parameters
    ----------
    grid : ElevationGrid
    """

    def __init__(self, grid: ElevationGrid) -> None:
        self.grid = grid
        self.dem = np.ascontiguousarray(grid.heights_m, dtype=np.float32)

    def local_to_dem(self, pose: Pose) -> FloatArray:
        """(2, 3) affine from metres east/north of the pose's position to DEM grid coordinates (column, row of
        the samples; exact: `shared.geo.local_to_latlon` is linear)."""
        g = self.grid
        lat, lon = local_to_latlon(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), pose.lat, pose.lon)
        lon = lon[0] + (lon - lon[0] + 180.0) % 360.0 - 180.0  # the steps, not the wrap at the antimeridian
        col = (lon - g.lon0_deg) / g.lon_step_deg
        row = (lat - g.lat0_deg) / g.lat_step_deg
        return np.array([[col[1] - col[0], col[2] - col[0], col[0]], [row[1] - row[0], row[2] - row[0], row[0]]])

    def sample(self, col: NDArray[np.float32], row: NDArray[np.float32]) -> NDArray[np.float32]:
        """DEM heights (above its datum) at grid coordinates (float32 arrays of one 2-D shape, each side < 32767),
        bilinear; NaN off the DEM or next to a sample without data."""
        return np.asarray(cv2.remap(self.dem, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                    borderValue=float("nan")), dtype=np.float32)

    def lattice_heights(self, cell_to_dem: FloatArray, shape: tuple[int, int]) -> NDArray[np.float32]:
        """DEM heights at the points (j, i) of a (rows, cols) lattice, mapped to DEM grid coordinates by the (2, 3)
        affine cell_to_dem (one warpAffine)."""
        return np.asarray(cv2.warpAffine(self.dem, cell_to_dem, (shape[1], shape[0]),
                                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan")), dtype=np.float32)


def reach_extremes(cells: TerrainCells, terrain: Terrain, pose: Pose, reach_m: float) -> tuple[float, float]:
    """(lowest, highest) DEM height above the pose's reference within reach_m of the UAV (from the DEM's block
    extremes: possibly a little wider); NaN when no sample there has data."""
    affine = cells.local_to_dem(pose)
    corners = np.array([[-reach_m, -reach_m, 1.0], [reach_m, reach_m, 1.0]]) @ affine.T
    rows_n, cols_n = cells.grid.shape
    low, high = cells.grid.extremes(max(float(corners[:, 0].min()), 0.0), min(float(corners[:, 0].max()), cols_n - 1.0),
                                    max(float(corners[:, 1].min()), 0.0), min(float(corners[:, 1].max()), rows_n - 1.0))
    base = terrain.base_elevation_m(pose)
    return low - base, high - base


def reach_polygon(camera: Camera, pose: Pose, low_m: float, high_m: float, max_range_m: float,
                  samples_per_edge: int = 32) -> FloatArray:
    """(M, 2) local east/north metres whose bounding box holds every ground point the frame can see on a terrain
    between heights low_m and high_m (above the pose's reference) up to max_range_m along the view's heading: the
    image border's rays cut by both planes (where a ray misses a plane within range: its point at the range
    limit, or 4 x max_range_m for rays within 75 deg of sideways), and the point below the UAV.

    A ray's first terrain hit lies between its hits on the two planes, and an interior pixel's ray between the
    border's, so the points' bounding box is a conservative block."""
    rays = pixel_rays_enu(image_border(camera, samples_per_edge), camera, pose)
    horiz = np.hypot(rays[:, 0], rays[:, 1])
    heading = math.radians(pose.heading_deg)
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.where(horiz > 1e-12, (rays[:, 0] * math.sin(heading) + rays[:, 1] * math.cos(heading)) / horiz, 1.0)
    limit = max_range_m / np.maximum(along, 0.25)  # the horizontal distance at which a ray leaves the range
    pts = [np.zeros((1, 2))]
    for z in (low_m, high_m):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z - pose.height_m) / rays[:, 2]
            dist = np.minimum(np.where(np.isfinite(t) & (t > 0), t * horiz, math.inf), limit)
            scale = np.where(horiz > 1e-12, dist / horiz, 0.0)
        pts.append(rays[:, :2] * scale[:, None])
    return np.vstack(pts)


def hidden_by_terrain(east_m: NDArray[np.floating], north_m: NDArray[np.floating], up_m: NDArray[np.floating],
                      pose: Pose, cells: TerrainCells, base_m: float, step_m: float) -> BoolArray:
    """(N,) True where the terrain between the camera and a ground point rises above the line of sight to it (or
    has no data there): the point is not seen.

    east_m, north_m, up_m: (N,) float32 or float64 points on the terrain in the pose's local frame (up above base_m, the
    DEM elevation of the pose's reference). A radial viewshed: the DEM is sampled on a polar grid about the point
    below the UAV (range steps of step_m, azimuth steps of step_m at the farthest point), each polar ray keeps
    the running maximum of the slope (height above the camera / distance) of the terrain up to each range, and
    a point is hidden when that maximum a step or more before it (linear between the two polar rays either side
    of its azimuth) is above the slope of its own line of sight. Against exact ray casting
    (`shared.terrain.Terrain.intersect_rays` to every cell) on the `hills` DEM it disagrees on ~0.25 % of the
    cells, all at the hidden region's edges (docs/anomaly.md, Terrain). Cost: one bilinear DEM lookup per polar
    sample, at most MAX_VIEWSHED_SAMPLES.
    """
    n = len(east_m)
    hidden = np.zeros(n, dtype=bool)
    if n == 0:
        return hidden
    h = float(pose.height_m)
    r = np.sqrt(east_m * east_m + north_m * north_m)
    ref = math.radians(pose.heading_deg)  # azimuths from the view's heading, so a view's span never wraps around
    rel = (np.arctan2(east_m, north_m) - ref + math.pi) % (2.0 * math.pi) - math.pi
    a0, a1 = float(rel.min()), float(rel.max())
    r_max = float(r.max())
    if r_max <= 2.0 * step_m:
        return hidden
    dr, da = step_m, step_m / r_max
    n_r, n_a = int(math.ceil(r_max / dr)), int(math.ceil((a1 - a0) / da)) + 1
    if n_a * n_r > MAX_VIEWSHED_SAMPLES:  # coarser, both spacings in proportion
        f = math.sqrt(n_a * n_r / MAX_VIEWSHED_SAMPLES)
        dr, da = dr * f, da * f
        n_r, n_a = int(math.ceil(r_max / dr)), int(math.ceil((a1 - a0) / da)) + 1
    azimuths = ref + a0 + da * np.arange(n_a)
    ranges = (dr * np.arange(1, n_r + 1)).astype(np.float32)
    sin_a, cos_a = np.sin(azimuths), np.cos(azimuths)
    m = cells.local_to_dem(pose)  # DEM coordinates are linear in range along each polar ray
    col = (m[0, 0] * sin_a + m[0, 1] * cos_a).astype(np.float32)[:, None] * ranges + np.float32(m[0, 2])
    row = (m[1, 0] * sin_a + m[1, 1] * cos_a).astype(np.float32)[:, None] * ranges + np.float32(m[1, 2])
    slope = (cells.sample(col, row) - np.float32(base_m + h)) / ranges
    # running maximum along each polar ray; NaN (no data) propagates: unknown ground may hide anything behind it
    horizon = np.maximum.accumulate(slope, axis=1)
    if n_r > 2 and not np.isnan(horizon).any() and (slope[:, 2:] >= horizon[:, :-2]).all():
        return hidden  # no polar sample is hidden: the view has no occlusion to look up
    j = np.minimum((r / dr).astype(np.int64) - 2, n_r - 1)  # the last sample a step or more before the point
    before = np.flatnonzero(j >= 0)
    # the horizon linear between the two polar rays either side of the point's azimuth
    pos = np.clip((rel[before] - a0) / da, 0.0, n_a - 1.0)
    k = np.minimum(pos.astype(np.int64), max(n_a - 2, 0))
    f = (pos - k).astype(np.float32)
    flat = horizon.ravel()
    at = k * n_r + j[before]
    limit = flat.take(at) * (1 - f) + flat.take(np.where(k + 1 < n_a, at + n_r, at)) * f
    with np.errstate(invalid="ignore", divide="ignore"):
        own = (up_m[before] - h) / r[before]
        hidden[before] = ~(own >= limit)
    return hidden


def _steps(values: NDArray[np.float32], axis: int) -> NDArray[np.float32]:
    """(rows, cols) differences to the next cell along axis (1: east, 0: south); the last cell, and a cell whose
    next one has no projection (NaN), take the step before it."""
    step = np.full_like(values, np.nan)
    if values.shape[axis] < 2:
        return step
    d = np.diff(values, axis=axis)
    head = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1),)
    last = (slice(None), -1) if axis == 1 else (-1,)
    step[head] = d
    step[last] = d[last]
    if np.isnan(d).any():
        tail = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None),)
        step[tail] = np.where(np.isnan(step[tail]), d, step[tail])
    return step


def terrain_view(camera: Camera, pose: Pose, terrain: Terrain, cells: TerrainCells, cell_to_local: FloatArray,
                 size_cells: int, cell_m: float, max_range_m: float, horizon_margin_deg: float,
                 ground_to_image: FloatArray | None = None) -> TerrainView | None:
    """The cells of a window a frame sees on a terrain, or None when it sees none.

    cells: the terrain's DEM prepared (TerrainCells of terrain.grid). cell_to_local: (3, 3) affine from window
    (col, row) cell coordinates to metres east/north of the pose's position; size_cells: the window's edge in
    cells; cell_m: about a cell's edge in metres (the viewshed's step). ground_to_image: the frame's (3, 3)
    homography from metres east/north of the pose's position to pixels when known better than the pose's own
    (`agent.anomaly.registration`): its difference to the pose's is applied to the projected cells as an image
    correction (a homography: exact for the pose's attitude errors, which dominate).
    """
    if size_cells <= 0:
        return None
    base = terrain.base_elevation_m(pose)
    if not math.isfinite(base):
        return None
    low, high = reach_extremes(cells, terrain, pose, max_range_m)
    if not (math.isfinite(low) and math.isfinite(high)):
        return None
    corners = cv2.perspectiveTransform(reach_polygon(camera, pose, low, high, max_range_m)[None],
                                       np.linalg.inv(cell_to_local))[0]
    c0, r0 = (max(int(v), 0) for v in np.floor(corners.min(axis=0)) - 1)
    c1, r1 = (min(int(v), size_cells) for v in np.ceil(corners.max(axis=0)) + 1)
    if c1 <= c0 or r1 <= r0:
        return None
    shape = (r1 - r0, c1 - c0)
    centre = np.array([[1.0, 0.0, c0 + 0.5], [0.0, 1.0, r0 + 0.5], [0.0, 0.0, 1.0]])  # lattice (j, i) -> cell centre
    lattice_to_local = cell_to_local @ centre
    up = cells.lattice_heights(cells.local_to_dem(pose) @ lattice_to_local, shape)
    up -= np.float32(base)
    # the image point of (east, north, up): the ground homography's plus up times the camera's up axis in the
    # image; float32 (a 4K frame's pixels to 1e-3)
    tel = ground_to_image_homography(camera, pose)
    g = tel if ground_to_image is None else ground_to_image
    up_axis = camera.K @ pose.R_world_from_cam[2, :]  # K R_cam_from_world (0, 0, 1)
    if ground_to_image is not None:
        up_axis = g @ np.linalg.solve(tel, up_axis)
    hom = g @ lattice_to_local
    scale = float(np.abs(hom).max())  # homogeneous coordinates of order 1 for float32
    hom, up_axis = hom / scale, up_axis / scale
    jj = np.arange(shape[1], dtype=np.float32)[None, :]
    ii = np.arange(shape[0], dtype=np.float32)[:, None]

    def lattice(coef: FloatArray, up_coef: float) -> NDArray[np.float32]:
        """coef . (j, i, 1) + up_coef * up over the lattice (in place: one array of the lattice's size)."""
        out = up * np.float32(up_coef)
        out += np.float32(coef[0]) * jj + np.float32(coef[2])
        out += np.float32(coef[1]) * ii
        return out

    w = lattice(hom[2], up_axis[2])
    with np.errstate(invalid="ignore", divide="ignore"):
        behind = ~(w > 1e-6 * float(np.nanmax(np.abs(w))))  # NaN (off the DEM) too
        np.reciprocal(w, out=w)
        x = lattice(hom[0], up_axis[0])
        x *= w
        y = lattice(hom[1], up_axis[1])
        y *= w
    del w
    x[behind] = np.nan
    y[behind] = np.nan
    # the range limit and the horizon margin on the distance along the view's heading, as the flat cut row takes
    # them (with no roll an image row is a ground line across the heading: the flat and a flat DEM's cells agree)
    a = lattice_to_local
    heading = math.radians(pose.heading_deg)
    fe, fn = math.sin(heading), math.cos(heading)
    forward = np.float32(fe * a[0, 0] + fn * a[1, 0]) * jj + np.float32(fe * a[0, 2] + fn * a[1, 2]) \
        + np.float32(fe * a[0, 1] + fn * a[1, 1]) * ii
    with np.errstate(invalid="ignore"):
        valid = x >= 0  # False for NaN (behind the camera, off the DEM)
        valid &= x < camera.width
        valid &= y >= 0
        valid &= y < camera.height
        valid &= forward <= max_range_m
        forward *= np.float32(math.tan(math.radians(horizon_margin_deg)))
        forward += up
        valid &= forward <= pose.height_m  # at least the margin below the horizontal
    del forward
    if not valid.any():
        return None
    rows, cols = np.nonzero(valid)
    colf, rowf = cols.astype(np.float32), rows.astype(np.float32)
    east = np.float32(a[0, 0]) * colf + np.float32(a[0, 1]) * rowf + np.float32(a[0, 2])
    north = np.float32(a[1, 0]) * colf + np.float32(a[1, 1]) * rowf + np.float32(a[1, 2])
    valid[rows, cols] = ~hidden_by_terrain(east, north, up[rows, cols], pose, cells, base, cell_m)
    if not valid.any():
        return None
    vr, vc = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    # steps on the view's block grown by a cell, so the cells at its edge keep their outer neighbours' steps
    i0, j0 = max(int(vr[0]) - 1, 0), max(int(vc[0]) - 1, 0)
    crop = (slice(i0, int(vr[-1]) + 2), slice(j0, int(vc[-1]) + 2))
    inner = (slice(int(vr[0]) - i0, int(vr[-1]) + 1 - i0), slice(int(vc[0]) - j0, int(vc[-1]) + 1 - j0))
    seen = valid[int(vr[0]):int(vr[-1]) + 1, int(vc[0]):int(vc[-1]) + 1]
    xc, yc = x[crop], y[crop]
    ex, ey = _steps(xc, 1)[inner][seen], _steps(yc, 1)[inner][seen]
    sx, sy = _steps(xc, 0)[inner][seen], _steps(yc, 0)[inner][seen]
    uv = np.column_stack([xc[inner][seen], yc[inner][seen]]).astype(np.float64)
    footprint = np.column_stack([np.abs(ex) + np.abs(sx), np.abs(ey) + np.abs(sy)]).astype(np.float64)
    cut = int(math.floor(float(uv[:, 1].min())))
    return TerrainView((c0 + int(vc[0]), r0 + int(vr[0]), c0 + int(vc[-1]) + 1, r0 + int(vr[-1]) + 1), seen, uv,
                       footprint, float(np.nanmax(np.hypot(ex, ey), initial=0.0)),
                       min(max(cut, 0), camera.height))


def terrain_cut_row(camera: Camera, pose: Pose, terrain: Terrain, cells: TerrainCells, cell_m: float,
                    max_range_m: float, horizon_margin_deg: float) -> int:
    """First full-resolution image row that shows a ground point the layer would map (seen, within range, below
    the margin), on a lattice of cell_m metres about the UAV instead of the layer's window: the cut of the
    per-frame baseline, which has no window. The camera's height when the frame sees no such point."""
    n = int(math.ceil(2.0 * max_range_m / cell_m)) + 2
    half = 0.5 * n * cell_m
    lattice = np.array([[cell_m, 0.0, -half], [0.0, -cell_m, half], [0.0, 0.0, 1.0]])
    view = terrain_view(camera, pose, terrain, cells, lattice, n, cell_m, max_range_m, horizon_margin_deg)
    return camera.height if view is None else view.cut_row

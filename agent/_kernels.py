"""Compiled (numba) inner loops of the per-frame detection pipeline: exact class-wise NMS, the fused
georeference + size filter, the memory map's reads, patches and impulse stamping, and the distinct class
ids of a frame. agent.pipeline and agent.memory_map wrap them; nothing else should call them directly.

The kernels have explicit signatures, so they are compiled when this module is first imported (~10 s
on the 2-core development machine), and with cache=True numba stores the machine code next to this
file in __pycache__ (else in its user-wide cache directory, or NUMBA_CACHE_DIR), which later processes
load in well under a second. Where no cache directory is writable they are compiled in memory once per
process (a warning is logged). Every kernel releases the GIL (nogil) and divides as numpy does
(error_model="numpy": x / 0 is inf or NaN, no exception).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numba as nb
import numpy as np
from numba import types as nbt

log = logging.getLogger(__name__)

#: std::numeric_limits<double>::epsilon(): OpenCV treats two boxes whose areas sum to at most this as
#: identical (IoU 1), wherever they are.
_DBL_EPSILON = float(np.finfo(np.float64).eps)
#: Cells per axis of the NMS grid at most, and cells a box may cover before it is checked against
#: every candidate of its class instead of being filed under its cells.
NMS_GRID_CELLS = 128
NMS_MAX_SPAN = 16
#: The NMS grid's cell edge in mean box sizes (the mean of width and height of the candidates).
NMS_CELL_BOXES = 1.0


#: Options of the small helpers the kernels inline (into numba's IR: they are never compiled on their own,
#: so they need neither signatures nor a cache).
_INLINE: dict[str, Any] = {"nogil": True, "error_model": "numpy", "inline": "always"}


def _compiled(signatures: list[Any]) -> Callable[[Callable[..., Any]], Any]:
    """njit with explicit signatures (compiled at import), cached on disk where numba finds a writable
    directory, in memory otherwise."""

    def wrap(fn: Callable[..., Any]) -> Any:
        try:
            return nb.njit(signatures, cache=True, nogil=True, error_model="numpy")(fn)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            log.warning("numba cannot cache %s (%s): compiling it in memory for this process", fn.__name__, exc)
            return nb.njit(signatures, cache=False, nogil=True, error_model="numpy")(fn)

    return wrap


@nb.njit(**_INLINE)
def _rect_overlap(ax, ay, aw, ah, bx, by, bw, bh):  # pragma: no cover - compiled
    """OpenCV's rectOverlap(a, b) for Rect2d boxes (x, y, w, h): 1.f - float(jaccardDistance(a, b)).

    Same branches and arithmetic as cv::jaccardDistance and Rect_::operator&= (OpenCV >= 4.8), so NaN,
    empty and negative-size boxes give what OpenCV gives (NaN compares False: "suppressed").
    """
    area_a = aw * ah
    area_b = bw * bh
    if area_a + area_b <= _DBL_EPSILON:
        return np.float32(1.0)
    inter = 0.0
    if not (aw <= 0 or ah <= 0 or bw <= 0 or bh <= 0):  # an empty box meets nothing
        if ax < bx:
            x_lo, w_lo, x_hi, w_hi = ax, aw, bx, bw
        else:
            x_lo, w_lo, x_hi, w_hi = bx, bw, ax, aw
        if ay < by:
            y_lo, h_lo, y_hi, h_hi = ay, ah, by, bh
        else:
            y_lo, h_lo, y_hi, h_hi = by, bh, ay, ah
        if not ((x_lo < 0 and x_lo + w_lo < x_hi) or (y_lo < 0 and y_lo + h_lo < y_hi)):
            iw = w_lo - (x_hi - x_lo)
            if w_hi < iw:  # std::min(a, b) is (b < a) ? b : a
                iw = w_hi
            ih = h_lo - (y_hi - y_lo)
            if h_hi < ih:
                ih = h_hi
            if not (iw <= 0 or ih <= 0):
                inter = iw * ih
    distance = 1.0 - inter / (area_a + area_b - inter)
    return np.float32(1.0) - np.float32(distance)


@_compiled([nbt.uint64[::1](nbt.float32[::1], nbt.float64)])
def rank_keys(scores, score_threshold):  # pragma: no cover - compiled
    """Sort keys of the scores > score_threshold (float32 compare, as OpenCV): (M,) uint64, unsorted.

    Each key holds an order-preserving uint32 of the score, inverted, above the score's index, so an
    ascending sort of the keys (np.sort: SIMD, ~15x faster than numba's) ranks by descending score,
    ties by ascending index, as OpenCV's stable sort does; the low 32 bits give the index.
    """
    n = scores.shape[0]
    thr = np.float32(score_threshold)
    bits = scores.view(np.uint32)
    keys = np.empty(n, np.uint64)
    m = 0
    for i in range(n):
        if scores[i] > thr:
            b = bits[i]
            ascending = ~b if b & np.uint32(0x80000000) else b | np.uint32(0x80000000)
            keys[m] = (np.uint64(~ascending) << np.uint64(32)) | np.uint64(i)
            m += 1
    return keys[:m]


_NMS_SIGNATURES = [
    nbt.int64[::1](nbt.float32[:, ::1], nbt.uint64[::1], nbt.int64[::1], nbt.float64, nbt.int64),
    nbt.int64[::1](nbt.float64[:, ::1], nbt.uint64[::1], nbt.int64[::1], nbt.float64, nbt.int64),
]


@_compiled(_NMS_SIGNATURES)
def nms_ranked(boxes_xyxy, ranked_keys, class_ids, iou, max_detections):  # pragma: no cover - compiled
    """Greedy class-wise NMS exactly as OpenCV's NMSBoxes per class (see agent.boxes.nms).

    ranked_keys: the sorted rank_keys() of the scores. Each box in rank order, as an OpenCV Rect2d
    (x, y, w, h rounded to float32), is kept unless its overlap with a kept box of its class is not
    <= iou (float32); stops at max_detections kept boxes. Kept boxes are filed under the cells of a
    grid they cover, so a box is compared only with kept boxes it may intersect (disjoint boxes have
    overlap 0); boxes that are not plain (NaN, empty, negative or tiny area, which OpenCV may find
    overlapping wherever they are) meet every kept box of their class.
    Returns the indices of the kept boxes, highest score first.
    """
    nms_thr = np.float32(iou)
    m = ranked_keys.shape[0]
    limit = min(max_detections, m)
    kept_out = np.empty(max(limit, 0), np.int64)
    if limit <= 0:
        return kept_out[:0]
    order = np.empty(m, np.int64)
    x = np.empty(m)
    y = np.empty(m)
    w = np.empty(m)
    h = np.empty(m)
    plain = np.empty(m, np.bool_)
    x_min = y_min = np.inf
    x_max = y_max = -np.inf
    size_sum = 0.0
    n_plain = 0
    for r in range(m):
        i = np.int64(ranked_keys[r] & np.uint64(0xFFFFFFFF))
        order[r] = i
        # OpenCV saw x, y and the widths (in the boxes' dtype) rounded to float32, as Rect2d
        x[r] = np.float32(boxes_xyxy[i, 0])
        y[r] = np.float32(boxes_xyxy[i, 1])
        w[r] = np.float32(boxes_xyxy[i, 2] - boxes_xyxy[i, 0])
        h[r] = np.float32(boxes_xyxy[i, 3] - boxes_xyxy[i, 1])
        ok = (np.isfinite(x[r]) and np.isfinite(y[r]) and np.isfinite(w[r]) and np.isfinite(h[r])
              and w[r] > 0 and h[r] > 0 and w[r] * h[r] > _DBL_EPSILON)
        plain[r] = ok
        if ok:
            n_plain += 1
            x_min = min(x_min, x[r])
            y_min = min(y_min, y[r])
            x_max = max(x_max, x[r] + w[r])
            y_max = max(y_max, y[r] + h[r])
            size_sum += 0.5 * (w[r] + h[r])
    # the grid over the plain boxes
    cell = 1.0
    nx = ny = 1
    if n_plain:
        cell = max(NMS_CELL_BOXES * size_sum / n_plain, (x_max - x_min) / NMS_GRID_CELLS,
                   (y_max - y_min) / NMS_GRID_CELLS)
        if not (cell > 0 and np.isfinite(cell)):
            cell = 1.0
        nx = min(int((x_max - x_min) / cell) + 1, NMS_GRID_CELLS + 1)
        ny = min(int((y_max - y_min) / cell) + 1, NMS_GRID_CELLS + 1)
    head = np.full(nx * ny, -1, np.int32)
    capacity = limit * NMS_MAX_SPAN
    entry_next = np.empty(capacity, np.int32)
    entry_kept = np.empty(capacity, np.int32)
    n_entries = 0
    # kept boxes (rank r), and those filed under no cell (wide or not plain): checked by every box
    kept_rank = np.empty(limit, np.int64)
    everywhere = np.empty(limit, np.int32)
    n_everywhere = 0
    tested_by = np.full(limit, -1, np.int64)
    n_kept = 0
    for r in range(m):
        cid = class_ids[order[r]]
        keep = True
        c0 = c1 = r0 = r1 = 0
        filed = False
        if plain[r]:
            c0 = min(max(int((x[r] - x_min) / cell), 0), nx - 1)
            c1 = min(max(int((x[r] + w[r] - x_min) / cell), 0), nx - 1)
            r0 = min(max(int((y[r] - y_min) / cell), 0), ny - 1)
            r1 = min(max(int((y[r] + h[r] - y_min) / cell), 0), ny - 1)
            filed = (c1 - c0 + 1) * (r1 - r0 + 1) <= NMS_MAX_SPAN
        if filed:
            for gy in range(r0, r1 + 1):
                for gx in range(c0, c1 + 1):
                    e = head[gy * nx + gx]
                    while e >= 0:
                        k = entry_kept[e]
                        e = entry_next[e]
                        if tested_by[k] == r:
                            continue
                        tested_by[k] = r
                        q = kept_rank[k]
                        if class_ids[order[q]] == cid and not (
                                _rect_overlap(x[r], y[r], w[r], h[r], x[q], y[q], w[q], h[q]) <= nms_thr):
                            keep = False
                            break
                    if not keep:
                        break
                if not keep:
                    break
            if keep:
                for j in range(n_everywhere):
                    k = everywhere[j]
                    q = kept_rank[k]
                    if class_ids[order[q]] == cid and not (
                            _rect_overlap(x[r], y[r], w[r], h[r], x[q], y[q], w[q], h[q]) <= nms_thr):
                        keep = False
                        break
        else:  # against every kept box of the class
            for k in range(n_kept):
                q = kept_rank[k]
                if class_ids[order[q]] == cid and not (
                        _rect_overlap(x[r], y[r], w[r], h[r], x[q], y[q], w[q], h[q]) <= nms_thr):
                    keep = False
                    break
        if not keep:
            continue
        kept_rank[n_kept] = r
        kept_out[n_kept] = order[r]
        if filed:
            for gy in range(r0, r1 + 1):
                for gx in range(c0, c1 + 1):
                    cell_id = gy * nx + gx
                    entry_kept[n_entries] = n_kept
                    entry_next[n_entries] = head[cell_id]
                    head[cell_id] = n_entries
                    n_entries += 1
        else:
            everywhere[n_everywhere] = n_kept
            n_everywhere += 1
        n_kept += 1
        if n_kept >= limit:
            break
    return kept_out[:n_kept]


@nb.njit(**_INLINE)
def _on_segment(x, knots, curves, row, c, j):  # pragma: no cover - compiled
    """np.interp's value of curve c of band `row` at x, knots[row, j] < x < knots[row, j + 1]."""
    slope = curves[row, 2 + c, j]
    y = slope * (x - knots[row, j]) + curves[row, c, j]
    if np.isnan(y):  # numpy's fallbacks for infinite slopes
        y = slope * (x - knots[row, j + 1]) + curves[row, c, j + 1]
        if np.isnan(y) and curves[row, c, j] == curves[row, c, j + 1]:
            y = curves[row, c, j]
    return y


@nb.njit(**_INLINE)
def _band_at(x, knots, curves, row, k):  # pragma: no cover - compiled
    """(mean, std) of band `row` at depression x (finite): np.interp(x, knots[row, :k], curve) of its mean
    and std curves, with numpy's branches (ends held, exact knots) and slopes (curves[row, 2:],
    precomputed as numpy does). Rows are indexed, not sliced: a slice per box costs two atomic
    reference counts, an array per box an allocation."""
    if k == 1 or x <= knots[row, 0]:
        return curves[row, 0, 0], curves[row, 1, 0]
    if x >= knots[row, k - 1]:
        return curves[row, 0, k - 1], curves[row, 1, k - 1]
    # j with knots[j] <= x < knots[j + 1]: guessed for evenly spaced knots (the built-in bands), then corrected
    j = min(max(int((x - knots[row, 0]) * ((k - 1) / (knots[row, k - 1] - knots[row, 0]))), 0), k - 2)
    while j > 0 and knots[row, j] > x:
        j -= 1
    while knots[row, j + 1] <= x:
        j += 1
    if knots[row, j] == x:
        return curves[row, 0, j], curves[row, 1, j]
    return _on_segment(x, knots, curves, row, 0, j), _on_segment(x, knots, curves, row, 1, j)


_GEO_SIGNATURE = nbt.Tuple((nbt.float64[::1], nbt.float64[::1], nbt.boolean[::1], nbt.boolean[::1]))(
    nbt.float32[:, ::1], nbt.int64[::1], nbt.float64, nbt.float64[::1], nbt.float64[:, ::1], nbt.float64,
    nbt.float64, nbt.float64, nbt.float64[::1], nbt.int64, nbt.int64[::1], nbt.float64[:, ::1], nbt.float64[:, :, ::1],
    nbt.int64[::1], nbt.float64[:, :, ::1], nbt.float64, nbt.float64)


@_compiled([_GEO_SIGNATURE])
def georeference_and_filter(boxes_xyxy, class_ids, anchor_frac, intrinsics, rotation, sin_min_depression,
                            height_m, max_range_m, origin, class_lo, band_of_class, knots_deg, band_curves, n_knots,
                            sure_bounds, k, focal_px):  # pragma: no cover - compiled
    """Ground point of each box's anchor and the size filter's decision, in one pass over the boxes.

    boxes_xyxy (N, 4) float32 pixels; class_ids (N,); anchor_frac: the anchor's height in the box
    (0 top, 1 bottom); intrinsics (fx, fy, cx, cy) of an undistorted camera; rotation:
    Pose.R_world_from_cam; sin_min_depression: sine of the horizon's dip; max_range_m: inf for none;
    origin: lat0, lon0 (degrees) of the point below the UAV, the meridian radius of curvature there and
    the prime-vertical one times cos(lat0) (metres), as shared.geo.local_to_latlon uses them.
    band_of_class[class_id - class_lo]: the class's row of the band tables, -1 (or outside the table)
    for no filtering; knots_deg (B, K) band knots, n_knots (B,) of them used per row, band_curves
    (B, 4, K): mean and std of log diameter at the knots and their slopes to the next knot, (v[j + 1] -
    v[j]) / (knot[j + 1] - knot[j]); sure_bounds (B, M, 4): SizeBand.sure_bounds(k, M) of each row;
    k: the band's half width in stds; focal_px: sqrt(fx * fy).
    Returns lat, lon (N,) degrees (NaN where invalid), valid (N,) and plausible (N,) bool: the same as
    shared.geo.pixel_to_local, local_to_latlon and DetectionPipeline.plausible, to float rounding (the
    ray's rotation sums in another order than numpy's matmul, and numpy's SIMD arcsin and log may
    differ in the last bit). The exact test (scalar arcsin, log and the band's interpolation, ~60 ns a
    box) runs only for boxes whose size lies within the sure bounds' margin of the band's edge; the
    others are decided by the sure bounds (~5 ns). The range limit is tested on the squared distance
    unless it is within 1e-9 of the limit (hypot there). The tile cells (tan, arcsinh) stay with
    numpy's SIMD functions, which are ~3x faster there.
    """
    n = boxes_xyxy.shape[0]
    lat = np.empty(n)
    lon = np.empty(n)
    to_deg = 180.0 / np.pi  # np.degrees
    valid = np.empty(n, np.bool_)
    plausible = np.empty(n, np.bool_)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    h2 = height_m ** 2
    # below range_in2 the distance is surely within the limit, above range_out2 surely beyond it
    range_in2 = (max_range_m * (1 - 1e-9)) ** 2 if max_range_m < 1e150 else -1.0
    range_out2 = (max_range_m * (1 + 1e-9)) ** 2 if max_range_m < 1e150 else np.inf
    n_bins = sure_bounds.shape[1]
    focal2 = focal_px * focal_px
    for i in range(n):
        x1 = np.float64(boxes_xyxy[i, 0])
        y1 = np.float64(boxes_xyxy[i, 1])
        x2 = np.float64(boxes_xyxy[i, 2])
        y2 = np.float64(boxes_xyxy[i, 3])
        xn = ((x1 + x2) / 2.0 - cx) / fx
        yn = (y1 + anchor_frac * (y2 - y1) - cy) / fy
        rx = xn * rotation[0, 0] + yn * rotation[0, 1] + rotation[0, 2]
        ry = xn * rotation[1, 0] + yn * rotation[1, 1] + rotation[1, 2]
        rz = xn * rotation[2, 0] + yn * rotation[2, 1] + rotation[2, 2]
        norm = np.sqrt(rx * rx + ry * ry + rz * rz)
        rx, ry, rz = rx / norm, ry / norm, rz / norm
        e = n_ = np.nan
        ok = rz < -sin_min_depression
        if ok:
            t = -height_m / rz
            e = t * rx
            n_ = t * ry
            d2 = e * e + n_ * n_
            if not (d2 <= range_in2 or (d2 <= range_out2 and np.hypot(e, n_) <= max_range_m)):
                ok = False
                e = n_ = np.nan
        lat[i] = origin[0] + (n_ / origin[2]) * to_deg
        lon[i] = origin[1] + (e / origin[3]) * to_deg
        valid[i] = ok
        keep = True
        c = class_ids[i] - class_lo
        row = band_of_class[c] if 0 <= c < band_of_class.shape[0] else -1
        if row >= 0:
            slant = np.sqrt(e ** 2 + n_ ** 2 + h2)
            sin_depression = height_m / slant
            sure = False
            if np.isfinite(slant) and 0.0 <= sin_depression < 1.0:
                b = int(sin_depression * n_bins)
                dw = np.float64(boxes_xyxy[i, 2] - boxes_xyxy[i, 0])
                dh = np.float64(boxes_xyxy[i, 3] - boxes_xyxy[i, 1])
                size2 = (dw * dw + dh * dh) * (slant * slant) / focal2
                if sure_bounds[row, b, 1] <= size2 <= sure_bounds[row, b, 2]:
                    sure = True
                elif size2 < sure_bounds[row, b, 0] or size2 > sure_bounds[row, b, 3]:
                    sure = True
                    keep = False
            depression = np.nan if sure else np.arcsin(sin_depression) * to_deg
            if np.isfinite(slant) and np.isfinite(depression):  # the exact test
                diag = np.float64(np.hypot(boxes_xyxy[i, 2] - boxes_xyxy[i, 0], boxes_xyxy[i, 3] - boxes_xyxy[i, 1]))
                log_size = np.log(diag * slant / focal_px)
                mean, std = _band_at(depression, knots_deg, band_curves, row, n_knots[row])
                keep = np.abs(log_size - mean) <= k * std
        plausible[i] = keep
    return lat, lon, valid, plausible


@nb.njit(**_INLINE)
def _window_dx(gx, gx0, world_cells):  # pragma: no cover - compiled
    """gx - gx0 wrapped round the world as MemoryMap._wrap does (bit for bit)."""
    half = world_cells / 2
    t = gx - gx0 + half
    if not (0.0 <= t < world_cells):  # inside, the modulo is the identity (and costs ~20 ns)
        t = t % world_cells
    return t - half


@nb.njit(**_INLINE)
def _window_cell(gx, gy, gx0, gy0, world_cells, size):  # pragma: no cover - compiled
    """(row, col) of global cell (gx, gy) in the window of `size` cells at (gx0, gy0), lon wrapped as
    MemoryMap.local_indices does (bit for bit); (-1, -1) outside the window or for NaN."""
    dx = _window_dx(gx, gx0, world_cells)
    dy = gy - gy0
    if 0 <= dx < size and 0 <= dy < size:
        return int(np.floor(dy)), int(np.floor(dx))
    return -1, -1


@_compiled([nbt.float32[::1](nbt.float32[:, ::1], nbt.float64[::1], nbt.float64[::1], nbt.int64, nbt.int64,
                             nbt.float64, nbt.float64)])
def map_values(layer, gx, gy, gx0, gy0, world_cells, scale):  # pragma: no cover - compiled
    """MemoryMap.values_at for one (size, size) layer stored at window origin (gx0, gy0): (N,) float32
    stored value * float32(scale), clipped at 1; 0 outside the window."""
    size = layer.shape[0]
    out = np.zeros(gx.shape[0], np.float32)
    f = np.float32(scale)
    for i in range(gx.shape[0]):
        row, col = _window_cell(gx[i], gy[i], gx0, gy0, world_cells, size)
        if row >= 0:
            v = layer[row, col]
            if scale != 1.0:
                v = min(v * f, np.float32(1.0))
            out[i] = v
    return out


@_compiled([nbt.Tuple((nbt.float32[:, ::1], nbt.int64, nbt.int64, nbt.int64))(
    nbt.float64[::1], nbt.float64[::1], nbt.float32[::1], nbt.int64, nbt.int64, nbt.float64, nbt.int64, nbt.int64,
    nbt.boolean, nbt.float64)])
def stamp_impulses(gx, gy, amplitudes, gx0, gy0, world_cells, size, radius, take_max, scale):  # pragma: no cover
    """The impulse image of MemoryMap.add: points in the window with finite amplitude > 0, amplitude *
    float32(1 / scale) (stored units) put at their cell, per cell the maximum (take_max) or the sum in
    point order (as np.maximum.at / np.add.at).

    Returns (impulses (r1 - r0, c1 - c0) float32, r0, c0, points stamped): the image covers the points'
    cells plus `radius` around them, clipped to the window; (0, 0) with 0 points.
    """
    n = gx.shape[0]
    rows = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    amps = np.empty(n, np.float32)
    r_lo = c_lo = size
    r_hi = c_hi = -1
    count = 0
    f = np.float32(1.0 / scale)
    for i in range(n):
        a = amplitudes[i]
        if not (np.isfinite(a) and a > 0):
            continue
        r, c = _window_cell(gx[i], gy[i], gx0, gy0, world_cells, size)
        if r >= 0:
            rows[count] = r
            cols[count] = c
            amps[count] = a * f if scale != 1.0 else a
            r_lo, r_hi, c_lo, c_hi = min(r_lo, r), max(r_hi, r), min(c_lo, c), max(c_hi, c)
            count += 1
    if count == 0:
        return np.zeros((0, 0), np.float32), 0, 0, 0
    r0, r1 = max(r_lo - radius, 0), min(r_hi + radius + 1, size)
    c0, c1 = max(c_lo - radius, 0), min(c_hi + radius + 1, size)
    impulses = np.zeros((r1 - r0, c1 - c0), np.float32)
    for j in range(count):
        r, c = rows[j] - r0, cols[j] - c0
        if take_max:
            impulses[r, c] = max(impulses[r, c], amps[j])
        else:
            impulses[r, c] += amps[j]
    return impulses, r0, c0, count


@_compiled([nbt.float32[:, :, ::1](nbt.float32[:, ::1], nbt.float64[::1], nbt.float64[::1], nbt.int64, nbt.int64,
                                   nbt.float64, nbt.int64, nbt.float64)])
def map_patches(layer, gx, gy, gx0, gy0, world_cells, radius, scale):  # pragma: no cover - compiled
    """MemoryMap.patches for one (size, size) layer stored at window origin (gx0, gy0): (N, 2r+1, 2r+1)
    float32, the stored values around each point's cell * float32(scale), clipped at 1 (when scale != 1);
    0 outside the window. The point's cell is floor() of its offset from the origin, lon wrapped, as
    MemoryMap.local_indices gives it; NaN points (no cell) give zero patches."""
    n = gx.shape[0]
    size = layer.shape[0]
    side = 2 * radius + 1
    out = np.zeros((n, side, side), np.float32)
    f = np.float32(scale)
    for i in range(n):
        dx = np.floor(_window_dx(gx[i], gx0, world_cells))
        dy = np.floor(gy[i] - gy0)
        if not (np.isfinite(dx) and np.isfinite(dy)):
            continue
        r0 = int(dy) - radius
        c0 = int(dx) - radius
        for a in range(max(r0, 0), min(r0 + side, size)):
            for b in range(max(c0, 0), min(c0 + side, size)):
                v = layer[a, b]
                if scale != 1.0:
                    v = min(v * f, np.float32(1.0))
                out[i, a - r0, b - c0] = v
    return out


@_compiled([nbt.void(nbt.float32[:, :], nbt.float32[:, ::1], nbt.float32)])
def add_clipped(target, spread, cap):  # pragma: no cover - compiled
    """target = minimum(target + spread, cap) in place, in float32 (as numpy's += and np.minimum), in one pass."""
    for r in range(target.shape[0]):
        for c in range(target.shape[1]):
            target[r, c] = min(target[r, c] + spread[r, c], cap)


@_compiled([nbt.Tuple((nbt.int64[::1], nbt.boolean))(nbt.int64[::1], nbt.int64)])
def small_distinct(ids, max_span):  # pragma: no cover - compiled
    """Sorted distinct values of ids (N,) when they span fewer than max_span values, from one pass for the
    range and one to mark them; (empty, False) when they span more (the caller falls back to np.unique)."""
    n = ids.shape[0]
    if n == 0:
        return np.empty(0, np.int64), True
    lo = hi = ids[0]
    for i in range(n):
        lo = min(lo, ids[i])
        hi = max(hi, ids[i])
    if hi - lo >= max_span:
        return np.empty(0, np.int64), False
    seen = np.zeros(hi - lo + 1, np.bool_)
    for i in range(n):
        seen[ids[i] - lo] = True
    return np.flatnonzero(seen) + lo, True

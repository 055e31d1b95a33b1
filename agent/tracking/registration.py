"""Registration of a frame's detections to the predicted tracks: the common ground offset that a GPS or
gimbal error puts on every detection of the frame, removed before gating and assignment.

The memory map's correction (agent.telemetry_correction) already removes most of it when the pipeline
boosts; this stage does the same against the tracker's own predictions, so the tracker is robust without
the map too. Arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from agent.boxes import paired_iou
from agent.tracking.assignment import near_pairs
from shared.geo import EARTH_MEAN_RADIUS_M, GroundSurface, Pose
from shared.terrain import effective_height_m

__all__ = ["anchored_offset", "correction_jacobian", "correction_offset", "fit_pose_correction", "image_pairs",
           "model_heights", "point_heights", "track_offset"]


def track_offset(det_xy: NDArray, track_xy: NDArray, gate_m: float, min_pairs: int,
                 inlier_m: float = 1.5) -> tuple[float, float] | None:
    """The common offset (east, north) metres from detections to the tracks they lie next to.

    det_xy (N, 2) ground points of confident detections; track_xy (M, 2) predicted positions of confirmed
    tracks. Each detection pairs with its nearest track within gate_m when that track's nearest detection
    is it too (mutual nearest neighbours: a crowd does not pull the offset); the offset is the median of
    the pairs' differences, refined as the mean of the pairs within inlier_m of it. None with fewer than
    min_pairs pairs, or when fewer than half of them agree (no common offset: the tracks or detections
    are wrong, not the telemetry).
    """
    det_xy = np.asarray(det_xy, dtype=np.float64).reshape(-1, 2)
    track_xy = np.asarray(track_xy, dtype=np.float64).reshape(-1, 2)
    if len(det_xy) < min_pairs or len(track_xy) < min_pairs:
        return None
    i, j = near_pairs(det_xy, np.full(len(det_xy), gate_m), track_xy, np.zeros(len(track_xy)))
    if len(i) < min_pairs:
        return None
    d = np.hypot(*(track_xy[j] - det_xy[i]).T)
    order = np.lexsort((d, i))  # per detection, nearest track first
    first = np.ones(len(order), dtype=bool)
    first[1:] = i[order][1:] != i[order][:-1]
    best_det = order[first]
    order_t = np.lexsort((d, j))
    first_t = np.ones(len(order_t), dtype=bool)
    first_t[1:] = j[order_t][1:] != j[order_t][:-1]
    mutual = np.intersect1d(best_det, order_t[first_t])
    if len(mutual) < min_pairs:
        return None
    diff = track_xy[j[mutual]] - det_xy[i[mutual]]
    med = np.median(diff, axis=0)
    inl = np.hypot(*(diff - med).T) <= inlier_m
    if 2 * inl.sum() < len(diff) or inl.sum() < min_pairs:
        return None
    off = diff[inl].mean(axis=0)
    return float(off[0]), float(off[1])


def image_pairs(track_boxes: NDArray, track_cls: NDArray, det_boxes: NDArray, det_cls: NDArray,
                iou_min: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Tracks and detections that are each other's best image overlap of their class, with IoU >= iou_min.

    track_boxes (M, 4), det_boxes (N, 4) xyxy pixels (where each track is expected in this image, and the
    frame's detections); track_cls (M,), det_cls (N,). Returns (K,) int64 indices into each. Pairs made in
    the image do not depend on the telemetry: an error that moves every ground point of the frame (a GPS
    step, a jittering gimbal angle) leaves them as they are, so their ground differences measure it.
    """
    empty = np.zeros(0, np.int64)
    a = np.asarray(track_boxes, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(det_boxes, dtype=np.float64).reshape(-1, 4)
    if not len(a) or not len(b):
        return empty, empty
    # Only boxes whose centres are within their half-diagonals can overlap (k-d tree: 1,000 tracks stay
    # sparse). Ties go to the lower index, as an argmax over the dense IoU matrix would.
    i, j = near_pairs(0.5 * (a[:, :2] + a[:, 2:]), 0.5 * np.hypot(a[:, 2] - a[:, 0], a[:, 3] - a[:, 1]),
                      0.5 * (b[:, :2] + b[:, 2:]), 0.5 * np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]))
    keep = np.asarray(track_cls)[i] == np.asarray(det_cls)[j]
    i, j = i[keep], j[keep]
    iou = paired_iou(a[i], b[j])
    keep = iou > 0
    i, j, iou = i[keep], j[keep], iou[keep]
    if not len(i):
        return empty, empty
    by_row = np.lexsort((j, -iou, i))
    row_first = by_row[np.r_[True, i[by_row][1:] != i[by_row][:-1]]]
    by_col = np.lexsort((i, -iou, j))
    col_first = by_col[np.r_[True, j[by_col][1:] != j[by_col][:-1]]]
    mutual = np.intersect1d(row_first, col_first)
    mutual = mutual[iou[mutual] >= iou_min]
    mutual = mutual[np.argsort(i[mutual], kind="stable")]
    return i[mutual].astype(np.int64), j[mutual].astype(np.int64)


def anchored_offset(track_boxes: NDArray, track_cls: NDArray, track_xy: NDArray, det_boxes: NDArray,
                    det_cls: NDArray, det_xy: NDArray, iou_min: float, min_pairs: int,
                    inlier_m: float) -> tuple[tuple[float, float], int] | None:
    """The common ground offset (east, north) metres from detections to the tracks they overlap in the image.

    Pairs as `image_pairs`; track_xy (M, 2) predicted ground positions, det_xy (N, 2) the detections'
    ground points. The offset is the mean of the pairs' differences within inlier_m of their median.
    Returns (offset, inliers), or None with fewer than min_pairs inliers or when fewer than half agree.
    """
    ti, di = image_pairs(track_boxes, track_cls, det_boxes, det_cls, iou_min)
    if len(ti) < min_pairs:
        return None
    diff = np.asarray(track_xy, dtype=np.float64)[ti] - np.asarray(det_xy, dtype=np.float64)[di]
    diff = diff[np.isfinite(diff).all(axis=1)]
    if len(diff) < min_pairs:
        return None
    med = np.median(diff, axis=0)
    inl = np.hypot(*(diff - med).T) <= inlier_m
    n_in = int(inl.sum())
    if n_in < min_pairs or 2 * n_in < len(diff):
        return None
    off = diff[inl].mean(axis=0)
    return (float(off[0]), float(off[1])), n_in


def correction_jacobian(rel_xy: NDArray, height_m: float | NDArray) -> NDArray[np.float64]:
    """How ground points move with a small pose correction: (N, 2) east/north metres relative to the point
    below the UAV -> (N, 2, 4), the derivative of each point by (east m, north m, heading rad, pitch rad).

    A position error moves every point alike; a heading error turns the points about the UAV (clockwise:
    range * d_theta sideways); a pitch error (more depression) pulls them in along the ray by
    slant^2 / h * d_beta (flat ground; height_m per point: the effective heights over a terrain).
    """
    rel = np.asarray(rel_xy, dtype=np.float64).reshape(-1, 2)
    e, n = rel[:, 0], rel[:, 1]
    r = np.hypot(e, n)
    along = (r * r + height_m * height_m) / height_m
    unit = np.where(r[:, None] > 1e-9, rel / np.where(r > 1e-9, r, 1.0)[:, None], 0.0)
    J = np.zeros((len(rel), 2, 4))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = n, -e
    J[:, :, 3] = -along[:, None] * unit
    return J


def correction_offset(rel_xy: NDArray, height_m: float | NDArray, correction: NDArray,
                      jacobian: NDArray | None = None) -> NDArray[np.float64]:
    """How far ground points (N, 2, relative to the point below the UAV) move with a pose correction (east m, north
    m, heading rad, pitch rad): `correction_jacobian` @ correction, with the pitch part's new range no farther out
    than the visible horizon (or the point's own range beyond it). The linear pitch part, slant^2 / h * d_beta,
    is unbounded: near a level gimbal, applied frame after frame, it threw tracks 1e300 m out (the contract audit
    of 1 Dec 2026: `uavmm track` at pitch 0). Within the horizon it is the Jacobian's move, as before. jacobian:
    `correction_jacobian(rel_xy, height_m)` when the caller has it already."""
    rel = np.asarray(rel_xy, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(correction, dtype=np.float64)
    J = correction_jacobian(rel, height_m) if jacobian is None else jacobian
    out = J[:, :, :3] @ p[:3]
    h = np.broadcast_to(np.asarray(height_m, dtype=np.float64), (len(rel),))
    r = np.hypot(rel[:, 0], rel[:, 1])
    limit = np.maximum(r, np.sqrt(2.0 * EARTH_MEAN_RADIUS_M * h + h * h))
    moved = np.clip(r - (r * r + h * h) / h * p[3], -limit, limit)  # (negative: through the nadir)
    unit = np.where(r[:, None] > 1e-9, rel / np.where(r > 1e-9, r, 1.0)[:, None], 0.0)
    return out + (moved - r)[:, None] * unit


def model_heights(effective_m: NDArray, height_m: float) -> NDArray[np.float64]:
    """The flat error models' height per point from effective heights over a terrain (NaN: unknown): the pose's
    height_m where unknown, at least 1 m."""
    return np.maximum(np.where(np.isfinite(effective_m), effective_m, height_m), 1.0)


def point_heights(rel_xy: NDArray, pose: Pose, terrain: GroundSurface | None) -> float | NDArray[np.float64]:
    """The height of the flat error models (correction_jacobian, the measurement covariance) for ground points
    (N, 2) metres relative to the point below the UAV at pose: the pose's over flat ground; over a terrain with
    slopes (`gradient`, as shared.terrain.Terrain has) each point's effective height
    (shared.terrain.effective_height_m; `model_heights`), the pose's where the DEM does not reach."""
    if terrain is None or not hasattr(terrain, "gradient"):
        return pose.height_m
    rel = np.asarray(rel_xy, dtype=np.float64).reshape(-1, 2)
    up = terrain.up_m(rel[:, 0], rel[:, 1], pose)
    return model_heights(effective_height_m(rel[:, 0], rel[:, 1], up, pose, terrain),  # type: ignore[arg-type]
                         pose.height_m)


def fit_pose_correction(rel_xy: NDArray, residual: NDArray, S: NDArray, height_m: float | NDArray, prior_sd: NDArray,
                        gate_chi2: float, min_pairs: int, *,
                        robust_scale: bool = False) -> tuple[NDArray, NDArray, NDArray[np.bool_], float] | None:
    """The pose correction (east m, north m, heading rad, pitch rad) that moves detections onto their tracks.

    rel_xy (K, 2): the paired detections' ground points relative to the point below the UAV, metres;
    residual (K, 2): track position - detection point; S (K, 2, 2): each pair's own error (track
    prediction + the detection's pixel error), square metres; prior_sd (4,): how large each part of the
    correction is expected to be (a weak position prior and tight angle priors make a far cluster of
    pairs a shift, pairs spread in range and bearing a turn). Weighted least squares with that prior
    (ridge), refitted without the pairs beyond gate_chi2 (squared Mahalanobis, each pair's S; on the
    better half of them when most are beyond it) until the inliers settle.
    With robust_scale, S is first scaled by c = max(1, median(d2) / 1.386) (the median of a chi-square of
    2 degrees of freedom is 1.386) from the residuals of a first fit: pairs noisier than their S says
    (part boxes, walking people) widen the gate and the correction's covariance instead of failing.
    Returns (p (4,), cov (4, 4), inliers (K,) bool, c), or None with fewer than min_pairs inliers or
    fewer than half of the pairs.
    """
    rel = np.asarray(rel_xy, dtype=np.float64).reshape(-1, 2)
    res = np.asarray(residual, dtype=np.float64).reshape(-1, 2)
    k = len(rel)
    if k < min_pairs:
        return None
    J = correction_jacobian(rel, height_m)
    W = np.linalg.inv(np.asarray(S, dtype=np.float64).reshape(-1, 2, 2))
    prior = np.diag(1.0 / np.square(np.asarray(prior_sd, dtype=np.float64)))
    inl = np.ones(k, dtype=bool)
    p = cov = np.zeros(4)
    scale = 1.0
    if robust_scale:
        A = (J.transpose(0, 2, 1) @ W @ J).sum(axis=0) + prior
        p0 = np.linalg.solve(A, np.einsum("kij,kj->i", J.transpose(0, 2, 1) @ W, res))
        left = res - np.einsum("kij,j->ki", J, p0)
        scale = max(1.0, float(np.median(np.einsum("ki,kij,kj->k", left, W, left))) / 1.386)
        W = W / scale
    for _ in range(4):
        JtW = J[inl].transpose(0, 2, 1) @ W[inl]  # (k, 4, 2)
        A = (JtW @ J[inl]).sum(axis=0) + prior
        b = np.einsum("kij,kj->i", JtW, res[inl])
        cov = np.linalg.inv(A)
        p = cov @ b
        left = res - np.einsum("kij,j->ki", J, p)
        d2 = np.einsum("ki,kij,kj->k", left, W, left)
        new = d2 <= gate_chi2
        if 2 * new.sum() < k:
            # a wrong pair pulled the fit so far that most pairs fail the gate: refit on the better half
            new = d2 <= np.median(d2)
        if (new == inl).all():
            break
        inl = new
    n_in = int((d2 <= gate_chi2).sum())
    inl = d2 <= gate_chi2
    if n_in < min_pairs or 2 * n_in < k:
        return None
    return p, cov, inl, scale

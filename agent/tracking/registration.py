"""Registration of a frame's detections to the predicted tracks: the common ground offset that a GPS or
gimbal error puts on every detection of the frame, removed before gating and assignment.

The memory map's correction (agent.telemetry_correction) already removes most of it when the pipeline
boosts; this stage does the same against the tracker's own predictions, so the tracker is robust without
the map too. Arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from agent.boxes import box_iou
from agent.tracking.assignment import near_pairs

__all__ = ["anchored_offset", "track_offset"]


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


def anchored_offset(track_boxes: NDArray, track_cls: NDArray, track_xy: NDArray, det_boxes: NDArray,
                    det_cls: NDArray, det_xy: NDArray, iou_min: float, min_pairs: int,
                    inlier_m: float) -> tuple[tuple[float, float], int] | None:
    """The common ground offset (east, north) metres from detections to the tracks they overlap in the image.

    track_boxes (M, 4) xyxy pixels: where each track is expected in this image (its last box moved by its
    image velocity); track_cls (M,), track_xy (M, 2) predicted ground positions; det_boxes (N, 4),
    det_cls (N,), det_xy (N, 2) the frame's confident detections and their ground points. A detection
    and a track pair when they are each other's best overlap of their class with IoU >= iou_min: the
    pair is made in the image, so an error of the telemetry (a GPS step, a jittering gimbal angle) that
    moves every ground point of the frame does not break it, and the pairs' ground differences measure
    that error. The offset is the mean of the differences within inlier_m of their median. Returns
    (offset, inliers), or None with fewer than min_pairs inliers or when fewer than half agree.
    """
    track_boxes = np.asarray(track_boxes, dtype=np.float64).reshape(-1, 4)
    det_boxes = np.asarray(det_boxes, dtype=np.float64).reshape(-1, 4)
    if len(track_boxes) < min_pairs or len(det_boxes) < min_pairs:
        return None
    iou = box_iou(track_boxes, det_boxes)
    iou[np.asarray(track_cls)[:, None] != np.asarray(det_cls)[None, :]] = 0.0
    best_det = iou.argmax(axis=1)
    best_track = iou.argmax(axis=0)
    ti = np.flatnonzero((best_track[best_det] == np.arange(len(track_boxes)))
                        & (iou[np.arange(len(track_boxes)), best_det] >= iou_min))
    if len(ti) < min_pairs:
        return None
    diff = np.asarray(track_xy, dtype=np.float64)[ti] - np.asarray(det_xy, dtype=np.float64)[best_det[ti]]
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

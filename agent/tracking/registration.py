"""Registration of a frame's detections to the predicted tracks: the common ground offset that a GPS or
gimbal error puts on every detection of the frame, removed before gating and assignment.

The memory map's correction (agent.telemetry_correction) already removes most of it when the pipeline
boosts; this stage does the same against the tracker's own predictions, so the tracker is robust without
the map too. Arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from agent.tracking.assignment import near_pairs

__all__ = ["track_offset"]


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

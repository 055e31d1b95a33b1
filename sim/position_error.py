"""Ground error of a tracker's reported positions against the simulator's truth (`uavmm eval` tracking).

Per frame, the reported tracks are matched one-to-one to the ground-truth boxes (Hungarian on 1 - IoU,
pairs below `MATCH_IOU` dropped) and each match gives the distance in metres between the track's reported
lat/lon and the object's true lat/lon (simulated annotations carry it). Arrays in, arrays out: no I/O.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from agent.boxes import box_iou
from shared.geo import latlon_to_local

__all__ = ["MATCH_IOU", "format_metres", "frame_position_errors", "mean_known", "summarise_position_errors"]

#: Minimum IoU between a track's box and a ground-truth box for the pair to be measured.
MATCH_IOU = 0.5


def frame_position_errors(gt_boxes_xyxy: NDArray, gt_latlon: NDArray, track_boxes_xyxy: NDArray,
                          track_latlon: NDArray, *, min_iou: float = MATCH_IOU) -> NDArray[np.float64]:
    """Ground distance of each matched (track, ground truth) pair of one frame.

    Parameters
    ----------
    gt_boxes_xyxy : (K, 4) float
        Ground-truth boxes, pixels.
    gt_latlon : (K, 2) float
        The objects' true lat, lon (degrees); rows with NaN are not measured.
    track_boxes_xyxy : (M, 4) float
        The reported tracks' boxes, pixels.
    track_latlon : (M, 2) float
        The tracks' reported lat, lon (degrees); rows with NaN (no ground position) are not measured.
    min_iou : float
        Pairs with a lower IoU are not matches.

    Returns
    -------
    (P,) float64
        Metres between reported and true position of each match (P <= min(K, M)); empty when nothing
        matches. Distances in the tangent plane at the frame's mean true position (mm-exact within a
        few hundred metres).
    """
    gt_boxes = np.asarray(gt_boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    tr_boxes = np.asarray(track_boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    gt_ll = np.asarray(gt_latlon, dtype=np.float64).reshape(-1, 2)
    tr_ll = np.asarray(track_latlon, dtype=np.float64).reshape(-1, 2)
    if len(gt_ll) != len(gt_boxes) or len(tr_ll) != len(tr_boxes):
        raise ValueError(f"boxes and lat/lon must have the same rows: ground truth {len(gt_boxes)} vs "
                         f"{len(gt_ll)}, tracks {len(tr_boxes)} vs {len(tr_ll)}")
    if not len(gt_boxes) or not len(tr_boxes):
        return np.zeros(0)
    iou = box_iou(gt_boxes, tr_boxes)
    rows, cols = linear_sum_assignment(1.0 - iou)
    keep = iou[rows, cols] >= min_iou
    rows, cols = rows[keep], cols[keep]
    known = np.isfinite(gt_ll[rows]).all(axis=1) & np.isfinite(tr_ll[cols]).all(axis=1)
    rows, cols = rows[known], cols[known]
    if not len(rows):
        return np.zeros(0)
    lat0, lon0 = (float(v) for v in gt_ll[rows].mean(axis=0))
    ge, gn = latlon_to_local(gt_ll[rows, 0], gt_ll[rows, 1], lat0, lon0)
    te, tn = latlon_to_local(tr_ll[cols, 0], tr_ll[cols, 1], lat0, lon0)
    return np.hypot(te - ge, tn - gn)


def summarise_position_errors(errors_m: NDArray) -> dict[str, Any]:
    """``pos_err_m`` (median), ``pos_err_p90_m`` (90th percentile), metres, and ``pos_err_n`` (matches) of
    a (N,) array of distances; the two figures are None when N = 0 (JSON null, a blank in tables)."""
    errors = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    errors = errors[np.isfinite(errors)]
    if not len(errors):
        return {"pos_err_m": None, "pos_err_p90_m": None, "pos_err_n": 0}
    return {"pos_err_m": float(np.median(errors)), "pos_err_p90_m": float(np.percentile(errors, 90)),
            "pos_err_n": int(len(errors))}


def mean_known(values: list[float | None]) -> float | None:
    """Mean of the values that are not None or NaN; None when there are none (a blank in tables)."""
    known = [float(v) for v in values if v is not None and math.isfinite(v)]
    return sum(known) / len(known) if known else None


def format_metres(value: float | None) -> str:
    """A distance for a Markdown table cell: two decimals, blank when unknown (None or NaN)."""
    return "" if value is None or not math.isfinite(value) else f"{value:.2f}"

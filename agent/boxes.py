"""Image boxes (xyxy pixels): the point where a box meets the ground, how two boxes overlap, and
class-wise non-maximum suppression.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agent._kernels import nms_ranked, rank_keys

__all__ = ["ANCHORS", "anchor_fraction", "anchor_points", "box_anchor_points", "box_iou", "nms", "outranked_overlaps",
           "paired_iou", "unboost_fragments"]

#: Where on a box its ground point is (`PipelineConfig.anchor`).
ANCHORS = ("auto", "center", "bottom")


def anchor_fraction(anchor: str, pitch_deg: float) -> float:
    """Height of a box's ground point in the box, 0 (top edge) to 1 (bottom edge)."""
    if anchor == "center":
        return 0.5
    if anchor == "bottom":
        return 1.0
    # upright objects stand on their box's bottom edge at grazing views, centred at nadir
    return 0.5 + 0.5 * math.cos(math.radians(pitch_deg))


def box_anchor_points(boxes_xyxy: NDArray, anchor: str, pitch_deg: float) -> NDArray[np.float64]:
    """(N, 4) boxes -> (N, 2) pixel of each box's ground point."""
    return anchor_points(boxes_xyxy, anchor_fraction(anchor, pitch_deg))


def anchor_points(boxes_xyxy: NDArray, frac: float) -> NDArray[np.float64]:
    """(N, 4) boxes -> (N, 2) pixels at the middle of each box, frac of its height down (anchor_fraction)."""
    x1, y1, x2, y2 = (boxes_xyxy[:, i].astype(np.float64) for i in range(4))
    return np.column_stack([(x1 + x2) / 2.0, y1 + frac * (y2 - y1)])


def box_iou(a_xyxy: NDArray, b_xyxy: NDArray) -> NDArray[np.float64]:
    """(A, 4) x (B, 4) xyxy boxes -> (A, B) float64 IoU (0 for empty unions)."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    iw = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0.0, None)
    ih = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0.0, None)
    inter = iw * ih
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def outranked_overlaps(boxes_xyxy: NDArray, rank: NDArray, min_iou: float,
                       class_ids: NDArray | None = None, rows: NDArray | None = None) -> NDArray[np.bool_]:
    """(N,) bool: which boxes a box of higher rank (and of the same class, when class_ids is given) overlaps by
    an IoU of at least min_iou; ties in rank do not outrank. rows: test only these indices (the others False).
    An R x N matrix (R = len(rows), N without): meant for the few hundred boxes a frame keeps, not for a
    detector's candidates."""
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    rank = np.asarray(rank, dtype=np.float64)
    sel = slice(None) if rows is None else np.asarray(rows, dtype=np.int64)  # a slice: views, no copies
    above = rank[None, :] > rank[sel, None]
    if class_ids is not None:
        class_ids = np.asarray(class_ids)
        above &= class_ids[None, :] == class_ids[sel, None]
    hit = np.asarray(((box_iou(boxes[sel], boxes) >= min_iou) & above).any(axis=1))  # (R,) bool
    if rows is None:
        return hit
    out = np.zeros(len(boxes), dtype=bool)
    out[sel] = hit
    return out


def unboost_fragments(boxes: NDArray, conf: NDArray, boosted: NDArray, class_ids: NDArray, keep: NDArray[np.int64],
                      fragment_iou: float, score_threshold: float) -> NDArray[np.int64]:
    """The boxes NMS kept (keep, highest boosted score first), with the boost taken back (boosted, in place:
    the detector's calibrated score conf again) from every kept box that a kept box of its class with a
    higher boosted score overlaps by an IoU of at least fragment_iou (PipelineConfig.fragment_iou; kept
    boxes overlap by at most nms_iou); reordered by score, those at or below score_threshold dropped.

    Done on the kept boxes (at most max_detections), not on the candidates: ~100 boxes a frame whatever the
    detector emits."""
    score = boosted[keep]
    # only a boosted box can lose something
    hit = (score > conf[keep]) & outranked_overlaps(boxes[keep], score, fragment_iou, class_ids[keep])
    if not hit.any():
        return keep
    back = keep[hit]
    boosted[back] = conf[back]
    order = np.argsort(-boosted[keep], kind="stable")  # ties keep NMS's order
    keep = keep[order]
    return keep[boosted[keep].astype(np.float32) > np.float32(score_threshold)]


def paired_iou(a_xyxy: NDArray, b_xyxy: NDArray, *, generalised: bool = False) -> NDArray[np.float64]:
    """(K, 4) x (K, 4) xyxy boxes -> (K,) IoU of a[k] with b[k] (0 for empty unions); generalised: the
    generalised IoU (Rezatofighi et al. 2019), IoU minus the share of the two boxes' hull they leave empty,
    in [-1, 1]."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    inter = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0.0, None) \
        * np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0.0, None)
    union = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]) + (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) - inter
    iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    if generalised:
        hull = (np.maximum(a[:, 2], b[:, 2]) - np.minimum(a[:, 0], b[:, 0])) \
            * (np.maximum(a[:, 3], b[:, 3]) - np.minimum(a[:, 1], b[:, 1]))
        iou -= np.where(hull > 0, (hull - union) / np.where(hull > 0, hull, 1.0), 0.0)
    return iou


def nms(boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray, iou: float,
        score_threshold: float, max_detections: int) -> NDArray[np.int64]:
    """Class-wise greedy NMS; indices of the kept boxes, highest score first, at most max_detections.

    boxes_xyxy (N, 4) pixels (float32 or float64; other dtypes are taken as float64), scores (N,),
    class_ids (N,) int; iou and score_threshold >= 0 (ValueError otherwise, as OpenCV asserts).
    Boxes with score <= score_threshold (float32 compare) are dropped; equal scores rank by index.
    The same boxes in the same order as cv2.dnn.NMSBoxesBatched over all N boxes, in OpenCV's Rect2d
    arithmetic (NaN, empty and negative-size boxes included), from a compiled kernel
    (agent._kernels.nms_ranked) that stops at max_detections and compares each box only with the kept
    boxes it may intersect: ~0.07 ms at 5,000 clustered candidates.
    """
    if not (iou >= 0 and score_threshold >= 0):
        raise ValueError(f"nms needs iou >= 0 and score_threshold >= 0, got {iou!r} and {score_threshold!r}")
    n = len(scores)
    if n == 0 or max_detections < 1:
        return np.zeros(0, dtype=np.int64)
    scores = np.ascontiguousarray(scores, dtype=np.float32).reshape(-1)
    boxes = np.asarray(boxes_xyxy)
    boxes = np.ascontiguousarray(boxes, dtype=np.float32 if boxes.dtype == np.float32 else np.float64).reshape(-1, 4)
    cids = np.ascontiguousarray(class_ids, dtype=np.int64).reshape(-1)
    keys = np.sort(rank_keys(scores, float(score_threshold)))  # numpy's sort is SIMD: ~15x numba's
    return nms_ranked(boxes, keys, cids, float(iou), int(max_detections))

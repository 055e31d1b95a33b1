"""Detection evaluation helpers: COCO AP50 / AR@100 (pycocotools), pre-NMS recall and the NMS baseline.

Inputs are the dataset layout of DESIGN.md 6: an ``images.json`` COCO ground truth (path or dict) and COCO
result lists ``[{image_id, category_id, bbox: [x, y, w, h], score}]`` (list or path to a JSON file).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from agent.coco_metrics import coco_detection_metrics, load_images, load_results

logger = logging.getLogger(__name__)

__all__ = ["baseline_nms", "coco_detection_metrics", "pr_curve", "prenms_recall", "recall_at_precision",
           "threshold_at_precision"]


def _iou_matrix(a_xywh: np.ndarray, b_xywh: np.ndarray) -> np.ndarray:
    """(A, 4) x (B, 4) COCO boxes -> (A, B) IoU."""
    ax0, ay0 = a_xywh[:, 0:1], a_xywh[:, 1:2]
    ax1, ay1 = ax0 + a_xywh[:, 2:3], ay0 + a_xywh[:, 3:4]
    bx0, by0 = b_xywh[None, :, 0], b_xywh[None, :, 1]
    bx1, by1 = bx0 + b_xywh[None, :, 2], by0 + b_xywh[None, :, 3]
    iw = np.clip(np.minimum(ax1, bx1) - np.maximum(ax0, bx0), 0.0, None)
    ih = np.clip(np.minimum(ay1, by1) - np.maximum(ay0, by0), 0.0, None)
    inter = iw * ih
    union = a_xywh[:, 2:3] * a_xywh[:, 3:4] + (b_xywh[:, 2] * b_xywh[:, 3])[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def _group_by_image(results: Sequence[dict[str, Any]]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """image_id -> (boxes (K, 4), scores (K,), category_ids (K,)) arrays."""
    if not results:
        return {}
    img = np.fromiter((int(r["image_id"]) for r in results), dtype=np.int64, count=len(results))
    boxes = np.array([r["bbox"] for r in results], dtype=np.float64).reshape(-1, 4)
    scores = np.fromiter((float(r["score"]) for r in results), dtype=np.float64, count=len(results))
    cats = np.fromiter((int(r["category_id"]) for r in results), dtype=np.int64, count=len(results))
    order = np.argsort(img, kind="stable")
    img, boxes, scores, cats = img[order], boxes[order], scores[order], cats[order]
    uniq, starts = np.unique(img, return_index=True)
    ends = np.append(starts[1:], len(img))
    return {int(u): (boxes[s:e], scores[s:e], cats[s:e]) for u, s, e in zip(uniq, starts, ends, strict=True)}


def prenms_recall(images_json: str | Path | dict[str, Any], candidates: str | Path | Sequence[dict[str, Any]],
                  iou: float = 0.5, *, score_threshold: float = 0.0) -> float:
    """Fraction of ground-truth boxes matched by at least one candidate of the same class with IoU >= iou.

    Parameters
    ----------
    images_json : path or dict
        COCO ground truth; ``iscrowd`` annotations are ignored.
    candidates : path or list of dict
        COCO results (pre-NMS candidates, or an NMS output for post-NMS recall).
    iou : float
        IoU needed for a match.
    score_threshold : float
        Only candidates with score >= this count (e.g. 0.25 for the recall "after NMS" of PAPER.md 2).

    Returns
    -------
    float
        Recall in [0, 1]; NaN when there is no ground truth.
    """
    gt = load_images(images_json)
    cands = [c for c in load_results(candidates) if float(c["score"]) >= score_threshold]
    by_image = _group_by_image(cands)
    anns = [a for a in gt["annotations"] if not a.get("iscrowd", 0)]
    if not anns:
        return float("nan")
    gt_by_image = _group_by_image([{**a, "score": 1.0} for a in anns])
    matched = 0
    for image_id, (g_boxes, _, g_cats) in gt_by_image.items():
        if image_id not in by_image:
            continue
        c_boxes, _, c_cats = by_image[image_id]
        ious = _iou_matrix(g_boxes, c_boxes)
        ok = (ious >= iou) & (g_cats[:, None] == c_cats[None, :])
        matched += int(ok.any(axis=1).sum())
    return matched / len(anns)


def _inside_fraction(a_xywh: np.ndarray, b_xywh: np.ndarray) -> np.ndarray:
    """(A, B) intersection of COCO boxes a with boxes b over a's area: COCO's IoU against a crowd box."""
    lt = np.maximum(a_xywh[:, None, :2], b_xywh[None, :, :2])
    rb = np.minimum(a_xywh[:, None, :2] + a_xywh[:, None, 2:], b_xywh[None, :, :2] + b_xywh[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0.0, None), axis=2)
    return inter / np.maximum(a_xywh[:, 2] * a_xywh[:, 3], 1e-12)[:, None]


def pr_curve(images_json: str | Path | dict[str, Any], results: str | Path | Sequence[dict[str, Any]],
             iou: float = 0.5) -> dict[str, np.ndarray]:
    """Precision-recall curve at one IoU: arrays over detections sorted by score (descending).

    Greedy one-to-one matching per image and class in score order (as COCO does; a detection left unmatched inside
    a crowd box of its class is ignored, as COCO does). Returns
    {"scores", "precision", "recall"}, each (D,) float64; recall is NaN without ground truth.
    """
    gt = load_images(images_json)
    dets = list(load_results(results))
    anns = [a for a in gt["annotations"] if not a.get("iscrowd", 0)]
    gt_by_image = _group_by_image([{**a, "score": 1.0} for a in anns])
    crowd_by_image = _group_by_image([{**a, "score": 1.0} for a in gt["annotations"] if a.get("iscrowd", 0)])
    all_scores: list[np.ndarray] = []
    all_tp: list[np.ndarray] = []
    for image_id, (d_boxes, d_scores, d_cats) in _group_by_image(dets).items():
        tp = np.zeros(len(d_scores), dtype=bool)
        keep = np.ones(len(d_scores), dtype=bool)
        if image_id in gt_by_image:
            g_boxes, _, g_cats = gt_by_image[image_id]
            ious = _iou_matrix(d_boxes, g_boxes)
            ious[d_cats[:, None] != g_cats[None, :]] = 0.0
            taken = np.zeros(len(g_boxes), dtype=bool)
            for i in np.argsort(-d_scores, kind="stable"):
                cand = np.where(taken, -1.0, ious[i])
                j = int(np.argmax(cand)) if len(cand) else -1
                if j >= 0 and cand[j] >= iou:
                    taken[j] = tp[i] = True
        if image_id in crowd_by_image:  # an unmatched detection inside a crowd region of its class: ignored (COCO)
            c_boxes, _, c_cats = crowd_by_image[image_id]
            ioa = _inside_fraction(d_boxes, c_boxes)
            ioa[d_cats[:, None] != c_cats[None, :]] = 0.0
            keep = tp | ~(ioa >= iou).any(axis=1)
        all_scores.append(d_scores[keep])
        all_tp.append(tp[keep])
    scores = np.concatenate(all_scores) if all_scores else np.zeros(0)
    tps = np.concatenate(all_tp) if all_tp else np.zeros(0, dtype=bool)
    order = np.argsort(-scores, kind="stable")
    cum_tp = np.cumsum(tps[order])
    precision = cum_tp / np.arange(1, len(order) + 1)
    recall = cum_tp / len(anns) if anns else np.full(len(order), np.nan)
    return {"scores": scores[order], "precision": precision, "recall": recall}


def operating_point(images_json: str | Path | dict[str, Any], results: str | Path | Sequence[dict[str, Any]],
                    score_threshold: float = 0.25, iou: float = 0.5) -> dict[str, float]:
    """Precision and recall of the detections a deployment keeps (score >= score_threshold)."""
    curve = pr_curve(images_json, results, iou)
    k = int(np.searchsorted(-curve["scores"], -score_threshold, side="right"))
    if k == 0:
        return {"precision": 1.0, "recall": 0.0}
    return {"precision": float(curve["precision"][k - 1]), "recall": float(curve["recall"][k - 1])}


def recall_at_precision(curve: dict[str, np.ndarray], precision: float) -> float:
    """Highest recall of a PR curve (pr_curve) whose precision is at least `precision`; 0 if none."""
    ok = curve["precision"] >= precision
    return float(curve["recall"][ok].max()) if ok.any() else 0.0


def threshold_at_precision(curve: dict[str, np.ndarray], precision: float) -> float:
    """Score threshold of a PR curve's highest-recall point with precision >= `precision`.

    Keeping the detections with score >= the returned value gives that point (the operating point of
    `recall_at_precision`). +inf when no point reaches the precision (keep nothing).
    """
    ok = np.flatnonzero(curve["precision"] >= precision)
    if not len(ok):
        return float("inf")
    best = ok[int(np.argmax(curve["recall"][ok]))]
    return float(curve["scores"][best])


def baseline_nms(candidates: str | Path | Sequence[dict[str, Any]], iou: float = 0.5) -> list[dict[str, Any]]:
    """The single-frame baseline: class-wise NMS per image (cv2.dnn.NMSBoxesBatched), every score kept.

    Parameters
    ----------
    candidates : path or list of dict
        COCO results ``{image_id, category_id, bbox [x, y, w, h], score}``.
    iou : float
        NMS IoU threshold.

    Returns
    -------
    list of dict
        The kept candidates (new dicts, ``bbox`` as floats), in image order then by descending score.
    """
    out: list[dict[str, Any]] = []
    for image_id, (boxes, scores, cats) in sorted(_group_by_image(load_results(candidates)).items()):
        # cv2 keeps scores strictly above the threshold: pass one below every score to keep them all.
        below = float(min(scores.min(), 0.0)) - 1.0
        keep = np.asarray(cv2.dnn.NMSBoxesBatched(boxes.tolist(), scores.tolist(), cats.tolist(),
                                                  below, float(iou)), dtype=np.int64).ravel()
        keep = keep[np.argsort(-scores[keep], kind="stable")]
        out.extend({"image_id": image_id, "category_id": int(cats[k]), "bbox": [float(x) for x in boxes[k]],
                    "score": float(scores[k])} for k in keep)
    return out

"""COCO detection metrics with pycocotools: AP50, AP and AR@100 of a result list against a ground truth.

The scores the paper reports. `uavmm tune` picks parameters by them and `uavmm eval` (sim.metrics,
sim.evaluate) reports them; inputs follow DESIGN.md section 6 (an ``images.json`` COCO dict or its path,
COCO result lists or their path).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from agent.dataset import read_json

__all__ = ["coco_detection_metrics", "load_images", "load_results"]


def _load_json(obj: Any, what: str) -> Any:
    """obj itself, or the JSON file it names (agent.dataset.read_json: errors name the file)."""
    return read_json(obj, what) if isinstance(obj, (str, Path)) else obj


def load_images(images_json: str | Path | dict[str, Any]) -> dict[str, Any]:
    """A COCO ground truth (dict, or path to its JSON) with 'images' and 'annotations'; ValueError otherwise."""
    gt = _load_json(images_json, "images")
    if not isinstance(gt, dict) or "images" not in gt or "annotations" not in gt:
        raise ValueError("images JSON must be a COCO dict with 'images' and 'annotations'")
    return gt


def load_results(results: str | Path | Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """A COCO result list (list, or path to its JSON); ValueError otherwise."""
    res = _load_json(results, "results")
    if not isinstance(res, list):
        raise ValueError(f"results must be a list of COCO result dicts, got {type(res).__name__}")
    return res


def coco_detection_metrics(images_json: str | Path | dict[str, Any],
                           results: str | Path | Sequence[dict[str, Any]], *,
                           image_ids: Iterable[int] | None = None) -> dict[str, float]:
    """COCO bounding-box metrics of `results` against the ground truth, as the paper reports them.

    Parameters
    ----------
    images_json : path or dict
        COCO ground truth (``images``, ``annotations``, ``categories``).
    results : path or list of dict
        ``{image_id, category_id, bbox [x, y, w, h], score}``; not modified.
    image_ids : iterable of int, optional
        Evaluate only these images (default: all images of the ground truth).

    Returns
    -------
    dict
        ``AP50`` (AP at IoU 0.5), ``AP`` (IoU 0.5:0.95) and ``AR100`` (recall averaged over IoU 0.5:0.95,
        at most 100 detections per image), all areas, as FRACTIONS in [0, 1] (pycocotools' scale; multiply
        by 100 for the paper's tables). With no results, or no ground truth, every value is 0.
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt = load_images(images_json)
    res = [dict(r) for r in load_results(results)]  # loadRes writes into the dicts
    ids = sorted({int(i["id"]) for i in gt["images"]}) if image_ids is None else sorted({int(i) for i in image_ids})
    if ids:
        id_set = set(ids)
        res = [r for r in res if int(r["image_id"]) in id_set]
    if not res or not ids:
        return {"AP50": 0.0, "AP": 0.0, "AR100": 0.0}
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = {"images": gt["images"], "annotations": gt["annotations"],
                           "categories": gt.get("categories", [])}
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(res)
        ev = COCOeval(coco_gt, coco_dt, "bbox")
        ev.params.imgIds = ids
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    stats = [max(float(s), 0.0) for s in ev.stats]  # -1 (no ground truth) -> 0
    return {"AP50": stats[1], "AP": stats[0], "AR100": stats[8]}

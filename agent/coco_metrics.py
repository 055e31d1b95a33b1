"""COCO detection metrics with pycocotools: AP50, AP and AR@100 of a result list against a ground truth.

The scores the paper reports. `uavmm tune` picks parameters by them and `uavmm eval` (sim.metrics,
sim.evaluate) reports them; inputs follow DESIGN.md section 6 (an ``images.json`` COCO dict or its path,
COCO result lists or their path).
"""

from __future__ import annotations

import contextlib
import io
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from agent.dataset import int_text, read_json

__all__ = ["coco_detection_metrics", "load_images", "load_results", "per_class_metrics"]


def _load_json(obj: Any, what: str) -> Any:
    """obj itself, or the JSON file it names (agent.dataset.read_json: errors name the file)."""
    return read_json(obj, what) if isinstance(obj, (str, Path)) else obj


def load_images(images_json: str | Path | dict[str, Any]) -> dict[str, Any]:
    """A COCO ground truth (dict, or path to its JSON) with 'images' and 'annotations'; ValueError otherwise, and for
    an annotation pycocotools would misread (see `_checked_annotations`)."""
    gt = _load_json(images_json, "images")
    if not isinstance(gt, dict) or "images" not in gt or "annotations" not in gt:
        raise ValueError("images JSON must be a COCO dict with 'images' and 'annotations'")
    annotations = _checked_annotations(gt)
    return gt if annotations is gt["annotations"] else {**gt, "annotations": annotations}


def _integer(value: Any) -> int | None:
    """An id as an int: an int, or an integral number or numeric string ("3464", as the candidate loader reads)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        try:
            return int(value.strip())  # exact for any length ("9007199254740993" through float lost its last digit)
        except ValueError:
            pass
    try:
        number = float(value) if isinstance(value, (float, str)) else math.nan
    except ValueError:
        return None
    return int(number) if math.isfinite(number) and number == int(number) else None


def _checked_annotations(gt: dict[str, Any]) -> list[Any]:
    """The annotations with integer ``image_id`` / ``category_id`` (numeric strings read as numbers: pycocotools
    matched none of them and every class scored 0) and ``bbox`` as 4 finite numbers of non-negative size; the list
    itself when nothing needed converting. ValueError naming the first annotation otherwise (a missing or short
    bbox was a pycocotools traceback, a negative size a box it silently ignores), or a category_id the file does
    not list."""
    annotations = gt["annotations"]
    if not isinstance(annotations, list):
        raise ValueError("images JSON: 'annotations' must be a list")
    listed = {_integer(c.get("id")) for c in gt.get("categories") or [] if isinstance(c, dict)}
    out, changed = [], False
    for i, a in enumerate(annotations):
        where = f"images JSON: annotation {i}"
        if not isinstance(a, dict):
            raise ValueError(f"{where} is not an object")
        image_id, category_id = _integer(a.get("image_id")), _integer(a.get("category_id"))
        if image_id is None or category_id is None:
            bad = "image_id" if image_id is None else "category_id"
            raise ValueError(f"{where} (id {a.get('id')!r}): {bad} {a.get(bad)!r} is not an integer")
        if listed and category_id not in listed:
            raise ValueError(f"{where} (id {a.get('id')!r}): category_id {category_id} is not in 'categories'")
        box = a.get("bbox")
        items = box if isinstance(box, list | tuple) else ()
        try:
            numbers = [float(v) for v in items]
        except (TypeError, ValueError):
            numbers = []
        if len(numbers) != 4 or not all(map(math.isfinite, numbers)) or numbers[2] < 0 or numbers[3] < 0:
            raise ValueError(f"{where} (id {a.get('id')!r}): bbox {box!r:.80} is not [x, y, w, h] of finite numbers "
                             "with w, h >= 0")
        if (image_id is not a["image_id"] or category_id is not a["category_id"]
                or any(type(v) is not float and type(v) is not int for v in items)):
            a = {**a, "image_id": image_id, "category_id": category_id, "bbox": numbers}
            changed = True
        out.append(a)
    return out if changed else annotations


def load_results(results: str | Path | Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """A COCO result list (list, or path to its JSON); ValueError otherwise."""
    res = _load_json(results, "results")
    if not isinstance(res, list):
        raise ValueError(f"results must be a list of COCO result dicts, got {type(res).__name__}")
    return res


def _gt_dataset(gt: dict[str, Any]) -> dict[str, Any]:
    """The ground truth as pycocotools reads it: real files often leave out ``iscrowd`` and ``area`` (COCO's
    own loader needs both), which default to 0 and the box's area."""
    annotations = []
    for a in gt["annotations"]:
        if "iscrowd" not in a or "area" not in a:
            a = dict(a)
            a.setdefault("iscrowd", 0)
            if "area" not in a:
                box = a.get("bbox") or [0, 0, 0, 0]
                a["area"] = float(box[2]) * float(box[3])
        annotations.append(a)
    images = [dict(im, id=whole_number(im["id"])) if isinstance(im.get("id"), str) else im for im in gt["images"]]
    annotations = [dict(a, image_id=whole_number(a["image_id"])) if isinstance(a.get("image_id"), str) else a
                   for a in annotations]
    return {"images": images, "annotations": annotations, "categories": gt.get("categories", [])}


def whole_number(value: Any) -> Any:
    """An id written as text (``"3464"``) as the integer it is, as the dataset reader takes it; anything else as
    it is (pycocotools then matches it against the results' integer ids as before)."""
    number = int_text(value) if isinstance(value, str) else None
    return value if number is None else number


def _evaluated(gt: dict[str, Any], res: list[dict[str, Any]], ids: list[int]) -> Any:
    """A pycocotools COCOeval of `res` against `gt` on images `ids`, evaluated and accumulated (quietly)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = _gt_dataset(gt)
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes([dict(r, image_id=whole_number(r["image_id"])) if isinstance(r.get("image_id"), str)
                                   else r for r in res])
        ev = COCOeval(coco_gt, coco_dt, "bbox")
        ev.params.imgIds = ids
        ev.evaluate()
        ev.accumulate()
    return ev


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

    gt = load_images(images_json)
    res = [dict(r) for r in load_results(results)]  # loadRes writes into the dicts
    ids = sorted({int(i["id"]) for i in gt["images"]}) if image_ids is None else sorted({int(i) for i in image_ids})
    if ids:
        id_set = set(ids)
        res = [r for r in res if int(r["image_id"]) in id_set]
    if not res or not ids:
        return {"AP50": 0.0, "AP": 0.0, "AR100": 0.0}
    ev = _evaluated(gt, res, ids)
    with contextlib.redirect_stdout(io.StringIO()):
        ev.summarize()
    stats = [max(float(s), 0.0) for s in ev.stats]  # -1 (no ground truth) -> 0
    return {"AP50": stats[1], "AP": stats[0], "AR100": stats[8]}


def _row_names(categories: list[dict[str, Any]]) -> dict[int, str]:
    """Category id -> its row's name: the category's name, with the id beside it where two categories share a name or
    one is named "all" (rows are keyed by name: one would have overwritten the other, or the overall row)."""
    names = {int(c["id"]): str(c.get("name", c["id"])) for c in categories}
    seen = Counter(names.values())
    return {cid: f"{name} ({cid})" if seen[name] > 1 or name == "all" else name for cid, name in names.items()}


def per_class_metrics(images_json: str | Path | dict[str, Any],
                      results: str | Path | Sequence[dict[str, Any]], *,
                      image_ids: Iterable[int] | None = None) -> dict[str, dict[str, float]]:
    """AP50 and AR@100 per category and over all of them, from one pycocotools evaluation.

    Returns ``{"all": {...}, name: {...}, ...}`` with ``AP50``, ``AR100`` and ``gt`` (ground-truth boxes) per
    category that has ground truth in the evaluated images, fractions in [0, 1] as `coco_detection_metrics`
    gives them ("all" is COCO's mean over those categories, the figure `coco_detection_metrics` reports).
    """
    import numpy as np

    gt = load_images(images_json)
    res = [dict(r) for r in load_results(results)]
    ids = sorted({int(i["id"]) for i in gt["images"]}) if image_ids is None else sorted({int(i) for i in image_ids})
    id_set = set(ids)
    res = [r for r in res if int(r["image_id"]) in id_set]
    names = _row_names(gt.get("categories", []))
    counts: dict[int, int] = {}
    for a in gt["annotations"]:
        if int(a["image_id"]) in id_set and not a.get("iscrowd", 0):
            counts[int(a["category_id"])] = counts.get(int(a["category_id"]), 0) + 1
    out: dict[str, dict[str, float]] = {}
    if not res or not ids:
        out["all"] = {"AP50": 0.0, "AR100": 0.0, "gt": float(sum(counts.values()))}
        for cid, n in sorted(counts.items()):
            out[names.get(cid, str(cid))] = {"AP50": 0.0, "AR100": 0.0, "gt": float(n)}
        return out
    ev = _evaluated(gt, res, ids)
    precision = ev.eval["precision"]  # (T, R, K, A, M): IoU thresholds, recall points, classes, areas, max dets
    recall = ev.eval["recall"]  # (T, K, A, M)
    t50 = int(np.argmin(np.abs(ev.params.iouThrs - 0.5)))
    ap50, ar100 = [], []
    for k, cid in enumerate(ev.params.catIds):
        if cid not in counts:
            continue
        p = precision[t50, :, k, 0, -1]
        r = recall[:, k, 0, -1]
        ap = float(np.mean(p[p > -1])) if (p > -1).any() else 0.0
        ar = float(np.mean(r[r > -1])) if (r > -1).any() else 0.0
        out[names.get(cid, str(cid))] = {"AP50": ap, "AR100": ar, "gt": float(counts[cid])}
        ap50.append(ap)
        ar100.append(ar)
    out = {"all": {"AP50": float(np.mean(ap50)) if ap50 else 0.0, "AR100": float(np.mean(ar100)) if ar100 else 0.0,
                   "gt": float(sum(counts.values()))}, **out}
    return out

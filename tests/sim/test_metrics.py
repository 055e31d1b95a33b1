"""Evaluation helpers, and the emulator's calibration: pre-NMS recall >= 0.95, baseline AP50 in 60-85."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.metrics import baseline_nms, coco_detection_metrics, prenms_recall
from tests.sim.conftest import load

GT = {
    "images": [{"id": 1, "width": 100, "height": 100}, {"id": 2, "width": 100, "height": 100}],
    "annotations": [
        {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "area": 400, "iscrowd": 0},
        {"id": 2, "image_id": 1, "category_id": 1, "bbox": [60, 60, 10, 10], "area": 100, "iscrowd": 0},
        {"id": 3, "image_id": 2, "category_id": 2, "bbox": [0, 0, 30, 30], "area": 900, "iscrowd": 0},
    ],
    "categories": [{"id": 1, "name": "person"}, {"id": 2, "name": "swimmer"}],
}


def _r(image_id, cat, bbox, score):
    return {"image_id": image_id, "category_id": cat, "bbox": bbox, "score": score}


def test_perfect_detections_score_one_and_none_score_zero() -> None:
    perfect = [_r(a["image_id"], a["category_id"], a["bbox"], 0.9) for a in GT["annotations"]]
    m = coco_detection_metrics(GT, perfect)
    assert m["AP50"] == pytest.approx(1.0) and m["AR100"] == pytest.approx(1.0) and m["AP"] == pytest.approx(1.0)
    assert coco_detection_metrics(GT, []) == {"AP50": 0.0, "AP": 0.0, "AR100": 0.0}


def test_metrics_do_not_modify_the_results_and_respect_image_ids() -> None:
    res = [_r(1, 1, [10, 10, 20, 20], 0.9), _r(1, 1, [60, 60, 10, 10], 0.8)]
    copy = [dict(r) for r in res]
    m_all = coco_detection_metrics(GT, res)
    assert res == copy
    assert m_all["AP50"] < 1.0  # image 2's swimmer is missed
    m1 = coco_detection_metrics(GT, res, image_ids=[1])
    assert m1["AP50"] == pytest.approx(1.0)


def test_a_confident_false_positive_lowers_ap50() -> None:
    res = [_r(1, 1, [10, 10, 20, 20], 0.5), _r(1, 1, [60, 60, 10, 10], 0.4), _r(2, 2, [0, 0, 30, 30], 0.3),
           _r(2, 2, [50, 50, 30, 30], 0.99)]
    assert coco_detection_metrics(GT, res)["AP50"] < 0.9


def test_prenms_recall_counts_any_matching_box_of_the_same_class() -> None:
    cands = [_r(1, 1, [11, 11, 20, 20], 0.03), _r(1, 2, [60, 60, 10, 10], 0.9), _r(2, 2, [50, 50, 30, 30], 0.9)]
    assert prenms_recall(GT, cands) == pytest.approx(1 / 3)
    cands.append(_r(2, 2, [1, 1, 30, 30], 0.05))
    assert prenms_recall(GT, cands) == pytest.approx(2 / 3)
    assert prenms_recall(GT, cands, score_threshold=0.1) == pytest.approx(0.0)
    assert prenms_recall(GT, cands, iou=0.95) == pytest.approx(0.0)


def test_baseline_nms_is_class_wise_per_image_and_keeps_low_scores() -> None:
    cands = [_r(1, 1, [10, 10, 20, 20], 0.9), _r(1, 1, [11, 11, 20, 20], 0.8),  # suppressed
             _r(1, 2, [11, 11, 20, 20], 0.7),  # other class: kept
             _r(1, 1, [60, 60, 10, 10], 0.001),  # far away, low score: kept
             _r(2, 1, [10, 10, 20, 20], 0.5)]  # other image: kept
    kept = baseline_nms(cands)
    assert [(k["image_id"], k["category_id"], k["score"]) for k in kept] == [
        (1, 1, 0.9), (1, 2, 0.7), (1, 1, 0.001), (2, 1, 0.5)]
    assert baseline_nms([]) == []
    assert len(baseline_nms(cands, iou=0.99)) == 5


def test_bad_inputs_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        coco_detection_metrics(tmp_path / "missing.json", [])
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        prenms_recall(bad, [])
    with pytest.raises(ValueError, match="COCO dict"):
        prenms_recall({"images": []}, [])


@pytest.mark.parametrize("fixture", ["sea_dir", "grass_dir"])
def test_emulator_matches_the_paper_statistics(fixture: str, request: pytest.FixtureRequest) -> None:
    """~97-99 % recall before NMS, ~86-88 % after NMS at 0.25, single-frame AP50 in 60-85 (room to improve)."""
    data = request.getfixturevalue(fixture)
    gt = load(data, "images.json")
    cands = load(data, "pre_nms.json")
    assert prenms_recall(gt, cands) >= 0.95
    kept = baseline_nms(cands)
    assert len(kept) < 0.5 * len(cands)
    post = prenms_recall(gt, kept, score_threshold=0.25)
    assert 0.80 <= post <= 0.93
    m = coco_detection_metrics(gt, kept)
    assert 0.60 <= m["AP50"] <= 0.85
    assert m["AR100"] < 0.6  # imperfect localisation, as real detectors on small objects


def test_pr_curve_ignores_unmatched_detections_inside_a_crowd_box_of_their_class() -> None:
    # probe: three detections inside a crowd region counted as false positives (precision 0.25, pycocotools 1.0)
    from sim.metrics import pr_curve

    gt = {"images": [{"id": 1, "width": 640, "height": 480}],
          "categories": [{"id": 1, "name": "p"}, {"id": 2, "name": "q"}],
          "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20]},
                          {"id": 2, "image_id": 1, "category_id": 1, "bbox": [200, 200, 200, 200], "iscrowd": 1}]}
    dets = [{"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9}]
    dets += [{"image_id": 1, "category_id": 1, "bbox": [220 + 40 * k, 220, 20, 20], "score": 0.95} for k in range(3)]
    curve = pr_curve(gt, dets)
    assert curve["precision"].tolist() == [1.0] and curve["recall"].tolist() == [1.0]
    # of another class, or outside the region, they count
    other = [{**d, "category_id": 2} for d in dets[1:]] + [{**dets[1], "bbox": [500, 10, 20, 20]}]
    curve = pr_curve(gt, dets[:1] + other)
    assert len(curve["scores"]) == 5 and curve["precision"][-1] == 0.2

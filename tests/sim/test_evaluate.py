"""`uavmm eval` end to end on a small scenario, the PR-curve metrics, and bad input."""

from __future__ import annotations

import json

import pytest

from sim.metrics import operating_point, pr_curve, recall_at_precision, threshold_at_precision
from uavmm.cli import main

GT = {
    "images": [{"id": 1, "width": 100, "height": 100}, {"id": 2, "width": 100, "height": 100}],
    "annotations": [
        {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "area": 400, "iscrowd": 0},
        {"id": 2, "image_id": 2, "category_id": 1, "bbox": [50, 50, 20, 20], "area": 400, "iscrowd": 0},
    ],
    "categories": [{"id": 1, "name": "person"}],
}


def test_pr_curve_matches_one_to_one_in_score_order():
    dets = [
        {"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20], "score": 0.9},   # TP
        {"image_id": 1, "category_id": 1, "bbox": [11, 10, 20, 20], "score": 0.8},   # duplicate: FP
        {"image_id": 2, "category_id": 1, "bbox": [0, 0, 5, 5], "score": 0.7},       # FP
        {"image_id": 2, "category_id": 1, "bbox": [50, 50, 20, 21], "score": 0.3},   # TP
    ]
    curve = pr_curve(GT, dets)
    assert curve["scores"].tolist() == [0.9, 0.8, 0.7, 0.3]
    assert curve["precision"].tolist() == pytest.approx([1.0, 0.5, 1 / 3, 0.5])
    assert curve["recall"].tolist() == pytest.approx([0.5, 0.5, 0.5, 1.0])
    assert operating_point(GT, dets, 0.5) == pytest.approx({"precision": 1 / 3, "recall": 0.5})
    assert recall_at_precision(curve, 0.5) == pytest.approx(1.0)
    assert recall_at_precision(curve, 1.01) == 0.0
    assert threshold_at_precision(curve, 0.5) == pytest.approx(0.3)  # the highest-recall point with p >= 0.5
    assert threshold_at_precision(curve, 0.9) == pytest.approx(0.9)
    assert threshold_at_precision(curve, 1.01) == float("inf")


def test_eval_memory_map_beats_baseline_on_a_short_run(tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["eval", "--scenarios", "sea", "--seeds", "0", "--frames", "90", "--noise-scales", "1",
                 "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    by_variant = {s["variant"]: s for s in report["summary"]}
    assert by_variant["memory map"]["AP50"] > by_variant["baseline"]["AP50"] + 2.0
    assert by_variant["memory map"]["R_op"] > by_variant["baseline"]["R_op"]
    assert by_variant["memory map"]["AR_op"] > by_variant["baseline"]["AR_op"]  # AR at equal precision goes up
    sf = report["size_filter"]["sea"]
    assert sf["removed"] > 0 and sf["removed_false_positives"] > 10 * sf["removed_true_positives"]
    assert "| sea | x1 | memory map |" in (out / "report.md").read_text()
    assert "memory map" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scenarios", "moon"], "unknown scenario 'moon'"),
        (["--seeds", "a,b"], "--seeds"),
        (["--seeds", "-1"], "--seeds must be >= 0"),
        (["--frames", "0"], "--frames must be in 1..36000 (frames per video), got 0"),
    ],
)
def test_eval_bad_input_is_named(tmp_path, capsys, args, message):
    assert main(["eval", "--out", str(tmp_path / "e"), *args]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "e" / "report.json").exists()

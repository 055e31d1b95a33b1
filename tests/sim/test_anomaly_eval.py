"""The anomaly protocol's recall at broadcasting rates (sim.anomaly_eval)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from sim.anomaly_eval import frame_hits, persistence, persistence_summary, summarise


def test_an_object_is_found_once_its_pixels_rank_within_the_flagged_share():
    scores = np.zeros((100, 100), np.float32)
    scores[10:12, 10:12] = 0.9  # object A: 4 px, the hottest
    scores[50:70, 50:70] = 0.5  # a 400 px glare patch
    scores[80, 80] = 0.4  # object B, below the glare
    boxes = np.array([[20.0, 20.0, 4.0, 4.0], [160.0, 160.0, 2.0, 2.0], [0.0, 180.0, 4.0, 4.0]])  # at 200x200
    hits = frame_hits(scores, boxes, (200, 200), rates=(0.0004, 0.01, 0.05, 0.5))
    # 4 px flag A only; 100 px add part of the glare; 500 px reach B's single pixel; object C has no heat
    assert hits.tolist() == [[True, False, False], [True, False, False], [True, True, False], [True, True, False]]


def test_ties_at_the_threshold_are_drawn_at_random_so_the_flagged_share_is_exact():
    # a saturated heatmap: 1000 pixels tied at 1; flagging all of them at a 1 % rate (100 px) overstated recall
    scores = np.zeros((100, 100), np.float32)
    scores[:10, :] = 1.0
    boxes = np.array([[5.0, 5.0, 1.0, 1.0],  # one tied pixel
                      [20.0, 3.0, 3.0, 2.0],  # six tied pixels
                      [50.0, 50.0, 2.0, 2.0]])  # below the ties
    hits = frame_hits(scores, boxes, (100, 100), rates=(0.01, 0.2))
    assert math.isclose(hits[0, 0], 100 / 1000)
    assert math.isclose(hits[0, 1], 1 - math.comb(994, 100) / math.comb(1000, 100))
    assert hits[0, 2] == 0.0
    assert hits[1].tolist() == [1.0, 1.0, 0.0]  # 2000 px flagged: all ties and zero scores never count


def test_tie_chances_match_enumerating_every_draw():
    rng = np.random.default_rng(3)
    scores = rng.choice(np.array([0.2, 0.5, 0.5, 0.5, 0.9], np.float32), size=(3, 4))
    boxes = np.array([[0.0, 0.0, 2.0, 1.0], [2.0, 1.0, 2.0, 2.0], [1.0, 2.0, 1.0, 1.0]])
    flat = scores.ravel()
    order = sorted(range(flat.size), key=lambda i: -flat[i])
    for p in (0.1, 0.25, 0.5):
        k = math.ceil(p * flat.size)
        thr = flat[order[k - 1]]
        above = [i for i in range(flat.size) if flat[i] > thr]
        tied = [i for i in range(flat.size) if flat[i] == thr]
        draws = list(itertools.combinations(tied, k - len(above)))
        for j, (x, y, w, h) in enumerate(boxes):
            own = {r * 4 + c for r in range(int(y), int(y + h)) for c in range(int(x), int(x + w))}
            found = sum(bool(own & (set(above) | set(d))) for d in draws) / len(draws)
            assert math.isclose(frame_hits(scores, boxes, (4, 3), rates=(p,))[0, j], found), (p, j)


def test_summary_is_recall_in_percent_averaged_over_rates_and_seeds():
    runs = [{"objects": 10, "fps": 20.0, "frame": {"hits": [5, 10]}, "memory": {"hits": [10, 10]}},
            {"objects": 20, "fps": 30.0, "frame": {"hits": [10, 20]}, "memory": {"hits": [10, 20]}}]
    out = summarise(runs, rates=(0.01, 0.05))
    assert out["frame"]["AR"] == 75.0 and out["memory"]["AR"] == 87.5
    assert out["frame"]["R@5%"] == 100.0 and out["gain"]["AR"] == 12.5 and out["fps"] == 25.0


def test_persistence_tells_kept_from_transient_false_alarms():
    heat = np.zeros((50, 50), np.float32)
    layer = np.zeros((50, 50), np.float32)
    heat[10, 10], layer[10, 10] = 0.9, 0.6  # the object: the layer keeps 2/3 of it
    heat[30, 30], layer[30, 30] = 0.8, 0.7  # a buoy that is not annotated: kept as well as the object
    heat[40, 5], layer[40, 5] = 0.95, 0.1  # a whitecap: gone from the layer
    alarms, objects = persistence(heat, layer, np.array([[20.0, 20.0, 2.0, 2.0]]), (100, 100), rate=3 / 2500)
    assert sorted(alarms.round(3).tolist()) == [round(0.1 / 0.95, 3), round(0.7 / 0.8, 3)]
    assert objects.round(3).tolist() == [round(0.6 / 0.9, 3)]
    assert persistence_summary(alarms, objects) == {"kept": 50.0, "transient": 50.0, "object_ratio": 0.67}
    assert persistence_summary(np.zeros(0), objects)["kept"] is None


def test_boats_and_buoys_are_anomalies_beside_the_annotated_swimmers(tmp_path):
    import json

    import pytest

    from sim.anomaly_eval import anomaly_boxes

    coco = {"categories": [{"id": 1, "name": "swimmer"}],
            "annotations": [{"image_id": 7, "category_id": 1, "bbox": [1, 2, 3, 4]}]}
    with pytest.raises(ValueError, match="unannotated.json is missing"):
        anomaly_boxes(tmp_path, coco)
    (tmp_path / "unannotated.json").write_text(json.dumps({"annotations": [
        {"image_id": 7, "kind": "buoy", "bbox": [10, 10, 2, 2]}, {"image_id": 8, "kind": "boat", "bbox": [0, 0, 9, 5]},
        {"image_id": 8, "kind": "tree", "bbox": [20, 20, 9, 9]}]}))
    assert anomaly_boxes(tmp_path, coco) == {7: [("swimmer", [1, 2, 3, 4]), ("buoy", [10, 10, 2, 2])],
                                             8: [("boat", [0, 0, 9, 5])]}


def test_the_summary_gives_recall_per_class_pooled_over_seeds():
    runs = [{"objects": 12, "fps": 20.0, "frame": {"hits": [6, 12]}, "memory": {"hits": [8, 12]},
             "classes": {"swimmer": {"objects": 10, "frame": {"hits": [4, 10]}, "memory": {"hits": [6, 10]}},
                         "boat": {"objects": 2, "frame": {"hits": [2, 2]}, "memory": {"hits": [2, 2]}}}},
            {"objects": 10, "fps": 20.0, "frame": {"hits": [5, 10]}, "memory": {"hits": [5, 10]},
             "classes": {"swimmer": {"objects": 10, "frame": {"hits": [5, 10]}, "memory": {"hits": [5, 10]}}}}]
    out = summarise(runs, rates=(0.01, 0.05))
    assert out["classes"]["swimmer"] == {"objects": 20, "frame": {"AR": 72.5, "R@5%": 100.0},
                                         "memory": {"AR": 77.5, "R@5%": 100.0}}
    assert out["classes"]["boat"]["objects"] == 2 and out["classes"]["boat"]["frame"]["AR"] == 100.0


def test_the_summary_also_gives_recall_over_the_mapped_region():
    """Objects wholly above the cut count as missed in both modes in the headline figures; the region figures
    count only the objects with a part below the cut (mean over seeds, like the headline)."""
    from sim.anomaly_eval import format_report

    runs = [{"objects": 10, "fps": 20.0, "frame": {"hits": [4, 8]}, "memory": {"hits": [6, 8]},
             "region": {"objects": 8, "frame": {"hits": [4, 8]}, "memory": {"hits": [6, 8]}}},
            {"objects": 10, "fps": 20.0, "frame": {"hits": [5, 10]}, "memory": {"hits": [5, 10]},
             "region": {"objects": 10, "frame": {"hits": [5, 10]}, "memory": {"hits": [5, 10]}}}]
    out = summarise(runs, rates=(0.01, 0.05))
    assert out["frame"]["R@5%"] == 90.0 and out["region"]["frame"]["R@5%"] == 100.0
    assert out["region"]["objects"] == 18 and out["region"]["memory"]["AR"] == 81.2
    assert out["region"]["gain"] == {"AR": 6.2, "R@5%": 0.0}
    report = {"rates": [0.01, 0.05], "seeds": [0, 1], "frames": 9, "image_size": [64, 36],
              "results": {"sea": {"median": {**out, "objects": 20}}}}
    assert "Mapped region only" in format_report(report)
    del runs[0]["region"]
    assert "region" not in summarise(runs, rates=(0.01, 0.05))

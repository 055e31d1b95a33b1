"""The anomaly protocol's recall at broadcasting rates (sim.anomaly_eval)."""

from __future__ import annotations

import numpy as np

from sim.anomaly_eval import frame_hits, summarise


def test_an_object_is_found_once_its_pixels_rank_within_the_flagged_share():
    scores = np.zeros((100, 100), np.float32)
    scores[10:12, 10:12] = 0.9  # object A: 4 px, the hottest
    scores[50:70, 50:70] = 0.5  # a 400 px glare patch
    scores[80, 80] = 0.4  # object B, below the glare
    boxes = np.array([[20.0, 20.0, 4.0, 4.0], [160.0, 160.0, 2.0, 2.0], [0.0, 180.0, 4.0, 4.0]])  # at 200x200
    hits = frame_hits(scores, boxes, (200, 200), rates=(0.0004, 0.01, 0.05, 0.5))
    # 4 px flag A only; 100 px add part of the glare; 500 px reach B's single pixel; object C has no heat
    assert hits.tolist() == [[True, False, False], [True, False, False], [True, True, False], [True, True, False]]


def test_summary_is_recall_in_percent_averaged_over_rates_and_seeds():
    runs = [{"objects": 10, "fps": 20.0, "frame": {"hits": [5, 10]}, "memory": {"hits": [10, 10]}},
            {"objects": 20, "fps": 30.0, "frame": {"hits": [10, 20]}, "memory": {"hits": [10, 20]}}]
    out = summarise(runs, rates=(0.01, 0.05))
    assert out["frame"]["AR"] == 75.0 and out["memory"]["AR"] == 87.5
    assert out["frame"]["R@5%"] == 100.0 and out["gain"]["AR"] == 12.5 and out["fps"] == 25.0

"""Ground error of reported track positions: one-to-one IoU matching, metres against the truth, and the
summary's blanks when nothing matches."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import local_to_latlon
from sim.position_error import format_metres, frame_position_errors, mean_known, summarise_position_errors

LAT0, LON0 = 47.6, 9.3


def _boxes(n: int) -> np.ndarray:
    """n disjoint 20 x 50 px boxes side by side."""
    x = 100.0 * np.arange(n)
    return np.column_stack([x, np.full(n, 100.0), x + 20.0, np.full(n, 150.0)])


def _truth_latlon(n: int) -> np.ndarray:
    lat, lon = local_to_latlon(15.0 * np.arange(n) - 30.0, np.linspace(-20.0, 40.0, n), LAT0, LON0)
    return np.column_stack([lat, lon])


def _shifted(latlon: np.ndarray, distance_m: float, bearing_deg: np.ndarray) -> np.ndarray:
    """Each point moved distance_m towards its bearing (tangent plane at the point)."""
    out = np.empty_like(latlon)
    for k, (lat, lon) in enumerate(latlon):
        b = math.radians(float(bearing_deg[k]))
        la, lo = local_to_latlon(distance_m * math.sin(b), distance_m * math.cos(b), lat, lon)
        out[k] = (float(la), float(lo))
    return out


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 8), distance_m=st.floats(0.0, 50.0), seed=st.integers(0, 2**31 - 1))
def test_a_known_offset_gives_that_error_whatever_the_order_of_the_tracks(n: int, distance_m: float,
                                                                        seed: int) -> None:
    rng = np.random.default_rng(seed)
    gt_boxes, gt_latlon = _boxes(n), _truth_latlon(n)
    order = rng.permutation(n)
    tr_latlon = _shifted(gt_latlon, distance_m, rng.uniform(0.0, 360.0, n))[order]
    errors = frame_position_errors(gt_boxes, gt_latlon, gt_boxes[order] + rng.uniform(-1, 1, (n, 4)), tr_latlon)
    assert errors.shape == (n,)
    np.testing.assert_allclose(errors, distance_m, atol=1e-3)
    summary = summarise_position_errors(errors)
    assert summary["pos_err_m"] == pytest.approx(distance_m, abs=1e-3) and summary["pos_err_n"] == n


def test_median_and_p90_of_mixed_offsets() -> None:
    gt_boxes, gt_latlon = _boxes(10), _truth_latlon(10)
    offsets = np.arange(1.0, 11.0)  # 1..10 m
    tr_latlon = np.vstack([_shifted(gt_latlon[k:k + 1], offsets[k], np.array([90.0])) for k in range(10)])
    errors = frame_position_errors(gt_boxes, gt_latlon, gt_boxes, tr_latlon)
    summary = summarise_position_errors(errors)
    assert summary["pos_err_m"] == pytest.approx(5.5, abs=1e-3)
    assert summary["pos_err_p90_m"] == pytest.approx(float(np.percentile(offsets, 90)), abs=1e-3)


def test_only_pairs_at_iou_half_or_more_and_one_to_one_are_measured() -> None:
    gt_boxes, gt_latlon = _boxes(2), _truth_latlon(2)
    near = _shifted(gt_latlon, 3.0, np.zeros(2))
    # track 0: on object 0 (IoU 1); track 1: a duplicate on object 0 (IoU 0.9); track 2: object 1 shifted by
    # 12 px (IoU 0.25: not a match)
    tr_boxes = np.vstack([gt_boxes[0], gt_boxes[0] + [1.0, 0.0, 1.0, 0.0], gt_boxes[1] + [12.0, 0.0, 12.0, 0.0]])
    tr_latlon = np.vstack([near[0], gt_latlon[0], near[1]])
    errors = frame_position_errors(gt_boxes, gt_latlon, tr_boxes, tr_latlon)
    assert errors.shape == (1,)  # one match per object, none below the IoU bar
    assert errors[0] == pytest.approx(3.0, abs=1e-3)  # the better box wins object 0
    # the bar is the caller's
    assert len(frame_position_errors(gt_boxes, gt_latlon, tr_boxes, tr_latlon, min_iou=0.2)) == 2


def test_no_match_gives_blanks_and_does_not_crash() -> None:
    gt_boxes, gt_latlon = _boxes(3), _truth_latlon(3)
    far = gt_boxes + 5000.0
    assert frame_position_errors(gt_boxes, gt_latlon, far, gt_latlon).shape == (0,)
    assert frame_position_errors(np.zeros((0, 4)), np.zeros((0, 2)), gt_boxes, gt_latlon).shape == (0,)
    assert frame_position_errors(gt_boxes, gt_latlon, np.zeros((0, 4)), np.zeros((0, 2))).shape == (0,)
    # a track without a ground position, or an annotation without a true one, is not measured
    assert frame_position_errors(gt_boxes, gt_latlon, gt_boxes, np.full((3, 2), np.nan)).shape == (0,)
    no_truth = gt_latlon.copy()
    no_truth[1] = np.nan
    assert frame_position_errors(gt_boxes, no_truth, gt_boxes, gt_latlon).shape == (2,)
    summary = summarise_position_errors(np.zeros(0))
    assert summary == {"pos_err_m": None, "pos_err_p90_m": None, "pos_err_n": 0}
    assert json.loads(json.dumps(summary))["pos_err_m"] is None  # valid JSON, no NaN
    assert summarise_position_errors(np.array([np.nan]))["pos_err_m"] is None
    with pytest.raises(ValueError, match="same rows"):
        frame_position_errors(gt_boxes, gt_latlon[:2], gt_boxes, gt_latlon)


def test_means_and_cells_leave_unknowns_blank() -> None:
    assert mean_known([1.0, None, 3.0, float("nan")]) == pytest.approx(2.0)
    assert mean_known([None, None]) is None and mean_known([]) is None
    assert format_metres(None) == "" and format_metres(float("nan")) == "" and format_metres(1.234) == "1.23"

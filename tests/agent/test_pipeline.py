"""Class-wise NMS of the pipeline (agent.pipeline.nms) against OpenCV's NMS over all boxes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.pipeline import _box_cells, _surely_suppressed, distinct_ids, nms
from benchmarks.bench_memory_map import clustered_candidates
from shared.geo import Camera


def nms_reference(boxes_xyxy, scores, class_ids, iou, score_threshold, max_detections):
    """cv2.dnn.NMSBoxesBatched over every box at once, highest score first (ties: lower index first)."""
    xywh = np.column_stack([boxes_xyxy[:, :2], boxes_xyxy[:, 2:] - boxes_xyxy[:, :2]]).astype(np.float32)
    keep = np.asarray(cv2.dnn.NMSBoxesBatched(xywh.tolist(), scores.tolist(), class_ids.astype(np.int32).tolist(),
                                              score_threshold, iou), dtype=np.int64).reshape(-1)
    keep = keep[np.argsort(-scores[keep], kind="stable")]
    return keep[:max_detections]


def nms_before_issue_4(boxes_xyxy, scores, class_ids, iou, score_threshold, max_detections):
    """The implementation this one replaced: NMS on the top 8K scores, widened 4x while < K survive."""
    n = len(scores)
    xywh = np.column_stack([boxes_xyxy[:, :2], boxes_xyxy[:, 2:] - boxes_xyxy[:, :2]])
    m = min(n, 8 * max_detections)
    while True:
        top = np.argpartition(-scores, m - 1)[:m] if m < n else np.arange(n)
        keep = cv2.dnn.NMSBoxesBatched(xywh[top].astype(np.float32).tolist(), scores[top].tolist(),
                                       class_ids[top].astype(np.int32).tolist(), score_threshold, iou)
        keep = top[np.asarray(keep, dtype=np.int64).reshape(-1)]
        if len(keep) >= max_detections or m >= n:
            break
        m = min(n, 4 * m)
    keep = keep[np.argsort(-scores[keep], kind="stable")]
    return keep[:max_detections]


@st.composite
def candidates(draw, distinct_scores: bool = False):
    n = draw(st.integers(1, 400))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    # a few clusters (many overlaps, deep suppression chains) plus scattered boxes
    centres = rng.uniform(0, 300, (draw(st.integers(1, 8)), 2))
    c = centres[rng.integers(0, len(centres), n)] + rng.normal(0, draw(st.sampled_from([1.0, 5.0, 40.0])), (n, 2))
    size = rng.uniform(2, 40, (n, 2))
    boxes = np.column_stack([c - size / 2, c + size / 2]).astype(np.float32)
    if distinct_scores:
        scores = (rng.permutation(n) + 1).astype(np.float32) / n
    else:  # ties, as saturated boosted scores produce them
        scores = rng.choice(np.float32([0.0, 0.001, 0.2, 0.5, 0.99, 1.0]), n) if draw(st.booleans()) \
            else rng.uniform(0, 1, n).astype(np.float32)
    class_ids = rng.integers(1, draw(st.integers(2, 4)), n)
    return boxes, scores.astype(np.float32), class_ids


@settings(max_examples=150, deadline=None)
@given(candidates(), st.sampled_from([0.3, 0.5, 0.7]), st.sampled_from([0.0, 0.001, 0.2]), st.integers(1, 60))
def test_nms_keeps_the_boxes_opencv_keeps_over_all_candidates(cands, iou, score_threshold, max_detections):
    boxes, scores, cids = cands
    got = nms(boxes, scores, cids, iou, score_threshold, max_detections)
    np.testing.assert_array_equal(got, nms_reference(boxes, scores, cids, iou, score_threshold, max_detections))


@settings(max_examples=100, deadline=None)
@given(candidates(distinct_scores=True), st.sampled_from([0.3, 0.5]), st.integers(1, 60))
def test_nms_matches_the_implementation_it_replaced_when_scores_differ(cands, iou, max_detections):
    boxes, scores, cids = cands
    np.testing.assert_array_equal(nms(boxes, scores, cids, iou, 0.001, max_detections),
                                  nms_before_issue_4(boxes, scores, cids, iou, 0.001, max_detections))


@pytest.mark.parametrize("n", [1000, 5000])
def test_nms_on_clustered_detector_output_equals_full_nms(n):
    # thousands of clustered candidates: several passes per class, the second class cut short
    camera = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    rng = np.random.default_rng(n)
    boxes, scores, cids = clustered_candidates(n, camera, rng)
    for boosted in (scores, np.where(cids == 1, np.sqrt(scores), scores).astype(np.float32)):
        got = nms(boxes, boosted, cids, 0.5, 0.001, 100)
        assert len(got) == 100
        np.testing.assert_array_equal(got, nms_reference(boxes, boosted, cids, 0.5, 0.001, 100))


def test_nms_edge_cases():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60]], dtype=np.float32)
    scores = np.array([0.5, 0.5, 0.4], dtype=np.float32)
    cids = np.array([1, 1, 1])
    assert nms(boxes[:0], scores[:0], cids[:0], 0.5, 0.0, 10).tolist() == []
    assert nms(boxes, scores, cids, 0.5, 0.6, 10).tolist() == []  # all at or below the threshold
    assert nms(boxes, scores, cids, 0.5, 0.4, 10).tolist() == [0]  # 0.4 is not above 0.4
    assert nms(boxes, scores, cids, 0.5, 0.0, 10).tolist() == [0, 2]  # equal scores: lower index wins
    assert nms(boxes, scores, cids, 0.5, 0.0, 1).tolist() == [0]
    assert nms(boxes, scores, np.array([1, 2, 1]), 0.5, 0.0, 10).tolist() == [0, 1, 2]  # classes apart


@given(st.lists(st.integers(-(2**40), 2**40), max_size=50), st.integers(-5, 5))
def test_distinct_ids_equals_numpy_unique(values, offset):
    for ids in (np.array(values, dtype=np.int64), np.array([v % 7 + offset for v in values], dtype=np.int64)):
        np.testing.assert_array_equal(distinct_ids(ids), np.unique(ids))


def _ranked_xywh(boxes_xyxy, scores):
    """Boxes in rank order as nms() hands them to OpenCV: float64 (x, y, w, h), widths via float32."""
    order = np.argsort(-scores, kind="stable")
    b = boxes_xyxy[order]
    xywh = np.column_stack([b[:, :2], b[:, 2:] - b[:, :2]]).astype(np.float32).astype(np.float64)
    return xywh, scores[order]


@settings(max_examples=150, deadline=None)
@given(candidates(), st.sampled_from([0.3, 0.5, 0.7]), st.integers(1, 100))
def test_surely_suppressed_boxes_are_ones_opencv_suppresses(cands, iou, split):
    boxes, scores, _ = cands
    xywh, _ = _ranked_xywh(boxes, scores)
    ranked = np.linspace(1.0, 0.5, len(xywh)).astype(np.float32)  # every box in, in rank order
    split = min(split, len(ranked))
    kept = np.sort(np.asarray(cv2.dnn.NMSBoxes(xywh[:split], ranked[:split], 0.0, iou), dtype=np.int64).reshape(-1))
    fresh = np.arange(split, len(ranked))
    if len(kept) == 0 or len(fresh) == 0:
        return
    corners, cells = _box_cells(xywh, kept)
    sure = _surely_suppressed(corners, cells, kept, fresh, iou)
    seen = np.concatenate([kept, fresh])
    picked = set(seen[np.asarray(cv2.dnn.NMSBoxes(xywh[seen], ranked[seen], 0.0, iou), dtype=np.int64)].tolist())
    assert not picked & set(fresh[sure].tolist())  # never one OpenCV keeps
    # and leaving them out changes nothing
    rest = np.concatenate([kept, fresh[~sure]])
    picked_rest = rest[np.asarray(cv2.dnn.NMSBoxes(xywh[rest], ranked[rest], 0.0, iou), dtype=np.int64)]
    assert set(picked_rest.tolist()) == picked


def test_surely_suppressed_leaves_boxes_at_the_threshold_to_opencv():
    # IoU of a 10x10 box with its left half is exactly 0.5: OpenCV keeps it at threshold 0.5
    xywh = np.array([[0, 0, 10, 10], [0, 0, 5, 10], [0, 0, 9.9, 10], [0, 0, 0, 0]], dtype=np.float64)
    kept, fresh = np.array([0]), np.array([1, 2, 3])
    corners, cells = _box_cells(xywh, kept)
    assert _surely_suppressed(corners, cells, kept, fresh, 0.5).tolist() == [False, True, False]
    assert _surely_suppressed(corners, cells, kept, fresh, 0.4).tolist() == [True, True, False]


def test_surely_suppressed_finds_most_duplicates_of_clustered_detector_output():
    # the point of it: OpenCV then converts and compares only a fraction of the later passes' boxes
    camera = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    boxes, scores, cids = clustered_candidates(5000, camera, np.random.default_rng(3))
    sel = cids == 1
    xywh, ranked = _ranked_xywh(boxes[sel], scores[sel])
    kept = np.sort(np.asarray(cv2.dnn.NMSBoxes(xywh[:300], ranked[:300], 0.001, 0.5), dtype=np.int64).reshape(-1))
    fresh = np.arange(300, 1300)
    corners, cells = _box_cells(xywh, kept)
    sure = _surely_suppressed(corners, cells, kept, fresh, 0.5)
    seen = np.concatenate([kept, fresh])
    picked = set(seen[np.asarray(cv2.dnn.NMSBoxes(xywh[seen], ranked[seen], 0.001, 0.5), dtype=np.int64)].tolist())
    suppressed = np.array([f not in picked for f in fresh])
    assert not (sure & ~suppressed).any()
    assert sure.sum() > 0.5 * suppressed.sum()

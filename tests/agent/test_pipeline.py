"""Class-wise NMS of the pipeline (agent.boxes.nms) against OpenCV's NMS over all boxes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.boxes import ANCHORS, anchor_fraction, anchor_points, box_anchor_points, nms
from agent.pipeline import DetectionPipeline, distinct_ids
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from benchmarks.bench_memory_map import clustered_candidates
from shared.geo import Camera, Pose, local_to_latlon, pixel_to_local


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


def nms_opencv_per_class(boxes_xyxy, scores, class_ids, iou, score_threshold, max_detections):
    """cv2.dnn.NMSBoxes per class on float64 (x, y, w, h) with widths via float32 (OpenCV's Rect2d path,
    no class offsets), merged highest score first (ties: lower index first)."""
    with np.errstate(invalid="ignore"):  # inf - inf
        xywh = np.column_stack([boxes_xyxy[:, :2], boxes_xyxy[:, 2:] - boxes_xyxy[:, :2]]).astype(np.float32)
    xywh = xywh.astype(np.float64)
    kept = []
    for cid in np.unique(class_ids):
        sel = np.flatnonzero(class_ids == cid)
        picked = cv2.dnn.NMSBoxes(xywh[sel], scores[sel].astype(np.float32), score_threshold, iou)
        kept.extend(sel[np.asarray(picked, dtype=np.int64).reshape(-1)].tolist())
    kept = np.array(kept, dtype=np.int64)
    return kept[np.lexsort((kept, -scores[kept]))][:max_detections]


@st.composite
def odd_candidates(draw):
    """Clustered boxes with ties, empty, negative-size, tiny and NaN boxes, 1-3 classes."""
    boxes, scores, _ = draw(candidates())
    n = len(scores)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    boxes = boxes.copy()
    for kind in draw(st.sets(st.sampled_from(["empty", "negative", "tiny", "nan", "inf"]))):
        rows = rng.integers(0, n, max(1, n // 10))
        if kind == "empty":
            boxes[rows, 2:] = boxes[rows, :2]
        elif kind == "negative":
            boxes[rows, 2] = boxes[rows, 0] - rng.uniform(0.5, 10, len(rows))
        elif kind == "tiny":
            boxes[rows, 2:] = boxes[rows, :2] + np.float32(1e-6)
        elif kind == "nan":
            boxes[rows, rng.integers(0, 4, len(rows))] = np.nan
        else:
            boxes[rows, rng.integers(0, 4, len(rows))] = np.inf
    class_ids = rng.integers(0, draw(st.integers(1, 3)), n)
    return boxes, scores, class_ids


@settings(max_examples=300, deadline=None)
@given(odd_candidates(), st.sampled_from([0.0, 0.3, 0.5, 0.7, 1.0]), st.sampled_from([0.0, 0.001, 0.2]),
       st.sampled_from([1, 3, 20, 100, 10_000]))
def test_nms_kernel_equals_opencv_on_odd_boxes(cands, iou, score_threshold, max_detections):
    # NaN boxes suppress (and are suppressed by) everything of their class, empty ones all empty ones:
    # OpenCV's own IoU, which the kernel reproduces
    boxes, scores, cids = cands
    want = nms_opencv_per_class(boxes, scores, cids, iou, score_threshold, max_detections)
    np.testing.assert_array_equal(nms(boxes, scores, cids, iou, score_threshold, max_detections), want)
    np.testing.assert_array_equal(nms(boxes.astype(np.float64), scores, cids, iou, score_threshold, max_detections),
                                  want)


def test_nms_kernel_grid_handles_wide_and_far_boxes():
    # boxes wider than the grid's cell limit and coordinates far apart still meet the boxes they overlap
    rng = np.random.default_rng(7)
    c = np.vstack([rng.uniform(0, 5000, (300, 2)), rng.uniform(1e6, 1e6 + 50, (50, 2))])
    size = np.vstack([rng.uniform(5, 20, (300, 2)), rng.uniform(5, 20, (50, 2))])
    size[::17] = rng.uniform(800, 3000, (len(size[::17]), 2))
    boxes = np.column_stack([c - size / 2, c + size / 2]).astype(np.float32)
    scores = rng.uniform(0, 1, len(boxes)).astype(np.float32)
    cids = rng.integers(0, 2, len(boxes))
    for iou in (0.05, 0.5):
        np.testing.assert_array_equal(nms(boxes, scores, cids, iou, 0.0, 10_000),
                                      nms_opencv_per_class(boxes, scores, cids, iou, 0.0, 10_000))


def test_nms_rejects_negative_thresholds_as_opencv_does():
    boxes = np.array([[0, 0, 10, 10]], dtype=np.float32)
    with pytest.raises(ValueError, match="iou"):
        nms(boxes, np.ones(1, np.float32), np.ones(1), -0.1, 0.0, 10)
    with pytest.raises(ValueError, match="score_threshold"):
        nms(boxes, np.ones(1, np.float32), np.ones(1), 0.5, -1.0, 10)


@st.composite
def frames(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    camera = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    boxes, scores, cids = clustered_candidates(draw(st.integers(1, 600)), camera, rng)
    if draw(st.booleans()):
        boxes[rng.integers(0, len(boxes), 3)] = np.nan
    pose = Pose(lat=draw(st.floats(-60, 60)), lon=draw(st.floats(-179.9, 179.9)),
                height_m=draw(st.floats(5, 300)), pitch_deg=draw(st.floats(5, 90)),
                heading_deg=draw(st.floats(0, 360)), roll_deg=draw(st.floats(-10, 10)))
    return camera, boxes, scores, cids, pose


@settings(max_examples=100, deadline=None)
@given(frames(), st.sampled_from(ANCHORS), st.sampled_from([None, 60.0, 1e4]))
def test_fused_georeference_and_filter_equals_pixel_to_local_and_plausible(frame, anchor, max_range_m):
    camera, boxes, scores, cids, pose = frame
    pipe = DetectionPipeline(camera, {1: "person", 2: "swimmer"},
                             PipelineConfig(anchor=anchor, max_range_m=max_range_m))
    lat, lon, valid, ok = pipe._georeference_and_filter(boxes, cids, [1, 2], pose)
    east, north, want_valid = pixel_to_local(box_anchor_points(boxes, anchor, pose.pitch_deg), camera, pose,
                                             max_range_m=pipe.config.range_limit_m)
    want_lat, want_lon = local_to_latlon(east, north, pose.lat, pose.lon)
    want_ok = pipe.plausible(boxes, cids, east, north, pose)
    # the same to float rounding: a flip needs a box within ~1e-12 of the horizon, range or band limit
    np.testing.assert_array_equal(valid, want_valid)
    np.testing.assert_array_equal(ok, want_ok)
    np.testing.assert_allclose(lat, want_lat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(lon, want_lon, rtol=0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(frames(), st.sampled_from([-1e-5, -1e-7, -1e-9, -1e-12, 0.0, 1e-12, 1e-9, 1e-7, 1e-5]))
def test_size_filter_sure_bounds_decide_as_the_exact_test_at_the_band_edges(frame, delta):
    camera, boxes, scores, cids, pose = frame
    pipe = DetectionPipeline(camera, {1: "person", 2: "swimmer"})
    # scale each box about its anchor so that its metric size sits at a band edge, times (1 + delta)
    frac = anchor_fraction(pipe.config.anchor, pose.pitch_deg)
    anchors = anchor_points(boxes, frac)
    east, north, _ = pixel_to_local(anchors, camera, pose, max_range_m=pipe.config.range_limit_m)
    slant = np.sqrt(east**2 + north**2 + pose.height_m**2)
    depression = np.degrees(np.arcsin(pose.height_m / slant))
    diag = np.hypot(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]).astype(np.float64)
    edge = np.ones(len(boxes))
    for cid, name in pipe.class_names.items():
        sel = cids == cid
        lo, hi = pipe.size_filter.bands[name].bounds_m(depression[sel], pipe.size_filter.k)
        edge[sel] = np.where(np.arange(sel.sum()) % 2 == 0, lo, hi)
    scale = np.nan_to_num(edge * pipe._focal_px / (diag * slant), nan=1.0) * (1 + delta)
    ax, ay = anchors[:, 0], anchors[:, 1]
    edged = np.column_stack([ax + (boxes[:, 0] - ax) * scale, ay + (boxes[:, 1] - ay) * scale,
                             ax + (boxes[:, 2] - ax) * scale, ay + (boxes[:, 3] - ay) * scale]).astype(np.float32)
    fast = pipe._georeference_and_filter(edged, cids, [1, 2], pose)
    exact = pipe._georeference_and_filter(edged, cids, [1, 2], pose, exact_only=True)
    for got, want in zip(fast, exact, strict=True):
        np.testing.assert_array_equal(got, want)


def test_size_band_sure_bounds_bracket_the_band():
    band = SizeFilter.builtin().bands["person"]
    sure = band.sure_bounds(3.0, 64)
    assert sure.shape == (64, 4)
    assert np.all(sure[:, 0] <= sure[:, 1]) and np.all(sure[:, 1] < sure[:, 2]) and np.all(sure[:, 2] <= sure[:, 3])
    # a depression inside each bin: its accepted squared size range lies between the sure bounds
    mid = np.degrees(np.arcsin((np.arange(64) + 0.5) / 64))
    lo, hi = band.bounds_m(mid, 3.0)
    assert np.all(sure[:, 0] < lo**2) and np.all(lo**2 <= sure[:, 1])
    assert np.all(sure[:, 2] <= hi**2) and np.all(hi**2 < sure[:, 3])


def test_pipeline_uses_numpy_path_for_distorted_cameras_with_the_same_result():
    camera = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)
    # a negligible distortion: the numpy path (OpenCV's undistortion) with the same geometry
    distorted = Camera(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0, dist=(1e-12, 0, 0, 0))
    boxes, scores, cids = clustered_candidates(2000, camera, np.random.default_rng(1))
    pose = Pose(lat=47.67, lon=9.27, height_m=40.0, pitch_deg=45.0, heading_deg=140.0)
    results = []
    for cam in (camera, distorted):
        # random box sizes: trust the priors without checking them, so that the filter is exercised
        pipe = DetectionPipeline(cam, {1: "person", 2: "swimmer"},
                                 PipelineConfig(size_check_max_shift=9.5, size_check_widen=False,
                                                size_check_min_boxes=1))
        for k in range(3):
            res = pipe.process(boxes, scores, cids, pose, k / 30.0)
        results.append(res)
    a, b = results
    assert a.n_size_filtered == b.n_size_filtered > 0 and a.n_georeferenced == b.n_georeferenced
    np.testing.assert_array_equal(a.class_ids, b.class_ids)
    np.testing.assert_allclose(a.scores, b.scores, rtol=1e-6)
    np.testing.assert_allclose(a.lat, b.lat, rtol=0, atol=1e-12)

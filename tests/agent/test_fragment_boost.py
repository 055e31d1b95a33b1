"""The boost of a box that a higher-ranked box of its class overlaps but NMS keeps (PipelineConfig.fragment_iou):
the map's evidence goes to the box on the object, not to its parts and displaced copies."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.boxes import box_iou, outranked_overlaps
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon

LAT, LON = 48.0, 9.0
CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
CLASSES = {1: "person", 2: "swimmer"}
POSE = Pose(lat=LAT, lon=LON, height_m=40.0, pitch_deg=60.0, heading_deg=30.0)


def reference(boxes, rank, rows, lo, hi):
    iou = box_iou(boxes, boxes)
    return np.array([any(rank[j] > rank[i] and lo <= iou[i, j] < hi for j in range(len(boxes)) if j != i)
                     for i in rows], dtype=bool)


@st.composite
def scenes(draw):
    n = draw(st.integers(0, 60))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    centres = rng.uniform(0, 200, (draw(st.integers(1, 5)), 2))  # clusters: many overlaps
    c = centres[rng.integers(0, len(centres), n)] + rng.normal(0, draw(st.sampled_from([2.0, 10.0])), (n, 2))
    size = rng.uniform(4, 40, (n, 2))
    boxes = np.column_stack([c - size / 2, c + size / 2]).astype(np.float32)
    rank = rng.choice([0.1, 0.5, 0.9], n) if draw(st.booleans()) else rng.uniform(0, 1, n)  # ties too
    rows = np.flatnonzero(rng.uniform(size=n) < draw(st.sampled_from([0.3, 1.0])))
    return boxes, rank, rows


@settings(max_examples=150, deadline=None)
@given(scenes(), st.sampled_from([0.05, 0.1, 0.3]))
def test_outranked_overlaps_equals_the_pairwise_definition(scene, lo):
    boxes, rank, rows = scene
    got = outranked_overlaps(boxes, rank, lo)[rows]
    np.testing.assert_array_equal(got, reference(boxes.astype(np.float64), rank, rows, lo, np.inf))
    # only some rows tested (the joint boxes' rule): the same answers there, False elsewhere
    only = outranked_overlaps(boxes, rank, lo, rows=rows)
    np.testing.assert_array_equal(only[rows], got)
    assert not np.delete(only, rows).any()


def box_at(east: float, north: float, size_px: float = 40.0, dx: float = 0.0) -> np.ndarray:
    lat, lon = local_to_latlon(np.array([east]), np.array([north]), LAT, LON)
    uv, ok = latlon_to_pixel(lat, lon, CAM, POSE)
    assert ok[0]
    u, v = uv[0]
    u += dx
    return np.array([u - size_px / 4, v - size_px * 0.75, u + size_px / 4, v + size_px * 0.25], np.float32)


def run(cfg: PipelineConfig, boxes: np.ndarray, scores: list[float], frames: int = 12):
    """The same boxes every frame for `frames` frames at 30 fps; the last frame's result."""
    pipe = DetectionPipeline(CAM, CLASSES, cfg)
    res = None
    for k in range(frames):
        res = pipe.process(boxes, np.array(scores, np.float32), np.ones(len(boxes), np.int64), POSE, k / 30)
    assert res is not None
    return res


def score_of(res, raw: float) -> float:
    k = np.flatnonzero(np.isclose(res.raw_scores, raw))
    assert len(k) == 1, res.raw_scores
    return float(res.scores[k[0]])


def test_a_part_of_a_remembered_object_is_not_boosted_but_the_object_is():
    whole = box_at(0.0, 30.0)
    part = whole.copy()
    part[1] = whole[1] + 0.55 * (whole[3] - whole[1])  # the lower part of the same person: IoU 0.45 with it
    part[0] -= 6.0
    boxes = np.stack([whole, part])
    assert 0.1 < box_iou(whole[None], part[None])[0, 0] < 0.5
    on = run(PipelineConfig(fragment_iou=0.1), boxes, [0.6, 0.35])
    off = run(PipelineConfig(fragment_iou=0.0), boxes, [0.6, 0.35])
    assert score_of(on, 0.6) > 0.6 and score_of(on, 0.6) == pytest.approx(score_of(off, 0.6))
    assert score_of(on, 0.35) == pytest.approx(0.35)  # kept by NMS, not boosted
    assert score_of(off, 0.35) > 0.5  # the paper's rule lifts it over the operating point: a false positive


def test_people_side_by_side_are_both_boosted():
    a, b = box_at(0.0, 30.0), box_at(1.5, 30.0)
    assert box_iou(a[None], b[None])[0, 0] == 0.0
    res = run(PipelineConfig(fragment_iou=0.1), np.stack([a, b]), [0.6, 0.35])
    assert score_of(res, 0.6) > 0.6 and score_of(res, 0.35) > 0.35


def test_the_map_picks_the_box_on_the_object_when_a_displaced_copy_is_more_confident():
    """Ranked by the score the map would give: a copy 1 m aside, more confident than the box on a remembered
    object, loses its boost when the object's evidence lifts that box above it (ranked by the detector's
    scores, the box on the object would lose it)."""
    whole = box_at(0.0, 30.0, size_px=80.0)
    pipe = DetectionPipeline(CAM, CLASSES, PipelineConfig(fragment_iou=0.1))
    for k in range(12):  # the object alone, remembered
        pipe.process(whole[None], np.array([0.6], np.float32), np.ones(1, np.int64), POSE, k / 30)
    shifted = box_at(0.0, 30.0, size_px=80.0, dx=30.0)
    assert 0.1 <= box_iou(whole[None], shifted[None])[0, 0] < 0.5
    res = pipe.process(np.stack([whole, shifted]), np.array([0.40, 0.41], np.float32), np.ones(2, np.int64), POSE,
                       12 / 30)
    assert score_of(res, 0.40) > 0.6  # boosted: the map's evidence ranks the box on the object first
    assert score_of(res, 0.41) == pytest.approx(0.41)


def test_classes_do_not_outrank_each_other():
    whole = box_at(0.0, 30.0)
    part = whole.copy()
    part[1] = whole[1] + 0.55 * (whole[3] - whole[1])
    pipe = DetectionPipeline(CAM, CLASSES, PipelineConfig(fragment_iou=0.1))
    res = None
    for k in range(12):
        res = pipe.process(np.stack([whole, part]), np.array([0.6, 0.35], np.float32), np.array([1, 2]), POSE, k / 30)
    assert res is not None
    assert score_of(res, 0.35) > 0.35  # a swimmer under a person's box is its own object


def test_mixed_classes_keep_their_own_ranks():
    """Kept boxes of two classes interleaved: each class's parts lose their boost to their own class's boxes
    only, as the pairwise definition says."""
    person = box_at(0.0, 30.0, size_px=80.0)
    person_part = person.copy()
    person_part[1] = person[1] + 0.55 * (person[3] - person[1])
    swimmer = box_at(6.0, 30.0, size_px=80.0)
    swimmer_copy = box_at(6.0, 30.0, size_px=80.0, dx=30.0)
    boxes = np.stack([person_part, swimmer, person, swimmer_copy])
    scores = [0.35, 0.62, 0.6, 0.41]
    cids = np.array([1, 2, 1, 2])
    on = DetectionPipeline(CAM, CLASSES, PipelineConfig(fragment_iou=0.1))
    off = DetectionPipeline(CAM, CLASSES, PipelineConfig(fragment_iou=0.0))
    for k in range(12):
        r_on = on.process(boxes, np.array(scores, np.float32), cids, POSE, k / 30)
        r_off = off.process(boxes, np.array(scores, np.float32), cids, POSE, k / 30)
    # the pairwise definition on the boxes the paper's rule keeps and their boosted scores
    ref = np.zeros(len(r_off.scores), dtype=bool)
    for c in (1, 2):
        sel = np.flatnonzero((r_off.class_ids == c) & (r_off.scores > r_off.raw_scores))
        same = np.flatnonzero(r_off.class_ids == c)
        iou = box_iou(r_off.boxes_xyxy[sel], r_off.boxes_xyxy[same])
        ref[sel] = ((iou >= 0.1) & (r_off.scores[same][None, :] > r_off.scores[sel][:, None])).any(axis=1)
    assert ref.sum() == 2  # the person's part and the swimmer's copy
    for raw, boosted, lost in zip(r_off.raw_scores, r_off.scores, ref, strict=True):
        assert score_of(r_on, float(raw)) == pytest.approx(float(raw) if lost else float(boosted))


def test_output_stays_sorted_and_within_the_score_threshold():
    whole = box_at(0.0, 30.0)
    part = whole.copy()
    part[1] = whole[1] + 0.55 * (whole[3] - whole[1])
    cfg = PipelineConfig(fragment_iou=0.1, score_threshold=0.1)
    res = run(cfg, np.stack([whole, part, box_at(3.0, 30.0)]), [0.6, 0.05, 0.3])
    assert list(res.scores) == sorted(res.scores, reverse=True)
    assert 0.05 not in np.round(res.raw_scores, 3)  # the part fell back to 0.05, under the threshold: dropped


@pytest.mark.parametrize("value", [-0.1, 1.0, float("nan"), float("inf"), True, "0.1"])
def test_bad_fragment_iou_is_named(value):
    with pytest.raises(ValueError, match="fragment_iou"):
        PipelineConfig(fragment_iou=value)


def test_a_low_nms_threshold_is_not_refused_for_the_default_fragment_iou():
    # the rule acts between fragment_iou and nms_iou; at or above nms_iou there is nothing to act on
    assert PipelineConfig(nms_iou=0.1).fragment_iou == 0.1
    assert dataclasses.replace(PipelineConfig(), fragment_iou=np.float32(0.2)).fragment_iou == pytest.approx(0.2)

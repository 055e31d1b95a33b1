"""Appearance descriptors: the HSV extractor, the optional pre_nms.json field, the pipeline's pass-through
and their use by GpsTracker for re-identification. Real parts, no mocks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent.appearance import hsv_histogram_descriptors
from agent.dataset import Candidates, Dataset
from agent.pipeline import DetectionPipeline, PipelineConfig
from agent.tracker import GpsTracker, TrackerConfig
from tests.agent.test_tracker import CAM, CLASSES, FPS, empty_result, observe, pose_at


def test_hsv_descriptors_match_the_same_colours_and_separate_different_ones():
    image = np.zeros((200, 300, 3), np.uint8)
    image[20:120, 20:60] = (0, 0, 200)      # red jacket (BGR)
    image[20:120, 120:160] = (0, 0, 180)    # another red one, a little darker
    image[20:120, 220:260] = (200, 120, 0)  # blue jacket
    boxes = np.array([[20, 20, 60, 120], [120, 20, 160, 120], [220, 20, 260, 120], [0, 150, 2, 152]], float)
    d = hsv_histogram_descriptors(image, boxes)
    assert d.shape == (4, 32)
    assert np.allclose(np.linalg.norm(d[:3], axis=1), 1.0, atol=1e-5)
    assert d[0] @ d[1] > 0.9 > 0.1 > d[0] @ d[2]
    assert np.isnan(d[3]).all()  # too small to say anything


def _dataset() -> Dataset:
    coco = {"images": [{"id": 1, "file_name": "a.jpg", "width": 3840, "height": 2160, "video_id": 1,
                        "frame_index": 0, "date_time": "2023-06-01T10:00:00.000Z", "meta": None}],
            "annotations": [], "categories": [{"id": 1, "name": "person"}], "videos": [{"id": 1, "name": "v"}]}
    return Dataset.from_dict(coco)


def test_candidates_read_the_optional_embedding_field():
    ds = _dataset()
    entries = [{"image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 40], "score": 0.9, "embedding": [1.0, 0.0]},
               {"image_id": 1, "category_id": 1, "bbox": [50, 10, 20, 40], "score": 0.1}]
    c = Candidates.from_list(entries, ds)
    emb = c.get_embeddings(1)
    assert emb is not None and emb.shape == (2, 2)
    assert emb[0].tolist() == [1.0, 0.0] and np.isnan(emb[1]).all()
    # backward compatible: files without the field have no embeddings
    assert Candidates.from_list([{k: v for k, v in e.items() if k != "embedding"} for e in entries],
                                ds).get_embeddings(1) is None
    with pytest.raises(ValueError, match="entry 0"):
        Candidates.from_list([{**entries[0], "embedding": "red"}], ds)
    with pytest.raises(ValueError, match="different lengths"):
        Candidates.from_list([entries[0], {**entries[1], "embedding": [1.0, 0.0, 0.0]}], ds)


def test_the_pipeline_passes_embeddings_through_nms_to_the_kept_boxes():
    pipe = DetectionPipeline(CAM, {1: "person"}, PipelineConfig(use_memory=False))
    boxes = np.array([[100, 100, 120, 150], [101, 101, 121, 151], [400, 100, 420, 150]], np.float32)
    scores = np.array([0.5, 0.9, 0.8], np.float32)
    emb = np.array([[1, 0], [0, 1], [0.6, 0.8]], np.float32)
    res = pipe.process(boxes, scores, np.ones(3, np.int64), pose_at(), 1.7e9, emb)
    assert res.embeddings is not None
    got = {tuple(b.tolist()): tuple(e.tolist()) for b, e in zip(res.boxes_xyxy, res.embeddings, strict=True)}
    assert got == {(101.0, 101.0, 121.0, 151.0): (0.0, 1.0), (400.0, 100.0, 420.0, 150.0): pytest.approx((0.6, 0.8))}
    assert pipe.process(boxes, scores, np.ones(3, np.int64), pose_at(), 1.7e9 + 0.1).embeddings is None


def _swap_run(config: TrackerConfig) -> tuple[dict[int, int], int]:
    """Two people 2.5 m apart with different looks; while the UAV looks away for 5 s they trade places.
    Returns {person: id after the return} and the number of re-identifications."""
    tracker = GpsTracker(config, CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    looks = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

    def seen(e: list[float]):
        return dataclasses.replace(observe(e, [25.0, 25.0], pose), embeddings=looks.astype(np.float32))

    frames = [(seen([0.0, 2.5]), pose)] * 60 + [(empty_result(), away)] * 150 + [(seen([2.5, 0.0]), pose)] * 20
    out = []
    for k, (result, p) in enumerate(frames):
        out = tracker.update(result, p, 1.7e9 + k / FPS, CAM)
    by_box = {round(tr.box_xyxy[0]): tr.id for tr in out if tr.confirmed and tr.matched}
    first = observe([2.5, 0.0], [25.0, 25.0], pose).boxes_xyxy[:, 0]
    return {person: by_box[round(float(first[person]))] for person in (0, 1)}, tracker.n_reidentified


def test_appearance_keeps_ids_when_neighbours_trade_places_out_of_view():
    ids, n_reid = _swap_run(TrackerConfig())
    assert ids == {0: 1, 1: 2} and n_reid == 2
    # Motion alone gives each the other's id: the cue is what makes the difference.
    ids_motion, _ = _swap_run(TrackerConfig(use_appearance=False))
    assert ids_motion == {0: 2, 1: 1}


def test_a_detection_that_looks_different_does_not_revive_a_lost_track():
    tracker = GpsTracker(TrackerConfig(), CLASSES)
    pose, away = pose_at(), pose_at(heading_deg=180.0)
    red = dataclasses.replace(observe(0.0, 25.0, pose), embeddings=np.array([[1.0, 0.0]], np.float32))
    blue = dataclasses.replace(observe(0.0, 25.0, pose), embeddings=np.array([[0.0, 1.0]], np.float32))
    frames = [(red, pose)] * 60 + [(empty_result(), away)] * 90 + [(blue, pose)] * 20
    out = []
    for k, (result, p) in enumerate(frames):
        out = tracker.update(result, p, 1.7e9 + k / FPS, CAM)
    assert [tr.id for tr in out if tr.confirmed] == [2]
    assert tracker.n_reidentified == 0 and [tr.id for tr in tracker.lost_tracks] == [1]

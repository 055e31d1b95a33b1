"""Appearance descriptors: the HSV extractor, the optional pre_nms.json field, the pipeline's pass-through
and their use by GpsTracker for re-identification. Real parts, no mocks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from agent.dataset import Candidates, Dataset
from agent.frame_result import FrameResult
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking.appearance import hsv_histogram_descriptors, with_image_descriptors
from agent.tracking_io import track_dataset, track_video
from shared.geo import Camera
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


# ---- the extractor on real images -------------------------------------------------------------------
def _hsv_patch(hue: int, size: tuple[int, int] = (40, 80)) -> np.ndarray:
    """A BGR image of one colour given by its OpenCV hue (0..179), fully saturated and bright."""
    import cv2

    hsv = np.zeros((size[1], size[0], 3), np.uint8)
    hsv[..., 0], hsv[..., 1], hsv[..., 2] = hue, 230, 220
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)


def test_red_at_both_ends_of_the_hue_circle_gets_the_same_descriptor():
    box = np.array([[0, 0, 40, 80]], float)
    reds = [hsv_histogram_descriptors(_hsv_patch(h), box)[0] for h in (1, 178)]
    green = hsv_histogram_descriptors(_hsv_patch(60), box)[0]
    # hue 1 and 178 are 3 of 180 apart on the circle: before the circular binning they shared no bin
    assert reds[0] @ reds[1] > 0.9
    assert reds[0] @ green < 0.1
    # a hue on a bin edge does not flip bins: 22 and 23 straddle the edge at 22.5 of 8 bins
    a, b = (hsv_histogram_descriptors(_hsv_patch(h), box)[0] for h in (22, 23))
    assert a @ b > 0.99


def _result(boxes: np.ndarray, embeddings: np.ndarray | None = None) -> FrameResult:
    k = len(boxes)
    return FrameResult(boxes.astype(np.float32), np.ones(k, np.float32), np.ones(k, np.float32),
                       np.ones(k, np.int64), np.full(k, np.nan), np.full(k, np.nan), k, 0, 0, embeddings)


def test_image_descriptors_fill_only_what_the_candidates_lack():
    image = np.zeros((100, 200, 3), np.uint8)
    image[10:90, 10:50] = _hsv_patch(0)
    image[10:90, 110:150] = _hsv_patch(120)
    boxes = np.array([[10, 10, 50, 90], [110, 10, 150, 90]], float)
    expected = hsv_histogram_descriptors(image, boxes)
    filled = with_image_descriptors(_result(boxes), image).embeddings
    assert filled is not None and np.allclose(filled, expected)
    given = np.full((2, 32), np.nan, np.float32)
    given[0] = np.eye(32)[5]
    mixed = with_image_descriptors(_result(boxes, given), image).embeddings
    assert mixed is not None and np.array_equal(mixed[0], np.eye(32)[5]) and np.allclose(mixed[1], expected[1])
    other_kind = np.full((2, 16), np.nan, np.float32)
    other_kind[0] = 0.25
    # a descriptor of another length is never mixed with colour histograms
    assert with_image_descriptors(_result(boxes, other_kind), image).embeddings is other_kind
    assert with_image_descriptors(_result(boxes), None).embeddings is None


def _dataset_with_images(tmp_path: Path, frames: int, with_images: int) -> Path:
    """A small simulated sea dataset without the emulated descriptors; the first `with_images` frames
    get JPEG files (each object a rectangle of its own colour on a blue-grey sea), the rest none."""
    import cv2

    from sim.dataset import write_dataset

    out = tmp_path / "data"
    write_dataset("sea", out, seed=4, frames=frames, progress=False)
    entries = json.loads((out / "pre_nms.json").read_text())
    (out / "pre_nms.json").write_text(json.dumps([{k: v for k, v in e.items() if k != "embedding"} for e in entries]))
    coco = json.loads((out / "images.json").read_text())
    by_image: dict[int, list[dict]] = {}
    for a in coco["annotations"]:
        by_image.setdefault(a["image_id"], []).append(a)
    for im in coco["images"]:
        if im["frame_index"] >= with_images:
            continue
        image = np.full((im["height"], im["width"], 3), (90, 80, 60), np.uint8)
        for a in by_image.get(im["id"], []):
            x, y, w, h = (int(round(v)) for v in a["bbox"])
            image[max(y, 0):y + h, max(x, 0):x + w] = _hsv_patch((37 * a["track_id"]) % 180, (1, 1))[0, 0]
        path = out / im["file_name"]
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), image)
    return out


def test_track_video_describes_the_kept_boxes_from_the_image_files_that_exist(tmp_path):
    import cv2

    data = _dataset_with_images(tmp_path, frames=12, with_images=8)
    ds = Dataset.load(data / "images.json")
    cands = Candidates.load(data / "pre_nms.json", ds)
    cam = Camera.from_file(data / "camera.json")
    video_id = next(iter(ds.videos))
    seen: list[tuple[int, FrameResult]] = []
    stats: dict = {}
    track_video(ds, cands, cam, video_id, PipelineConfig(), stats=stats, image_dir=data,
                on_frame=lambda frame, result, tracks: seen.append((frame.image.frame_index, result)))
    assert stats["images_read"] == 8 and stats["images_missing"] == 4
    described = 0
    for index, result in seen:
        if index >= 8:  # no file: no descriptors (the candidates carry none either)
            assert result.embeddings is None
            continue
        image = cv2.imread(str(data / ds.videos[video_id][index].file_name))
        assert result.embeddings is not None and result.embeddings.shape == (len(result), 32)
        # row k describes kept box k
        np.testing.assert_allclose(result.embeddings, hsv_histogram_descriptors(image, result.boxes_xyxy),
                                   equal_nan=True)
        described += int(np.isfinite(result.embeddings).all(axis=1).sum())
    assert described > 0
    # without images (or with --no-images) the same run reads none and does not fail
    summary = track_dataset(data / "images.json", data / "pre_nms.json", data / "camera.json", tmp_path / "out/",
                            PipelineConfig(), use_images=False)
    assert summary["images_read"] == summary["images_missing"] == 0 and summary["frames"] == 12 * len(ds.videos)
    summary = track_dataset(data / "images.json", data / "pre_nms.json", data / "camera.json", tmp_path / "out/",
                            PipelineConfig(), image_dir=tmp_path / "nowhere")
    assert summary["images_read"] == 0 and summary["images_missing"] == summary["frames"]


def test_the_live_agent_describes_detections_of_its_video_source(tmp_path):
    import cv2

    from agent.node import AgentNode, AgentSettings
    from agent.sources import VideoSource
    from tests.agent.test_sources import _write_model

    # the model's constant box: (320, 320) 60 x 120 in the 640 x 640 letterbox = (160, 90) 30 x 60 here
    path = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 180))
    assert writer.isOpened()
    for _ in range(6):
        image = np.full((180, 320, 3), (90, 80, 60), np.uint8)
        image[55:125, 140:180] = _hsv_patch(0, (40, 70))  # a red jacket
        writer.write(image)
    writer.release()
    telemetry = tmp_path / "flight.csv"
    telemetry.write_text("time_s,lat,lon,height_m,pitch_deg,heading_deg\n"
                         + "".join(f"{100 + 0.5 * i},48.53,9.06,30,90,0\n" for i in range(3)))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    source = VideoSource(path, telemetry, _write_model(tmp_path / "model.onnx"), camera)
    frames = list(source.frames())
    assert frames[0].image is not None and frames[0].image.shape == (180, 320, 3)
    # the synthetic box is not person-sized for this camera height: no size filter
    node = AgentNode(AgentSettings(uav_id="uav1"), source, PipelineConfig(use_size_filter=False))
    result, _ = node.step(frames[0])
    assert result.embeddings is not None and len(result) >= 1
    red = result.embeddings[0].reshape(8, 4).sum(axis=1)  # hue bins: red is at both ends of the circle
    assert red[0] + red[-1] > 0.9 * red.sum()


def test_no_descriptor_rows_are_no_rows_not_an_error():
    # regression: a frame whose every box was removed handed the tracker a (0, D) array; reshape(0, -1) failed
    from agent.tracking.appearance import unit_rows

    out = unit_rows(np.zeros((0, 16), np.float32), 0)
    assert out is not None and out.shape == (0, 16)
    assert unit_rows(np.zeros((0, 0)), 0) is None

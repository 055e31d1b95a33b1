"""The annotated frames of `uavmm detect --render-video` (agent.offline.annotate): a box, an id label and a trail
per track, the kept detections, and a north-up inset of the memory map (issue 18, Build 1). Checked on the drawn
frames themselves (`VideoAnnotator.draw`), before the lossy MP4 encoder."""

from __future__ import annotations

import os
import stat

import cv2
import numpy as np
import pytest

from agent.offline.annotate import VideoAnnotator, _track_colour
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.tracking import TrackOutput
from shared.geo import Camera, Pose, pixel_to_latlon

CAM = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)
# looking east, 30 deg below the horizon: the image centre is ~69 m east of the UAV
POSE = Pose(lat=47.67, lon=9.27, height_m=40.0, pitch_deg=30.0, heading_deg=90.0)
GREY = 90
FPS = 10.0


def _box(u: float) -> np.ndarray:
    return np.array([[u - 10, 170, u + 10, 210]], np.float32)


def _track(box: np.ndarray, track_id: int = 1) -> TrackOutput:
    x1, _, x2, y2 = (float(v) for v in box[0])
    lat, lon, valid = pixel_to_latlon(np.array([[0.5 * (x1 + x2), y2]]), CAM, POSE)
    assert valid[0]
    return TrackOutput(id=track_id, cls=0, box_xyxy=(x1, float(box[0, 1]), x2, y2), lat=float(lat[0]),
                       lon=float(lon[0]), vel_en=(0.0, 0.0), score=0.9, confirmed=True, matched=True, hits=5)


def _is(pixel: np.ndarray, colour: tuple[int, int, int], tol: int = 40) -> bool:
    return bool(np.all(np.abs(pixel.astype(int) - np.array(colour)) <= tol))


@pytest.fixture()
def drawn(tmp_path):
    """A person walking right through the frame centre for 11 frames (20 px a frame): the last frame drawn with
    its track, and the annotator."""
    pipe = DetectionPipeline(CAM, {0: "person"}, PipelineConfig(use_size_filter=False))
    annotator = VideoAnnotator(tmp_path / "a.mp4", FPS, CAM.width, CAM.height, {0: "person"}, trail_s=2.0,
                               inset_fraction=0.5)
    image = np.full((CAM.height, CAM.width, 3), GREY, np.uint8)
    canvas = image
    for i in range(11):
        box = _box(220 + 20 * i)
        result = pipe.process(box, np.array([0.9], np.float32), np.array([0]), POSE, i / FPS)
        canvas = annotator.draw(image, i / FPS, CAM, POSE, result, [_track(box)], pipe.memory)
    annotator.abort()
    return canvas, pipe, annotator


def test_each_track_has_a_box_and_a_label_in_its_colour(drawn):
    canvas, _, _ = drawn
    colour = _track_colour(1)
    x1, y1, x2, y2 = 410, 170, 430, 210  # the last frame's box
    assert _is(canvas[190, x1], colour) and _is(canvas[190, x2], colour)  # left and right edges
    assert _is(canvas[y1, 420], colour) and _is(canvas[y2, 420], colour)  # top and bottom
    label = canvas[y1 - 16:y1 - 2, x1:x1 + 60].reshape(-1, 3)  # "1 person 0.90" on a dark box above it
    assert (label.max(axis=1) < 30).mean() > 0.4  # the dark box
    assert sum(_is(p, colour, 60) for p in label) >= 10  # the text in the track's colour


def test_a_track_leaves_a_trail_on_the_ground_behind_it(drawn):
    canvas, _, _ = drawn
    colour = _track_colour(1)
    # the bottom centres of the earlier boxes (u = 220 ... 400 at v = 210), outside the current box
    on_trail = [canvas[209:212, u] for u in (240, 300, 360)]
    assert all(any(_is(p, colour) for p in column) for column in on_trail)
    assert _is(canvas[260, 300], (GREY, GREY, GREY), 2)  # off the trail: the frame as it was


def test_the_inset_is_north_up_with_the_memory_map_the_uav_and_the_tracks(drawn):
    canvas, pipe, annotator = drawn
    s = annotator.inset_px
    h, w = canvas.shape[:2]
    inset = canvas[4:4 + s, w - s - 4:w - 4]
    assert s == 180 and not _is(inset[s // 2, s // 2], (GREY, GREY, GREY), 2)  # drawn over the frame
    # the track is east of the UAV: in a north-up inset its dot is right of the UAV, on about the same row
    colour = _track_colour(1)
    mask = np.all(np.abs(inset.astype(int) - np.array(colour)) <= 40, axis=2)
    rows, cols = np.nonzero(mask)
    assert len(rows) > 5
    uav_rows, uav_cols = np.nonzero(np.all(inset[10:-10, 10:-30] == 255, axis=2))  # the white triangle
    uav_row, uav_col = uav_rows.mean() + 10, uav_cols.mean() + 10
    window_m = pipe.memory.size_cells * pipe.memory.grid.cell_size_m(POSE.lat)
    expected_px = 69.3 / window_m * s
    assert cols.mean() - uav_col == pytest.approx(expected_px, rel=0.3)
    assert abs(rows.mean() - uav_row) < 0.25 * expected_px
    # the memory map: the person walked right in the image, i.e. south on the ground (the camera looks east), so
    # the evidence it left is a streak north of its dot (inferno colours: neither black nor the cyan footprint)
    dot_row, dot_col = int(rows.mean()), int(round(cols.mean()))
    streak = inset[dot_row - 15:dot_row - 5, dot_col - 1:dot_col + 2].reshape(-1, 3).astype(int)
    assert (streak.max(axis=1) > 60).all() and not any(_is(p, (255, 255, 0), 60) for p in streak)
    assert (inset[dot_row - 15:dot_row - 5, dot_col + 8:dot_col + 12].max(axis=2) < 30).all()  # beside it: black


def test_no_inset_without_pose_or_when_switched_off(tmp_path):
    pipe = DetectionPipeline(CAM, {0: "person"}, PipelineConfig(use_size_filter=False))
    image = np.full((CAM.height, CAM.width, 3), GREY, np.uint8)
    box = _box(320)
    result = pipe.process(box, np.array([0.9], np.float32), np.array([0]), POSE, 0.0)
    for fraction, pose in ((0.5, None), (0.0, POSE)):
        annotator = VideoAnnotator(tmp_path / "a.mp4", FPS, CAM.width, CAM.height, {0: "person"},
                                   inset_fraction=fraction)
        canvas = annotator.draw(image, 0.0, CAM, pose, result, [_track(box)], pipe.memory)
        annotator.abort()
        assert np.all(canvas[30:, CAM.width - 150:] == GREY)  # the top-right corner is the frame's


def test_the_video_decodes_at_the_input_size_with_the_drawn_frames(tmp_path):
    pipe = DetectionPipeline(CAM, {0: "person"}, PipelineConfig(use_size_filter=False))
    annotator = VideoAnnotator(tmp_path / "a.mp4", FPS, CAM.width, CAM.height, {0: "person"})
    image = np.full((CAM.height, CAM.width, 3), GREY, np.uint8)
    for i in range(5):
        box = _box(300 + 10 * i)
        result = pipe.process(box, np.array([0.9], np.float32), np.array([0]), POSE, i / FPS)
        annotator.write(image, i / FPS, CAM, POSE, result, [_track(box)], pipe.memory)
    annotator.close()
    capture = cv2.VideoCapture(str(tmp_path / "a.mp4"))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == 5 and frames[-1].shape == (CAM.height, CAM.width, 3)
    assert _is(frames[-1][190, 330], _track_colour(1), 80)  # the last box's left edge survives the encoder
    assert not list(tmp_path.glob(".*tmp*"))


def test_the_video_is_never_written_through_a_link_planted_at_a_temporary_name(tmp_path):
    """The partial video goes to a new hidden name (not `.a.tmp.mp4`, where a link could point at another file)."""
    precious = tmp_path / "precious.bin"
    precious.write_bytes(b"precious")
    (tmp_path / ".a.tmp.mp4").symlink_to(precious)
    annotator = VideoAnnotator(tmp_path / "a.mp4", FPS, CAM.width, CAM.height, {0: "person"})
    pipe = DetectionPipeline(CAM, {0: "person"}, PipelineConfig(use_size_filter=False))
    image = np.full((CAM.height, CAM.width, 3), GREY, np.uint8)
    result = pipe.process(_box(300), np.array([0.9], np.float32), np.array([0]), POSE, 0.0)
    annotator.write(image, 0.0, CAM, POSE, result, [_track(_box(300))], pipe.memory)
    annotator.close()
    assert precious.read_bytes() == b"precious" and (tmp_path / "a.mp4").stat().st_size > 0
    assert sorted(p.name for p in tmp_path.glob(".*")) == [".a.tmp.mp4"]  # only the planted link is left
    dropped = VideoAnnotator(tmp_path / "b.mp4", FPS, CAM.width, CAM.height, {0: "person"})
    dropped.abort()
    assert not (tmp_path / "b.mp4").exists() and sorted(p.name for p in tmp_path.glob(".*")) == [".a.tmp.mp4"]


def test_the_video_gets_the_permissions_every_other_output_gets(tmp_path):
    """Its new temporary name (mkstemp) is made 0600; the video then was too, unreadable to a web server or another
    user (the review's finding): it gets open()'s 0666 less the umask, as the other outputs."""
    old = os.umask(0o022)
    try:
        pipe = DetectionPipeline(CAM, {0: "person"}, PipelineConfig(use_size_filter=False))
        result = pipe.process(_box(300), np.array([0.9], np.float32), np.array([0]), POSE, 0.0)
        annotator = VideoAnnotator(tmp_path / "a.mp4", FPS, CAM.width, CAM.height, {0: "person"})
        annotator.write(np.full((CAM.height, CAM.width, 3), GREY, np.uint8), 0.0, CAM, POSE, result, [], pipe.memory)
        annotator.close()
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.mp4").stat().st_mode) == 0o644

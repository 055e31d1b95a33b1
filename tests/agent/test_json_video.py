"""A SeaDronesSee COCO file as the telemetry of its video (agent.json_video): each meta at its own video frame,
a held sample counted once, the video chosen by name, the pitch convention the file's."""

from __future__ import annotations

import datetime as dt
import json
import logging

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.json_video import on_video_frames, read_video_json
from agent.sources import VideoSource
from shared.telemetry import Telemetry, read_telemetry
from tests.agent.test_sources import _write_model, _write_video

FPS = 10.0
T0 = dt.datetime(2020, 8, 25, 12, 19, 0, tzinfo=dt.timezone.utc)  # video frame 0, UTC


def _lat(s: float) -> float:  # flying north at 10 m/s
    return 47.672 + 10.0 * s / 111_320.0


def _images(first: int, last: int, step: int, video: str = "DJI_0032.MP4", ids: int = 0) -> list[dict]:
    """Images from frame `first` every `step` frames; the 1 Hz flight log's sample of each second held on them."""
    out = []
    for k, f in enumerate(range(first, last, step)):
        second = int(f / FPS)
        out.append({"id": ids + k, "file_name": f"{ids + k}.jpg", "width": 320, "height": 180,
                    "source": {"video": video, "frame_no": f},
                    "meta": {"datetime(utc)": (T0 + dt.timedelta(seconds=second)).strftime("%Y-%m-%d %H:%M:%S"),
                             "latitude": _lat(second), "longitude": 9.2679, "height_above_takeoff(meter)": 30.0,
                             "gimbal_heading(degrees)": 0.0, "gimbal_pitch(degrees)": 90.0}})
    return out


def test_each_frame_gets_the_pose_of_its_own_place_in_the_video(tmp_path):
    """The file starts at frame 30 of the video (real ones start mid-video: DJI_0032 at frame 5415) and keeps every
    5th frame; before, the first image was taken for video time 0 and every frame got the pose of 3 s later (30 m
    at 10 m/s), and each held copy of a sample was a sample of its own (a staircase lagging up to 1 s)."""
    video = _write_video(tmp_path / "DJI_0032.avi", 80, fps=FPS)
    (tmp_path / "camera.json").write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    images = _images(30, 80, 5)
    (tmp_path / "instances.json").write_text(json.dumps({"images": images, "annotations": [], "categories": []}))
    source = VideoSource(video, tmp_path / "instances.json", _write_model(tmp_path / "model.onnx"),
                         tmp_path / "camera.json")
    frames = {f.index: f for f in source.frames()}
    assert source.telemetry_offset_s == pytest.approx(T0.timestamp(), abs=1e-6)
    for f in (30, 40, 50, 60, 70):  # the frames where a second's sample first appears: exactly its place
        assert (frames[f].pose.lat - _lat(f / FPS)) * 111_320.0 == pytest.approx(0.0, abs=1e-3)
    # between samples a frame is interpolated (a held copy no longer stands for it): frame 55 half-way
    assert (frames[55].pose.lat - _lat(5.5)) * 111_320.0 == pytest.approx(0.0, abs=1e-3)


def test_the_video_named_like_the_file_is_read_from_a_file_of_several(tmp_path, caplog):
    path = tmp_path / "instances.json"
    images = _images(0, 40, 5, "DJI_0032.MP4") + _images(0, 40, 5, "DJI_0099.MP4", ids=100)
    for im in images[8:]:
        im["meta"]["longitude"] = 8.0
    path.write_text(json.dumps({"images": images, "annotations": [], "categories": []}))
    with caplog.at_level(logging.INFO, logger="agent.sources"):
        records = read_video_json(path, tmp_path / "DJI_0099.mp4")
    assert {r.lon for r in records} == {8.0} and len(records) == 8
    assert "video DJI_0099.MP4 of 2 (named like DJI_0099.mp4)" in caplog.text
    with pytest.raises(ValueError, match=r"holds 2 videos \(DJI_0032.MP4, DJI_0099.MP4\) and none named like the "
                                         r"video flight.mp4: name the video file as its entry"):
        read_video_json(path, tmp_path / "flight.mp4")


def test_the_pitch_convention_is_the_files_not_each_values():
    """Positive below the horizon, one frame tilted 3 deg above it (-3): that frame has no pose; before, -3 was read
    as DJI's sign for 3 deg down (a ground ray ~570 m out at 30 m)."""
    from shared.telemetry.seadronessee import parse_seadronessee_coco

    images = _images(0, 50, 5)
    for im, pitch in zip(images, [40.0, 30.0, 20.0, 10.0, 5.0, 1.6, -3.0, 1.6, 10.0, 20.0], strict=True):
        im["meta"]["gimbal_pitch(degrees)"] = pitch
    records = parse_seadronessee_coco({"images": images})
    assert 30 not in [r.frame for r in records]  # frame 30's meta (-3) is no depression
    assert [r.pitch_deg for r in records][:2] == [40.0, 30.0]


def _rec(t: float, frame: int | None, lat: float = 48.0) -> Telemetry:
    return Telemetry(t=t, lat=lat, lon=9.0, height_m=30.0, pitch_deg=60.0, heading_deg=0.0, frame=frame)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 10_000), min_size=1, max_size=30, unique=True), st.floats(-5e4, 5e4),
       st.sampled_from([10.0, 25.0, 29.97, 30.0, 60.0]))
def test_samples_are_placed_at_their_frames_whatever_the_stamps_clock(frames, shift, fps):
    """Stamps on any clock (a zone, an offset) that follow the frames: each sample lands at offset + frame / fps."""
    records = [_rec(1.6e9 + shift + f / fps, f, lat=48.0 + 1e-6 * f) for f in frames]
    out, start = on_video_frames(records, fps, "t.json")
    assert start == pytest.approx(1.6e9 + shift, abs=1e-5)
    assert [r.frame for r in out] == sorted(frames)
    assert [r.t for r in out] == pytest.approx([start + f / fps for f in sorted(frames)], abs=1e-6)


def test_records_without_frames_or_a_video_without_a_rate_are_left_as_they_are():
    records = [_rec(100.0, None), _rec(101.0, 3)]
    assert on_video_frames(records, 10.0, "t.json") == (records, None)
    framed = [_rec(100.0, 0), _rec(101.0, 10)]
    assert on_video_frames(framed, None, "t.json") == (framed, None)
    assert on_video_frames(framed, float("nan"), "t.json") == (framed, None)


def test_read_telemetry_of_a_json_is_unchanged_by_the_video_rule(tmp_path):
    """`read_telemetry` (not the video source) keeps each image's record, as the other readers do."""
    path = tmp_path / "one.json"
    path.write_text(json.dumps({"images": _images(0, 30, 5)}))
    assert len(read_telemetry(path)) == 6
    assert len(read_video_json(path, None)) == 6


def test_frame_numbers_that_do_not_follow_the_stamps_are_not_used(caplog):
    """Image indices of a sequence sampled every 15th frame (0, 1, 2, ... half a second apart): read as video frames
    at 30 frames/s they would squeeze the flight 15 times. The stamps say so: the rule stands down."""
    records = [_rec(1.6e9 + 0.5 * i, i, lat=48.0 + 1e-5 * i) for i in range(40)]
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        out, start = on_video_frames(records, 30.0, "seq.json")
    assert (out, start) == (records, None)
    assert "its frame numbers do not follow its stamps at the video's 30 frames/s" in caplog.text


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["video_id", "frame_no", "latitude"]),
       st.sampled_from([[1, 2], {"a": 1}, 10**400, -10**400, None, "x"]))
def test_an_odd_video_id_frame_number_or_meta_value_is_read_or_a_value_error(tmp_path_factory, field, value):
    """Fuzzing (1 Dec 2026): ``"video_id": [1, 2]`` on one image raised TypeError (unhashable) in read_video_json and
    own_video_ids, a frame number or a meta value of 1e400 written out OverflowError: tracebacks from --telemetry."""
    path = tmp_path_factory.mktemp("odd") / "instances.json"
    images = _images(0, 40, 5, "DJI_0032.MP4") + _images(0, 40, 5, "DJI_0099.MP4", ids=100)
    for image in images:
        image["video_id"] = 1 if image["id"] < 100 else 2
    target = images[3]
    {"video_id": target, "frame_no": target["source"], "latitude": target["meta"]}[field][field] = value
    path.write_text(json.dumps({"images": images, "annotations": [], "categories": [],
                                "videos": [{"id": 1, "name": "DJI_0032.MP4"}, {"id": 2, "name": "DJI_0099.MP4"}]}))
    try:
        records = read_video_json(path, "DJI_0032.MP4")
    except ValueError:
        return
    assert records

"""Real dataset files as they are (agent.dataset): SeaDronesSee Object Detection v2's `source` and flight-log
meta, several drones in one file, no video ids at all, frames without a usable pose counted by reason."""

from __future__ import annotations

import json
import logging
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from agent.boost import boost_dataset
from agent.dataset import Dataset, PoseProblem, VideoTelemetry, count_reasons, iter_video_frames
from agent.pipeline_config import PipelineConfig
from agent.tracking_io import mot_output_paths
from shared.geo import Camera

CAMERA = Camera.from_preset("dji-mavic2-pro")
REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "seadronessee-v2-dev"
T0 = datetime(2020, 8, 25, 14, 19, 21, 647133)


def _flight_log_image(image_id: int, video: str, frame_no: int, k: int, *, drone: str = "mavic",
                      heading: float = 99.3, meta: bool = True) -> dict:
    """A frame as SeaDronesSee Object Detection v2 writes it: local frame clock, UTC meta at whole seconds."""
    when = T0 + timedelta(seconds=0.5 * k)
    image = {"id": image_id, "file_name": f"{image_id}.jpg", "width": 3840, "height": 2160,
             "date_time": when.isoformat(), "source": {"drone": drone, "video": video, "frame_no": frame_no}}
    stamp = (when - timedelta(hours=2) + timedelta(seconds=0.5)).replace(microsecond=0)
    image["meta"] = {"datetime(utc)": stamp.strftime("%Y-%m-%d %H:%M:%S"), "latitude": 47.67209 - 1e-5 * (k // 2),
                     "longitude": 9.267889, "height_above_takeoff(meter)": 10.0,
                     "gimbal_heading(degrees)": heading + 5.0 * (k // 2), "gimbal_pitch(degrees)": 13.7,
                     "compass_heading(degrees)": 116.5} if meta else None
    return image


def _coco(images: list[dict]) -> dict:
    return {"images": images, "annotations": [], "categories": [{"id": 1, "name": "swimmer"}]}


def test_source_video_groups_and_frame_no_orders_the_frames():
    images = [_flight_log_image(10 + k, "DJI_0032.MP4", 5415 + 15 * k, k) for k in range(6)][::-1]
    images += [_flight_log_image(30 + k, "DJI_0069.MP4", 3120 + 15 * k, k) for k in range(4)]
    ds = Dataset.from_dict(_coco(images))
    assert sorted(ds.video_names.values()) == ["DJI_0032.MP4", "DJI_0069.MP4"]
    (v32,) = [v for v, name in ds.video_names.items() if name == "DJI_0032.MP4"]
    assert [im.frame_index for im in ds.videos[v32]] == [5415 + 15 * k for k in range(6)]
    assert [im.id for im in ds.videos[v32]] == list(range(10, 16))


def test_two_drones_with_one_video_name_are_two_videos():
    images = [_flight_log_image(k, "DJI_0001.MP4", k, k, drone="mavic") for k in range(3)]
    images += [_flight_log_image(10 + k, "DJI_0001.MP4", k, k, drone="matrice") for k in range(3)]
    ds = Dataset.from_dict(_coco(images))
    assert len(ds.videos) == 2 and sorted(ds.video_names.values()) == ["matrice_DJI_0001.MP4", "mavic_DJI_0001.MP4"]


def test_a_video_is_found_by_its_id_or_its_name():
    images = [_flight_log_image(k, "DJI_0001.MP4", k, k, drone="mavic") for k in range(3)]
    images += [_flight_log_image(10 + k, "DJI_0001.MP4", k, k, drone="matrice") for k in range(3)]
    images += [_flight_log_image(20 + k, "7", k, k) for k in range(3)]  # a video named like an id
    ds = Dataset.from_dict(_coco(images))
    ids = {name: vid for vid, name in ds.video_names.items()}
    assert ds.resolve_video("mavic_DJI_0001.MP4") == ids["mavic_DJI_0001.MP4"]
    assert ds.resolve_video(" matrice_DJI_0001.MP4 ") == ids["matrice_DJI_0001.MP4"]
    for vid in ds.videos:
        assert ds.resolve_video(vid) == ds.resolve_video(str(vid)) == vid
    assert ds.resolve_video("7") == (7 if 7 in ds.videos else ids["7"])  # an id wins over a name
    with pytest.raises(ValueError, match=r"unknown video 'DJI_0001.MP4'; known ids: \[.*names: .*'mavic_DJI_0001.MP4'"):
        ds.resolve_video("DJI_0001.MP4")  # two drones' videos share the file name: the drone tells them apart
    with pytest.raises(ValueError, match="unknown video '99'"):
        ds.resolve_video(99)


def test_images_without_any_video_are_split_where_their_clock_jumps():
    images = []
    for k in range(6):
        im = _flight_log_image(k + 1, "x", k, k)
        del im["source"]
        if k >= 3:  # a second flight an hour later
            im["date_time"] = (T0 + timedelta(hours=1, seconds=0.5 * k)).isoformat()
        images.append(im)
    ds = Dataset.from_dict(_coco(images[::-1]))
    assert sorted(len(v) for v in ds.videos.values()) == [3, 3]
    for frames in ds.videos.values():
        assert [f.frame_index for f in frames] == [0, 1, 2]
    plain = Dataset.from_dict(_coco([{"id": 1, "width": 10, "height": 10}, {"id": 2, "width": 10, "height": 10}]))
    assert list(plain.videos) == [0]  # no clock, no video: one video 0 in file order, as before


def test_frames_get_a_pose_at_their_own_time_and_problems_are_counted_by_reason():
    images = [_flight_log_image(k + 1, "DJI_0032.MP4", 15 * k, k) for k in range(8)]
    images[2]["meta"] = None
    del images[5]["meta"]["gimbal_pitch(degrees)"]
    images[6]["meta"]["latitude"] = "n/a"
    ds = Dataset.from_dict(_coco(images))
    problems: list[PoseProblem] = []
    report = VideoTelemetry()
    frames = list(iter_video_frames(ds, CAMERA, next(iter(ds.videos)), problems=problems, report=report))
    # the frame without a pitch lies between others' samples: the pose interpolated at its time (since 1 Dec 2026)
    assert [f.pose is None for f in frames] == [False, False, True, False, False, False, True, False]
    assert count_reasons(problems) == {"no meta": 1, "bad position": 1} and report.bridged_frames == 1
    assert report.clock.zone_offset_s == 7200.0 and report.clock.whole_seconds
    # poses are at the frames' own (local) times: the heading moves between the 1 Hz samples
    headings = [f.pose.heading_deg for f in frames if f.pose is not None]
    assert len(set(np.round(headings, 6))) == len(headings)
    assert all(f.pose_retimed and f.pose_t == f.t for f in frames if f.pose is not None)
    held = list(iter_video_frames(ds, CAMERA, next(iter(ds.videos)), at_frame_time=False))
    assert held[0].pose.heading_deg == held[1].pose.heading_deg  # the sample as carried (the paper's rule)
    assert abs(held[0].t - held[0].pose_t) < 1.0  # its stamp on the frame clock, not two hours away


def test_boost_summary_counts_frames_without_pose_by_reason(tmp_path):
    images = [_flight_log_image(k + 1, "DJI_0032.MP4", 15 * k, k) for k in range(6)]
    images[0]["meta"] = None
    images[3]["meta"]["datetime(utc)"] = "not a time"
    (tmp_path / "images.json").write_text(json.dumps(_coco(images)))
    dets = [{"image_id": k + 1, "category_id": 1, "bbox": [1800, 1600, 200, 150], "score": 0.8} for k in range(6)]
    (tmp_path / "dets.json").write_text(json.dumps(dets))
    results, stats = boost_dataset(tmp_path / "images.json", tmp_path / "dets.json", "dji-mavic2-pro",
                                   PipelineConfig())
    assert len(results) == 6  # every frame passes through, boosted or not
    assert stats["frames_without_pose"] == 2
    assert stats["frames_without_pose_by_reason"] == {"no meta": 1, "bad time": 1}
    assert stats["frames_with_bad_meta"] == 1
    assert stats["stages"]["time zone"]["acted"] == 1


@pytest.mark.skipif(not (REAL / "instances_dev.json").is_file(), reason="the team's real data is not beside the repo")
def test_every_frame_of_the_real_dev_file_has_a_pose():
    ds = Dataset.load(REAL / "instances_dev.json")
    assert len(ds.videos) == 8
    problems: list[PoseProblem] = []
    for video_id in ds.videos:
        report = VideoTelemetry()
        frames = list(iter_video_frames(ds, CAMERA, video_id, problems=problems, report=report))
        assert all(f.pose is not None for f in frames)
        assert report.clock.zone_offset_s == 7200.0 and report.clock.whole_seconds
        assert all(0.0 < f.pose.pitch_deg < 90.0 for f in frames)
    assert problems == []


def _fixed_wing(image_id: int, k: int) -> dict:
    """The fixed-wing of the same public files: no video field, its latitude in gps_latitude_ref, flying at once."""
    when = T0 + timedelta(seconds=0.5 * k + 0.25)
    return {"id": image_id, "file_name": f"{image_id}.jpg", "width": 3840, "height": 2160,
            "date_time": when.isoformat(), "source": {"drone": "fixedwing", "frame_no": 15 * k},
            "meta": {"gps_latitude_ref": 54.1 + 1e-5 * k, "gps_longitude_ref": 8.3, "altitude": 80.0,
                     "gimbal_pitch": 60.0, "gimbal_heading": 180.0,
                     "date_time": (when - timedelta(hours=2)).isoformat()}}


def test_two_drones_without_a_video_field_are_two_videos_with_their_own_poses(caplog):
    """Before: one video whose poses jumped 22 km between the two drones every frame (a memory map and a tracker
    fed two flights at once)."""
    images = [im for k in range(6) for im in (_flight_log_image(k + 1, "x", 15 * k, k), _fixed_wing(100 + k, k))]
    for im in images:
        im["source"].pop("video", None)
    with caplog.at_level(logging.WARNING, logger="agent.dataset"):
        ds = Dataset.from_dict(_coco(images), source="two.json")
    assert {ds.video_names[v]: [im.id for im in frames] for v, frames in ds.videos.items()} == {
        "fixedwing": list(range(100, 106)), "mavic": list(range(1, 7))}
    for v in ds.videos:
        lats = {round(f.pose.lat, 1) for f in iter_video_frames(ds, CAMERA, v)}
        assert lats == ({54.1} if ds.video_names[v] == "fixedwing" else {47.7})
    assert "two.json: 12 images without a video" in caplog.text
    assert sorted(p.name for p in mot_output_paths("out/", ds, list(ds.videos)).values()) == ["fixedwing.txt",
                                                                                              "mavic.txt"]


def test_one_drones_video_name_on_two_days_is_two_videos():
    """DJI_0001.MP4 recorded again the next day, frame numbers from 0: before, one video whose frames alternated
    between the two days (time clamped, poses from two flights)."""
    images = [_flight_log_image(k, "DJI_0001.MP4", 15 * k, k) for k in range(4)]
    for k in range(4):
        image = _flight_log_image(10 + k, "DJI_0001.MP4", 15 * k, k, heading=200.0)
        image["date_time"] = (T0 + timedelta(days=1, seconds=0.5 * k)).isoformat()
        stamp = T0 + timedelta(days=1, hours=-2, seconds=0.5 * k)
        image["meta"]["datetime(utc)"] = stamp.strftime("%Y-%m-%d %H:%M:%S")
        images.append(image)
    ds = Dataset.from_dict(_coco(images))
    assert {ds.video_names[v]: [im.id for im in frames] for v, frames in ds.videos.items()} == {
        "20200825T141921_DJI_0001.MP4": [0, 1, 2, 3], "20200826T141921_DJI_0001.MP4": [10, 11, 12, 13]}


def test_the_video_telemetry_of_one_of_two_drones_sharing_a_video_name(tmp_path):
    """`--telemetry FLIGHT.json` beside a video: before, both drones' samples were one video's (the second drone's
    dropped as 'repeats of a held sample', or taken for the first's)."""
    from agent.json_video import read_video_json

    images = [_flight_log_image(k, "DJI_0001.MP4", 15 * k, k) for k in range(4)]
    images += [_flight_log_image(10 + k, "DJI_0001.MP4", 15 * k, k, drone="matrice", heading=200.0) for k in range(4)]
    path = tmp_path / "two.json"
    path.write_text(json.dumps(_coco(images)))
    assert {r.heading_deg for r in read_video_json(path, tmp_path / "matrice_DJI_0001.mp4")} >= {200.0}
    assert all(r.heading_deg < 200.0 for r in read_video_json(path, tmp_path / "mavic_DJI_0001.mp4"))
    with pytest.raises(ValueError, match=r"holds 2 videos \(matrice_DJI_0001.MP4, mavic_DJI_0001.MP4\) and none named "
                                         r"like the video DJI_0001.mp4"):
        read_video_json(path, tmp_path / "DJI_0001.mp4")


@pytest.mark.skipif(not (REAL / "instances_dev.json").is_file(), reason="the team's real data is not beside the repo")
def test_the_real_dev_file_keeps_its_video_ids_names_and_output_files(caplog):
    with caplog.at_level(logging.WARNING, logger="agent.dataset"):
        ds = Dataset.load(REAL / "instances_dev.json")
    assert caplog.text == ""  # nothing split
    names = ["DJI_0032.MP4", "DJI_0069.MP4", "NorthSea_Fri_DJI_0110.MP4", "NorthSea_Fri_DJI_0113.MP4",
             "NorthSea_Fri_DJI_0115.MP4", "NorthSea_Sat_DJI_0122.MP4", "NorthSea_Sat_DJI_0129.MP4",
             "NorthSea_Thu_DJI_0108.MP4"]
    assert ds.video_names == dict(enumerate(names, start=1)) and list(ds.videos) == list(range(1, 9))
    assert [p.name for p in mot_output_paths("out/tracks.txt", ds, list(ds.videos)).values()] == [
        f"tracks_{n}.txt" for n in names]


def test_videos_whose_names_make_one_file_name_get_their_ids_appended(tmp_path, caplog):
    """Before: `a b` and `a_b` (and `A` / `a` on a case-insensitive file system) wrote one MOT file, the second
    video's tracks over the first's."""
    images = [_flight_log_image(k, name, 15 * k, k) for name in ("a b", "a_b", "c") for k in range(2)]
    for i, im in enumerate(images):
        im["id"] = i
    ds = Dataset.from_dict(_coco(images))
    ids = {ds.video_names[v]: v for v in ds.videos}
    with caplog.at_level(logging.WARNING, logger="agent.tracking_io"):
        paths = mot_output_paths(f"{tmp_path}/out/", ds, list(ds.videos))
    assert sorted(p.name for p in paths.values()) == sorted(
        [f"a_b_video{ids['a b']}.txt", f"a_b_video{ids['a_b']}.txt", "c.txt"])
    assert "make one file name (a_b)" in caplog.text
    assert len({p.name.casefold() for p in mot_output_paths(tmp_path / "t.txt", ds, list(ds.videos)).values()}) == 3
    # a third video named as a renamed one would be: told apart again
    images += [_flight_log_image(10 + k, f"a_b_video{ids['a b']}", 15 * k, k) for k in range(2)]
    for i, im in enumerate(images):
        im["id"] = i
    ds = Dataset.from_dict(_coco(images))
    names = [p.name.casefold() for p in mot_output_paths(f"{tmp_path}/out/", ds, list(ds.videos)).values()]
    assert len(set(names)) == len(names) == 4

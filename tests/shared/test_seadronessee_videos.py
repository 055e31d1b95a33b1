"""Which video each image of a SeaDronesSee COCO file is of (shared.telemetry.seadronessee_videos): one drone's one
recording per video. Before, images without a video field from two drones were one video (their telemetry
interleaved, the position jumping between the drones every frame), and one video name written by two drones, or by
one drone on two days, was one video on the telemetry path (`--telemetry FLIGHT.json`) and, for two folders or two
days, on the dataset path too (proof scripts in the commit's note)."""

from __future__ import annotations

import datetime as dt
import json
import logging
import random
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry.seadronessee import parse_seadronessee_coco
from shared.telemetry.seadronessee_videos import group_videos

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "seadronessee-v2-dev"
T0 = dt.datetime(2020, 8, 25, 14, 19, 0)


def _image(image_id: int, k: int, *, drone: str | None = "mavic", video: str | None = None, folder: str | None = None,
           lat0: float = 53.90, day: int = 0, frame: int | None = None, seconds: float | None = None) -> dict:
    """A v2 image: local frame clock, flight-log meta (UTC, whole seconds); k-th frame of its flight, 0.5 s apart."""
    when = T0 + dt.timedelta(days=day, seconds=0.5 * k if seconds is None else seconds)
    src = {"frame_no": 15 * k if frame is None else frame}
    src |= {"drone": drone} if drone is not None else {}
    src |= {"video": video} if video is not None else {}
    src |= {"folder_name": folder} if folder is not None else {}
    stamp = (when - dt.timedelta(hours=2)).replace(microsecond=0)
    return {"id": image_id, "file_name": f"{image_id}.jpg", "width": 3840, "height": 2160, "source": src,
            "date_time": when.isoformat(),
            "meta": {"datetime(utc)": stamp.strftime("%Y-%m-%d %H:%M:%S"), "latitude": lat0 + 2e-5 * k,
                     "longitude": 8.1, "height_above_takeoff(meter)": 40.0, "gimbal_heading(degrees)": 0.0,
                     "gimbal_pitch(degrees)": 60.0}}


def _fixed_wing(image_id: int, k: int, *, source: bool = True) -> dict:
    """The other drone of the public files: gps_latitude_ref holding the latitude as a number, no video field."""
    when = T0 + dt.timedelta(seconds=0.5 * k + 0.25)
    image = {"id": image_id, "file_name": f"{image_id}.jpg", "width": 3840, "height": 2160,
             "date_time": when.isoformat(),
             "meta": {"gps_latitude_ref": 54.10 + 2e-5 * k, "gps_longitude_ref": 8.3, "altitude": 80.0,
                      "gimbal_pitch": 60.0, "gimbal_heading": 180.0,
                      "date_time": (when - dt.timedelta(hours=2)).isoformat()}}
    return image | ({"source": {"drone": "fixedwing", "frame_no": 15 * k}} if source else {})


def _partition(images: list[dict]) -> dict:
    return {g.name: sorted(images[i]["id"] for i in g.images) for g in group_videos(images).groups}


def test_two_drones_without_a_video_field_are_two_videos_with_their_own_telemetry(caplog):
    images = [im for k in range(6) for im in (_image(k, k), _fixed_wing(100 + k, k))]  # flying at once, interleaved
    assert _partition(images) == {"fixedwing": list(range(100, 106)), "mavic": list(range(6))}
    coco = {"images": images}
    with pytest.raises(ValueError, match=r"holds 2 videos \('fixedwing', 'mavic'\): pass video_id"):
        parse_seadronessee_coco(coco)
    with caplog.at_level(logging.WARNING, logger="shared.telemetry.seadronessee"):
        mavic = parse_seadronessee_coco(coco, video_id="mavic", source="two.json")
    assert [round(r.lat, 2) for r in mavic] == [53.9] * 6  # before: 12 records, the latitude 53.9, 54.1, 53.9, ...
    assert {round(r.lat, 2) for r in parse_seadronessee_coco(coco, video_id="fixedwing")} == {54.1}
    assert "two.json: 12 images without a video (no source.video, no video_id) are of 2 drones or meta layouts: " \
           "read apart as fixedwing (6 images), mavic (6 images)" in caplog.text


def test_images_without_a_drone_or_a_video_are_told_apart_by_their_meta_layout():
    images = [im for k in range(4) for im in (_image(k, k, drone=None), _fixed_wing(100 + k, k, source=False))]
    for im in images:
        if "source" in im:
            del im["source"]
    images.append({**_image(50, 9, drone=None), "meta": None})  # no meta: it tells nothing
    names = _partition(images)
    assert names == {"meta-flightlog": [0, 1, 2, 3], "meta-gps-signed": [100, 101, 102, 103], "meta-none": [50]}
    one_drone = [im for im in images if im["id"] < 100]  # one layout: a frame without meta joins it, no name, as before
    (group,) = group_videos(one_drone).groups
    assert group.name is None and len(group.images) == 5 and group_videos(one_drone).notices == ()


def test_one_video_name_written_by_two_drones_is_two_videos_on_the_telemetry_path():
    images = [_image(k, k, video="DJI_0001.MP4") for k in range(5)]
    images += [_image(100 + k, k, video="DJI_0001.MP4", drone="matrice", lat0=54.1) for k in range(5)]
    coco = {"images": images}
    with pytest.raises(ValueError, match=r"holds 2 videos \('matrice_DJI_0001.MP4', 'mavic_DJI_0001.MP4'\)"):
        parse_seadronessee_coco(coco)  # before: one video of 10 records, the two drones' samples interleaved
    assert {round(r.lat, 2) for r in parse_seadronessee_coco(coco, video_id="matrice_DJI_0001.MP4")} == {54.1}
    assert len(parse_seadronessee_coco(coco, video_id="mavic_DJI_0001.MP4")) == 5
    with pytest.raises(ValueError, match="no image with meta in video 'DJI_0001.MP4'"):
        parse_seadronessee_coco(coco, video_id="DJI_0001.MP4")  # the ambiguous name selects nothing


def test_one_drones_video_name_on_two_days_is_two_recordings_named_by_their_start():
    """DJI names restart on every card: DJI_0001.MP4 on Tuesday and on Wednesday, frame numbers from 0 on both."""
    images = [_image(k, k, video="DJI_0001.MP4") for k in range(5)]
    images += [_image(100 + k, k, video="DJI_0001.MP4", day=1, lat0=54.1) for k in range(5)]
    random.Random(3).shuffle(images)
    grouping = group_videos(images)
    assert _partition(images) == {"20200825T141900_DJI_0001.MP4": [0, 1, 2, 3, 4],
                                  "20200826T141900_DJI_0001.MP4": [100, 101, 102, 103, 104]}
    assert any("2 recordings of drone mavic (the frame numbers start again after a pause)" in n
               for n in grouping.notices)


def test_a_pause_in_one_recording_whose_frames_go_on_is_no_second_recording():
    """A file keeping parts of a video (frames 0-60, then 9000-9060 five minutes later): one video, its name kept."""
    images = [_image(k, k, video="DJI_0032.MP4") for k in range(5)]
    images += [_image(100 + k, k, video="DJI_0032.MP4", frame=9000 + 15 * k, seconds=300 + 0.5 * k) for k in range(5)]
    grouping = group_videos(images)
    assert [g.name for g in grouping.groups] == ["DJI_0032.MP4"] and grouping.notices == ()


def test_repeated_frame_numbers_without_one_clock_stay_one_video_and_say_so():
    images = [_image(k, k, video="DJI_0001.MP4") for k in range(4)] + [_image(10 + k, k, video="DJI_0001.MP4",
                                                                              day=1) for k in range(4)]
    for im in images[:2]:
        del im["date_time"]  # two clocks (local frames, UTC metas): no recording is told apart by them
    grouping = group_videos(images)
    assert [g.name for g in grouping.groups] == ["DJI_0001.MP4"]
    assert grouping.notices == ("video 'DJI_0001.MP4' of drone mavic: 4 frame number(s) repeat on frames whose clock "
                                "does not tell recordings apart: kept as one video",)


def test_one_drones_video_name_in_two_folders_is_two_videos():
    images = [_image(k, k, video="DJI_0001.MP4", folder="Thu") for k in range(3)]
    images += [_image(10 + k, k, video="DJI_0001.MP4", folder="Fri") for k in range(3)]
    assert _partition(images) == {"Fri_DJI_0001.MP4": [10, 11, 12], "Thu_DJI_0001.MP4": [0, 1, 2]}


def test_a_made_up_name_never_takes_a_name_the_file_uses():
    images = [_image(k, k, video="DJI_0001.MP4") for k in range(3)]
    images += [_image(10 + k, k, video="DJI_0001.MP4", drone="matrice") for k in range(3)]
    images += [_image(20 + k, k, video="mavic_DJI_0001.MP4", drone="matrice") for k in range(3)]
    assert _partition(images) == {"matrice_DJI_0001.MP4": [10, 11, 12], "mavic_DJI_0001.MP4": [20, 21, 22],
                                  "mavic_DJI_0001.MP4_2": [0, 1, 2]}


# A single-drone file: names of up to 4 videos, each a run of frames (start, step) at 0.5 s, in any file order.
_flights = st.lists(st.tuples(st.sampled_from(["DJI_0032.MP4", "DJI_0069.MP4", "NorthSea_Fri_DJI_0110.MP4", "A b.MP4"]),
                              st.integers(0, 9000), st.integers(1, 30), st.integers(1, 8)),
                    min_size=1, max_size=4, unique_by=lambda f: f[0])


@settings(max_examples=60, deadline=None)
@given(flights=_flights, seed=st.integers(0, 2**16), folders=st.booleans())
def test_a_single_drone_file_keeps_its_video_names_and_frames(flights, seed, folders):
    images = []
    for n, (video, start, step, count) in enumerate(flights):
        folder = Path(video).stem if folders else None
        images += [_image(100 * n + k, k, video=video, folder=folder, frame=start + step * k,
                          seconds=3600.0 * n + 0.5 * k) for k in range(count)]
    random.Random(seed).shuffle(images)
    grouping = group_videos(images)
    assert grouping.notices == ()
    assert [g.name for g in grouping.groups] == sorted(video for video, *_ in flights)  # the sorted order, as before
    assert _partition(images) == {video: [100 * n + k for k in range(count)]
                                  for n, (video, _, _, count) in enumerate(flights)}


_images = st.lists(st.tuples(st.sampled_from(["mavic", "matrice", None]), st.sampled_from(["DJI_0001.MP4", None]),
                             st.sampled_from(["Thu", "Fri", None]), st.integers(0, 3), st.integers(0, 40)),
                   min_size=1, max_size=30, unique_by=lambda t: (t[3], t[4]))


@settings(max_examples=80, deadline=None)
@given(specs=_images, seed=st.integers(0, 2**16))
def test_every_image_is_in_one_video_whatever_the_file_order(specs, seed):
    """Any mix of drones, folders, days, with and without a video field: every image in exactly one video, one
    drone's, with a unique name, and the same videos and names whatever the order of the file."""
    images = [_image(n, k, drone=drone, video=video, folder=folder, day=day, frame=k % 7)
              for n, (drone, video, folder, day, k) in enumerate(specs)]
    partition = _partition(images)
    assert sorted(i for ids in partition.values() for i in ids) == list(range(len(images)))
    assert len(partition) == len(group_videos(images).groups)  # names unique
    for ids in partition.values():
        assert len({(images[i]["source"].get("drone"), images[i]["source"].get("video")) for i in ids}) == 1
    shuffled = images[:]
    random.Random(seed).shuffle(shuffled)
    assert _partition(shuffled) == partition


@pytest.mark.skipif(not (REAL / "instances_dev.json").is_file(), reason="the team's real data is not beside the repo")
def test_the_real_dev_file_keeps_its_eight_videos_and_their_names():
    images = json.loads((REAL / "instances_dev.json").read_text())["images"]
    grouping = group_videos(images)
    assert grouping.notices == ()
    assert [g.name for g in grouping.groups] == [
        "DJI_0032.MP4", "DJI_0069.MP4", "NorthSea_Fri_DJI_0110.MP4", "NorthSea_Fri_DJI_0113.MP4",
        "NorthSea_Fri_DJI_0115.MP4", "NorthSea_Sat_DJI_0122.MP4", "NorthSea_Sat_DJI_0129.MP4",
        "NorthSea_Thu_DJI_0108.MP4"]
    assert all(images[i]["source"]["video"] == g.name for g in grouping.groups for i in g.images)

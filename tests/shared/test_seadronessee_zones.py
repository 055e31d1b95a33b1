"""One zone for one video's stamps (`harmonise_zones`): a file whose frames of one video mix ``+02:00`` and naive
``date_time`` (a helper's walk-through on the real dev set: the video was cut in two recordings, 'the frame numbers
start again after a pause', and the re-timing stages saw two clocks)."""

from __future__ import annotations

import datetime as dt
import json
import logging

from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Dataset
from shared.telemetry.dates import parse_datetime
from shared.telemetry.seadronessee import parse_seadronessee_coco
from shared.telemetry.seadronessee_videos import group_videos
from shared.telemetry.seadronessee_zones import harmonise_zones

START = dt.datetime(2020, 8, 25, 12, 19, 22, tzinfo=dt.timezone.utc)


def _zone(minutes: int) -> str:
    return f"{'-' if minutes < 0 else '+'}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"


def _images(n: int, zone_min: int, naive: set[int], *, fps: float = 5.0, frames: bool = True, video="DJI_0032.MP4",
            meta: bool = False) -> list[dict]:
    out = []
    for k in range(n):
        utc = START + dt.timedelta(seconds=k / fps)
        local = (utc + dt.timedelta(minutes=zone_min)).replace(tzinfo=None).isoformat(timespec="microseconds")
        stamp = local if k in naive else local + _zone(zone_min)
        im = {"id": k + 1, "width": 3840, "height": 2160, "file_name": f"{k}.jpg",
              "source": {"drone": "mavic", "folder_name": "DJI_0032", "video": video} | (
                  {"frame_no": 100 + 3 * k} if frames else {})}
        if meta:
            im["meta"] = {"gps_latitude": 47.67, "gps_latitude_ref": "N", "gps_longitude": 9.27,
                          "gps_longitude_ref": "E", "altitude": 40.0, "gimbal_pitch": 45.0, "gimbal_heading": 10.0,
                          "date_time": stamp}
        else:
            im["date_time"] = stamp
        out.append(im)
    return out


def _truth(k: int, fps: float = 5.0) -> float:
    return (START + dt.timedelta(seconds=k / fps)).timestamp()


@settings(max_examples=60, deadline=None)
@given(zone_q=st.integers(-48, 56).filter(lambda q: q != 0), n=st.integers(4, 40), data=st.data(),
       frames=st.booleans())
def test_naive_stamps_take_the_zone_of_the_others(zone_q, n, data, frames):
    naive = set(data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=n - 2, unique=True)))
    zoned = set(range(n)) - naive
    if not frames and len(zoned) < 1:
        return
    images = _images(n, 15 * zone_q, naive, frames=frames)
    out, notices = harmonise_zones(images)
    if frames and len(zoned) < 2:  # one zoned stamp draws no line: left as written, said so
        assert out == images and len(notices) == 1 and "left as written" in notices[0]
        return
    assert [parse_datetime(im["date_time"]) for im in out] == [_truth(k) for k in range(n)]
    assert len(notices) == 1 and f"read at {_zone(15 * zone_q)}" in notices[0]
    assert all(out[k] is images[k] for k in zoned)  # the others untouched
    assert all("+" not in images[k]["date_time"][-6:] and "-" not in images[k]["date_time"][-6:] for k in naive)


def test_naive_stamps_already_utc_beside_z_or_no_mix_are_left_alone():
    images = _images(10, 0, {1, 3, 5})
    assert [im["date_time"][-6:] for im in images[:2]] == ["+00:00", images[1]["date_time"][-6:]]
    out, notices = harmonise_zones(images)
    assert out == images and notices == []
    plain = _images(10, 120, set(range(10)))
    assert harmonise_zones(plain) == (plain, [])
    zoned = _images(10, 120, set())
    assert harmonise_zones(zoned) == (zoned, [])


def test_no_evidence_leaves_the_stamps_as_written_with_a_notice():
    # an offset that is no time zone (7 min): a clock set wrong, not a zone
    images = _images(10, 120, {2, 4, 6})
    for k in (2, 4, 6):
        t = dt.datetime.fromisoformat(images[k]["date_time"]) + dt.timedelta(minutes=7)
        images[k]["date_time"] = t.isoformat(timespec="microseconds")
    out, notices = harmonise_zones(images)
    assert out == images and len(notices) == 1 and "is no time zone" in notices[0]
    # naive stamps that disagree among themselves
    images = _images(10, 120, {2, 4, 6})
    images[4]["date_time"] = "2020-08-25T20:19:22.000000"
    out, notices = harmonise_zones(images)
    assert out == images and "do not agree on one offset" in notices[0]
    # without frame numbers and with too few seconds between the groups to tell them apart (naive read as UTC)
    images = _images(10, 0, {2, 4, 6}, frames=False)
    out, notices = harmonise_zones(images)
    assert out == images and "not told apart" in notices[0]


def test_meta_stamps_and_videos_are_judged_apart():
    a = _images(8, 120, {0, 1, 2}, meta=True)
    b = _images(8, -300, {5}, video="DJI_0033.MP4")
    out, notices = harmonise_zones(a + b)
    assert [parse_datetime(im["meta"]["date_time"]) for im in out[:8]] == [_truth(k) for k in range(8)]
    assert [parse_datetime(im["date_time"]) for im in out[8:]] == [_truth(k) for k in range(8)]
    assert len(notices) == 2 and "meta date_time" in notices[0] and "read at -05:00" in notices[1]
    assert a[0]["meta"]["date_time"][-6:] != "+02:00"  # the caller's dicts are not changed


def test_the_readers_keep_a_mixed_video_as_one(caplog):
    images = _images(40, 120, set(range(0, 40, 2)))
    for k, im in enumerate(images):
        utc = dt.datetime.fromtimestamp(int(_truth(k)), dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        im["meta"] = {"latitude": 47.67, "longitude": 9.27, "height_above_takeoff(meter)": 20.0,
                      "gimbal_pitch(degrees)": -40.0, "gimbal_heading(degrees)": 99.0, "datetime(utc)": utc}
    assert len(group_videos(images).groups) == 2  # as written: the 2 h jump cuts it in two recordings
    coco = {"images": images, "categories": [{"id": 1, "name": "swimmer"}], "annotations": []}
    with caplog.at_level(logging.WARNING):
        ds = Dataset.from_dict(json.loads(json.dumps(coco)), source="mixed.json")
    assert len(ds.videos) == 1 and ds.video_names == {next(iter(ds.videos)): "DJI_0032.MP4"}
    assert "read at +02:00" in caplog.text and "recordings" not in caplog.text
    frames = next(iter(ds.videos.values()))
    assert [parse_datetime(r.date_time) for r in frames] == [_truth(k) for k in range(40)]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        records = parse_seadronessee_coco(coco, source="mixed.json")  # one video: no video_id needed
    assert len(records) == 40 and "read at +02:00" in caplog.text

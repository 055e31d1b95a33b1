"""agent.track_rows: the agent's --tracks-out rows as columns write the GeoJSON `geojson_tracks` writes, byte for byte,
in a fraction of the memory."""

from __future__ import annotations

import json
import math
import tracemalloc

from hypothesis import given, settings
from hypothesis import strategies as st

from agent.track_rows import TrackRowLog
from agent.tracking import TrackOutput
from agent.tracking_io import TrackRow, geojson_tracks

NAMES = {1: "swimmer", 2: "boat"}


def _track(track_id: int, cls: int, lat: float, lon: float, score: float = 0.5, ve: float = 0.1, vn: float = -0.2):
    return TrackOutput(id=track_id, cls=cls, box_xyxy=(0.0, 0.0, 1.0, 1.0), lat=lat, lon=lon, vel_en=(ve, vn),
                       score=score, confirmed=True, matched=True)


coordinate = st.one_of(st.floats(-80, 80, allow_nan=False), st.just(math.nan))
frame_tracks = st.lists(st.tuples(st.integers(1, 2**53 - 1) | st.integers(1, 6), st.sampled_from([1, 2]), coordinate,
                                  st.floats(-179, 179), st.floats(0, 1.5), st.floats(-30, 30), st.floats(-30, 30)),
                        max_size=5)


@given(frames=st.lists(st.tuples(st.floats(1.6e9, 1.8e9), frame_tracks), max_size=12), chunk=st.integers(1, 7))
@settings(max_examples=60, deadline=None)
def test_the_columns_write_what_geojson_tracks_writes(tmp_path_factory, frames, chunk):
    log = TrackRowLog(chunk_rows=chunk)
    rows = []
    for index, (t, items) in enumerate(frames):
        tracks = [_track(*item) for item in items]
        log.extend(index, t, tracks)
        rows += [TrackRow(index, index, t, tr) for tr in tracks]
    assert len(log) == len(rows)
    expected = geojson_tracks({0: rows}, NAMES)
    path = tmp_path_factory.mktemp("rows") / "tracks.geojson"
    assert log.write_geojson(path, NAMES) == len(expected["features"])
    assert path.read_text() == json.dumps(expected)


def test_properties_are_added_and_a_failed_write_keeps_the_old_file(tmp_path):
    log = TrackRowLog()
    log.extend(0, 1.7e9, [_track(5, 1, 47.6, 9.3)])
    path = tmp_path / "tracks.geojson"
    path.write_text("old")
    n = log.write_geojson(path, NAMES, lambda props: props.update(uav="uav1", gid=None))
    doc = json.loads(path.read_text())
    assert n == 1 and doc["features"][0]["properties"]["uav"] == "uav1" and doc["features"][0]["geometry"]["type"] \
        == "Point"

    def boom(props):
        raise RuntimeError("disk full")

    path.write_text("old")
    try:
        log.write_geojson(path, NAMES, boom)
    except RuntimeError:
        pass
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["tracks.geojson"]


def test_an_hour_of_rows_costs_a_seventh_of_the_objects():
    # probe: held as (frame, t, TrackOutput) an agent's rows cost ~540 B each: ten tracks at 30 fps, ~580 MB an hour
    tracks = [_track(i, 1, 47.6 + i * 1e-5, 9.3) for i in range(10)]
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    log = TrackRowLog()
    for index in range(3000):  # 100 s at 30 fps, 30,000 rows
        log.extend(index, 1.7e9 + index / 30, [_track(tr.id, tr.cls, tr.lat, tr.lon + index * 1e-7) for tr in tracks])
    held = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.stop()
    assert len(log) == 30_000
    assert held < 30_000 * 80  # 72 B a row, one chunk of slack

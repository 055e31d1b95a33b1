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


def test_an_hour_of_rows_costs_a_fifth_of_the_objects():
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
    assert held < (30_000 + 8192) * 104  # 104 B a row, one open chunk of slack


def _old_objects(rows: list[TrackRow], names: dict[int, str]) -> dict:
    """`uavmm detect`'s objects.geojson as it was built from TrackRow objects before 30 Nov 2026 (the oracle)."""
    from agent.offline.outputs import _utc

    by_track: dict[int, list[TrackRow]] = {}
    for r in rows:
        if math.isfinite(r.track.lat) and math.isfinite(r.track.lon):
            by_track.setdefault(r.track.id, []).append(r)
    features = []
    for tid, trs in sorted(by_track.items()):
        last = trs[-1]
        scores = [min(max(r.track.score, 0.0), 1.0) for r in trs]
        features.append({
            "type": "Feature", "id": tid,
            "geometry": {"type": "Point", "coordinates": [round(last.track.lon, 8), round(last.track.lat, 8)]},
            "properties": {
                "id": tid, "cls": names.get(last.track.cls, str(last.track.cls)), "cls_id": last.track.cls,
                "score": round(max(scores), 4), "mean_score": round(sum(scores) / len(scores), 4),
                "frames": len(trs), "first_t": round(trs[0].t, 3), "t": round(last.t, 3),
                "first_seen": _utc(trs[0].t), "last_seen": _utc(last.t),
                "vel_en": [round(last.track.vel_en[0], 3), round(last.track.vel_en[1], 3)],
            },
        })
    return {"type": "FeatureCollection", "features": features}


@given(frames=st.lists(st.tuples(st.floats(1.6e9, 1.8e9), frame_tracks), max_size=10), chunk=st.integers(1, 5),
       boxes=st.lists(st.floats(-50, 4000), min_size=4, max_size=4))
@settings(max_examples=40, deadline=None)
def test_detects_files_from_the_columns_are_the_documents_built_from_the_rows(tmp_path_factory, frames, chunk, boxes):
    # uavmm detect held every row as objects to the end (~840 MB an hour of 30 fps video): it now writes its MOT,
    # tracks, objects and KML files from the columns, piece by piece, and they must be the same bytes
    import dataclasses

    from agent.offline.outputs import OUTPUT_FILES, write_outputs
    from agent.tracking_io import mot_lines
    from shared.kml import feature_collections_kml

    log, rows = TrackRowLog(chunk_rows=chunk), []
    for index, (t, items) in enumerate(frames):
        tracks = [dataclasses.replace(_track(*item), box_xyxy=tuple(boxes)) for item in items]
        log.extend(index, t, tracks)
        rows += [TrackRow(index, index, t, tr) for tr in tracks]
    out = tmp_path_factory.mktemp("detect")
    write_outputs(out, detections=None, images=None, rows=log, class_names=NAMES, video_name="v<&>")
    tracks = geojson_tracks({0: rows}, NAMES)
    for feature in tracks["features"]:
        props = feature["properties"]
        props["cls_id"] = props["cls"]
        props["cls"] = props.pop("cls_name")
    objects = _old_objects(rows, NAMES)
    assert (out / OUTPUT_FILES["mot"]).read_text() == "".join(line + "\n" for line in mot_lines(rows))
    assert (out / OUTPUT_FILES["tracks_geojson"]).read_text() == json.dumps(tracks)
    assert (out / OUTPUT_FILES["objects_geojson"]).read_text() == json.dumps(objects)
    assert (out / OUTPUT_FILES["kml"]).read_bytes() == feature_collections_kml("uavmm detect: v<&>", {  # ids: export's
        "objects": {"features": [{**f, "id": f"track-{f['id']}"} for f in objects["features"]]},
        "tracks": {"features": [{**f, "id": f"track-{f['properties']['id']}-path"} for f in tracks["features"]]}})
    assert sorted(p.name for p in out.iterdir()) == sorted(
        OUTPUT_FILES[k] for k in ("mot", "tracks_geojson", "objects_geojson", "kml"))


@given(name=st.text(max_size=12), folders=st.dictionaries(
    st.text(min_size=1, max_size=8), st.lists(st.tuples(st.integers(0, 9), st.text(max_size=6),
                                                        st.floats(-170, 170), st.floats(-80, 80)), max_size=4),
    max_size=3))
@settings(max_examples=60, deadline=None)
def test_the_kml_written_piece_by_piece_is_the_tree_serialised_whole(name, folders):
    import xml.etree.ElementTree as ET

    import shared.kml as kml

    collections = {k: {"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": i, "geometry": {"type": "Point", "coordinates": [lon, lat]},
         "properties": {"id": i, "cls": cls, "times": [1.7e9, 1.7e9 + i]}} for i, cls, lon, lat in items]}
        for k, items in folders.items()}
    root = ET.Element("kml", {"xmlns": kml._NS})  # the builder before 30 Nov 2026, the oracle
    document = ET.SubElement(root, "Document")
    ET.SubElement(document, "name").text = name
    for folder_name, collection in collections.items():
        folder = ET.SubElement(document, "Folder")
        ET.SubElement(folder, "name").text = folder_name
        for feature in collection["features"]:
            kml._placemark(folder, feature)
    whole = b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="utf-8")
    assert b"".join(kml.kml_chunks(name, {k: c["features"] for k, c in collections.items()})) == whole

"""`uavmm detect`'s files written as the frames come (agent.offline.outputs.StreamedImages, the streamed detections):
the same bytes as the documents built whole, and nothing left behind by a run that fails."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.offline.outputs import OUTPUT_FILES, StreamedImages, image_entry, images_json
from agent.offline.run import run_detect
from agent.sources import SourceFrame
from shared.geo import Camera, Pose

CAMERA = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)
POSE = Pose(lat=48.53, lon=9.06, height_m=40.0, pitch_deg=60.0, heading_deg=10.0)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.floats(1.0, 120.0)), max_size=12), st.booleans(),
       st.text(max_size=8), st.dictionaries(st.integers(0, 5), st.text(min_size=1, max_size=6), max_size=3))
def test_streamed_images_are_the_document_built_whole(tmp_path_factory, frames, zoomed, name, classes):
    out = tmp_path_factory.mktemp("images") / "images.json"
    entries = [image_entry(i, 1.7e9 + i, 640, 360, POSE if posed else None, 1.7e9 + i)
               for i, (posed, _) in enumerate(frames)]
    spool = StreamedImages(out)
    for entry in entries:
        spool.add(entry)
    hfovs = [h for _, h in frames]
    spool.close(classes, name, source="src", hfovs=hfovs if zoomed else None)
    if zoomed:
        for entry, hfov in zip(entries, hfovs, strict=True):
            if entry["meta"] is not None:
                entry["meta"]["hfov_deg"] = hfov
    assert out.read_text() == json.dumps(images_json(entries, classes, name, source="src"))
    assert sorted(p.name for p in out.parent.iterdir()) == ["images.json"]


class _Source:
    """Frames with two candidates each; frame `fail_at` raises (a decoder error mid-video)."""

    name = "test"
    class_names = {0: "person"}
    camera = CAMERA

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        self.n, self.fail_at = n, fail_at

    def frames(self):
        for i in range(self.n):
            if i == self.fail_at:
                raise OSError("the video broke off")
            boxes = np.array([[300, 200, 320, 240], [301, 201, 321, 241]], np.float32)
            yield SourceFrame(i, 1.7e9 + 0.1 * i, POSE, 1.7e9 + 0.1 * i, boxes, np.array([0.9, 0.5], np.float32),
                              np.zeros(2, np.int64), CAMERA)

    def close(self) -> None:
        pass


def test_a_run_writes_its_streamed_files_and_one_that_fails_leaves_none(tmp_path):
    summary = run_detect(_Source(6), tmp_path / "ok")
    images = json.loads((tmp_path / "ok" / "images.json").read_text())["images"]
    detections = json.loads((tmp_path / "ok" / "detections.json").read_text())
    assert [im["id"] for im in images] == list(range(6))
    assert {d["image_id"] for d in detections} == set(range(6)) and len(detections) == summary["detections"]
    assert not [p.name for p in (tmp_path / "ok").iterdir() if "tmp" in p.name]
    with pytest.raises(OSError, match="broke off"):
        run_detect(_Source(6, fail_at=4), tmp_path / "failed")
    assert list((tmp_path / "failed").iterdir()) == []


def test_no_output_is_written_through_a_link_planted_at_its_old_temporary_name(tmp_path):
    """Every file of `uavmm detect` went through a fixed ``.NAME.tmp`` (``.images.json.lines.tmp`` for the frames,
    ``detections.json.tmp`` for the results) opened with a plain open(): a link left there took the file's content
    and the rename made the output that link. Each now gets a new temporary of its own."""
    import os

    out = tmp_path / "out"
    out.mkdir()
    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    planted = []
    for name in OUTPUT_FILES.values():
        planted += [f".{name}.tmp", f"{name}.tmp", f".{name}.{os.getpid()}.tmp"]
    planted.append(".images.json.lines.tmp")
    for name in planted:
        (out / name).symlink_to(outside)
    summary = run_detect(_Source(4), out)
    assert outside.read_text() == "precious\n"
    for path in summary["files"].values():
        assert not Path(path).is_symlink() and Path(path).stat().st_size > 0
    assert sorted(p.name for p in out.iterdir() if not p.is_symlink()) == sorted(
        Path(p).name for p in summary["files"].values())


def test_detect_kml_ids_are_unique_xml_ids_named_as_the_export_names_them(tmp_path):
    """tracks.kml's objects had the bare track number as Placemark@id (an XML ID cannot start with a digit) and its
    tracks no id: now ``track-ID`` (where the track was last seen) and ``track-ID-path`` (its track), the ids
    `uavmm export` gives a global track's position and line."""
    import re
    import xml.etree.ElementTree as ET

    from agent.offline.outputs import OUTPUT_FILES, write_outputs
    from agent.track_rows import TrackRowLog
    from agent.tracking import TrackOutput

    log = TrackRowLog()
    for frame in range(3):  # track 7 seen in every frame, 12 in the first only (a Point in the tracks folder)
        log.extend(frame, 1.7e9 + frame, [
            TrackOutput(id=tid, cls=0, box_xyxy=(0.0, 0.0, 1.0, 1.0), lat=48.53 + 1e-5 * frame, lon=9.06 + 1e-4 * tid,
                        vel_en=(0.1, 0.0), score=0.8, confirmed=True, matched=True)
            for tid in ((7, 12) if frame == 0 else (7,))])
    write_outputs(tmp_path, detections=[], images=[], rows=log, class_names={0: "person"}, video_name="v")
    ns = "{http://www.opengis.net/kml/2.2}"
    root = ET.parse(tmp_path / OUTPUT_FILES["kml"]).getroot()
    ids = {folder.findtext(f"{ns}name"): [mark.get("id") for mark in folder.iter(f"{ns}Placemark")]
           for folder in root.iter(f"{ns}Folder")}
    assert ids == {"objects": ["track-7", "track-12"], "tracks": ["track-7-path", "track-12-path"]}
    every = ids["objects"] + ids["tracks"]
    ncname = re.compile(r"[A-Za-z_][\w.\-]*\Z")  # xsd:ID, what KML's Placemark@id is
    assert len(set(every)) == len(every) and all(ncname.match(i) for i in every)
    names = [mark.findtext(f"{ns}name") for mark in root.iter(f"{ns}Placemark")]
    assert names == ["7", "12", "7", "12"]  # the number stays the name, and `id` in ExtendedData
    objects = json.loads((tmp_path / OUTPUT_FILES["objects_geojson"]).read_text())["features"]
    assert [f["id"] for f in objects] == [7, 12]  # the GeoJSON keeps the number as the feature id, as REST does


def test_the_write_check_of_the_out_folder_never_writes_through_a_planted_link(tmp_path):
    from agent.offline.run import prepare_out_dir

    precious = tmp_path / "precious.txt"
    precious.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / ".uavmm-write-test").symlink_to(precious)
    assert prepare_out_dir(out) == out
    assert precious.read_text() == "precious"
    assert [p.name for p in out.iterdir()] == [".uavmm-write-test"]

"""The files `uavmm detect` writes: COCO detections with the frames they refer to, MOTChallenge tracks, GeoJSON
tracks and objects, and KML of both (docs/detect.md lists them).

Pure builders (frames, tracks -> dicts/text) plus one writer that stores every file atomically, so a failed or
interrupted run never leaves a truncated file.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from agent.track_rows import TrackRowLog, collection_chunks, write_chunks_atomic
from shared.files import PendingFile
from shared.geo import Pose
from shared.kml import kml_chunks
from shared.telemetry import Telemetry, to_seadronessee_meta
from shared.telemetry.dates import format_datetime

__all__ = [
    "OPTIONAL_OUTPUTS",
    "OUTPUT_FILES",
    "StreamedImages",
    "image_entry",
    "images_json",
    "objects_geojson",
    "write_text_atomic",
]

#: Output file names inside the --out directory (the annotated video is ``annotated.mp4``).
OUTPUT_FILES = {
    "detections": "detections.json",
    "images": "images.json",
    "mot": "tracks.txt",
    "tracks_geojson": "tracks.geojson",
    "objects_geojson": "objects.geojson",
    "kml": "tracks.kml",
    "video": "annotated.mp4",
    "summary": "summary.json",
    # with DetectOptions.dataset_files (`uavmm detect --dataset-files`): with images.json, a dataset directory
    "candidates": "pre_nms.json",
    "camera": "camera.json",
}
#: The files written only when asked for: kind -> the `uavmm detect` flag that asks.
OPTIONAL_OUTPUTS = {"video": "--render-video", "candidates": "--dataset-files", "camera": "--dataset-files"}


def write_text_atomic(path: Path, text: str | bytes) -> None:
    """Write a file through a new hidden temporary beside it, on disk before the rename (no partial files;
    `shared.files.write_chunks_atomic`)."""
    write_chunks_atomic(path, [text])


def _date_time(t: float) -> str | None:
    try:
        return format_datetime(t)
    except ValueError:
        return None


def _utc(t: float) -> str | None:
    """ISO 8601 with the zone said ("Z"): a map or a browser reads a time without one as its own local time."""
    text = _date_time(t)
    return None if text is None else text + "Z"


def image_entry(index: int, t: float, width: int, height: int, pose: Pose | None, pose_t: float | None, *,
                video_id: int = 0) -> dict[str, Any]:
    """One frame as an IMAGES.json image (DESIGN.md 6): id = frame index, SeaDronesSee ``meta`` from its pose.

    ``file_name`` is empty (no image files are written; ``frame_index`` says which frame of the video it is);
    ``meta`` is None for a frame without pose. The meta's ``date_time`` is the telemetry's time, the image's
    ``date_time`` the frame's. A zoom lens's field of view is added to the meta by the caller (`agent.offline.run`).
    """
    meta = None
    if pose is not None:
        tel = Telemetry(t=pose_t if pose_t is not None else t, lat=pose.lat, lon=pose.lon, height_m=pose.height_m,
                        pitch_deg=pose.pitch_deg, heading_deg=pose.heading_deg, roll_deg=pose.roll_deg)
        meta = to_seadronessee_meta(tel)
    return {"id": index, "file_name": "", "width": width, "height": height, "video_id": video_id,
            "frame_index": index, "date_time": _date_time(t), "meta": meta}


def images_json(images: Sequence[dict[str, Any]], class_names: Mapping[int, str], video_name: str, *,
                video_id: int = 0, source: str = "") -> dict[str, Any]:
    """The COCO document the detections refer to: images, categories, one video; no annotations.

    Add ground truth ``annotations`` to it to score the detections (pycocotools) as `uavmm eval` does.
    """
    return {
        "info": {"description": f"frames of {video_name} processed by uavmm detect", "source": source},
        "images": list(images),
        "annotations": [],
        "categories": [{"id": int(cid), "name": name} for cid, name in sorted(class_names.items())],
        "videos": [{"id": video_id, "name": video_name}],
    }


class StreamedImages:
    """The frames' `images_json` document written as the frames come: each entry goes to a hidden lines file beside
    `path` at once (an hour's entries held in memory were ~2 KB a frame), and `close` writes the document through a
    new hidden temporary and renames it (`shared.files.PendingFile`): the same bytes as
    ``json.dumps(images_json(...))``. Both hidden files get new names of their own (never a file or link already
    there, never another run's). `abort` removes what was written (a failed run leaves no file)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        fd, lines = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".lines.tmp", dir=self.path.parent)
        self._lines = Path(lines)
        self._file: Any = os.fdopen(fd, "w", encoding="utf-8")
        self.count = 0

    def add(self, entry: dict[str, Any]) -> None:
        self._file.write(json.dumps(entry) + "\n")
        self.count += 1

    def abort(self) -> None:
        """Drop what was written (idempotent)."""
        if not self._file.closed:
            self._file.close()
        self._lines.unlink(missing_ok=True)

    def close(self, class_names: Mapping[int, str], video_name: str, *, source: str = "",
              hfovs: Sequence[float] | None = None) -> None:
        """Write the document; `hfovs` (one per frame, a zoom lens's) go into the meta of every frame that has one."""
        self._file.close()
        head = images_json([], class_names, video_name, source=source)
        text = json.dumps(head)
        before, after = text.split('"images": []', 1)  # the images' place in the document, keys in images_json's order
        try:
            out = PendingFile(self.path)
            try:
                with self._lines.open(encoding="utf-8") as lines:
                    out.write(before + '"images": [')
                    for i, line in enumerate(lines):
                        if hfovs is not None:
                            entry = json.loads(line)
                            if entry["meta"] is not None:
                                entry["meta"]["hfov_deg"] = hfovs[i]
                            line = json.dumps(entry)
                        out.write((", " if i else "") + line.rstrip("\n"))
                    out.write("]" + after)
                out.commit()
            finally:
                out.discard()
        finally:
            self._lines.unlink(missing_ok=True)


def objects_geojson(rows: TrackRowLog, class_names: Mapping[int, str]) -> dict[str, Any]:
    """One Point per track: where it was last seen, with when, how often and how confidently.

    Properties: ``id, cls`` (class name), ``cls_id, score`` (highest boosted confidence, clipped to 1),
    ``mean_score, frames`` (frames reported), ``first_t, t`` (first and last seen, UNIX s or the telemetry's
    clock), ``first_seen, last_seen`` (ISO 8601 UTC, ending in "Z"), ``vel_en`` (m/s at the last sighting).
    """
    features = []
    for trs in rows.by_track():
        last = trs[-1]
        tid, cls, first_t, t = int(last["id"]), int(last["cls"]), float(trs["t"][0]), float(last["t"])
        scores = [min(max(score, 0.0), 1.0) for score in trs["score"].tolist()]
        features.append({
            "type": "Feature", "id": tid,
            "geometry": {"type": "Point", "coordinates": [round(float(last["lon"]), 8), round(float(last["lat"]), 8)]},
            "properties": {
                "id": tid, "cls": class_names.get(cls, str(cls)), "cls_id": cls,
                "score": round(max(scores), 4), "mean_score": round(sum(scores) / len(scores), 4),
                "frames": len(trs), "first_t": round(first_t, 3), "t": round(t, 3),
                "first_seen": _utc(first_t), "last_seen": _utc(t),
                "vel_en": [round(float(last["ve"]), 3), round(float(last["vn"]), 3)],
            },
        })
    return {"type": "FeatureCollection", "features": features}


def _track_features(rows: TrackRowLog, names: Mapping[int, str]) -> Iterator[dict[str, Any]]:
    """The tracks' GeoJSON features (`agent.tracking_io.geojson_tracks`) with the class name as `cls` (REST and KML
    convention) and the id as `cls_id`, one at a time."""
    def rename(props: dict[str, Any]) -> None:
        props["cls_id"] = props["cls"]
        props["cls"] = props.pop("cls_name")

    return iter(rows.features(dict(names), rename))


def _kml_ids(features: Iterable[dict[str, Any]], suffix: str) -> Iterator[dict[str, Any]]:
    """The features with the ids `uavmm export` gives a global track's position and line: ``track-ID`` (the object,
    where the track was last seen) and ``track-ID-path`` (its track), ID the track id. KML's Placemark@id is an XML
    ID, which cannot start with a digit (the ids were the bare numbers), and unique in the document (the tracks had
    none)."""
    for feature in features:
        yield {**feature, "id": f"track-{feature['properties']['id']}{suffix}"}


def write_outputs(out_dir: Path, *, detections: list[dict[str, Any]] | None, images: list[dict[str, Any]] | None,
                  rows: TrackRowLog, class_names: Mapping[int, str], video_name: str,
                  source: str = "") -> dict[str, str]:
    """Write the COCO, MOT, GeoJSON and KML files into out_dir; returns {kind: path}. `detections` / `images` None:
    that file was streamed (`agent.boost.StreamedResults`, `StreamedImages`) and is only named. The track files are
    written from the rows' columns piece by piece (a long video's tracks are never one document in memory)."""
    names = dict(class_names)
    paths: dict[str, str] = {}
    files: dict[str, str] = {}
    if detections is not None:
        files["detections"] = json.dumps(detections)
    else:
        paths["detections"] = str(out_dir / OUTPUT_FILES["detections"])
    if images is not None:
        files["images"] = json.dumps(images_json(images, names, video_name, source=source))
    else:
        paths["images"] = str(out_dir / OUTPUT_FILES["images"])
    write_chunks_atomic(out_dir / OUTPUT_FILES["mot"], (line + "\n" for line in rows.mot_lines()))
    write_chunks_atomic(out_dir / OUTPUT_FILES["tracks_geojson"], collection_chunks(_track_features(rows, names)))
    objects = objects_geojson(rows, names)
    write_text_atomic(out_dir / OUTPUT_FILES["objects_geojson"], json.dumps(objects))
    for kind in ("mot", "tracks_geojson", "objects_geojson"):
        paths[kind] = str(out_dir / OUTPUT_FILES[kind])
    for kind, text in files.items():
        path = out_dir / OUTPUT_FILES[kind]
        write_text_atomic(path, text)
        paths[kind] = str(path)
    write_chunks_atomic(out_dir / OUTPUT_FILES["kml"], kml_chunks(f"uavmm detect: {video_name}", {
        "objects": _kml_ids(objects["features"], ""), "tracks": _kml_ids(_track_features(rows, names), "-path")}))
    paths["kml"] = str(out_dir / OUTPUT_FILES["kml"])
    return paths

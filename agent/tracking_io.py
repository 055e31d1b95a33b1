"""Run the detection pipeline and the GPS tracker over a dataset; write MOTChallenge and GeoJSON tracks.

The file-facing edge of `agent.tracking` (which takes arrays only), used by `uavmm track` and the
tracking evaluation.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.dataset import (
    Candidates,
    Dataset,
    Frame,
    PoseProblem,
    VideoTelemetry,
    count_reasons,
    read_image,
    read_json,
)
from agent.file_frames import prepared_frames, telemetry_reports
from agent.frame_result import FrameResult
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig, refuse_huge_int
from agent.pixel_tracker import ImageOnlyTracks
from agent.size_filter import SizeFilter
from agent.stage_report import StageSummary
from agent.tracking import ClassMotion, GpsTracker, TrackerConfig, TrackOutput
from agent.tracking.appearance import with_image_descriptors
from shared.files import write_chunks_atomic
from shared.geo import Camera

log = logging.getLogger(__name__)


def tracker_config_from_dict(d: Any, base: TrackerConfig | None = None) -> TrackerConfig:
    """A TrackerConfig from a JSON mapping of its fields (metres, seconds, degrees).

    ``class_motion`` is a mapping {class name: {accel_sigma_mps2, max_speed_mps, reid_spread_mps,
    persistence_s}} merged over the base's; ``default_motion`` such a mapping. Unknown keys raise
    ValueError listing the valid ones; bad values the config's own ValueError.
    """
    base = base or TrackerConfig()
    if not isinstance(d, dict):
        raise ValueError(f"tracker config must be a JSON object, got {type(d).__name__}")
    names = {f.name for f in dataclasses.fields(TrackerConfig)}
    motion_fields = {f.name for f in dataclasses.fields(ClassMotion)}

    def motion(value: Any, what: str, start: ClassMotion) -> ClassMotion:
        if not isinstance(value, dict):
            raise ValueError(f"{what} must be an object of {', '.join(sorted(motion_fields))}")
        unknown = set(value) - motion_fields
        if unknown:
            raise ValueError(f"unknown {what} setting(s) {sorted(unknown)}; valid: {', '.join(sorted(motion_fields))}")
        for k, v in value.items():
            refuse_huge_int(f"{what}.{k}", v)
        return dataclasses.replace(start, **value)

    kw: dict[str, Any] = {}
    for key, value in d.items():
        if key not in names:
            raise ValueError(f"unknown tracker setting {key!r}; valid: {', '.join(sorted(names))}")
        refuse_huge_int(key, value)
        if key == "class_motion":
            if not isinstance(value, dict):
                raise ValueError("tracker setting 'class_motion' must be an object {class name: {...}}")
            merged = dict(base.class_motion)
            for cls_name, m in value.items():
                merged[cls_name] = motion(m, f"class_motion[{cls_name!r}]", merged.get(cls_name, base.default_motion))
            kw[key] = tuple(merged.items())
        elif key == "default_motion":
            kw[key] = motion(value, "default_motion", base.default_motion)
        else:
            kw[key] = value
    return dataclasses.replace(base, **kw)


def load_tracker_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> TrackerConfig:
    """Tracker settings file (JSON) then command-line overrides (None values ignored)."""
    cfg = TrackerConfig()
    if path is not None:
        data = read_json(path, "tracker config")
        try:
            cfg = tracker_config_from_dict(data, cfg)
        except ValueError as exc:
            raise ValueError(f"tracker config {path}: {exc}") from None
        except TypeError as exc:  # a value of another JSON type ([1] for a number) in the settings' own checks
            raise ValueError(f"tracker config {path}: a setting of the wrong type ({exc})") from None
    if overrides:
        cfg = tracker_config_from_dict({k: v for k, v in overrides.items() if v is not None}, cfg)
    return cfg


@dataclass(frozen=True, slots=True)
class TrackRow:
    """One reported track in one frame: `frame_index` (0-based), image id, time (s) and the track."""

    frame_index: int
    image_id: int
    t: float
    track: TrackOutput


def _image_only_rows(image_only: ImageOnlyTracks, video: object, frames: int) -> list[TrackRow]:
    """A video none of whose frames had a pose: its tracks in the image alone (`agent.pixel_tracker`), said in a
    warning; the GPS tracker starts no track without a ground point, and the MOT file was empty, silently."""
    if image_only.unavailable is not None:
        log.warning("video %s: none of its %d frames has a pose: no track (the image-only fallback needs norfair: "
                    "%s)", video, frames, image_only.unavailable)
        return []
    log.warning("video %s: none of its %d frames has a pose (see the reasons below): tracked in the image alone "
                "(norfair, as the evaluation's pixel baseline), without ground positions or re-identification",
                video, frames)
    return [TrackRow(*row) for row in image_only.rows]


def frame_time_s(frame: Frame) -> float:
    """The frame's own clock, seconds (`iter_video_frames` puts the image's date_time in `frame.t`)."""
    return frame.t


def memory_evidence(pipeline: DetectionPipeline) -> Callable[[int, np.ndarray, np.ndarray], np.ndarray]:
    """An evidence function for `GpsTracker` reading the pipeline's memory map at lat/lon points."""

    def evidence_at(class_id: int, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        gx, gy = pipeline.grid.latlon_to_cell(lat, lon)
        return pipeline.memory.values_at(pipeline.class_names[class_id], gx, gy)

    return evidence_at


def track_video(dataset: Dataset, candidates: Candidates, camera: Camera, video_id: int,
                pipeline_config: PipelineConfig, tracker_config: TrackerConfig | None = None,
                size_filter: SizeFilter | None = None, *,
                on_frame: Callable[[Frame, FrameResult, list[TrackOutput]], None] | None = None,
                stats: dict[str, Any] | None = None, image_dir: str | Path | None = None,
                clock_offsets: list[tuple] | None = None,
                registrations: list[tuple] | None = None) -> list[TrackRow]:
    """Run pipeline and tracker over one video.

    Parameters
    ----------
    dataset, candidates, camera
        The loaded IMAGES.json, PRE_NMS.json and CAMERA.json.
    video_id : int
        A key of `dataset.videos`; ValueError listing the known ones otherwise.
    pipeline_config : PipelineConfig
        `use_memory=False` gives our tracker on single-frame detections.
    tracker_config : TrackerConfig, optional
    size_filter : SizeFilter, optional
    on_frame : callable, optional
        Called per frame with (frame, pipeline result, all active tracks).
    stats : dict, optional
        Counters added in place: frames, frames_without_pose, detections, pipeline_s, tracker_s,
        reidentified, images_read, images_missing, appearance_s.
    image_dir : path, optional
        Where the images' ``file_name`` are relative to. When given and a frame's image file exists, the
        kept boxes get `hsv_histogram_descriptors` (`with_image_descriptors`; descriptors from the
        candidates file win). Missing or unreadable images are skipped (counted, logged once), never an
        error.
    clock_offsets : list, optional
        With `pipeline_config.estimate_clock_offset`, one row per frame is appended: CLOCK_OFFSET_COLUMNS
        (the video/telemetry clock offset applied, agent.clock_offset; frames without pose: NaN).
    registrations : list, optional
        One row per frame is appended: REGISTRATION_COLUMNS (the tracker's pose correction from its image
        registration, `GpsTracker.last_correction`; registered True where this frame was registered, carried
        True where the pending part of an earlier correction was applied instead (TrackerConfig.carry_correction),
        zeros where neither).

    Returns
    -------
    list of TrackRow
        The reported tracks (`GpsTracker.report`: confirmed, matched, good quality) of every frame,
        in frame order.
    """
    if video_id not in dataset.videos:
        raise ValueError(f"unknown video_id {video_id}; known: {sorted(dataset.videos)}")
    pipe = DetectionPipeline(camera, dataset.categories, pipeline_config, size_filter=size_filter)
    tracker = GpsTracker(tracker_config, dataset.categories, evidence_at=memory_evidence(pipe))
    rows: list[TrackRow] = []
    counts = {"frames": 0, "frames_without_pose": 0, "detections": 0, "pipeline_s": 0.0, "tracker_s": 0.0,
              "images_read": 0, "images_missing": 0, "appearance_s": 0.0, "confident_posed": 0,
              "confident_without_ground_point": 0}
    t_prev = -math.inf
    problems: list[PoseProblem] = []
    telemetry = VideoTelemetry()
    image_only: ImageOnlyTracks | None = ImageOnlyTracks()  # while no frame has had a pose
    for frame, offset in prepared_frames(dataset, camera, video_id, candidates, pipeline_config, pipe,
                                         problems=problems, report=telemetry):
        if clock_offsets is not None and pipeline_config.estimate_clock_offset:
            clock_offsets.append((frame.image.id, frame.image.video_id, frame.image.frame_index,
                                  round(offset.offset_s, 4) if offset is not None else math.nan,
                                  bool(offset is not None and offset.measured)))
        if pipe.camera != frame.camera:
            pipe.camera = frame.camera
        boxes, scores, cids = candidates.get(frame.image.id)
        t0 = time.perf_counter()
        result = pipe.process(boxes, scores, cids, frame.pose, frame.t, candidates.get_embeddings(frame.image.id))
        counts["pipeline_s"] += time.perf_counter() - t0
        if image_dir is not None:
            image = read_image(image_dir, frame.image)
            if image is None:
                if not counts["images_missing"]:
                    log.info("video %d: no image file %s under %s: no image descriptors for such frames",
                             video_id, frame.image.file_name or "(no file_name)", image_dir)
                counts["images_missing"] += 1
            else:
                ta = time.perf_counter()
                result = with_image_descriptors(result, image)
                counts["appearance_s"] += time.perf_counter() - ta
                counts["images_read"] += 1
        t1 = time.perf_counter()
        t = max(frame_time_s(frame), t_prev)
        t_prev = t
        tracks = tracker.update(result, frame.pose, t, frame.camera, pose_t=frame.pose_t,
                                pose_retimed=frame.pose_retimed,
                                terrain=pipe.terrain_for(frame.pose))
        counts["tracker_s"] += time.perf_counter() - t1
        if registrations is not None:
            c = tracker.last_correction
            carried = tracker.last_correction_carried
            registrations.append((frame.image.id, frame.image.video_id, frame.image.frame_index,
                                  *(round(v, 4) for v in (c or (0.0, 0.0, 0.0, 0.0))), c is not None and not carried,
                                  carried))
        counts["frames"] += 1
        counts["frames_without_pose"] += frame.pose is None
        counts["detections"] += len(result)
        if frame.pose is not None:  # a track starts only at a ground point: count the confident boxes without one
            confident = result.raw_scores >= tracker.config.birth_score
            assert tracker.last_grounded is not None  # set by every frame with a pose
            counts["confident_posed"] += int(confident.sum())
            counts["confident_without_ground_point"] += int((confident & ~tracker.last_grounded).sum())
        rows.extend(TrackRow(frame.image.frame_index, frame.image.id, t, tr) for tr in tracker.report(tracks))
        if frame.pose is not None:
            image_only = None
        elif image_only is not None:
            image_only.add(frame.image.frame_index, frame.image.id, t, result)
        if on_frame is not None:
            on_frame(frame, result, tracks)
    if image_only is not None and counts["frames"] and not rows:
        rows = _image_only_rows(image_only, dataset.video_names.get(video_id, video_id), int(counts["frames"]))
        counts["videos_tracked_in_image"] = int(bool(rows))
    far, posed = counts["confident_without_ground_point"], counts["confident_posed"]
    if posed and far * 2 >= posed:
        log.warning("video %s: %d of %d confident detections in frames with a pose have no ground point (at or "
                    "above the horizon, over a DEM beyond the pipeline's range, or beyond far_reach_sigma_m's reach "
                    "with far_loose_gate 0): they follow tracks but start none%s",
                    dataset.video_names.get(video_id, video_id), far, posed,
                    "" if rows else ", and the video has no track")
    if stats is not None:
        for k, v in counts.items():
            stats[k] = stats.get(k, 0) + v
        stats["reidentified"] = stats.get("reidentified", 0) + tracker.n_reidentified
        stats.setdefault("problems", []).extend(problems)
        stages = stats.setdefault("stage_summary", StageSummary())
        for report in [*telemetry_reports(telemetry, pipeline_config.clock_offset_settings()), *pipe.stage_reports(),
                       *tracker.stage_reports()]:
            stages.add(report)
    return rows


# ---------------------------------------------------------------------------------------------
# Output files
# ---------------------------------------------------------------------------------------------

def video_name(dataset: Dataset, video_id: int) -> str:
    """A file-name-safe name of a video: its name (the COCO `videos` list, SeaDronesSee's ``source.video``),
    else ``video<id>``."""
    name = dataset.video_names.get(video_id)
    if isinstance(name, str) and name:
        safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
        if safe:
            return safe
    return f"video{video_id}"


def output_names(dataset: Dataset, video_ids: list[int]) -> dict[int, str]:
    """`video_name` of each video, told apart where two would give one file name (``a b`` and ``a_b``; ``A`` and ``a``
    too, which a case-insensitive file system takes for one): those get ``_video<id>`` appended, and a warning names
    them."""
    names = {v: video_name(dataset, v) for v in video_ids}
    while True:  # again after appending: a third video may be named like a renamed one (`a_b_video0`)
        seen: dict[str, list[int]] = {}
        for v, name in names.items():
            seen.setdefault(name.casefold(), []).append(v)
        clashes = [ids for ids in seen.values() if len(ids) > 1]
        if not clashes:
            return names
        for same in clashes:
            log.warning("videos %s have names that make one file name (%s): each gets _video<id> appended",
                        ", ".join(str(v) for v in same), names[same[0]])
            for v in same:
                names[v] = f"{names[v]}_video{v}"


def mot_output_paths(out: str | Path, dataset: Dataset, video_ids: list[int]) -> dict[int, Path]:
    """Where each video's MOT file goes (see docs/tracking.md).

    - `out` an existing directory, or written with a trailing slash: ``out/<video name>.txt`` per
      video (the MOTChallenge / TrackEval layout);
    - else `out` is a file: with one video, that file; with several, one file per video beside it,
      ``<stem>_<video name><suffix>``.

    Two videos whose names make one file name get ``_video<id>`` appended (`output_names`).
    """
    text = str(out)
    path = Path(out)
    names = output_names(dataset, video_ids)
    if path.is_dir() or text.endswith(("/", os.sep)):
        return {v: path / f"{names[v]}.txt" for v in video_ids}
    if len(video_ids) == 1:
        return {video_ids[0]: path}
    suffix = path.suffix or ".txt"
    return {v: path.with_name(f"{path.stem}_{names[v]}{suffix}") for v in video_ids}


def check_writable(path: str | Path, *, create_dir: bool = False) -> None:
    """Fail early (OSError naming the path) if a file cannot be written at `path`."""
    path = Path(path)
    parent = path.parent
    if create_dir:
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"cannot create output directory {parent}: {exc.strerror or exc}") from None
    if path.is_dir():
        raise IsADirectoryError(f"output {path} is a directory, expected a file")
    if not parent.is_dir():
        raise FileNotFoundError(f"output directory {parent} does not exist (for {path})")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".uavmm-write-test-", dir=parent)
    except OSError as exc:
        raise OSError(f"cannot write {path}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(tmp)


def _write_atomic(path: Path, text: str) -> None:
    write_chunks_atomic(path, [text])  # a new temporary beside it (never one there or a link), on disk, renamed


def mot_lines(rows: list[TrackRow]) -> list[str]:
    """MOTChallenge rows ``frame,id,x,y,w,h,score,-1,-1,-1`` (frame = frame_index + 1), sorted."""
    lines = []
    for r in sorted(rows, key=lambda r: (r.frame_index, r.track.id)):
        x1, y1, x2, y2 = r.track.box_xyxy
        lines.append(f"{r.frame_index + 1},{r.track.id},{x1:.2f},{y1:.2f},{x2 - x1:.2f},{y2 - y1:.2f},"
                     f"{r.track.score:.5f},-1,-1,-1")
    return lines


def write_mot(rows: list[TrackRow], path: str | Path) -> int:
    """Write one video's rows as a MOTChallenge text file (atomically); returns the row count."""
    lines = mot_lines(rows)
    _write_atomic(Path(path), "".join(line + "\n" for line in lines))
    return len(lines)


def read_mot(path: str | Path) -> np.ndarray:
    """Read a MOTChallenge file into an (N, 10) float64 array (frame, id, x, y, w, h, score, ...)."""
    path = Path(path)
    text = path.read_text()
    if not text.strip():
        return np.zeros((0, 10))
    try:
        arr = np.loadtxt(path, delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path} is not a MOTChallenge file: {exc}") from None
    if arr.shape[1] < 6:
        raise ValueError(f"{path}: expected at least 6 comma-separated columns, got {arr.shape[1]}")
    return arr


def geojson_tracks(rows_by_video: dict[int, list[TrackRow]], class_names: dict[int, str]) -> dict[str, Any]:
    """Tracks as a GeoJSON FeatureCollection: one feature per (video, track).

    Geometry: a LineString of [lon, lat] (filtered positions at the frames the track was reported),
    or a Point when it was reported once. Properties: ``id, video_id, cls, cls_name, frames``
    (0-based frame indices), ``times`` (UNIX s), ``scores`` and ``vel_en`` (m/s, per position).
    """
    features = []
    for video_id, rows in rows_by_video.items():
        by_track: dict[int, list[TrackRow]] = {}
        for r in rows:
            if math.isfinite(r.track.lat) and math.isfinite(r.track.lon):
                by_track.setdefault(r.track.id, []).append(r)
        for tid, trs in sorted(by_track.items()):
            coords = [[round(r.track.lon, 8), round(r.track.lat, 8)] for r in trs]
            geometry = ({"type": "Point", "coordinates": coords[0]} if len(coords) == 1
                        else {"type": "LineString", "coordinates": coords})
            cls = trs[0].track.cls
            features.append({
                "type": "Feature", "geometry": geometry,
                "properties": {
                    "id": tid, "video_id": video_id, "cls": cls, "cls_name": class_names.get(cls, str(cls)),
                    "frames": [r.frame_index for r in trs], "times": [round(r.t, 3) for r in trs],
                    "scores": [round(r.track.score, 4) for r in trs],
                    "vel_en": [[round(r.track.vel_en[0], 3), round(r.track.vel_en[1], 3)] for r in trs],
                },
            })
    return {"type": "FeatureCollection", "features": features}


def write_geojson(rows_by_video: dict[int, list[TrackRow]], class_names: dict[int, str], path: str | Path) -> int:
    """Write `geojson_tracks` to path (atomically); returns the number of features."""
    collection = geojson_tracks(rows_by_video, class_names)
    _write_atomic(Path(path), json.dumps(collection))
    return len(collection["features"])


#: Columns of `uavmm track --clock-offsets-out`: the video/telemetry clock offset applied to each frame.
CLOCK_OFFSET_COLUMNS = ("image_id", "video_id", "frame_index", "offset_s", "measured")
#: Columns of `uavmm track --registrations-out`: the pose correction the tracker's image registration
#: applied to each frame's ground points (metres east/north, degrees heading/pitch).
REGISTRATION_COLUMNS = ("image_id", "video_id", "frame_index", "east_m", "north_m", "heading_deg", "pitch_deg",
                        "registered", "carried")


def track_dataset(images_path: str | Path, candidates_path: str | Path, camera_path: str | Path, out: str | Path,
                  pipeline_config: PipelineConfig, tracker_config: TrackerConfig | None = None,
                  size_filter: SizeFilter | None = None, *, video_id: int | str | None = None,
                  geojson_path: str | Path | None = None, image_dir: str | Path | None = None,
                  use_images: bool = True, clock_offsets_path: str | Path | None = None,
                  registrations_path: str | Path | None = None,
                  check_outputs: Callable[[dict[int, Path]], None] | None = None) -> dict[str, Any]:
    """Load the three files, track every video (or `video_id`), write MOT files (and GeoJSON).

    Image files (``file_name`` relative to `image_dir`, default the directory of images.json) that exist
    give the kept boxes appearance descriptors (`track_video`); `use_images=False` reads none.
    clock_offsets_path: a CSV of the clock offset applied to each frame (CLOCK_OFFSET_COLUMNS).
    registrations_path: a CSV of the tracker's pose correction of each frame (REGISTRATION_COLUMNS).

    Output paths are checked before any work: an unknown video id raises ValueError, an unwritable
    output OSError; `check_outputs` is called with each video's MOT file path as soon as they are known (after
    reading the frames, before anything else is read or written), e.g. to refuse one that names an input.
    Returns a summary: ``files`` {video_id: path}, ``rows``, ``tracks`` (distinct ids
    per video), ``geojson``, timing and counters.
    """
    dataset = Dataset.load(images_path)
    video_ids = [dataset.resolve_video(video_id)] if video_id is not None else list(dataset.videos)
    if not video_ids:
        raise ValueError(f"{images_path}: no images, nothing to track")
    paths = mot_output_paths(out, dataset, video_ids)
    if check_outputs is not None:
        check_outputs(paths)
    out_is_dir = Path(out).is_dir() or str(out).endswith(("/", os.sep))
    for p in paths.values():
        check_writable(p, create_dir=out_is_dir)
    for extra in (geojson_path, clock_offsets_path, registrations_path):
        if extra is not None:
            check_writable(extra)
    candidates = Candidates.load(candidates_path, dataset)
    camera = Camera.from_spec(camera_path)
    stats: dict[str, Any] = {}
    rows_by_video: dict[int, list[TrackRow]] = {}
    t0 = time.perf_counter()
    images = (Path(images_path).parent if image_dir is None else Path(image_dir)) if use_images else None
    offsets: list[tuple] = []
    registered: list[tuple] = []
    for v in video_ids:
        rows_by_video[v] = track_video(dataset, candidates, camera, v, pipeline_config, tracker_config, size_filter,
                                       stats=stats, image_dir=images, clock_offsets=offsets,
                                       registrations=registered)
    summary: dict[str, Any] = {"files": {}, "rows": 0, "tracks": {}}
    for v, rows in rows_by_video.items():
        summary["rows"] += write_mot(rows, paths[v])
        summary["files"][v] = str(paths[v])
        summary["tracks"][v] = len({r.track.id for r in rows})
    if geojson_path is not None:
        summary["geojson"] = str(geojson_path)
        summary["geojson_features"] = write_geojson(rows_by_video, dataset.categories, geojson_path)
    if clock_offsets_path is not None:
        _write_atomic(Path(clock_offsets_path), ",".join(CLOCK_OFFSET_COLUMNS) + "\n"
                      + "".join(",".join(str(v) for v in row) + "\n" for row in offsets))
        summary["clock_offsets"] = str(clock_offsets_path)
    if registrations_path is not None:
        _write_atomic(Path(registrations_path), ",".join(REGISTRATION_COLUMNS) + "\n"
                      + "".join(",".join(str(v) for v in row) + "\n" for row in registered))
        summary["registrations"] = str(registrations_path)
    summary["frames_registered"] = sum(row[-2] for row in registered)
    summary["frames_carried"] = sum(row[-1] for row in registered)
    applied = [row[3] for row in offsets if math.isfinite(row[3])]
    if applied:
        summary["clock_offset_median_s"] = round(statistics.median(applied), 3)
        summary["clock_offset_frames_measured"] = sum(row[4] for row in offsets)
    frames = max(stats.get("frames", 0), 1)
    summary["frames_without_pose_by_reason"] = count_reasons(stats.get("problems", []))
    summary["stages"] = stats["stage_summary"].as_dict() if "stage_summary" in stats else {}
    summary.update({
        "frames": stats.get("frames", 0), "frames_without_pose": stats.get("frames_without_pose", 0),
        "reidentified": stats.get("reidentified", 0),
        "pipeline_ms_per_frame": round(1000 * stats.get("pipeline_s", 0.0) / frames, 3),
        "tracker_ms_per_frame": round(1000 * stats.get("tracker_s", 0.0) / frames, 3),
        "images_read": stats.get("images_read", 0), "images_missing": stats.get("images_missing", 0),
        "appearance_ms_per_image": round(1000 * stats.get("appearance_s", 0.0) / max(stats.get("images_read", 0), 1),
                                         3),
        "seconds": round(time.perf_counter() - t0, 3), "skipped_candidates": candidates.skipped,
        "confident_without_ground_point": stats.get("confident_without_ground_point", 0),
    })
    return summary

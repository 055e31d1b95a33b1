"""Read COCO/SeaDronesSee datasets and pre-NMS candidate lists, and walk them video by video.

File I/O and validation live here so the pipeline, tracker and evaluation take plain arrays.
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.candidates import Candidates  # noqa: F401  (re-exported: agent.dataset.Candidates, as before)
from agent.field_of_view import ZoomedCamera
from agent.json_files import read_json
from agent.partial_meta import PARTIAL_META, bridged_pose, gimbal_less_compass, meta_hfov, plus
from agent.telemetry_clock import ClockReport, TelemetryClockSettings, TelemetryTrack, reconcile_clock
from agent.telemetry_dequantize import DEQUANTIZE_OFF, dequantize_track
from shared.files import listed_names
from shared.geo import Camera, Pose
from shared.telemetry import Telemetry, from_seadronessee_meta, parse_datetime
from shared.telemetry.interpolation import spread_whole_second_stamps
from shared.telemetry.seadronessee import MetaProblem, compass_heading_of, meta_object, pitch_convention_of
from shared.telemetry.seadronessee_videos import (  # noqa: F401  (TIME_GAP_*, own_video_ids: re-exported, as before)
    TIME_GAP_S,
    TIME_GAP_STEPS,
    group_videos,
    image_time,
    own_video_ids,
    parse_time,
    source_of,
    time_gap_s,
)
from shared.telemetry.seadronessee_zones import harmonise_zones

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0


def _one_file(folder: Path, name: str, pattern: str, what: str) -> Path:
    """folder/name, else the one file matching pattern; ValueError naming what was found otherwise."""
    found = [folder / name]
    if not found[0].is_file():
        found = sorted(folder.glob(pattern))
    if len(found) != 1:
        raise ValueError(f"{folder}: expected {name} or one {pattern}{what}, found "
                         f"{', '.join(p.name for p in found) or 'none'}")
    return found[0]


def dataset_files(path: str | Path, detections: str | Path | None = None,
                  camera: str | Path | None = None) -> tuple[Path, Path, str | Path]:
    """(images, candidates, camera spec) of a dataset as users have it: `path` is the images JSON, or a
    folder holding it (``images.json``, else the one ``instances*.json``) with the candidates
    (``pre_nms.json``, else the one ``detections*.json``) and ``camera.json`` (a camera preset's name or file
    may be given instead). ValueError naming what is missing or ambiguous."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    if path.is_dir():
        images = _one_file(folder, "images.json", "instances*.json", "")
    elif path.is_file():
        images = path
    else:
        raise ValueError(f"dataset {path} does not exist")
    if detections is None:
        detections = _one_file(folder, "pre_nms.json", "detections*.json", " (the detector's results)")
    if camera is None:
        if not (folder / "camera.json").is_file():
            raise ValueError(f"{folder}: no camera.json: give the camera (a CAMERA.json or a preset such as "
                             "dji-mavic2-pro; SeaDronesSee meta has no focal length)")
        camera = folder / "camera.json"
    return images, Path(detections), camera


@dataclass(frozen=True, slots=True)
class ImageRecord:
    id: int
    width: int
    height: int
    video_id: int
    frame_index: int
    date_time: str | None
    meta: dict | None
    file_name: str = ""


@dataclass
class Dataset:
    """A COCO images file: images grouped by video (sorted by frame index) and categories.

    Videos: `shared.telemetry.seadronessee_videos.group_videos`'s (``source.video`` per drone, folder and
    recording, with the file's own ``video_id`` where it is consistent; else ``video_id``; else per drone or meta
    layout), images without any video then split by their clock; what was split is logged as a warning. Frame
    index: ``source.frame_no``, else ``frame_index``, else the rank in time (the frames' own ``date_time``).
    """

    images: dict[int, ImageRecord]
    videos: dict[int, list[ImageRecord]]
    categories: dict[int, str]
    coco: dict[str, Any] = field(repr=False)
    #: video id -> name (the COCO ``videos`` list, ``source.video``); videos without one are absent
    video_names: dict[int, str] = field(default_factory=dict)

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        return cls.from_dict(read_json(path, "images"), source=str(path))

    def resolve_video(self, video: int | str) -> int:
        """The id of a video given by its id (an int, or a string of digits) or its name (`video_names`: the
        COCO ``videos`` list, SeaDronesSee v2's ``source.video``); an id wins over a name spelled the same.
        Raises ValueError naming the known ids and names."""
        text = str(video).strip()
        if text.lstrip("-").isdigit() and int(text) in self.videos:
            return int(text)
        ids = [vid for vid, name in self.video_names.items() if name == text and vid in self.videos]
        if ids:
            return ids[0]
        names = [self.video_names[v] for v in self.videos if v in self.video_names]
        shown = listed_names([repr(n) for n in names], 12)
        raise ValueError(f"unknown video {text!r}; known ids: {sorted(self.videos)}"
                         + (f"; names: {shown}" if names else ""))

    @classmethod
    def from_dict(cls, coco: Any, *, source: str = "<images>") -> Dataset:
        if not isinstance(coco, dict) or not isinstance(coco.get("images"), list):
            raise ValueError(f"{source}: not a COCO images file (no 'images' list)")
        cats = coco.get("categories")
        if not isinstance(cats, list) or not cats:
            raise ValueError(f"{source}: no 'categories' list")
        categories: dict[int, str] = {}
        for i, c in enumerate(cats):
            if not isinstance(c, dict) or not isinstance(c.get("id"), int) or not isinstance(c.get("name"), str):
                raise ValueError(f"{source}: categories[{i}] needs an integer 'id' and a string 'name'")
            categories[c["id"]] = c["name"]
        listed = [v["id"] for v in coco.get("videos") or [] if isinstance(v, dict) and isinstance(v.get("id"), int)]
        raw, notices = harmonise_zones(coco["images"])
        for notice in notices:
            log.warning("%s: %s", source, notice)
        try:  # a video_id or frame number that is no integer: named with the file
            ids, found = _video_ids([im for im in raw if isinstance(im, dict)], listed, source)
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None
        images: dict[int, ImageRecord] = {}
        for i, im in enumerate(raw):
            if not isinstance(im, dict):
                raise ValueError(f"{source}: images[{i}] is not an object")
            try:
                video_id, frame_index = ids[id(im)]
                rec = ImageRecord(
                    id=_int(im, "id"), width=_side(im, "width"), height=_side(im, "height"),
                    video_id=video_id, frame_index=i if frame_index is None else frame_index,
                    date_time=im.get("date_time") if isinstance(im.get("date_time"), str) else None,
                    meta=_meta(im.get("meta")),
                    file_name=str(im.get("file_name", "")),
                )
            except ValueError as exc:
                raise ValueError(f"{source}: images[{i}]: {exc}") from None
            if rec.id in images:
                raise ValueError(f"{source}: images[{i}]: duplicate image id {rec.id}")
            images[rec.id] = rec
        unread = [r.date_time for r in images.values() if r.date_time and r.date_time.strip()
                  and parse_time(r.date_time) is None]
        unread += [str(im["date_time"]) for im in raw if isinstance(im, dict)
                   and im.get("date_time") is not None and not isinstance(im.get("date_time"), str)]
        if unread:
            log.warning("%s: %d images have a date_time that is no date and time this reader knows (first: %r): those "
                        "frames have no clock of their own (their meta's stamps stand in)", source, len(unread),
                        unread[0][:40])
        videos: dict[int, list[ImageRecord]] = defaultdict(list)
        for rec in images.values():
            videos[rec.video_id].append(rec)
        for frames in videos.values():
            frames.sort(key=lambda r: r.frame_index)
        return cls(images, dict(sorted(videos.items())), categories, coco, _video_names(coco, found))


def _meta(meta: Any) -> dict | None:
    """An image's meta: an object, or one written as JSON text (`shared.telemetry.seadronessee.meta_object`)."""
    value = meta_object(meta)
    return value if isinstance(value, dict) or value is None else dict(value)


def _frame(im: dict) -> int | None:
    src = source_of(im)
    key, frame = ("source.frame_no", src["frame_no"]) if "frame_no" in src else ("frame_index", im.get("frame_index"))
    return None if frame is None else _int({key: frame}, key)


def _video_ids(images: list[dict], reserved: Iterable[int] = (), source: str = "<images>"
               ) -> tuple[dict[int, tuple[int, int | None]], dict[int, str]]:
    """Video id and frame index of every image (keyed by id() of its dict), and the names of the videos that have one.

    Videos are `group_videos`'s (its notices logged as warnings). A ``source`` video whose images all carry one integer
    ``video_id`` that no other video claims keeps it (DESIGN 6's layout with v2's ``source`` kept: the file's ids and
    its ``videos`` names then agree); other ``source`` videos get integer ids after the largest id in the file
    (``reserved``: the ``videos`` list's), in their order (drone, video, folder, recording); images without any video
    then, per group (drone, meta layout), split where their clock jumps (TIME_GAP_S). Frame indices:
    ``source.frame_no``, else ``frame_index``, else the rank in time by the frames' own ``date_time``
    (`_ranked_by_time`; None: the file's order).
    """
    grouping = group_videos(images)
    for notice in grouping.notices:
        log.warning("%s: %s", source, notice)
    of_image = grouping.of_images(len(images))
    out: dict[int, tuple[int, int | None]] = {}
    used: set[int] = set(reserved)
    for im, group in zip(images, of_image, strict=True):
        if group.kind == "id":
            vid = _int(im, "video_id")
            used.add(vid)
            out[id(im)] = (vid, _frame(im))
    named = {g.order: [images[i] for i in g.images] for g in grouping.groups if g.kind == "source"}
    own = own_video_ids(named)  # (images without a source that carry the same id join it: the file says so)
    taken = used | set(own.values())
    next_id = max(taken) + 1 if taken else (1 if named else 0)  # a file of loose images alone: video 0, as before
    names: dict[int, str] = {}
    for group in grouping.groups:
        if group.kind != "source":
            continue
        if group.order in own:
            vid = own[group.order]
        else:
            vid, next_id = next_id, next_id + 1
        names[vid] = group.name
        for i in group.images:
            out[id(images[i])] = (vid, _frame(images[i]))
    for group in (g for g in grouping.groups if g.kind == "loose"):
        pieces = _split_by_time([images[i] for i in group.images])
        for n, piece in enumerate(pieces):
            timed = all(image_time(im) is not None for im in piece)
            for rank, im in enumerate(piece):
                frame = im.get("frame_index")
                out[id(im)] = (next_id, _int(im, "frame_index") if frame is not None else (rank if timed else None))
            if group.name is not None:
                names[next_id] = group.name if len(pieces) == 1 else f"{group.name}_{n + 1}"
            next_id += 1
    _warn_repeated_frames(out, names, source)
    return _ranked_by_time(images, out), names


def _warn_repeated_frames(out: dict[int, tuple[int, int | None]], names: dict[int, str], source: str) -> None:
    """One warning per video two of whose images have one frame number (two recordings under one `video_id`, a
    duplicated frame, ...): taken as one video, its tracks' MOTChallenge rows repeat those frames."""
    frames: dict[int, list[int]] = defaultdict(list)
    for vid, frame in out.values():
        if frame is not None:
            frames[vid].append(frame)
    for vid, found in frames.items():
        counts = Counter(found)
        repeated = sum(n - 1 for n in counts.values() if n > 1)
        if repeated:
            log.warning("%s: video %s holds %d images whose frame number another of its images has (first: frame %d): "
                        "two recordings or a duplicated frame under one video? They are taken as one video, and its "
                        "tracks' MOTChallenge rows repeat those frames: give each recording its own video",
                        source, names.get(vid, f"id {vid}"), repeated, min(f for f, n in counts.items() if n > 1))


def _ranked_by_time(images: list[dict], out: dict[int, tuple[int, int | None]]) -> dict[int, tuple[int, int | None]]:
    """Frames of a video without frame indices: ranked by their own ``date_time`` when every one has one, by their
    metas' stamps when none has one (they were walked in the file's order, interleaved or shuffled: time went back 24
    times in 50 frames); a mix of the two is left to the file's order (a meta's UTC stamp beside another frame's local
    clock would mix two clocks)."""
    pending: dict[int, list[tuple[int, dict]]] = defaultdict(list)
    for order, im in enumerate(images):
        vid, frame = out[id(im)]
        if frame is None:
            pending[vid].append((order, im))
    for vid, frames in pending.items():
        own = [_frame_date(im) for _, im in frames]
        if any(t is None for t in own):  # one clock for all: the frames' own, else (none has one) the metas'
            own = [image_time(im) for _, im in frames] if all(t is None for t in own) else [None]
        if all(t is not None for t in own):
            ranked = sorted(zip(own, frames, strict=True), key=lambda item: (item[0], item[1][0]))
            for rank, (_, (_, im)) in enumerate(ranked):
                out[id(im)] = (vid, rank)
    return out


def _frame_date(im: dict) -> float | None:
    """An image's own ``date_time`` (the frame clock), None when absent or unreadable."""
    return parse_time(im.get("date_time"))


def _split_by_time(images: list[dict]) -> list[list[dict]]:
    """Images without a video, as videos: in time order, split where the clock jumps by more than
    TIME_GAP_S and TIME_GAP_STEPS median steps; images without a time form one video in file order."""
    timed = [(t, i, im) for i, im in enumerate(images) if (t := image_time(im)) is not None]
    untimed = [im for im in images if image_time(im) is None]
    groups: list[list[dict]] = []
    if timed:
        timed.sort(key=lambda item: (item[0], item[1]))
        times = np.array([item[0] for item in timed])
        cuts = np.flatnonzero(np.diff(times) > time_gap_s(times)) + 1
        for part in np.split(np.arange(len(timed)), cuts):
            groups.append([timed[k][2] for k in part])
    if untimed:
        groups.append(untimed)
    return groups


def _video_names(coco: dict, found: dict[int, str]) -> dict[int, str]:
    """Video id -> name: the COCO ``videos`` list, else the name `_video_ids` found (``source.video``, told apart when
    it holds several recordings; a label for images without a video split apart)."""
    names: dict[int, str] = {}
    for v in coco.get("videos") or []:
        if isinstance(v, dict) and isinstance(v.get("id"), int) and isinstance(v.get("name"), str) and v["name"]:
            names[v["id"]] = v["name"]
    return names | {vid: name for vid, name in found.items() if vid not in names}


def int_text(text: str) -> int | None:
    """A whole number written as text (ASCII digits, ``"12"`` or ``"12.0"``, spaces around), else None."""
    whole = re.fullmatch(r"\s*([+-]?[0-9]+)(?:\.0*)?\s*", text)
    return None if whole is None else int(whole[1])


#: The largest image side read (px): larger is no camera's frame (and 1e400 overflowed float arithmetic).
MAX_SIDE_PX = 1_000_000


def _side(d: dict, key: str) -> int:
    """An image's width or height, in 1..MAX_SIDE_PX (0 divided the camera's aspect ratio by zero)."""
    side = _int(d, key)
    if not 1 <= side <= MAX_SIDE_PX:
        raise ValueError(f"field {key!r} must be a number of pixels in 1..{MAX_SIDE_PX}, got {side!r}")
    return side


def _int(d: dict, key: str, default: int | None = None) -> int:
    """d[key] as an integer: a whole number, also written as text (``"5415"``, as some tools write every field)."""
    value = d.get(key, default)
    if value is None:
        raise ValueError(f"missing field {key!r}")
    if isinstance(value, str):
        number = int_text(value)
        if number is None:
            raise ValueError(f"field {key!r} must be an integer, got {value!r}")
        return number
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (isinstance(value, float) and not (
            math.isfinite(value) and value == int(value))):  # an int of any size is whole (isfinite would overflow)
        raise ValueError(f"field {key!r} must be an integer, got {d.get(key, default)!r}")
    return int(value)


def image_file(image_dir: str | Path, image: ImageRecord) -> Path | None:
    """The file of an image: its ``file_name`` (absolute, or relative to image_dir); None when there is no
    such file (simulated datasets name files they do not write; SeaDronesSee keeps images apart)."""
    if not image.file_name:
        return None
    path = Path(image.file_name)
    if not path.is_absolute():
        path = Path(image_dir) / path
    return path if path.is_file() else None


def read_image(image_dir: str | Path, image: ImageRecord) -> NDArray[np.uint8] | None:
    """The image as an (H, W, 3) uint8 BGR array (OpenCV), or None when the file is missing or unreadable."""
    import cv2

    path = image_file(image_dir, image)
    if path is None:
        return None
    pixels = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if pixels is None:
        log.warning("image %s cannot be read by OpenCV", path)
        return None
    return np.asarray(pixels, dtype=np.uint8)  # IMREAD_COLOR: always 8-bit


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame ready for the pipeline: image, its pose (None without usable meta), time."""

    image: ImageRecord
    pose: Pose | None
    t: float
    camera: Camera
    pose_t: float | None = None  # time of the telemetry sample behind the pose (may lag t)
    #: The pose is the telemetry at the frame's own time (interpolated between its samples, or re-timed by the
    #: clock-offset estimate, agent.clock_offset): it needs no latency compensation
    #: (GpsTracker.update(pose_retimed=True)).
    pose_retimed: bool = False
    #: The video's telemetry samples on the frame clock (shared by its frames), for stages that re-time poses.
    track: TelemetryTrack | None = None


@dataclass(frozen=True, slots=True)
class PoseProblem:
    """Why a frame has no pose: reason (a short class, counted in summaries) and the detail."""

    image_id: int
    reason: str
    detail: str

    def __str__(self) -> str:
        return f"image {self.image_id}: {self.detail}"


def count_reasons(problems: Iterable[PoseProblem]) -> dict[str, int]:
    """{reason: frames}, most frequent first."""
    counts = Counter(p.reason for p in problems)
    return dict(counts.most_common())


@dataclass
class VideoTelemetry:
    """What reading one video's telemetry found and did: the pitch convention of its meta, the clock stage's
    report (agent.telemetry_clock), the quanta made continuous and the coordinates held between updates interpolated
    (agent.telemetry_dequantize), and whether poses were interpolated at the frames' times."""

    pitch_convention: str = "depression"
    clock: ClockReport = field(default_factory=ClockReport)
    quanta: dict[str, float] = field(default_factory=dict)
    #: coordinates held between regular updates: their update period, seconds (agent.telemetry_holds)
    holds: dict[str, float] = field(default_factory=dict)
    at_frame_time: bool = False
    #: informative windows the clock-offset estimate found (agent.clock_offset; 0 when it did not run)
    offset_windows: int = 0
    #: why the dequantisation did not run ("" when it ran): a switch turned it off
    dequantize_off: str = ""
    #: view cuts (agent.view_cuts): telemetry intervals turning sharply enough to hide one, the cuts placed and the
    #: intervals with too few frames to judge; None when the stage did not run
    view_cuts: tuple[int, int, int] | None = None
    #: frames without the gimbal's heading that took the aircraft's compass heading
    compass_frames: int = 0
    #: frames whose meta lacked a field (pitch, heading, height) given the pose interpolated between the others'
    bridged_frames: int = 0


def frame_telemetry(image: ImageRecord, pitch_convention: str = "auto",
                    compass_records: dict[int, Telemetry] | None = None) -> tuple[Telemetry | None, PoseProblem | None]:
    """An image's telemetry record from its meta, or (None, the problem). A frame without meta has the
    problem "no meta"; its own date_time stands in for a meta without a time. A meta without the gimbal's heading
    but with the aircraft's ``compass_heading`` has the problem "no heading", and its record with the compass
    heading goes into `compass_records` (by image id; `iter_video_frames` uses them for a video with no gimbal
    heading at all)."""
    if image.meta is None:
        return None, PoseProblem(image.id, "no meta", "no meta")
    t_default = None
    if image.date_time:
        try:
            t_default = parse_datetime(image.date_time)
        except ValueError:
            t_default = None
    try:
        tel = from_seadronessee_meta(image.meta, image.frame_index, pitch_convention=pitch_convention,
                                     t_default=t_default)
    except MetaProblem as exc:
        return None, PoseProblem(image.id, exc.reason, str(exc))
    except ValueError as exc:
        return None, PoseProblem(image.id, "bad value", str(exc))
    assert tel is not None
    if tel.pitch_deg is None:
        return None, PoseProblem(image.id, "no pitch", "telemetry has no gimbal pitch")
    if tel.height_m is None or tel.height_m <= 0:
        return None, PoseProblem(image.id, "no height", f"height above ground {tel.height_m!r} is not > 0 m")
    if tel.heading_deg is None:
        compass = compass_heading_of(image.meta)
        if compass is not None and compass_records is not None:
            compass_records[image.id] = replace(tel, heading_deg=compass)  # the aircraft's
        return None, PoseProblem(image.id, "no heading", "telemetry has no gimbal heading")
    return tel, None


def _frame_clock(image: ImageRecord) -> float | None:
    return parse_time(image.date_time)


def iter_video_frames(dataset: Dataset, camera: Camera, video_id: int, *, fps: float = DEFAULT_FPS,
                      problems: list[PoseProblem] | None = None, at_frame_time: bool = True,
                      dequantize: bool = False, clock: TelemetryClockSettings | None = None,
                      report: VideoTelemetry | None = None) -> Iterator[Frame]:
    """Frames of one video in frame order, with pose and time.

    Time: the image's date_time (the frame clock), else its telemetry stamp moved onto the frame clock,
    else the previous frame's time plus the frame-index step / fps (frame_index / fps for the first); never
    backwards. The telemetry is put on the frame clock first (agent.telemetry_clock: a time-zone offset
    removed, sample-and-hold repeats recognised). at_frame_time: each pose is the telemetry interpolated at
    its frame's time between the samples (pose_retimed, with the video's track); False: each frame keeps the
    sample it carries (the paper's rule), stamped on the frame clock. dequantize: GPS written with 4-5
    decimals and altitude in whole or half metres made continuous (agent.telemetry_dequantize; with
    at_frame_time). A frame whose meta is missing or cannot be used gets pose None and its problem is
    appended to `problems` (when given); `report` (when given) is filled with what was found. The camera is
    rescaled when the image size differs. The pitch convention (positive or, as DJI writes it, negative
    below the horizon) is decided per video (`shared.telemetry.seadronessee.pitch_convention_of`).
    """
    images = dataset.videos[video_id]
    info = report if report is not None else VideoTelemetry()
    info.pitch_convention = pitch_convention_of(image.meta for image in images)
    info.at_frame_time = at_frame_time
    cameras: dict[tuple[int, int], Camera] = {}
    zoomed = ZoomedCamera()
    records: list[Telemetry | None] = []
    clocks: list[float | None] = []
    compass: dict[int, Telemetry] = {}
    missing: dict[int, PoseProblem] = {}
    for image in images:
        key = (image.width, image.height)
        if key not in cameras:
            cameras[key] = camera.fitted_to(*key, source=f"the frames of video {video_id}")
            if key != (camera.width, camera.height) and camera.preset is None:  # a preset has no size of its own
                log.warning("camera is %dx%d, the frames of video %s are %dx%d: scaled the intrinsics to them",
                            camera.width, camera.height, video_id, *key)
        tel, problem = frame_telemetry(image, info.pitch_convention, compass)
        if problem is not None:
            missing[image.id] = problem
        records.append(tel)
        clocks.append(_frame_clock(image))
    if compass and not any(tel is not None for tel in records):
        # no frame has the gimbal's heading (a file without the field): the aircraft's compass heading stands in,
        # the gimbal mostly points its way; where other frames have it, they say more (`bridged_pose`)
        for i, image in enumerate(images):
            if image.id in compass:
                records[i] = compass[image.id]
                del missing[image.id]
        info.compass_frames = len(compass)
        log.warning("video %s: no frame has a gimbal_heading: the aircraft's compass_heading stands in for %d of %d "
                    "(the camera may point elsewhere)", video_id, len(compass), len(images))
    # frames whose meta lacks a field: their meta's own stamp (when the frame has no clock of its own) and zoom
    partial_t = {image.id: image_time({"meta": image.meta}) for image in images
                 if image.id in missing and missing[image.id].reason in PARTIAL_META}
    compass_offset = None if not compass else gimbal_less_compass(
        [image.meta for image in images], [None if tel is None else tel.heading_deg for tel in records])
    posed = [(tel, clocks[i]) for i, tel in enumerate(records) if tel is not None]
    track: TelemetryTrack | None = None
    zone = 0.0
    if posed:
        stamps = np.array([tel.t for tel, _ in posed])
        own_clock = np.array([c is not None for _, c in posed])
        frame_t = np.array([c if c is not None else tel.t for tel, c in posed])
        values = np.array([[r.lat, r.lon, r.height_m, r.heading_deg, r.pitch_deg] for r, _ in posed], dtype=np.float64)
        track, info.clock = reconcile_clock(frame_t, stamps, values, own_clock, clock)
        zone = info.clock.zone_offset_s
        if dequantize and at_frame_time:
            track, info.quanta, info.holds = dequantize_track(track)
        else:
            info.dequantize_off = DEQUANTIZE_OFF if not dequantize else "off: each frame keeps the sample it carries"
    # The frame's own clock first (telemetry at 10 Hz repeats its time for 3 frames at 30 fps), else its telemetry
    # stamp moved onto the frame clock; such times at whole seconds that repeat are spread over their second in frame
    # order, as a log's rows are (the frames of one second shared a time: a zero step, no memory evidence, one pose)
    stamped = [c if c is not None else (tel.t + zone if tel is not None else plus(partial_t.get(image.id), zone))
               for c, tel, image in zip(clocks, records, images, strict=True)]
    known = [i for i, v in enumerate(stamped) if v is not None and math.isfinite(v)]
    for i, v in zip(known, spread_whole_second_stamps([stamped[i] for i in known]), strict=True):  # type: ignore[misc]
        stamped[i] = v
    t_prev: float | None = None
    i_prev = 0
    for image, tel, t in zip(images, records, stamped, strict=True):
        if t is None or not math.isfinite(t):
            # No clock on this frame: continue the last one by the frame-index step.
            t = image.frame_index / fps if t_prev is None else t_prev + (image.frame_index - i_prev) / fps
        if t_prev is not None and t < t_prev:
            t = t_prev  # non-monotonic clocks: never run the memory backwards
        t_prev, i_prev = t, image.frame_index
        cam = cameras[(image.width, image.height)]
        if tel is not None and tel.hfov_deg is not None:  # a zoom lens's frame (meta hfov_deg, `uavmm detect`)
            cam = zoomed(cam, tel.hfov_deg)
        if tel is None:
            problem = missing.get(image.id)
            pose = bridged_pose(track, t, None if problem is None else problem.reason) if at_frame_time else None
            hfov = meta_hfov(image.meta)
            own_cam = zoomed(cam, hfov) if hfov else cam
            if pose is not None:
                info.bridged_frames += 1
                yield Frame(image, pose, t, own_cam, t, True, track)
                continue
            if image.id in compass and compass_offset is not None:  # too far from the gimbal's headings
                rec = compass[image.id]
                rec = replace(rec, heading_deg=(rec.heading_deg or 0.0) + compass_offset)
                info.compass_frames += 1
                yield Frame(image, rec.to_pose(), t, own_cam, rec.t + zone)
                continue
            if problem is not None and problems is not None:
                problems.append(problem)
            yield Frame(image, None, t, cam)
            continue
        try:
            if at_frame_time and track is not None:
                lat, lon, height, heading, pitch = (float(v) for v in track.at(t)[0])
                pose = Pose(lat, lon, max(height, 0.1), min(max(pitch, 0.0), 90.0), heading, tel.roll_deg)
                frame = Frame(image, pose, t, cam, t, True, track)
            else:
                frame = Frame(image, tel.to_pose(), t, cam, tel.t + zone)
        except ValueError as exc:
            if problems is not None:
                problems.append(PoseProblem(image.id, "bad pose", str(exc)))
            frame = Frame(image, None, t, cam)
        yield frame
    if info.bridged_frames:
        log.warning("video %s: %d frames whose meta lacks pitch, heading or height took the pose interpolated between "
                    "the other frames' samples", video_id, info.bridged_frames)

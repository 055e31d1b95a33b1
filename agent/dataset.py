"""Read COCO/SeaDronesSee datasets and pre-NMS candidate lists, and walk them video by video.

File I/O and validation live here so the pipeline, tracker and evaluation take plain arrays.
"""

from __future__ import annotations

import json
import logging
import math
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose
from shared.telemetry import from_seadronessee_meta, parse_datetime

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0


def read_json(path: str | Path, what: str) -> Any:
    """Parse a JSON file; errors name the file and what it was meant to be."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{what} file {path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} file {path} is not valid JSON: {exc}") from None


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
    """A COCO images file: images grouped by video (sorted by frame index) and categories."""

    images: dict[int, ImageRecord]
    videos: dict[int, list[ImageRecord]]
    categories: dict[int, str]
    coco: dict[str, Any] = field(repr=False)

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        return cls.from_dict(read_json(path, "images"), source=str(path))

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
        images: dict[int, ImageRecord] = {}
        for i, im in enumerate(coco["images"]):
            if not isinstance(im, dict):
                raise ValueError(f"{source}: images[{i}] is not an object")
            try:
                rec = ImageRecord(
                    id=_int(im, "id"), width=_int(im, "width"), height=_int(im, "height"),
                    video_id=_int(im, "video_id", 0), frame_index=_int(im, "frame_index", i),
                    date_time=im.get("date_time") if isinstance(im.get("date_time"), str) else None,
                    meta=im.get("meta") if isinstance(im.get("meta"), dict) else None,
                    file_name=str(im.get("file_name", "")),
                )
            except ValueError as exc:
                raise ValueError(f"{source}: images[{i}]: {exc}") from None
            if rec.id in images:
                raise ValueError(f"{source}: images[{i}]: duplicate image id {rec.id}")
            images[rec.id] = rec
        videos: dict[int, list[ImageRecord]] = defaultdict(list)
        for rec in images.values():
            videos[rec.video_id].append(rec)
        for frames in videos.values():
            frames.sort(key=lambda r: r.frame_index)
        return cls(images, dict(sorted(videos.items())), categories, coco)


def _int(d: dict, key: str, default: int | None = None) -> int:
    value = d.get(key, default)
    if value is None:
        raise ValueError(f"missing field {key!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise ValueError(f"field {key!r} must be an integer, got {value!r}")
    return int(value)


@dataclass
class Candidates:
    """Pre-NMS candidates per image: boxes_xyxy (N, 4) float32, scores (N,) float32, class ids (N,).

    embeddings: per image, (N, D) float32 appearance descriptors from the optional ``embedding`` field
    of the entries (NaN rows for entries without one); only images where some entry has one.
    """

    by_image: dict[int, tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]]
    skipped: dict[str, int]
    embeddings: dict[int, NDArray[np.float32]] = field(default_factory=dict)

    def get_embeddings(self, image_id: int) -> NDArray[np.float32] | None:
        """(N, D) descriptors of the image's candidates in `get`'s order, or None when it has none."""
        return self.embeddings.get(image_id)

    def get(self, image_id: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
        return self.by_image.get(image_id, empty)

    @classmethod
    def load(cls, path: str | Path, dataset: Dataset) -> Candidates:
        return cls.from_list(read_json(path, "candidates"), dataset, source=str(path))

    @classmethod
    def from_list(cls, entries: Any, dataset: Dataset, *, source: str = "<candidates>") -> Candidates:
        """Validate a COCO result list.

        Entries naming an unknown image_id or category_id, or malformed ones (missing fields,
        non-numeric values) raise ValueError naming the entry: they mean the files do not belong
        together. Degenerate boxes (NaN/inf, width or height <= 0) and scores outside [0, 1] or NaN
        are skipped and counted in `skipped` (detectors emit those; one should not stop a run).
        """
        if not isinstance(entries, list):
            raise ValueError(f"{source}: expected a JSON list of {{image_id, category_id, bbox, score}}")
        n = len(entries)
        image_ids = np.empty(n, np.int64)
        cat_ids = np.empty(n, np.int64)
        boxes = np.empty((n, 4), np.float64)
        scores = np.empty(n, np.float64)
        emb_rows: dict[int, list[float]] = {}  # optional appearance descriptors (docs/tracking.md)
        for i, e in enumerate(entries):
            try:
                image_ids[i] = e["image_id"]
                cat_ids[i] = e["category_id"]
                bbox = e["bbox"]
                if len(bbox) != 4:
                    raise ValueError(f"bbox must have 4 numbers, got {len(bbox)}")
                boxes[i] = bbox
                scores[i] = e["score"]
                if "embedding" in e:
                    emb = e["embedding"]
                    if not isinstance(emb, list) or not emb or not all(
                            isinstance(v, (int, float)) and not isinstance(v, bool) for v in emb):
                        raise ValueError("embedding must be a non-empty list of numbers")
                    emb_rows[i] = emb
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                raise ValueError(f"{source}: entry {i} is malformed ({exc!r}): {str(e)[:200]}") from None
        dims = {len(v) for v in emb_rows.values()}
        if len(dims) > 1:
            raise ValueError(f"{source}: embeddings of different lengths {sorted(dims)}")
        emb_all = None
        if emb_rows:
            emb_all = np.full((n, dims.pop()), np.nan, np.float32)
            rows = np.fromiter(emb_rows, np.int64, len(emb_rows))
            emb_all[rows] = np.asarray(list(emb_rows.values()), np.float32)
        unknown_img = ~np.isin(image_ids, np.fromiter(dataset.images, np.int64, len(dataset.images)))
        if unknown_img.any():
            i = int(np.flatnonzero(unknown_img)[0])
            raise ValueError(f"{source}: entry {i} references unknown image_id {int(image_ids[i])} "
                             f"({int(unknown_img.sum())} such entries)")
        unknown_cat = ~np.isin(cat_ids, np.fromiter(dataset.categories, np.int64, len(dataset.categories)))
        if unknown_cat.any():
            i = int(np.flatnonzero(unknown_cat)[0])
            raise ValueError(f"{source}: entry {i} references unknown category_id {int(cat_ids[i])}; "
                             f"known: {sorted(dataset.categories)}")
        finite = np.isfinite(boxes).all(axis=1)
        positive = finite & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
        good_score = np.isfinite(scores) & (scores >= 0) & (scores <= 1)
        skipped = {
            "non_finite_box": int((~finite).sum()),
            "non_positive_size": int((finite & ~positive).sum()),
            "score_out_of_range": int((positive & ~good_score).sum()),
        }
        if any(skipped.values()):
            log.warning("%s: skipped candidates: %s", source, skipped)
        keep = positive & good_score
        image_ids, cat_ids, boxes, scores = image_ids[keep], cat_ids[keep], boxes[keep], scores[keep]
        xyxy = np.column_stack([boxes[:, 0], boxes[:, 1], boxes[:, 0] + boxes[:, 2], boxes[:, 1] + boxes[:, 3]])
        order = np.argsort(image_ids, kind="stable")
        image_ids, cat_ids, xyxy, scores = image_ids[order], cat_ids[order], xyxy[order], scores[order]
        if emb_all is not None:
            emb_all = emb_all[keep][order]
        by_image = {}
        embeddings = {}
        if len(image_ids):
            splits = np.flatnonzero(np.diff(image_ids)) + 1
            for idx in np.split(np.arange(len(image_ids)), splits):
                by_image[int(image_ids[idx[0]])] = (xyxy[idx].astype(np.float32), scores[idx].astype(np.float32),
                                                    cat_ids[idx])
                if emb_all is not None and np.isfinite(emb_all[idx]).all(axis=1).any():
                    embeddings[int(image_ids[idx[0]])] = emb_all[idx]
        return cls(by_image, skipped, embeddings)


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
    return pixels


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame ready for the pipeline: image, its pose (None without usable meta), time."""

    image: ImageRecord
    pose: Pose | None
    t: float
    camera: Camera
    pose_t: float | None = None  # time of the telemetry sample behind the pose (may lag t)
    #: The pose was interpolated at the frame's time by the clock-offset estimate (agent.clock_offset): it
    #: needs no latency compensation (GpsTracker.update(pose_retimed=True)).
    pose_retimed: bool = False


def frame_pose(image: ImageRecord) -> tuple[Pose | None, float | None, str | None]:
    """Pose and time from an image's meta: (pose, t, problem). Problem names why pose is None."""
    if image.meta is None:
        return None, None, None
    meta = image.meta
    if "date_time" not in meta and image.date_time:
        meta = {**meta, "date_time": image.date_time}
    try:
        tel = from_seadronessee_meta(meta, image.frame_index)
        assert tel is not None
        return tel.to_pose(), tel.t, None
    except ValueError as exc:
        return None, None, str(exc)


def iter_video_frames(dataset: Dataset, camera: Camera, video_id: int, *, fps: float = DEFAULT_FPS,
                      problems: list[str] | None = None) -> Iterator[Frame]:
    """Frames of one video in frame order, with pose and time.

    Time: the image's date_time (the frame clock), else the meta's, else the previous frame's time plus
    the frame-index step / fps (frame_index / fps for the first); a frame whose
    meta cannot be used (missing gimbal angles, garbage values) gets pose None and its problem is
    appended to `problems` (when given). The camera is rescaled when the image size differs.
    """
    cameras: dict[tuple[int, int], Camera] = {}
    t_prev: float | None = None
    i_prev = 0
    for image in dataset.videos[video_id]:
        key = (image.width, image.height)
        if key not in cameras:
            cameras[key] = camera.fitted_to(*key, source=f"the frames of video {video_id}")
            if key != (camera.width, camera.height) and camera.preset is None:  # a preset has no size of its own
                log.warning("camera is %dx%d, the frames of video %s are %dx%d: scaled the intrinsics to them",
                            camera.width, camera.height, video_id, *key)
        pose, pose_t, problem = frame_pose(image)
        if problem is not None and problems is not None:
            problems.append(f"image {image.id}: {problem}")
        # The frame's own clock first: telemetry at 10 Hz repeats its time for 3 frames at 30 fps.
        t = None
        if image.date_time:
            try:
                t = parse_datetime(image.date_time)
            except ValueError:
                t = None
        if t is None:
            t = pose_t
        if t is None or not math.isfinite(t):
            # No clock on this frame: continue the last one by the frame-index step.
            t = image.frame_index / fps if t_prev is None else t_prev + (image.frame_index - i_prev) / fps
        if t_prev is not None and t < t_prev:
            t = t_prev  # non-monotonic clocks: never run the memory backwards
        t_prev, i_prev = t, image.frame_index
        yield Frame(image, pose, t, cameras[key], pose_t)

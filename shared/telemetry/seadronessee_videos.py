"""Which video each image of a SeaDronesSee COCO file is of: one drone's one recording per video.

The dataset reader (`agent.dataset`) and the telemetry path (`parse_seadronessee_coco`, `agent.json_video`) both
group by `group_videos`, so a video has one name everywhere (docs/geometry.md, "Videos of a COCO file").
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from shared.telemetry.dates import parse_datetime

__all__ = ["TIME_GAP_S", "TIME_GAP_STEPS", "VideoGroup", "VideoGrouping", "group_videos", "meta_object",
           "image_time", "own_video_ids", "parse_time", "source_of", "time_gap_s"]

K = TypeVar("K")

#: A clock jump of more than this many seconds (and more than TIME_GAP_STEPS of the median step) ends a flight:
#: images without any video split there, and a video's frame numbers starting again there begin a second recording.
TIME_GAP_S = 10.0
TIME_GAP_STEPS = 20.0


@dataclass(frozen=True, slots=True)
class VideoGroup:
    """One video of a COCO file.

    kind: "source" (SeaDronesSee v2's ``source.video``), "id" (the image's ``video_id``), "loose" (neither).
    order: the group's sort key among those of its kind: (drone, video, folder, recording) for "source", (drone,
    folder, meta layout) for "loose", () for "id".
    name: "source": ``source.video`` (stripped), with what tells it apart in front when that name holds several
    recordings (`group_videos`); "id": the ``video_id`` as written; "loose": None when the file's images without a
    video are one group, else a label (drone, folder, meta layout).
    images: indices into the file's image list, in file order.
    """

    kind: str
    order: tuple
    name: Any
    images: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class VideoGrouping:
    """The videos of a file (source groups by order, then id groups in file order, then loose groups by order) and
    one line per split made or doubt left (empty for a file whose every video name is one drone's one recording)."""

    groups: tuple[VideoGroup, ...]
    notices: tuple[str, ...]

    def of_images(self, n_images: int) -> list[VideoGroup]:
        """The group of each of the file's n_images images, by index."""
        out: list[VideoGroup | None] = [None] * n_images
        for group in self.groups:
            for i in group.images:
                out[i] = group
        assert all(g is not None for g in out), "every image is in one video"
        return out  # type: ignore[return-value]


def meta_object(value: Any) -> Mapping[str, Any] | None:
    """An image's ``meta`` as an object: as it is, or decoded from JSON text (a CSV-minded export writes it so);
    None for anything else (no meta, or not one)."""
    if isinstance(value, str) and value.strip().startswith("{"):
        try:
            value = json.loads(value)
        except json.JSONDecodeError:
            return None
    return value if isinstance(value, Mapping) else None


def own_video_ids(groups: Mapping[K, Sequence[Mapping[str, Any]]]) -> dict[K, int]:
    """The file's own ``video_id`` of each group of images (a ``source`` video) whose images all carry one integer id
    that no other group carries (DESIGN 6's layout with v2's ``source`` kept); groups without one are absent."""
    claims: dict[int, list[K]] = defaultdict(list)
    for key, group in groups.items():
        ids = [im.get("video_id") for im in group]  # not a set: an id written as a list is unhashable
        vid = ids[0] if ids else None
        if isinstance(vid, int) and not isinstance(vid, bool) and all(v == vid for v in ids):
            claims[vid].append(key)
    return {keys[0]: vid for vid, keys in claims.items() if len(keys) == 1}


def time_gap_s(times: ArrayLike) -> float:
    """The clock jump that ends a flight among sorted times: TIME_GAP_S, or TIME_GAP_STEPS median positive steps when
    the images are sparser (one a minute)."""
    steps = np.diff(np.asarray(times, dtype=np.float64))
    median = float(np.median(steps[steps > 0])) if (steps > 0).any() else 0.0
    return max(TIME_GAP_S, TIME_GAP_STEPS * median)


def source_of(image: Mapping[str, Any]) -> Mapping[str, Any]:
    src = image.get("source")
    return src if isinstance(src, Mapping) else {}


def _text(value: Any) -> str:
    return value.strip() if isinstance(value, str) else ""


def _frame_no(image: Mapping[str, Any]) -> int | None:
    frame = source_of(image).get("frame_no")
    frame = image.get("frame_index") if frame is None else frame
    return frame if isinstance(frame, int) and not isinstance(frame, bool) else None


def parse_time(text: Any) -> float | None:
    if not isinstance(text, str) or not text.strip():
        return None
    try:
        t = parse_datetime(text)
    except ValueError:
        return None
    return t if math.isfinite(t) else None


def _meta_time(image: Mapping[str, Any]) -> float | None:
    meta = meta_object(image.get("meta"))
    if meta is None:
        return None
    texts = [meta.get("date_time")] + [v for k, v in meta.items() if isinstance(k, str)
                                       and k.lower().startswith("datetime")]
    return next((t for t in map(parse_time, texts) if t is not None), None)


def image_time(image: Mapping[str, Any]) -> float | None:
    """An image's time: its own ``date_time``, else its meta's stamp; None when neither parses."""
    own = parse_time(image.get("date_time"))
    return own if own is not None else _meta_time(image)


def _one_clock(images: Sequence[Mapping[str, Any]]) -> list[float] | None:
    """Every image's own ``date_time``, else (when none has one) every meta's stamp; None without one clock for all
    (a meta's UTC stamp beside another frame's local clock would mix two clocks)."""
    own = [parse_time(im.get("date_time")) for im in images]
    if all(t is not None for t in own):
        return own  # type: ignore[return-value]
    if all(t is None for t in own):
        meta = [_meta_time(im) for im in images]
        if all(t is not None for t in meta):
            return meta  # type: ignore[return-value]
    return None


def _meta_layout(image: Mapping[str, Any]) -> str:
    """The layout of an image's meta, which tells drones apart when nothing else does: "gps" (SeaDronesSee's
    ``gps_latitude`` + letter ref), "gps-signed" (a ref holding the signed coordinate: a fixed-wing of the same public
    files), "flightlog" (v2's ``latitude``, ...); "" without a meta position (no meta: it tells nothing)."""
    meta = meta_object(image.get("meta"))
    if meta is None:
        return ""
    keys = {k.strip().lower().split("(")[0].strip() for k in meta if isinstance(k, str)}
    if any(k.startswith("gps_") for k in keys):
        ref = meta.get("gps_latitude_ref")
        signed = isinstance(ref, (int, float)) and not isinstance(ref, bool)
        if isinstance(ref, str):
            try:
                float(ref)
                signed = True
            except ValueError:
                signed = False
        return "gps-signed" if signed else "gps"
    return "flightlog" if keys & {"lat", "latitude"} else ""


def _start_label(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y%m%dT%H%M%S")


def _recordings(images: Sequence[Mapping[str, Any]], members: list[int]) -> tuple[list[tuple[list[int], float]], int]:
    """One (drone, video, folder)'s images as recordings: in time order, cut where the clock jumps (`time_gap_s`) and
    the frame numbers start again (DJI names restart on every card and day). Returns the recordings (members in file
    order, start time) when there are several, [] otherwise, and how many frame numbers repeat within a recording on
    frames the clock does not tell apart (no clock for all, or stamps more than TIME_GAP_S apart)."""
    frames = [_frame_no(images[i]) for i in members]
    clock = _one_clock([images[i] for i in members])
    parts = [list(range(len(members)))]
    if clock is not None:
        ranked = sorted(range(len(members)), key=lambda k: (clock[k], k))
        gap = time_gap_s([clock[k] for k in ranked])
        parts, top = [[ranked[0]]], -1
        for a, b in zip(ranked, ranked[1:], strict=False):
            before = frames[a]
            top = max(top, -1 if before is None else before)
            after = frames[b]
            if clock[b] - clock[a] > gap and after is not None and after <= top:
                parts.append([])
                top = -1
            parts[-1].append(b)
    repeated = 0
    for part in parts:
        seen: dict[int, list[float]] = defaultdict(list)
        for k in part:
            if frames[k] is not None:
                seen[frames[k]].append(math.nan if clock is None else clock[k])  # type: ignore[index]
        repeated += sum(len(ts) - 1 for ts in seen.values()
                        if len(ts) > 1 and not (max(ts) - min(ts) <= TIME_GAP_S))
    if len(parts) == 1:
        return [], repeated
    assert clock is not None
    return [([members[k] for k in sorted(part)], clock[part[0]]) for part in parts], repeated


def _unique(names: list[str], taken: set[str]) -> list[str]:
    """Names made unique against `taken` and each other with _2, _3, ... (a made-up name meeting a real one)."""
    out = []
    for name in names:
        candidate, n = name, 2
        while candidate in taken:
            candidate, n = f"{name}_{n}", n + 1
        taken.add(candidate)
        out.append(candidate)
    return out


def _source_groups(images: Sequence[Mapping[str, Any]], indices: list[int], notices: list[str]) -> list[VideoGroup]:
    """Images with a ``source.video``: one group per (drone, video, folder) and recording, named (`group_videos`)."""
    by_key: dict[tuple[str, str, str], list[int]] = defaultdict(list)
    for i in indices:
        src = source_of(images[i])
        by_key[(_text(src.get("drone")), _text(src.get("video")), _text(src.get("folder_name")))].append(i)
    per_video: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for drone, video, folder in sorted(by_key):
        per_video[video].append((drone, folder))
    made: list[tuple[tuple, list[int], str]] = []  # (order, members, name with a prefix or "" for the name as written)
    why: dict[str, list[str]] = defaultdict(list)
    for video, keys in per_video.items():
        drones = sorted({d for d, _ in keys})
        if len(drones) > 1:
            why[video].append(f"{len(drones)} drones ({', '.join(d or '(none)' for d in drones)})")
        for drone, folder in keys:
            prefix = f"{drone}_" if len(drones) > 1 and drone else ""
            folders = sorted(f for d, f in keys if d == drone)
            if len(folders) > 1:
                prefix += f"{folder}_" if folder else ""
                if folder == folders[0]:
                    why[video].append(f"{len(folders)} folders{f' of drone {drone}' if drone else ''} "
                                      f"({', '.join(f or '(none)' for f in folders)})")
            recordings, repeated = _recordings(images, by_key[(drone, video, folder)])
            what = f"video {video!r}" + (f" of drone {drone}" if drone else "") + (f" in {folder}" if folder else "")
            if recordings:
                why[video].append(f"{len(recordings)} recordings" + (f" of drone {drone}" if drone else "")
                                  + (f" in folder {folder}" if folder else "")
                                  + " (the frame numbers start again after a pause)")
            if repeated:
                notices.append(f"{what}: {repeated} frame number(s) repeat on frames whose clock does not tell "
                               "recordings apart: kept as one video")
            for k, (members, start) in enumerate(recordings or [(by_key[(drone, video, folder)], math.nan)]):
                stamp = f"{_start_label(start)}_" if recordings else ""
                made.append(((drone, video, folder, k), members, f"{stamp}{prefix}{video}" if stamp or prefix else ""))
    plain = {order[1] for order, _, name in made if not name}
    invented = iter(_unique([name for _, _, name in made if name], plain))
    groups = [VideoGroup("source", order, next(invented) if name else order[1], tuple(members))
              for order, members, name in made]
    for video, reasons in why.items():
        names = [g.name for g in groups if g.order[1] == video]
        notices.append(f"video name {video!r} holds " + "; ".join(reasons) + f": read as {len(names)} videos, "
                       + ", ".join(names))
    return sorted(groups, key=lambda g: g.order)


def _loose_groups(images: Sequence[Mapping[str, Any]], indices: list[int], taken: set[str],
                  notices: list[str]) -> list[VideoGroup]:
    """Images with neither ``source.video`` nor ``video_id``: per drone, then folder; images with no drone per meta
    layout (a meta without a position joins the only layout there is)."""
    keys: dict[int, tuple[str, str, str]] = {}
    for i in indices:
        src = source_of(images[i])
        drone, folder = _text(src.get("drone")), _text(src.get("folder_name"))
        keys[i] = (drone, folder, "" if drone else _meta_layout(images[i]))
    for drone, folder in {(d, f) for d, f, _ in keys.values() if not d}:
        layouts = {lay for d, f, lay in keys.values() if (d, f) == (drone, folder) and lay}
        if len(layouts) == 1:
            (only,) = layouts
            keys.update({i: (d, f, only) for i, (d, f, lay) in keys.items() if (d, f, lay) == (drone, folder, "")})
    by_key: dict[tuple[str, str, str], list[int]] = defaultdict(list)
    for i in indices:
        by_key[keys[i]].append(i)
    if len(by_key) <= 1:
        return [VideoGroup("loose", key, None, tuple(members)) for key, members in by_key.items()]
    drones = {d for d, _, _ in by_key}
    labels = []
    for drone, folder, layout in sorted(by_key):
        parts = [drone or "no-drone"] if len(drones) > 1 else []
        if len({f for d, f, _ in by_key if d == drone}) > 1:
            parts.append(folder or "no-folder")
        if len({lay for d, f, lay in by_key if (d, f) == (drone, folder)}) > 1:
            parts.append(f"meta-{layout or 'none'}")
        labels.append("_".join(parts))
    names = _unique(labels, taken)
    notices.append(f"{len(indices)} images without a video (no source.video, no video_id) are of {len(by_key)} "
                   "drones or meta layouts: read apart as " + ", ".join(
                       f"{name} ({len(by_key[key])} images)" for name, key in zip(names, sorted(by_key), strict=True)))
    return [VideoGroup("loose", key, name, tuple(by_key[key]))
            for name, key in zip(names, sorted(by_key), strict=True)]


def group_videos(images: Sequence[Mapping[str, Any]]) -> VideoGrouping:
    """The videos of a SeaDronesSee COCO file's images (dicts; other entries are left out).

    - ``source.video`` (a non-blank string, stripped): one video per (``source.drone``, video, ``source.folder_name``)
      and per recording (`_recordings`: frame numbers starting again after a pause). A name that is one drone's one
      recording stays as written; otherwise it gets in front, joined by ``_``, the drone when several drones write
      it, the folder when one drone has it in several folders, the recording's start (``20200825T141921``, its first
      frame's clock) when it holds several: ``mavic_DJI_0001.MP4``, ``20200826T101500_DJI_0001.MP4``; a made-up name
      meeting another gets ``_2``, ...
    - else ``video_id`` as written (one video per value).
    - else per ``source.drone``, then ``source.folder_name``; images without a drone per meta layout (`_meta_layout`).
      These have no name when they are one group (the dataset reader numbers them), else a label:
      ``mavic``, ``fixedwing``, ``no-drone_meta-gps-signed``, ...
    Every image is in exactly one group; `VideoGrouping.notices` says what was split and why.
    """
    notices: list[str] = []
    source, by_id, loose = [], defaultdict(list), []
    for i, im in enumerate(images):
        if not isinstance(im, Mapping):
            continue
        if _text(source_of(im).get("video")):
            source.append(i)
        elif im.get("video_id") is not None:
            by_id[repr(im.get("video_id"))].append(i)
        else:
            loose.append(i)
    groups = _source_groups(images, source, notices)
    groups += [VideoGroup("id", (), images[members[0]].get("video_id"), tuple(members)) for members in by_id.values()]
    groups += _loose_groups(images, loose, {g.name for g in groups if g.kind == "source"}, notices)
    for key, members in by_id.items():
        drones = sorted({_text(source_of(images[i]).get("drone")) for i in members} - {""})
        if len(drones) > 1:
            notices.append(f"video_id {key} holds images of drones {', '.join(drones)}: kept as one video (the file's "
                           "own id)")
    return VideoGrouping(tuple(groups), tuple(notices))

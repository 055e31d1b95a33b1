"""One zone for the stamps of one video of a SeaDronesSee COCO file.

A file written by several tools (or merged from several exports) can give some frames of one video a ``date_time``
with its zone (``2020-08-25T14:19:21.6+02:00``) and the others without (``2020-08-25T14:19:21.6``). Read as written,
the naive ones are taken as UTC: the video's clock jumps by the zone's offset between frames, it is cut in two
recordings and the re-timing stages see two clocks.

`harmonise_zones` measures, per video and per field (the image's own ``date_time``, its meta's ``date_time``), the
zone the naive stamps were written in: the offset that puts them on the zoned stamps' line (time against frame
number), or, without frame numbers, between the two groups' medians. It acts only on evidence: the offset a whole
number of quarter hours within MAX_ZONE_ERROR_S, MIN_AGREEING of the naive stamps on it within MAX_SPREAD_S, a
zone within +-14 h other than UTC itself; else the stamps stay as written and a notice says so.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from shared.telemetry.dates import DATETIME_RE, parse_datetime
from shared.telemetry.seadronessee_videos import meta_object, source_of

__all__ = ["MAX_SPREAD_S", "MAX_ZONE_ERROR_S", "MIN_AGREEING", "harmonise_zones"]

#: How far the measured offset may lie from a whole number of quarter hours (s): whole-second stamps and a frame
#: clock that drifts a little stay well inside; a wrong frame number line does not.
MAX_ZONE_ERROR_S = 120.0
#: The naive stamps agree on one zone when MIN_AGREEING of them lie within MAX_SPREAD_S of the measured offset.
MAX_SPREAD_S = 60.0
MIN_AGREEING = 0.8
_QUARTER_HOUR_S = 900.0
_MAX_ZONE_S = 14 * 3600.0


def _stamp(text: Any) -> tuple[float, bool] | None:
    """(epoch s, read as UTC when naive; whether the text names its zone), or None for no readable stamp."""
    if not isinstance(text, str):
        return None
    match = DATETIME_RE.fullmatch(text.strip())
    if match is None:
        return None
    try:
        t = parse_datetime(text)
    except ValueError:
        return None
    return (t, match["tz"] is not None) if np.isfinite(t) else None


def _zone_text(offset_s: float) -> str:
    minutes = int(round(abs(offset_s) / 60.0))
    return f"{'-' if offset_s < 0 else '+'}{minutes // 60:02d}:{minutes % 60:02d}"


def _frame_no(image: Mapping[str, Any]) -> float | None:
    frame = source_of(image).get("frame_no")
    frame = image.get("frame_index") if frame is None else frame
    if isinstance(frame, bool) or not isinstance(frame, (int, float, str)):
        return None
    try:
        number = float(frame)
    except (ValueError, OverflowError):  # OverflowError: a JSON integer beyond float's range
        return None
    return number if np.isfinite(number) else None


def _video_key(image: Mapping[str, Any]) -> tuple:
    src = source_of(image)
    video = src.get("video")
    if isinstance(video, str) and video.strip():
        return ("source", str(src.get("drone", "")).strip(), video.strip(), str(src.get("folder_name", "")).strip())
    if image.get("video_id") is not None:
        return ("id", repr(image.get("video_id")))
    return ("loose", str(src.get("drone", "")).strip(), str(src.get("folder_name", "")).strip())


def _measured_zone(naive: list[tuple[float, float | None]], zoned: list[tuple[float, float | None]]
                   ) -> tuple[float | None, str]:
    """The zone (s east of UTC) the naive stamps (time read as UTC, frame number) were written in, from the zoned ones
    (UTC time, frame number); (None, why not) without evidence."""
    t_naive = np.array([t for t, _ in naive])
    t_zoned = np.array([t for t, _ in zoned])
    frames_zoned = [f for _, f in zoned]
    frames_naive = [f for _, f in naive]
    lined = (all(f is not None for f in frames_zoned + frames_naive) and len(set(frames_zoned)) >= 2)
    if lined:
        slope, intercept = np.polyfit(np.array(frames_zoned, dtype=np.float64), t_zoned, 1)
        if not slope > 0.0:
            return None, "the zoned stamps do not go on with the frame numbers"
        diffs = t_naive - (slope * np.array(frames_naive, dtype=np.float64) + intercept)
        how = "by frame number"
    else:
        diffs = t_naive - float(np.median(t_zoned))
        span = max(float(np.ptp(t_naive)), float(np.ptp(t_zoned)))
        if abs(float(np.median(diffs))) < 2.0 * span + MAX_ZONE_ERROR_S:
            return None, "without frame numbers the two groups of stamps are not told apart by their times"
        how = "by their times (no frame numbers)"
    offset = float(np.median(diffs))
    agree = float(np.mean(np.abs(diffs - offset) <= MAX_SPREAD_S))
    zone = round(offset / _QUARTER_HOUR_S) * _QUARTER_HOUR_S
    if lined and agree < MIN_AGREEING:
        return None, f"they do not agree on one offset ({100 * agree:.0f} % within {MAX_SPREAD_S:.0f} s of it)"
    if abs(offset - zone) > MAX_ZONE_ERROR_S or abs(zone) > _MAX_ZONE_S:
        return None, f"their offset from the zoned stamps, {offset:.0f} s, is no time zone"
    return zone, how


def _harmonise_field(images: list[dict], members: list[int], get: Callable[[Mapping[str, Any]], Any],
                     put: Callable[[dict, str], dict], what: str, notices: list[str]) -> None:
    naive: list[tuple[int, float, float | None]] = []
    zoned: list[tuple[int, float, float | None]] = []
    for i in members:
        stamp = _stamp(get(images[i]))
        if stamp is None:
            continue
        (zoned if stamp[1] else naive).append((i, stamp[0], _frame_no(images[i])))
    if not naive or not zoned:
        return
    zone, how = _measured_zone([(t, f) for _, t, f in naive], [(t, f) for _, t, f in zoned])
    first = get(images[naive[0][0]])
    if zone is None:
        notices.append(f"{what}: {len(naive)} of {len(naive) + len(zoned)} stamps have no time zone beside zoned "
                       f"ones (first: {first.strip()!r}); left as written (naive read as UTC): {how}")
        return
    if zone == 0.0:
        return  # the naive stamps are UTC already: one clock as written
    suffix = _zone_text(zone)
    for i, _, _ in naive:
        images[i] = put(images[i], get(images[i]).strip() + suffix)
    notices.append(f"{what}: {len(naive)} of {len(naive) + len(zoned)} stamps have no time zone beside zoned ones "
                   f"(first: {first.strip()!r}); read at {suffix}, measured {how}")


def _put_own(image: dict, text: str) -> dict:
    return {**image, "date_time": text}


def _put_meta(image: dict, text: str) -> dict:
    return {**image, "meta": {**(meta_object(image.get("meta")) or {}), "date_time": text}}


def _meta_date(image: Mapping[str, Any]) -> Any:
    meta = meta_object(image.get("meta"))
    return None if meta is None else meta.get("date_time")


def harmonise_zones(images: Sequence[Any]) -> tuple[list[Any], list[str]]:
    """The images (a new list; an image whose stamp gained its zone is a new dict, the others are the same objects)
    with, per video (``source`` drone, video and folder; else ``video_id``; else drone and folder), the naive
    ``date_time`` stamps written in the zone measured from the video's zoned ones (module docstring), and one notice
    per video and field that mixes the two (what was done, or why not)."""
    out = list(images)
    by_video: dict[tuple, list[int]] = defaultdict(list)
    for i, image in enumerate(out):
        if isinstance(image, Mapping):
            by_video[_video_key(image)].append(i)
    notices: list[str] = []
    for key, members in by_video.items():
        name = key[2] if key[0] == "source" else (f"video_id {key[1]}" if key[0] == "id" else "images without video")
        _harmonise_field(out, members, lambda im: im.get("date_time"), _put_own, f"video {name}: date_time", notices)
        _harmonise_field(out, members, _meta_date, _put_meta, f"video {name}: meta date_time", notices)
    return out, notices

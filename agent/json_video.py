"""A SeaDronesSee COCO file as the telemetry of its video (``--telemetry FLIGHT.json`` beside ``FLIGHT.MP4``).

Such a file says which video frame each meta belongs to (``source.frame_no``, or ``frame_index``), and real ones
start mid-video and keep every 15th frame (the dev file's ``DJI_0032`` starts at frame 5415): taking the first
image for video time 0, as for a log, gave every frame the pose of three minutes later. Its stamps are the flight
log's (``datetime(utc)`` at whole seconds, one sample repeated on the frames until the next: sample and hold). So:

- the video is the one named like the video file (a file with several videos; the only one otherwise);
- a sample repeated on later frames (the same stamp second and the same values) counts once, at the frame where it
  first appears (held, it became a staircase lagging up to a sample interval);
- each sample is put at its frame's time on the video clock, ``offset + frame / fps``, the offset being the median
  of ``stamp - frame / fps`` over the samples (the records keep UTC, to within the stamps' rounding), so every frame
  gets the pose of its own place in the video whatever the stamps' zone or rounding.

Records without frame numbers (or a video without a frame rate), and frame numbers that do not follow the stamps at
the video's rate (their stamp - frame / fps spreading over more than `MAX_SPREAD_S`: image indices of a sampled
sequence, another video's frames) are left as they are, and a line says which.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from shared.telemetry import Telemetry
from shared.telemetry.seadronessee import parse_seadronessee_coco
from shared.telemetry.seadronessee_videos import group_videos, own_video_ids
from shared.telemetry.seadronessee_zones import harmonise_zones
from shared.telemetry.text import read_text

__all__ = ["MAX_SPREAD_S", "on_video_frames", "read_video_json"]

#: The inter-quartile range of stamp - frame / fps above which the frame numbers are not the video's (s).
MAX_SPREAD_S = 2.0

log = logging.getLogger("agent.sources")  # the video source's messages, under its name


def read_video_json(path: str | Path, video: str | Path | None) -> list[Telemetry]:
    """The records of the video `video` in the SeaDronesSee COCO file `path`: the file's only video, else the one
    whose name (`group_videos`': ``source.video``, with the drone in front when two drones wrote it, ...; or the
    ``videos`` entry of its ``video_id``) has the video file's stem. ValueError naming the file's videos when none or
    several match."""
    try:
        coco = json.loads(read_text(path))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
    images = coco.get("images") if isinstance(coco, Mapping) else None
    if not isinstance(images, list) or not all(isinstance(im, Mapping) for im in images):
        return parse_seadronessee_coco(coco, source=str(path))  # its own error for a file that is no COCO
    images = harmonise_zones(images)[0]  # as parse_seadronessee_coco reads them (its notices are logged there)
    groups: dict[str, list[Mapping[str, Any]]] = {}
    ids: dict[str, Any] = {}
    for group in group_videos(images).groups:
        groups.setdefault(repr(group.name), []).extend(images[i] for i in group.images)
        ids[repr(group.name)] = group.name
    if len(ids) <= 1 or video is None:
        return parse_seadronessee_coco(coco, source=str(path))
    names = {v["id"]: v.get("name") for v in coco.get("videos") or [] if isinstance(v, Mapping) and "id" in v}
    stem = Path(str(video)).stem.lower()
    # a video's names: its own (group_videos'), and the `videos` entry of the video_id its images carry
    # (only where all of a video's images carry one id that no other video claims, as agent.dataset decides)
    listed = {key: {Path(str(_name(names, ids[key]))).stem.lower()} for key in groups}
    for key, vid_id in own_video_ids(groups).items():
        if isinstance(name := _name(names, vid_id, None), str):
            listed[key].add(Path(name).stem.lower())
    matching = [vid for key, vid in ids.items() if stem in listed[key]]
    if len(matching) != 1:
        shown = ", ".join(sorted({str(_name(names, v)) for v in ids.values()})[:12])
        raise ValueError(f"telemetry {path} holds {len(ids)} videos ({shown}) and "
                         f"{'none' if not matching else 'several'} named like the video {Path(str(video)).name}: "
                         "name the video file as its entry in the JSON (e.g. DJI_0032.MP4 for source.video "
                         "DJI_0032.MP4, mavic_DJI_0001.MP4 where two drones wrote DJI_0001.MP4), or give a JSON of "
                         "that video alone")
    log.info("telemetry %s: video %s of %d (named like %s)", path, _name(names, matching[0]), len(ids),
             Path(str(video)).name)
    return parse_seadronessee_coco(coco, video_id=matching[0], source=str(path))


_OWN = object()


def _name(names: Mapping[Any, Any], video: Any, default: Any = _OWN) -> Any:
    """The ``videos`` entry's name of a video id, else `default` (the id itself): an id the file wrote as a list or
    an object (``"video_id": [1, 2]``) names no entry (``names.get`` raised TypeError: unhashable)."""
    try:
        return names.get(video, video if default is _OWN else default)
    except TypeError:
        return video if default is _OWN else default


def _values(r: Telemetry) -> tuple[Any, ...]:
    return (r.lat, r.lon, r.height_m, r.heading_deg, r.pitch_deg, r.roll_deg)


def on_video_frames(records: Sequence[Telemetry], fps: float | None, telemetry: str | Path
                    ) -> tuple[list[Telemetry], float | None]:
    """(records put on the video clock by their frame numbers, the telemetry time of video time 0), or (the records
    as they are, None) when a record has no frame number or the video no frame rate (module docstring)."""
    if not records or fps is None or not (math.isfinite(fps) and fps > 0.0) or any(r.frame is None for r in records):
        missing = sum(r.frame is None for r in records)
        if records and missing:
            log.info("telemetry %s: %d of %d records have no frame number: video time 0 is the first record's time",
                     telemetry, missing, len(records))
        return list(records), None
    ordered = sorted(records, key=lambda r: (r.frame, r.t))
    samples: list[Telemetry] = []
    for r in ordered:  # sample and hold: the same values in the same stamp second are one sample, first seen here
        if samples and math.floor(samples[-1].t) == math.floor(r.t) and _values(samples[-1]) == _values(r):
            continue
        if samples and samples[-1].frame == r.frame:
            continue  # two images of one frame: the first
        samples.append(r)
    frame_of = [float(r.frame) for r in samples]  # type: ignore[arg-type]
    gaps = sorted(r.t - f / fps for r, f in zip(samples, frame_of, strict=True))
    offset = statistics.median(gaps)
    # the frame numbers must follow the stamps at the video's rate (whole-second stamps and held samples scatter
    # them by about a second): image indices of a sampled sequence, or another video's frames, do not
    spread = gaps[(3 * len(gaps)) // 4] - gaps[len(gaps) // 4]
    if spread > MAX_SPREAD_S:
        log.warning("telemetry %s: its frame numbers do not follow its stamps at the video's %.3g frames/s (stamp - "
                    "frame / fps spreads over %.1f s): not used; video time 0 is the first record's time (pass "
                    "--telemetry-offset-s for another)", telemetry, fps, spread)
        return list(records), None
    out = [dataclasses.replace(r, t=offset + f / fps) for r, f in zip(samples, frame_of, strict=True)]
    held = len(records) - len(samples)
    log.info("telemetry %s: %d samples placed at their video frames (%d repeats of a held sample dropped); video "
             "time 0 is telemetry time %.3f", telemetry, len(samples), held, offset)
    return out, offset

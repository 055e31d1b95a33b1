"""SeaDronesSee ``meta`` dicts and COCO files: reading them into records and writing records back as meta."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from shared.telemetry.dates import format_datetime, parse_datetime
from shared.telemetry.record import PITCH_TOLERANCE_DEG, Telemetry, clamp_pitch
from shared.telemetry.text import read_text

logger = logging.getLogger(__name__)

SEADRONESSEE_META_FIELDS = (
    "gps_latitude",
    "gps_latitude_ref",
    "gps_longitude",
    "gps_longitude_ref",
    "altitude",
    "gimbal_pitch",
    "compass_heading",
    "gimbal_heading",
    "speed",
    "xspeed",
    "yspeed",
    "zspeed",
    "date_time",
)


def _meta_number(meta: Mapping[str, Any], name: str, *, required: bool) -> float | None:
    value = meta.get(name)
    if value is None or (isinstance(value, str) and not value.strip()):
        if required:
            raise ValueError(f"SeaDronesSee meta field {name!r} is missing")
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int, float, np.integer, np.floating)):
        raise ValueError(f"SeaDronesSee meta field {name!r}={value!r} is not a number")
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"SeaDronesSee meta field {name!r}={value!r} is not a number") from None
    if not math.isfinite(number):
        raise ValueError(f"SeaDronesSee meta field {name!r}={value!r} is not finite")
    return number


def _meta_coordinate(meta: Mapping[str, Any], name: str, refs: tuple[str, str], limit_deg: float) -> float:
    value = _meta_number(meta, name, required=True)
    assert value is not None
    ref_name = f"{name}_ref"
    ref = meta.get(ref_name)
    if not isinstance(ref, str) or not ref.strip():
        raise ValueError(f"SeaDronesSee meta field {ref_name!r} is missing (expected {refs[0]!r} or {refs[1]!r})")
    letter = ref.strip().upper()
    positive, negative = refs
    if letter not in (positive, negative, {"N": "NORTH", "E": "EAST"}[positive], {"S": "SOUTH", "W": "WEST"}[negative]):
        raise ValueError(f"SeaDronesSee meta field {ref_name!r}={ref!r} is not {positive!r} or {negative!r}")
    if abs(value) > limit_deg:
        raise ValueError(f"SeaDronesSee meta field {name!r}={value!r} is outside +-{limit_deg:g} degrees")
    if letter[0] == negative:
        return -abs(value)
    if value < 0.0:
        raise ValueError(f"SeaDronesSee meta field {name!r}={value!r} is negative but {ref_name!r} is {ref!r}")
    return value


def from_seadronessee_meta(
    meta: Mapping[str, Any] | None, frame: int | None = None, *, utc_offset_s: float = 0.0
) -> Telemetry | None:
    """Build a record from a SeaDronesSee image ``meta`` dict.

    Parameters
    ----------
    meta : dict or None
        SeaDronesSee fields (numbers or numeric strings): ``gps_latitude`` + ``gps_latitude_ref`` ('N'/'S'),
        ``gps_longitude`` + ``gps_longitude_ref`` ('E'/'W'), ``altitude`` (height above the water, m),
        ``gimbal_pitch`` (positive depression), ``gimbal_heading`` (camera yaw; the aircraft's
        ``compass_heading`` is deliberately not used), ``speed``, ``xspeed`` (north) and ``yspeed`` (east)
        in m/s as DJI logs them, ``date_time`` (e.g. ``2020-08-24T15:45:20``).
    frame : int, optional
        The image's frame index, stored in `Telemetry.frame`.
    utc_offset_s : float
        Offset of a naive ``date_time`` from UTC (default: it is UTC).

    Returns
    -------
    Telemetry or None
        None when ``meta`` is None (frames without metadata get no memory-map help, never an error).
        Missing ``gimbal_pitch`` / ``gimbal_heading`` / speeds give None fields.

    Raises
    ------
    ValueError
        Naming the field, when a required field (position, refs, altitude, date_time) is missing or any
        field is not a finite number in range.
    """
    if meta is None:
        return None
    if not isinstance(meta, Mapping):
        raise ValueError(f"SeaDronesSee meta must be a dict or None, got {type(meta).__name__}")
    lat = _meta_coordinate(meta, "gps_latitude", ("N", "S"), 90.0)
    lon = _meta_coordinate(meta, "gps_longitude", ("E", "W"), 180.0)
    height_m = _meta_number(meta, "altitude", required=True)
    pitch_raw = _meta_number(meta, "gimbal_pitch", required=False)
    pitch = None
    if pitch_raw is not None:
        pitch = clamp_pitch(pitch_raw, PITCH_TOLERANCE_DEG, f"SeaDronesSee meta field 'gimbal_pitch'={pitch_raw!r}")
    heading = _meta_number(meta, "gimbal_heading", required=False)
    speed = _meta_number(meta, "speed", required=False)
    if speed is not None and speed < 0.0:
        raise ValueError(f"SeaDronesSee meta field 'speed'={speed!r} is negative")
    north = _meta_number(meta, "xspeed", required=False)
    east = _meta_number(meta, "yspeed", required=False)
    date_time = meta.get("date_time")
    if not isinstance(date_time, str) or not date_time.strip():
        raise ValueError(f"SeaDronesSee meta field 'date_time' is missing or not a string: {date_time!r}")
    try:
        t = parse_datetime(date_time, utc_offset_s=utc_offset_s)
    except ValueError as err:
        raise ValueError(f"SeaDronesSee meta field 'date_time': {err}") from None
    assert height_m is not None
    return Telemetry(
        t=t,
        lat=lat,
        lon=lon,
        height_m=height_m,
        pitch_deg=pitch,
        heading_deg=heading,
        speed_mps=speed,
        vel_en_mps=None if north is None or east is None else (east, north),
        frame=frame,
    )


def to_seadronessee_meta(
    tel: Telemetry, *, compass_heading_deg: float | None = None, zspeed_mps: float | None = None
) -> dict[str, Any]:
    """Write a record as a SeaDronesSee ``meta`` dict (the inverse of `from_seadronessee_meta`).

    Parameters
    ----------
    tel : Telemetry
    compass_heading_deg, zspeed_mps : float, optional
        The aircraft heading and vertical speed (down positive), which `Telemetry` does not model.

    Returns
    -------
    dict
        All of `SEADRONESSEE_META_FIELDS`; unknown values are None (JSON null), never a made-up 0.
        ``date_time`` is ISO 8601 UTC with microseconds, e.g. ``2020-08-24T15:45:20.250000``.
    """
    vel = tel.vel_en_mps
    return {
        "gps_latitude": abs(tel.lat),
        "gps_latitude_ref": "S" if tel.lat < 0.0 else "N",
        "gps_longitude": abs(tel.lon),
        "gps_longitude_ref": "W" if tel.lon < 0.0 else "E",
        "altitude": tel.height_m,
        "gimbal_pitch": tel.pitch_deg,
        "compass_heading": compass_heading_deg,
        "gimbal_heading": tel.heading_deg,
        "speed": tel.speed_mps,
        "xspeed": None if vel is None else vel[1],
        "yspeed": None if vel is None else vel[0],
        "zspeed": zspeed_mps,
        "date_time": format_datetime(tel.t),
    }


def parse_seadronessee_coco(
    coco: Mapping[str, Any], *, video_id: Any = None, source: str = "<json>", utc_offset_s: float = 0.0
) -> list[Telemetry]:
    """Records of one video of a SeaDronesSee COCO file, ordered by ``frame_index``.

    Parameters
    ----------
    coco : dict
        COCO dict whose ``images[i]`` carry ``frame_index``, ``video_id`` and ``meta`` (may be null).
    video_id : optional
        Which video to read; required when the file holds several.
    source : str
        Name used in error messages.

    Returns
    -------
    list of Telemetry
        One per image with non-null meta, ``frame`` = ``frame_index``. Images with null meta are skipped.

    Raises
    ------
    ValueError
        Naming the source and image id on malformed images or meta, when several videos are present and
        ``video_id`` is not given, or when no image has meta.
    """
    images = coco.get("images") if isinstance(coco, Mapping) else None
    if not isinstance(images, list):
        raise ValueError(f"{source}: not a COCO file: no 'images' list")
    for image in images:
        if not isinstance(image, Mapping):
            raise ValueError(f"{source}: images must be objects, got {image!r:.80}")
    videos = sorted({repr(image.get("video_id")) for image in images})
    if video_id is None and len(videos) > 1:
        raise ValueError(f"{source}: holds {len(videos)} videos ({', '.join(videos[:10])}): pass video_id")
    chosen = [image for image in images if video_id is None or image.get("video_id") == video_id]
    records: list[tuple[int, Telemetry]] = []
    skipped = 0
    for image in chosen:
        frame = image.get("frame_index")
        if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            raise ValueError(f"{source}: image id {image.get('id')!r}: frame_index={frame!r} is not an index")
        try:
            tel = from_seadronessee_meta(image.get("meta"), frame=frame, utc_offset_s=utc_offset_s)
        except ValueError as err:
            raise ValueError(f"{source}: image id {image.get('id')!r}: {err}") from None
        if tel is None:
            skipped += 1
            continue
        records.append((frame, tel))
    if skipped:
        logger.info("%s: %d image(s) without meta carry no telemetry", source, skipped)
    if not records:
        raise ValueError(f"{source}: no image with meta" + ("" if video_id is None else f" in video {video_id!r}"))
    records.sort(key=lambda item: item[0])
    return [tel for _, tel in records]


def read_seadronessee_json(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a SeaDronesSee COCO JSON file; keyword arguments as in `parse_seadronessee_coco`."""
    kw.setdefault("source", str(path))
    try:
        coco = json.loads(read_text(path))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
    return parse_seadronessee_coco(coco, **kw)

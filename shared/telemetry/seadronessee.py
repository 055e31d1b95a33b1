"""SeaDronesSee ``meta`` dicts and COCO files: reading them into records and writing records back as meta."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from shared.telemetry.columns import OPTIONAL_FIELDS, UNITS, UnknownUnit, match_column, split_unit, unit_rank
from shared.telemetry.dates import format_datetime, parse_datetime
from shared.telemetry.interpolation import spread_whole_second_stamps
from shared.telemetry.record import PITCH_TOLERANCE_DEG, Telemetry, clamp_pitch
from shared.telemetry.seadronessee_videos import group_videos, meta_object
from shared.telemetry.seadronessee_zones import harmonise_zones
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


class MetaProblem(ValueError):
    """Why a frame's meta gives no telemetry record.

    `reason` is a short class of problem for counting in summaries (e.g. ``"no position"``, ``"bad time"``);
    the message names the field and its value.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


#: Pitch conventions of a meta's gimbal pitch: "depression" (positive below the horizon, SeaDronesSee),
#: "dji" (negative below, DJI logs and AirData exports), "auto" (the SeaDronesSee layout's is a depression;
#: in the flight-log layout a negative reading is DJI's). A reader that sees a whole video decides better
#: (`pitch_convention_of`).
PITCH_CONVENTIONS = ("auto", "depression", "dji")


def _number(value: Any, name: str, what: str, *, required: bool) -> float | None:
    if value is None or (isinstance(value, str) and not value.strip()):
        if required:
            raise MetaProblem(f"no {what}", f"SeaDronesSee meta field {name!r} is missing")
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int, float, np.integer, np.floating)):
        raise MetaProblem(f"bad {what}", f"SeaDronesSee meta field {name!r}={value!r} is not a number")
    try:
        number = float(value)
    except ValueError:
        raise MetaProblem(f"bad {what}", f"SeaDronesSee meta field {name!r}={value!r} is not a number") from None
    except OverflowError:  # a JSON integer beyond float's range (json reads any number of digits)
        number = math.inf
    if not math.isfinite(number):
        raise MetaProblem(f"bad {what}", f"SeaDronesSee meta field {name!r}={value!r} is not finite")
    return number


#: The quantity of each field of the ``gps_latitude`` layout that may name a unit (``altitude(feet)``).
_META_UNITS = {"altitude": "length", "gimbal_pitch": "angle", "gimbal_heading": "angle", "compass_heading": "angle",
               "speed": "speed", "xspeed": "speed", "yspeed": "speed", "zspeed": "speed"}


def _meta_number(meta: Mapping[str, Any], name: str, what: str, *, required: bool) -> float | None:
    """A number of the ``gps_latitude`` layout: ``name`` as written, or (``name`` absent or null) under
    ``name(unit)`` / ``name [unit]`` with the unit's factor to SI (``altitude(feet)``: feet to metres); an unknown
    unit is a MetaProblem."""
    if meta.get(name) is not None or name not in _META_UNITS:
        return _number(meta.get(name), name, what, required=required)
    units = UNITS[_META_UNITS[name]]
    for key in meta:
        if not isinstance(key, str):
            continue
        base, unit = split_unit(key)
        if base != name or key == name:
            continue
        if unit not in units:
            if not required and _META_UNITS[name] == "speed":
                continue  # no pose needs a speed: one in a unit we do not know is left out, not the frame
            raise MetaProblem("bad unit", f"SeaDronesSee meta field {key!r}: unknown unit {unit!r} (accepted: "
                                          f"{', '.join(u for u in units if u)})")
        value = _number(meta[key], key, what, required=required)
        return None if value is None else value * units[unit]
    return _number(None, name, what, required=required)


def _is_number(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, (int, float, np.integer, np.floating)):
        return True
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return False
        return True
    return False


def _meta_coordinate(meta: Mapping[str, Any], name: str, refs: tuple[str, str], limit_deg: float) -> float:
    """A signed coordinate from ``name`` and ``name_ref``.

    The usual layout is a positive number with a hemisphere letter in the ref. Files that mix drones also
    hold a layout where the ref field holds the (signed) coordinate as a number, with or without the letter
    in the other field: whichever of the two is a number is the coordinate, and a letter, when present,
    signs it. Two different numbers are ambiguous and refused.
    """
    ref_name = f"{name}_ref"
    value_raw, ref = meta.get(name), meta.get(ref_name)
    if _is_number(ref):
        ref_number = _number(ref, ref_name, "position", required=True)
        assert ref_number is not None
        if _is_number(value_raw):
            value = _number(value_raw, name, "position", required=True)
            if value is not None and abs(value - ref_number) > 1e-9:
                raise MetaProblem("bad position", f"SeaDronesSee meta fields {name!r}={value_raw!r} and "
                                                  f"{ref_name!r}={ref!r} are two different coordinates")
        value_raw, ref = ref_number, (value_raw if isinstance(value_raw, str) and value_raw.strip() else None)
        if ref is None:  # a bare signed number
            if abs(ref_number) > limit_deg:
                raise MetaProblem("bad position",
                                  f"SeaDronesSee meta field {ref_name!r}={ref_number!r} is outside +-{limit_deg:g} deg")
            return ref_number
    value = _number(value_raw, name, "position", required=True)
    assert value is not None
    if not isinstance(ref, str) or not ref.strip():
        raise MetaProblem("no position", f"SeaDronesSee meta field {ref_name!r} is missing "
                                         f"(expected {refs[0]!r} or {refs[1]!r})")
    letter = ref.strip().upper()
    positive, negative = refs
    if letter not in (positive, negative, {"N": "NORTH", "E": "EAST"}[positive], {"S": "SOUTH", "W": "WEST"}[negative]):
        raise MetaProblem("bad position",
                          f"SeaDronesSee meta field {ref_name!r}={ref!r} is not {positive!r} or {negative!r}")
    if abs(value) > limit_deg:
        raise MetaProblem("bad position",
                          f"SeaDronesSee meta field {name!r}={value!r} is outside +-{limit_deg:g} degrees")
    if letter[0] == negative:
        return -abs(value)
    if value < 0.0:
        raise MetaProblem("bad position",
                          f"SeaDronesSee meta field {name!r}={value!r} is negative but {ref_name!r} is {ref!r}")
    return value


def _pitch(raw: float | None, name: str, convention: str, *, flight_log: bool) -> float | None:
    if raw is None:
        return None
    dji = convention == "dji" or (convention == "auto" and flight_log and raw < 0.0)
    depression = -raw if dji else raw
    try:
        return clamp_pitch(depression, PITCH_TOLERANCE_DEG, f"SeaDronesSee meta field {name!r}={raw!r}")
    except ValueError as err:
        raise MetaProblem("pitch out of range", str(err)) from None


def _time(value: Any, name: str, utc_offset_s: float) -> float:
    if not isinstance(value, str) or not value.strip():
        raise MetaProblem("no time", f"SeaDronesSee meta field {name!r} is missing or not a string: {value!r}")
    try:
        return parse_datetime(value, utc_offset_s=utc_offset_s)
    except ValueError as err:
        raise MetaProblem("bad time", f"SeaDronesSee meta field {name!r}: {err}") from None


#: Flight-log names a meta field may carry per telemetry field (the aircraft's own attitude columns,
#: ``pitch``/``roll``/``yaw``, are not the camera's and are not read from meta).
_FLIGHT_LOG_ALIASES = {
    "datetime": ("date_time", "datetime", "datetime_utc"),
    "lat": ("lat", "latitude"),
    "lon": ("lon", "lng", "longitude"),
    "height": ("height_m", "rel_alt", "height_above_takeoff"),
    "pitch": ("pitch_deg", "gimbal_pitch"),
    "heading": ("heading_deg", "gimbal_heading"),
    "roll": ("roll_deg", "gimbal_roll"),
    "speed": ("speed_mps", "speed"),
    "vel_north": ("vel_north_mps", "xspeed"),
    "vel_east": ("vel_east_mps", "yspeed"),
}


def raw_pitch(meta: Mapping[str, Any] | None) -> float | None:
    """The gimbal pitch a meta dict holds, as written (either layout), or None when absent or not a number."""
    if not isinstance(meta, Mapping):
        return None
    if is_flight_log_meta(meta):
        try:
            found = _flight_log_fields(meta).get("pitch")
        except MetaProblem:
            return None
        value = None if found is None else meta[found[0]]
        try:
            return _number(value, "gimbal_pitch", "pitch", required=False)
        except MetaProblem:
            return None
    try:  # `gimbal_pitch`, or one naming its unit (`gimbal_pitch(degrees)`)
        return _meta_number(meta, "gimbal_pitch", "pitch", required=False)
    except MetaProblem:
        return None


def pitch_convention_of(metas: Iterable[Mapping[str, Any] | None]) -> str:
    """The pitch convention of one video's metas: "dji" when more of its readings are clearly negative
    (below -1 deg) than clearly positive, else "depression" (a camera looks down far more than up)."""
    negative = positive = 0
    for meta in metas:
        value = raw_pitch(meta)
        if value is not None:
            negative += value < -PITCH_TOLERANCE_DEG
            positive += value > PITCH_TOLERANCE_DEG
    return "dji" if negative > positive else "depression"


def compass_heading_of(meta: Mapping[str, Any] | None) -> float | None:
    """The aircraft's compass heading a meta dict holds (``compass_heading``, or with a unit:
    ``compass_heading(degrees)`` in the flight-log layout, ``(rad)``), in degrees in [0, 360), or None when absent,
    not a finite number or in a unit we do not know. Not the camera's heading: a stand-in for a frame without
    ``gimbal_heading`` (on the dev set's flights the two differ by 6.5 deg in the median, 22 deg at most)."""
    if not isinstance(meta, Mapping):
        return None
    for key, value in meta.items():
        if not isinstance(key, str):
            continue
        name, unit = split_unit(key)
        if name != "compass_heading" or unit not in UNITS["angle"]:
            continue
        try:
            heading = _number(value, key, "heading", required=False)
        except ValueError:
            return None
        return None if heading is None else heading * UNITS["angle"][unit] % 360.0
    return None


def is_flight_log_meta(meta: Mapping[str, Any]) -> bool:
    """True for the flight-log layout (``latitude``, ``height_above_takeoff(meter)``, ``datetime(utc)``, ...)
    of SeaDronesSee Object Detection v2 and AirData-style exports; False for the ``gps_latitude`` layout."""
    if any(isinstance(k, str) and k.startswith("gps_") for k in meta):
        return False
    names = {alias for aliases in _FLIGHT_LOG_ALIASES.values() for alias in aliases}
    return any(isinstance(k, str) and k.strip().lower().split("(")[0].strip() in names for k in meta)


def _flight_log_fields(meta: Mapping[str, Any]) -> dict[str, tuple[str, float]]:
    """field -> (meta key, factor to SI) of the flight-log keys present (the earlier alias wins)."""
    found: dict[str, tuple[str, float, tuple[int, int]]] = {}
    for key in meta:
        if not isinstance(key, str):
            continue
        try:
            matched = match_column(key)
        except UnknownUnit as err:
            if err.field in OPTIONAL_FIELDS:
                continue  # no pose needs a speed: one in a unit we do not know is left out, not the frame
            raise MetaProblem("bad unit", f"SeaDronesSee meta field {err}") from None
        if matched is None:
            continue
        fld, alias, scale = matched
        aliases = _FLIGHT_LOG_ALIASES.get(fld, ())
        if alias not in aliases:
            continue
        rank = (aliases.index(alias), unit_rank(fld, key))  # datetime(utc) before datetime(local)
        if fld not in found or rank < found[fld][2]:
            found[fld] = (key, scale, rank)
    return {fld: (key, scale) for fld, (key, scale, _) in found.items()}


def _from_flight_log(meta: Mapping[str, Any], frame: int | None, utc_offset_s: float, pitch_convention: str,
                     t_default: float | None) -> Telemetry:
    fields = _flight_log_fields(meta)

    def number(fld: str, what: str, *, required: bool) -> float | None:
        if fld not in fields:
            if required:
                names = ", ".join(_FLIGHT_LOG_ALIASES[fld])
                raise MetaProblem(f"no {what}", f"SeaDronesSee meta has no {what} (flight-log names: {names})")
            return None
        key, scale = fields[fld]
        value = _number(meta[key], key, what, required=required)
        return None if value is None else value * scale

    lat, lon = number("lat", "position", required=True), number("lon", "position", required=True)
    assert lat is not None and lon is not None
    for value, name, limit in ((lat, "latitude", 90.0), (lon, "longitude", 180.0)):
        if abs(value) > limit:
            raise MetaProblem("bad position", f"SeaDronesSee meta field {name!r}={value!r} is outside +-{limit:g} deg")
    height_m = number("height", "height", required=True)
    pitch = _pitch(number("pitch", "pitch", required=False), fields.get("pitch", ("pitch",))[0], pitch_convention,
                   flight_log=True)
    heading = number("heading", "heading", required=False)
    roll = number("roll", "roll", required=False)
    speed = number("speed", "speed", required=False)
    if speed is not None and speed < 0.0:
        raise MetaProblem("bad speed", f"SeaDronesSee meta field {fields['speed'][0]!r}={speed!r} is negative")
    north, east = number("vel_north", "speed", required=False), number("vel_east", "speed", required=False)
    key = fields["datetime"][0] if "datetime" in fields else None
    if key is not None and meta[key] not in (None, ""):  # a null time is a missing one: the frame's own stands in
        t = _time(meta[key], key, 0.0 if "utc" in key.lower() else utc_offset_s)
    elif t_default is not None:
        t = t_default
    else:
        raise MetaProblem("no time", "SeaDronesSee meta has no time (flight-log name: datetime(utc))")
    return Telemetry(t=t, lat=lat, lon=lon, height_m=height_m, pitch_deg=pitch, heading_deg=heading,
                     roll_deg=roll or 0.0, speed_mps=speed,
                     vel_en_mps=None if north is None or east is None else (east, north), frame=frame)


def from_seadronessee_meta(
    meta: Mapping[str, Any] | None, frame: int | None = None, *, utc_offset_s: float = 0.0,
    pitch_convention: str = "auto", t_default: float | None = None,
) -> Telemetry | None:
    """Build a record from a SeaDronesSee image ``meta`` dict, in either of its layouts.

    Parameters
    ----------
    meta : dict or None
        The SeaDronesSee layout (numbers or numeric strings): ``gps_latitude`` + ``gps_latitude_ref``
        ('N'/'S'), ``gps_longitude`` + ``gps_longitude_ref`` ('E'/'W'), ``altitude`` (height above the water,
        m), ``gimbal_pitch`` (positive depression), ``gimbal_heading`` (camera yaw; the aircraft's
        ``compass_heading`` is not read here: `compass_heading_of`, and agent.dataset lets it stand in for a missing
        gimbal heading), ``speed``, ``xspeed`` (north) and ``yspeed`` (east) in m/s as DJI logs them,
        ``date_time`` (e.g. ``2020-08-24T15:45:20``). A ref that holds the coordinate as a number (a layout of
        other drones in the same files) is read as that coordinate.
        Or the flight-log layout (SeaDronesSee Object Detection v2, AirData names): ``latitude``,
        ``longitude``, ``height_above_takeoff(meter)`` (or ``(feet)``), ``gimbal_pitch(degrees)``,
        ``gimbal_heading(degrees)``, ``speed(m/s)``, ``xspeed(m/s)``, ``yspeed(m/s)``, ``datetime(utc)``
        (units as in `shared.telemetry.csv_table.CSV_COLUMNS`; a time named ``(utc)`` is UTC). Ours beside them:
        ``hfov_deg``, a zoom lens's horizontal field of view at the frame (`uavmm detect` writes it).
    frame : int, optional
        The image's frame index, stored in `Telemetry.frame`.
    utc_offset_s : float
        Offset of a naive time from UTC (default: it is UTC).
    pitch_convention : str
        One of `PITCH_CONVENTIONS`: "auto" (default) reads a negative pitch as DJI's (negative down).
    t_default : float, optional
        The time to use when a flight-log meta has no time of its own (e.g. the frame's clock).

    Returns
    -------
    Telemetry or None
        None when ``meta`` is None (frames without metadata get no memory-map help, never an error).
        Missing gimbal pitch / heading / speeds give None fields.

    Raises
    ------
    MetaProblem
        A ValueError naming the field, when a required field (position, refs, altitude, time) is missing
        or any field is not a finite number in range; its ``reason`` classifies the problem.
    """
    if meta is None:
        return None
    if pitch_convention not in PITCH_CONVENTIONS:
        raise ValueError(f"pitch_convention must be one of {', '.join(PITCH_CONVENTIONS)}, got {pitch_convention!r}")
    if not isinstance(meta, Mapping):
        raise MetaProblem("not a dict", f"SeaDronesSee meta must be a dict or None, got {type(meta).__name__}")
    if is_flight_log_meta(meta):
        try:
            record = _from_flight_log(meta, frame, utc_offset_s, pitch_convention, t_default)
        except MetaProblem:
            raise
        except ValueError as err:  # Telemetry's own range checks
            raise MetaProblem("bad value", f"SeaDronesSee meta: {err}") from None
        _no_fix(record.lat, record.lon)
        return record
    lat = _meta_coordinate(meta, "gps_latitude", ("N", "S"), 90.0)
    lon = _meta_coordinate(meta, "gps_longitude", ("E", "W"), 180.0)
    _no_fix(lat, lon)
    height_m = _meta_number(meta, "altitude", "height", required=True)
    pitch = _pitch(_meta_number(meta, "gimbal_pitch", "pitch", required=False), "gimbal_pitch", pitch_convention,
                   flight_log=False)
    heading = _meta_number(meta, "gimbal_heading", "heading", required=False)
    hfov = _meta_number(meta, "hfov_deg", "field of view", required=False)  # ours: a zoom lens's frame
    speed = _meta_number(meta, "speed", "speed", required=False)
    if speed is not None and speed < 0.0:
        raise MetaProblem("bad speed", f"SeaDronesSee meta field 'speed'={speed!r} is negative")
    north = _meta_number(meta, "xspeed", "speed", required=False)
    east = _meta_number(meta, "yspeed", "speed", required=False)
    date_time = meta.get("date_time")
    if (date_time is None or (isinstance(date_time, str) and not date_time.strip())) and t_default is not None:
        t = t_default
    else:
        t = _time(date_time, "date_time", utc_offset_s)
    assert height_m is not None
    try:
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
            hfov_deg=hfov,
        )
    except ValueError as err:
        raise MetaProblem("bad value", f"SeaDronesSee meta: {err}") from None


def _no_fix(lat: float, lon: float) -> None:
    """MetaProblem "no position" for (0, 0): what DJI's logs write before the GPS fix, as every other reader takes
    it (a pose there was 5,000 km off, and interpolated poses beside it 1,900 km)."""
    if lat == 0.0 and lon == 0.0:
        raise MetaProblem("no position", "SeaDronesSee meta position (0, 0): no GPS fix yet")


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
        ``date_time`` is ISO 8601 UTC with microseconds, e.g. ``2020-08-24T15:45:20.250000``. A record with a field
        of view (a zoom lens's, `Telemetry.hfov_deg`) adds ``hfov_deg``, which SeaDronesSee's layout does not have.
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
    } | ({} if tel.hfov_deg is None else {"hfov_deg": tel.hfov_deg})


def parse_seadronessee_coco(
    coco: Mapping[str, Any], *, video_id: Any = None, source: str = "<json>", utc_offset_s: float = 0.0
) -> list[Telemetry]:
    """Records of one video of a SeaDronesSee COCO file, ordered by ``frame_index``.

    Parameters
    ----------
    coco : dict
        COCO dict whose ``images[i]`` carry ``frame_index``, ``video_id`` and ``meta`` (may be null).
    video_id : optional
        Which video to read, by its name (`shared.telemetry.seadronessee_videos.group_videos`: ``source.video``,
        with the drone, folder or start in front when that name holds several recordings; else ``video_id``);
        required when the file holds several.
    source : str
        Name used in error messages.

    Returns
    -------
    list of Telemetry
        One per image with usable meta, ``frame`` = ``source.frame_no`` (SeaDronesSee Object Detection v2) or
        ``frame_index``; the videos are `group_videos`'s (what it split is logged as a warning). Images with null
        meta are skipped, those
        with unusable meta or no frame index too, counted in one warning (half of the images with meta or more
        unusable fails the file, naming the first). Stamps at whole seconds that repeat
        (flight-log meta) are spread over their second in frame order.

    Raises
    ------
    ValueError
        Naming the source and image id when no image, or not half of those with meta, has usable meta (the first
        problem), and when several videos are present and ``video_id`` is not given.
    """
    images = coco.get("images") if isinstance(coco, Mapping) else None
    if not isinstance(images, list):
        raise ValueError(f"{source}: not a COCO file: no 'images' list")
    for image in images:
        if not isinstance(image, Mapping):
            raise ValueError(f"{source}: images must be objects, got {image!r:.80}")
    images, notices = harmonise_zones(images)
    grouping = group_videos(images)
    for notice in notices + list(grouping.notices):
        logger.warning("%s: %s", source, notice)
    videos = sorted({repr(group.name) for group in grouping.groups})
    if video_id is None and len(videos) > 1:
        raise ValueError(f"{source}: holds {len(videos)} videos ({', '.join(videos[:10])}): pass video_id")
    chosen = [images[i] for i in sorted(i for group in grouping.groups if video_id is None or group.name == video_id
                                        for i in group.images)]
    # the pitch convention is the video's (a camera looks down far more than up), not each value's: one frame
    # looking 3 deg above the horizon (-3 where positive is down) is no DJI-signed depression of 3 deg
    metas = [meta_object(image.get("meta")) for image in chosen]
    convention = pitch_convention_of(meta for meta in metas if meta is not None)
    records: list[tuple[int, Telemetry]] = []
    skipped, problems = 0, []
    for image, meta in zip(chosen, metas, strict=True):
        src = image.get("source")
        frame = src.get("frame_no") if isinstance(src, Mapping) else None
        frame = image.get("frame_index") if frame is None else frame
        if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            problems.append(f"image id {image.get('id')!r}: frame index {frame!r} is not an index")
            continue
        try:
            tel = from_seadronessee_meta(meta if meta is not None else image.get("meta"), frame=frame,
                                         utc_offset_s=utc_offset_s, pitch_convention=convention)
        except ValueError as err:  # one frame's meta: that frame has no telemetry, the others keep theirs
            problems.append(f"image id {image.get('id')!r}: {err}")
            continue
        if tel is None:
            skipped += 1
            continue
        records.append((frame, tel))
    if skipped:
        logger.info("%s: %d image(s) without meta carry no telemetry", source, skipped)
    if not records or len(problems) * 2 >= len(records) + len(problems):  # half unusable: the file is wrong
        raise ValueError(f"{source}: " + (problems[0] if problems else "no image with meta"
                                          + ("" if video_id is None else f" in video {video_id!r}")))
    if problems:
        logger.warning("%s: %d image(s) with unusable meta carry no telemetry; first: %s", source, len(problems),
                       problems[0])
    records.sort(key=lambda item: item[0])
    # flight-log meta at whole seconds (v2's datetime(utc)): the frames of one second spread over it in order
    spread = spread_whole_second_stamps([tel.t for _, tel in records])
    return [tel if tel.t == t else dataclasses.replace(tel, t=t) for (_, tel), t in zip(records, spread, strict=True)]


def read_seadronessee_json(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a SeaDronesSee COCO JSON file; keyword arguments as in `parse_seadronessee_coco`."""
    kw.setdefault("source", str(path))
    try:
        coco = json.loads(read_text(path))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
    return parse_seadronessee_coco(coco, **kw)

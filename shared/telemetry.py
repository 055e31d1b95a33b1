"""Drone telemetry ingestion: one validated `Telemetry` record per sample from DJI SRT, CSV and SeaDronesSee meta.

Also interpolates telemetry to video frame times and writes SeaDronesSee meta; angles follow DESIGN.md 2.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from shared.geo import Pose

logger = logging.getLogger(__name__)

#: Gimbal pitch readings this far outside 0..90 deg are measurement noise and are clamped; beyond, an error.
PITCH_TOLERANCE_DEG = 1.0


# ---------------------------------------------------------------------------------------------
# The record
# ---------------------------------------------------------------------------------------------


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"Telemetry.{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"Telemetry.{name} must be finite, got {value!r}")
    return number


def _wrap360(deg: float) -> float:
    wrapped = deg % 360.0
    return 0.0 if wrapped >= 360.0 else wrapped + 0.0  # -1e-20 % 360 rounds to 360.0; + 0.0 drops -0.0


def _wrap180(deg: float) -> float:
    return _wrap360(deg + 180.0) - 180.0


@dataclass(frozen=True, slots=True)
class Telemetry:
    """One telemetry sample of a UAV and its gimbal.

    Attributes
    ----------
    t : float
        Seconds. UNIX epoch (UTC) when the source gives a date; otherwise the source's own relative clock
        (SRT subtitle start time, a CSV's time column), which starts near 0 at the first sample.
    lat, lon : float
        WGS84 degrees, signed (S and W negative); lat in [-90, 90], lon in [-180, 180].
    height_m : float
        Metres above the ground under the UAV (SeaDronesSee ``altitude``, DJI ``rel_alt``). Any finite
        value is accepted (a UAV on its pad reads 0 or slightly below); `to_pose` needs > 0.
    pitch_deg : float or None
        Gimbal depression below the horizon, 0..90 (90 = nadir); None if the source lacks it.
    heading_deg : float or None
        Gimbal yaw clockwise from true north, normalised to [0, 360); None if the source lacks it.
    roll_deg : float
        Gimbal roll, normalised to [-180, 180); 0 when unknown (gimbals hold the horizon level).
    speed_mps : float or None
        Horizontal ground speed, >= 0.
    vel_en_mps : tuple of float or None
        (east, north) velocity in m/s if known.
    frame : int or None
        The source's frame counter or index (DJI counters start at 1), >= 0.
    """

    t: float
    lat: float
    lon: float
    height_m: float
    pitch_deg: float | None
    heading_deg: float | None
    roll_deg: float = 0.0
    speed_mps: float | None = None
    vel_en_mps: tuple[float, float] | None = None
    frame: int | None = None

    def __post_init__(self) -> None:
        put = object.__setattr__  # frozen: normalised values are written once, here
        put(self, "t", _number("t", self.t))
        lat = _number("lat", self.lat)
        if not -90.0 <= lat <= 90.0:
            raise ValueError(f"Telemetry.lat={lat!r} is outside [-90, 90] degrees")
        put(self, "lat", lat)
        lon = _number("lon", self.lon)
        if not -180.0 <= lon <= 180.0:
            raise ValueError(f"Telemetry.lon={lon!r} is outside [-180, 180] degrees")
        put(self, "lon", lon)
        put(self, "height_m", _number("height_m", self.height_m))
        if self.pitch_deg is not None:
            pitch = _number("pitch_deg", self.pitch_deg)
            if not 0.0 <= pitch <= 90.0:
                raise ValueError(f"Telemetry.pitch_deg={pitch!r} is outside [0, 90] (depression, 90 = nadir)")
            put(self, "pitch_deg", pitch + 0.0)
        if self.heading_deg is not None:
            put(self, "heading_deg", _wrap360(_number("heading_deg", self.heading_deg)))
        put(self, "roll_deg", _wrap180(_number("roll_deg", self.roll_deg)))
        if self.speed_mps is not None:
            speed = _number("speed_mps", self.speed_mps)
            if speed < 0.0:
                raise ValueError(f"Telemetry.speed_mps={speed!r} must be >= 0")
            put(self, "speed_mps", speed)
        if self.vel_en_mps is not None:
            if isinstance(self.vel_en_mps, (str, bytes)) or len(self.vel_en_mps) != 2:
                raise ValueError(f"Telemetry.vel_en_mps={self.vel_en_mps!r} must be (east, north)")
            east, north = self.vel_en_mps
            put(self, "vel_en_mps", (_number("vel_en_mps[0]", east), _number("vel_en_mps[1]", north)))
        if self.frame is not None:
            if isinstance(self.frame, bool) or not isinstance(self.frame, (int, np.integer)):
                raise ValueError(f"Telemetry.frame must be an integer, got {self.frame!r}")
            if self.frame < 0:
                raise ValueError(f"Telemetry.frame={self.frame!r} must be >= 0")
            put(self, "frame", int(self.frame))

    def to_pose(self, pitch_deg: float | None = None, heading_deg: float | None = None) -> Pose:
        """Camera pose for `shared.geo`, with optional gimbal angles that override or supply missing ones.

        Parameters
        ----------
        pitch_deg, heading_deg : float, optional
            Depression 0..90 and heading in degrees; when given they replace the telemetry's values.

        Returns
        -------
        shared.geo.Pose

        Raises
        ------
        ValueError
            If an angle is missing from both the telemetry and the arguments, or `shared.geo.Pose`
            rejects a value (e.g. height_m <= 0 on the ground).
        """
        from shared.geo import Pose  # geo imports OpenCV; telemetry parsing does not need it

        pitch = self.pitch_deg if pitch_deg is None else pitch_deg
        if pitch is None:
            raise ValueError("telemetry has no gimbal pitch: pass --pitch-deg or use a source with gimbal angles")
        heading = self.heading_deg if heading_deg is None else heading_deg
        if heading is None:
            raise ValueError("telemetry has no gimbal heading: pass --heading-deg or use a source with gimbal angles")
        heading = _number("heading_deg", heading)
        return Pose(
            lat=self.lat,
            lon=self.lon,
            height_m=self.height_m,
            pitch_deg=_number("pitch_deg", pitch),
            heading_deg=_wrap360(heading),
            roll_deg=self.roll_deg,
        )


def pitch_from_dji(gb_pitch_deg: float, tolerance_deg: float = PITCH_TOLERANCE_DEG) -> float:
    """Convert a DJI gimbal pitch (negative down, -90 = nadir) to our depression 0..90.

    Parameters
    ----------
    gb_pitch_deg : float
        DJI ``gb_pitch`` / ``G.PRY`` pitch / XMP ``GimbalPitchDegree`` in degrees.
    tolerance_deg : float
        Readings up to this far beyond the range (e.g. -90.3, +0.5) are clamped to 90 or 0.

    Returns
    -------
    float
        Depression below the horizon in [0, 90].

    Raises
    ------
    ValueError
        If the reading is non-finite or further outside than the tolerance (camera tilted up, or past nadir).
    """
    return _clamp_pitch(-float(gb_pitch_deg), tolerance_deg, f"DJI gimbal pitch {gb_pitch_deg!r}")


def _clamp_pitch(depression_deg: float, tolerance_deg: float, what: str) -> float:
    if not math.isfinite(depression_deg):
        raise ValueError(f"{what} is not finite")
    if 0.0 <= depression_deg <= 90.0:
        return depression_deg + 0.0
    if -tolerance_deg <= depression_deg < 0.0:
        return 0.0
    if 90.0 < depression_deg <= 90.0 + tolerance_deg:
        return 90.0
    raise ValueError(
        f"{what} is a depression of {depression_deg:g} deg, outside 0..90 by more than {tolerance_deg:g} deg"
    )


def _pitch_or_none(depression_deg: float, what: str) -> float | None:
    """A record's pitch, or None (with a warning) when the camera looks up or past nadir.

    A pilot tilting the gimbal above the horizon for a moment is normal flying: those samples
    have no ground view (no pose), the rest of the flight stays usable.
    """
    try:
        return _clamp_pitch(depression_deg, PITCH_TOLERANCE_DEG, what)
    except ValueError as err:
        logger.warning("%s: no pose for this sample", err)
        return None


# ---------------------------------------------------------------------------------------------
# Dates
# ---------------------------------------------------------------------------------------------

# 2020-08-24T15:45:20 | 2017.07.29 15:18:50 | 2020:08:24 15:45:20 (EXIF) | 2022-08-07 13:40:40,774,808 (DJI ms,us)
_DATETIME_RE = re.compile(
    r"(?P<y>\d{4})[-.:/](?P<mo>\d{1,2})[-.:/](?P<d>\d{1,2})(?:T|\s+)(?P<h>\d{1,2}):(?P<mi>\d{1,2}):(?P<s>\d{1,2})"
    r"(?:[.,](?P<frac>\d{1,9}))?(?:,(?P<us>\d{3}))?(?:\s*(?P<tz>Z|[+-]\d{2}:?\d{2}))?"
)
_DATE_START_RE = re.compile(r"(?<![\d.])\d{4}[-./]\d{1,2}[-./]\d{1,2}(?![\d.])")


def _epoch_from_match(match: re.Match[str], utc_offset_s: float) -> float:
    """Seconds since the epoch; a naive time is the drone clock at UTC + utc_offset_s."""
    fields = {k: int(v) for k, v in match.groupdict().items() if v is not None and k not in ("frac", "tz")}
    stamp = datetime(
        fields["y"], fields["mo"], fields["d"], fields["h"], fields["mi"], fields["s"], tzinfo=timezone.utc
    )
    seconds = stamp.timestamp()
    if match["frac"]:
        seconds += int(match["frac"]) / 10 ** len(match["frac"])
    if match["us"]:  # the ",808" of DJI's "40,774,808": microseconds after the milliseconds
        seconds += int(match["us"]) * 1e-6
    tz = match["tz"]
    if tz is None:
        return seconds - utc_offset_s
    if tz == "Z":
        return seconds
    sign = -1.0 if tz[0] == "-" else 1.0
    digits = tz[1:].replace(":", "")
    return seconds - sign * (int(digits[:2]) * 3600 + int(digits[2:]) * 60)


def parse_datetime(text: str, *, utc_offset_s: float = 0.0) -> float:
    """Parse a date-time string to seconds since the UNIX epoch.

    Parameters
    ----------
    text : str
        ISO 8601 (``2020-08-24T15:45:20.5``, optional ``Z`` or ``+02:00``), EXIF (``2020:08:24 15:45:20``)
        or DJI (``2017.07.29 15:18:50``, ``2022-08-07 13:40:40,774,808``).
    utc_offset_s : float
        Offset of the clock that wrote a naive time from UTC (e.g. 7200 for CEST); ignored when the text
        carries its own zone. Naive times are UTC by default.

    Raises
    ------
    ValueError
        If the text is not one of these forms or names an impossible date.
    """
    match = _DATETIME_RE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"{text!r} is not a date-time like 2020-08-24T15:45:20")
    try:
        return _epoch_from_match(match, utc_offset_s)
    except (ValueError, OverflowError) as err:
        raise ValueError(f"{text!r} is not a valid date-time: {err}") from None


def _format_datetime(t: float) -> str:
    try:
        stamp = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(seconds=t)
    except OverflowError as err:
        raise ValueError(f"t={t!r} cannot be written as a date: {err}") from None
    return stamp.replace(tzinfo=None).isoformat(timespec="microseconds")


# ---------------------------------------------------------------------------------------------
# SeaDronesSee meta
# ---------------------------------------------------------------------------------------------

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
        pitch = _clamp_pitch(pitch_raw, PITCH_TOLERANCE_DEG, f"SeaDronesSee meta field 'gimbal_pitch'={pitch_raw!r}")
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
        "date_time": _format_datetime(tel.t),
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
        coco = json.loads(_read_text(path))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
    return parse_seadronessee_coco(coco, **kw)


# ---------------------------------------------------------------------------------------------
# DJI SRT
# ---------------------------------------------------------------------------------------------

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
_NUM_RE = re.compile(_NUM)
_TIMING_RE = re.compile(
    r"(\d{1,9}):(\d{1,2}):(\d{1,2})[,.](\d{1,3})\s*-->\s*(\d{1,9}):(\d{1,2}):(\d{1,2})[,.](\d{1,3})"
)
_INDEX_RE = re.compile(r"[0-9]{1,12}")
_HTML_TAG_RE = re.compile(r"<[^<>]*>")
_TOKEN = r"\s*:\s*([^\s\[\],]*)"  # the raw value after "key:", checked afterwards so garbage is reported
_SRT_KEYS = {
    "latitude": re.compile(r"\blatitude" + _TOKEN, re.IGNORECASE),
    "longitude": re.compile(r"\blongt?itude" + _TOKEN, re.IGNORECASE),  # Mavic 2 firmware writes "longtitude"
    "rel_alt": re.compile(r"\brel_alt" + _TOKEN, re.IGNORECASE),
    "abs_alt": re.compile(r"\babs_alt" + _TOKEN, re.IGNORECASE),
    "altitude": re.compile(r"\baltitude" + _TOKEN, re.IGNORECASE),
    "barometer": re.compile(r"\bBAROMETER" + _TOKEN, re.IGNORECASE),
    "gb_pitch": re.compile(r"\bgb_pitch" + _TOKEN, re.IGNORECASE),
    "gb_yaw": re.compile(r"\bgb_yaw" + _TOKEN, re.IGNORECASE),
    "gb_roll": re.compile(r"\bgb_roll" + _TOKEN, re.IGNORECASE),
    "counter": re.compile(r"\b(?:FrameCnt|SrtCnt)" + _TOKEN, re.IGNORECASE),
}
_GPS_TUPLE_RE = re.compile(r"\b(?:GPS|RTK)\s*\(([^()]*)\)")
_GIMBAL_PRY_RE = re.compile(r"\bG\.PRY\s*\(([^()]*)\)")
_HEIGHT_H_RE = re.compile(rf"(?<![\w.])H\s*[:=]?\s*({_NUM})\s*m(?![/\w])")
_SPEED_HS_RE = re.compile(rf"\bH\.S\s*[:=]?\s*({_NUM})\s*m/s")
_METRES_RE = re.compile(rf"({_NUM})\s*[mM]?")
_ANGLE_RE = re.compile(rf"({_NUM})\s*(?:°|Â°|deg)?")


@dataclass
class _SrtBlock:
    """Raw facts of one subtitle block, each with the line it came from."""

    index: int | None
    timing_line: int
    start_s: float
    values: dict[str, tuple[float, int]] = field(default_factory=dict)
    epoch_s: float | None = None
    frame: int | None = None
    gps: tuple[float, float, bool, int] | None = None  # a, b, third value had an "M" suffix, line
    gimbal_pry: tuple[float, float, float, int] | None = None


def _srt_error(source: str, line: int, message: str) -> ValueError:
    return ValueError(f"{source}:{line}: {message}")


def _split_srt(text: str, source: str) -> list[tuple[int | None, int, float, list[tuple[int, str]]]]:
    """Blocks as (index, timing line number, start seconds, [(line number, text without HTML)])."""
    blocks: list[tuple[int | None, int, float, list[tuple[int, str]]]] = []
    pending: list[tuple[int, str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = _HTML_TAG_RE.sub(" ", raw).strip()
        if "-->" not in line:
            if line:
                pending.append((lineno, line))
            continue
        match = _TIMING_RE.fullmatch(line)
        if match is None:
            raise _srt_error(source, lineno, f"malformed subtitle timing line {line[:80]!r}")
        h, m, s, frac = match.group(1, 2, 3, 4)
        start_s = int(h) * 3600 + int(m) * 60 + int(s) + int(frac) / 10 ** len(frac)
        index = None
        if pending and _INDEX_RE.fullmatch(pending[-1][1]):
            index = int(pending.pop()[1])
        if blocks:
            blocks[-1][3].extend(pending)
        elif pending:
            raise _srt_error(source, pending[0][0], f"text before the first subtitle block: {pending[0][1][:80]!r}")
        pending = []
        blocks.append((index, lineno, start_s, []))
    if not blocks:
        if not text.strip():
            raise ValueError(f"{source}: empty SRT file")
        raise ValueError(f"{source}: no subtitle blocks (no 'HH:MM:SS,mmm --> HH:MM:SS,mmm' line)")
    blocks[-1][3].extend(pending)
    return blocks


def _srt_number(source: str, line: int, key: str, token: str, pattern: re.Pattern[str] = _NUM_RE) -> float:
    match = pattern.fullmatch(token)
    if match is None:
        raise _srt_error(source, line, f"{key} value {token!r} is not a number")
    value = float(match.group(1) if match.groups() else match.group(0))
    if not math.isfinite(value):
        raise _srt_error(source, line, f"{key} value {token!r} is not finite")
    return value


def _parse_srt_block(
    index: int | None,
    timing_line: int,
    start_s: float,
    lines: list[tuple[int, str]],
    source: str,
    utc_offset_s: float,
) -> _SrtBlock:
    block = _SrtBlock(index=index, timing_line=timing_line, start_s=start_s, frame=index)
    counter_seen = False
    gps_text: tuple[str, str, int] | None = None
    for lineno, line in lines:
        for key, pattern in _SRT_KEYS.items():
            match = pattern.search(line)
            if match is None or key in block.values or (key == "counter" and counter_seen):
                continue
            token = match.group(1)
            if key == "counter":
                if not _INDEX_RE.fullmatch(token):
                    raise _srt_error(source, lineno, f"frame counter {token!r} is not a non-negative integer")
                block.frame, counter_seen = int(token), True
                continue
            number_re = _METRES_RE if key == "barometer" else _NUM_RE
            block.values[key] = (_srt_number(source, lineno, key, token, number_re), lineno)
        if block.epoch_s is None:
            date = _DATETIME_RE.search(line)
            if date is not None:
                try:
                    block.epoch_s = _epoch_from_match(date, utc_offset_s)
                except (ValueError, OverflowError) as err:
                    raise _srt_error(source, lineno, f"invalid date-time {date.group(0)!r}: {err}") from None
            elif _DATE_START_RE.search(line):
                raise _srt_error(source, lineno, f"date-time does not parse: {line[:80]!r}")
        if gps_text is None and (gps := _GPS_TUPLE_RE.search(line)) is not None:
            gps_text = (gps.group(0), gps.group(1), lineno)
        if block.gimbal_pry is None and (pry := _GIMBAL_PRY_RE.search(line)) is not None:
            parts = [part.strip() for part in pry.group(1).split(",")]
            if len(parts) != 3:
                raise _srt_error(source, lineno, f"G.PRY {pry.group(0)!r} needs pitch, roll, yaw")
            p, r, y = (_srt_number(source, lineno, "G.PRY", part, _ANGLE_RE) for part in parts)
            block.gimbal_pry = (p, r, y, lineno)
        if "H" not in block.values and (height := _HEIGHT_H_RE.search(line)) is not None:
            block.values["H"] = (_srt_number(source, lineno, "H", height.group(1)), lineno)
        if "H.S" not in block.values and (speed := _SPEED_HS_RE.search(line)) is not None:
            block.values["H.S"] = (_srt_number(source, lineno, "H.S", speed.group(1)), lineno)
    if gps_text is not None and "latitude" not in block.values:  # a named latitude beats a positional tuple
        whole, inner, lineno = gps_text
        parts = [part.strip() for part in inner.split(",")]
        if len(parts) not in (2, 3):
            raise _srt_error(source, lineno, f"GPS tuple {whole!r} needs 2 or 3 values")
        a = _srt_number(source, lineno, "GPS", parts[0])
        b = _srt_number(source, lineno, "GPS", parts[1])
        if len(parts) == 3:
            _srt_number(source, lineno, "GPS third value", parts[2], _METRES_RE)
        block.gps = (a, b, len(parts) == 3 and parts[2][-1:] in ("M", "m"), lineno)
    return block


def _gps_order(blocks: list[_SrtBlock], gps_order: str, source: str) -> str:
    """'latlon' or 'lonlat' for the positional GPS tuples of a file (rule in `parse_srt`)."""
    tuples = [b.gps for b in blocks if b.gps is not None]
    if not tuples:
        return "lonlat"
    first_is_lon = next((t for t in tuples if abs(t[0]) > 90.0), None)
    second_is_lon = next((t for t in tuples if abs(t[1]) > 90.0), None)
    if first_is_lon and second_is_lon:
        raise _srt_error(
            source, second_is_lon[3], f"GPS values beyond +-90 in both positions (see also line {first_is_lon[3]})"
        )
    if gps_order in ("latlon", "lonlat"):
        contradiction = first_is_lon if gps_order == "latlon" else second_is_lon
        if contradiction is not None:
            raise _srt_error(source, contradiction[3], f"gps_order={gps_order!r} puts a longitude in latitude")
        return gps_order
    if gps_order != "auto":
        raise ValueError(f"gps_order={gps_order!r} must be 'auto', 'latlon' or 'lonlat'")
    if first_is_lon or second_is_lon:
        return "lonlat" if first_is_lon else "latlon"
    # Values cannot tell: a metre-suffixed third value is the Matrice's altitude, a bare one a satellite count.
    return "latlon" if any(t[2] for t in tuples) else "lonlat"


def _srt_height(block: _SrtBlock, source: str, height_offset_m: float | None, warned: set[str]) -> float:
    """Height above ground: rel_alt, else H, else BAROMETER, else altitude; abs_alt only with an offset."""
    offset = 0.0 if height_offset_m is None else height_offset_m
    for key in ("rel_alt", "H", "barometer"):
        if key in block.values:
            return block.values[key][0] + offset
    if "altitude" in block.values:
        if height_offset_m is None and "altitude" not in warned:
            warned.add("altitude")
            logger.warning(
                "%s: using the SRT 'altitude' field as height above ground; Mavic 2 / Air 2S firmware writes "
                "altitude above sea level there: pass height_offset_m=-(ground elevation) if so",
                source,
            )
        return block.values["altitude"][0] + offset
    if "abs_alt" in block.values:
        if height_offset_m is None:
            raise _srt_error(
                source,
                block.values["abs_alt"][1],
                "only absolute altitude (abs_alt, above sea level) is given, which is not height above "
                "ground: pass height_offset_m=-(ground elevation in metres)",
            )
        return block.values["abs_alt"][0] + offset
    raise _srt_error(source, block.timing_line, "block has no height (rel_alt, H, BAROMETER or altitude)")


def parse_srt(
    text: str,
    *,
    source: str = "<srt>",
    utc_offset_s: float = 0.0,
    height_offset_m: float | None = None,
    gps_order: str = "auto",
) -> list[Telemetry]:
    """Parse a DJI SRT subtitle file into one record per subtitle block.

    Variants read (real samples in tests/shared/test_telemetry.py):

    - Mavic Pro / Phantom 4: ``HOME(lon,lat) 2017.07.29 15:18:50`` / ``GPS(lon,lat,sats) BAROMETER:1.9``.
    - Mavic Mini / Phantom 4 (RTK): ``F/2.8, SS 206.14, ISO 150, EV 0, GPS (lon, lat, sats), D 2.80m,
      H 0.00m, H.S 0.00m/s, V.S 0.00m/s``, optionally ``RTK (lon, lat, n)``, ``F.PRY (p°, r°, y°)``
      (aircraft, ignored) and ``G.PRY (p°, r°, y°)`` (gimbal pitch, roll, yaw).
    - Matrice 300: ``2022.06.21 16:06:17`` / ``GPS(lat,lon,altM) BAROMETER:0.3M`` (latitude first).
    - Mavic 2 / Air 2 / Air 2S: ``<font ...>FrameCnt : 1, DiffTime : 41ms`` (or ``SrtCnt``), a date like
      ``2023-06-23 11:26:03,972,307`` (ms, us), ``[latitude : 38.9] [longtitude : -92.2] [altitude: 274.2]``.
    - Mini 3 / Mavic 3 / Matrice 30: ``FrameCnt: 1, DiffTime: 33ms``, ``2025-04-09 09:15:02.655``,
      ``[latitude: 53.38] [longitude: 5.36] [rel_alt: 55.774 abs_alt: 98.364]`` and optionally
      ``[gb_yaw: -83.6 gb_pitch: -9.1 gb_roll: 0.0]``; HTML ``<font>`` tags are dropped.

    The positional ``GPS(a, b, c)`` form has no single axis order: consumer models write (lon, lat,
    satellites), the Matrice 300 writes (lat, lon, altitude with an ``M`` suffix). With ``gps_order='auto'``
    the order is decided per file: a value beyond +-90 can only be a longitude; otherwise an ``M``-suffixed
    third value means (lat, lon, alt) and a bare one (the satellite count) means (lon, lat, sats).

    Height, in order of preference: ``rel_alt`` (above the take-off point), ``H``, ``BAROMETER``, then
    ``altitude`` (logged as ambiguous: some firmware writes altitude above sea level there); ``abs_alt``
    (above sea level) is not height above ground and is used only with ``height_offset_m``.

    Parameters
    ----------
    text : str
        The file's text.
    source : str
        Name used in error messages (``source:line: what``).
    utc_offset_s : float
        Offset of the drone clock from UTC in seconds (DJI writes local time without a zone; e.g. 7200
        for CEST). The default treats the date lines as UTC.
    height_offset_m : float, optional
        Metres added to every height. Needed when the file has only ``abs_alt`` (above sea level): pass
        minus the ground elevation. Also silences the warning about the ambiguous ``altitude`` field.
    gps_order : {'auto', 'latlon', 'lonlat'}
        Axis order of positional ``GPS(a, b, c)`` tuples; 'auto' decides per file.

    Returns
    -------
    list of Telemetry
        In file order. ``t`` is the UNIX epoch from the date lines when every block has one, else the
        subtitle start time in seconds. ``frame`` is ``FrameCnt``/``SrtCnt`` or the subtitle index.
        Pitch and heading come only from the gimbal (``gb_pitch``/``gb_yaw``/``gb_roll`` or ``G.PRY``),
        converted with `pitch_from_dji`; aircraft attitude (``F.PRY``) is ignored; without gimbal fields
        they are None. Blocks whose position is exactly (0, 0) are DJI's "no GPS fix" and are skipped
        with a warning.

    Raises
    ------
    ValueError
        ``source:line: what`` for an empty file, a malformed timing or date line, a block without
        latitude/longitude/height, a non-numeric value, a gimbal pitch more than `PITCH_TOLERANCE_DEG`
        outside 0..90 (camera tilted up), a file mixing blocks with and without dates, or no GPS fix at all.
    """
    if not isinstance(text, str):
        raise TypeError(f"parse_srt needs str, got {type(text).__name__}")
    blocks = [
        _parse_srt_block(index, timing_line, start_s, lines, source, utc_offset_s)
        for index, timing_line, start_s, lines in _split_srt(text, source)
    ]
    dated = [b.epoch_s is not None for b in blocks]
    if any(dated) and not all(dated):
        odd = blocks[dated.index(not dated[0])]
        raise _srt_error(source, odd.timing_line, "some blocks have a date-time line and others do not")
    order = _gps_order(blocks, gps_order, source)
    warned: set[str] = set()
    records: list[Telemetry] = []
    no_fix_lines: list[int] = []
    for block in blocks:
        lat, lon = _srt_position(block, order, source)
        if lat == 0.0 and lon == 0.0:
            no_fix_lines.append(block.timing_line)
            continue
        height_m = _srt_height(block, source, height_offset_m, warned)
        pitch, heading, roll = _srt_gimbal(block, source)
        speed = block.values.get("H.S")
        try:
            records.append(
                Telemetry(
                    t=block.epoch_s if block.epoch_s is not None else block.start_s,
                    lat=lat,
                    lon=lon,
                    height_m=height_m,
                    pitch_deg=pitch,
                    heading_deg=heading,
                    roll_deg=roll,
                    speed_mps=None if speed is None else abs(speed[0]),
                    frame=block.frame,
                )
            )
        except ValueError as err:
            raise _srt_error(source, block.timing_line, str(err)) from None
    if no_fix_lines:
        logger.warning(
            "%s: skipped %d block(s) at position (0, 0) = no GPS fix, first at line %d",
            source,
            len(no_fix_lines),
            no_fix_lines[0],
        )
    if not records:
        raise ValueError(f"{source}: no block has a GPS fix (all positions are 0, 0)")
    return records


def _srt_position(block: _SrtBlock, order: str, source: str) -> tuple[float, float]:
    if "latitude" in block.values or "longitude" in block.values:
        for key in ("latitude", "longitude"):
            if key not in block.values:
                raise _srt_error(source, block.timing_line, f"block has no {key}")
        lat, lat_line = block.values["latitude"]
        lon, lon_line = block.values["longitude"]
    elif block.gps is not None:
        a, b, _, lat_line = block.gps
        lon_line = lat_line
        lat, lon = (a, b) if order == "latlon" else (b, a)
    else:
        raise _srt_error(source, block.timing_line, "block has no latitude (no [latitude: ...] or GPS(...))")
    if not -90.0 <= lat <= 90.0:
        raise _srt_error(source, lat_line, f"latitude {lat:g} is outside [-90, 90]")
    if not -180.0 <= lon <= 180.0:
        raise _srt_error(source, lon_line, f"longitude {lon:g} is outside [-180, 180]")
    return lat, lon


def _srt_gimbal(block: _SrtBlock, source: str) -> tuple[float | None, float | None, float]:
    values = block.values
    if "gb_pitch" in values or "gb_yaw" in values:
        raw_pitch, pitch_line = values.get("gb_pitch", (None, block.timing_line))
        heading = values["gb_yaw"][0] if "gb_yaw" in values else None
        roll = values["gb_roll"][0] if "gb_roll" in values else 0.0
    elif block.gimbal_pry is not None:
        raw_pitch, roll, heading, pitch_line = block.gimbal_pry
    else:
        return None, None, 0.0
    pitch = None
    if raw_pitch is not None:
        if not math.isfinite(raw_pitch):
            raise _srt_error(source, pitch_line, f"gimbal pitch {raw_pitch!r} is not finite")
        pitch = _pitch_or_none(-raw_pitch, f"{source}:{pitch_line}: DJI gimbal pitch {raw_pitch:g}")
    return pitch, heading, roll


def _read_text(path: str | Path) -> str:
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        logger.debug("%s is not UTF-8; reading it as Latin-1", path)
        return data.decode("latin-1")


def read_srt(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a DJI SRT file; keyword arguments as in `parse_srt` (``source`` defaults to the path)."""
    kw.setdefault("source", str(path))
    return parse_srt(_read_text(path), **kw)


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------

_TIME_UNITS = {"": 1.0, "s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0,
               "ms": 1e-3, "millisecond": 1e-3, "milliseconds": 1e-3}  # fmt: skip
_LENGTH_UNITS = {"": 1.0, "m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0,
                 "ft": 0.3048, "feet": 0.3048}  # fmt: skip
_ANGLE_UNITS = {"": 1.0, "deg": 1.0, "degree": 1.0, "degrees": 1.0}
_SPEED_UNITS = {"": 1.0, "m/s": 1.0, "mps": 1.0, "mph": 0.44704, "km/h": 1 / 3.6, "kph": 1 / 3.6}

#: field -> (accepted column names in order of preference, accepted units with their factor to SI)
CSV_COLUMNS: dict[str, tuple[tuple[str, ...], Mapping[str, float]]] = {
    "time": (("time_s", "time", "t", "timestamp"), _TIME_UNITS),
    "datetime": (("date_time", "datetime", "datetime_utc"), {"": 1.0, "utc": 1.0}),
    "lat": (("lat", "latitude"), _ANGLE_UNITS),
    "lon": (("lon", "lng", "longitude"), _ANGLE_UNITS),
    "height": (("height_m", "rel_alt", "height_above_takeoff", "height", "altitude"), _LENGTH_UNITS),
    "pitch": (("pitch_deg", "gimbal_pitch", "gb_pitch", "gimbal_pitch_dji", "pitch"), _ANGLE_UNITS),
    "heading": (("heading_deg", "gimbal_heading", "gb_yaw", "heading", "yaw"), _ANGLE_UNITS),
    "roll": (("roll_deg", "gimbal_roll", "gb_roll", "roll"), _ANGLE_UNITS),
    "speed": (("speed_mps", "speed"), _SPEED_UNITS),
    "frame": (("frame", "frame_index", "framecnt"), {"": 1.0}),
}
_DJI_PITCH_COLUMNS = ("gb_pitch", "gimbal_pitch_dji")
_HEADER_RE = re.compile(r"(?P<name>.*?)\s*(?:\((?P<paren>[^()]*)\)|\[(?P<bracket>[^\[\]]*)\])?")


@dataclass
class _CsvColumn:
    field: str
    name: str  # as written in the header
    alias: str
    index: int
    scale: float


def _csv_columns(header: list[str], header_line: int, source: str) -> dict[str, _CsvColumn]:
    found: dict[str, _CsvColumn] = {}
    for index, cell in enumerate(header):
        match = _HEADER_RE.fullmatch(cell.strip().lower())
        assert match is not None  # every string matches: the unit group is optional
        name, unit = match["name"].strip(), (match["paren"] or match["bracket"] or "").strip()
        for fld, (aliases, units) in CSV_COLUMNS.items():
            if name not in aliases:
                continue
            if unit not in units:
                accepted = ", ".join(u for u in units if u) or "none"
                raise ValueError(
                    f"{source}:{header_line}: column {cell!r}: unknown unit {unit!r} (accepted: {accepted})"
                )
            column = _CsvColumn(fld, cell.strip(), name, index, units[unit])
            previous = found.get(fld)
            if previous is not None and previous.alias == name:
                raise ValueError(
                    f"{source}:{header_line}: columns {previous.name!r} and {cell.strip()!r} are the same field"
                )
            if previous is None or aliases.index(name) < aliases.index(previous.alias):
                found[fld] = column
    for required in ("lat", "lon", "height"):
        if required not in found:
            names = ", ".join(CSV_COLUMNS[required][0])
            raise ValueError(f"{source}: missing required column {required!r} (accepted names: {names})")
    if "time" not in found and "datetime" not in found:
        names = ", ".join(CSV_COLUMNS["time"][0] + CSV_COLUMNS["datetime"][0])
        raise ValueError(f"{source}: missing required column 'time' (accepted names: {names})")
    return found


def _csv_float(cell: str, line: int, column: _CsvColumn, source: str) -> float | None:
    text = cell.strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{source}:{line}: column {column.name!r}: {text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{source}:{line}: column {column.name!r}: {text[:40]!r} is not finite")
    return value * column.scale


def parse_csv(
    text: str, *, source: str = "<csv>", utc_offset_s: float = 0.0, height_offset_m: float = 0.0
) -> list[Telemetry]:
    """Parse a comma-separated telemetry table with a header row.

    Column names are matched case-insensitively, with an optional unit in parentheses or brackets, as
    AirData exports write them (``time(millisecond)``, ``height_above_takeoff(feet)``, ``speed(mph)``):

    - time: ``time_s, time, t, timestamp`` (seconds or ms; numbers, or date-times) and/or ``date_time,
      datetime, datetime(utc)``. With both, t = first date + (time - first time): the date anchors the
      epoch, the finer time column spaces the rows. A naive date is UTC unless ``utc_offset_s`` is given.
    - required: ``lat, latitude``; ``lon, lng, longitude``; height ``height_m, rel_alt,
      height_above_takeoff, height, altitude`` (m or ft; ``height_offset_m`` is added).
    - optional: pitch ``pitch_deg, gimbal_pitch, gb_pitch, gimbal_pitch_dji, pitch``; heading
      ``heading_deg, gimbal_heading, gb_yaw, heading, yaw``; roll ``roll_deg, gimbal_roll, gb_roll, roll``;
      ``speed_mps, speed``; ``frame, frame_index, framecnt``. An empty optional cell is None.

    When several names of one field are present the earlier one in these lists wins (a gimbal column
    beats the aircraft's ``pitch``/``yaw``/``roll``).

    DJI pitch rule: the pitch column is in DJI convention (negative down, -90 = nadir) when it is named
    ``gb_pitch`` or ``gimbal_pitch_dji``, or when any of its values is negative; it is then converted
    with `pitch_from_dji`. Otherwise it is our depression 0..90. Either way readings within
    `PITCH_TOLERANCE_DEG` outside 0..90 are clamped and others rejected.

    Parameters
    ----------
    text : str
        The file's text (comma-separated, first non-blank row is the header).
    source : str
        Name used in error messages (``source:line: ...``).
    utc_offset_s : float
        Offset of naive date-times from UTC in seconds.
    height_offset_m : float
        Metres added to every height (e.g. minus the ground elevation for an above-sea-level column).

    Returns
    -------
    list of Telemetry
        One per non-blank data row, in file order.

    Raises
    ------
    ValueError
        Naming the missing column; or ``source:line: column 'name': ...`` for a bad cell, a row with the
        wrong number of cells, or an out-of-range value.
    """
    if not isinstance(text, str):
        raise TypeError(f"parse_csv needs str, got {type(text).__name__}")
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff")), strict=True)
    rows: list[tuple[int, list[str]]] = []
    try:
        for row in reader:
            if any(cell.strip() for cell in row):
                rows.append((reader.line_num, row))
    except csv.Error as err:
        raise ValueError(f"{source}:{reader.line_num}: unreadable CSV: {err}") from None
    if not rows:
        raise ValueError(f"{source}: empty CSV file")
    header_line, header = rows[0]
    columns = _csv_columns(header, header_line, source)
    if len(rows) == 1:
        raise ValueError(f"{source}: no data rows after the header")
    for line, row in rows[1:]:
        if len(row) != len(header):
            raise ValueError(f"{source}:{line}: {len(row)} cells, the header has {len(header)}")

    def floats(fld: str) -> list[float | None] | None:
        column = columns.get(fld)
        if column is None:
            return None
        return [_csv_float(row[column.index], line, column, source) for line, row in rows[1:]]

    def required(fld: str) -> list[float]:
        column, values = columns[fld], floats(fld)
        out: list[float] = []
        for (line, _), value in zip(rows[1:], values or [], strict=True):
            if value is None:
                raise ValueError(f"{source}:{line}: column {column.name!r} is empty")
            out.append(value)
        return out

    lat, lon, height = required("lat"), required("lon"), required("height")
    times = _csv_times(rows[1:], columns, source, utc_offset_s)
    pitch = _csv_pitch(rows[1:], columns, floats("pitch"), source)
    heading, roll, speed = floats("heading"), floats("roll"), floats("speed")
    frames = _csv_frames(rows[1:], columns.get("frame"), source)
    records = []
    for i, (line, _) in enumerate(rows[1:]):
        try:
            records.append(
                Telemetry(
                    t=times[i],
                    lat=lat[i],
                    lon=lon[i],
                    height_m=height[i] + height_offset_m,
                    pitch_deg=pitch[i],
                    heading_deg=None if heading is None else heading[i],
                    roll_deg=0.0 if roll is None else roll[i] or 0.0,
                    speed_mps=None if speed is None else speed[i],
                    frame=frames[i],
                )
            )
        except ValueError as err:
            raise ValueError(f"{source}:{line}: {err}") from None
    return records


def _csv_times(
    rows: list[tuple[int, list[str]]], columns: dict[str, _CsvColumn], source: str, utc_offset_s: float
) -> list[float]:
    def dates(column: _CsvColumn) -> list[float]:
        out = []
        for line, row in rows:
            try:
                out.append(parse_datetime(row[column.index], utc_offset_s=utc_offset_s))
            except ValueError as err:
                raise ValueError(f"{source}:{line}: column {column.name!r}: {err}") from None
        return out

    numeric: list[float] | None = None
    time_column = columns.get("time")
    if time_column is not None:
        first = rows[0][1][time_column.index].strip()
        if _NUM_RE.fullmatch(first) or not _DATETIME_RE.fullmatch(first):
            numeric = []
            for line, row in rows:
                value = _csv_float(row[time_column.index], line, time_column, source)
                if value is None:
                    raise ValueError(f"{source}:{line}: column {time_column.name!r} is empty")
                numeric.append(value)
        else:
            return dates(time_column)
    date_column = columns.get("datetime")
    if date_column is None:
        assert numeric is not None
        return numeric
    anchors = dates(date_column)
    if numeric is None:
        return anchors
    return [anchors[0] + (value - numeric[0]) for value in numeric]


def _csv_pitch(
    rows: list[tuple[int, list[str]]],
    columns: dict[str, _CsvColumn],
    raw: list[float | None] | None,
    source: str,
) -> list[float | None]:
    if raw is None:
        return [None] * len(rows)
    column = columns["pitch"]
    dji = column.alias in _DJI_PITCH_COLUMNS or any(v is not None and v < 0.0 for v in raw)
    out: list[float | None] = []
    for (line, _), value in zip(rows, raw, strict=True):
        if value is None:
            out.append(None)
            continue
        if not math.isfinite(value):
            raise ValueError(f"{source}:{line}: column {column.name!r}: pitch {value!r} is not finite")
        depression = -value if dji else value
        out.append(_pitch_or_none(depression, f"{source}:{line}: column {column.name!r}: pitch {value:g}"))
    return out


def _csv_frames(rows: list[tuple[int, list[str]]], column: _CsvColumn | None, source: str) -> list[int | None]:
    if column is None:
        return [None] * len(rows)
    out: list[int | None] = []
    for line, row in rows:
        value = _csv_float(row[column.index], line, column, source)
        if value is not None and (value < 0.0 or value != int(value)):
            raise ValueError(f"{source}:{line}: column {column.name!r}: {value:g} is not a frame index")
        out.append(None if value is None else int(value))
    return out


def read_csv(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a telemetry CSV file; keyword arguments as in `parse_csv` (``source`` defaults to the path)."""
    kw.setdefault("source", str(path))
    return parse_csv(_read_text(path), **kw)


def read_telemetry(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read telemetry, choosing the reader by file extension.

    ``.srt`` -> `read_srt`, ``.csv`` -> `read_csv`, ``.json`` -> `read_seadronessee_json` (SeaDronesSee
    COCO ``images[*].meta``, ordered by ``frame_index``). Keyword arguments go to the reader.

    Raises
    ------
    ValueError
        For another extension, or whatever the reader rejects.
    """
    readers = {".srt": read_srt, ".csv": read_csv, ".json": read_seadronessee_json}
    suffix = Path(path).suffix.lower()
    if suffix not in readers:
        raise ValueError(f"{path}: unknown telemetry format {suffix!r} (supported: {', '.join(readers)})")
    return readers[suffix](path, **kw)


# ---------------------------------------------------------------------------------------------
# Interpolation
# ---------------------------------------------------------------------------------------------


def _optional(values: Iterable[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _unwrap_deg(deg: np.ndarray) -> np.ndarray:
    """Unwrap angles (period 360) over the finite entries so neighbours differ by at most 180 deg."""
    out = deg.copy()
    finite = np.isfinite(deg)
    if finite.any():
        out[finite] = np.unwrap(deg[finite], period=360.0)
    return out


def interpolate(
    records: Sequence[Telemetry], times: ArrayLike, *, extrapolate_s: float = 0.0
) -> list[Telemetry | None]:
    """Interpolate telemetry to query times (e.g. video frame times).

    Parameters
    ----------
    records : sequence of Telemetry
        Sorted by ``t`` (non-decreasing); of records with equal ``t`` the first is used.
    times : array_like, shape (N,)
        Query times in the records' clock, seconds.
    extrapolate_s : float
        Times up to this far before the first / after the last record get that record's values
        (held, not extrapolated); further out they get None.

    Returns
    -------
    list of Telemetry or None, length N
        ``t`` = the query time. lat, height, pitch and speeds are linear; lon, heading and roll follow
        the shortest arc (359 -> 1 passes 0, +179 -> -179 lon crosses the antimeridian). An optional
        field is None where a bracketing record lacks it. ``frame`` is kept only where a query time
        equals a record's ``t``.

    Raises
    ------
    ValueError
        If ``records`` is empty or unsorted, or a time or ``extrapolate_s`` is not finite (or negative).
    """
    recs = list(records)
    if not recs:
        raise ValueError("interpolate needs at least one telemetry record")
    query = np.atleast_1d(np.asarray(times, dtype=float)).reshape(-1)
    if not np.isfinite(query).all():
        raise ValueError("interpolate: query times must be finite")
    if not (math.isfinite(extrapolate_s) and extrapolate_s >= 0.0):
        raise ValueError(f"extrapolate_s={extrapolate_s!r} must be finite and >= 0")
    t_rec = np.array([r.t for r in recs], dtype=float)
    if (np.diff(t_rec) < 0).any():
        first = int(np.flatnonzero(np.diff(t_rec) < 0)[0]) + 1
        raise ValueError(f"interpolate: records must be sorted by t (record {first} goes back in time)")
    t_rec, keep = np.unique(t_rec, return_index=True)
    recs = [recs[i] for i in keep]

    def interp(values: np.ndarray) -> np.ndarray:
        return np.interp(np.clip(query, t_rec[0], t_rec[-1]), t_rec, values)

    lat = np.clip(interp(np.array([r.lat for r in recs])), -90.0, 90.0)
    lon = interp(_unwrap_deg(np.array([r.lon for r in recs])))
    height = interp(np.array([r.height_m for r in recs]))
    pitch = np.clip(interp(_optional(r.pitch_deg for r in recs)), 0.0, 90.0)
    heading = interp(_unwrap_deg(_optional(r.heading_deg for r in recs)))
    roll = interp(_unwrap_deg(np.array([r.roll_deg for r in recs])))
    speed = interp(_optional(r.speed_mps for r in recs))
    vel_e = interp(_optional(None if r.vel_en_mps is None else r.vel_en_mps[0] for r in recs))
    vel_n = interp(_optional(None if r.vel_en_mps is None else r.vel_en_mps[1] for r in recs))
    inside = (query >= t_rec[0] - extrapolate_s) & (query <= t_rec[-1] + extrapolate_s)
    hit = np.clip(np.searchsorted(t_rec, query), 0, len(t_rec) - 1)
    exact = t_rec[hit] == query

    def opt(values: np.ndarray, i: int) -> float | None:
        return None if np.isnan(values[i]) else float(values[i])

    out: list[Telemetry | None] = []
    for i in range(query.size):
        if not inside[i]:
            out.append(None)
            continue
        out.append(
            Telemetry(
                t=float(query[i]),
                lat=float(lat[i]),
                lon=_wrap180(float(lon[i])) if abs(lon[i]) > 180.0 else float(lon[i]),
                height_m=float(height[i]),
                pitch_deg=opt(pitch, i),
                heading_deg=opt(heading, i),
                roll_deg=float(roll[i]),
                speed_mps=None if np.isnan(speed[i]) else max(float(speed[i]), 0.0),
                vel_en_mps=None if np.isnan(vel_e[i]) or np.isnan(vel_n[i]) else (float(vel_e[i]), float(vel_n[i])),
                frame=recs[hit[i]].frame if exact[i] else None,
            )
        )
    return out

"""DJI SRT subtitle files: one record per subtitle block, across the firmware variants DJI has written."""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.telemetry.dates import DATE_START_RE, DATETIME_RE, epoch_from_match
from shared.telemetry.record import Telemetry, pitch_or_none
from shared.telemetry.text import NUM, NUM_RE, read_text

logger = logging.getLogger(__name__)

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
_HEIGHT_H_RE = re.compile(rf"(?<![\w.])H\s*[:=]?\s*({NUM})\s*m(?![/\w])")
_SPEED_HS_RE = re.compile(rf"\bH\.S\s*[:=]?\s*({NUM})\s*m/s")
_METRES_RE = re.compile(rf"({NUM})\s*[mM]?")
_ANGLE_RE = re.compile(rf"({NUM})\s*(?:°|Â°|deg)?")


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


def _srt_number(source: str, line: int, key: str, token: str, pattern: re.Pattern[str] = NUM_RE) -> float:
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
            number_re = _METRES_RE if key == "barometer" else NUM_RE
            block.values[key] = (_srt_number(source, lineno, key, token, number_re), lineno)
        if block.epoch_s is None:
            date = DATETIME_RE.search(line)
            if date is not None:
                try:
                    block.epoch_s = epoch_from_match(date, utc_offset_s)
                except (ValueError, OverflowError) as err:
                    raise _srt_error(source, lineno, f"invalid date-time {date.group(0)!r}: {err}") from None
            elif DATE_START_RE.search(line):
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
        pitch = pitch_or_none(-raw_pitch, f"{source}:{pitch_line}: DJI gimbal pitch {raw_pitch:g}")
    return pitch, heading, roll


def read_srt(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a DJI SRT file; keyword arguments as in `parse_srt` (``source`` defaults to the path)."""
    kw.setdefault("source", str(path))
    return parse_srt(read_text(path), **kw)

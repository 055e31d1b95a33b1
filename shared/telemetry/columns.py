"""Telemetry column and field names with their units (``height_above_takeoff(feet)``, ``speed [m/s]``): the CSV
reader's header and the SeaDronesSee meta's field names are matched here, with each unit's factor to SI."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

__all__ = ["CSV_COLUMNS", "OPTIONAL_FIELDS", "UNITS", "UnknownUnit", "match_column", "split_unit", "unit_rank"]

_TIME_UNITS = {"": 1.0, "s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0,
               "ms": 1e-3, "millisecond": 1e-3, "milliseconds": 1e-3}  # fmt: skip
_LENGTH_UNITS = {"": 1.0, "m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0,
                 "ft": 0.3048, "feet": 0.3048}  # fmt: skip
# "360": a DJI log's yaw written in 0..360 (``GIMBAL.yaw [360]`` beside ``GIMBAL.yaw`` in -180..180)
_ANGLE_UNITS = {"": 1.0, "deg": 1.0, "degree": 1.0, "degrees": 1.0, "360": 1.0,
                "rad": 180.0 / math.pi, "radian": 180.0 / math.pi, "radians": 180.0 / math.pi}  # fmt: skip
_KNOT = 1852.0 / 3600.0
_SPEED_UNITS = {"": 1.0, "m/s": 1.0, "mps": 1.0, "mph": 0.44704, "km/h": 1 / 3.6, "kph": 1 / 3.6,
                "knots": _KNOT, "knot": _KNOT, "kn": _KNOT, "kt": _KNOT, "kts": _KNOT}  # fmt: skip
#: The units a quantity may name, with their factor to SI (`split_unit`).
UNITS = {"length": _LENGTH_UNITS, "angle": _ANGLE_UNITS, "speed": _SPEED_UNITS}

#: field -> (accepted column names in order of preference, accepted units with their factor to SI)
# Besides our own names: AirData (``gimbal_pitch(degrees)``, ``isVideo``), Litchi (``altitude(m)``, ``gimbalPitchRaw``
# in tenths of a degree, ``isTakingVideo``, ``datetime(local)``; its ``pitch(deg)``/``yaw(deg)`` are the aircraft's
# and rank last), DJI logs converted by TXTlogToCSVtool / Flight Reader (``OSD.latitude``, ``OSD.height [ft]``,
# ``GIMBAL.pitch``, ``GIMBAL.yaw [360]``, ``OSD.flyTime [s]``, ``CUSTOM.isVideo``; ``OSD.pitch``/``OSD.yaw`` are the
# aircraft's and are not read).
CSV_COLUMNS: dict[str, tuple[tuple[str, ...], Mapping[str, float]]] = {
    "time": (("time_s", "time", "t", "timestamp", "osd.flytime"), _TIME_UNITS),
    # a date that names its zone first: AirData and Litchi write datetime(utc) beside datetime(local)
    "datetime": (("date_time", "datetime", "datetime_utc"), {"utc": 1.0, "": 1.0, "local": 1.0}),
    "lat": (("lat", "latitude", "osd.latitude"), _ANGLE_UNITS),
    "lon": (("lon", "lng", "longitude", "osd.longitude"), _ANGLE_UNITS),
    "height": (("height_m", "rel_alt", "height_above_takeoff", "height", "altitude", "osd.height"), _LENGTH_UNITS),
    "pitch": (("pitch_deg", "gimbal_pitch", "gb_pitch", "gimbal_pitch_dji", "gimbal.pitch", "gimbalpitchraw", "pitch"),
              _ANGLE_UNITS),
    "heading": (("heading_deg", "gimbal_heading", "gb_yaw", "gimbal.yaw", "gimbalyawraw", "heading", "yaw"),
                _ANGLE_UNITS),
    "roll": (("roll_deg", "gimbal_roll", "gb_roll", "gimbal.roll", "gimbalrollraw", "roll"), _ANGLE_UNITS),
    "speed": (("speed_mps", "speed", "osd.hspeed"), _SPEED_UNITS),
    # DJI flight logs: x north, y east (AirData writes xSpeed(mph), ySpeed(mph))
    "vel_north": (("vel_north_mps", "xspeed", "osd.xspeed"), _SPEED_UNITS),
    "vel_east": (("vel_east_mps", "yspeed", "osd.yspeed"), _SPEED_UNITS),
    "frame": (("frame", "frame_index", "framecnt"), {"": 1.0}),
    "recording": (("isvideo", "is_video", "recording", "istakingvideo", "camera.isvideo", "custom.isvideo"),
                  {"": 1.0}),
}
#: Names whose values are in other steps than their unit says: Litchi's raw gimbal angles are tenths of a degree.
_ALIAS_SCALE = {"gimbalpitchraw": 0.1, "gimbalyawraw": 0.1, "gimbalrollraw": 0.1}
_HEADER_RE = re.compile(r"(?P<name>.*?)\s*(?:\((?P<paren>[^()]*)\)|\[(?P<bracket>[^\[\]]*)\])?")


def split_unit(cell: str) -> tuple[str, str]:
    """A column name or meta key as (name, unit), lower case: ``altitude(feet)`` -> ("altitude", "feet"),
    ``speed [m/s]`` -> ("speed", "m/s"), ``altitude`` -> ("altitude", "")."""
    match = _HEADER_RE.fullmatch(cell.strip().lower())
    assert match is not None  # every string matches: the unit group is optional
    return match["name"].strip(), (match["paren"] or match["bracket"] or "").strip()


#: Fields no pose needs (the ground speed feeds only checks): a column of one in a unit we do not know is left out
#: with a warning, not the whole file or frame.
OPTIONAL_FIELDS = frozenset({"speed", "vel_north", "vel_east"})


class UnknownUnit(ValueError):
    """A column or meta key names a known field in a unit we do not know (`field`: which)."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


def match_column(cell: str) -> tuple[str, str, float] | None:
    """The telemetry field a column name stands for: (field, alias, factor to SI), or None for other columns.

    `cell` is a header cell or a flight-log meta key, matched case-insensitively with an optional unit in
    parentheses or brackets (``height_above_takeoff(feet)`` -> ("height", "height_above_takeoff", 0.3048)).
    UnknownUnit (a ValueError) when the name is known but its unit is not.
    """
    name, unit = split_unit(cell)
    for fld, (aliases, units) in CSV_COLUMNS.items():
        if name not in aliases:
            continue
        if unit not in units:
            accepted = ", ".join(u for u in units if u) or "none"
            raise UnknownUnit(f"column {cell.strip()!r}: unknown unit {unit!r} (accepted: {accepted})", fld)
        return fld, name, units[unit] * _ALIAS_SCALE.get(name, 1.0)
    return None


def unit_rank(field: str, cell: str) -> int:
    """How preferred the unit of a column of `field` is among two columns of one name in two units (``height [m]``
    beside ``height [ft]``, ``datetime(utc)`` beside ``datetime(local)``): lower is preferred."""
    return list(CSV_COLUMNS[field][1]).index(split_unit(cell)[1])

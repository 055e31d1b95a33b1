"""Message schemas other than tiles (DESIGN.md section 4): UAV state, local tracks, global tracks.

Each schema is a frozen dataclass that validates itself, plus msgpack ``encode_*``/``decode_*``
functions. Decoders never raise anything but :class:`MessageError`, whose ``.reason`` is a short
machine-readable string (for counters) and whose message names the field and the offending value.

Forward compatibility: unknown keys in a map are ignored, so producers may add optional fields.
Numbers: float fields accept msgpack ints or floats (never bools); int fields accept ints only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from shared.keys import JOINT_UAV, name_problem, uav_id_problem

__all__ = [
    "DEFAULT_MAX_STATE_BYTES",
    "DEFAULT_MAX_TRACKS_BYTES",
    "MAX_FOOTPRINT_POINTS",
    "MAX_MEMBERS",
    "MAX_TRACKS",
    "MESSAGE_ERROR_REASONS",
    "VERSION",
    "CameraInfo",
    "JointTrackItem",
    "JointTracksMessage",
    "MessageError",
    "StateMessage",
    "TrackItem",
    "TracksMessage",
    "decode_joint_tracks",
    "decode_state",
    "decode_tracks",
    "encode_joint_tracks",
    "encode_joint_tracks_within",
    "encode_state",
    "encode_tracks",
]

VERSION = 1
DEFAULT_MAX_STATE_BYTES = 64 * 1024
DEFAULT_MAX_TRACKS_BYTES = 8 * 1024 * 1024
MAX_FOOTPRINT_POINTS = 256
MAX_TRACKS = 10_000
#: Largest number of local tracks one global track may list as members.
MAX_MEMBERS = 1024
#: Largest accepted track id (ids are unsigned 63-bit so they fit int64 everywhere).
MAX_TRACK_ID = 2**63 - 1
MAX_CAMERA_PIXELS = 100_000

#: Every ``MessageError.reason`` the decoders of this module and of ``shared.tilecodec`` use.
MESSAGE_ERROR_REASONS = frozenset(
    {
        "too_large",  # payload longer than max_bytes
        "not_msgpack",  # not a single well-formed msgpack object
        "not_a_map",  # top level (or a nested record) is not a map
        "missing_field",
        "bad_type",  # wrong type, including bools where numbers are expected
        "bad_version",  # v != 1
        "non_finite",  # NaN or inf
        "out_of_range",  # a number outside its documented range
        "bad_name",  # uav/cls not a valid key chunk (shared.keys.name_problem)
        "bad_length",  # wrong list/bytes length
        "too_many",  # more footprint points / tracks / members than allowed
        "duplicate_id",
        # tile messages (shared.tilecodec)
        "bad_zoom",
        "tile_out_of_range",
        "bad_n",
        "bad_seq",
        "index_out_of_range",
        "duplicate_index",
    }
)


class MessageError(ValueError):
    """A message that does not follow its schema.

    reason: short machine-readable cause, one of ``MESSAGE_ERROR_REASONS``.
    field: dotted path of the offending field (e.g. ``"tracks[3].lat"``), or None.
    """

    def __init__(self, reason: str, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.field = field


# ---- field checks shared with shared.tilecodec ---------------------------------------------------
def check_name(value: object, field: str) -> str:
    """Return a valid UAV id / class name or raise MessageError("bad_type" | "bad_name")."""
    if not isinstance(value, str):
        raise MessageError("bad_type", f"{field} must be a str, got {type(value).__name__}", field)
    problem = name_problem(value)
    if problem is not None:
        raise MessageError("bad_name", f"{field} {problem}", field)
    return value


def check_uav(value: object, field: str, *, allow_joint: bool = False) -> str:
    """Return a valid UAV id (``shared.keys.uav_id_problem``; ``"joint"`` too when ``allow_joint``)
    or raise MessageError("bad_type" | "bad_name")."""
    if allow_joint and value == JOINT_UAV:
        return JOINT_UAV
    if not isinstance(value, str):
        raise MessageError("bad_type", f"{field} must be a str, got {type(value).__name__}", field)
    problem = uav_id_problem(value)
    if problem is not None:
        raise MessageError("bad_name", f"{field} {problem}", field)
    return value


def check_int(value: object, field: str, low: int, high: int, reason: str = "out_of_range") -> int:
    """Return ``value`` as an int in low..high or raise MessageError("bad_type" | ``reason``).

    Accepts Python and numpy integers; bools are refused.
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise MessageError("bad_type", f"{field} must be an int, got {type(value).__name__} {value!r:.40}", field)
    value = int(value)
    if not low <= value <= high:
        raise MessageError(reason, f"{field} must be in {low}..{high}, got {value}", field)
    return value


def check_float(value: object, field: str, low: float = -math.inf, high: float = math.inf) -> float:
    """Return a finite float in [low, high] from an int or float (Python or numpy), else raise MessageError."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.integer | np.floating):
        raise MessageError("bad_type", f"{field} must be a number, got {type(value).__name__} {value!r:.40}", field)
    try:
        number = float(value)
    except OverflowError:  # an int too large for a float
        raise MessageError("out_of_range", f"{field} is too large: {value!r:.40}", field) from None
    if not math.isfinite(number):
        raise MessageError("non_finite", f"{field} must be finite, got {number!r}", field)
    if not low <= number <= high:
        raise MessageError("out_of_range", f"{field} must be in [{low}, {high}], got {number!r}", field)
    return number


def check_version(value: object) -> None:
    """Raise MessageError unless ``value`` is the int ``VERSION`` ("bad_type" | "bad_version")."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise MessageError("bad_type", f"v must be an int, got {type(value).__name__} {value!r:.40}", "v")
    if value != VERSION:
        raise MessageError("bad_version", f"v must be {VERSION}, got {value!r}", "v")


def unpack_map(payload: object, max_bytes: int, error: type[MessageError] = MessageError) -> dict:
    """Unpack a msgpack payload whose top level must be a map; raise ``error`` otherwise.

    payload: bytes, bytearray or memoryview of at most ``max_bytes`` bytes.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise error("bad_type", f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > max_bytes:
        raise error("too_large", f"payload has {len(payload)} bytes, limit {max_bytes}")
    try:
        # unpackb bounds every str/bin/array/map length by len(payload), so garbage cannot make it
        # allocate more than the payload announces
        obj = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=True)
    except Exception as exc:  # msgpack raises many types on garbage; all mean "not msgpack"
        raise error("not_msgpack", f"payload is not a single msgpack object: {exc!r:.120}") from None
    if not isinstance(obj, dict):
        raise error("not_a_map", f"payload must be a msgpack map, got {type(obj).__name__}")
    return obj


def get_field(record: Mapping[Any, Any], key: str, path: str = "") -> Any:
    """``record[key]`` or MessageError("missing_field") naming ``path + key``."""
    try:
        return record[key]
    except KeyError:
        raise MessageError("missing_field", f"missing field {path}{key}", path + key) from None


def _check_list(value: object, field: str, max_len: int, exact: int | None = None) -> list:
    if isinstance(value, np.ndarray):  # constructors may pass arrays, e.g. a (k, 2) footprint
        value = value.tolist()
    if not isinstance(value, list | tuple):
        raise MessageError("bad_type", f"{field} must be a list, got {type(value).__name__}", field)
    if exact is not None and len(value) != exact:
        raise MessageError("bad_length", f"{field} must have {exact} items, got {len(value)}", field)
    if len(value) > max_len:
        raise MessageError("too_many", f"{field} must have at most {max_len} items, got {len(value)}", field)
    return list(value)


def _check_map(value: object, field: str) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise MessageError("not_a_map", f"{field} must be a map, got {type(value).__name__}", field)
    return value


def _check_vel(value: object, field: str) -> tuple[float, float]:
    east, north = _check_list(value, field, 2, exact=2)
    return check_float(east, f"{field}[0]"), check_float(north, f"{field}[1]")


def _set(obj: object, name: str, value: Any) -> Any:
    """Store a normalised value (e.g. np.float32 -> float) on a frozen dataclass; returns it."""
    object.__setattr__(obj, name, value)
    return value


def _pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


# ---- state --------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class CameraInfo:
    """Pinhole intrinsics in a state message: image size in pixels, focal lengths and principal point.

    width, height: ints in 1..100000; fx, fy: finite > 0 pixels; cx, cy: finite pixels.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        _set(self, "width", check_int(self.width, "camera.width", 1, MAX_CAMERA_PIXELS))
        _set(self, "height", check_int(self.height, "camera.height", 1, MAX_CAMERA_PIXELS))
        for name in ("fx", "fy"):
            field = f"camera.{name}"
            if _set(self, name, check_float(getattr(self, name), field)) <= 0.0:
                raise MessageError("out_of_range", f"{field} must be > 0, got {getattr(self, name)!r}", field)
        _set(self, "cx", check_float(self.cx, "camera.cx"))
        _set(self, "cy", check_float(self.cy, "camera.cy"))

    def to_dict(self) -> dict[str, Any]:
        """The msgpack map ``{width, height, fx, fy, cx, cy}``."""
        return {
            "width": self.width,
            "height": self.height,
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
        }


@dataclass(frozen=True, slots=True)
class StateMessage:
    """A UAV's pose and view at time ``t`` (published each cycle on ``uav/{uav}/state``).

    t: seconds since the UNIX epoch (finite). lat in [-90, 90], lon in [-180, 180] degrees.
    height_m: finite metres above the ground plane. pitch_deg: depression below the horizon in
    [-90, 90] (90 = nadir; negative = looking up, allowed here although geo.Pose takes 0..90).
    heading_deg: clockwise from true north, in [-360, 360]. footprint: up to 256 ground polygon
    vertices ``((lat, lon), ...)``, empty when unknown. camera: intrinsics.
    """

    uav: str
    t: float
    lat: float
    lon: float
    height_m: float
    pitch_deg: float
    heading_deg: float
    footprint: tuple[tuple[float, float], ...]
    camera: CameraInfo

    def __post_init__(self) -> None:
        check_uav(self.uav, "uav")
        _set(self, "t", check_float(self.t, "t"))
        _set(self, "lat", check_float(self.lat, "lat", -90.0, 90.0))
        _set(self, "lon", check_float(self.lon, "lon", -180.0, 180.0))
        _set(self, "height_m", check_float(self.height_m, "height_m"))
        _set(self, "pitch_deg", check_float(self.pitch_deg, "pitch_deg", -90.0, 90.0))
        _set(self, "heading_deg", check_float(self.heading_deg, "heading_deg", -360.0, 360.0))
        points = _check_list(self.footprint, "footprint", MAX_FOOTPRINT_POINTS)
        footprint = []
        for i, point in enumerate(points):
            lat, lon = _check_list(point, f"footprint[{i}]", 2, exact=2)
            footprint.append(
                (
                    check_float(lat, f"footprint[{i}][0]", -90.0, 90.0),
                    check_float(lon, f"footprint[{i}][1]", -180.0, 180.0),
                )
            )
        object.__setattr__(self, "footprint", tuple(footprint))
        if not isinstance(self.camera, CameraInfo):
            raise MessageError("bad_type", f"camera must be a CameraInfo, got {type(self.camera).__name__}", "camera")


_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy")


def encode_state(msg: StateMessage) -> bytes:
    """msgpack bytes of a state message (map with ``v = 1``)."""
    return _pack(
        {
            "v": VERSION,
            "uav": msg.uav,
            "t": float(msg.t),
            "lat": float(msg.lat),
            "lon": float(msg.lon),
            "height_m": float(msg.height_m),
            "pitch_deg": float(msg.pitch_deg),
            "heading_deg": float(msg.heading_deg),
            "footprint": [[float(lat), float(lon)] for lat, lon in msg.footprint],
            "camera": msg.camera.to_dict(),
        }
    )


def decode_state(payload: bytes, *, max_bytes: int = DEFAULT_MAX_STATE_BYTES) -> StateMessage:
    """Parse and validate a state message; raise MessageError on anything malformed."""
    record = unpack_map(payload, max_bytes)
    check_version(get_field(record, "v"))
    camera = _check_map(get_field(record, "camera"), "camera")
    camera_info = CameraInfo(**{k: get_field(camera, k, "camera.") for k in _CAMERA_FIELDS})
    return StateMessage(
        uav=check_uav(get_field(record, "uav"), "uav"),
        t=check_float(get_field(record, "t"), "t"),
        lat=check_float(get_field(record, "lat"), "lat"),
        lon=check_float(get_field(record, "lon"), "lon"),
        height_m=check_float(get_field(record, "height_m"), "height_m"),
        pitch_deg=check_float(get_field(record, "pitch_deg"), "pitch_deg"),
        heading_deg=check_float(get_field(record, "heading_deg"), "heading_deg"),
        footprint=get_field(record, "footprint"),
        camera=camera_info,
    )


# ---- local tracks ------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class TrackItem:
    """One local track of a UAV.

    id: the UAV's local track id, an int in 0..2**63-1 (ints, not strings, so ids are cheap to
    compare and store; a global track refers to it as ``(uav, id)``). cls: class name.
    lat, lon: degrees. score: confidence in [0, 1]. vel_en: (east, north) velocity, m/s, finite.
    """

    id: int
    cls: str
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]

    def __post_init__(self) -> None:
        _set(self, "id", check_int(self.id, "id", 0, MAX_TRACK_ID))
        _check_track_body(self, "")

    def to_dict(self) -> dict[str, Any]:
        """The msgpack map ``{id, cls, lat, lon, score, vel_en}``."""
        return {"id": self.id, **_track_body(self)}


def _check_track_body(item: TrackItem | JointTrackItem, path: str) -> None:
    check_name(item.cls, f"{path}cls")
    _set(item, "lat", check_float(item.lat, f"{path}lat", -90.0, 90.0))
    _set(item, "lon", check_float(item.lon, f"{path}lon", -180.0, 180.0))
    _set(item, "score", check_float(item.score, f"{path}score", 0.0, 1.0))
    _set(item, "vel_en", _check_vel(item.vel_en, f"{path}vel_en"))


def _track_body(item: TrackItem | JointTrackItem) -> dict[str, Any]:
    return {
        "cls": item.cls,
        "lat": float(item.lat),
        "lon": float(item.lon),
        "score": float(item.score),
        "vel_en": [float(item.vel_en[0]), float(item.vel_en[1])],
    }


def _track_kwargs(record: Mapping[Any, Any], path: str) -> dict[str, Any]:
    return {
        "cls": check_name(get_field(record, "cls", path), f"{path}cls"),
        "lat": check_float(get_field(record, "lat", path), f"{path}lat", -90.0, 90.0),
        "lon": check_float(get_field(record, "lon", path), f"{path}lon", -180.0, 180.0),
        "score": check_float(get_field(record, "score", path), f"{path}score", 0.0, 1.0),
        "vel_en": _check_vel(get_field(record, "vel_en", path), f"{path}vel_en"),
    }


def _check_items(value: object, item_type: type, id_attr: str) -> tuple:
    """The ``tracks`` of a tracks message: a list of at most MAX_TRACKS ``item_type`` with unique ``id_attr``.

    The one validator of a message's item list (local and global tracks alike); MessageError
    ("bad_type" | "too_many" | "duplicate_id") naming the item.
    """
    items = tuple(_check_list(value, "tracks", MAX_TRACKS))
    seen: set[int] = set()
    for i, item in enumerate(items):
        if not isinstance(item, item_type):
            raise MessageError("bad_type", f"tracks[{i}] must be a {item_type.__name__}", f"tracks[{i}]")
        track_id = getattr(item, id_attr)
        if track_id in seen:
            field = f"tracks {id_attr}"
            raise MessageError("duplicate_id", f"{field} {track_id} appears more than once", field)
        seen.add(track_id)
    return items


def _decode_tracks_message(payload: bytes, max_bytes: int, check_sender: Any, item: Any) -> tuple[str, float, list]:
    """Decode the envelope of a tracks message (v, uav, t) and each ``tracks[i]`` with ``item(raw, path)``.

    check_sender validates ``uav``; item builds one validated item from its map and its field path.
    """
    record = unpack_map(payload, max_bytes)
    check_version(get_field(record, "v"))
    uav = check_sender(get_field(record, "uav"), "uav")
    t = check_float(get_field(record, "t"), "t")
    items = []
    for i, raw in enumerate(_check_list(get_field(record, "tracks"), "tracks", MAX_TRACKS)):
        items.append(item(_check_map(raw, f"tracks[{i}]"), f"tracks[{i}]."))
    return uav, t, items


def _encode_tracks_message(msg: TracksMessage | JointTracksMessage) -> bytes:
    return _pack({"v": VERSION, "uav": msg.uav, "t": float(msg.t), "tracks": [item.to_dict() for item in msg.tracks]})


@dataclass(frozen=True, slots=True)
class TracksMessage:
    """A UAV's local tracks at time ``t`` (``uav/{uav}/tracks``): at most 10,000, ids unique."""

    uav: str
    t: float
    tracks: tuple[TrackItem, ...]

    def __post_init__(self) -> None:
        check_uav(self.uav, "uav")
        _set(self, "t", check_float(self.t, "t"))
        _set(self, "tracks", _check_items(self.tracks, TrackItem, "id"))


def encode_tracks(msg: TracksMessage) -> bytes:
    """msgpack bytes of a local tracks message."""
    return _encode_tracks_message(msg)


def decode_tracks(payload: bytes, *, max_bytes: int = DEFAULT_MAX_TRACKS_BYTES) -> TracksMessage:
    """Parse and validate a local tracks message; raise MessageError on anything malformed."""
    def item(raw: Mapping[Any, Any], path: str) -> TrackItem:
        track_id = check_int(get_field(raw, "id", path), f"{path}id", 0, MAX_TRACK_ID)
        return TrackItem(id=track_id, **_track_kwargs(raw, path))

    uav, t, items = _decode_tracks_message(payload, max_bytes, check_uav, item)
    return TracksMessage(uav=uav, t=t, tracks=tuple(items))


# ---- global (joint) tracks ---------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class JointTrackItem:
    """One global track of the fusion server.

    gid: global id, int in 0..2**63-1. cls, lat, lon, score, vel_en: as in :class:`TrackItem`.
    members: the local tracks it absorbed, ``((uav, local_id), ...)``, at most 1024, no repeats.
    active (optional extension, docs/protocol.md): indexes into ``members`` of the members their UAVs
    still report (distinct; kept increasing); ``()`` for a track nobody reports (held, "lost"). None when the message
    does not say, which means every member reports it (the field is left out then, and messages of
    servers older than the field read so).
    """

    gid: int
    cls: str
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]
    members: tuple[tuple[str, int], ...]
    active: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        _set(self, "gid", check_int(self.gid, "gid", 0, MAX_TRACK_ID))
        _check_track_body(self, "")
        object.__setattr__(self, "members", check_members(self.members, "members"))
        if self.active is not None:
            _set(self, "active", _check_active(self.active, "active", len(self.members)))

    @property
    def active_members(self) -> tuple[tuple[str, int], ...]:
        """The members still reporting the track (all of them when ``active`` is None)."""
        if self.active is None:
            return self.members
        return tuple(self.members[i] for i in self.active)

    def to_dict(self) -> dict[str, Any]:
        """The msgpack map ``{gid, cls, lat, lon, score, vel_en, members}``, and ``active`` unless None."""
        body = {
            "gid": self.gid,
            **_track_body(self),
            "members": [[uav, local_id] for uav, local_id in self.members],
        }
        if self.active is not None:
            body["active"] = list(self.active)
        return body


def _check_active(value: object, field: str, n_members: int) -> tuple[int, ...]:
    """Distinct member indexes in 0..n_members-1, returned increasing; MessageError naming ``field``
    ("bad_type" | "too_many" | "out_of_range" | "duplicate_index") otherwise."""
    indexes = [check_int(v, f"{field}[{i}]", 0, max(n_members - 1, 0))
               for i, v in enumerate(_check_list(value, field, MAX_MEMBERS))]
    if n_members == 0 and indexes:
        raise MessageError("out_of_range", f"{field} names members of a track without any", field)
    distinct = sorted(set(indexes))
    if len(distinct) != len(indexes):
        raise MessageError("duplicate_index", f"{field} repeats a member index", field)
    return tuple(distinct)


def check_members(value: object, field: str) -> tuple[tuple[str, int], ...]:
    """``((uav, local_id), ...)`` of a global track: at most MAX_MEMBERS valid, distinct pairs; else MessageError."""
    members = []
    for i, member in enumerate(_check_list(value, field, MAX_MEMBERS)):
        uav, local_id = _check_list(member, f"{field}[{i}]", 2, exact=2)
        members.append((check_uav(uav, f"{field}[{i}][0]"), check_int(local_id, f"{field}[{i}][1]", 0, MAX_TRACK_ID)))
    if len(set(members)) != len(members):
        raise MessageError("duplicate_id", f"{field} repeat a (uav, id) pair", field)
    return tuple(members)


@dataclass(frozen=True, slots=True)
class JointTracksMessage:
    """The fusion server's global tracks at time ``t`` (``joint/tracks``); ``uav`` is always "joint"."""

    t: float
    tracks: tuple[JointTrackItem, ...]
    uav: str = JOINT_UAV

    def __post_init__(self) -> None:
        if self.uav != JOINT_UAV:
            raise MessageError("bad_name", f"uav must be {JOINT_UAV!r}, got {self.uav!r:.40}", "uav")
        _set(self, "t", check_float(self.t, "t"))
        _set(self, "tracks", _check_items(self.tracks, JointTrackItem, "gid"))


def encode_joint_tracks(msg: JointTracksMessage) -> bytes:
    """msgpack bytes of a global tracks message."""
    return _encode_tracks_message(msg)


def encode_joint_tracks_within(make: Callable[[int], JointTracksMessage],
                               max_bytes: int) -> tuple[JointTracksMessage, bytes]:
    """The largest global tracks message ``make(limit)`` gives that encodes within ``max_bytes`` (limit MAX_TRACKS,
    halved while too large; at 1 track it is taken as it is), and its bytes. ``make`` orders the tracks it keeps
    (tracked ones first): a flood of tracks shortens the message instead of stopping it."""
    limit = MAX_TRACKS
    while True:
        message = make(limit)
        payload = encode_joint_tracks(message)
        if len(payload) <= max_bytes or limit <= 1:
            return message, payload
        limit = len(message.tracks) // 2


def decode_joint_tracks(payload: bytes, *, max_bytes: int = DEFAULT_MAX_TRACKS_BYTES) -> JointTracksMessage:
    """Parse and validate a global tracks message; raise MessageError on anything malformed."""
    def item(raw: Mapping[Any, Any], path: str) -> JointTrackItem:
        members = check_members(get_field(raw, "members", path), f"{path}members")
        active = raw.get("active")  # optional: absent in older servers' messages
        return JointTrackItem(
            gid=check_int(get_field(raw, "gid", path), f"{path}gid", 0, MAX_TRACK_ID),
            members=members,
            active=None if active is None else _check_active(active, f"{path}active", len(members)),
            **_track_kwargs(raw, path),
        )

    uav, t, items = _decode_tracks_message(payload, max_bytes, check_name, item)
    return JointTracksMessage(uav=uav, t=t, tracks=tuple(items))

"""Zenoh key space of uav-memory-maps (DESIGN.md section 4): key builders, selectors and a parser.

Every key lives under one prefix (default ``uavmm/v1``); names (UAV ids, class names) are single key
chunks, so they are validated here and by the message codecs with the same rule (:func:`name_problem`);
UAV ids, which are identities, with the stricter :func:`uav_id_problem` (ASCII, no homoglyphs).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

__all__ = [
    "DEFAULT_PREFIX",
    "JOINT_UAV",
    "KEY_KINDS",
    "MAX_NAME_LEN",
    "MAX_ZOOM",
    "TRACK_REGION_ZOOM_DROP",
    "KeySpace",
    "ParsedKey",
    "name_problem",
    "track_region",
    "uav_id_problem",
    "validate_name",
    "validate_uav_id",
]

DEFAULT_PREFIX = "uavmm/v1"
#: Value of the ``uav`` field of messages published by the fusion server (and of ParsedKey.uav for
#: ``joint/...`` keys), so "message uav equals key uav" is one uniform check.
JOINT_UAV = "joint"
MAX_NAME_LEN = 128
MAX_ZOOM = 24
KEY_KINDS = ("uav_tile", "uav_state", "uav_tracks", "uav_alive", "joint_tile", "joint_tracks", "region_tracks",
             "region_state")
#: Joint tracks are also published per region: the tile of the grid's zoom minus this (z 16 for z 18,
#: 4 x 4 grid tiles, ~610 m at 48 N), so a UAV subscribes to the one to four regions its window touches.
TRACK_REGION_ZOOM_DROP = 2

# Characters with a meaning in Zenoh key expressions ('/' separates chunks, the rest are wildcards or
# reserved); '@' is refused only as the first character because Zenoh treats '@...' chunks as verbatim
# chunks that wildcards never match.
_FORBIDDEN_CHARS = frozenset("/*$?#")
_DECIMAL = re.compile(r"(?:0|[1-9][0-9]*)\Z")
#: A UAV id is an identity (it names keys, ACL rules and certificates): ASCII letters, digits and
#: ``_ . -`` only, starting with a letter or digit, so no two ids look alike (no homoglyphs such as a
#: Cyrillic 'а' in 'uаv1', no invisible characters) and every id is safe in a file name or a config.
_UAV_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*\Z")
#: Names and UAV ids found valid (a fleet repeats a few in every message): checked once, not per
#: message. Bounded: beyond _MAX_KNOWN they are checked every time.
_KNOWN_NAMES: set[str] = set()
_KNOWN_UAV_IDS: set[str] = set()
_MAX_KNOWN = 65_536


def name_problem(value: object) -> str | None:
    """Say why ``value`` is not a valid UAV id or class name, or return None when it is valid.

    A valid name is a ``str`` of 1..128 characters, all printable, none of them whitespace or one of
    ``/ * $ ? #``, and not starting with ``@``. Such a name is exactly one Zenoh key chunk.
    """
    if type(value) is str and value in _KNOWN_NAMES:
        return None
    if not isinstance(value, str):
        return f"must be a str, got {type(value).__name__}"
    if not value:
        return "must not be empty"
    if len(value) > MAX_NAME_LEN:
        return f"must have at most {MAX_NAME_LEN} characters, got {len(value)}"
    if value.startswith("@"):
        return f"must not start with '@', got {value!r}"
    for char in value:
        if char in _FORBIDDEN_CHARS:
            return f"must not contain {char!r}, got {value!r}"
        if char.isspace() or not char.isprintable():
            return f"must not contain whitespace or non-printable characters, got {value!r}"
    if type(value) is str and len(_KNOWN_NAMES) < _MAX_KNOWN:
        _KNOWN_NAMES.add(value)
    return None


def uav_id_problem(value: object) -> str | None:
    """Say why ``value`` is not a valid UAV id, or return None when it is valid.

    A UAV id is a :func:`name_problem`-valid name made of ASCII letters, digits, ``_``, ``.`` and
    ``-`` only, starting with a letter or digit, and not ``"joint"`` (reserved for the fusion
    server's own messages).
    """
    if type(value) is str and value in _KNOWN_UAV_IDS:
        return None
    problem = name_problem(value)
    if problem is not None:
        return problem
    assert isinstance(value, str)
    if not _UAV_ID.match(value):
        return f"must use only ASCII letters, digits, '_', '.' and '-' and start with a letter or digit, got {value!r}"
    if value == JOINT_UAV:
        return f"{JOINT_UAV!r} is reserved for the fusion server"
    if type(value) is str and len(_KNOWN_UAV_IDS) < _MAX_KNOWN:
        _KNOWN_UAV_IDS.add(value)
    return None


def validate_uav_id(value: object, field: str = "uav") -> str:
    """Return ``value`` if it is a valid UAV id (see :func:`uav_id_problem`), else raise ValueError."""
    problem = uav_id_problem(value)
    if problem is not None:
        raise ValueError(f"{field} {problem}")
    return value  # type: ignore[return-value]


def validate_name(value: object, field: str) -> str:
    """Return ``value`` if it is a valid name (see :func:`name_problem`), else raise ValueError.

    ``field`` names the argument in the error message, e.g. ``"uav"`` or ``"cls"``.
    """
    problem = name_problem(value)
    if problem is not None:
        raise ValueError(f"{field} {problem}")
    return value  # type: ignore[return-value]


def _validate_int(value: object, field: str, low: int, high: int) -> int:
    # bool is an int subclass but never a valid coordinate
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{field} must be an int, got {type(value).__name__} {value!r}")
    value = int(value)  # type: ignore[arg-type]
    if not low <= value <= high:
        raise ValueError(f"{field} must be in {low}..{high}, got {value}")
    return value


def _validate_tile(z: object, x: object, y: object) -> tuple[int, int, int]:
    z = _validate_int(z, "z", 0, MAX_ZOOM)
    side = 1 << z
    x = _validate_int(x, "x", 0, side - 1)
    y = _validate_int(y, "y", 0, side - 1)
    return z, x, y


def track_region(z: int, x: int, y: int) -> tuple[int, int, int]:
    """The region tile (z - TRACK_REGION_ZOOM_DROP, x >> drop, y >> drop) of grid tile (z, x, y)."""
    drop = min(TRACK_REGION_ZOOM_DROP, z)
    return z - drop, x >> drop, y >> drop


def _name_or_star(value: object, field: str) -> str:
    if value == "*":
        return "*"
    return validate_name(value, field)


def _uav_or_star(value: object) -> str:
    if value == "*":
        return "*"
    return validate_uav_id(value, "uav")


@dataclass(frozen=True, slots=True)
class ParsedKey:
    """A key of the key space taken apart by :meth:`KeySpace.parse`.

    kind: one of ``KEY_KINDS``. ``uav`` is the UAV id, or ``"joint"`` for ``joint/...`` keys (but the
    forwarded state's UAV for ``region/states/...``).
    ``cls``, ``z``, ``x``, ``y`` are set for tile keys and None otherwise.
    """

    kind: str
    uav: str
    cls: str | None = None
    z: int | None = None
    x: int | None = None
    y: int | None = None


@dataclass(frozen=True, slots=True)
class KeySpace:
    """Builders and parser for the keys under one prefix.

    prefix: one or more non-empty key chunks separated by ``/`` (default ``uavmm/v1``), without
    wildcards and without a leading or trailing ``/``.

    Builders that take ``uav="*"`` (or ``cls="*"``) return a selector for all UAVs (classes); every
    other name must pass :func:`validate_name`. All builders raise ValueError naming the bad field.
    """

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        if not isinstance(self.prefix, str) or not self.prefix:
            raise ValueError(f"prefix must be a non-empty str, got {self.prefix!r}")
        for chunk in self.prefix.split("/"):
            problem = name_problem(chunk)
            if problem is not None:
                raise ValueError(f"prefix chunk {chunk!r} of {self.prefix!r} {problem}")

    # ---- per-UAV keys -------------------------------------------------------------------------
    def uav_tile(self, uav: str, cls: str, z: int, x: int, y: int) -> str:
        """Key of one tile of one UAV: ``{prefix}/uav/{uav}/tiles/{cls}/{z}/{x}/{y}``."""
        uav = validate_uav_id(uav, "uav")
        cls = validate_name(cls, "cls")
        z, x, y = _validate_tile(z, x, y)
        return f"{self.prefix}/uav/{uav}/tiles/{cls}/{z}/{x}/{y}"

    def uav_tiles_all(self, uav: str = "*", cls: str | None = None) -> str:
        """Selector of tiles: ``{prefix}/uav/{uav}/tiles/**``, or ``.../tiles/{cls}/**`` with ``cls``."""
        uav = _uav_or_star(uav)
        if cls is None:
            return f"{self.prefix}/uav/{uav}/tiles/**"
        cls = _name_or_star(cls, "cls")
        return f"{self.prefix}/uav/{uav}/tiles/{cls}/**"

    def uav_state(self, uav: str) -> str:
        """Key of a UAV's state message: ``{prefix}/uav/{uav}/state`` (``uav="*"``: all UAVs)."""
        return f"{self.prefix}/uav/{_uav_or_star(uav)}/state"

    def uav_tracks(self, uav: str) -> str:
        """Key of a UAV's local tracks: ``{prefix}/uav/{uav}/tracks`` (``uav="*"``: all UAVs)."""
        return f"{self.prefix}/uav/{_uav_or_star(uav)}/tracks"

    def uav_alive(self, uav: str) -> str:
        """Key of a UAV's liveliness token: ``{prefix}/uav/{uav}/alive`` (``uav="*"``: all UAVs)."""
        return f"{self.prefix}/uav/{_uav_or_star(uav)}/alive"

    def uav_all(self) -> str:
        """Selector of everything the agents publish: ``{prefix}/uav/**``."""
        return f"{self.prefix}/uav/**"

    # ---- fusion (joint) keys ------------------------------------------------------------------
    def joint_tile(self, cls: str, z: int, x: int, y: int) -> str:
        """Key of one fused tile: ``{prefix}/joint/tiles/{cls}/{z}/{x}/{y}``."""
        cls = validate_name(cls, "cls")
        z, x, y = _validate_tile(z, x, y)
        return f"{self.prefix}/joint/tiles/{cls}/{z}/{x}/{y}"

    def joint_tiles_all(self, cls: str = "*") -> str:
        """Selector of fused tiles: ``{prefix}/joint/tiles/{cls}/**`` (``cls="*"``: all classes)."""
        return f"{self.prefix}/joint/tiles/{_name_or_star(cls, 'cls')}/**"

    def joint_tracks(self) -> str:
        """Key of the global tracks: ``{prefix}/joint/tracks``."""
        return f"{self.prefix}/joint/tracks"

    def region_tracks(self, z: int, x: int, y: int) -> str:
        """Key of the global tracks inside one region tile: ``{prefix}/region/tracks/{z}/{x}/{y}``
        (z = grid zoom - TRACK_REGION_ZOOM_DROP; see :func:`track_region`)."""
        z, x, y = _validate_tile(z, x, y)
        return f"{self.prefix}/region/tracks/{z}/{x}/{y}"

    def region_tracks_all(self) -> str:
        """Selector of every region's global tracks: ``{prefix}/region/tracks/**``."""
        return f"{self.prefix}/region/tracks/**"

    def region_state(self, z: int, x: int, y: int, uav: str) -> str:
        """Key of a UAV's state message as the fusion server forwards it to a region its footprint
        touches: ``{prefix}/region/states/{z}/{x}/{y}/{uav}`` (regions as :meth:`region_tracks`)."""
        z, x, y = _validate_tile(z, x, y)
        return f"{self.prefix}/region/states/{z}/{x}/{y}/{validate_uav_id(uav, 'uav')}"

    def region_states(self, z: int, x: int, y: int) -> str:
        """Selector of the states forwarded to one region: ``{prefix}/region/states/{z}/{x}/{y}/*``."""
        z, x, y = _validate_tile(z, x, y)
        return f"{self.prefix}/region/states/{z}/{x}/{y}/*"

    def region_all(self) -> str:
        """Selector (and queryable) of the fusion server's per-region messages: ``{prefix}/region/**``.

        Outside ``{prefix}/joint/**`` on purpose: that selector keeps exactly DESIGN.md's joint tiles and
        global tracks for its subscribers and late-join queries.
        """
        return f"{self.prefix}/region/**"

    def shard_alive(self, index: int | str, count: int | str, region_zoom: int | str = "*") -> str:
        """Liveliness token of fusion shard ``index`` of ``count`` over regions of zoom ``region_zoom``:
        ``{prefix}/fusion/shards/{count}/{index}/{region_zoom}`` (any of them ``"*"``: a selector)."""
        parts = []
        for name, value in (("count", count), ("index", index), ("region zoom", region_zoom)):
            if value == "*":
                parts.append("*")
            elif isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"shard {name} must be an int >= 0 or '*', got {value!r}")
            else:
                parts.append(str(value))
        return f"{self.prefix}/fusion/shards/{'/'.join(parts)}"

    def parse_shard_token(self, key: str) -> tuple[int, int, int]:
        """(index, count, region zoom) of a shard liveliness key; ValueError for any other key."""
        head = f"{self.prefix}/fusion/shards/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or not all(_DECIMAL.match(p) for p in parts):
            raise ValueError(f"key {key!r} is not a shard liveliness key {head}COUNT/INDEX/REGION_ZOOM")
        count, index, zoom = (int(p) for p in parts)
        if not 0 <= index < count:
            raise ValueError(f"key {key!r}: shard index {index} is not below the count {count}")
        return index, count, zoom

    def parse_shard_alive(self, key: str) -> tuple[int, int]:
        """(index, count) of a shard liveliness key; ValueError for any other key."""
        index, count, _ = self.parse_shard_token(key)
        return index, count

    def shard_tracks(self, index: int | str, count: int | str) -> str:
        """Queryable of fusion shard ``index`` of ``count`` answering with its global tracks and their
        history (``fusion_server.shard_tracks``): ``{prefix}/fusion/tracks/{count}/{index}`` (either
        ``"*"``: a selector, e.g. the gateway's ``fusion/tracks/{count}/*``)."""
        parts = []
        for name, value in (("count", count), ("index", index)):
            if value == "*":
                parts.append("*")
            elif isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"shard {name} must be an int >= 0 or '*', got {value!r}")
            else:
                parts.append(str(value))
        return f"{self.prefix}/fusion/tracks/{'/'.join(parts)}"

    def parse_shard_tracks(self, key: str) -> tuple[int, int]:
        """(index, count) of a :meth:`shard_tracks` key; ValueError for any other key."""
        head = f"{self.prefix}/fusion/tracks/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 2 or not all(_DECIMAL.match(p) for p in parts):
            raise ValueError(f"key {key!r} is not a shard tracks key {head}COUNT/INDEX")
        count, index = (int(p) for p in parts)
        if not 0 <= index < count:
            raise ValueError(f"key {key!r}: shard index {index} is not below the count {count}")
        return index, count

    def uav_bucket_tile(self, uav: str, region_zoom: int, bucket: int, cls: str, z: int, x: int, y: int) -> str:
        """Key of one tile of one UAV routed to its fusion shard:
        ``{prefix}/uav/{uav}/shard/{region_zoom}/{bucket}/tiles/{cls}/{z}/{x}/{y}`` (``shared.sharding``: the
        bucket of the tile's region; a shard subscribes to its buckets only). Parsed as kind ``uav_tile``."""
        for name, value in (("region_zoom", region_zoom), ("bucket", bucket)):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 1024:
                raise ValueError(f"{name} must be an int in 0..1023, got {value!r}")
        return (f"{self.prefix}/uav/{validate_uav_id(uav, 'uav')}/shard/{region_zoom}/{bucket}/tiles/"
                f"{validate_name(cls, 'cls')}/{'/'.join(str(v) for v in _validate_tile(z, x, y))}")

    def uav_bucket_tiles(self, region_zoom: int, bucket: int) -> str:
        """Selector of every UAV's tiles of one bucket: ``{prefix}/uav/*/shard/{region_zoom}/{bucket}/tiles/**``."""
        return f"{self.prefix}/uav/*/shard/{int(region_zoom)}/{int(bucket)}/tiles/**"

    def joint_all(self) -> str:
        """Selector (and queryable) of everything the fusion server publishes: ``{prefix}/joint/**``."""
        return f"{self.prefix}/joint/**"

    # ---- parser ------------------------------------------------------------------------------
    def parse(self, key: str) -> ParsedKey:
        """Take a concrete key of this key space apart.

        Raises ValueError for anything that :meth:`uav_tile`, :meth:`uav_state`, :meth:`uav_tracks`,
        :meth:`uav_alive`, :meth:`joint_tile` or :meth:`joint_tracks` would not build: another
        prefix, wildcards, unknown layout, invalid names, non-canonical integers (``"07"``, ``"+7"``)
        and tiles outside the zoom level.
        """
        if not isinstance(key, str):
            raise ValueError(f"key must be a str, got {type(key).__name__}")
        head = self.prefix + "/"
        if not key.startswith(head):
            raise ValueError(f"key {key!r} is not under prefix {self.prefix!r}")
        parts = key[len(head) :].split("/")
        try:
            return self._parse_parts(parts)
        except ValueError as exc:
            raise ValueError(f"key {key!r}: {exc}") from None

    def _parse_parts(self, parts: list[str]) -> ParsedKey:
        if parts[0] == "uav" and len(parts) >= 3:
            uav = validate_uav_id(parts[1], "uav")
            rest = parts[2:]
            if len(rest) == 1 and rest[0] in ("state", "tracks", "alive"):
                return ParsedKey(kind=f"uav_{rest[0]}", uav=uav)
            if len(rest) == 5 and rest[0] == "tiles":
                cls, z, x, y = self._parse_tile(rest[1:])
                return ParsedKey(kind="uav_tile", uav=uav, cls=cls, z=z, x=x, y=y)
            if len(rest) == 8 and rest[0] == "shard" and rest[3] == "tiles":
                if not (_DECIMAL.match(rest[1]) and _DECIMAL.match(rest[2])):
                    raise ValueError(f"region zoom and bucket must be canonical decimal integers, got "
                                     f"{rest[1]!r}, {rest[2]!r}")
                cls, z, x, y = self._parse_tile(rest[4:])
                return ParsedKey(kind="uav_tile", uav=uav, cls=cls, z=z, x=x, y=y)
        elif parts[0] == "region":
            if len(parts) == 5 and parts[1] == "tracks":
                _, z, x, y = self._parse_tile(["tracks", *parts[2:]])
                return ParsedKey(kind="region_tracks", uav=JOINT_UAV, z=z, x=x, y=y)
            if len(parts) == 6 and parts[1] == "states":
                _, z, x, y = self._parse_tile(["states", *parts[2:5]])
                return ParsedKey(kind="region_state", uav=validate_uav_id(parts[5], "uav"), z=z, x=x, y=y)
        elif parts[0] == "joint":
            if parts[1:] == ["tracks"]:
                return ParsedKey(kind="joint_tracks", uav=JOINT_UAV)
            if len(parts) == 6 and parts[1] == "tiles":
                cls, z, x, y = self._parse_tile(parts[2:])
                return ParsedKey(kind="joint_tile", uav=JOINT_UAV, cls=cls, z=z, x=x, y=y)
        raise ValueError(f"unknown key layout {'/'.join(parts)!r}")

    @staticmethod
    def _parse_tile(parts: list[str]) -> tuple[str, int, int, int]:
        cls = validate_name(parts[0], "cls")
        numbers = []
        for field, text in zip(("z", "x", "y"), parts[1:], strict=True):
            if not _DECIMAL.match(text):
                raise ValueError(f"{field} must be a canonical decimal integer, got {text!r}")
            numbers.append(int(text))
        z, x, y = _validate_tile(*numbers)
        return cls, z, x, y

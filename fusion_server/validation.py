"""Validation of every message the agents publish (DESIGN.md 4): key, payload schema, key/payload agreement.

:meth:`MessageValidator.validate` turns ``(key, payload)`` into a decoded message or raises
:class:`Rejected` with a short machine-readable ``reason`` (for the rejection counters). Given the UAVs' clocks
(fusion_server.uav_clocks), a message of a UAV whose clock is known to run ahead comes out moved onto the server's.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from shared.keys import KeySpace, ParsedKey
from shared.messages import (
    DEFAULT_MAX_STATE_BYTES,
    MESSAGE_ERROR_REASONS,
    MessageError,
    StateMessage,
    TracksMessage,
    decode_state,
    decode_tracks,
)
from shared.tilecodec import DEFAULT_MAX_TILE_BYTES, SparseTile, TileMessage, decode_tile, decode_tile_sparse
from shared.tiles import MAX_LAT_DEG, TileGrid

if TYPE_CHECKING:
    from fusion_server.uav_clocks import UavClocks

__all__ = ["REJECT_REASONS", "MessageValidator", "Received", "Rejected"]

#: Reasons of this module on top of the codecs' ``MESSAGE_ERROR_REASONS``, plus those of the
#: server ("stale", "too_many_tiles", "too_many_uavs", "unexpected_delete", "internal_error").
REJECT_REASONS = frozenset(
    {
        "bad_key",  # not a key of the key space (wrong prefix, shape, names, numbers)
        "unexpected_key",  # a valid key nobody may put on (e.g. a put on .../alive)
        "uav_mismatch",  # the message's uav differs from the key's: a UAV publishes under its own key only
        "tile_mismatch",  # cls/z/x/y of a tile differ from its key
        "wrong_grid",  # z or n differ from the server's grid
        "rate_limited",  # more messages a second than the UAV's limit (fusion_server.rate_limit)
        "byte_rate_limited",  # more payload bytes a second than the UAV's limit
        "t_in_future",  # t later than the server clock + max_clock_skew_s (+ the UAV's adopted clock lead; 1e300)
        "seq_in_future",  # a tile seq above the server clock (+ the UAV's lead) in nanoseconds + skew (2**64 - 1)
        "stale",  # not newer than the stored tile of that UAV
        "too_many_tiles",
        "too_many_uavs",
        "unexpected_delete",  # a DELETE sample on an agent key
        "overloaded",  # the fusion thread's inbox was full (more samples than the process can handle)
        "internal_error",  # a bug: counted, logged with a traceback, never raised into Zenoh
    }
    | MESSAGE_ERROR_REASONS
)


class Rejected(Exception):
    """A message the server drops. reason: one of REJECT_REASONS; kind: "tile", "state",
    "tracks" or "unknown" (the key could not tell); detail: human-readable text."""

    def __init__(self, reason: str, detail: str, kind: str = "unknown") -> None:
        super().__init__(detail)
        self.reason = reason
        self.kind = kind


@dataclass(frozen=True, slots=True)
class Received:
    """A valid message. kind: "tile", "state" or "tracks"; key: the parsed key; nbytes: payload size.
    lead_s: seconds taken off the message's t (its UAV's adopted clock lead; 0.0: as it came)."""

    kind: str
    key: ParsedKey
    message: TileMessage | SparseTile | StateMessage | TracksMessage
    nbytes: int
    lead_s: float = 0.0


_KINDS = {"uav_tile": "tile", "uav_state": "state", "uav_tracks": "tracks"}
_MAX_KNOWN_KEYS = 65_536


class MessageValidator:
    """Checks agent messages against the key space and the shared grid.

    keys: the key space; grid: the accepted (z, n). The max_* arguments bound payload sizes in bytes.
    max_clock_skew_s: how far a message's ``t`` may be ahead of the server clock ``wall`` (epoch
    seconds); a tile's ``seq`` may not exceed that time in nanoseconds (counters and clock stamps in
    micro- or nanoseconds pass; 2**64 - 1 does not). Times in the past are accepted: freshness is
    judged by receive time. Both bounds keep one forged message from blocking a UAV's real tiles as
    "stale" (DESIGN.md 4: a tile replaces the stored one when it is newer by seq or by t).
    clocks: the UAVs' clock leads (fusion_server.uav_clocks), or None (the gateway's: every message ahead is
    rejected). With them, an otherwise valid message ahead is evidence of its UAV's lead, and once that lead is
    taken the UAV's messages that need it pass with ``t`` minus the lead (``seq`` is bounded by the clock plus the
    lead, not moved: it orders one UAV's tiles only, and is often a counter).
    """

    def __init__(
        self,
        keys: KeySpace,
        grid: TileGrid,
        *,
        max_tile_bytes: int = DEFAULT_MAX_TILE_BYTES,
        max_state_bytes: int = DEFAULT_MAX_STATE_BYTES,
        max_tracks_bytes: int = 256 * 1024,
        max_clock_skew_s: float = 30.0,
        wall=time.time,
        clocks: UavClocks | None = None,
    ) -> None:
        self.keys = keys
        self.grid = grid
        self.max_tile_bytes = max_tile_bytes
        self.max_state_bytes = max_state_bytes
        self.max_tracks_bytes = max_tracks_bytes
        self.max_clock_skew_s = float(max_clock_skew_s)
        self._wall = wall
        self.clocks = clocks
        self._known_keys: dict[str, tuple[ParsedKey, str]] = {}

    def parse_key(self, key: str) -> tuple[ParsedKey, str]:
        """The parsed key and its message kind; Rejected("bad_key" | "unexpected_key") otherwise.

        Valid keys are remembered (a UAV puts on the same keys every cycle; at most 65,536, then the
        memory starts over), so a key is parsed once, not per message.
        """
        known = self._known_keys.get(key)
        if known is not None:
            return known
        found = self._parse_key(key)
        if len(self._known_keys) >= _MAX_KNOWN_KEYS:
            self._known_keys.clear()
        self._known_keys[key] = found
        return found

    def _parse_key(self, key: str) -> tuple[ParsedKey, str]:
        try:
            parsed = self.keys.parse(key)
        except ValueError as exc:
            raise Rejected("bad_key", str(exc)[:200]) from None
        kind = _KINDS.get(parsed.kind)
        if kind is None:
            raise Rejected("unexpected_key", f"nobody may put on {key[:200]!r}")
        return parsed, kind

    def max_bytes(self, kind: str) -> int:
        """Largest accepted payload of a message kind ("tile", "state", "tracks"), bytes."""
        return {"tile": self.max_tile_bytes, "state": self.max_state_bytes}.get(kind, self.max_tracks_bytes)

    def validate(self, key: str, payload, parsed: ParsedKey | None = None, *, sparse: bool = False) -> Received:
        """Decode and check one message published on ``key``; raise Rejected when it is invalid.

        payload: bytes, or an object with ``len()`` and ``to_bytes()`` (a ``zenoh.ZBytes``), whose
        size is checked before it is copied out. parsed: ``parse_key(key)[0]`` when already known.
        sparse: a tile is decoded to a :class:`shared.tilecodec.SparseTile` (its non-zero cells, the
        fusion server's form) instead of a dense TileMessage; the checks are the same.
        """
        if parsed is None:
            parsed, kind = self.parse_key(key)
        else:
            kind = _KINDS[parsed.kind]
        if not isinstance(payload, bytes | bytearray | memoryview):
            size = len(payload)
            if size > self.max_bytes(kind):
                raise Rejected("too_large", f"payload has {size} bytes, limit {self.max_bytes(kind)}", kind)
            payload = payload.to_bytes()
        message: TileMessage | SparseTile | StateMessage | TracksMessage
        try:
            if kind == "tile":
                decode = decode_tile_sparse if sparse else decode_tile
                message = decode(payload, max_bytes=self.max_tile_bytes)
            elif kind == "state":
                message = decode_state(payload, max_bytes=self.max_state_bytes)
            else:
                message = decode_tracks(payload, max_bytes=self.max_tracks_bytes)
        except MessageError as exc:
            raise Rejected(exc.reason, str(exc)[:200], kind) from None
        if message.uav != parsed.uav:
            raise Rejected("uav_mismatch", f"message uav {message.uav!r} published under {parsed.uav!r}", kind)
        wall = self._wall()
        latest = wall + self.max_clock_skew_s
        try:
            self._check_fields(message, parsed, kind)
        except Rejected:
            if message.t > latest:  # the reason it had before the clocks: the time comes first
                raise self._in_future(message.t, kind) from None
            raise
        lead = 0.0
        if self.clocks is not None:  # evidence only from messages valid but for their time
            found = self.clocks.lead_for(parsed.uav, kind, message.t, wall)
            if found is None:
                raise self._in_future(message.t, kind)
            lead = found
        elif message.t > latest:
            raise self._in_future(message.t, kind)
        if kind == "tile":
            assert isinstance(message, TileMessage | SparseTile)
            if message.seq > int((latest + lead) * 1e9):
                raise Rejected("seq_in_future", f"seq {message.seq} is above the server clock in nanoseconds", kind)
        if lead:
            message = dataclasses.replace(message, t=message.t - lead)
        return Received(kind, parsed, message, len(payload), lead)

    def _in_future(self, t: float, kind: str) -> Rejected:
        return Rejected("t_in_future", f"t {t!r:.30} is more than {self.max_clock_skew_s:g} s ahead of the server "
                                       "clock", kind)

    def _check_fields(self, message: TileMessage | SparseTile | StateMessage | TracksMessage, parsed: ParsedKey,
                      kind: str) -> None:
        """The checks of a decoded message beyond its time: footprint latitudes, tile key and grid."""
        if isinstance(message, StateMessage) and any(abs(lat) > MAX_LAT_DEG for lat, _ in message.footprint):
            raise Rejected("out_of_range", f"footprint beyond the map's latitude limit +-{MAX_LAT_DEG:.4f}", kind)
        if kind == "tile":
            assert isinstance(message, TileMessage | SparseTile)
            if (message.cls, message.z, message.x, message.y) != (parsed.cls, parsed.z, parsed.x, parsed.y):
                raise Rejected(
                    "tile_mismatch",
                    f"tile {message.cls}/{message.z}/{message.x}/{message.y} on key "
                    f"{parsed.cls}/{parsed.z}/{parsed.x}/{parsed.y}",
                    kind,
                )
            if message.z != self.grid.z or message.n != self.grid.n:
                raise Rejected(
                    "wrong_grid", f"tile z={message.z} n={message.n}, server grid z={self.grid.z} n={self.grid.n}", kind
                )

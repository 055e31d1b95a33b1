"""One global id across a shard border: what a fusion shard learns from the other shards' region tracks.

A sharded fusion server (``uavmm fusion --shard K/N``, :mod:`shared.sharding`) tracks the objects of
its own regions only: it keeps the local tracks of a UAV's tracks message that lie in its regions
(:meth:`Handover.own_tracks`). When an object walks over a border into another shard's region, that
shard would start a new global track; instead it asks :meth:`Handover.adopt`, which answers from
the other shards' ``region/tracks/...`` messages (subscribed by :meth:`Handover.on_region_tracks`):

1. the global id that already absorbed the same local track ``(uav, local id)`` (the usual case:
   the UAV that saw the object before the border still sees it), else
2. the nearest global track of the same class within the association gate, published in the last
   few seconds (another UAV picks the object up on this side).

The shard that carried the id before sees it in the new shard's region messages and ends its own
copy once no UAV reports it there (:meth:`fusion_server.global_tracks.GlobalTracker.hand_over`), so
the id lives on in exactly one shard.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from fusion_server.association import ground_distance_m
from shared.messages import MessageError, TracksMessage, decode_joint_tracks

if TYPE_CHECKING:
    import zenoh

    from fusion_server.global_tracks import GlobalTracker
    from shared.keys import KeySpace
    from shared.sharding import ShardSpec
    from shared.tiles import TileGrid

__all__ = ["Handover"]

_K = TypeVar("_K")
_V = TypeVar("_V")

log = logging.getLogger(__name__)

#: A local track's global id in another shard is reused this long after that shard last reported it, s.
MEMBER_KEEP_S = 30.0
#: A global track of another shard is a position match this long after its region last listed it, s
#: (regions are published at least once a second).
POSITION_KEEP_S = 3.0
#: Most remembered local tracks and global tracks of other shards (oldest forgotten first).
MAX_ENTRIES = 200_000


class Handover:
    """What one shard knows of the others' global tracks, and the per-shard split of tracks messages.

    shard: this process's shard. keys: the key space. tracker: this shard's global tracker (its held
    copies of handed-over ids end here). grid: the tile grid (positions to tiles).
    """

    def __init__(self, shard: ShardSpec, keys: KeySpace, tracker: GlobalTracker, grid: TileGrid, *,
                 clock=time.monotonic) -> None:
        self.shard = shard
        self.keys = keys
        self.tracker = tracker
        self.grid = grid
        self.gate_m = tracker.gate_m
        self._clock = clock
        self._lock = threading.Lock()
        # both oldest seen first (an entry seen again moves to the end), so pruning pops from the front only
        self._by_member: dict[tuple[str, int], tuple[int, float]] = {}  # (uav, local id) -> (gid, seen)
        self._recent: dict[int, tuple[str, float, float, float]] = {}  # gid -> (cls, lat, lon, seen)
        #: foreign region messages taken and refused (malformed, or on a region of ours)
        self.received = 0
        self.rejected = 0

    # ---- the split ------------------------------------------------------------------------------
    def own_tracks(self, message: TracksMessage) -> TracksMessage:
        """The tracks of ``message`` inside this shard's regions (the rest belongs to other shards)."""
        if not message.tracks:
            return message
        lat = np.array([item.lat for item in message.tracks])
        lon = np.array([item.lon for item in message.tracks])
        xs, ys = self.grid.tile_of(lat, lon)
        z = self.grid.z
        kept = tuple(item for item, x, y in zip(message.tracks, xs.tolist(), ys.tolist(), strict=True)
                     if self.shard.owns(z, x, y))
        return message if len(kept) == len(message.tracks) else dataclasses.replace(message, tracks=kept)

    # ---- what the other shards publish (Zenoh thread) ------------------------------------------------
    def on_region_tracks(self, sample: zenoh.Sample) -> None:
        """A ``region/tracks/{z}/{x}/{y}`` message: remember another shard's ids; end our held copies."""
        key = str(sample.key_expr)
        try:
            parsed = self.keys.parse(key)
            if parsed.kind != "region_tracks":
                raise ValueError("not a region tracks key")
            message = decode_joint_tracks(sample.payload.to_bytes())
        except (ValueError, MessageError) as exc:
            self.rejected += 1
            log.debug("foreign region tracks on %.120s refused: %s", key, exc)
            return
        assert parsed.z is not None and parsed.x is not None and parsed.y is not None
        if self.shard.owns(parsed.z, parsed.x, parsed.y):
            return  # our own region (our echo, or a shard that believes it owns it: ignored)
        self.received += 1
        now = self._clock()
        with self._lock:
            recent, by_member = self._recent, self._by_member
            for item in message.tracks:
                recent.pop(item.gid, None)
                recent[item.gid] = (item.cls, item.lat, item.lon, now)
                for member in item.members:
                    by_member.pop(member, None)
                    by_member[member] = (item.gid, now)
            self._prune(now)
        for item in message.tracks:
            self.tracker.hand_over(item.gid)

    def _prune(self, now: float) -> None:
        """Forget what is past its use (lock held): entries are oldest seen first, so this costs what it drops.

        Without it a day of other shards' ids piled up to MAX_ENTRIES and ``adopt`` scanned them all.
        """
        _drop_oldest(self._by_member, lambda entry: now - entry[1] <= MEMBER_KEEP_S)
        _drop_oldest(self._recent, lambda entry: now - entry[3] <= POSITION_KEEP_S)

    # ---- the question of the global tracker -------------------------------------------------------
    def adopt(self, uav: str, local_id: int, cls: str, lat: float, lon: float) -> int | None:
        """The global id another shard gave this object, or None (the tracker gives a new one)."""
        now = self._clock()
        with self._lock:
            self._prune(now)
            found = self._by_member.get((uav, local_id))
            if found is not None and now - found[1] <= MEMBER_KEEP_S:
                return found[0]
            near = [(gid, t_lat, t_lon) for gid, (t_cls, t_lat, t_lon, seen) in self._recent.items()
                    if t_cls == cls and now - seen <= POSITION_KEEP_S]
        if not near:
            return None
        dist = ground_distance_m(np.full(len(near), lat), np.full(len(near), lon),
                                 np.array([n[1] for n in near]), np.array([n[2] for n in near]))
        best = int(np.argmin(dist))
        return int(near[best][0]) if float(dist[best]) <= self.gate_m else None


def _drop_oldest(table: dict[_K, _V], fresh: Callable[[_V], bool]) -> None:
    """Drop entries, oldest inserted first, until the oldest is fresh and the table holds at most MAX_ENTRIES."""
    while table:
        key = next(iter(table))
        if fresh(table[key]) and len(table) <= MAX_ENTRIES:
            break
        del table[key]

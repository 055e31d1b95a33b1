"""The global tracks of a sharded deployment, merged by the gateway from the shards' per-region messages.

Every shard publishes the global tracks of its regions on ``{prefix}/region/tracks/{z}/{x}/{y}`` (at
least once a second while a region has tracks, one empty message when it has none left). The gateway
keeps each region's last message; the merged view is the union of the regions heard from within
``stale_s`` seconds (3 by default: a region of a dead shard drops out), one track per global id, the
one from the newest message (during a handover both shards may publish the id for a moment). A track's
status comes with it: the region message lists which members still report it (``JointTrackItem.active``;
a message of an older shard without it reads as all of them: "tracked"). Its history, creation and
last-update times and the ended tracks come from the shards themselves when ``details`` is set (the
gateway's :class:`fusion_server.shard_tracks.ShardTracks`, asked over Zenoh); without it, or for a
track no shard answered about, the gateway's own record stands in: the history it built from what it
heard (a point per ``history_interval_s``), and the tracks that left the view as ended ones. It offers
the read side of
:class:`fusion_server.global_tracks.GlobalTracker` that the REST API and the ``joint/tracks``
publisher use (``records``, ``joint_message``, ``len``). Thread-safe.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable

from fusion_server.global_tracks import TrackRecord
from fusion_server.shard_tracks import ShardTrack
from shared.messages import MAX_TRACKS, JointTrackItem, JointTracksMessage

__all__ = ["DEFAULT_STALE_S", "MergedTracks"]

#: A region whose last message is older than this drops out of the merged view, seconds.
DEFAULT_STALE_S = 3.0
#: Most regions remembered (the oldest are forgotten beyond it; stale ones are forgotten anyway).
_MAX_REGIONS = 65_536
#: Ended tracks kept for ``include_ended``.
_MAX_ENDED = 256

Region = tuple[int, int, int]


class _Seen:
    """What the gateway remembers of one global id: first seen, history of (t, lat, lon)."""

    __slots__ = ("created", "history")

    def __init__(self, created: float, history_len: int) -> None:
        self.created = created
        self.history: deque[tuple[float, float, float]] = deque(maxlen=history_len)


class MergedTracks:
    """The shards' region tracks merged by global id (newest message wins), regions older than
    ``stale_s`` left out.

    history_len: most history rows per track; history_interval_s: least time between two rows.
    clock: monotonic seconds (freshness); wall: epoch seconds (ended times, message times).
    """

    def __init__(self, *, stale_s: float = DEFAULT_STALE_S, history_len: int = 600,
                 history_interval_s: float = 1.0, clock=time.monotonic, wall=time.time) -> None:
        self.stale_s = float(stale_s)
        self.history_len = int(history_len)
        self.history_interval_s = float(history_interval_s)
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        # region -> (monotonic receive time, message t, its tracks)
        self._regions: OrderedDict[Region, tuple[float, float, tuple[JointTrackItem, ...]]] = OrderedDict()
        self._seen: dict[int, _Seen] = {}
        self._current: dict[int, tuple[float, JointTrackItem]] = {}
        self._ended: OrderedDict[int, TrackRecord] = OrderedDict()
        #: bumped whenever the merged view changes (the joint/tracks publisher compares it)
        self.version = 0
        #: when set, ``details(include_ended)`` gives the shards' own records of their tracks (history,
        #: times, the ended ones), or None when no shard answered (ShardTracks.live)
        self.details: Callable[[bool], list[ShardTrack] | None] | None = None

    def put(self, region: Region, message: JointTracksMessage) -> None:
        """Record a region's tracks message (an empty one: the region has no tracks any more)."""
        now = self._clock()
        with self._lock:
            self._regions[region] = (now, message.t, message.tracks)
            self._regions.move_to_end(region)
            while len(self._regions) > _MAX_REGIONS:
                self._regions.popitem(last=False)
            for item in message.tracks:
                seen = self._seen.get(item.gid)
                if seen is None:
                    seen = self._seen[item.gid] = _Seen(message.t, self.history_len)
                history = seen.history
                if not history or message.t - history[-1][0] >= self.history_interval_s:
                    history.append((message.t, item.lat, item.lon))
            self._merge(now)

    def refresh(self) -> None:
        """Drop regions that went stale (their shard stopped publishing) from the merged view."""
        with self._lock:
            self._merge(self._clock())

    def regions(self) -> dict[Region, float]:
        """Fresh regions and the age of their last message, seconds."""
        now = self._clock()
        with self._lock:
            return {region: now - entry[0] for region, entry in self._regions.items()
                    if now - entry[0] <= self.stale_s}

    def _merge(self, now: float) -> None:
        """Recompute the merged view (lock held); tracks that left it become ended ones."""
        # regions are oldest heard first (put moves a region to the end): forget the stale ones, so a fleet
        # moving over new ground for days costs what the fresh regions cost, not every region ever heard
        regions = self._regions
        while regions and now - next(iter(regions.values()))[0] > self.stale_s:
            regions.popitem(last=False)
        merged: dict[int, tuple[float, JointTrackItem]] = {}
        for received, t, items in self._regions.values():
            if now - received > self.stale_s:
                continue
            for item in items:
                old = merged.get(item.gid)
                if old is None or t > old[0]:
                    merged[item.gid] = (t, item)
        if merged == self._current:
            return
        wall = self._wall()
        for gid in self._current.keys() - merged.keys():
            t, item = self._current[gid]
            self._ended[gid] = self._record(gid, t, item, ended=wall)
            self._ended.move_to_end(gid)
            while len(self._ended) > _MAX_ENDED:
                old_gid, _ = self._ended.popitem(last=False)
                if old_gid not in merged:
                    self._seen.pop(old_gid, None)
        for gid in merged.keys() & self._ended.keys():
            del self._ended[gid]  # back (a shard restarted, a region came back)
        self._current = merged
        self.version += 1

    def _record(self, gid: int, t: float, item: JointTrackItem, ended: float | None = None) -> TrackRecord:
        seen = self._seen.get(gid)
        # the region message says which members still report it (all of them in an older shard's message)
        return TrackRecord(gid=gid, cls=item.cls, lat=item.lat, lon=item.lon, score=item.score, vel_en=item.vel_en,
                           created=seen.created if seen is not None else t, last_update=t, members=item.members,
                           active=item.active_members if ended is None else (), ended=ended,
                           history=tuple(seen.history) if seen is not None else ())

    # ---- the read side the REST API uses (GlobalTracker's) ------------------------------------------
    def records(self, include_ended: bool = False) -> list[TrackRecord]:
        """The merged global tracks, plus the recently ended ones if asked, by gid: where each is and its
        status from the regions, its history and times from the shards (``details``) when they answer."""
        details = self.details(include_ended) if self.details is not None else None  # a query: not under the lock
        with self._lock:
            self._merge(self._clock())
            rows = [self._record(gid, t, item) for gid, (t, item) in self._current.items()]
            ended = list(self._ended.values()) if include_ended else []
        if details is not None:
            rows, ended = _with_details(rows, ended, details, include_ended)
        return sorted(rows + ended, key=lambda r: r.gid)

    def joint_message(self, max_tracks: int = MAX_TRACKS) -> JointTracksMessage:
        """The ``joint/tracks`` message of the whole map: at most ``max_tracks``, the newest first, by gid."""
        with self._lock:
            self._merge(self._clock())
            found = list(self._current.values())
        if len(found) > max_tracks:
            found.sort(key=lambda entry: -entry[0])
            found = found[:max_tracks]
        items = tuple(item for _, item in sorted(found, key=lambda entry: entry[1].gid))
        return JointTracksMessage(t=self._wall(), tracks=items)

    def gids(self) -> set[int]:
        """Global ids in the merged view."""
        with self._lock:
            return set(self._current)

    def __len__(self) -> int:
        return len(self._current)


def _with_details(rows: list[TrackRecord], ended: list[TrackRecord], details: list[ShardTrack],
                  include_ended: bool) -> tuple[list[TrackRecord], list[TrackRecord]]:
    """The live rows with the shards' history, creation and last-update times (their members too: after a
    handover they hold every copy's); the ended tracks the shards list instead of the gateway's own,
    except for those no shard answered about (a dead shard's tracks that left the view)."""
    by_gid = {track.gid: track for track in details}
    live = []
    for row in rows:
        track = by_gid.get(row.gid)
        if track is not None:
            members = track.members if set(row.active) <= set(track.members) else row.members
            row = dataclasses.replace(row, created=track.created, last_update=track.last_update, members=members,
                                      history=track.history)
        live.append(row)
    if not include_ended:
        return live, []
    alive = {row.gid for row in rows}
    shards_ended = [track.to_record() for track in details if track.ended is not None and track.gid not in alive]
    listed = {record.gid for record in shards_ended}
    return live, shards_ended + [record for record in ended if record.gid not in listed and record.gid not in by_gid]

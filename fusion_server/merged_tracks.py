"""The global tracks of a sharded deployment, merged by the gateway from the shards' per-region messages.

Every shard publishes the global tracks of its regions on ``{prefix}/region/tracks/{z}/{x}/{y}`` (at
least once a second while a region has tracks, one empty message when it has none left). The gateway
keeps each region's last message; the merged view is the union of the regions heard from within
``stale_s`` seconds (3 by default: a region of a dead shard drops out), one track per global id, the
one from the newest message (during a handover both shards may publish the id for a moment; a message's time is
its `t` or its arrival, whichever is earlier, and the gateway node drops one stamped more than the clock skew
ahead: a future stamp wins nothing). A track's
status comes with it: the region message lists which members still report it (``JointTrackItem.active``;
a message of an older shard without it reads as all of them: "tracked"). Its history, creation and
last-update times and the ended tracks come from the shards themselves when ``details`` is set (the
gateway's :class:`fusion_server.shard_tracks_client.ShardTracks`, asked over Zenoh); without it, or for a
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
    max_tracks: most tracks held over all regions (each shard lists at most ``shared.messages.MAX_TRACKS``);
    beyond it the regions heard from longest ago are forgotten first (counted in ``regions_evicted``), so what
    the network sends costs bounded memory. clock: monotonic seconds (freshness); wall: epoch seconds (ended
    times, message times).

    A message costs the tracks it and the region's previous message list, not every track of the map: the
    merged view is kept up to date per global id (a fleet of 10,000 tracks in 100 regions, each published
    twice a second, cost ~2 s of CPU a second when every message merged every region again).
    """

    def __init__(self, *, stale_s: float = DEFAULT_STALE_S, history_len: int = 600,
                 history_interval_s: float = 1.0, max_tracks: int = 20 * MAX_TRACKS, clock=time.monotonic,
                 wall=time.time) -> None:
        if max_tracks < MAX_TRACKS:
            raise ValueError(f"max_tracks must be at least one region message's {MAX_TRACKS}, got {max_tracks}")
        self.stale_s = float(stale_s)
        self.history_len = int(history_len)
        self.history_interval_s = float(history_interval_s)
        self.max_tracks = int(max_tracks)
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        # region -> (monotonic receive time, message t, its tracks by gid); oldest heard first
        self._regions: OrderedDict[Region, tuple[float, float, dict[int, JointTrackItem]]] = OrderedDict()
        self._tracks_held = 0  # tracks over all of _regions
        self._holders: dict[int, dict[Region, None]] = {}  # gid -> the regions that list it
        self._seen: dict[int, _Seen] = {}
        self._current: dict[int, tuple[float, JointTrackItem]] = {}
        self._ended: OrderedDict[int, TrackRecord] = OrderedDict()
        #: bumped whenever the merged view changes (the joint/tracks publisher compares it)
        self.version = 0
        #: regions forgotten while fresh because more than ``max_tracks`` tracks (or _MAX_REGIONS regions) came
        self.regions_evicted = 0
        #: when set, ``details(include_ended)`` gives the shards' own records of their tracks (history,
        #: times, the ended ones), or None when no shard answered (ShardTracks.live)
        self.details: Callable[[bool], list[ShardTrack] | None] | None = None

    def put(self, region: Region, message: JointTracksMessage) -> None:
        """Record a region's tracks message (an empty one: the region has no tracks any more). Its time is its
        `t`, or the time it arrived when that is earlier: a message stamped ahead (forged without the ACL, or from
        a shard whose clock runs ahead) wins no id over a copy heard after it, nor holds back the history."""
        now = self._clock()
        t = min(message.t, self._wall())
        tracks = {item.gid: item for item in message.tracks}
        with self._lock:
            changed = self._drop_region(region)
            self._regions[region] = (now, t, tracks)
            self._tracks_held += len(tracks)
            for gid, item in tracks.items():
                self._holders.setdefault(gid, {})[region] = None
                changed.add(gid)
                seen = self._seen.get(gid)
                if seen is None:
                    seen = self._seen[gid] = _Seen(t, self.history_len)
                history = seen.history
                if not history or t - history[-1][0] >= self.history_interval_s:
                    history.append((t, item.lat, item.lon))
            self._merge(now, changed)

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

    def _drop_region(self, region: Region) -> set[int]:
        """Forget a region's message (lock held); the gids it listed."""
        entry = self._regions.pop(region, None)
        if entry is None:
            return set()
        tracks = entry[2]
        self._tracks_held -= len(tracks)
        for gid in tracks:
            holders = self._holders.get(gid)
            if holders is not None:
                holders.pop(region, None)
                if not holders:
                    del self._holders[gid]
        return set(tracks)

    def _merge(self, now: float, changed: set[int] | None = None) -> None:
        """Bring the merged view up to date (lock held): forget stale regions, and the oldest ones beyond the
        bounds, then merge again the gids they and ``changed`` list; tracks that left the view become ended ones."""
        changed = set() if changed is None else changed
        # regions are oldest heard first (put moves a region to the end): forget the stale ones, so a fleet
        # moving over new ground for days costs what the fresh regions cost, not every region ever heard
        regions = self._regions
        while regions:
            region, (received, _, _) = next(iter(regions.items()))
            stale = now - received > self.stale_s
            if not stale and len(regions) <= _MAX_REGIONS and (self._tracks_held <= self.max_tracks
                                                               or len(regions) == 1):
                break
            if not stale:
                self.regions_evicted += 1
            changed |= self._drop_region(region)
        if not changed:
            return
        left: list[int] = []
        came = False
        for gid in changed:
            best: tuple[float, float, JointTrackItem] | None = None
            for region in self._holders.get(gid, ()):
                received, t, tracks = regions[region]
                # the newest message's copy; of equal times the one heard first (as the regions' order gave it)
                if best is None or (t, -received) > (best[0], -best[1]):
                    best = (t, received, tracks[gid])
            old = self._current.get(gid)
            if best is None:
                if old is not None:
                    left.append(gid)
                continue
            found = (best[0], best[2])
            if found != old:
                self._current[gid] = found
                came = True
                self._ended.pop(gid, None)  # back (a shard restarted, a region came back)
        if not left and not came:
            return
        wall = self._wall()
        for gid in sorted(left):
            t, item = self._current.pop(gid)
            self._ended[gid] = self._record(gid, t, item, ended=wall)
            self._ended.move_to_end(gid)
            while len(self._ended) > _MAX_ENDED:
                old_gid, _ = self._ended.popitem(last=False)
                if old_gid not in self._current:
                    self._seen.pop(old_gid, None)
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
        """The ``joint/tracks`` message of the whole map, by gid: at most ``max_tracks``, as a fusion server
        chooses them (``GlobalTracker.joint_message``): tracked ones first (a member still reports them), then
        held ones, each the most recently updated first."""
        with self._lock:
            self._merge(self._clock())
            found = list(self._current.values())
        if len(found) > max_tracks:
            found.sort(key=lambda entry: (entry[1].active == (), -entry[0]))
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

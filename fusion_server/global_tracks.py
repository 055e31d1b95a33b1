"""Global tracks: the UAVs' local tracks associated on the ground into global ids, with history.

Per class, a UAV's new local tracks are assigned to the nearest global tracks (metres on the ground,
gated, :mod:`fusion_server.association`); a local id once mapped keeps its global id; a
global track survives while any UAV reports it, then for ``hold_s``, so a UAV that finds the object
again re-adopts its global id. No I/O: the Zenoh side feeds it, persistence drains its changes.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable

import numpy as np

from fusion_server.association import gated_assignment, ground_distance_m, weighted_lon
from fusion_server.reassociation import Reassociation, seen_at
from fusion_server.track_records import GlobalTrack, Member, TrackRecord, active_indexes, moved_on
from shared.messages import MAX_MEMBERS, MAX_TRACKS, JointTrackItem, JointTracksMessage, TrackItem, TracksMessage

__all__ = ["MAX_INACTIVE_MEMBERS", "GlobalTrack", "GlobalTracker", "TrackRecord", "ground_distance_m"]

_MAX_MEMBERS_KEPT = min(MAX_MEMBERS, 256)
#: Members no UAV reports any more kept per track, the most recent (a local id that comes back finds its global
#: id): in a crowd a held track takes in new local tracks near it and never ends, and with every ended member
#: kept its member list (sent with every joint/tracks message) grew all flight (a soak: 4.9 -> 14.5 members a
#: track in 12 minutes, the message 22 -> 44 KiB, heading for the cap of 256 in an hour).
MAX_INACTIVE_MEMBERS = 8


class GlobalTracker:
    """Associates local tracks into global tracks. Thread-safe (one lock).

    gate_m: largest ground distance at which a new local track joins a global track. hold_s: how long
    a global track nobody reports is kept. member_ttl_s: a UAV's member counts as lost when its UAV
    sent no tracks message for that long. history_len / history_interval_s: at most that many
    history rows per track, one per interval. max_ended: ended tracks kept in memory for the API. reassociate_m:
    a local track moves to the global track other UAVs report its object under when, for seconds, that one lies
    within this distance and clearly nearer than its own (`fusion_server.reassociation`; 0: never moves).

    Bounds (so one UAV, real or forged, cannot exhaust memory or stall the API): a tracks message is
    cut to its ``max_tracks_per_message`` best-scored tracks; one UAV may have created at most
    ``max_tracks_per_uav`` of the live global tracks and all UAVs together ``max_global_tracks``.
    Beyond a bound a new track first ends the oldest held (lost) track of the UAV that created the
    most, else it gets no global id. Counted in :meth:`dropped`. Association is
    :func:`fusion_server.association.gated_assignment` (exact for ordinary groups, greedy for piles).
    """

    def __init__(
        self,
        *,
        gate_m: float = 10.0,
        hold_s: float = 10.0,
        member_ttl_s: float = 2.0,
        history_len: int = 600,
        history_interval_s: float = 1.0,
        max_ended: int = 1000,
        max_tracks_per_message: int = 1000,
        max_tracks_per_uav: int = 2000,
        max_global_tracks: int = 20_000,
        next_gid: int = 1,
        gid_step: int = 1,
        adopt: Callable[[str, int, str, float, float], int | None] | None = None,
        keep_changes: bool = True,
        same_uav_gate_m: float | None = 3.0,
        reassociate_m: float = 6.0,
        clock=time.monotonic,
        wall=time.time,
    ) -> None:
        self.gate_m = gate_m
        self.hold_s = hold_s
        self.member_ttl_s = member_ttl_s
        self.history_len = history_len
        self.history_interval_s = history_interval_s
        self.max_tracks_per_message = max_tracks_per_message
        self.max_tracks_per_uav = max_tracks_per_uav
        self.max_global_tracks = max_global_tracks
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        self._tracks: dict[int, GlobalTrack] = {}
        self._local: dict[tuple[str, int], int] = {}
        self._ended: deque[TrackRecord] = deque(maxlen=max_ended)
        if isinstance(gid_step, bool) or not isinstance(gid_step, int) or gid_step < 1:
            raise ValueError(f"gid_step must be an int >= 1, got {gid_step!r}")
        #: new global ids are next_gid, next_gid + gid_step, ... (a shard K of N: K + 1 + i N, disjoint)
        self.gid_step = gid_step
        self._gid_residue = next_gid % gid_step
        #: when set, asked for the global id of a local track about to start a new global track: another
        #: shard's id for the same object (handover across a region border), or None for a new id
        self.adopt = adopt
        #: global ids taken over from another shard ("in") and held ones ended because another shard
        #: carries them on ("out")
        self.handovers: Counter[str] = Counter()
        self._next_gid = next_gid
        #: collect what changed for `drain_changes` (persistence); a server without a database never drains, and
        #: kept its history rows, ended tracks and changed ids all flight (a soak: 63k rows in 8 minutes)
        self.keep_changes = keep_changes
        self.same_uav_gate_m = same_uav_gate_m  # metres, None: off (`_elsewhere_for`)
        #: moves of local tracks to the global track other UAVs see their object under, up to reassociate_m away
        self.reassociation = (Reassociation(search_gate_m=gate_m, move_gate_m=reassociate_m) if reassociate_m > 0
                              else None)
        self._dirty: set[int] = set()  # for persistence
        self._history_out: list[tuple[int, float, float, float]] = []
        self._ended_pending: dict[int, TrackRecord] = {}
        # indexes that keep every step proportional to one message, not to all tracks
        self._active: dict[str, set[int]] = {}  # uav -> local ids of its active members
        self._last_msg: dict[str, float] = {}  # uav -> monotonic time of its last tracks message
        self._lost: dict[int, None] = {}  # held gids, oldest lost first
        self._owner: dict[int, str] = {}  # gid -> the UAV whose track created it
        self._owned: dict[str, dict[int, None]] = {}  # uav -> live gids it created, oldest first
        self._dropped: Counter[str] = Counter()
        self._greedy_groups = 0
        self.version = 0  # increases on every change, for rate-limited publishing

    # ---- input ---------------------------------------------------------------------------------
    def update(self, msg: TracksMessage, now: float | None = None) -> bool:
        """Take one UAV's local tracks; returns True if the global tracks changed."""
        now = self._clock() if now is None else now
        wall = self._wall()
        uav = msg.uav
        items = msg.tracks
        if len(items) > self.max_tracks_per_message:
            self._count("too_many_tracks", len(items) - self.max_tracks_per_message)
            items = tuple(sorted(items, key=lambda item: -item.score)[: self.max_tracks_per_message])
        with self._lock:
            touched: set[int] = set()
            claimed: set[int] = set()
            unmatched = []
            for item in items:
                key = (uav, item.id)
                gid = self._local.get(key)
                track = self._tracks.get(gid) if gid is not None else None
                if gid is None or track is None or track.cls != item.cls or gid in claimed:
                    unmatched.append(item)
                    continue
                track.members[key] = Member(item.lat, item.lon, item.score, item.vel_en, now)
                claimed.add(gid)
            for cls in sorted({item.cls for item in unmatched}):
                self._associate(uav, [item for item in unmatched if item.cls == cls], claimed, now, wall)
            touched |= claimed
            if self.reassociation is not None:
                touched |= self._reassociate(uav, items, claimed, now, wall)
            reported = {item.id for item in items}
            for local_id in self._active.get(uav, set()) - reported:
                touched |= self._deactivate(uav, local_id)
            self._active[uav] = {local_id for local_id in reported if (uav, local_id) in self._local}
            self._last_msg[uav] = now
            for gid in touched:
                if gid in self._tracks:
                    self._refresh(self._tracks[gid], now, wall)
            if touched:
                self.version += 1
            return bool(touched)

    def _count(self, reason: str, n: int = 1) -> None:
        self._dropped[reason] += n

    def _deactivate(self, uav: str, local_id: int) -> set[int]:
        gid = self._local.get((uav, local_id))
        track = self._tracks.get(gid) if gid is not None else None
        member = track.members.get((uav, local_id)) if track is not None else None
        if gid is None or track is None or member is None or not member.active:
            return set()
        member.active = False
        self._trim_members(track)
        return {gid}

    def _associate(self, uav: str, items: list, claimed: set[int], now: float, wall: float) -> None:
        candidates = [t for gid, t in self._tracks.items() if t.cls == items[0].cls and gid not in claimed]
        assigned: dict[int, GlobalTrack] = {}
        if candidates:
            t_lat, t_lon = self._predicted(candidates, now)
            match = gated_assignment([item.lat for item in items], [item.lon for item in items], t_lat, t_lon,
                                     self.gate_m, forbid=self._elsewhere_for(uav, items, candidates, now))
            self._greedy_groups += match.greedy_groups
            for r, c in zip(match.rows, match.cols, strict=True):
                assigned[int(r)] = candidates[int(c)]
        for i, item in enumerate(items):
            track = assigned.get(i)
            if track is not None and self._tracks.get(track.gid) is not track:  # ended to make room for an earlier item
                track = None
            adopted = self.adopt(uav, item.id, item.cls, item.lat, item.lon) if track is None and self.adopt else None
            if adopted is not None and adopted in self._tracks:  # our held copy of the handed-over track
                mine = self._tracks[adopted]
                track = mine if mine.cls == item.cls and adopted not in claimed else None
                adopted = None
            if track is None:
                if not self._make_room(uav, claimed):
                    continue
                gid = adopted
                if gid is None:
                    gid = self._next_gid
                    self._next_gid += self.gid_step
                else:
                    self.handovers["in"] += 1
                track = self._new_track(uav, item, gid, wall)
            key = (uav, item.id)
            if self._local.get(key, track.gid) != track.gid:  # moved on (its old track claimed): no longer a member
                for old in self._deactivate(*key):  # there (it was active there forever: a track that never ended)
                    self._refresh(self._tracks[old], now, wall)
            track.members.pop(key, None)  # re-insert: most recent last
            track.members[key] = Member(item.lat, item.lon, item.score, item.vel_en, now)
            self._trim_members(track)
            self._local[key] = track.gid
            claimed.add(track.gid)

    def _new_track(self, uav: str, item: TrackItem, gid: int | None, wall: float) -> GlobalTrack:
        """A new global track of `uav`'s local track `item` (a new gid when gid is None), without members yet."""
        if gid is None:
            gid = self._next_gid
            self._next_gid += self.gid_step
        track = GlobalTrack(gid=gid, cls=item.cls, lat=item.lat, lon=item.lon, score=item.score, vel_en=item.vel_en,
                            created=wall, last_update=wall, history=deque(maxlen=self.history_len))
        self._tracks[gid] = track
        self._owner[gid] = uav
        self._owned.setdefault(uav, {})[gid] = None
        return track

    def _reassociate(self, uav: str, items: tuple[TrackItem, ...], claimed: set[int], now: float,
                     wall: float) -> set[int]:
        """Move `uav`'s local tracks to the global tracks the other UAVs see their objects under, where the
        distances of seconds say so (`fusion_server.reassociation`). Returns the global ids changed."""
        plan = self.reassociation
        assert plan is not None
        plan.forget(uav, {item.id for item in items})
        mapped = [item for item in items if self._local.get((uav, item.id)) in self._tracks]
        if not mapped or not plan.turn(uav, now):
            return set()
        near = plan.near(self._tracks, now, [item.lat for item in mapped], [item.lon for item in mapped])
        seen: dict[int, list[Member]] = {}  # gid -> the active members other UAVs have on it
        for gid in near:
            track = self._tracks.get(gid)
            others = [m for (u, _), m in track.members.items() if m.active and u != uav] if track is not None else []
            if others:
                seen[gid] = others
        touched: set[int] = set()
        for cls in sorted({item.cls for item in mapped}):
            mine = [item for item in mapped if item.cls == cls]
            gids = [gid for gid in seen if self._tracks[gid].cls == cls]
            if not gids:
                continue
            at_lat, at_lon = seen_at([seen[gid] for gid in gids], now, self.member_ttl_s)
            current = [self._local[(uav, item.id)] for item in mine]
            moves = plan.plan(uav, [item.id for item in mine], current, [item.lat for item in mine],
                              [item.lon for item in mine], gids, at_lat, at_lon, now)
            # a track taken over needs room for its displaced local track first; without room it is not taken, nor
            # then the track the taker would have left (a chain), so no UAV holds two members on one track
            blocked: set[int] = set()
            for i in [i for i, target in moves.items() if target is None]:
                if self._make_room(uav, claimed | {current[i]}):
                    touched |= self._move(uav, mine[i], current[i], None, now, wall)
                    plan.moved += 1
                else:
                    blocked.add(current[i])
            while stuck := {current[i] for i, target in moves.items() if target is not None and
                            (target in blocked or target not in self._tracks)} - blocked:
                blocked |= stuck
            for i, target in moves.items():
                if target is not None and target not in blocked and current[i] not in blocked:
                    touched |= self._move(uav, mine[i], current[i], target, now, wall)
                    plan.moved += 1
        return touched

    def _move(self, uav: str, item: TrackItem, old_gid: int, gid: int | None, now: float, wall: float) -> set[int]:
        """Make `uav`'s local track `item` a member of global track gid (a new one when None) instead of old_gid;
        the old track ends when no UAV reports it any more (it would only take in the next newcomer near it)."""
        key = (uav, item.id)
        old = self._tracks.get(old_gid)
        if old is None or self._local.get(key) != old_gid:  # gone, or the local track is no member of it any more
            return set()
        member = old.members.pop(key, None) or Member(item.lat, item.lon, item.score, item.vel_en, now)
        track = self._new_track(uav, item, None, wall) if gid is None else self._tracks[gid]
        track.members.pop(key, None)
        track.members[key] = member
        self._trim_members(track)
        self._local[key] = track.gid
        if not any(m.active for m in old.members.values()):
            self._end(old_gid, wall)
        return {old_gid, track.gid}

    def _elsewhere_for(self, uav: str, items: list, candidates: list[GlobalTrack], now: float
                       ) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
        """Pairs (item, candidate) to forbid: the candidate holds an active member of this UAV (another of its local
        tracks, moved on by its velocity since its report) more than `same_uav_gate_m` from the item: two objects
        (joined when that member went unreported for a message, the global track held both as they parted). Closer,
        it may be the same object under a new local id (a tracker's id switch)."""
        if self.same_uav_gate_m is None:
            return None
        own: dict[int, Member] = {}  # gid -> this UAV's active member on it, from the index of its active ids
        for local_id in self._active.get(uav, ()):
            gid = self._local.get((uav, local_id))
            track = self._tracks.get(gid) if gid is not None else None
            member = track.members.get((uav, local_id)) if track is not None else None
            if track is not None and member is not None and member.active:
                own.setdefault(track.gid, member)
        mine = [own.get(track.gid) for track in candidates]
        at = [m for m in mine if m is not None]
        if not at:
            return None
        has_own = np.array([m is not None for m in mine])
        own_lat = np.full(len(candidates), np.nan)
        own_lon = np.full(len(candidates), np.nan)
        own_lat[has_own], own_lon[has_own] = moved_on(
            np.array([m.lat for m in at]), np.array([m.lon for m in at]), np.array([m.vel_en for m in at]),
            np.array([min(max(now - m.received, 0.0), self.member_ttl_s) for m in at]))
        lat = np.array([item.lat for item in items])
        lon = np.array([item.lon for item in items])
        gate = self.same_uav_gate_m

        def forbid(ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
            has = ~np.isnan(own_lat[ib])
            out = np.zeros(len(ia), bool)
            out[has] = ground_distance_m(lat[ia[has]], lon[ia[has]], own_lat[ib[has]], own_lon[ib[has]]) > gate
            return out

        return forbid

    def _make_room(self, uav: str, claimed: set[int]) -> bool:
        """Whether ``uav`` may create a global track now, ending a held one to make room if needed (not one
        `claimed` by this message: it is reported again, though still marked held until the message is done)."""
        owned = self._owned.get(uav, {})
        if len(owned) >= self.max_tracks_per_uav:
            victim = next((gid for gid in owned if gid in self._lost and gid not in claimed), None)
            if victim is None:
                self._count("uav_track_quota")
                return False
            self._evict(victim)
        if len(self._tracks) >= self.max_global_tracks:
            # the UAV that created the most pays first: a flood evicts its own held tracks
            for owner in sorted(self._owned, key=lambda u: -len(self._owned[u])):
                victim = next((gid for gid in self._owned[owner] if gid in self._lost and gid not in claimed), None)
                if victim is not None:
                    self._evict(victim)
                    break
            else:
                self._count("too_many_global_tracks")
                return False
        return True

    def _evict(self, gid: int) -> None:
        self._count("evicted_lost")
        self._end(gid, self._wall())

    def _predicted(self, tracks: list[GlobalTrack], now: float) -> tuple[np.ndarray, np.ndarray]:
        # a lost track is extrapolated with its last velocity (for at most hold_s) so a UAV that
        # finds a moving object again still falls inside the gate
        lat, lon = np.array([t.lat for t in tracks]), np.array([t.lon for t in tracks])
        dt = np.array([min(now - t.lost_since, self.hold_s) if t.lost_since is not None else 0.0 for t in tracks])
        return moved_on(lat, lon, np.array([t.vel_en for t in tracks]).reshape(-1, 2), dt)

    def _trim_members(self, track: GlobalTrack) -> None:
        inactive = [k for k, m in track.members.items() if not m.active]
        excess = max(len(inactive) - MAX_INACTIVE_MEMBERS, len(track.members) - _MAX_MEMBERS_KEPT, 0)
        if not excess:
            return
        # the ones that ended first go: last reported longest ago (a member reported all along that ends now is
        # the most recent, wherever it stands in the list)
        inactive.sort(key=lambda k: track.members[k].received)
        for oldest in inactive[:excess]:
            del track.members[oldest]
            if self._local.get(oldest) == track.gid:
                del self._local[oldest]

    def _refresh(self, track: GlobalTrack, now: float, wall: float) -> None:
        active = [m for m in track.members.values() if m.active]
        if active:
            weights = np.array([max(m.score, 1e-3) for m in active])
            weights /= weights.sum()
            track.lat = float(np.dot(weights, [m.lat for m in active]))
            track.lon = weighted_lon(weights, [m.lon for m in active])  # across the antimeridian too
            track.vel_en = (
                float(np.dot(weights, [m.vel_en[0] for m in active])),
                float(np.dot(weights, [m.vel_en[1] for m in active])),
            )
            track.score = float(max(m.score for m in active))
            track.last_update = wall
            track.lost_since = None
            self._lost.pop(track.gid, None)
            last = track.history[-1][0] if track.history else -math.inf
            if wall - last >= self.history_interval_s:
                row = (wall, track.lat, track.lon)
                track.history.append(row)
                if self.keep_changes:
                    self._history_out.append((track.gid, *row))
        elif track.lost_since is None:
            track.lost_since = now
            self._lost[track.gid] = None
        if self.keep_changes:
            self._dirty.add(track.gid)

    def expire(self, now: float | None = None) -> bool:
        """Lose members whose UAV went quiet, end tracks held longer than hold_s; True if changed."""
        now = self._clock() if now is None else now
        wall = self._wall()
        changed = False
        with self._lock:
            for uav in [u for u, last in self._last_msg.items() if now - last > self.member_ttl_s]:
                changed |= self._lose_uav(uav, now, wall)
            for gid in list(self._lost):
                track = self._tracks[gid]
                if track.lost_since is not None and now - track.lost_since <= self.hold_s:
                    break  # oldest first: the rest were lost later
                self._end(gid, wall)
                changed = True
            if changed:
                self.version += 1
        return changed

    def _lose_uav(self, uav: str, now: float, wall: float) -> bool:
        if self.reassociation is not None:
            self.reassociation.forget(uav)
        touched: set[int] = set()
        for local_id in self._active.pop(uav, set()):
            touched |= self._deactivate(uav, local_id)
        self._last_msg.pop(uav, None)
        for gid in touched:
            self._refresh(self._tracks[gid], now, wall)
        return bool(touched)

    def uav_lost(self, uav: str, now: float | None = None) -> bool:
        """Mark every member of ``uav`` lost (its liveliness token went away); True if changed."""
        now = self._clock() if now is None else now
        wall = self._wall()
        with self._lock:
            changed = self._lose_uav(uav, now, wall)
            if changed:
                self.version += 1
        return changed

    def _end(self, gid: int, wall: float) -> None:
        track = self._tracks.pop(gid)
        self._lost.pop(gid, None)
        owner = self._owner.pop(gid, None)
        if owner is not None:
            owned = self._owned.get(owner)
            if owned is not None:
                owned.pop(gid, None)
                if not owned:
                    del self._owned[owner]
        track.ended = wall
        for key, member in track.members.items():
            if self._local.get(key) == gid:
                del self._local[key]
                if member.active:
                    self._active.get(key[0], set()).discard(key[1])
        record = track.to_record()
        self._ended.append(record)
        if self.keep_changes:
            self._dirty.add(gid)
            self._ended_pending[gid] = record

    def dropped(self) -> dict[str, int]:
        """What the bounds refused, by reason: "too_many_tracks" (track items cut from messages), "uav_track_quota"
        / "too_many_global_tracks" (new tracks that got no global id), "evicted_lost" (held ones ended for room)."""
        with self._lock:
            return dict(self._dropped)

    def stats(self) -> dict[str, int]:
        """Sizes and counters: global tracks, held ones, mapped local ids, greedy association groups."""
        with self._lock:
            return {"tracks": len(self._tracks), "lost": len(self._lost), "local_ids": len(self._local),
                    "greedy_components": self._greedy_groups,
                    "reassociated": self.reassociation.moved if self.reassociation is not None else 0}

    # ---- restore / persistence -----------------------------------------------------------------
    def restore(self, records: Iterable[TrackRecord], now: float | None = None) -> int:
        """Load tracks saved by a previous run: alive ones are held as lost (hold_s from now) so
        UAVs re-adopt them; their members' local ids keep their global ids. Returns the count."""
        now = self._clock() if now is None else now
        count = 0
        with self._lock:
            for rec in records:
                self._next_gid = max(self._next_gid, self._aligned(rec.gid + 1))
                if rec.ended is not None:
                    self._ended.append(rec)
                    continue
                track = GlobalTrack(
                    gid=rec.gid, cls=rec.cls, lat=rec.lat, lon=rec.lon, score=rec.score, vel_en=rec.vel_en,
                    created=rec.created, last_update=rec.last_update, lost_since=now,
                    history=deque(rec.history, maxlen=self.history_len),
                )
                for key in rec.members:
                    track.members[key] = Member(rec.lat, rec.lon, rec.score, rec.vel_en, now, active=False)
                    self._local[key] = rec.gid
                self._tracks[rec.gid] = track
                self._lost[rec.gid] = None
                owner = rec.members[0][0] if rec.members else ""
                self._owner[rec.gid] = owner
                self._owned.setdefault(owner, {})[rec.gid] = None
                count += 1
            self.version += 1
        return count

    def _aligned(self, value: int) -> int:
        """The smallest id >= value in this tracker's id series (next_gid modulo gid_step)."""
        return value + (self._gid_residue - value) % self.gid_step

    def hand_over(self, gid: int) -> bool:
        """End global track ``gid`` if it is held (no UAV reports it here any more) because another
        shard carries it on; returns whether it ended. A track still reported here stays."""
        with self._lock:
            if gid not in self._lost:
                return False
            self.handovers["out"] += 1
            self._end(gid, self._wall())
            self.version += 1
            return True

    def drain_changes(self) -> tuple[list[TrackRecord], list[tuple[int, float, float, float]]]:
        """Tracks changed (or ended) since the last call, and new history rows (gid, t, lat, lon)."""
        with self._lock:
            records = []
            for gid in self._dirty:
                track = self._tracks.get(gid)
                if track is not None:
                    records.append(track.to_record())
                elif gid in self._ended_pending:
                    records.append(self._ended_pending[gid])
            self._dirty.clear()
            self._ended_pending.clear()
            history, self._history_out = self._history_out, []
            return records, history

    @property
    def next_gid(self) -> int:
        """The global id the next new track gets."""
        return self._next_gid  # no lock: one attribute read

    # ---- reading -------------------------------------------------------------------------------
    def records(self, include_ended: bool = False) -> list[TrackRecord]:
        """Current global tracks (tracked and lost), plus recently ended ones if asked, by gid."""
        with self._lock:
            rows = [track.to_record() for track in self._tracks.values()]
            if include_ended:
                rows.extend(self._ended)
        return sorted(rows, key=lambda r: r.gid)

    def gid_of(self, uav: str, local_id: int) -> int | None:
        """The global id of a UAV's local track (a member of a live global track), else None."""
        gid = self._local.get((uav, local_id))  # no lock: two dict reads
        return gid if gid in self._tracks else None

    def joint_message(self, max_tracks: int = MAX_TRACKS) -> JointTracksMessage:
        """The ``joint/tracks`` message: the current global tracks with the local ids they absorbed, and
        (``active``) which of them still report each track when not all do.

        At most ``max_tracks`` (by gid): tracked ones first, then the most recently updated held ones.
        """
        with self._lock:
            tracks = list(self._tracks.values())
            if len(tracks) > max_tracks:
                tracks.sort(key=lambda t: (t.lost_since is not None, -t.last_update))
                tracks = tracks[:max_tracks]
            items = tuple(
                JointTrackItem(
                    gid=t.gid, cls=t.cls, lat=t.lat, lon=t.lon, score=min(max(t.score, 0.0), 1.0),
                    vel_en=t.vel_en, members=tuple(t.members), active=active_indexes(t),
                )
                for t in sorted(tracks, key=lambda t: t.gid)
            )
        return JointTracksMessage(t=self._wall(), tracks=items)

    def __len__(self) -> int:
        # no lock: len() of a dict is atomic, and /healthz must never wait for an association
        return len(self._tracks)

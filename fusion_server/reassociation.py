"""Re-association: a UAV's local track moves to the global track the other UAVs see its object under, on the
evidence of seconds.

The global tracker joins a new local track to the nearest global track once, when it first arrives, and keeps it
there. That one look is often wrong: the partner's track of the object may not exist yet (it joins the nearest
other object's, within the 10 m gate), two UAVs' telemetry places one object 1-5 m apart, so in a group the
nearest is another person, and a UAV's tracker can swap two people's local ids. On the simulator's cooperative
flights a third to a half of the objects two UAVs both tracked ended with two global ids (issue 30; docs/fusion.md,
"Re-association").

Here every UAV's live local tracks are compared, twice a second, with the global tracks other UAVs report: the
distance from each local track to each such track's other-UAV members (their score-weighted position, moved on
by their velocities) is averaged over `window_s` (an exponential mean, restarted after a gap). A local track moves
only when an assignment of all that UAV's tracks of a class (one to one, `fusion_server.association`) puts it on
another global track whose mean distance has been measured for `min_age_s`, stays within `move_gate_m` and beats
its current track's by more than `hysteresis_m`; a local track whose track another of this UAV's takes over gets a
new global id. Weak or short evidence moves nothing. No I/O, no locks: `GlobalTracker` calls it under its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from fusion_server.association import gated_assignment, sphere_xyz
from fusion_server.track_records import GlobalTrack, Member, moved_on

__all__ = ["Reassociation", "seen_at"]

_MAX_SPEED_MS = 60.0  # the fastest a tracked object is taken to move in the neighbourhood search (a jetski: ~25)


@dataclass(slots=True)
class _Pair:
    mean_m: float  # exponential mean of the distance
    first: float  # when this run of measurements began
    last: float  # the latest measurement


class Reassociation:
    """Which of a UAV's local tracks to move to another global track (module doc).

    search_gate_m: pairs farther apart than this are not measured (the global tracker's gate); move_gate_m: the
    largest mean distance a move may go to; hysteresis_m: how much closer the new track must be than the current
    one; window_s: time constant of the mean; min_age_s: how long a pair must have been measured before it may win;
    period_s: at most one plan per UAV this often. Counts the moves in `moved`.
    """

    def __init__(self, *, search_gate_m: float = 10.0, move_gate_m: float = 6.0, hysteresis_m: float = 1.5,
                 window_s: float = 3.0, min_age_s: float = 3.0, period_s: float = 0.5) -> None:
        for name, value in (("search_gate_m", search_gate_m), ("move_gate_m", move_gate_m),
                            ("window_s", window_s), ("period_s", period_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Reassociation: {name} must be a finite number > 0, got {value!r}")
        for name, value in (("hysteresis_m", hysteresis_m), ("min_age_s", min_age_s)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"Reassociation: {name} must be a finite number >= 0, got {value!r}")
        self.search_gate_m = search_gate_m
        self.move_gate_m = move_gate_m
        self.hysteresis_m = hysteresis_m
        self.window_s = window_s
        self.min_age_s = min_age_s
        self.period_s = period_s
        #: a measurement this long after the previous one starts the pair's mean again
        self.max_gap_s = max(1.0, 2.5 * period_s)
        #: what a local track on no other UAV's track pays in the assignment for staying alone: without it the
        #: assignment formed the most pairs first and broke a right pair to pair a neighbour with it
        self.unmatched_cost = search_gate_m
        #: local tracks moved (counted by the tracker as it moves them)
        self.moved = 0
        self._index: tuple[float, cKDTree | None, list[int], float] = (-math.inf, None, [], 0.0)
        self._pairs: dict[str, dict[int, dict[int, _Pair]]] = {}  # uav -> local id -> gid -> its mean distance
        self._last_plan: dict[str, float] = {}

    def turn(self, uav: str, now: float) -> bool:
        """Whether `uav`'s local tracks are to be planned at `now` (at most once per period_s); True starts a turn."""
        if now - self._last_plan.get(uav, -math.inf) < self.period_s - 1e-9:
            return False
        self._last_plan[uav] = now
        return True

    def plan(self, uav: str, local_ids: list[int], current: list[int], lat: ArrayLike, lon: ArrayLike,
             gids: list[int], other_lat: ArrayLike, other_lon: ArrayLike, now: float) -> dict[int, int | None]:
        """The moves for one UAV's local tracks of one class: {index into local_ids: new gid, or None for a new
        global track}. current: each local track's global id now; lat, lon: their positions; gids, other_lat,
        other_lon: the global tracks of the class that other UAVs report, at their other-UAV members' position.
        Either UAV's plan may mend a wrong pair, so which of the two ids the object keeps is whichever moves first
        (moving only to older tracks, to keep the older id, scored IDF1 84.4 against 85.4 on the tuning flights)."""
        if not local_ids or not gids:
            return {}
        book = self._pairs.setdefault(uav, {})

        def cost(ia: np.ndarray, ib: np.ndarray, dist: np.ndarray) -> np.ndarray:
            out = np.full(len(ia), np.inf)
            for k, (i, j, d) in enumerate(zip(ia.tolist(), ib.tolist(), dist.tolist(), strict=True)):
                pair = self._measure(book.setdefault(local_ids[i], {}), gids[j], d, now)
                if gids[j] == current[i]:
                    out[k] = pair.mean_m - self.hysteresis_m
                elif now - pair.first >= self.min_age_s and pair.mean_m <= self.move_gate_m:
                    out[k] = pair.mean_m
            return out

        # a local track on no other UAV's track may stay alone (at unmatched_cost: a move must pay for itself); one
        # on another UAV's track leaves it only when another of this UAV's takes it over
        on_shared = set(gids)
        alone = np.array([self.unmatched_cost if g not in on_shared else np.inf for g in current])
        match = gated_assignment(lat, lon, other_lat, other_lon, self.search_gate_m, cost=cost, unmatched_cost=alone)
        for local_id in local_ids:  # a pair not measured now starts again when it is
            pairs = book.get(local_id, {})
            for gid in [g for g, pair in pairs.items() if pair.last != now]:
                del pairs[gid]
        want = {int(r): gids[int(c)] for r, c in zip(match.rows, match.cols, strict=True)}
        taken = set(want.values())
        moves: dict[int, int | None] = {}
        for i, gid in enumerate(current):
            new = want.get(i)
            if new is not None and new != gid:
                moves[i] = new
            elif new is None and gid in taken:  # another of this UAV's local tracks takes its track over
                moves[i] = None
        return moves

    def near(self, tracks: dict[int, GlobalTrack], now: float, lat: list[float], lon: list[float]) -> set[int]:
        """The global ids of `tracks` that may lie within the search gate of the points (lat, lon): a k-d tree
        over all tracks' positions, rebuilt at most once per period_s (so a turn costs what its neighbourhood
        holds, not the fleet), searched with a margin for what the fastest track (20-60 m/s) moves meanwhile."""
        built, tree, gids, speed = self._index
        if tree is None or now - built >= self.period_s or now < built:
            gids = list(tracks)
            tree = cKDTree(sphere_xyz(np.array([tracks[g].lat for g in gids]).reshape(-1),
                                      np.array([tracks[g].lon for g in gids]).reshape(-1))) if gids else None
            speed = max((math.hypot(*tracks[g].vel_en) for g in gids), default=0.0)
            # a forged velocity must not make every turn search the whole map: at most _MAX_SPEED_MS
            self._index = built, tree, gids, speed = (now, tree, gids, min(speed, _MAX_SPEED_MS)
                                                      if math.isfinite(speed) else _MAX_SPEED_MS)
        if tree is None or not lat:
            return set()
        # what the fastest track (at least 20 m/s) can move between the tree's build and the end of its period
        radius = self.search_gate_m + max(speed, 20.0) * (now - built + self.period_s) + 1.0
        hits = tree.query_ball_point(sphere_xyz(np.asarray(lat, np.float64), np.asarray(lon, np.float64)), radius)
        return {gids[k] for row in hits for k in row}

    def _measure(self, pairs: dict[int, _Pair], gid: int, dist: float, now: float) -> _Pair:
        pair = pairs.get(gid)
        if pair is None or now - pair.last > self.max_gap_s:
            pair = pairs[gid] = _Pair(dist, now, now)
        elif now > pair.last:
            pair.mean_m += (1.0 - math.exp(-(now - pair.last) / self.window_s)) * (dist - pair.mean_m)
            pair.last = now
        return pair

    def forget(self, uav: str, keep: set[int] | None = None) -> None:
        """Drop the measurements of `uav`'s local tracks not in keep (all of them with None)."""
        if keep is None:
            self._pairs.pop(uav, None)
            self._last_plan.pop(uav, None)
            return
        book = self._pairs.get(uav, {})
        for local_id in [k for k in book if k not in keep]:
            del book[local_id]


def seen_at(groups: list[list[Member]], now: float, max_age_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Per group of members, their score-weighted position moved on by their velocities to now (for at most
    max_age_s; degrees, the longitudes averaged as offsets from each group's first, across the antimeridian)."""
    members = [m for group in groups for m in group]
    sizes = [len(group) for group in groups]
    index = np.repeat(np.arange(len(groups)), sizes)
    lat, lon = moved_on(np.array([m.lat for m in members]), np.array([m.lon for m in members]),
                        np.array([m.vel_en for m in members]).reshape(-1, 2),
                        np.array([min(max(now - m.received, 0.0), max_age_s) for m in members]))
    weights = np.array([max(m.score, 1e-3) for m in members])
    total = np.bincount(index, weights, len(groups))
    first = lon[np.r_[0, np.cumsum(sizes)[:-1]]]
    offsets = (lon - first[index] + 180.0) % 360.0 - 180.0
    mean_lon = first + np.bincount(index, weights * offsets, len(groups)) / total
    return np.bincount(index, weights * lat, len(groups)) / total, (mean_lon + 180.0) % 360.0 - 180.0

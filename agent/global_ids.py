"""Global track ids for this UAV's local tracks: the fusion server's membership lists, or, for a newly
seen object, the nearest global track of its class (the id another UAV has been tracking it under).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from shared.geo import latlon_to_local
from shared.messages import JointTracksMessage

__all__ = ["GlobalIdAdopter"]

log = logging.getLogger(__name__)


@dataclass(slots=True)
class _LocalTrack:
    born: float  # wall seconds (monotonic) the local track was first reported
    last: float
    gid: int | None = None
    via: str = ""  # "position" or "server"


class GlobalIdAdopter:
    """Which global track (fusion server id) each local track of this UAV is.

    Two rules, checked every update:

    * membership: a global track listing ``(uav, local id)`` among its members gives its gid (the
      server's association wins over everything else);
    * position: a local track reported for less than ``window_s`` with no gid yet takes the gid of the
      nearest global track of its class within ``gate_m`` metres that is not already another of this
      UAV's current tracks: the object another UAV has been tracking keeps its id when this UAV
      starts seeing it.

    uav: this UAV's id; horizon_s: a local track unseen this long is forgotten.
    """

    def __init__(self, uav: str, *, gate_m: float = 10.0, window_s: float = 2.0, horizon_s: float = 300.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.uav = uav
        self.gate_m = gate_m
        self.window_s = window_s
        self.horizon_s = horizon_s
        self.clock = clock
        self._tracks: dict[int, _LocalTrack] = {}
        self.n_adopted_by_position = 0

    def gid_of(self, local_id: int) -> int | None:
        """The adopted global id of a local track, or None."""
        entry = self._tracks.get(local_id)
        return None if entry is None else entry.gid

    def gids(self) -> dict[int, int]:
        """local id -> global id for every local track that has one."""
        return {lid: e.gid for lid, e in self._tracks.items() if e.gid is not None}

    def update(self, tracks: list[tuple[int, str, float, float]], joint: JointTracksMessage | None) -> dict[int, int]:
        """Take this UAV's reported tracks ``(local id, class name, lat, lon)`` and the latest global
        tracks (None when none are known or they are stale); returns :meth:`gids`."""
        now = self.clock()
        for lid, *_ in tracks:
            entry = self._tracks.get(lid)
            if entry is None:
                self._tracks[lid] = _LocalTrack(born=now, last=now)
            else:
                entry.last = now
        if joint is not None and joint.tracks:
            self._by_membership(joint)
            self._by_position(tracks, joint, now)
        for lid in [k for k, e in self._tracks.items() if now - e.last > self.horizon_s]:
            del self._tracks[lid]
        return self.gids()

    def _by_membership(self, joint: JointTracksMessage) -> None:
        for g in joint.tracks:
            for uav, lid in g.members:
                if uav == self.uav and lid in self._tracks:
                    entry = self._tracks[lid]
                    if entry.gid != g.gid:
                        log.debug("local track %d is global %d (server membership)", lid, g.gid)
                    entry.gid, entry.via = g.gid, "server"

    def _by_position(self, tracks: list[tuple[int, str, float, float]], joint: JointTracksMessage, now: float) -> None:
        current = {lid for lid, *_ in tracks}
        taken = {self._tracks[lid].gid for lid in current if self._tracks[lid].gid is not None}
        # a global track holding another of our current local tracks is that object, not this one
        taken |= {g.gid for g in joint.tracks if any(u == self.uav and lid in current for u, lid in g.members)}
        want = [(lid, cls, lat, lon) for lid, cls, lat, lon in tracks
                if self._tracks[lid].gid is None and now - self._tracks[lid].born <= self.window_s]
        if not want:
            return
        for cls in sorted({w[1] for w in want}):
            mine = [w for w in want if w[1] == cls]
            theirs = [g for g in joint.tracks if g.cls == cls and g.gid not in taken]
            if not theirs:
                continue
            lat0, lon0 = mine[0][2], mine[0][3]
            e1, n1 = latlon_to_local(np.array([w[2] for w in mine]), np.array([w[3] for w in mine]), lat0, lon0)
            e2, n2 = latlon_to_local(np.array([g.lat for g in theirs]), np.array([g.lon for g in theirs]), lat0, lon0)
            dist = np.hypot(e1[:, None] - e2[None, :], n1[:, None] - n2[None, :])  # (mine, theirs) metres
            # greedy by distance: closest pairs first, each global and local track used once
            for flat in np.argsort(dist, axis=None):
                i, j = divmod(int(flat), len(theirs))
                if dist[i, j] > self.gate_m:
                    break
                lid, gid = mine[i][0], theirs[j].gid
                if self._tracks[lid].gid is not None or gid in taken:
                    continue
                self._tracks[lid].gid, self._tracks[lid].via = gid, "position"
                taken.add(gid)
                self.n_adopted_by_position += 1
                log.info("local track %d adopts global id %d (%.1f m away)", lid, gid, dist[i, j])

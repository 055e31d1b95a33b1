"""A global track and its parts: the members (UAVs' local tracks) it absorbed and the immutable record the REST
API, persistence and the shards read. No I/O, no locks: `fusion_server.global_tracks.GlobalTracker` owns them."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fusion_server.association import M_PER_DEG_LAT as _M_PER_DEG_LAT

__all__ = ["GlobalTrack", "Member", "TrackRecord", "active_indexes", "moved_on"]


def moved_on(lat: np.ndarray, lon: np.ndarray, vel_en: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (degrees) moved on by velocities (N, 2) east, north m/s for dt (N,) seconds."""
    return (lat + vel_en[:, 1] * dt / _M_PER_DEG_LAT,
            lon + vel_en[:, 0] * dt / (_M_PER_DEG_LAT * np.maximum(np.cos(np.radians(lat)), 1e-6)))


@dataclass(slots=True)
class Member:
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]
    received: float  # monotonic
    active: bool = True


@dataclass(slots=True)
class GlobalTrack:
    """One global track. Positions in degrees, velocities (east, north) m/s, times epoch seconds.

    members: every local track it absorbed, ``(uav, local_id) -> observation``, insertion ordered;
    ``active`` members are the ones their UAV still reports. lost_since: monotonic time the last
    active member was lost (None while tracked). history: (t, lat, lon) rows, oldest first, bounded.
    """

    gid: int
    cls: str
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]
    created: float
    last_update: float
    members: dict[tuple[str, int], Member] = field(default_factory=dict)
    lost_since: float | None = None
    history: deque = field(default_factory=deque)
    ended: float | None = None

    def active_members(self) -> list[tuple[str, int]]:
        """(uav, local_id) of the members their UAVs currently report."""
        return [key for key, member in self.members.items() if member.active]

    def to_record(self) -> TrackRecord:
        """A plain copy for persistence and for the REST API."""
        return TrackRecord(
            gid=self.gid,
            cls=self.cls,
            lat=self.lat,
            lon=self.lon,
            score=self.score,
            vel_en=self.vel_en,
            created=self.created,
            last_update=self.last_update,
            members=tuple(self.members),
            active=tuple(self.active_members()),
            ended=self.ended,
            history=tuple(self.history),
        )


def active_indexes(track: GlobalTrack) -> tuple[int, ...] | None:
    """``JointTrackItem.active`` of a track: the indexes of its active members, None when all are."""
    flags = [member.active for member in track.members.values()]
    if flags and all(flags):
        return None
    return tuple(i for i, active in enumerate(flags) if active)


@dataclass(frozen=True, slots=True)
class TrackRecord:
    """Immutable view of a global track (see :class:`GlobalTrack`); ``ended`` is None while alive."""

    gid: int
    cls: str
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]
    created: float
    last_update: float
    members: tuple[tuple[str, int], ...]
    active: tuple[tuple[str, int], ...] = ()
    ended: float | None = None
    history: tuple[tuple[float, float, float], ...] = ()

    @property
    def status(self) -> str:
        """"tracked" (a UAV reports it), "lost" (held, nobody reports it) or "ended"."""
        if self.ended is not None:
            return "ended"
        return "tracked" if self.active else "lost"

    def to_geojson(self) -> dict[str, Any]:
        """A GeoJSON Point Feature; properties hold gid, cls, score, vel_en, members, history, times."""
        return {
            "type": "Feature",
            "id": self.gid,
            "geometry": {"type": "Point", "coordinates": [self.lon, self.lat]},
            "properties": {
                "gid": self.gid, "cls": self.cls, "score": self.score, "vel_en": list(self.vel_en),
                "status": self.status, "created": self.created, "last_update": self.last_update, "ended": self.ended,
                "members": [list(m) for m in self.members],
                "active_members": [list(m) for m in self.active],
                "history": [list(row) for row in self.history],
            },
        }

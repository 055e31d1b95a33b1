"""What the server knows about each UAV: liveliness, last message, last state, message rates.

Fed by the Zenoh side (liveliness samples and valid messages), read by ``GET /v1/uavs``. The number
of UAVs is bounded so a flood of made-up ids cannot exhaust memory. Thread-safe.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from fusion_server.metrics import RateWindow
from shared.messages import StateMessage

__all__ = ["UavRegistry", "state_to_dict"]


def state_to_dict(state: StateMessage) -> dict[str, Any]:
    """A state message as JSON-ready data (the wire fields without ``v``)."""
    return {
        "uav": state.uav,
        "t": state.t,
        "lat": state.lat,
        "lon": state.lon,
        "height_m": state.height_m,
        "pitch_deg": state.pitch_deg,
        "heading_deg": state.heading_deg,
        "footprint": [[lat, lon] for lat, lon in state.footprint],
        "camera": state.camera.to_dict(),
    }


@dataclass(slots=True)
class _Uav:
    online: bool = False
    last_seen: float | None = None  # wall time
    online_since: float | None = None
    state: StateMessage | None = None
    rates: dict[str, RateWindow] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)


class UavRegistry:
    """Per-UAV status. max_uavs bounds the number of ids kept (new ids beyond it are refused)."""

    def __init__(self, max_uavs: int = 256, clock=time.monotonic, wall=time.time) -> None:
        self.max_uavs = max_uavs
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        self._uavs: dict[str, _Uav] = {}

    def _get(self, uav: str) -> _Uav | None:
        entry = self._uavs.get(uav)
        if entry is None:
            if len(self._uavs) >= self.max_uavs:
                self._evict_one()
                if len(self._uavs) >= self.max_uavs:
                    return None
            entry = self._uavs[uav] = _Uav()
        return entry

    def _evict_one(self) -> None:
        # forget the offline UAV seen longest ago, so a fleet that changes over a long mission fits
        offline = [(e.last_seen or 0.0, uav) for uav, e in self._uavs.items() if not e.online]
        if offline:
            del self._uavs[min(offline)[1]]

    def alive(self, uav: str, online: bool) -> bool:
        """Record a liveliness token appearing (online) or disappearing; False if refused (full)."""
        now = self._wall()
        with self._lock:
            entry = self._get(uav)
            if entry is None:
                return False
            if online and not entry.online:
                entry.online_since = now
            entry.online = online
            entry.last_seen = now
            return True

    def message(self, uav: str, kind: str, nbytes: int, state: StateMessage | None = None) -> bool:
        """Record a valid message (kind "tile", "state" or "tracks"); False if refused (full)."""
        now_mono = self._clock()
        with self._lock:
            entry = self._get(uav)
            if entry is None:
                return False
            entry.last_seen = self._wall()
            window = entry.rates.get(kind)
            if window is None:
                window = entry.rates[kind] = RateWindow()
            window.add(now_mono, 1, nbytes)
            entry.counts[kind] = entry.counts.get(kind, 0) + 1
            if state is not None:
                entry.state = state
            return True

    def online(self) -> list[str]:
        """Ids of the UAVs whose liveliness token is present."""
        with self._lock:
            return sorted(uav for uav, entry in self._uavs.items() if entry.online)

    def snapshot(self, tile_counts: dict[str, int] | None = None) -> list[dict[str, Any]]:
        """``GET /v1/uavs`` rows, sorted by id.

        Each: id, online, last_seen (epoch seconds or None), online_since, state (last state message
        or None), rates ({kind: messages/s} over 10 s), bytes_per_s, messages ({kind: count}),
        tiles (fresh tiles it covers, when tile_counts is given).
        """
        now = self._clock()
        rows = []
        with self._lock:
            for uav, entry in sorted(self._uavs.items()):
                rates = {kind: window.rates(now) for kind, window in entry.rates.items()}
                row = {
                    "id": uav,
                    "online": entry.online,
                    "last_seen": entry.last_seen,
                    "online_since": entry.online_since,
                    "state": state_to_dict(entry.state) if entry.state is not None else None,
                    "rates": {kind: round(r[0], 3) for kind, r in rates.items()},
                    "bytes_per_s": round(sum(r[1] for r in rates.values()), 1),
                    "messages": dict(entry.counts),
                }
                if tile_counts is not None:
                    row["tiles"] = tile_counts.get(uav, 0)
                rows.append(row)
        return rows

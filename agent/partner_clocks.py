"""The other UAVs' source clocks, as their state messages show them (for AgentSettings.replay_sync_s)."""

from __future__ import annotations

import threading
import time
from collections import deque

__all__ = ["CLOCK_HISTORY_S", "PartnerClocks"]

#: Each UAV's state messages are kept at least this long (s), for its clock's rate.
CLOCK_HISTORY_S = 1.5


class PartnerClocks:
    """Thread-safe: `observe` from the Zenoh callbacks, `read` from the agent's loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # uav -> (source time, monotonic receive time) of its states over the last CLOCK_HISTORY_S
        self._history: dict[str, deque[tuple[float, float]]] = {}

    def observe(self, uav: str, t: float) -> None:
        """A state message of uav with source time t arrived now."""
        now = time.monotonic()
        with self._lock:
            history = self._history.setdefault(uav, deque())
            history.append((t, now))
            while len(history) > 2 and now - history[1][1] >= CLOCK_HISTORY_S:
                history.popleft()

    def read(self, max_age_s: float) -> list[tuple[str, float, float, float | None]]:
        """(uav, t of its latest state, that state's age in wall seconds, the clock's rate in source seconds per wall
        second over the last second or more, None before a second of states), for UAVs whose latest state is at
        most max_age_s old."""
        now = time.monotonic()
        out = []
        with self._lock:
            for uav, history in self._history.items():
                t, received = history[-1]
                if now - received > max_age_s:
                    continue
                t0, w0 = history[0]
                rate = (t - t0) / (received - w0) if received - w0 >= 1.0 else None
                out.append((uav, t, now - received, rate))
        return out

"""The other UAVs' source clocks, as their state messages show them (for AgentSettings.replay_sync_s)."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

__all__ = ["CLOCK_HISTORY_S", "PARTNER_KEEP_S", "PartnerClocks"]

#: Each UAV's state messages are kept at least this long (s), for its clock's rate.
CLOCK_HISTORY_S = 1.5
#: A UAV whose latest state is older than this (s) is forgotten (a day of UAVs coming and going piles up otherwise).
PARTNER_KEEP_S = 60.0
#: Least time between two sweeps for forgotten UAVs (s).
_SWEEP_S = 1.0


class PartnerClocks:
    """Thread-safe: `observe` from the Zenoh callbacks, `read` from the agent's loop.

    clock: monotonic seconds (receive times and ages).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        # uav -> (source time, monotonic receive time) of its states over the last CLOCK_HISTORY_S
        self._history: dict[str, deque[tuple[float, float]]] = {}
        self._next_sweep = -float("inf")

    def observe(self, uav: str, t: float) -> None:
        """A state message of uav with source time t arrived now."""
        now = self._clock()
        with self._lock:
            self._sweep(now)
            history = self._history.setdefault(uav, deque())
            history.append((t, now))
            while len(history) > 2 and now - history[1][1] >= CLOCK_HISTORY_S:
                history.popleft()

    def read(self, max_age_s: float) -> list[tuple[str, float, float, float | None]]:
        """(uav, t of its latest state, that state's age in wall seconds, the clock's rate in source seconds per wall
        second over the last second or more, None before a second of states), for UAVs whose latest state is at
        most max_age_s old (and at most PARTNER_KEEP_S: older ones are forgotten)."""
        now = self._clock()
        out = []
        with self._lock:
            self._sweep(now)
            for uav, history in self._history.items():
                t, received = history[-1]
                if now - received > max_age_s:
                    continue
                t0, w0 = history[0]
                rate = (t - t0) / (received - w0) if received - w0 >= 1.0 else None
                out.append((uav, t, now - received, rate))
        return out

    def _sweep(self, now: float) -> None:
        """Forget the UAVs not heard for PARTNER_KEEP_S (lock held; at most once per _SWEEP_S)."""
        if now < self._next_sweep:
            return
        self._next_sweep = now + _SWEEP_S
        for uav in [uav for uav, history in self._history.items() if now - history[-1][1] > PARTNER_KEEP_S]:
            del self._history[uav]

"""Per-UAV rate limits of the fusion server: messages and payload bytes per second, token buckets.

Checked before a message is decoded (its size is known from the sample), so a UAV that floods the
server, misbehaving or forged, costs a dictionary lookup per message and cannot crowd out the other
UAVs' data. The number of buckets is bounded (least recently used ones are forgotten). Thread-safe.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

__all__ = ["UavRateLimiter"]


class UavRateLimiter:
    """Token buckets per UAV id: ``max_msgs_per_s`` messages and ``max_bytes_per_s`` bytes a second,
    each allowing a burst of ``burst_s`` seconds' worth. max_uavs: buckets kept."""

    def __init__(self, max_msgs_per_s: float = 500.0, max_bytes_per_s: float = 4 * 1024 * 1024,
                 burst_s: float = 2.0, max_uavs: int = 1024, clock=time.monotonic) -> None:
        for name, value in (("max_msgs_per_s", max_msgs_per_s), ("max_bytes_per_s", max_bytes_per_s),
                            ("burst_s", burst_s)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self.max_msgs_per_s = float(max_msgs_per_s)
        self.max_bytes_per_s = float(max_bytes_per_s)
        self.burst_s = float(burst_s)
        self.max_uavs = int(max_uavs)
        self._clock = clock
        self._lock = threading.Lock()
        # uav -> [message tokens, byte tokens, monotonic time of the last refill]
        self._buckets: OrderedDict[str, list[float]] = OrderedDict()

    def check(self, uav: str, nbytes: int, now: float | None = None) -> str | None:
        """Charge one message of ``nbytes`` to ``uav``: None if allowed, else the reason it is not
        ("rate_limited": too many messages a second; "byte_rate_limited": too many bytes). A refused
        message costs no tokens."""
        now = self._clock() if now is None else now
        msg_cap = self.max_msgs_per_s * self.burst_s
        byte_cap = self.max_bytes_per_s * self.burst_s
        with self._lock:
            bucket = self._buckets.get(uav)
            if bucket is None:
                bucket = self._buckets[uav] = [msg_cap, byte_cap, now]
                while len(self._buckets) > self.max_uavs:
                    self._buckets.popitem(last=False)
            else:
                self._buckets.move_to_end(uav)
                elapsed = max(now - bucket[2], 0.0)
                bucket[0] = min(msg_cap, bucket[0] + elapsed * self.max_msgs_per_s)
                bucket[1] = min(byte_cap, bucket[1] + elapsed * self.max_bytes_per_s)
                bucket[2] = now
            if bucket[0] < 1.0:
                return "rate_limited"
            if bucket[1] < nbytes:
                return "byte_rate_limited"
            bucket[0] -= 1.0
            bucket[1] -= nbytes
            return None

"""Counters, message rates and the fusion-latency histogram of the server, in Prometheus text format.

Thread-safe; cheap enough to update from Zenoh callbacks (a lock and a few dict operations).
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections import deque
from collections.abc import Mapping

import numpy as np

__all__ = ["FusionMetrics", "LatencyHistogram", "RateWindow"]

#: Upper bounds (seconds) of the fusion latency histogram buckets.
LATENCY_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class RateWindow:
    """Events and bytes per second over the last ``window_s`` seconds, in 1-second buckets."""

    def __init__(self, window_s: int = 10) -> None:
        self.window_s = int(window_s)
        self._buckets: deque[list[float]] = deque()  # [second, count, bytes]

    def add(self, now: float, count: int = 1, nbytes: int = 0) -> None:
        """Count ``count`` events of ``nbytes`` bytes in total at monotonic time ``now``."""
        second = math.floor(now)
        if self._buckets and self._buckets[-1][0] == second:
            bucket = self._buckets[-1]
            bucket[1] += count
            bucket[2] += nbytes
        else:
            self._buckets.append([second, count, nbytes])
        while self._buckets and self._buckets[0][0] <= second - self.window_s:
            self._buckets.popleft()

    def rates(self, now: float) -> tuple[float, float]:
        """(events per second, bytes per second) over the window ending at ``now``."""
        start = math.floor(now) - self.window_s
        count = sum(b[1] for b in self._buckets if b[0] > start)
        nbytes = sum(b[2] for b in self._buckets if b[0] > start)
        return count / self.window_s, nbytes / self.window_s


class LatencyHistogram:
    """Cumulative histogram (Prometheus buckets) plus the last ``recent`` samples for quantiles."""

    def __init__(self, buckets: tuple[float, ...] = LATENCY_BUCKETS_S, recent: int = 4096) -> None:
        self.bounds = buckets
        self.counts = [0] * (len(buckets) + 1)
        self.total = 0.0
        self.n = 0
        self._recent: deque[float] = deque(maxlen=recent)

    def observe(self, seconds: float) -> None:
        """Add one sample (seconds)."""
        self.counts[bisect.bisect_left(self.bounds, seconds)] += 1
        self.total += seconds
        self.n += 1
        self._recent.append(seconds)

    def quantile(self, q: float) -> float:
        """Quantile q in [0, 1] of the recent samples, seconds (NaN when there are none)."""
        if not self._recent:
            return math.nan
        return float(np.quantile(np.fromiter(self._recent, dtype=np.float64), q))


def _labels(labels: Mapping[str, str]) -> str:
    if not labels:
        return ""
    inner = ",".join(f'{k}="{_escape(v)}"' for k, v in labels.items())
    return "{" + inner + "}"


def _escape(value: str) -> str:
    return str(value).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _num(value: float) -> str:
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value)) if not float(value).is_integer() else str(int(value))


class FusionMetrics:
    """All counters of one fusion server. Kinds: "tile", "state", "tracks", "alive", "unknown"."""

    def __init__(self, clock=time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self.started = clock()
        self.received: dict[str, int] = {}
        self.received_bytes: dict[str, int] = {}
        self.rates: dict[str, RateWindow] = {}
        self.rejected: dict[tuple[str, str], int] = {}
        self.rejected_rate = RateWindow()
        self.joint_published = 0
        self.joint_dropped = 0
        self.tracks_published = 0
        self.tracks_left_out_total = 0
        self.queries = 0
        self.fusion_latency = LatencyHistogram()

    def message(self, kind: str, nbytes: int, count: int = 1) -> None:
        """Count ``count`` accepted messages of ``kind`` and ``nbytes`` payload bytes in total."""
        now = self._clock()
        with self._lock:
            self.received[kind] = self.received.get(kind, 0) + count
            self.received_bytes[kind] = self.received_bytes.get(kind, 0) + nbytes
            window = self.rates.get(kind)
            if window is None:
                window = self.rates[kind] = RateWindow()
            window.add(now, count, nbytes)

    def reject(self, kind: str, reason: str, count: int = 1) -> None:
        """Count ``count`` dropped messages (one by default)."""
        with self._lock:
            self.rejected[(kind, reason)] = self.rejected.get((kind, reason), 0) + count
            self.rejected_rate.add(self._clock(), count)

    def published(self, latency_s: float | None, dropped: bool = False) -> None:
        """Count one joint tile publication and its fusion latency (receive -> publish)."""
        with self._lock:
            if dropped:
                self.joint_dropped += 1
            else:
                self.joint_published += 1
            if latency_s is not None:
                self.fusion_latency.observe(latency_s)

    def tracks_sent(self) -> None:
        """Count one joint tracks publication."""
        with self._lock:
            self.tracks_published += 1

    def tracks_left_out(self, n: int) -> None:
        """Count global tracks left out of a joint tracks message (size bounds)."""
        with self._lock:
            self.tracks_left_out_total += n

    def query(self) -> None:
        """Count one query answered by the joint queryable."""
        with self._lock:
            self.queries += 1

    def rejected_by_reason(self) -> dict[str, int]:
        """Dropped messages per reason, all kinds added up."""
        with self._lock:
            totals: dict[str, int] = {}
            for (_, reason), count in self.rejected.items():
                totals[reason] = totals.get(reason, 0) + count
            return totals

    def message_rates(self) -> dict[str, float]:
        """Accepted messages per second per kind over the last 10 s."""
        now = self._clock()
        with self._lock:
            return {kind: window.rates(now)[0] for kind, window in self.rates.items()}

    def prometheus(self, gauges: Mapping[str, tuple[str, float]] | None = None,
                   reasons: Mapping[str, tuple[str, Mapping[str, int]]] | None = None,
                   labelled: Mapping[str, tuple[str, str, Mapping[str, float]]] | None = None) -> str:
        """The metrics in Prometheus text exposition format (version 0.0.4).

        gauges: extra gauges ``name -> (help, value)`` from other components. reasons: extra
        counters by reason ``name -> (help, {reason: count})`` (e.g. the tracker's bounds). labelled:
        extra gauges with one label ``name -> (help, label, {label value: value})`` (e.g. per UAV).
        """
        now = self._clock()
        lines: list[str] = []

        def family(name: str, kind: str, help_text: str) -> None:
            lines.append(f"# HELP {name} {help_text}")
            lines.append(f"# TYPE {name} {kind}")

        with self._lock:
            family("uavmm_fusion_messages_total", "counter", "Accepted agent messages by kind.")
            for kind, count in sorted(self.received.items()):
                lines.append(f"uavmm_fusion_messages_total{_labels({'kind': kind})} {count}")
            family("uavmm_fusion_message_bytes_total", "counter", "Payload bytes of accepted agent messages by kind.")
            for kind, count in sorted(self.received_bytes.items()):
                lines.append(f"uavmm_fusion_message_bytes_total{_labels({'kind': kind})} {count}")
            family("uavmm_fusion_message_rate", "gauge", "Accepted agent messages per second over the last 10 s.")
            for kind, window in sorted(self.rates.items()):
                lines.append(f"uavmm_fusion_message_rate{_labels({'kind': kind})} {_num(window.rates(now)[0])}")
            family("uavmm_fusion_rejected_total", "counter", "Dropped (invalid) messages by kind and reason.")
            for (kind, reason), count in sorted(self.rejected.items()):
                lines.append(f"uavmm_fusion_rejected_total{_labels({'kind': kind, 'reason': reason})} {count}")
            family("uavmm_fusion_rejected_rate", "gauge", "Dropped messages per second over the last 10 s.")
            lines.append(f"uavmm_fusion_rejected_rate {_num(self.rejected_rate.rates(now)[0])}")
            family("uavmm_fusion_joint_published_total", "counter", "Joint tiles published.")
            lines.append(f"uavmm_fusion_joint_published_total {self.joint_published}")
            family("uavmm_fusion_joint_dropped_total", "counter", "Joint tiles dropped (empty tile published).")
            lines.append(f"uavmm_fusion_joint_dropped_total {self.joint_dropped}")
            family("uavmm_fusion_tracks_published_total", "counter", "Joint tracks messages published.")
            lines.append(f"uavmm_fusion_tracks_published_total {self.tracks_published}")
            family("uavmm_fusion_tracks_left_out_total", "counter",
                   "Global tracks left out of joint tracks messages (message size bounds).")
            lines.append(f"uavmm_fusion_tracks_left_out_total {self.tracks_left_out_total}")
            family("uavmm_fusion_queries_total", "counter", "Queries answered on the joint queryable.")
            lines.append(f"uavmm_fusion_queries_total {self.queries}")
            hist = self.fusion_latency
            family("uavmm_fusion_latency_seconds", "histogram", "Receive of a tile -> publish of its joint tile.")
            cumulative = 0
            for bound, count in zip(hist.bounds, hist.counts, strict=False):
                cumulative += count
                lines.append(f'uavmm_fusion_latency_seconds_bucket{{le="{_num(bound)}"}} {cumulative}')
            lines.append(f'uavmm_fusion_latency_seconds_bucket{{le="+Inf"}} {hist.n}')
            lines.append(f"uavmm_fusion_latency_seconds_sum {_num(hist.total)}")
            lines.append(f"uavmm_fusion_latency_seconds_count {hist.n}")
            family("uavmm_fusion_latency_recent_seconds", "gauge", "Quantiles of the last 4096 fusion latencies.")
            for q in (0.5, 0.9, 0.99):
                lines.append(f'uavmm_fusion_latency_recent_seconds{{quantile="{q}"}} {_num(hist.quantile(q))}')
            family("uavmm_fusion_uptime_seconds", "gauge", "Seconds since the server started.")
            lines.append(f"uavmm_fusion_uptime_seconds {_num(now - self.started)}")
        for name, (help_text, counts) in sorted((reasons or {}).items()):
            family(name, "counter", help_text)
            for reason, count in sorted(counts.items()):
                lines.append(f"{name}{_labels({'reason': reason})} {count}")
        for name, (help_text, value) in sorted((gauges or {}).items()):
            family(name, "gauge", help_text)
            lines.append(f"{name} {_num(value)}")
        for name, (help_text, label, values) in sorted((labelled or {}).items()):
            family(name, "gauge", help_text)
            for key, value in sorted(values.items()):
                lines.append(f"{name}{_labels({label: key})} {_num(value)}")
        return "\n".join(lines) + "\n"

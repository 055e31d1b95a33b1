"""The autopilot's boot clock in MAVLink telemetry: its UNIX offset from ``SYSTEM_TIME`` (and that clock's jumps),
its ``time_boot_ms`` wrap at 2**32 ms, reboots in a ``.tlog``, and the vehicle's yaw interpolated to a position's boot
time.

Pure: numbers in, numbers out (the messages are decoded in `shared.telemetry.mavlink`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["BOOT_MS_WRAP", "CLOCK_JUMP_S", "RECEIVE_OFFSET_PERCENTILE", "REBOOT_S", "WRAP_WINDOW_S", "BootTimeUnwrap",
           "UnixClock", "boot_segments", "interpolate_yaw_deg", "receive_offset_s", "yaw_between_deg"]

#: Consecutive ``SYSTEM_TIME`` offsets (UNIX - boot) further apart than this are a step of the vehicle's UNIX clock
#: (set from the ground station's clock, then from GPS), not jitter: both stamps are taken at one tick on board.
CLOCK_JUMP_S = 1.0
#: A boot time this far behind the latest of the boot while the log's receive time goes on is a new boot; messages
#: of one boot come out of order by far less.
REBOOT_S = 3.0
#: ... unless the boot goes on within this much receive time after it (a late repeat, not a reboot).
REPEAT_WINDOW_S = 5.0

#: Without the vehicle's ``SYSTEM_TIME`` its boot clock is put on the log's receive clock at this low percentile of
#: (receive time - boot time): a packet is received its link latency after it was stamped, never before, so the
#: fastest packets say best where boot time 0 was; the median carried the median latency (0.4 s on a 0.15-0.65 s
#: radio: 2.9 m at 7 m/s). A percentile, not the minimum, so a few packets stamped early (a ground-station clock
#: step) do not pull it.
RECEIVE_OFFSET_PERCENTILE = 2.0

#: ``time_boot_ms`` counts modulo this (uint32 milliseconds: 49.7 days).
BOOT_MS_WRAP = 1 << 32
#: A wrap goes from within this of 2**32 ms to within this of 0 (a link gap up to this long), seconds.
WRAP_WINDOW_S = 60.0


@dataclass(slots=True)
class BootTimeUnwrap:
    """One boot clock's ``time_boot_ms`` (uint32) -> milliseconds since boot, counting on past 2**32 (`unwrap`).

    A value that went back is a wrap (2**32 ms more from then on) when, one wrap later, it is at most `WRAP_WINDOW_S`
    after the latest (so the latest was within that of 2**32 ms and it is within that of 0) and, with receive times,
    the receive time moved on as much: receive minus unwrapped boot time within `REBOOT_S` of the latest's (a reboot
    restarts the clock later by the boot's length). Other values that went back are kept for the reboot detection
    (a reboot, or a late repeat); one of the last wrap received after it stays on it. Values >= 2**32 pass unchanged.
    """

    wraps: int = 0
    _top_ms: int | None = None  # the largest unwrapped value so far
    _top_offset_s: float | None = None  # receive time minus boot time of that one, seconds

    def unwrap(self, boot_ms: int, rx_s: float | None = None) -> int:
        """The unwrapped boot time (ms) of ``boot_ms`` received at UNIX time ``rx_s`` (None: unknown)."""
        value, top, window = int(boot_ms), self._top_ms, WRAP_WINDOW_S * 1e3
        if value < BOOT_MS_WRAP and top is not None:
            value, later = value + self.wraps * BOOT_MS_WRAP, value + (self.wraps + 1) * BOOT_MS_WRAP
            if 0 < later - top <= window and (rx_s is None or self._top_offset_s is None
                                              or abs(rx_s - later / 1e3 - self._top_offset_s) <= REBOOT_S):
                self.wraps, value = self.wraps + 1, later
            elif self.wraps and 0 <= top - (value - BOOT_MS_WRAP) <= window:
                value -= BOOT_MS_WRAP  # sent before the wrap, received after it
        if top is None or value > top:
            self._top_ms, self._top_offset_s = value, None if rx_s is None else rx_s - value / 1e3
        return value


@dataclass(slots=True)
class UnixClock:
    """The UNIX time of one boot clock's zero, from a system's ``SYSTEM_TIME`` messages.

    offset_s: UNIX - boot seconds of the first message after the last jump (None before any message with a UNIX
    time); jumps: (boot s, step s) per step of the UNIX clock by more than `CLOCK_JUMP_S`, in arrival order.
    """

    offset_s: float | None = None
    jumps: list[tuple[float, float]] = field(default_factory=list)
    _last_s: float | None = None

    def add(self, boot_s: float, offset_s: float) -> None:
        """Take one ``SYSTEM_TIME``: its boot time and UNIX - boot offset, seconds."""
        if self._last_s is not None and abs(offset_s - self._last_s) > CLOCK_JUMP_S:
            self.jumps.append((boot_s, offset_s - self._last_s))
            self.offset_s = offset_s
        elif self.offset_s is None:
            self.offset_s = offset_s
        self._last_s = offset_s


def boot_segments(stamp_s: ArrayLike, boot_s: ArrayLike) -> NDArray[np.int64]:
    """Which boot each message of a log belongs to: (N,) receive times and (N,) boot times (NaN: the message has
    none) -> (N,) int segment index 0, 1, ... in log order.

    A new boot starts where the boot time falls more than `REBOOT_S` behind the latest of the current boot while the
    receive time is not behind the receive time of that latest one, and the current boot's stream does not go on
    within `REPEAT_WINDOW_S` of receive time after it (a reboot: receive time minus boot time jumps by more than
    REBOOT_S for good). Messages logged with an old receive time, and a late
    repeat (a link buffer flushed, a second link with more latency: old boot times received late while the stream
    goes on), start none.
    """
    stamps = np.asarray(stamp_s, dtype=float)
    boots = np.asarray(boot_s, dtype=float)
    out = np.zeros(len(stamps), dtype=np.int64)
    timed = np.flatnonzero(np.isfinite(boots))
    segment, top_boot, top_stamp = 0, -math.inf, -math.inf
    for k, i in enumerate(timed):  # a Python loop: one comparison per message, ~10^5 in a log
        boot, stamp = boots[i], stamps[i]
        if boot < top_boot - REBOOT_S and stamp >= top_stamp:
            if _goes_on(stamps, boots, timed[k + 1:], stamp + REPEAT_WINDOW_S, top_stamp - top_boot):
                continue  # a late repeat: the boot's own stream goes on
            segment += 1
            out[i:] = segment
            top_boot, top_stamp = boot, stamp
        elif boot > top_boot:
            top_boot, top_stamp = boot, stamp
    return out


def _goes_on(stamps: NDArray, boots: NDArray, later: NDArray[np.intp], until_s: float, offset_s: float) -> bool:
    """Whether a message of `later` (indices, in log order) received up to until_s is on the clock of the current
    boot: its receive time minus boot time within REBOOT_S of offset_s, that boot's (a reboot moves it by more)."""
    for j in later:
        if stamps[j] > until_s:
            return False
        if abs(stamps[j] - boots[j] - offset_s) <= REBOOT_S:
            return True
    return False


def receive_offset_s(stamp_s: ArrayLike, boot_s: ArrayLike) -> float:
    """The receive clock's time of boot time 0: (N,) receive times and (N,) boot times of the messages of one boot
    (seconds; NaN boot times skipped) -> the `RECEIVE_OFFSET_PERCENTILE` percentile of their difference, which lags
    the true one by about the link's smallest latency. NaN without a message with both."""
    diff = np.asarray(stamp_s, dtype=float) - np.asarray(boot_s, dtype=float)
    diff = diff[np.isfinite(diff)]
    return float(np.percentile(diff, RECEIVE_OFFSET_PERCENTILE)) if len(diff) else math.nan


def yaw_between_deg(t0_s: float, yaw0_deg: float, t1_s: float, yaw1_deg: float, t_s: float) -> float:
    """The yaw at `t_s` between two samples (t0 <= t <= t1; t0 == t1 gives yaw1), on the shorter arc, in
    [0, 360): `interpolate_yaw_deg` for one time, without numpy's per-call cost (one per live message)."""
    frac = (t_s - t0_s) / (t1_s - t0_s) if t1_s > t0_s else 1.0
    yaw = (yaw0_deg + frac * ((yaw1_deg - yaw0_deg + 180.0) % 360.0 - 180.0)) % 360.0
    return 0.0 if yaw >= 360.0 else yaw  # -1e-20 % 360 rounds to 360


def interpolate_yaw_deg(t_s: ArrayLike, yaw_deg: ArrayLike, query_s: ArrayLike) -> NDArray[np.float64]:
    """The yaw at (M,) query times from (N,) attitude samples (times in any order), degrees in [0, 360).

    Linear on the circle (350 -> 10 passes 0) between the samples that bracket a query; a query at a sample's time
    takes it. NaN where no sample is at or after the query, or none at or before it (nothing to interpolate).
    """
    t = np.asarray(t_s, dtype=float)
    yaw = np.asarray(yaw_deg, dtype=float)
    query = np.atleast_1d(np.asarray(query_s, dtype=float))
    if len(t) == 0:
        return np.full(len(query), np.nan)
    order = np.argsort(t, kind="stable")
    t, yaw = t[order], yaw[order]
    j = np.searchsorted(t, query, side="right") - 1  # the last sample at or before each query
    lo, hi = np.clip(j, 0, len(t) - 1), np.clip(j + 1, 0, len(t) - 1)
    t0, t1 = t[lo], t[hi]
    valid = (j >= 0) & ((j + 1 < len(t)) | (t0 == query))
    span = t1 - t0
    frac = np.divide(query - t0, span, out=np.zeros_like(query), where=span > 0)
    step = (yaw[hi] - yaw[lo] + 180.0) % 360.0 - 180.0
    out = (yaw[lo] + frac * step) % 360.0
    return np.where(valid, np.where(out >= 360.0, 0.0, out), np.nan)  # -1e-20 % 360 rounds to 360

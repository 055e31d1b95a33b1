"""A gimbal's logged angles at the times of a flight log's positions: interpolated between its samples, held no
further than a bounded time beyond them (`.tlog` and `.ulg` readers alike).

Pure: arrays in, arrays out (the readers decode the messages and topics).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["HOLD_INTERVALS", "MIN_HOLD_S", "SAME_S", "bounded_interp", "camera_angles", "describe_spans",
           "hold_limit_s", "unwrapped_deg"]

#: A gimbal value is carried at most this many of the gimbal's own median sample intervals beyond its samples ...
HOLD_INTERVALS = 3.0
#: Times this close are one instant (seconds).
SAME_S = 1e-6
#: ... and at least this long (a gimbal at 10-50 Hz has jitter and gaps of a few samples; seconds).
MIN_HOLD_S = 1.0


def hold_limit_s(t_s: ArrayLike) -> float:
    """How far (seconds) a gimbal's samples at times `t_s` (M,) are carried: `HOLD_INTERVALS` of their median
    interval, at least `MIN_HOLD_S` (`MIN_HOLD_S` for fewer than two distinct times)."""
    steps = np.diff(np.unique(np.asarray(t_s, dtype=float)))
    return max(MIN_HOLD_S, HOLD_INTERVALS * float(np.median(steps))) if len(steps) else MIN_HOLD_S


def unwrapped_deg(yaw_deg: ArrayLike) -> NDArray[np.float64]:
    """Angles (degrees) with their 360-degree jumps removed over the finite entries, for interpolation."""
    out = np.array(yaw_deg, dtype=np.float64)
    ok = np.isfinite(out)
    out[ok] = np.degrees(np.unwrap(np.radians(out[ok])))
    return out


def _neighbours(t: NDArray, t_src: NDArray, hold_s: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """(lo, hi, bracketed, near) per query: the last sample at or before it and the next one (clipped indices),
    whether those two bracket it no more than 2 * hold_s apart, and whether a sample is within hold_s of it."""
    j = np.searchsorted(t_src, t, side="right") - 1
    lo, hi = np.clip(j, 0, len(t_src) - 1), np.clip(j + 1, 0, len(t_src) - 1)
    after_first, before_last = j >= 0, j + 1 < len(t_src)
    to_lo = np.where(after_first, t - t_src[lo], np.inf)
    to_hi = np.where(before_last, t_src[hi] - t, np.inf)
    bracketed = after_first & before_last & (t_src[hi] - t_src[lo] <= 2.0 * hold_s)
    near = bracketed | (np.minimum(to_lo, to_hi) <= hold_s)
    return np.where(to_lo <= to_hi, lo, hi), bracketed, near, j


def bounded_interp(t: ArrayLike, t_src: ArrayLike, values: ArrayLike, hold_s: float) -> NDArray[np.float64]:
    """`values` (M,) at sorted times `t_src` (M,) at the query times `t` (N,), NaN where they say nothing.

    Linear between two samples no more than 2 * hold_s apart; elsewhere the nearer sample's value within hold_s of
    it (ends of the series, the edges of a long gap); NaN further away (a gimbal that stopped reporting, started
    late or paused: its last value is not carried on) and where no sample is finite. A query within `SAME_S` of a
    sample takes its value as it is (logs stamp in microseconds; UNIX seconds in float64 carry ~1e-7 s of noise).
    """
    query = np.atleast_1d(np.asarray(t, dtype=float))
    src, vals = np.asarray(t_src, dtype=float), np.asarray(values, dtype=float)
    ok = np.isfinite(vals)
    if not ok.any():
        return np.full(len(query), np.nan)
    src, vals = src[ok], vals[ok]
    nearest, bracketed, near, _ = _neighbours(query, src, hold_s)
    out = np.where(bracketed & (np.abs(query - src[nearest]) > SAME_S), np.interp(query, src, vals), vals[nearest])
    return np.where(near, out, np.nan)


def camera_angles(t: ArrayLike, t_gimbal: ArrayLike, pitch_gimbal: ArrayLike, roll_gimbal: ArrayLike,
                  yaw_gimbal: ArrayLike, earth_gimbal: ArrayLike, t_vehicle: ArrayLike, yaw_vehicle: ArrayLike,
                  hold_s: float | None = None) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The camera's (pitch, roll, heading) in degrees at times `t` (N,), and (N,) bool `stale`.

    t_gimbal, pitch/roll/yaw_gimbal, earth_gimbal: (M,) gimbal samples sorted by time (pitch positive up, as
    MAVLink; yaw in the earth frame where earth_gimbal, else relative to the vehicle). t_vehicle, yaw_vehicle: (K,)
    the vehicle's yaw (K may be 0). hold_s: how far a sample is carried (`hold_limit_s` of t_gimbal when None).

    Pitch and roll are linear between samples, heading on the short arc (`bounded_interp`). Each time takes the
    frame of the gimbal sample in effect (the latest at or before it, the first before any): the pilot may switch
    follow and lock mid-flight; the samples are brought into that frame with the vehicle's yaw at their own time
    before interpolating, so no interpolation mixes the two frames. `stale` marks times beyond hold_s of every
    sample: there pitch is NaN (no gimbal reading), roll 0 and heading the vehicle's yaw, the rule for a camera
    without a gimbal report. Heading is NaN where the vehicle's yaw it needs is unknown; not wrapped.
    """
    query = np.atleast_1d(np.asarray(t, dtype=float))
    t_g = np.asarray(t_gimbal, dtype=float)
    earth_g = np.asarray(earth_gimbal, dtype=bool)
    t_v, yaw_v = np.asarray(t_vehicle, dtype=float), unwrapped_deg(yaw_vehicle)
    hold = hold_limit_s(t_g) if hold_s is None else float(hold_s)

    def vehicle_yaw_at(times: NDArray) -> NDArray:
        ok = np.isfinite(yaw_v)
        return np.interp(times, t_v[ok], yaw_v[ok]) if ok.any() else np.full(len(times), np.nan)

    vehicle_at_gimbal = vehicle_yaw_at(t_g)
    yaw_g = np.asarray(yaw_gimbal, dtype=float)
    in_earth = unwrapped_deg(np.where(earth_g, yaw_g, yaw_g + vehicle_at_gimbal))
    relative = unwrapped_deg(np.where(earth_g, yaw_g - vehicle_at_gimbal, yaw_g))
    earth = earth_g[np.clip(np.searchsorted(t_g, query, side="right") - 1, 0, None)]
    vehicle_now = vehicle_yaw_at(query)
    heading = np.where(earth, bounded_interp(query, t_g, in_earth, hold),
                       vehicle_now + bounded_interp(query, t_g, relative, hold))
    pitch = bounded_interp(query, t_g, pitch_gimbal, hold)
    roll = bounded_interp(query, t_g, roll_gimbal, hold)
    stale = ~_neighbours(query, t_g, hold)[2] if len(t_g) else np.ones(len(query), dtype=bool)
    heading = np.where(stale, vehicle_now, heading)
    pitch = np.where(stale, np.nan, pitch)
    roll = np.where(stale | ~np.isfinite(roll), 0.0, roll)
    return pitch, roll, heading, stale


def describe_spans(t_s: ArrayLike, mask: ArrayLike, origin_s: float, *, most: int = 3) -> str:
    """The runs of consecutive True in `mask` (N,) over sorted times `t_s` (N,) as text, times in seconds after
    `origin_s`: "12 from 6.2 s to 14.8 s, 3 from ...", at most `most` runs named ("and N more")."""
    t, m = np.asarray(t_s, dtype=float), np.asarray(mask, dtype=bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], m.astype(np.int8), [0]])))
    runs = list(zip(edges[::2], edges[1::2], strict=True))
    parts = [f"{b - a} from {t[a] - origin_s:.1f} s to {t[b - 1] - origin_s:.1f} s" for a, b in runs[:most]]
    return ", ".join(parts) + (f" and {len(runs) - most} more runs" if len(runs) > most else "")

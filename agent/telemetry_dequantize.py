"""Quantised telemetry made continuous again: GPS written with 3 to 5 decimals, altitude in whole or half
metres.

Old DJI SRT files round latitude and longitude to 4 decimals: the position holds for seconds and then jumps
by 11 m (north) or 7 m (east at 48 N) in one frame, and every ground point of that frame jumps with it.
The value written is the true one rounded, so while the UAV moves the true coordinate crosses the middle
between two written levels at the moment the written value steps: the midpoint of a step, placed halfway
between the two samples, is a measurement of the true position that is far better than either level.
From each crossing the coordinate moves into the written level at the speed of the neighbouring steps and stops
there (`dequantize`): steady motion comes out linear through the crossings, a UAV that stops or hovers keeps its
written level once the ramp reaches it, and nothing is extrapolated past what the file says before the first and
after the last step (an extrapolated slope put hovering flights up to a whole quantum off). Never more than half a
quantum from what the file says; a UAV whose value never steps keeps its written level.

The quantum is detected from the file itself: a coordinate is treated as quantised when every sample of
the video is a multiple of 1e-3, 1e-4 or 1e-5 degrees (height: its steps multiples of 1 m or 0.5 m, whatever
offset was added) and it has at least two distinct values (height: three), but not when they all sit on a grid
ten times coarser (2 decimals: no position); otherwise the poses are left alone. Needs the samples after each
frame, so it is for files (`uavmm boost`, `uavmm track`, `uavmm tune`, the evaluations; `dequantize_records`
for a video's telemetry file, read whole before its first frame by `uavmm detect`, `uavmm agent --video` and
`uavmm anomaly --video`), not for a live feed. Arrays in, arrays out (records in, records out).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.stage_report import StageReport
from agent.telemetry_clock import TelemetryTrack
from shared.telemetry import Telemetry

__all__ = ["GPS_QUANTA_DEG", "HEIGHT_QUANTA_M", "dequantize", "dequantize_records", "dequantize_report",
           "dequantize_track", "detect_quantum"]

#: Quanta tried, coarsest first: 3, 4 and 5 decimals of a degree (6 decimals, 0.11 m, is left alone; 2 decimals,
#: 1.1 km, is no position: `detect_quantum` stands down).
GPS_QUANTA_DEG = (1e-3, 1e-4, 1e-5)
#: Altitude steps tried: whole and half metres.
HEIGHT_QUANTA_M = (1.0, 0.5)


def detect_quantum(values: NDArray, quanta: tuple[float, ...], *, offset: bool = False) -> float | None:
    """The coarsest quantum of which every value is a multiple (to 1e-6 of it), None when none is, when fewer than
    two distinct values were written, or when they all sit on a grid ten times coarser than the coarsest quantum
    (GPS with 2 decimals, 1.1 km: no position to make continuous). offset: the values may carry a constant added
    after the rounding (`--height-offset-m`): the differences between the distinct values are judged instead, and
    at least three distinct values are needed."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(v) < 2 or not np.isfinite(v).all():
        return None
    distinct = np.unique(v)
    if len(distinct) < (3 if offset else 2):
        return None
    judged = np.diff(distinct) if offset else v

    def on_grid(q: float) -> bool:
        k = judged / q
        return bool(np.all(np.abs(k - np.round(k)) < 1e-6))

    if on_grid(10.0 * quanta[0]):
        return None
    for q in quanta:
        if on_grid(q):
            return q
    return None


#: An interval between two steps whose neighbour moved this many times faster is a hover or a stop (`dequantize`).
SLOW_RATIO = 3.0


def dequantize(t: NDArray, x: NDArray, q: float) -> NDArray:
    """The continuous coordinate behind samples x (rounded to multiples of q) at their times t (increasing).

    Each step of the written value is a crossing of the middle between two levels, placed halfway between the two
    samples that step. From each crossing the coordinate moves into the new level at the speed of its interval
    (q over the time to the next crossing; where a neighbouring interval moved more than SLOW_RATIO times faster,
    a hover or a stop, half that neighbour's speed) and stops at the written level: a sample takes the ramp of the
    nearer crossing (in distance moved), so steady motion comes out linear through the crossings, a hover or a stop
    holds the written level once the ramp gets there, and beyond the first and last crossing nothing is
    extrapolated past what the file says. One crossing alone gives no speed: it is taken to last one sample
    interval. Never more than q/2 from x; x itself where it never steps.
    """
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    steps = np.flatnonzero(x[1:] != x[:-1]) + 1
    if not len(steps):
        return x.copy()
    tau = (t[steps - 1] + t[steps]) / 2.0
    mid = (x[steps - 1] + x[steps]) / 2.0
    n = len(tau)
    # speed of each interval between crossings: the distance between its crossings (at least q: a return to the
    # crossing it came from is taken as a pass through the level) over its time
    gaps = np.diff(tau)
    own = np.maximum(np.abs(np.diff(mid)), q) / np.maximum(gaps, 1e-9)
    # a crossing's speed into the interval after it (`into_next`) and out of the interval before it (`from_prev`):
    # the interval's own, or, where a neighbouring interval moved more than SLOW_RATIO times faster (a hover or a
    # stop in this one), half of that neighbour's; with one crossing, one sample interval
    if n >= 2:
        faster_before = np.concatenate([[0.0], own[:-1]])  # the interval before each interval
        faster_after = np.concatenate([own[1:], [0.0]])
        neighbour = np.maximum(faster_before, faster_after)
        interval_speed = np.where(neighbour > SLOW_RATIO * own, neighbour / 2.0, own)
        into_next = np.concatenate([interval_speed, [interval_speed[-1]]])  # after the last crossing: its last
        from_prev = np.concatenate([[interval_speed[0]], interval_speed])   # before the first: its first
    else:
        one = q / max(float(t[steps[0]] - t[steps[0] - 1]), 1e-9)
        into_next = from_prev = np.array([one])
    # per sample: the crossing before it (a) and after it (b), -1 / n where there is none
    after = np.searchsorted(tau, t, side="right")
    a, b = after - 1, after
    out = x.copy()
    half = q / 2.0
    has_a, has_b = a >= 0, b < n
    ia, ib = np.clip(a, 0, n - 1), np.clip(b, 0, n - 1)
    # distance moved from each crossing into the written level, whose edge is half a quantum from it (a step over
    # several levels: the crossing is beyond the edge, and the ramp starts at the edge)
    moved_a = np.where(has_a, into_next[ia] * (t - tau[ia]), np.inf)
    moved_b = np.where(has_b, from_prev[ib] * (tau[ib] - t), np.inf)
    from_a = x + np.sign(mid[ia] - x) * np.maximum(np.minimum(np.abs(mid[ia] - x), half) - moved_a, 0.0)
    from_b = x + np.sign(mid[ib] - x) * np.maximum(np.minimum(np.abs(mid[ib] - x), half) - moved_b, 0.0)
    use_a = has_a & (~has_b | (moved_a <= moved_b))
    use_b = has_b & ~use_a
    out[use_a] = from_a[use_a]
    out[use_b] = from_b[use_b]
    return np.clip(out, x - half, x + half)


def dequantize_track(track: TelemetryTrack) -> tuple[TelemetryTrack, dict[str, float]]:
    """One video's telemetry samples (agent.telemetry_clock) with quantised latitude, longitude and height
    made continuous.

    Returns the track (the same object when nothing is quantised) and the quanta found per coordinate
    ({} when none): the stage acts only where every sample of a coordinate sits on one quantum's grid.
    """
    if len(track) < 2:
        return track, {}
    quanta: dict[str, float] = {}
    out = track
    for name in ("lat", "lon", "height_m"):
        values = track.column(name)
        q = (detect_quantum(values, HEIGHT_QUANTA_M, offset=True) if name == "height_m"
             else detect_quantum(values, GPS_QUANTA_DEG))
        if q is None:
            continue
        quanta[name] = q
        fixed = dequantize(track.t, values, q)
        if name == "height_m":
            fixed = np.maximum(fixed, 0.1)
        out = out.replace_column(name, fixed)
    return out, quanta


def dequantize_records(records: list[Telemetry]) -> tuple[list[Telemetry], dict[str, float]]:
    """A telemetry file's records (a video's, sorted by time) with quantised latitude, longitude and height made
    continuous, as `dequantize_track` does for a dataset's video.

    The quanta are judged on the records with a GPS fix (`Telemetry.has_fix`), one a time (the first at a repeated
    time), height only when every one of them has one; longitude is unwrapped across the antimeridian. Each such
    record gets the continuous value at its time, never more than half a quantum from what it says; records without
    a fix keep theirs. Returns the records (the same list when nothing is quantised) and the quanta found ({} when
    none).
    """
    fixed = [i for i, r in enumerate(records) if r.has_fix]
    if len(fixed) < 2:
        return records, {}
    t_all = np.array([records[i].t for i in fixed], dtype=np.float64)
    if np.any(np.diff(t_all) < 0):
        raise ValueError("dequantize_records needs the records in time order")
    first = np.concatenate([[True], np.diff(t_all) > 0])  # one sample a time: the first
    columns: dict[str, NDArray] = {
        "lat": np.array([records[i].lat for i in fixed], dtype=np.float64),
        "lon": np.unwrap(np.array([records[i].lon for i in fixed], dtype=np.float64), period=360.0),
    }
    heights = [records[i].height_m for i in fixed]
    if all(h is not None for h in heights):
        columns["height_m"] = np.array(heights, dtype=np.float64)
    quanta: dict[str, float] = {}
    fixed_values: dict[str, NDArray] = {}
    for name, values in columns.items():
        q = (detect_quantum(values[first], HEIGHT_QUANTA_M, offset=True) if name == "height_m"  # --height-offset-m
             else detect_quantum(values[first], GPS_QUANTA_DEG))
        if q is None:
            continue
        quanta[name] = q
        smooth = dequantize(t_all[first], values[first], q)
        fixed_values[name] = np.clip(np.interp(t_all, t_all[first], smooth), values - q / 2.0, values + q / 2.0)
    if not quanta:
        return records, {}
    if "lon" in fixed_values:
        fixed_values["lon"] = (fixed_values["lon"] + 180.0) % 360.0 - 180.0
    if "lat" in fixed_values:  # half a step past a pole is no latitude
        fixed_values["lat"] = np.clip(fixed_values["lat"], -90.0, 90.0)
    out = list(records)
    for k, i in enumerate(fixed):
        changes: dict[str, Any] = {name: float(v[k]) for name, v in fixed_values.items()}
        out[i] = replace(records[i], **changes)
    return out, quanta


def dequantize_report(quanta: dict[str, float]) -> StageReport:
    """What the dequantisation found in one video (`dequantize_track`'s or `dequantize_records`' quanta) as a stage
    report."""
    return StageReport("dequantize", bool(quanta),
                       ", ".join(f"{k} {v:g}" for k, v in quanta.items()) or "no quantised coordinate")

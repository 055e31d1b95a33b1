"""Quantised telemetry made continuous again: GPS written with 3 to 5 decimals, altitude in whole or half
metres.

Old DJI SRT files round latitude and longitude to 4 decimals: the position holds for seconds and then jumps
by 11 m (north) or 7 m (east at 48 N) in one frame, and every ground point of that frame jumps with it.
The value written is the true one rounded, so while the UAV moves the true coordinate crosses the middle
between two written levels at the moment the written value steps: the midpoint of a step, placed halfway
between the two samples, is a measurement of the true position that is far better than either level.
Where the coordinate moves steadily (successive steps in one direction, a few seconds apart), it is taken linear
through those crossings; everywhere else the written staircase is averaged over a few seconds (`dequantize`): a
step followed by a hold (a survey line changed, a stop) becomes a short ramp and then the level written, a hover
whose GPS noise flips the value about a level's edge comes out near that edge, a hover inside a level keeps it, and
nothing is extrapolated at the ends. Never more than half a quantum from what the file says; a coordinate that never
steps keeps its written level.

The quantum is detected from the file itself: a coordinate is treated as quantised when every sample of
the video is a multiple of 1e-3, 1e-4 or 1e-5 degrees (height: its steps multiples of 1 m or 0.5 m, whatever
offset was added) and it has at least two distinct values (height: three), but not when they all sit on a grid
ten times coarser (2 decimals: no position); otherwise the poses are left alone. Needs the samples after each
frame, so it is for files (`uavmm boost`, `uavmm track`, `uavmm tune`, the evaluations; `dequantize_records`
for a video's telemetry file, read whole before its first frame by `uavmm detect`, `uavmm agent --video` and
`uavmm anomaly --video`), not for a live feed. Arrays in, arrays out (records in, records out).

A coordinate held between regular updates (a 1 Hz GPS repeated in a record per frame) is taken linear between its
updates in the same stage, whether or not it is quantised (agent.telemetry_holds, tried first: a quantised
coordinate that steps one quantum at a time is no hold and comes here); the stage reports both
(`describe_quanta`: ``lat 0.0001`` or ``lat held 1 s``), and one switch (`dequantize_telemetry`) turns both off.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.stage_report import StageReport
from agent.telemetry_clock import TelemetryTrack
from agent.telemetry_holds import (
    changes,
    detect_hold,
    held_with,
    interpolate_holds,
    phase_locked_period,
    update_times,
)
from shared.telemetry import Telemetry

__all__ = ["DEQUANTIZE_OFF", "GPS_QUANTA_DEG", "HEIGHT_QUANTA_M", "dequantize", "dequantize_records",
           "dequantize_report", "dequantize_track", "describe_quanta", "detect_quantum"]

#: Quanta tried, coarsest first: 3, 4 and 5 decimals of a degree (6 decimals, 0.11 m, is left alone; 2 decimals,
#: 1.1 km, is no position: `detect_quantum` stands down).
GPS_QUANTA_DEG = (1e-3, 1e-4, 1e-5)
#: Altitude steps tried: whole and half metres.
HEIGHT_QUANTA_M = (1.0, 0.5)
#: The stage report's reason when the switch turned it off (`dequantize_report`).
DEQUANTIZE_OFF = "off (dequantize_telemetry false)"


def detect_quantum(values: NDArray, quanta: tuple[float, ...], *, offset: bool = False) -> float | None:
    """The coarsest quantum of which every value is a multiple (to 1e-6 of it), None when none is, when fewer than
    two distinct values were written, or when they all sit on a grid ten times coarser than the coarsest quantum
    (GPS with 2 decimals, 1.1 km: no position to make continuous), or when two distinct values alone are not one
    quantum apart. offset: the values may carry a constant added
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
            # two values alone sit on a ten times coarser grid by chance once in a hundred: only one step apart
            # do they say that step (a 5-decimal log that jumped 3e-4 is no 4-decimal one)
            if len(distinct) == 2 and abs(abs(float(distinct[1] - distinct[0])) / q - 1.0) > 1e-6:
                return None
            return q
    return None


#: Width of the moving average over the written staircase, seconds (`dequantize`).
AVERAGE_S = 4.0
#: An interval between two steps is steady motion when it passes through its level within this many seconds and a
#: neighbouring interval does so in the same direction, within STEADY_RATIO of its time (`dequantize`).
STEADY_MAX_S = 8.0
STEADY_RATIO = 3.0


def _moving_average(t: NDArray, x: NDArray, width_s: float) -> NDArray:
    """The written staircase (each value held from halfway after the previous sample to halfway before the next)
    averaged over a window of width_s seconds centred on each sample; the window shrinks symmetrically near the ends
    of the data, so the first and last samples keep their values."""
    n = len(t)
    edges = np.concatenate([[t[0]], (t[1:] + t[:-1]) / 2.0, [t[-1]]])
    area = np.concatenate([[0.0], np.cumsum(x * np.diff(edges))])  # the staircase's integral up to each edge

    def integral(s: NDArray) -> NDArray:
        i = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, n - 1)
        return area[i] + x[i] * (s - edges[i])

    half = np.minimum(width_s / 2.0, np.minimum(t - t[0], t[-1] - t))
    inside = half > 1e-9
    out = x.copy()
    out[inside] = (integral(t[inside] + half[inside]) - integral(t[inside] - half[inside])) / (2.0 * half[inside])
    return out


def dequantize(t: NDArray, x: NDArray, q: float) -> NDArray:
    """The continuous coordinate behind samples x (rounded to multiples of q) at their times t (increasing).

    Each step of the written value is a crossing of the middle between two levels, placed halfway between the two
    samples that step. Where the coordinate moves steadily (an interval between two crossings that passes through
    its level within STEADY_MAX_S, beside another doing so in the same direction within STEADY_RATIO of its time),
    it is linear through the crossings, and goes on at that speed into the levels before and after such a run until
    it reaches the level written (where the UAV may have stopped). Everywhere else, the written staircase averaged
    over AVERAGE_S seconds: a
    step then a hold (a survey line changed, a stop) becomes a short ramp and the level written; a hover whose GPS
    noise flips it about a level's edge comes out near that edge; a hover inside a level keeps it; nothing is
    extrapolated at the ends. (Linear through every crossing, as before 30 Nov 2026, read a step followed by a hold
    as a slow drift across the level, and a hover's noise flips as passes through it: worse than written.) Never
    more than q/2 from x; x itself where it never steps.
    """
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    steps = changes(x)
    if not len(steps):
        return x.copy()
    out = _moving_average(t, x, AVERAGE_S)
    tau = update_times(t, steps)
    mid = (x[steps - 1] + x[steps]) / 2.0
    if len(tau) >= 3:
        moved, took = np.diff(mid), np.diff(tau)
        through = (np.abs(moved) >= q * (1.0 - 1e-6)) & (took > 0.0) & (took <= STEADY_MAX_S)
        # neighbouring intervals that agree: both through-passes, one direction, times within STEADY_RATIO
        agree = (through[:-1] & through[1:] & (np.sign(moved[:-1]) == np.sign(moved[1:]))
                 & (took[:-1] <= STEADY_RATIO * took[1:]) & (took[1:] <= STEADY_RATIO * took[:-1]))
        steady = np.zeros(len(took), dtype=bool)
        steady[:-1] |= agree
        steady[1:] |= agree
        i = np.searchsorted(tau, t, side="right") - 1  # the interval each sample lies in (-1: before the first)
        within = (i >= 0) & (i < len(took))
        linear = within.copy()
        linear[within] = steady[i[within]]
        j = i[linear]
        out[linear] = mid[j] + (t[linear] - tau[j]) * moved[j] / took[j]
        # into the levels either side of a steady run: on at the run's speed from its first (last) crossing until
        # the level written is reached, not past it (the UAV may have stopped there)
        speed = np.abs(moved) / np.maximum(took, 1e-9)

        def ramp(level: int, crossing: int, run: int) -> None:
            """The samples of interval `level` (-1: before the first crossing) from `crossing` at run's speed."""
            idx = np.flatnonzero(i == level)
            edge = np.abs(x[idx] - mid[crossing])
            reach = speed[run] * np.abs(t[idx] - tau[crossing])
            on = reach < edge
            out[idx[on]] = mid[crossing] + np.sign(x[idx[on]] - mid[crossing]) * reach[on]

        for k in np.flatnonzero(steady & ~np.concatenate([[False], steady[:-1]])).tolist():  # a run's first
            ramp(k - 1, k, k)
        for k in np.flatnonzero(steady & ~np.concatenate([steady[1:], [False]])).tolist():  # a run's last
            ramp(k + 1, k + 1, k)
    return np.clip(out, x - q / 2.0, x + q / 2.0)


def _quantum_of(name: str, values: NDArray) -> float | None:
    """`detect_quantum` of one coordinate: lat / lon on GPS_QUANTA_DEG, height on HEIGHT_QUANTA_M by its steps (an
    offset such as `--height-offset-m` may have been added after the rounding)."""
    if name == "height_m":
        return detect_quantum(values, HEIGHT_QUANTA_M, offset=True)
    return detect_quantum(values, GPS_QUANTA_DEG)


def _continuous(name: str, t: NDArray, values: NDArray, quanta: dict[str, float],
                holds: dict[str, float]) -> NDArray | None:
    """One coordinate's values made continuous (None: left as written), recording what was found: the period it is
    held for between updates (agent.telemetry_holds: also a quantised one, e.g. 5-decimal GPS held for a second,
    whose steps are many quanta), else its quantum (`dequantize`)."""
    period = detect_hold(t, values)
    if period is not None:
        holds[name] = period
        return interpolate_holds(t, values, period)
    q = _quantum_of(name, values)
    if q is None:
        return None
    quanta[name] = q
    out = dequantize(t, values, q)
    locked = phase_locked_period(t, values)
    if locked is None:
        return out
    holds[name] = locked
    return _earlier_by_half_period(t, out, locked)


def _earlier_by_half_period(t: NDArray, values: NDArray, period: float) -> NDArray:
    """A quantised coordinate's continuous values when it was also held (`phase_locked_period`): each step was
    seen at the update after its crossing, half a period later on average than the crossing placed halfway between
    two records (`dequantize`), so the whole curve goes that much earlier (the last values held)."""
    lag = max(period - float(np.median(np.diff(t))), 0.0) / 2.0
    return np.interp(t + lag, t, values)


def _continuous_all(t: NDArray, columns: dict[str, NDArray], quanta: dict[str, float],
                    holds: dict[str, float]) -> dict[str, NDArray]:
    """`_continuous` for each coordinate (lat, lon, height_m as present), and then latitude and longitude as one
    fix: a coordinate left as written that changes where the other's held updates are (`held_with`: its own steps
    too few or too small to show the hold) is held with them. The values of those made continuous."""
    out: dict[str, NDArray] = {}
    for name, values in columns.items():
        fixed = _continuous(name, t, values, quanta, holds)
        if fixed is not None:
            out[name] = fixed
    for name, other in (("lat", "lon"), ("lon", "lat")):
        if name in quanta and name not in holds and other in holds and other in quanta:
            # quantised, its steps too few to judge their phase alone: at the partner's
            locked = phase_locked_period(t, columns[name], partner=columns[other])
            if locked is not None and locked == holds[other]:
                holds[name] = locked
                out[name] = _earlier_by_half_period(t, out[name], locked)
        if name in columns and name not in out and other in holds:
            updates = held_with(columns[name], changes(columns[other]))
            if updates is not None:
                holds[name] = holds[other]
                out[name] = interpolate_holds(t, columns[name], holds[other], updates=updates)
    order = {name: i for i, name in enumerate(columns)}
    found = sorted(holds.items(), key=lambda item: order.get(item[0], len(order)))
    holds.clear()
    holds.update(found)
    return out


def dequantize_track(track: TelemetryTrack) -> tuple[TelemetryTrack, dict[str, float], dict[str, float]]:
    """One video's telemetry samples (agent.telemetry_clock) with quantised latitude, longitude and height
    made continuous, and those held between regular updates interpolated between them (agent.telemetry_holds).

    Returns the track (the same object when nothing changed), the quanta found per coordinate and the update
    periods of the held ones (seconds; {} when none): the stage acts only where every sample of a coordinate sits
    on one quantum's grid (height: its steps, `detect_quantum`) or the file shows regular updates held between.
    """
    quanta: dict[str, float] = {}
    holds: dict[str, float] = {}
    if len(track) < 2:
        return track, quanta, holds
    out = track
    columns = {name: track.column(name) for name in ("lat", "lon", "height_m")}
    for name, fixed in _continuous_all(track.t, columns, quanta, holds).items():
        out = out.replace_column(name, np.maximum(fixed, 0.1) if name == "height_m" else fixed)
    return out, quanta, holds


def dequantize_records(records: list[Telemetry]) -> tuple[list[Telemetry], dict[str, float], dict[str, float]]:
    """A telemetry file's records (a video's, sorted by time) with quantised latitude, longitude and height made
    continuous, and those held between regular updates interpolated, as `dequantize_track` does for a dataset's
    video.

    Judged on the records with a GPS fix (`Telemetry.has_fix`), one a time (the first at a repeated time), height
    only when every one of them has one; longitude is unwrapped across the antimeridian. Each such record gets the
    continuous value at its time (a quantised one never more than half a quantum from what it says); records
    without a fix keep theirs. Returns the records (the same list when nothing changed), the quanta found and the
    held coordinates' update periods ({} when none).
    """
    quanta: dict[str, float] = {}
    holds: dict[str, float] = {}
    fixed = [i for i, r in enumerate(records) if r.has_fix]
    if len(fixed) < 2:
        return records, quanta, holds
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
    fixed_values: dict[str, NDArray] = {}
    judged = {name: values[first] for name, values in columns.items()}
    for name, smooth in _continuous_all(t_all[first], judged, quanta, holds).items():
        at_all = np.interp(t_all, t_all[first], smooth)
        q = quanta.get(name)
        values = columns[name]
        # a quantised value stays within half a quantum of what it says, unless also held (its steps seen late)
        fixed_values[name] = at_all if q is None or name in holds else np.clip(at_all, values - q / 2.0,
                                                                                values + q / 2.0)
    if not fixed_values:
        return records, quanta, holds
    if "lon" in fixed_values:
        fixed_values["lon"] = (fixed_values["lon"] + 180.0) % 360.0 - 180.0
    if "lat" in fixed_values:  # half a step past a pole is no latitude
        fixed_values["lat"] = np.clip(fixed_values["lat"], -90.0, 90.0)
    out = list(records)
    for k, i in enumerate(fixed):
        updated: dict[str, Any] = {name: float(v[k]) for name, v in fixed_values.items()}
        out[i] = replace(records[i], **updated)
    return out, quanta, holds


def dequantize_report(quanta: dict[str, float], off: str = "", holds: dict[str, float] | None = None) -> StageReport:
    """What the stage found in one video (`dequantize_track`'s or `dequantize_records`' quanta and holds) as a stage
    report; off: why it did not run (e.g. DEQUANTIZE_OFF), "" when it ran."""
    if off:
        return StageReport("dequantize", False, off)
    return StageReport("dequantize", bool(quanta or holds),
                       describe_quanta(quanta, holds) or "no quantised or held coordinate")


def describe_quanta(quanta: dict[str, float], holds: dict[str, float] | None = None) -> str:
    """What was made continuous, as the stage reports, logs and `uavmm anomaly` print it: ``lat 0.0001, lon 0.0001``
    for quanta, ``lat held 1 s`` for a coordinate held between updates once a second."""
    return ", ".join([f"{k} {v:g}" for k, v in quanta.items()]
                     + [f"{k} held {v:.2g} s" for k, v in (holds or {}).items()])

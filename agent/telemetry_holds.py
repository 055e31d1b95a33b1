"""Coordinates held between their updates made continuous: GPS that updates once a second in records written for
every frame.

A flight log or subtitle file writes a record for every frame (or at 10 Hz), but its GPS receiver, barometer or
the drone's own logger updates a coordinate less often and repeats the last value in between (sample and hold,
field by field: the attitude changes every record, the position once a second). At 6 m/s and 1 Hz the written
position lags the UAV by up to 6 m and jumps 6 m every second, and every ground point of those frames with it.
When a whole record repeats, agent.telemetry_clock already takes it as one sample; this stage handles one
coordinate that holds while the rest of the record moves on.

Each new value is a sample taken when it first appears (halfway between the record before and the first record
holding it: the update came in between), so between two updates the coordinate is taken linear from one to the
next (`interpolate_holds`). Only what the file shows is applied (`detect_hold`): at least MIN_UPDATES updates, at
least MIN_SAMPLES_PER_UPDATE records per update (median), and at least MIN_UPDATES held steps: steps of
MIN_HELD_STEP_UNITS or more units of the grid the values sit on (`grid_unit`: 1e-6 for 6 decimals, whole feet, a KLV
altitude's 0.30 m, a float32's spacing; none at full precision). A coordinate rounded to a grid, with records
between its steps, moves one unit at a time (a slow coordinate in 6 decimals, a barometer flipping between two
levels, a hover's fix noise); rounding steps where the coordinate crosses the middle between two values, half a
unit earlier than a held value's, so reading it as a hold would move it half a unit the wrong way
(agent.telemetry_dequantize makes 3 to 5 decimals continuous when they step one quantum at a time). The held steps
come at a regular period: the time since the update before each (a hover's small steps between them are updates
too), their inter-quartile range within MAX_SPREAD of their median, the period. So a long hover whose one-unit steps
outnumber a leg's held steps, and whose fixes round to the same value for seconds, does not hide the leg. At exactly
constant speed every step of a hold is the same: the grid is that step, the file cannot tell it from rounding, and
the stage stands down.

A value held longer than LONG_HOLD periods (the UAV stopped, a dropout) is reached by a ramp over the time its
step takes at the speed of the faster regular interval beside it, at least one period and at most the whole interval: a
missed update while moving (a step two periods' worth) is linear across, a stop keeps its value until one period
before the next update. Never further from what the file says than the step the file itself makes next. The last
values after the last update go on at the last updates' speed for up to a period when those were steady (the update
the file did not reach), else stay as written.

A quantised coordinate held between updates (4 decimals on every frame, a fix once a second) steps one unit at a
time, which `detect_hold` takes for rounding; its steps then all come at one phase of the update period
(`phase_locked_period`), and agent.telemetry_dequantize moves its continuous curve half a period earlier.

Used by agent.telemetry_dequantize (before its quantum: a 5-decimal GPS held for a second steps by several quanta)
on files, not on a live feed: it needs the update after each record. Arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["LONG_HOLD", "MAX_SPREAD", "MIN_HELD_STEP_UNITS", "MIN_LOCKED_STEPS", "MIN_OTHER_MULTIPLE",
           "MIN_PARTNER_CHANGES", "MIN_PARTNER_SHARE", "MIN_PHASE_LOCK", "MIN_RECORDS_PER_PERIOD",
           "MIN_SAMPLES_PER_UPDATE", "MIN_UPDATES", "PHASE_PERIODS_S", "RECEIVER_PERIODS_S", "RECEIVER_PERIOD_MATCH",
           "TAIL_SPREAD", "TAIL_UPDATES", "changes", "detect_hold", "grid_unit", "held_with", "interpolate_holds",
           "phase_locked_period", "update_times", "varied"]

#: Updates (changes of the value) needed to judge a period.
MIN_UPDATES = 5
#: Records per update (median) needed to say the value is held between updates.
MIN_SAMPLES_PER_UPDATE = 2
#: The update intervals' inter-quartile range may be at most this fraction of their median (25 fps records of a
#: 10 Hz GPS alternate 2 and 3 frames: 0.4 to 0.5; updates at random times: about 1.6).
MAX_SPREAD = 0.6
#: An interval between updates longer than this many periods is a hold (the UAV stopped, a dropout), not an update
#: period (`interpolate_holds`).
LONG_HOLD = 1.5
#: A held step moves at least this many units of the grid the values sit on (`grid_unit`); a coordinate rounded to
#: that grid, with records between its steps, moves one unit at a time (two where noise flips it).
MIN_HELD_STEP_UNITS = 3
#: Held steps all within one written unit of each other may be a coarser grid written with more decimals, rounding
#: (`detect_hold`): a hold then needs the update period of a receiver, one of these (s), within this fraction.
RECEIVER_PERIODS_S = (0.1, 0.2, 0.25, 0.5, 1.0, 2.0)
RECEIVER_PERIOD_MATCH = 0.03
#: A coordinate changing only where its partner's held updates are needs this many changes to be held with it
#: (`held_with`).
MIN_PARTNER_CHANGES = 3
#: ... at least this share of them where the partner's value changes (one change in 30 frames falls on a
#: partner's change by chance).
MIN_PARTNER_SHARE = 0.8
#: Update periods (s) tried for steps at one phase (`phase_locked_period`), longest first.
PHASE_PERIODS_S = (1.0, 0.5, 0.2)
#: Steps needed to judge their phase, ...
MIN_LOCKED_STEPS = 8
#: ... the length of their mean phase vector (1: all at one phase) ...
MIN_PHASE_LOCK = 0.9
#: ... and the records a period needed; the intervals between the steps must be more than one whole number of
#: periods, the second commonest at least this share of them (`varied`).
MIN_RECORDS_PER_PERIOD = 3
MIN_OTHER_MULTIPLE = 0.05
#: The values after the last update go on at the last speed when this many intervals before it were steady ...
TAIL_UPDATES = 3
#: ... their speeds of one sign and within this fraction of the largest (a hover's noise, a turn: as written).
TAIL_SPREAD = 0.3


def detect_hold(t: NDArray, x: NDArray) -> float | None:
    """The update period (seconds) of a coordinate x sampled at times t (increasing, one sample a time) that holds
    its value between regular updates; None when the file does not show that (see the module docstring)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if len(t) != len(x) or len(t) < 2 or not (np.isfinite(t).all() and np.isfinite(x).all()):
        return None
    updates = changes(x)
    if len(updates) < MIN_UPDATES:
        return None
    if float(np.median(np.diff(updates))) < MIN_SAMPLES_PER_UPDATE:
        return None
    steps = np.abs(x[updates] - x[updates - 1])
    # the float's own error in a difference of two values read from text (far below a 7-decimal longitude's grid)
    tolerance = 1e-11 * (1.0 + float(np.max(np.abs(x))))
    unit = grid_unit(steps, tolerance)
    # only steps of several units are a hold's: rounding with records between its steps moves one unit at a time
    held = steps > (MIN_HELD_STEP_UNITS - 0.5) * unit + tolerance
    if int(held.sum()) < MIN_UPDATES:
        return None
    # steps all of one size give or take a written unit: a coarser grid written with more decimals (KLV's 0.30 m
    # altitude to 0.1 m, whole feet in centimetres, a float32 latitude to 6 decimals) rounding one of its units at a
    # time, or a hold at a steady speed (a filtered or RTK position). Only a receiver's update period tells them
    # apart: rounding crosses its grid every grid / speed seconds, any period
    k = steps[held] / unit if unit > 0.0 else None
    one_size = k is not None and float(k.max() - k.min()) <= 1.0 + 1e-6
    # the time since the update before, at each held step (a hover's one-unit flips between them are updates too;
    # updates lost where a hover's fix rounds to the value before are not held steps' intervals)
    intervals = np.diff(t[updates])[held[1:]]
    if len(intervals) < MIN_UPDATES - 1:
        return None
    period = float(np.median(intervals))
    if not period > 0.0:
        return None
    q25, q75 = np.percentile(intervals, [25.0, 75.0])
    if q75 - q25 > MAX_SPREAD * period:
        return None
    # the median is one of the intervals, each a whole number of records: their mean about it is finer
    regular = intervals[np.abs(intervals - period) <= 0.5 * period]
    found = float(np.mean(regular))
    if one_size and not any(abs(found - p) <= RECEIVER_PERIOD_MATCH * p for p in RECEIVER_PERIODS_S):
        return None
    return found


def phase_locked_period(t: NDArray, x: NDArray, partner: NDArray | None = None) -> float | None:
    """The update period (seconds) of a coordinate whose steps all come at one phase of it, None when they do not:
    a value held between updates that steps one unit of its grid at a time (GPS in 4 decimals, 11 m, from a fix
    updated once a second and written on every frame), whose steps `detect_hold` cannot see as a hold. The steps
    (each placed halfway between the record before and the first with the new value) must number at least
    MIN_LOCKED_STEPS and sit within one phase of a period in PHASE_PERIODS_S (the longest that fits: their mean
    phase vector at least MIN_PHASE_LOCK long; steps at random times give about 1 / sqrt(steps)), with at least
    MIN_RECORDS_PER_PERIOD records a period (with fewer, every step falls on one of a few phases by itself).
    partner: the other coordinate of the same fix (latitude for longitude), locked itself: then MIN_PARTNER_CHANGES
    steps of x suffice, locked at that period and, with the partner's, at one phase."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if len(t) != len(x) or len(t) < 2 or not (np.isfinite(t).all() and np.isfinite(x).all()):
        return None
    record = float(np.median(np.diff(t)))

    def locked(u: NDArray, period: float) -> bool:
        return bool(abs(np.mean(np.exp(2j * np.pi * u / period))) >= MIN_PHASE_LOCK)

    own = update_times(t, changes(x))
    theirs = None if partner is None else update_times(t, changes(partner))
    if len(own) < (MIN_LOCKED_STEPS if theirs is None else MIN_PARTNER_CHANGES):
        return None
    for period in PHASE_PERIODS_S:
        if period < MIN_RECORDS_PER_PERIOD * record or not locked(own, period):
            continue
        if theirs is None and varied(own, period):
            return period
        if theirs is not None and len(theirs) >= MIN_LOCKED_STEPS and locked(theirs, period) \
                and varied(theirs, period) and locked(np.concatenate([own, theirs]), period):
            return period
    return None


def varied(u: NDArray, period: float) -> bool:
    """Whether the intervals between steps at times u are whole numbers of periods of more than one kind (the
    second commonest at least MIN_OTHER_MULTIPLE of them, and twice): a hold of a flight whose speed varies. At
    one constant speed whose crossings come every whole number of periods (5.566 m/s north in 4 decimals: every
    2.000 s) steps written as they cross are locked as well, and cannot be told from a hold."""
    k = np.round(np.diff(u) / period).astype(np.int64)
    if len(k) < 2:
        return False
    counts = np.sort(np.unique(k, return_counts=True)[1])[::-1]
    return len(counts) > 1 and counts[1] >= max(2.0, MIN_OTHER_MULTIPLE * len(k))


def grid_unit(steps: NDArray, tolerance: float) -> float:
    """The largest value that every step is a whole multiple of, within `tolerance` (the grid written values sit on:
    1e-6 for 6 decimals, 0.3048 for whole feet, a float32's spacing); for values at full precision, which sit on no
    grid, 0.0 or a few tolerances (where Euclid's remainders stop)."""
    unit = 0.0
    for step in np.abs(np.asarray(steps, dtype=np.float64)).tolist():
        a, b = max(unit, step), min(unit, step)
        while b > tolerance:  # Euclid's algorithm, the remainder taken the short way (either side of a multiple)
            r = a % b
            a, b = b, min(r, b - r)
        unit = a
        if unit <= tolerance:
            return 0.0
    return unit


def changes(x: NDArray) -> NDArray:
    """Indices of the samples whose value differs from the one before."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    return np.flatnonzero(x[1:] != x[:-1]) + 1


def update_times(t: NDArray, idx: NDArray) -> NDArray:
    """When the values new at samples `idx` (>= 1) arrived: halfway between the sample before and the first with
    them (the update came in between)."""
    return (t[idx - 1] + t[idx]) / 2.0


def held_with(x: NDArray, updates: NDArray) -> NDArray | None:
    """The samples where x took new values when it changes at `updates` (the samples where a partner coordinate
    held between updates takes its new value) at least MIN_PARTNER_SHARE of the times, and at least
    MIN_PARTNER_CHANGES times: the same fix writes both (a latitude that moves a few units a second beside a
    longitude held for a second), so x is held with the partner's updates though its own steps are too few or too
    small to show it. Its own other changes are updates the partner's value did not show (rounded to the value
    before): the union of both. None when x is not held with the partner."""
    own, updates = changes(x), np.asarray(updates, dtype=np.intp).reshape(-1)
    if len(own) < MIN_PARTNER_CHANGES or float(np.mean(np.isin(own, updates))) < MIN_PARTNER_SHARE:
        return None
    return np.union1d(own, updates)


def interpolate_holds(t: NDArray, x: NDArray, period: float, updates: NDArray | None = None) -> NDArray:
    """x with each held value taken linear from the update that wrote it to the next one (`detect_hold`'s period;
    a hold longer than LONG_HOLD periods ramps over the time its step takes at the speed of the faster regular
    interval beside it, between one period and the whole hold; the first values, written before the data began,
    ramp over the period before the first update; after the last update, `_extrapolate_tail`). t increasing, one
    sample a time. updates: the samples where a new value arrived, when a partner coordinate shows them
    (`held_with`; x may keep its value at some); default: where x changes."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if len(t) != len(x):
        raise ValueError(f"interpolate_holds needs one time per value, got {len(t)} times and {len(x)} values")
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("interpolate_holds needs increasing times, one sample a time")
    if not (np.isfinite(period) and period > 0.0):
        raise ValueError(f"interpolate_holds needs a period > 0, got {period!r}")
    out = x.copy()
    if updates is None:
        updates = changes(x)
    else:
        updates = np.asarray(updates, dtype=np.intp).reshape(-1)
        if len(updates) and (updates[0] < 1 or updates[-1] >= len(x) or np.any(np.diff(updates) <= 0)):
            raise ValueError("interpolate_holds needs updates as increasing sample indices from 1 to len(x) - 1")
        if not np.isin(changes(x), updates).all():
            raise ValueError("interpolate_holds: the values change where no update is given")
    if not len(updates):
        return out
    u = update_times(t, updates)
    interval = np.diff(np.concatenate([[-np.inf], u]))  # since the update before (the first: unknown)
    step = np.abs(x[updates] - x[updates - 1])
    regular = interval <= LONG_HOLD * period
    speed = np.where(regular, step / np.where(regular, interval, 1.0), np.nan)
    ramp = np.full(len(u), period)
    ramp[regular] = interval[regular]
    for i in np.flatnonzero(~regular & np.isfinite(interval)).tolist():
        beside = [speed[j] for j in (i - 1, i + 1) if 0 <= j < len(u) and np.isfinite(speed[j]) and speed[j] > 0]
        if beside:  # the time this step takes at the faster neighbour's speed, within [period, interval]
            ramp[i] = min(max(step[i] / max(beside), period), interval[i])
    start = u - ramp
    nxt = np.searchsorted(updates, np.arange(len(x)), side="right")  # the update after each sample
    idx = np.flatnonzero(nxt < len(updates))
    k = nxt[idx]
    on = t[idx] >= start[k]
    idx, k = idx[on], k[on]
    out[idx] = x[idx] + (x[updates[k]] - x[idx]) * (t[idx] - start[k]) / (u[k] - start[k])
    _extrapolate_tail(t, x, out, updates, u, interval, period)
    return out


def _extrapolate_tail(t: NDArray, x: NDArray, out: NDArray, updates: NDArray, u: NDArray, interval: NDArray,
                      period: float) -> None:
    """The values after the last update (no update follows to interpolate to) go on at the last updates' speed
    when those were steady (TAIL_UPDATES regular intervals, speeds of one sign within TAIL_SPREAD of the largest)
    and the file ends before a hold would have shown (within LONG_HOLD periods of the last update), for at most
    one period: the update the file did not reach. Else (a hover's noise, a turn, a stop) as written."""
    if len(u) < TAIL_UPDATES + 1 or t[-1] - u[-1] > LONG_HOLD * period:
        return
    last = interval[-TAIL_UPDATES:]
    if not np.all(last <= LONG_HOLD * period):
        return
    speed = (x[updates[-TAIL_UPDATES:]] - x[updates[-TAIL_UPDATES - 1:-1]]) / last
    top = float(np.max(np.abs(speed)))
    if not (top > 0.0 and (np.all(speed > 0) or np.all(speed < 0))
            and float(np.max(speed) - np.min(speed)) <= TAIL_SPREAD * top):
        return
    tail = np.arange(int(updates[-1]), len(x))
    out[tail] = x[tail] + speed[-1] * np.minimum(t[tail] - u[-1], period)

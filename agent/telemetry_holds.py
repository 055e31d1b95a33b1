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
least MIN_SAMPLES_PER_UPDATE records per update (median), updates at a regular period (their intervals'
inter-quartile range within MAX_SPREAD of the median interval, the period), steps of at least MIN_STEP_DIGITS of the
last decimal they are written to (median), and at least MIN_ONWARD of the steps in the direction of the one before.
A slow coordinate that steps one last digit at a time is rounded, not held: its steps come where it crosses the
middle between two values, half a digit earlier than a held value's (agent.telemetry_dequantize makes 3 to 5
decimals continuous; finer rounding is left as written); a barometer's height written to 0.1 m that flips between
two values is noise about a value, not updates. A value held much longer than the period (the UAV stopped, a
dropout) is kept until one period before the next update, which is reached by a ramp over that period: never
further from what the file says than the step the file itself makes next. The last values, after the last update,
stay as written (nothing is extrapolated).

Used by agent.telemetry_dequantize (for coordinates that are not quantised) on files, not on a live feed: it needs
the update after each record. Arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["LONG_HOLD", "MAX_SPREAD", "MIN_ONWARD", "MIN_SAMPLES_PER_UPDATE", "MIN_STEP_DIGITS", "MIN_UPDATES",
           "detect_hold", "interpolate_holds", "last_digit"]

#: Updates (changes of the value) needed to judge a period.
MIN_UPDATES = 5
#: Records per update (median) needed to say the value is held between updates.
MIN_SAMPLES_PER_UPDATE = 2
#: The update intervals' inter-quartile range may be at most this fraction of their median (25 fps records of a
#: 10 Hz GPS alternate 2 and 3 frames: 0.4 to 0.5; updates at random times: about 1.6).
MAX_SPREAD = 0.6
#: An interval between updates longer than this many periods is a hold (the UAV stopped, a dropout), not an update
#: period: the value is kept until one period before the next update.
LONG_HOLD = 1.5
#: A held coordinate's steps are at least this many of the last decimal they are written to (median).
MIN_STEP_DIGITS = 3.0
#: At least this share of the steps go on in the direction of the step before (a moving coordinate: differences of
#: noise about a value do so a third of the time).
MIN_ONWARD = 0.5


def last_digit(x: NDArray) -> float:
    """The last decimal the values are written to: the finest 10**-d (d = 0..9) of which every value is a multiple;
    0.0 when they have more decimals (a binary float: no decimal grid)."""
    x = np.asarray(x, dtype=np.float64)
    scale = float(np.max(np.abs(x), initial=1.0))
    for d in range(10):
        k = x * 10.0 ** d
        if np.all(np.abs(k - np.round(k)) < 1e-12 * scale * 10.0 ** d + 1e-9):  # the float's own error allowed
            return 10.0 ** -d
    return 0.0


def detect_hold(t: NDArray, x: NDArray) -> float | None:
    """The update period (seconds) of a coordinate x sampled at times t (increasing, one sample a time) that holds
    its value between regular updates; None when the file does not show that (see the module docstring)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if len(t) != len(x) or len(t) < 2 or not (np.isfinite(t).all() and np.isfinite(x).all()):
        return None
    updates = np.flatnonzero(x[1:] != x[:-1]) + 1
    if len(updates) < MIN_UPDATES:
        return None
    if float(np.median(np.diff(updates))) < MIN_SAMPLES_PER_UPDATE:
        return None
    steps = x[updates] - x[updates - 1]
    if float(np.median(np.abs(steps))) < MIN_STEP_DIGITS * last_digit(steps):
        return None
    if float(np.mean(np.sign(steps[1:]) == np.sign(steps[:-1]))) < MIN_ONWARD:
        return None
    intervals = np.diff(t[updates])
    period = float(np.median(intervals))
    if not period > 0.0:
        return None
    q25, q75 = np.percentile(intervals, [25.0, 75.0])
    if q75 - q25 > MAX_SPREAD * period:
        return None
    # the median is one of the intervals, each a whole number of records: their mean about it is finer
    regular = intervals[np.abs(intervals - period) <= 0.5 * period]
    return float(np.mean(regular))


def interpolate_holds(t: NDArray, x: NDArray, period: float) -> NDArray:
    """x with each held value taken linear from the update that wrote it to the next one (`detect_hold`'s period:
    a hold longer than LONG_HOLD periods keeps the value until one period before the next update; the first values,
    written before the data began, ramp over the period before the first update; after the last update, as
    written)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    out = x.copy()
    updates = np.flatnonzero(x[1:] != x[:-1]) + 1
    if not len(updates) or not period > 0.0:
        return out
    u = (t[updates - 1] + t[updates]) / 2.0  # each update came between the two records: halfway is the estimate
    previous = np.concatenate([[-np.inf], u[:-1]])
    start = np.where(u - previous <= LONG_HOLD * period, previous, u - period)
    nxt = np.searchsorted(updates, np.arange(len(x)), side="right")  # the update after each sample
    on = nxt < len(updates)
    idx = np.flatnonzero(on)
    k = nxt[idx]
    ramp = t[idx] >= start[k]
    idx, k = idx[ramp], k[ramp]
    frac = (t[idx] - start[k]) / (u[k] - start[k])
    out[idx] = x[idx] + (x[updates[k]] - x[idx]) * frac
    return out

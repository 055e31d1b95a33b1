"""Quantised telemetry made continuous again: GPS written with 4 or 5 decimals, altitude in whole or half
metres.

Old DJI SRT files round latitude and longitude to 4 decimals: the position holds for seconds and then jumps
by 11 m (north) or 7 m (east at 48 N) in one frame, and every ground point of that frame jumps with it.
The value written is the true one rounded, so while the UAV moves the true coordinate crosses the middle
between two written levels at the moment the written value steps: the midpoint of a step, placed halfway
between the two samples, is a measurement of the true position that is far better than either level.
Between such crossings the coordinate is interpolated linearly, kept inside the rounding interval of the
level written at each sample (never more than half a quantum from what the file says), and beyond the
first and last crossing it is extrapolated with the neighbouring slope, clipped the same way. A hovering
UAV whose value never steps keeps its written level.

The quantum is detected from the file itself: a coordinate is treated as quantised when every sample of
the video is a multiple of 1e-4 or 1e-5 degrees (height: 1 m or 0.5 m) and it has at least two distinct
values; otherwise the poses are left alone. Needs the samples after each frame, so it is for files
(`uavmm boost`, `uavmm track`, `uavmm tune`, the evaluations; `dequantize_records` for a video's telemetry file,
read whole before its first frame by `uavmm detect`, `uavmm agent --video` and `uavmm anomaly --video`), not for a
live feed. Arrays in, arrays out (records in, records out).
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

#: Quanta tried, coarsest first: 4 and 5 decimals of a degree (6 decimals, 0.11 m, is left alone).
GPS_QUANTA_DEG = (1e-4, 1e-5)
#: Altitude steps tried: whole and half metres.
HEIGHT_QUANTA_M = (1.0, 0.5)


def detect_quantum(values: NDArray, quanta: tuple[float, ...]) -> float | None:
    """The coarsest quantum of which every value is a multiple (to 1e-6 of it), None when none is or
    when fewer than two distinct values were written."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(v) < 2 or len(np.unique(v)) < 2 or not np.isfinite(v).all():
        return None
    for q in quanta:
        k = v / q
        if np.all(np.abs(k - np.round(k)) < 1e-6):
            return q
    return None


def dequantize(t: NDArray, x: NDArray, q: float) -> NDArray:
    """The continuous coordinate behind samples x (rounded to multiples of q) at their times t (increasing):
    linear through the midpoints of the steps, placed halfway between the samples that step, clipped to
    [x - q/2, x + q/2]; x itself where it never steps."""
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    steps = np.flatnonzero(x[1:] != x[:-1]) + 1
    if not len(steps):
        return x.copy()
    tau = (t[steps - 1] + t[steps]) / 2.0
    mid = (x[steps - 1] + x[steps]) / 2.0
    out = np.interp(t, tau, mid)
    if len(tau) >= 2:  # extrapolate beyond the first and last crossing with the neighbouring slope
        dt0, dt1 = tau[1] - tau[0], tau[-1] - tau[-2]
        slope0 = (mid[1] - mid[0]) / dt0 if dt0 > 0 else 0.0
        slope1 = (mid[-1] - mid[-2]) / dt1 if dt1 > 0 else 0.0
        before, after = t < tau[0], t > tau[-1]
        out[before] = mid[0] + slope0 * (t[before] - tau[0])
        out[after] = mid[-1] + slope1 * (t[after] - tau[-1])
    return np.clip(out, x - q / 2.0, x + q / 2.0)


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
        q = detect_quantum(values, HEIGHT_QUANTA_M if name == "height_m" else GPS_QUANTA_DEG)
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
        q = detect_quantum(values[first], HEIGHT_QUANTA_M if name == "height_m" else GPS_QUANTA_DEG)
        if q is None:
            continue
        quanta[name] = q
        smooth = dequantize(t_all[first], values[first], q)
        fixed_values[name] = np.clip(np.interp(t_all, t_all[first], smooth), values - q / 2.0, values + q / 2.0)
    if not quanta:
        return records, {}
    if "lon" in fixed_values:
        fixed_values["lon"] = (fixed_values["lon"] + 180.0) % 360.0 - 180.0
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

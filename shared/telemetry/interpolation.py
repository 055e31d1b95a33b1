"""Interpolating telemetry records to query times (video frames): linear, angles on the shortest arc."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from shared.telemetry.record import Telemetry, wrap180


def _optional(values: Iterable[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _unwrap_deg(deg: np.ndarray) -> np.ndarray:
    """Unwrap angles (period 360) over the finite entries so neighbours differ by at most 180 deg."""
    out = deg.copy()
    finite = np.isfinite(deg)
    if finite.any():
        out[finite] = np.unwrap(deg[finite], period=360.0)
    return out


def interpolate(
    records: Sequence[Telemetry], times: ArrayLike, *, extrapolate_s: float = 0.0, max_gap_s: float | None = None
) -> list[Telemetry | None]:
    """Interpolate telemetry to query times (e.g. video frame times).

    Parameters
    ----------
    records : sequence of Telemetry
        Sorted by ``t`` (non-decreasing); of records with equal ``t`` the first is used.
    times : array_like, shape (N,)
        Query times in the records' clock, seconds.
    extrapolate_s : float
        Times up to this far before the first / after the last record get that record's values
        (held, not extrapolated); further out they get None.
    max_gap_s : float, optional
        Times inside the records' span farther than this from both records around them (a gap in the log: a
        radio dropout, a logger paused) get None instead of a pose drawn straight across the gap; None: every
        time inside the span is interpolated.

    Returns
    -------
    list of Telemetry or None, length N
        ``t`` = the query time. lat, height, pitch, speeds and field of view are linear; lon, heading and roll follow
        the shortest arc (359 -> 1 passes 0, +179 -> -179 lon crosses the antimeridian). An optional
        field (height included) is None where a bracketing record lacks it. ``frame`` is kept only where a query time
        equals a record's ``t``. Records at latitude and longitude 0 (a logger's "no GPS fix") are left out, as if
        the log had a gap there; with only such records every time gets None.

    Raises
    ------
    ValueError
        If ``records`` is empty or unsorted, or a time or ``extrapolate_s`` is not finite (or negative).
    """
    recs = list(records)
    if not recs:
        raise ValueError("interpolate needs at least one telemetry record")
    query = np.atleast_1d(np.asarray(times, dtype=float)).reshape(-1)
    if not np.isfinite(query).all():
        raise ValueError("interpolate: query times must be finite")
    if not (math.isfinite(extrapolate_s) and extrapolate_s >= 0.0):
        raise ValueError(f"extrapolate_s={extrapolate_s!r} must be finite and >= 0")
    if max_gap_s is not None and not (math.isfinite(max_gap_s) and max_gap_s >= 0.0):
        raise ValueError(f"max_gap_s={max_gap_s!r} must be finite and >= 0")
    t_rec = np.array([r.t for r in recs], dtype=float)
    if (np.diff(t_rec) < 0).any():
        first = int(np.flatnonzero(np.diff(t_rec) < 0)[0]) + 1
        raise ValueError(f"interpolate: records must be sorted by t (record {first} goes back in time)")
    t_rec, keep = np.unique(t_rec, return_index=True)
    recs = [recs[i] for i in keep]
    fixed = np.array([r.has_fix for r in recs])
    if not fixed.all():  # a logger's "no GPS fix" (0, 0): no sample of the position, so no pose from it
        if not fixed.any():
            return [None] * len(query)
        t_rec, recs = t_rec[fixed], [r for r, f in zip(recs, fixed, strict=True) if f]

    def interp(values: np.ndarray) -> np.ndarray:
        return np.interp(np.clip(query, t_rec[0], t_rec[-1]), t_rec, values)

    lat = np.clip(interp(np.array([r.lat for r in recs])), -90.0, 90.0)
    lon = interp(_unwrap_deg(np.array([r.lon for r in recs])))
    height = interp(_optional(r.height_m for r in recs))
    pitch = np.clip(interp(_optional(r.pitch_deg for r in recs)), 0.0, 90.0)
    heading = interp(_unwrap_deg(_optional(r.heading_deg for r in recs)))
    roll = interp(_unwrap_deg(np.array([r.roll_deg for r in recs])))
    speed = interp(_optional(r.speed_mps for r in recs))
    vel_e = interp(_optional(None if r.vel_en_mps is None else r.vel_en_mps[0] for r in recs))
    vel_n = interp(_optional(None if r.vel_en_mps is None else r.vel_en_mps[1] for r in recs))
    hfov = interp(_optional(r.hfov_deg for r in recs))
    zoom = interp(_optional(r.zoom_ratio for r in recs))
    inside = (query >= t_rec[0] - extrapolate_s) & (query <= t_rec[-1] + extrapolate_s)
    if max_gap_s is not None and len(t_rec) > 1:
        after = np.clip(np.searchsorted(t_rec, query, side="left"), 1, len(t_rec) - 1)
        nearest = np.minimum(np.abs(query - t_rec[after - 1]), np.abs(t_rec[after] - query))
        within = (query < t_rec[0]) | (query > t_rec[-1]) | (nearest <= max_gap_s + 1e-9)  # stamps in float
        inside &= within
    hit = np.clip(np.searchsorted(t_rec, query), 0, len(t_rec) - 1)
    exact = t_rec[hit] == query

    def opt(values: np.ndarray, i: int) -> float | None:
        return None if np.isnan(values[i]) else float(values[i])

    out: list[Telemetry | None] = []
    for i in range(query.size):
        if not inside[i]:
            out.append(None)
            continue
        out.append(
            Telemetry(
                t=float(query[i]),
                lat=float(lat[i]),
                lon=wrap180(float(lon[i])) if abs(lon[i]) > 180.0 else float(lon[i]),
                height_m=opt(height, i),
                pitch_deg=opt(pitch, i),
                heading_deg=opt(heading, i),
                roll_deg=float(roll[i]),
                speed_mps=None if np.isnan(speed[i]) else max(float(speed[i]), 0.0),
                vel_en_mps=None if np.isnan(vel_e[i]) or np.isnan(vel_n[i]) else (float(vel_e[i]), float(vel_n[i])),
                frame=recs[hit[i]].frame if exact[i] else None,
                hfov_deg=opt(hfov, i),
                zoom_ratio=opt(zoom, i),
            )
        )
    return out


def spread_whole_second_stamps(stamps: list[float]) -> list[float]:
    """Stamps at whole seconds that repeat (a log stamped at whole seconds without a finer clock): the samples of
    one second are spread over it in their order (`spread_repeated_stamps`); any other list is returned as it is.

    A first second with fewer rows than the file's usual seconds (a log started at .7 s) holds the end of that
    second at the usual rate (.7, .8, .9 at 10 rows a second), a last one the start: spread over the whole second
    they put every later frame's pose up to a second early (the usual rate: the median count of the seconds between
    two others; without one, each second is spread whole)."""
    if not (all(a == round(a) for a in stamps) and len(set(stamps)) < len(stamps)):
        return stamps
    out = spread_repeated_stamps(stamps, True)
    groups: list[tuple[int, int]] = []  # (start, count) of each run of one stamp
    for i, value in enumerate(stamps):
        if groups and stamps[groups[-1][0]] == value:
            groups[-1] = (groups[-1][0], groups[-1][1] + 1)
        else:
            groups.append((i, 1))
    inner = [count for k, (start, count) in enumerate(groups[1:-1], 1)
             if stamps[start] - stamps[groups[k - 1][0]] == 1.0 and stamps[groups[k + 1][0]] - stamps[start] == 1.0]
    if inner:
        usual = int(np.median(inner))
        (s0, k0), (s1, k1) = groups[0], groups[-1]
        if len(groups) > 1 and 0 < k0 < usual and stamps[groups[1][0]] - stamps[s0] == 1.0:
            out[s0:s0 + k0] = stamps[s0] + (usual - k0 + np.arange(k0)) / usual
        if len(groups) > 1 and 0 < k1 < usual and stamps[s1] - stamps[groups[-2][0]] == 1.0:
            out[s1:s1 + k1] = stamps[s1] + np.arange(k1) / usual
    return [float(v) for v in out]


def spread_repeated_stamps(stamps: ArrayLike, whole_seconds: bool) -> np.ndarray:
    """Sample times from stamps that repeat: consecutive samples under one stamp (a 10 Hz log stamped at whole
    seconds) are spread evenly up to the next stamp (a whole-second stamp: over its second at most; the last
    stamp: over the median step between stamps). (M,) in, (M,) float64 out; other stamps are kept."""
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    out = stamps.copy()
    m = len(stamps)
    if m == 0:
        return out
    distinct = np.unique(stamps)
    default_step = 1.0 if whole_seconds else (float(np.median(np.diff(distinct))) if len(distinct) > 1 else 0.0)
    start = 0
    while start < m:
        end = start
        while end + 1 < m and stamps[end + 1] == stamps[start]:
            end += 1
        count = end - start + 1
        if count > 1:
            nxt = stamps[end + 1] if end + 1 < m else stamps[start] + default_step
            step = (nxt - stamps[start]) / count
            if whole_seconds:
                step = min(step, 1.0 / count)
            out[start:end + 1] = stamps[start] + step * np.arange(count)
        start = end + 1
    return out

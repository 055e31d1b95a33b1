"""ST 0601 samples as a time series: a time for every sample when encoders repeat the time stamp, and sensor
positions in time between the packets that sent them.

NumPy on arrays in stream order; `klv._report` applies both to the decoded samples before they become records.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from shared.telemetry.interpolation import spread_repeated_stamps
from shared.telemetry.klv_sample import KlvSample

__all__ = ["ALTITUDE_BRACKET_S", "POSITION_BRACKET_S", "POSITION_HOLD_S", "SampleTimes", "positions_in_time",
           "sample_times", "with_positions_in_time"]

#: Two packets that sent the position at most this far apart bracket the samples between them, which get the
#: position interpolated in time (a position sent at 1 Hz beside 30 Hz angles is; a longer GPS outage is not).
POSITION_BRACKET_S = 3.0
#: Else a sample keeps a position sent at most this long before it (then it has none: no record), or, after the
#: last packet that sent it, one interval of the stream's positions (the tail of a 1 Hz stream is no outage).
POSITION_HOLD_S = 0.5
#: The sensor's altitude changes slowly and encoders send it less often (on change, every few seconds): it is
#: interpolated between packets that sent it up to this far apart, else held as the decoder holds it.
ALTITUDE_BRACKET_S = 10.0
#: Fields interpolated together (a latitude without its longitude is no position); longitude on the shortest arc.
POSITION_GROUPS = (("sensor_lat", "sensor_lon"), ("sensor_alt_msl_m",), ("sensor_hae_m",))


@dataclass(frozen=True, slots=True)
class SampleTimes:
    """Each sample's time, and how it was found.

    t: (N,) float64 UNIX seconds. method: "stamps" (no stamp repeats the one before: the stamps as they are),
    "pts" (repeated stamps timed by their PES PTS) or "spread" (repeated stamps spread between the stamps).
    repeated: the samples whose stamp equals the one before.
    """

    t: np.ndarray
    method: str
    repeated: int


def sample_times(stamps_s: ArrayLike, pts_s: Sequence[float | None]) -> SampleTimes:
    """Times for samples whose Precision Time Stamp repeats (an encoder holding it, e.g. from the GPS's 1 Hz PPS).

    Parameters
    ----------
    stamps_s : array_like, shape (N,)
        The samples' time stamps (tag 2), UNIX seconds, in stream order.
    pts_s : sequence of float or None, length N
        Each sample's PES PTS in seconds, unwrapped (None: none, as in a raw ``.klv`` file).

    Returns
    -------
    SampleTimes
        No stamp repeats the one before: the stamps, unchanged. Else, with a PTS for every sample: the first
        sample of each stamp value is the one whose stamp is fresh, so its stamp minus its PTS time is the
        offset between the clocks there, and each sample gets its PTS time plus the offset of the last fresh
        stamp (never before its own stamp; a stream that starts while a stamp is held takes the offset of the
        next fresh one). A fresh stamp keeps its value. Without PTS: `spread_repeated_stamps` (samples under
        one stamp spread evenly up to the next; whole-second stamps over their second at most).
    """
    stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    n = len(stamps)
    if len(pts_s) != n:
        raise ValueError(f"sample_times: {n} stamps but {len(pts_s)} PTS")
    repeated = np.zeros(n, dtype=bool)
    repeated[1:] = stamps[1:] == stamps[:-1]
    count = int(repeated.sum())
    if not count:
        return SampleTimes(stamps.copy(), "stamps", 0)
    if any(p is None for p in pts_s):
        whole = bool(np.all(stamps == np.round(stamps)))
        return SampleTimes(spread_repeated_stamps(stamps, whole), "spread", count)
    pts = np.array(pts_s, dtype=np.float64)
    fresh = np.flatnonzero(~repeated)
    ref = fresh[np.searchsorted(fresh, np.arange(n), side="right") - 1]  # the last fresh sample at or before
    t = stamps[ref] + np.maximum(pts - pts[ref], 0.0)
    if len(fresh) > 1:  # the first stamp may have been held already when the stream began: not fresh
        head, nxt = np.arange(fresh[1]), fresh[1]
        ahead = pts[nxt] - pts[head]  # 0 for packets sharing the next stamp's PES: no timing to go by, kept
        t[head] = np.where(ahead > 0, np.maximum(stamps[0], stamps[nxt] - ahead), stamps[head])
    # a held sample stays before the next fresh stamp: one on the stamps' boundary (its stamp not yet new) would
    # tie with the fresh one, and a PTS discontinuity would push it past
    later = np.searchsorted(fresh, np.arange(n), side="right")
    has_next = later < len(fresh)
    limit = np.full(n, np.inf)
    limit[has_next] = stamps[fresh[later[has_next]]]
    over = t >= limit
    t[over] = limit[over] - 1e-6
    return SampleTimes(t, "pts", count)


def positions_in_time(t_s: ArrayLike, values: Mapping[str, ArrayLike], sent: Mapping[str, ArrayLike], *,
                      bracket_s: float = POSITION_BRACKET_S, hold_s: float = POSITION_HOLD_S) -> dict[str, np.ndarray]:
    """Sensor positions at the samples' times from the packets that sent them (not the values held in between).

    Parameters
    ----------
    t_s : array_like, shape (N,)
        The samples' times, seconds.
    values : mapping of field name to array_like, shape (N,)
        The `POSITION_GROUPS` fields (those present) as decoded: the packet's own value or one held, NaN where
        the decoder has none (never sent, sent as "unknown", held past its hold).
    sent : mapping of field name to array_like of bool, shape (N,)
        True where the sample's own packet sent the field.

    Returns
    -------
    dict of field name to (N,) float64
        Per group of fields: a sample whose packet sent them keeps them, as does one without all of them (NaN in
        `values`: an "unknown" is not bridged); else the values interpolated linearly in time between the last
        packet that sent them at or before its time and the first at or after it, when those are at most
        `bracket_s` apart; else the last sent value if it is at most `hold_s` old; else NaN.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    out: dict[str, np.ndarray] = {}
    for group in POSITION_GROUPS:
        if not all(name in values for name in group):
            continue
        latlon = group[-1] == "sensor_lon"
        group_bracket_s = bracket_s if latlon else max(bracket_s, ALTITUDE_BRACKET_S)
        vals = np.column_stack([np.asarray(values[name], dtype=np.float64).reshape(-1) for name in group])
        have = np.isfinite(vals).all(axis=1)
        own = have & np.logical_and.reduce([np.asarray(sent[name], dtype=bool).reshape(-1) for name in group])
        result = np.where((own | ~have)[:, None], vals, np.nan)  # a half position stays as decoded (no record)
        senders = np.flatnonzero(own)
        senders = senders[np.argsort(t[senders], kind="stable")]
        others = np.flatnonzero(have & ~own)
        if senders.size and others.size:
            q = t[others]
            before = np.searchsorted(t[senders], q, side="right") - 1
            after = np.searchsorted(t[senders], q, side="left")
            prev = senders[np.clip(before, 0, None)]
            nxt = senders[np.clip(after, None, len(senders) - 1)]
            span = t[nxt] - t[prev]
            bracket = (before >= 0) & (after < len(senders)) & (span <= group_bracket_s)
            step = vals[nxt] - vals[prev]
            if latlon:
                step[:, -1] = (step[:, -1] + 180.0) % 360.0 - 180.0  # across the antimeridian the short way
            frac = np.divide(q - t[prev], span, out=np.zeros_like(q), where=span > 0)
            between = vals[prev] + frac[:, None] * step
            if latlon:
                between[:, -1] = np.where(np.abs(between[:, -1]) > 180.0,
                                          (between[:, -1] + 180.0) % 360.0 - 180.0, between[:, -1])
            if latlon:
                # after the last sender, the stream's own interval (a 1 Hz position's last second) is no outage
                period = float(np.median(np.diff(t[senders]))) if senders.size > 1 else 0.0
                tail = (after >= len(senders)) & (q - t[prev] <= min(max(period, hold_s), group_bracket_s))
                held = (before >= 0) & ~bracket & ((q - t[prev] <= hold_s) | tail)
            else:  # the decoder's hold already let it go when too old (NaN): what is left stands
                held = (before >= 0) & ~bracket
            result[others[bracket]] = between[bracket]
            result[others[held]] = vals[prev][held]
        for k, name in enumerate(group):
            out[name] = result[:, k]
    return out


def with_positions_in_time(samples: Sequence[KlvSample],
                           sent: Sequence[frozenset[str]]) -> tuple[list[KlvSample], list[bool]]:
    """`positions_in_time` applied to samples (at their ``t``): the samples with those positions (None where NaN),
    and per sample whether it lost a latitude / longitude that was only held too long (a GPS outage)."""
    if len(sent) != len(samples):
        raise ValueError(f"with_positions_in_time: {len(samples)} samples but {len(sent)} sets of sent fields")
    names = [name for group in POSITION_GROUPS for name in group]
    values = {name: [np.nan if (v := getattr(s, name)) is None else v for s in samples] for name in names}
    placed = positions_in_time([s.t for s in samples], values,
                               {name: [name in own for own in sent] for name in names})
    columns = {name: [None if math.isnan(v) else v for v in placed[name].tolist()] for name in names}
    out, stale = [], []
    for i, sample in enumerate(samples):
        changes = {name: columns[name][i] for name in names if columns[name][i] != getattr(sample, name)}
        out.append(replace(sample, **changes) if changes else sample)  # type: ignore[arg-type]
        stale.append(columns["sensor_lat"][i] is None and sample.sensor_lat is not None
                     and sample.sensor_lon is not None)
    return out, stale

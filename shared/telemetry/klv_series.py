"""ST 0601 samples as a time series: a time for every sample when encoders repeat the time stamp.

Pure NumPy on arrays in stream order; `klv._report` applies it to the decoded samples before they become records.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from shared.telemetry.interpolation import spread_repeated_stamps

__all__ = ["SampleTimes", "sample_times"]


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
        t[head] = np.maximum(stamps[0], stamps[nxt] - np.maximum(pts[nxt] - pts[head], 0.0))
    return SampleTimes(t, "pts", count)

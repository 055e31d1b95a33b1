"""The size filter checks its priors against the data, and widens them to it, before it removes anything.

A size prior (built in, or fitted on other flights) says which metric sizes a class can have at each
viewing angle. On a camera, a height reference, an annotation style or a detector it was not made for it
can be off by a factor: on real SeaDronesSee flights the built-in swimmer prior (0.5 x 0.5 x 0.3 m) would
have removed a fifth of the true swimmers, whose confident boxes sit 1.2 to 3.5 of its standard deviations
above its mean. The detector's confident boxes (score >= `min_score`) are mostly real objects: per class,
where they lie in the prior's band (z = (log size - mean) / std) is collected, and once at least
`min_boxes` were seen the band is widened on the side of their median z by that much (rounded to `step`)
when it lies within +-`max_shift`: the data can only loosen a prior, never make it stricter than it is
(centring it instead cut the small, partly hidden people of the simulator's `coop` scenario: -0.8 AP50).
Further off, the prior is not for these data and the class stays unfiltered. A median, not a share of
rejected boxes: confident false positives of implausible size, which the filter is for, put 1-9 % of the
simulator's dense pre-NMS candidates beyond the band's edge and in a video with few objects make up most of
its confident boxes, but they do not move the median far (-0.3 std there), while a scale error moves all
real objects together. Files are checked on the whole video before its first frame (`prime`); a live feed
is checked as it goes (the class stays unfiltered until its evidence is in).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.size_filter import SizeBand, SizeFilter
from agent.stage_report import StageReport

__all__ = ["SizeCheckSettings", "SizeFilterCheck", "widened"]

#: z is collected in a histogram over +-_Z_RANGE (bounded memory on long flights), bins of _Z_BIN std.
_Z_RANGE = 10.0
_Z_BIN = 0.05


@dataclass(frozen=True, slots=True)
class SizeCheckSettings:
    """min_score: boxes at least this confident stand for real objects; min_boxes: confident boxes of a
    class needed before its prior may act; max_shift: the band is widened to the confident boxes' median z
    (in std of its band) when that is within +-max_shift, else the class stays unfiltered; step: the
    shift is rounded to multiples of this (a live feed's band changes only when the median moves that
    far); widen: False keeps the prior as it is (the check alone)."""

    min_score: float = 0.5
    min_boxes: int = 15
    max_shift: float = 3.0
    step: float = 0.25
    widen: bool = True

    def __post_init__(self) -> None:
        if not (0.0 <= self.min_score <= 1.0):
            raise ValueError(f"size check min_score must be in [0, 1], got {self.min_score!r}")
        if isinstance(self.min_boxes, bool) or not isinstance(self.min_boxes, int) or self.min_boxes < 1:
            raise ValueError(f"size check min_boxes must be an integer >= 1, got {self.min_boxes!r}")
        if not (isinstance(self.max_shift, (int, float)) and 0.0 <= self.max_shift < _Z_RANGE):
            raise ValueError(f"size check max_shift must be in [0, {_Z_RANGE:g}), got {self.max_shift!r}")
        if not (isinstance(self.step, (int, float)) and 0.0 < self.step <= 1.0):
            raise ValueError(f"size check step must be in (0, 1], got {self.step!r}")


class SizeFilterCheck:
    """One video's check of a size filter's priors: where the confident boxes of each class lie in its band;
    `active` is the filter restricted to the classes whose prior the data support."""

    def __init__(self, size_filter: SizeFilter, settings: SizeCheckSettings | None = None) -> None:
        self.size_filter = size_filter
        self.settings = settings or SizeCheckSettings()
        self._hist: dict[str, NDArray[np.int64]] = {}
        self._frozen = False
        self._active = SizeFilter({}, size_filter.k)
        self._active_names: frozenset[tuple[str, float]] = frozenset()
        self._edges = np.round(np.arange(-_Z_RANGE, _Z_RANGE + _Z_BIN / 2, _Z_BIN), 9)

    @property
    def frozen(self) -> bool:
        """Decided for good (`freeze`)."""
        return self._frozen

    def observe(self, class_name: str, z: NDArray) -> None:
        """Count where a class's confident boxes lie in its band ((N,) z; NaN ignored); ignored once frozen."""
        if self._frozen or class_name not in self.size_filter.bands:
            return
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        z = np.clip(z[np.isfinite(z)], -_Z_RANGE, _Z_RANGE)
        hist = self._hist.setdefault(class_name, np.zeros(len(self._edges) + 1, dtype=np.int64))
        np.add.at(hist, np.searchsorted(self._edges, z), 1)

    def freeze(self) -> None:
        """Decide on what was seen (a file's whole video) and observe no more."""
        self._frozen = True

    def seen(self, name: str) -> int:
        """Confident boxes of a class seen so far."""
        hist = self._hist.get(name)
        return 0 if hist is None else int(hist.sum())

    def median_z(self, name: str) -> float | None:
        """The median z of the class's confident boxes (to the histogram's bin), None before any was seen."""
        hist = self._hist.get(name)
        if hist is None or not hist.sum():
            return None
        cum = np.cumsum(hist) / hist.sum()
        i = int(np.searchsorted(cum, 0.5, side="left"))
        lower = -_Z_RANGE if i == 0 else float(self._edges[i - 1])
        upper = float(self._edges[min(i, len(self._edges) - 1)])
        return 0.5 * (lower + upper)

    def shift(self, name: str) -> float | None:
        """The band's shift for a class (std, rounded to `step`; 0 without recentring), None when the class
        stays unfiltered (too few confident boxes, or their median beyond max_shift)."""
        s = self.settings
        median = self.median_z(name)
        if self.seen(name) < s.min_boxes or median is None or abs(median) > s.max_shift:
            return None
        return round(median / s.step) * s.step if s.widen else 0.0

    @property
    def active(self) -> SizeFilter:
        """The size filter as applied: the bands of the classes whose check passed, each widened on the side
        of its shift s by |s| std (`widened`; the others pass unfiltered)."""
        shifts = {name: shift for name in self.size_filter.bands if (shift := self.shift(name)) is not None}
        key = frozenset(shifts.items())
        if key != self._active_names:  # a new object only when the decision changes (it keys cached tables)
            self._active_names = key
            k = self.size_filter.k
            bands = {name: widened(self.size_filter.bands[name], shift, k) for name, shift in shifts.items()}
            self._active = SizeFilter(bands, k)
        return self._active

    def reports(self, classes: list[str] | None = None) -> list[StageReport]:
        """One decision per class with a prior (only `classes` when given, e.g. those the video holds), and one
        standing down for each of `classes` the filter has no band for (its boxes pass unfiltered)."""
        out = [StageReport("size filter", False, f"{name}: no size band for this class (boxes unfiltered)")
               for name in classes or () if name not in self.size_filter.bands]
        s = self.settings
        for name in self.size_filter.bands:
            if classes is not None and name not in classes:
                continue
            shift = self.shift(name)
            median = self.median_z(name)
            if self.seen(name) < s.min_boxes:
                why = f"{name}: too few confident boxes to check the prior (< {s.min_boxes})"
            elif shift is None:
                why = f"{name}: the confident boxes lie beyond +-{s.max_shift:g} std of the prior: not for these data"
            elif shift:
                way = "larger" if shift > 0 else "smaller"
                why = f"{name}: prior widened to the confident boxes ({way} sizes, {abs(shift):g} std)"
            else:
                why = f"{name}: the confident boxes agree with the prior (median {median:+.2f} std)"
            out.append(StageReport("size filter", shift is not None, why))
        return out


def widened(band: SizeBand, shift: float, k: float) -> SizeBand:
    """The band [mean - k std, mean + k std] reaching |shift| std further on the side of shift's sign and
    unchanged on the other: mean + shift / 2 std, std x (1 + |shift| / (2 k)). The band itself when shift is 0."""
    if not shift:
        return band
    means = tuple(m + 0.5 * shift * sd for m, sd in zip(band.mean_log_m, band.std_log, strict=True))
    stds = tuple(sd * (1.0 + abs(shift) / (2.0 * k)) for sd in band.std_log)
    return dataclasses.replace(band, mean_log_m=means, std_log=stds)

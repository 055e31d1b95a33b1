"""The size filter checks its priors against the data before it removes anything.

A size prior (built in, or fitted on other flights) says which metric sizes a class can have at each
viewing angle. On a camera, a height reference or a detector it was not made for it can be wrong by a
factor: on real SeaDronesSee flights the built-in swimmer prior would have removed a fifth of the true
swimmers. The detector's confident boxes (score >= `min_score`) are mostly real objects: per class, where
they lie in the prior's band (z = (log size - mean) / std) is collected, and the filter acts only once at
least `min_boxes` of them were seen and their central part, from the `quantile` to the 1 - `quantile`
quantile of z, lies within +-`max_z`. A correct prior puts that central 80 % within +-1.28; a prior that is
wrong by a factor shifts the bulk of the data towards its band's edge (real swimmers: a tenth beyond
+2.1 to +4.5 std). The share beyond the band's edge (|z| > k) is not the test: confident false positives of
implausible size, which the filter is for, put 1-9 % of the simulator's dense pre-NMS candidates there.
Files are checked on the whole video before its first frame (`prime`); a live feed is checked as it goes
(the class stays unfiltered until its evidence is in).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.size_filter import SizeFilter
from agent.stage_report import StageReport

__all__ = ["SizeCheckSettings", "SizeFilterCheck"]

#: z is collected in a histogram over +-_Z_RANGE (bounded memory on long flights), bins of _Z_BIN std.
_Z_RANGE = 10.0
_Z_BIN = 0.05


@dataclass(frozen=True, slots=True)
class SizeCheckSettings:
    """min_score: boxes at least this confident stand for real objects; min_boxes: confident boxes of a
    class needed before its prior may act; quantile, max_z: the prior agrees with the data when the
    confident boxes from the quantile to the 1 - quantile quantile of z lie within +-max_z (std of the
    prior's band)."""

    min_score: float = 0.5
    min_boxes: int = 15
    quantile: float = 0.1
    max_z: float = 2.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.min_score <= 1.0):
            raise ValueError(f"size check min_score must be in [0, 1], got {self.min_score!r}")
        if isinstance(self.min_boxes, bool) or not isinstance(self.min_boxes, int) or self.min_boxes < 1:
            raise ValueError(f"size check min_boxes must be an integer >= 1, got {self.min_boxes!r}")
        if not (0.0 <= self.quantile < 0.5):
            raise ValueError(f"size check quantile must be in [0, 0.5), got {self.quantile!r}")
        if not (isinstance(self.max_z, (int, float)) and 0.0 < self.max_z < _Z_RANGE):
            raise ValueError(f"size check max_z must be in (0, {_Z_RANGE:g}), got {self.max_z!r}")


class SizeFilterCheck:
    """One video's check of a size filter's priors: where the confident boxes of each class lie in its band;
    `active` is the filter restricted to the classes whose prior the data support."""

    def __init__(self, size_filter: SizeFilter, settings: SizeCheckSettings | None = None) -> None:
        self.size_filter = size_filter
        self.settings = settings or SizeCheckSettings()
        self._hist: dict[str, NDArray[np.int64]] = {}
        self._frozen = False
        self._active = SizeFilter({}, size_filter.k)
        self._active_names: frozenset[str] = frozenset()
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

    def central_range(self, name: str) -> tuple[float, float] | None:
        """(quantile, 1 - quantile) of the class's z, to the histogram's bin; None before any box was seen."""
        hist = self._hist.get(name)
        if hist is None or not hist.sum():
            return None
        cum = np.cumsum(hist) / hist.sum()
        q = self.settings.quantile
        lo = int(np.searchsorted(cum, q, side="left"))
        hi = int(np.searchsorted(cum, 1.0 - q, side="left"))
        edges = np.concatenate([[-_Z_RANGE], self._edges])  # bin i holds z in (edges[i], edges[i + 1]]
        return float(edges[lo]), float(edges[min(hi + 1, len(edges) - 1)])

    def _passes(self, name: str) -> bool:
        if self.seen(name) < self.settings.min_boxes:
            return False
        central = self.central_range(name)
        assert central is not None
        return -self.settings.max_z <= central[0] and central[1] <= self.settings.max_z

    @property
    def active(self) -> SizeFilter:
        """The size filter with the bands of the classes whose check passed (the others pass unfiltered)."""
        names = frozenset(name for name in self.size_filter.bands if self._passes(name))
        if names != self._active_names:  # a new object only when the decision changes (it keys cached tables)
            self._active_names = names
            self._active = SizeFilter({n: b for n, b in self.size_filter.bands.items() if n in names},
                                      self.size_filter.k)
        return self._active

    def reports(self, classes: list[str] | None = None) -> list[StageReport]:
        """One decision per class with a prior (only `classes` when given, e.g. those the video holds)."""
        out = []
        s = self.settings
        for name in self.size_filter.bands:
            if classes is not None and name not in classes:
                continue
            if self.seen(name) < s.min_boxes:
                why = f"{name}: too few confident boxes to check the prior (< {s.min_boxes})"
            elif self._passes(name):
                why = f"{name}: the confident boxes agree with the prior"
            else:
                why = (f"{name}: the confident boxes contradict the prior (their central "
                       f"{100 - 200 * s.quantile:g} % beyond +-{s.max_z:g} std)")
            out.append(StageReport("size filter", self._passes(name), why))
        return out

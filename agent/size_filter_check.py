"""The size filter checks its priors against the data before it removes anything.

A size prior (built in, or fitted on other flights) says which metric sizes a class can have at each
viewing angle. On a camera, a height reference or a detector it was not made for it can be wrong by a
factor: on real SeaDronesSee flights the built-in swimmer prior would have removed a fifth of the true
swimmers. The detector's confident boxes (score >= `min_score`) are mostly real objects: per class, the
filter acts only once at least `min_boxes` of them were seen and the prior would have rejected at most
`max_rejected` of them; otherwise it stands down for that class and says why. Files are checked on the
whole video before its first frame (`prime`); a live feed is checked as it goes (the class stays unfiltered
until its evidence is in).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.size_filter import SizeFilter
from agent.stage_report import StageReport

__all__ = ["SizeCheckSettings", "SizeFilterCheck"]


@dataclass(frozen=True, slots=True)
class SizeCheckSettings:
    """min_score: boxes at least this confident stand for real objects; min_boxes: confident boxes of a
    class needed before its prior may act; max_rejected: the largest fraction of them the prior may reject
    (a correct prior at k = 3 rejects well under 1 %: 0.27 % of a normal distribution; 2 % leaves room for the
    confident false positives it should reject)."""

    min_score: float = 0.5
    min_boxes: int = 15
    max_rejected: float = 0.02

    def __post_init__(self) -> None:
        if not (0.0 <= self.min_score <= 1.0):
            raise ValueError(f"size check min_score must be in [0, 1], got {self.min_score!r}")
        if isinstance(self.min_boxes, bool) or not isinstance(self.min_boxes, int) or self.min_boxes < 1:
            raise ValueError(f"size check min_boxes must be an integer >= 1, got {self.min_boxes!r}")
        if not (0.0 <= self.max_rejected < 1.0):
            raise ValueError(f"size check max_rejected must be in [0, 1), got {self.max_rejected!r}")


class SizeFilterCheck:
    """One video's check of a size filter's priors: the confident boxes seen per class and how many the
    prior rejects; `active` is the filter restricted to the classes whose prior the data support."""

    def __init__(self, size_filter: SizeFilter, settings: SizeCheckSettings | None = None) -> None:
        self.size_filter = size_filter
        self.settings = settings or SizeCheckSettings()
        self._seen: dict[str, int] = {}
        self._rejected: dict[str, int] = {}
        self._frozen = False
        self._active = SizeFilter({}, size_filter.k)
        self._active_names: frozenset[str] = frozenset()

    def observe(self, class_name: str, accepted: NDArray[np.bool_]) -> None:
        """Count a class's confident boxes and which the prior accepts ((N,) bool); ignored once frozen."""
        if self._frozen or class_name not in self.size_filter.bands:
            return
        accepted = np.asarray(accepted, dtype=bool).reshape(-1)
        self._seen[class_name] = self._seen.get(class_name, 0) + len(accepted)
        self._rejected[class_name] = self._rejected.get(class_name, 0) + int((~accepted).sum())

    @property
    def frozen(self) -> bool:
        """Decided for good (`freeze`)."""
        return self._frozen

    def freeze(self) -> None:
        """Decide on what was seen (a file's whole video) and observe no more."""
        self._frozen = True

    def _passes(self, name: str) -> bool:
        seen = self._seen.get(name, 0)
        return seen >= self.settings.min_boxes and self._rejected.get(name, 0) <= self.settings.max_rejected * seen

    @property
    def active(self) -> SizeFilter:
        """The size filter with the bands of the classes whose check passed (the others pass unfiltered)."""
        names = frozenset(name for name in self.size_filter.bands if self._passes(name))
        if names != self._active_names:  # a new object only when the decision changes (it keys cached tables)
            self._active_names = names
            self._active = SizeFilter({n: b for n, b in self.size_filter.bands.items() if n in names},
                                      self.size_filter.k)
        return self._active

    def share_rejected(self, name: str) -> float | None:
        """The share of a class's confident boxes the prior rejects, None before any was seen."""
        seen = self._seen.get(name, 0)
        return self._rejected.get(name, 0) / seen if seen else None

    def reports(self, classes: list[str] | None = None) -> list[StageReport]:
        """One decision per class with a prior (only `classes` when given, e.g. those the video holds)."""
        out = []
        s = self.settings
        for name in self.size_filter.bands:
            if classes is not None and name not in classes:
                continue
            seen = self._seen.get(name, 0)
            if seen < s.min_boxes:
                why = f"{name}: too few confident boxes to check the prior (< {s.min_boxes})"
            elif self._passes(name):
                why = f"{name}: the confident boxes agree with the prior"
            else:
                why = f"{name}: the confident boxes contradict the prior (> {100 * s.max_rejected:g} % rejected)"
            out.append(StageReport("size filter", self._passes(name), why))
        return out

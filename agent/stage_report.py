"""What each adaptive stage did: acted or stood down, and why, gathered over a run for its summary.

Every adaptive stage (telemetry clock, dequantisation, clock offset, size filter, telemetry correction,
score calibration) has the same shape: estimate, judge its own evidence, apply or stand down, and report
which it did. A stage reports once per scope it decides for (a video, a class of a video, a frame); the
run's summary then says, per stage, how often it acted and the reasons it did not.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

__all__ = ["StageReport", "StageSummary", "stage_lines"]


@dataclass(frozen=True, slots=True)
class StageReport:
    """One decision of a stage: stage name, acted, and why (what it found, or why it stood down)."""

    stage: str
    acted: bool
    why: str = ""


@dataclass
class StageSummary:
    """The decisions of a run, per stage: counts of acting and standing down, and the reasons."""

    acted: Counter[str] = field(default_factory=Counter)
    stood_down: Counter[str] = field(default_factory=Counter)
    reasons: dict[str, Counter[str]] = field(default_factory=dict)

    def add(self, report: StageReport) -> None:
        """Count one decision."""
        (self.acted if report.acted else self.stood_down)[report.stage] += 1
        if report.why:
            self.reasons.setdefault(report.stage, Counter())[report.why] += 1

    def as_dict(self) -> dict[str, Any]:
        """{stage: {"acted": n, "stood_down": m, "why": {reason: count}}} in the order stages first reported."""
        stages = list(dict.fromkeys([*self.acted, *self.stood_down, *self.reasons]))
        return {name: {"acted": self.acted[name], "stood_down": self.stood_down[name],
                       "why": dict(self.reasons.get(name, Counter()).most_common(5))} for name in stages}

    def lines(self) -> list[str]:
        """One human-readable line per stage."""
        return stage_lines(self.as_dict())


def stage_lines(stages: dict[str, Any]) -> list[str]:
    """One line per stage of a `StageSummary.as_dict` (as a run's summary holds it)."""
    out = []
    for name, entry in stages.items():
        why = "; ".join(f"{reason} ({n})" for reason, n in entry["why"].items())
        head = f"{name}: acted {entry['acted']}, stood down {entry['stood_down']}"
        out.append(head + (f" - {why}" if why else ""))
    return out

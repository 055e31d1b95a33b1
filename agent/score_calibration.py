"""Self-calibrating detector scores: the detector's own score statistics, estimated online, map its
confidences onto a reference detector's temperature, so the memory map's evidence and boost hold for over-
and under-confident detectors without re-tuning.

An over- or under-confident detector differs from a calibrated one mostly by the scale (temperature) of
its logits. The statistic used here is the spread of the logits of the strongest detections within each
frame after NMS (the top `top_k` by score): NMS and ranking do not change under a monotone map of the
scores, and within one frame the spread is untouched by what moves a whole frame (blur, a change of
scene), so it follows the temperature alone (measured: 1.3-1.5 on the simulator's default detector,
0.75-0.87 when its logits are scaled by 0.6, 1.9-2.8 when scaled by 1.6). Logits are scaled by
reference spread / running spread, about 0 (a shift of all logits changes no ranking after the log-odds
boost). The running spread starts at the reference (measured on the tuning domains) and follows the data
with a time constant in seconds (frame-rate independent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.stage_report import StageReport

__all__ = ["CalibrationSettings", "InputCheck", "ScoreCalibration"]

_EPS = 1e-6


def _logit(p: NDArray) -> NDArray:
    q = np.clip(p, _EPS, 1.0 - _EPS)
    return np.log(q / (1.0 - q))


@dataclass(frozen=True, slots=True)
class CalibrationSettings:
    """top_k: strongest kept detections per frame that feed the statistic; tau_s: time constant of the
    running spread, seconds; prior_s: weight of the reference spread, in seconds of data (the estimate is
    the reference at the start and mostly the data's after a few prior_s); ref_sd_logit: the reference
    detector's within-frame spread of those logits; max_scale: the largest factor (and its inverse the
    smallest) the logits are scaled by. The input check (`InputCheck`): the calibration acts only once
    min_candidates scores were seen and at least min_low_share of them lie below max_floor (pre-NMS
    candidates reach down to the detector's floor; a thresholded final output does not, and the spread of
    its strongest detections is the threshold's, not the temperature's)."""

    top_k: int = 10
    tau_s: float = 30.0
    prior_s: float = 2.0
    ref_sd_logit: float = 1.35
    max_scale: float = 3.0
    max_floor: float = 0.05
    min_low_share: float = 0.01
    min_candidates: int = 50

    def __post_init__(self) -> None:
        if isinstance(self.top_k, bool) or not isinstance(self.top_k, int) or self.top_k < 2:
            raise ValueError(f"calibration top_k must be an integer >= 2, got {self.top_k!r}")
        for name in ("tau_s", "prior_s", "ref_sd_logit", "max_scale"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"calibration {name} must be a finite number > 0, got {value!r}")
        for name in ("max_floor", "min_low_share"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0.0 <= value < 1.0):
                raise ValueError(f"calibration {name} must be a number in [0, 1), got {value!r}")
        if isinstance(self.min_candidates, bool) or not isinstance(self.min_candidates, int) or self.min_candidates < 1:
            raise ValueError(f"calibration min_candidates must be an integer >= 1, got {self.min_candidates!r}")


class InputCheck:
    """Is the input pre-NMS candidates (scores down to the detector's floor) or a thresholded final output?
    Counts the scores seen and those below max_floor; decided once min_candidates were seen (or `freeze`)."""

    def __init__(self, settings: CalibrationSettings) -> None:
        self.settings = settings
        self.seen = 0
        self.low = 0
        self.frozen = False

    def observe(self, scores: NDArray) -> None:
        """Count a frame's candidate scores (ignored once frozen)."""
        if self.frozen:
            return
        scores = np.asarray(scores).reshape(-1)
        self.seen += len(scores)
        self.low += int(np.count_nonzero(scores < self.settings.max_floor))

    def freeze(self) -> None:
        """Decide on what was seen (a file's whole video) and observe no more."""
        self.frozen = True

    @property
    def acts(self) -> bool:
        s = self.settings
        return self.seen >= s.min_candidates and self.low >= s.min_low_share * self.seen

    def why(self) -> str:
        s = self.settings
        if self.seen < s.min_candidates:
            return f"{self.seen} scores seen, {s.min_candidates} needed to tell pre-NMS from final output"
        share = 100.0 * self.low / self.seen
        if self.acts:
            return f"pre-NMS input ({share:.0f} % of scores below {s.max_floor:g})"
        return f"thresholded input ({share:.1f} % of scores below {s.max_floor:g}): its spread is the threshold's"


class ScoreCalibration:
    """Running within-frame logit spread of one video's strongest detections, and the scaling onto the
    reference. Per frame: `apply(scores)` with the statistic so far, then `observe(t, kept_scores)`.
    """

    def __init__(self, settings: CalibrationSettings | None = None) -> None:
        self.settings = settings or CalibrationSettings()
        self.reset()

    def reset(self) -> None:
        """Back to the reference (start of another video)."""
        self.check = InputCheck(self.settings)
        self._weight_s = 0.0  # seconds of data in the running mean (decayed)
        self._var = self.settings.ref_sd_logit ** 2
        self._t: float | None = None

    @property
    def sd(self) -> float:
        """The current estimate of the within-frame spread (prior included)."""
        s = self.settings
        w = self._weight_s / (self._weight_s + s.prior_s)
        return math.sqrt(w * self._var + (1 - w) * s.ref_sd_logit ** 2)

    @property
    def scale(self) -> float:
        """The factor logits are multiplied by: reference spread / running spread, clamped."""
        s = self.settings
        return min(max(s.ref_sd_logit / max(self.sd, 1e-9), 1.0 / s.max_scale), s.max_scale)

    def report(self) -> StageReport:
        """Whether the calibration acted in this video, and why (agent.stage_report)."""
        why = self.check.why()
        if self.check.acts:
            why += f", scale {self.scale:.2f}"
        return StageReport("score calibration", self.check.acts, why)

    def observe(self, t: float, kept_scores: NDArray) -> None:
        """Fold in a frame's kept detections (raw detector scores, any order) at time t (seconds); nothing
        while the input check says the input is not pre-NMS candidates."""
        if not self.check.acts:
            return
        s = self.settings
        scores = np.asarray(kept_scores, dtype=np.float64).reshape(-1)
        dt = 1.0 / 30.0 if self._t is None else min(max(t - self._t, 0.0), 1.0)
        self._t = t if self._t is None else max(self._t, t)
        if len(scores) < s.top_k or dt <= 0:
            return  # too few to speak for the top of the distribution
        top = np.partition(scores, len(scores) - s.top_k)[-s.top_k:]
        var = float(_logit(top).var())
        w_old = self._weight_s * math.exp(-dt / s.tau_s)
        self._weight_s = w_old + dt
        self._var = (w_old * self._var + dt * var) / self._weight_s

    def apply(self, scores: NDArray) -> NDArray[np.float32]:
        """Scores at the reference temperature: sigmoid(scale * logit(score)), float32, same shape (the
        scores themselves, as float32, while the scale is 1 or the input check stands the calibration down).
        The scores are counted by the input check first (unless it is frozen)."""
        self.check.observe(scores)
        a = self.scale if self.check.acts else 1.0
        if abs(a - 1.0) < 1e-6:
            return np.asarray(scores, dtype=np.float32)
        # float32 throughout: this runs on every candidate of every frame
        q = np.clip(np.asarray(scores, dtype=np.float32), np.float32(_EPS), np.float32(1.0 - _EPS))
        odds = np.power(q / (np.float32(1.0) - q), np.float32(a))  # exp(a * logit)
        return np.asarray(odds / (np.float32(1.0) + odds), dtype=np.float32)  # float32 already: no copy

"""Telemetry self-correction: the common-mode ground offset of one frame's projection, found by registering
the frame's confident detections to the memory map's evidence, bounded, smoothed, with a fallback to the
raw telemetry.

Every box of a frame is projected with the same pose, so a GPS error, a time offset or a jittering gimbal
angle moves all of them together (to first order, by one ground offset). The memory map holds where the
previous frames put the objects; the offset that best lays this frame's confident boxes onto that
evidence is the frame's correction. Arrays in, arrays out: the map is read, never written.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.stage_report import StageReport
from shared.geo import Pose, local_to_latlon

__all__ = ["CorrectionSettings", "GroundCorrection", "GroundOffsetEstimator", "register_offset"]


@dataclass(frozen=True, slots=True)
class CorrectionSettings:
    """Settings of the correction (PipelineConfig.correction_* hold them for the pipeline).

    min_score: detections at least this confident (the detector's own score) register.
    search_m: largest offset searched around the raw telemetry's ground points, metres (the bound: a
        larger error is not corrected, and a best offset on the bound is not applied: the true one may lie
        beyond it, or the evidence is another object's).
    min_points: confident detections a frame needs for a measurement.
    min_support: the mean evidence under the registered detections a measurement needs (0..1).
    smoothing_s: time constant of the exponential smoothing of the measurements (0: none).
    hold_s: without a measurement, the last correction is held this long, then decays to 0 (raw
        telemetry) with the same time constant.
    max_points: at most this many detections (the most confident) register.
    local_m: the offset is first searched within this many metres of the current correction; only when
        the evidence there gives less than min_support is the whole search_m window searched (a GPS
        step). Two objects some metres apart make an alias: the shift that lays one of them onto the
        other's evidence can score as well as the true one in a frame where the other is faint, and the
        correction jumped by it for single frames. 0 (default): the whole window every frame; 2 m halved
        the tracker's id switches on sea-tele-gps4 when it tracked on corrected points, and cost 0.2 AP50
        on the tuning domains (docs/memory-map.md).
    anchor_s: the correction is anchored to the telemetry over this time (seconds; 0: not anchored; 10 s by
        default, chosen 29 Nov 2026, docs/memory-map.md). The map holds the earlier frames' points moved by
        their corrections, so a measurement is the correction this frame needs plus what the map already
        carries, and a constant added to every correction is invisible to the measurements: unanchored, each
        frame's measurement error (a fraction of a cell) and the evidence walkers leave behind them add up, and
        on noise-free telemetry the map walked 1-3 m away from the truth within 10 s (`coop-slope`,
        docs/geometry.md, Two UAVs on opposite sides of a slope). Anchored, the applied corrections averaged
        over anchor_s are taken off each measurement: what the correction keeps for longer than that is the
        telemetry's own (a bias no registration can see), and the map stays where the telemetry puts the
        objects on average. Faster errors (jitter) are corrected as before; a lasting step is corrected at
        first and handed back to the telemetry over roughly anchor_s. Meant for anchor_s at or above the map's
        memory (its half-life / ln 2); below it the correction rings.
    """

    min_score: float = 0.5
    search_m: float = 8.0
    min_points: int = 2
    min_support: float = 0.3
    smoothing_s: float = 0.0
    hold_s: float = 2.0
    max_points: int = 16
    local_m: float = 0.0
    anchor_s: float = 10.0

    def __post_init__(self) -> None:
        for name in ("min_score", "search_m", "min_support", "smoothing_s", "hold_s", "local_m", "anchor_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"correction {name} must be a finite number >= 0, got {value!r}")
        for name in ("min_points", "max_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"correction {name} must be an integer >= 1, got {value!r}")


@dataclass(frozen=True, slots=True)
class GroundCorrection:
    """The correction applied to one frame.

    east_m, north_m: offset added to every ground point, metres; measured: this frame registered (else
    the held or decayed earlier correction, or 0); points: detections that registered; support: mean
    evidence under them at the measured offset (0 without a measurement).
    """

    east_m: float = 0.0
    north_m: float = 0.0
    measured: bool = False
    points: int = 0
    support: float = 0.0

    def moved(self, pose: Pose) -> Pose:
        """The pose with the UAV moved by this correction: over flat ground the same as moving every ground point
        by it; over a terrain the rays are marched again from it (agent.pipeline)."""
        lat, lon = local_to_latlon(self.east_m, self.north_m, pose.lat, pose.lon)
        return dataclasses.replace(pose, lat=float(lat), lon=float(lon))


def register_offset(patches: NDArray[np.float32], weights: NDArray, *,
                    near: tuple[float, float, float] | None = None,
                    near_support: float = 0.0) -> tuple[float, float, float]:
    """The shift that lays points onto evidence, from the evidence around each point.

    patches: (N, 2R+1, 2R+1) evidence around each point (row = y, col = x offset + R, cells);
    weights: (N,) non-negative. Returns (dx, dy, support): the weighted centroid of the offsets whose
    summed evidence is within 5 % of the best (a steadily seen object is a clipped plateau, so the
    centre of the top region, not its first maximum), in cells, and support = best summed evidence /
    sum of weights. (0, 0, 0) without evidence.
    near: (dx, dy, r) cells: search the offsets within r of (dx, dy) first and keep that answer when its
    support reaches near_support; otherwise (or when the disc lies outside the window) the whole window.
    """
    w = np.asarray(weights, dtype=np.float32).reshape(-1)
    total = float(w.sum())
    if not len(patches) or total <= 0:
        return 0.0, 0.0, 0.0
    # np.tensordot(w, patches, axes=1) as the one matrix product it makes, without its ~10 us of set-up
    side = patches.shape[1]
    score = np.dot(w.reshape(1, -1), patches.reshape(len(w), -1)).reshape(side, side)  # (2R+1, 2R+1)
    r = score.shape[0] // 2
    offsets = np.arange(-r, r + 1, dtype=np.float32)
    if near is not None:
        disc = (offsets[None, :] - near[0]) ** 2 + (offsets[:, None] - near[1]) ** 2 <= near[2] ** 2
        if disc.any():
            local = np.where(disc, score, np.float32(0.0))
            best = float(local.max())
            if best > 0 and best / total >= near_support:
                score = local
    best = float(score.max())
    if best <= 0:
        return 0.0, 0.0, 0.0
    top = score - np.float32(0.95 * best)
    np.maximum(top, 0.0, out=top)
    mass = float(top.sum())
    return float(top.sum(axis=0) @ offsets / mass), float(top.sum(axis=1) @ offsets / mass), best / total


class GroundOffsetEstimator:
    """Per-video state of the correction: the smoothed offset, when it was last measured and (anchored) the
    applied corrections averaged over the anchor time."""

    def __init__(self, settings: CorrectionSettings | None = None) -> None:
        self.settings = settings or CorrectionSettings()
        self.reset()

    def reset(self) -> None:
        """Forget the correction (start of another video)."""
        self._east = self._north = 0.0
        self._t: float | None = None
        self._t_measured: float | None = None
        self._carried: tuple[float, float] | None = None  # anchored: the applied corrections, averaged
        #: frames per outcome: "measured", "at the search bound", "low support", "too few boxes"
        self.outcomes: dict[str, int] = {}

    def count(self, outcome: str) -> None:
        """Count one frame's outcome for the report."""
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1

    def report(self) -> StageReport:
        """Acted when some frame was measured (agent.stage_report); why: the frames per outcome."""
        measured = self.outcomes.get("measured", 0)
        if measured:
            total = sum(self.outcomes.values())
            return StageReport("telemetry correction", True, f"measured in {100 * measured / total:.0f} % of frames")
        others = sorted(self.outcomes.items(), key=lambda kv: -kv[1])
        return StageReport("telemetry correction", False, f"never measured: {others[0][0]}" if others else "no frames")

    @property
    def current_en(self) -> tuple[float, float]:
        """The correction (east, north) metres as last applied."""
        return self._east, self._north

    @property
    def expected_en(self) -> tuple[float, float]:
        """The measurement (east, north metres) a frame like the last one would give: its correction plus,
        anchored, the averaged corrections taken off the measurements."""
        carried = self._carried or (0.0, 0.0)
        return self._east + carried[0], self._north + carried[1]

    def update(self, t: float, measurement_en: tuple[float, float] | None, points: int = 0,
               support: float = 0.0) -> GroundCorrection:
        """Advance to time t with this frame's measured offset (east, north metres) or None; returns the
        correction to apply (smoothed, held, or decaying to 0 without measurements). Anchored
        (`CorrectionSettings.anchor_s` > 0) the applied corrections averaged over anchor_s are first taken off
        the measurement, and the correction applied now joins that average."""
        s = self.settings
        dt = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t if self._t is None else max(self._t, t)
        if measurement_en is not None and self._carried is not None:
            measurement_en = (measurement_en[0] - self._carried[0], measurement_en[1] - self._carried[1])
        if measurement_en is not None:
            a = 1.0 if s.smoothing_s <= 0 or self._t_measured is None else 1.0 - math.exp(-dt / s.smoothing_s)
            self._east += a * (measurement_en[0] - self._east)
            self._north += a * (measurement_en[1] - self._north)
            self._t_measured = self._t
            out = GroundCorrection(self._east, self._north, True, points, support)
        else:
            if self._t_measured is not None and self._t - self._t_measured > s.hold_s:
                k = math.exp(-dt / max(s.hold_s, 1e-3))
                self._east *= k
                self._north *= k
            out = GroundCorrection(self._east, self._north, False, points, 0.0)
        if s.anchor_s > 0:
            if self._carried is None:
                self._carried = (self._east, self._north)
            else:
                k = 1.0 - math.exp(-dt / s.anchor_s)
                self._carried = (self._carried[0] + k * (self._east - self._carried[0]),
                                 self._carried[1] + k * (self._north - self._carried[1]))
        return out

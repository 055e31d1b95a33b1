"""The joint registration: where the other UAVs' evidence lands in this UAV's image, relative to its own detections.

Used by agent.joint_detections (the peaks of the others' evidence are moved by the offset before they are
matched or synthesised) and agent.joint_boost (registered joint boosting, an option).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.pipeline_config import PipelineConfig

__all__ = ["JointRegistration"]

#: The settings' defaults (PipelineConfig.joint_register_* fields).
_DEFAULTS = PipelineConfig()
_KERNEL = np.ones((3, 3), np.uint8)


class JointRegistration:
    """Running estimate of where the other UAVs' evidence lands in this UAV's image, relative to its detections.

    Every UAV georeferences with its own telemetry errors, so the others' peak of an object this UAV
    also detects projects beside this UAV's box of it (on `coop` by 100-300 px at 80 m). The largest
    errors are attitude biases (heading, 2 deg RMS), and an attitude bias shifts every projection by
    the same view angle whatever the UAV looks at, while the ground shift it causes grows with range
    and turns with the view. So the offset is an angle: image offsets in focal lengths (pixels /
    focal_px, ~radians).

    Pairs: every (peak, own confident detection) within radius_m of each other on the ground, with
    the image offset of the peak from the detection, over the last window_s seconds. People in groups
    make many wrong pairs, and residues of this UAV's own evidence in the others' make pairs at zero
    offset; the true offset is the one the most peaks share. The estimate: of the `candidates`
    strongest maxima of the pairs' smoothed 2-D histogram (bins of bin_rad), the one with the most
    peaks having a pair within match_rad of it, refined to the median of those pairs. Offsets beyond
    max_rad are ignored. Zero until min_pairs pairs are in. Defaults: PipelineConfig.joint_register_*.
    """

    def __init__(self, radius_m: float = _DEFAULTS.joint_register_radius_m,
                 window_s: float = _DEFAULTS.joint_register_window_s,
                 min_pairs: int = _DEFAULTS.joint_register_min_pairs, *,
                 bin_rad: float = _DEFAULTS.joint_register_bin_rad,
                 match_rad: float = _DEFAULTS.joint_register_match_rad,
                 candidates: int = _DEFAULTS.joint_register_candidates,
                 max_rad: float = _DEFAULTS.joint_register_max_rad) -> None:
        self.radius_m = radius_m
        self.window_s = window_s
        self.min_pairs = min_pairs
        self.bin_rad = bin_rad
        self.match_rad = match_rad
        self.candidates = candidates
        self.max_rad = max_rad
        self._frames: list[tuple[float, NDArray[np.float64], NDArray[np.int64]]] = []  # (t, offsets, peak ids)
        self._next_peak = 0
        self._cached: tuple[float, float] | None = None

    @classmethod
    def from_config(cls, config: PipelineConfig) -> JointRegistration:
        """The registration with the joint_register_* settings of a PipelineConfig."""
        return cls(config.joint_register_radius_m, config.joint_register_window_s, config.joint_register_min_pairs,
                   bin_rad=config.joint_register_bin_rad, match_rad=config.joint_register_match_rad,
                   candidates=config.joint_register_candidates, max_rad=config.joint_register_max_rad)

    def reset(self) -> None:
        self._frames.clear()
        self._cached = None

    def update(self, t: float, peak_en: NDArray, own_en: NDArray, peak_xy: NDArray, own_xy: NDArray) -> None:
        """Add one frame: peaks and own detections on the ground, peak_en (P, 2) and own_en (Q, 2) metres,
        and in the image, peak_xy (P, 2) and own_xy (Q, 2) in focal lengths (pixels / focal_px; NaN = none)."""
        self._frames = [f for f in self._frames if t - self.window_s <= f[0] <= t]
        self._cached = None
        if len(peak_en) == 0 or len(own_en) == 0:
            return
        peak_en, own_en = np.asarray(peak_en, np.float64), np.asarray(own_en, np.float64)
        dist = np.hypot(peak_en[:, None, 0] - own_en[None, :, 0], peak_en[:, None, 1] - own_en[None, :, 1])
        ii, jj = np.nonzero(dist <= self.radius_m)
        d = np.asarray(peak_xy, np.float64)[ii] - np.asarray(own_xy, np.float64)[jj]
        ok = np.isfinite(d).all(axis=1) & (np.abs(d) <= self.max_rad).all(axis=1)
        if ok.any():
            self._frames.append((t, d[ok], self._next_peak + ii[ok]))
        self._next_peak += len(peak_en)

    def offset(self) -> tuple[float, float]:
        """Current (x, y) image offset of the others' evidence, in focal lengths (multiply by focal_px)."""
        if self._cached is not None:
            return self._cached
        n_pairs = sum(len(f[2]) for f in self._frames)
        if n_pairs < self.min_pairs:
            return 0.0, 0.0
        d = np.concatenate([f[1] for f in self._frames])
        ids = np.concatenate([f[2] for f in self._frames])
        b = self.bin_rad
        lo = d.min(axis=0) - 3 * b
        bins = np.maximum(np.ceil((d.max(axis=0) + 3 * b - lo) / b).astype(int), 1)
        cells = np.minimum(((d - lo) / b).astype(int), bins - 1)
        counts = np.bincount(cells[:, 1] * bins[0] + cells[:, 0], minlength=int(bins[0] * bins[1]))
        hist = cv2.GaussianBlur(counts.astype(np.float32).reshape(bins[1], bins[0]), (0, 0), 2.0)
        rows, cols = np.nonzero((hist >= cv2.dilate(hist, _KERNEL)) & (hist > 0))
        order = np.argsort(-hist[rows, cols], kind="stable")[:self.candidates]
        # peaks with a pair near each candidate, counted on a mark per peak id (np.unique sorted them: ~3x slower)
        first_id = int(ids.min())
        marks = np.zeros(int(ids.max()) - first_id + 1, bool)
        best_near, best_n = None, -1
        for k in order:
            centre = lo + (np.array([cols[k], rows[k]]) + 0.5) * b
            near = np.hypot(*(d - centre).T) <= self.match_rad
            marks[:] = False
            marks[ids[near] - first_id] = True
            n = int(np.count_nonzero(marks))
            if n > best_n:
                best_near, best_n = near, n
        best = np.median(d[best_near], axis=0) if best_near is not None else np.zeros(2)
        self._cached = (float(best[0]), float(best[1]))
        return self._cached

"""The camera's motion in the image as far tracks show it: one common shift per frame, found by the boxes' vote.

Beyond the far reach (agent.tracking.far_points) every object is hundreds of metres away and moves a pixel a
frame at most, while a tele camera's slow sweep moves every box 20-30 px a frame and its sway 10-20 px more, two
or three box sizes (simulated `sea-farther-tele`: the GT centres of one frame move together within 1-6 px). Each
track's box is expected where the frame's common image motion since its last match took it (`ImageMotion`), and
that motion is measured in each frame by the shift that the most tracks agree on (`common_shift`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from agent.tracking.assignment import near_pairs

__all__ = ["ImageMotion", "common_shift"]

FloatArray = NDArray[np.float64]


@dataclass
class ImageMotion:
    """The image's accumulated common motion (offset, px) and its rate (px/s), an alpha-beta filter with alpha 1.

    A track stores the offset of the frame it was last matched in; its box centre is expected moved by
    `offset_at(t)` minus that. The offset moves on at the rate (a sweep goes on) for up to hold_s seconds after
    the last measured frame (`update`), and then stays: a sweep nothing shows any more has ended as far as the
    tracker can tell, and a stale rate would carry every later prediction off.
    """

    offset: FloatArray = field(default_factory=lambda: np.zeros(2))
    rate: FloatArray = field(default_factory=lambda: np.zeros(2))
    t: float | None = None  # the last frame's time (s)
    t_measured: float | None = None  # the last measured frame's time (s)
    hold_s: float = 0.0

    def offset_at(self, t: float) -> FloatArray:
        """(2,) px: the offset expected at time t (s), moved on at the rate up to hold_s after the last measurement
        (never backwards)."""
        if self.t is None or self.t_measured is None:
            return self.offset.copy()
        return self.offset + self.rate * max(min(t, self.t_measured + self.hold_s) - self.t, 0.0)

    def update(self, t: float, residual: FloatArray | None, rate_gain: float, hold_s: float) -> None:
        """Move to the frame at time t: the offset expected then, plus the measured residual (2,) px when there is
        one, which also moves the rate by rate_gain * residual / dt (from 0 when the last measurement is more than
        hold_s old); None: nothing measured."""
        self.hold_s = hold_s
        expected = self.offset_at(t)
        stale = self.t_measured is None or t - self.t_measured > hold_s
        if stale:
            self.rate = np.zeros(2)
        if residual is not None:
            expected = expected + residual
            dt = 0.0 if self.t is None else t - self.t
            if dt > 0:
                self.rate = self.rate + rate_gain * np.asarray(residual) / dt
            self.t_measured = t
        self.offset, self.t = expected, t


def common_shift(pred_xy: FloatArray, pred_size: FloatArray, pred_cls: NDArray, det_xy: FloatArray,
                 det_size: FloatArray, det_cls: NDArray, radius: float, tol: float,
                 min_tracks: int) -> FloatArray | None:
    """The shift (2,) px from the tracks' expected box centres to this frame's boxes that the most tracks agree on.

    pred_xy (T, 2) expected box centres, pred_size (T,) box sizes (px), pred_cls (T,) classes; det_xy (D, 2),
    det_size (D,), det_cls (D,) the frame's boxes alike. A pair counts in the smaller of its two sizes (a large box
    does not widen the search). Candidate pairs, of one class, lie within radius sizes of each other; a pair agrees
    with a candidate's shift when its own lies within tol sizes of it. The candidate with the most distinct tracks
    in agreement (ties: the smallest shift) wins when they are at least min_tracks; the shift is the median of the
    agreeing pairs' own. Returns None when no candidate has that many. Pairs are found with k-d trees, so a crowded
    frame stays sparse.
    """
    ti, dj = near_pairs(pred_xy, radius * pred_size, det_xy, np.zeros(len(det_xy)))
    size = np.minimum(pred_size[ti], det_size[dj])
    step = det_xy[dj] - pred_xy[ti]
    keep = (pred_cls[ti] == det_cls[dj]) & (np.hypot(step[:, 0], step[:, 1]) <= radius * size)
    ti, step, size = ti[keep], step[keep], size[keep]
    if len(np.unique(ti)) < min_tracks:
        return None
    k, m = near_pairs(step, np.zeros(len(step)), step, tol * size)  # pair m agrees with candidate k
    votes = np.bincount(np.unique(np.column_stack([k, ti[m]]), axis=0)[:, 0], minlength=len(step))
    best = np.lexsort((np.hypot(step[:, 0], step[:, 1]), -votes))[0]
    if votes[best] < min_tracks:
        return None
    return np.median(step[m[k == best]], axis=0)

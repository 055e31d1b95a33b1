"""A partner's confidence lent along a shared global track (issue 30, part 2).

The memory map's log-odds boost keeps the detector's order among candidates whose evidence has saturated: an
object this UAV sees weakly (glare, thin foliage) is found, but ranks below everything it sees well, false
positives included, while another UAV that sees the object clearly reports it with a high confidence. Lending
that confidence box by box, at the partner's detection's registered spot, lifted this UAV's fragments and
displaced boxes beside a person as much as the person (docs/simulator.md, "Fifth measurement"). Here it goes
along tracks instead: the fusion server joins this UAV's local track and the partner's into one global track
only after seconds of agreement on the ground, and a fragment seldom holds a track of its own.

Each frame, a detection the tracker assigned to a local track that the latest ``joint/tracks`` message lists as
an active member of a global track beside another UAV's active member takes, in log-odds, the share `weight` of
the way from its own confidence to the global track's (the highest confidence among the members still reporting
it), when that is above the confidence this UAV itself last reported for the track (so the lent confidence is
another UAV's); a track keeps the best confidence lent to it over the last MEMORY_S seconds. Only the output
changes (the detections the agent writes): the tracker, the memory map and the tracks it publishes take the frame
as the pipeline scored it, so no UAV's confidence comes back to it through the server.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from agent.frame_result import FrameResult
from agent.tracking.tracker import TrackOutput
from shared.messages import JointTracksMessage, TracksMessage

__all__ = ["MEMORY_S", "TrackLending", "lend_scores", "partner_scores"]

_EPS = 1e-6
#: A track keeps the highest confidence lent to it over this many seconds of frame time: a partner that saw the
#: object clearly a moment ago still vouches for it when its latest frame saw it less well.
MEMORY_S = 2.0
#: Fields of FrameResult with one row per detection (reordered with the scores).
_ROWS = ("boxes_xyxy", "scores", "raw_scores", "class_ids", "lat", "lon", "embeddings", "from_joint", "view_height_m",
         "alt_latlon")


def partner_scores(joint: JointTracksMessage | None, uav: str, own: Mapping[int, float]) -> dict[int, float]:
    """Local track id -> the confidence another UAV reports for its object.

    joint: the latest ``joint/tracks`` message (None: nothing known); uav: this UAV's id; own: the confidence this
    UAV last reported per local track (its tracks message). A local track qualifies when a global track lists it
    and another UAV's member as active (the members still reporting it) and the global track's score, the highest
    of those members', is above `own` for it: then that score is another UAV's.
    """
    out: dict[int, float] = {}
    if joint is None:
        return out
    for track in joint.tracks:
        active = track.active_members
        mine = [lid for u, lid in active if u == uav]
        if not mine or all(u == uav for u, _ in active):
            continue
        for lid in mine:
            if track.score > own.get(lid, 1.0) + _EPS:
                out[lid] = max(out.get(lid, 0.0), float(track.score))
    return out


def lend_scores(result: FrameResult, tracks: Sequence[TrackOutput], lent: Mapping[int, float],
                weight: float) -> FrameResult:
    """`result` with each detection of a track in `lent` moved, in log-odds, `weight` of the way to the lent
    confidence where that is higher (`partner_scores`); reordered highest score first. A detection belongs to the
    track matched to it in this frame (the track's box is the detection's). weight 0 or nothing lent: `result`."""
    _check_weight(weight)
    return _lend(result, tracks, lent, weight)[0]


def _check_weight(weight: float) -> None:
    if not (0.0 <= weight <= 1.0) or not math.isfinite(weight):
        raise ValueError(f"track lending: weight must be in [0, 1], got {weight!r}")


def _lend(result: FrameResult, tracks: Sequence[TrackOutput], lent: Mapping[int, float],
          weight: float) -> tuple[FrameResult, int]:
    """`lend_scores` (weight checked by the caller) and how many detections it raised."""
    if weight == 0.0 or not lent or not len(result):
        return result, 0
    pairs = [(track.box_xyxy, lent[track.id]) for track in tracks if track.matched and track.id in lent]
    if not pairs:
        return result, 0
    boxes = np.asarray(result.boxes_xyxy, dtype=np.float64)
    wanted = np.asarray([box for box, _ in pairs], dtype=np.float64).reshape(-1, 4)
    # each lent track's detection: the box the tracker matched (a track's box is its detection's), all at once
    same = np.all(np.abs(boxes[:, None, :] - wanted[None, :, :]) <= 1e-3, axis=2)  # (K detections, T tracks)
    goal = np.full(len(boxes), -np.inf)
    rows_hit, cols_hit = np.nonzero(same)
    np.maximum.at(goal, rows_hit, np.asarray([score for _, score in pairs], dtype=np.float64)[cols_hit])
    scores = np.asarray(result.scores, dtype=np.float64).copy()
    own = np.clip(scores, _EPS, 1.0 - _EPS)
    raise_ = goal > own
    changed = int(np.count_nonzero(raise_))
    if changed:
        lo = np.log(own[raise_] / (1.0 - own[raise_]))
        g = np.clip(goal[raise_], _EPS, 1.0 - _EPS)
        lg = np.log(g / (1.0 - g))
        scores[raise_] = 1.0 / (1.0 + np.exp(-(lo + weight * (lg - lo))))
    if not changed:
        return result, 0
    order = np.argsort(-scores, kind="stable")
    rows: dict[str, object] = {}
    for name in _ROWS:
        value = scores.astype(np.float32) if name == "scores" else getattr(result, name)
        rows[name] = None if value is None else np.asarray(value)[order]
    return dataclasses.replace(result, **rows), changed  # type: ignore[arg-type]


class TrackLending:
    """`lend_scores` for one UAV fed with what it publishes and receives: `reported` with each tracks message it
    sends (its own confidences), `apply` each frame with its time and the latest ``joint/tracks`` message (or
    None). A track takes the highest confidence lent to it within the last `memory_s` seconds of frame time.
    weight: PipelineConfig.track_lending (0: off). `lent_detections` counts the detections whose score rose."""

    def __init__(self, uav: str, weight: float, memory_s: float = MEMORY_S) -> None:
        _check_weight(weight)
        if not (memory_s >= 0.0 and math.isfinite(memory_s)):
            raise ValueError(f"track lending: memory_s must be >= 0, got {memory_s!r}")
        self.uav = uav
        self.weight = weight
        self.memory_s = memory_s
        self.lent_detections = 0
        self._own: dict[int, float] = {}
        self._joint: JointTracksMessage | None = None
        self._fresh = False  # a message or report not yet taken into the memory
        self._memory: dict[int, list[tuple[float, float]]] = {}  # local id -> (frame time, lent score), oldest first
        self._best: dict[int, float] = {}
        self._valid = (math.inf, math.inf)  # frame times for which _best holds: [since, until)

    def reported(self, msg: TracksMessage) -> None:
        """This UAV's tracks message just sent: the confidences the server now has of it."""
        self._own = {item.id: float(item.score) for item in msg.tracks}
        self._fresh = True

    def lent(self, t: float) -> dict[int, float]:
        """Local id -> the highest confidence lent to the track within memory_s before frame time t."""
        if self._fresh:
            self._fresh = False
            for lid, score in partner_scores(self._joint, self.uav, self._own).items():
                self._memory.setdefault(lid, []).append((t, score))
        elif self._valid[0] <= t < self._valid[1]:
            return self._best  # nothing came in or expired since it was computed
        best: dict[int, float] = {}
        until = math.inf
        for lid in list(self._memory):
            kept = [(tt, s) for tt, s in self._memory[lid] if t - self.memory_s <= tt <= t]
            if kept:
                self._memory[lid] = kept
                best[lid] = max(s for _, s in kept)
                until = min(until, kept[0][0] + self.memory_s)
            else:
                del self._memory[lid]
        self._best, self._valid = best, (t, until if until > t else math.nextafter(t, math.inf))
        return best

    def apply(self, result: FrameResult, tracks: Sequence[TrackOutput], joint: JointTracksMessage | None,
              t: float) -> FrameResult:
        """The frame's result (at frame time t) with the partners' confidences lent (see the module docstring)."""
        if self.weight == 0.0:
            return result
        if joint is not self._joint:
            self._joint = joint
            self._fresh = True
        out, raised = _lend(result, tracks, self.lent(t), self.weight)
        self.lent_detections += raised
        return out

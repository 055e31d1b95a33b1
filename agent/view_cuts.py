"""View cuts hidden between telemetry samples: a gimbal that jumps between two frames, logged sparsely.

A log at 1 Hz (or one whose samples are held for a second, as flight logs' whole-second stamps are) turns a
60 deg view jump into a smooth 60 deg/s turn when the poses are interpolated at the frames' times: for up to a
second every frame has a heading tens of degrees off, its boxes land on the ground far from the objects, and
the tracker's view-jump guard (`agent.tracking.view_jump`, a rate threshold) never fires. The frames themselves
show when the view jumped: the detections stop continuing the previous frame's.

Here every telemetry interval of at least `ViewCutSettings.min_interval_s` whose heading or pitch changes by at
least `min_turn_deg` is searched, half an interval beyond both samples (truncated stamps, lags), for the cut: a
frame whose confident boxes and those of the last frame before it with boxes (blur empties the frames of a
jump) do not continue each other (`continuity`: no common image shift carries one set onto the other), nor do
the next frame's with boxes (else it was a dropout), beside a steady view on at least one side (a view of false
positives alone continues nothing anywhere, so it cannot place a cut). Of such frames, the one beside the
steadiest view. Frames before the cut get the interval's first sample's heading and pitch, the frames from it
the last sample's. An interval without a cut (a smooth sweep, whose boxes shift together from frame to frame;
too few boxes to tell) keeps its interpolated poses, and the stage report says so. Positions and heights stay
interpolated. File drivers only: a live feed cannot look ahead to the next sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from agent.boxes import nms
from agent.clock_offset import ClockOffset
from agent.dataset import Frame
from agent.stage_report import StageReport

__all__ = ["ViewCutSettings", "ViewCutReport", "continuity", "pan", "place_view_cuts"]

_MATCH_FRAC = 0.5
#: frames (at least; ViewCutSettings.max_gap_s) looked back for the old view's last frame with boxes and ahead for
#: the new view's next one
_LOOKAHEAD = 5
#: frame pairs on each side of a candidate cut that show whether the view there is steady
_SIDE = 4
Detections = Callable[[Frame], tuple[NDArray, NDArray, NDArray]]


@dataclass(frozen=True, slots=True)
class ViewCutSettings:
    """min_turn_deg: a telemetry interval whose heading or pitch changes this much may hide a cut.
    min_score: the detector score of the boxes that show continuity (NMS'd, at most max_boxes per frame).
    match_frac: two boxes continue each other when their centres lie within this fraction of their mean
    diagonal after the common shift. max_continuity: a cut is a frame that continues at most this much of the
    last frame before it with boxes (`continuity`), nor does the next frame with boxes, beside a view whose
    frame pairs continue at least cut_margin more (`_find_cut`). min_boxes: one of the two frames compared needs
    this many boxes.
    reach: the frames searched extend this many interval lengths beyond both samples (stamps truncated to whole
    seconds, a telemetry lag). min_interval_s: shorter intervals are left as they are: a jump smeared over
    0.1 s (a 10 Hz log) turns faster than the tracker's view-jump guard's rate, which holds those frames back;
    stepping them too cost 0.3-0.6 HOTA on the 10 Hz tuning jump domains (seeds 0-2). min_frames: an interval
    needs this many frames between its samples: at 2 fps a smooth turn of 24 deg moves the boxes as far from one
    frame to the next as a cut does (the real dev file has one). still_frac: the view beside a cut must pan at
    most this share of what a smooth turn through the interval would show per frame (sweeps logged at 1 Hz have
    boxes that continue, shifted, and blur that empties frames like a jump's). max_gap_s: the old view's last
    frame with boxes and the new view's first may lie this far apart (at least _LOOKAHEAD frames): a gimbal turn
    of 0.1-0.45 s blurs 3-13 frames at 30 fps empty; longer empty stretches are blur through a sweep, whose
    views beside it a cut would misplace (1.0 s placed false cuts in a 1 Hz sweep domain)."""

    min_turn_deg: float = 20.0
    min_score: float = 0.3
    max_boxes: int = 40
    match_frac: float = _MATCH_FRAC
    max_continuity: float = 0.25
    cut_margin: float = 0.25
    min_boxes: int = 3
    reach: float = 0.5
    min_interval_s: float = 0.25
    min_frames: int = 4
    still_frac: float = 0.5
    max_gap_s: float = 0.5

    def __post_init__(self) -> None:
        for name in ("min_turn_deg", "min_score", "match_frac", "max_continuity", "cut_margin", "reach",
                     "min_interval_s", "still_frac", "max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"ViewCutSettings.{name}={value!r} must be a finite number >= 0")
        if self.max_boxes < 1 or self.min_boxes < 1 or self.min_frames < 1:
            raise ValueError("ViewCutSettings.max_boxes, min_boxes and min_frames must be >= 1")


@dataclass(slots=True)
class ViewCutReport:
    """What the stage found in one video: intervals turning at least min_turn_deg between two telemetry samples
    with frames inside, the cuts placed in them, and the intervals with too few frames to judge."""

    intervals: int = 0
    cuts: int = 0
    too_few_frames: int = 0

    def stage_report(self) -> StageReport:
        if not self.intervals:
            return StageReport("view cuts", False, "no telemetry interval turns enough to hide a view jump")
        sparse = f", {self.too_few_frames} with too few frames to judge" if self.too_few_frames else ""
        if self.cuts:
            return StageReport("view cuts", True, f"{self.cuts} of {self.intervals} sharply turning telemetry "
                                                  f"intervals cut where the detections jump{sparse}")
        return StageReport("view cuts", False, f"no cut in {self.intervals} turning intervals{sparse}: poses "
                                               "interpolated")


def _centres(boxes: NDArray, scores: NDArray, class_ids: NDArray, settings: ViewCutSettings) -> NDArray:
    """(N, 3) centre x, y and diagonal (pixels) of a frame's confident boxes after NMS."""
    scores = np.asarray(scores, dtype=np.float32).reshape(-1)
    keep = np.flatnonzero(scores >= settings.min_score)
    if not len(keep):
        return np.zeros((0, 3))
    b = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)[keep]
    kept = nms(b, scores[keep], np.asarray(class_ids).reshape(-1)[keep], 0.5, 0.0, settings.max_boxes)
    b = b[kept].astype(np.float64)
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2,
                            np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])])


def continuity(a: NDArray, b: NDArray, match_frac: float = _MATCH_FRAC) -> float:
    """How much two frames' boxes (rows: centre x, y, diagonal) continue each other, in [0, 1].

    One way: the share of a's boxes that b's continue under the best common image shift (each shift sending one
    box of a onto one of b is tried), that one box not counted, since some shift always matches one box, by
    chance in an unrelated view: (matched - 1) / (len(a) - 1). Both ways, the lesser (a few boxes in a dense
    unrelated view find partners by chance one way, not the other); a frame with fewer than two boxes is left
    out. 0 when one frame has boxes and the other none, NaN when neither has two."""
    return _compare(a, b, match_frac)[0]


def pan(a: NDArray, b: NDArray, match_frac: float = _MATCH_FRAC) -> float:
    """Length (pixels) of the common image shift that carries most of frame a's boxes onto frame b's (the shortest
    of equals); NaN when either frame has fewer than two boxes. A still camera gives a few pixels, a pan its rate."""
    return _compare(a, b, match_frac)[1]


def _compare(a: NDArray, b: NDArray, match_frac: float) -> tuple[float, float]:
    """(`continuity`, `pan`) of two frames' boxes, the forward shift search shared by both."""
    ways: list[float] = []
    pan_px = math.nan
    if len(a) >= 2:
        if len(b):
            shifts, matched = _shift_matches(a, b, match_frac)
            ways.append(float((matched.max() - 1) / (len(a) - 1)))
            if len(b) >= 2:
                best = np.flatnonzero(matched == matched.max())
                pan_px = float(np.hypot(shifts[best, 0], shifts[best, 1]).min())
        else:
            ways.append(0.0)
    if len(b) >= 2:
        ways.append(float((_shift_matches(b, a, match_frac)[1].max() - 1) / (len(b) - 1)) if len(a) else 0.0)
    return (min(ways) if ways else math.nan), pan_px


def _shift_matches(a: NDArray, b: NDArray, match_frac: float) -> tuple[NDArray, NDArray]:
    """Each common shift that sends one box of a onto one of b, (S, 2) pixels, and how many of a's boxes it carries
    onto one of b's, (S,).

    Box i of a lands on box j of b under shift s when |(b_j - a_i) - s| <= match_frac * mean diagonal: so the
    shifts near each candidate are found among the S differences themselves with a k-d tree, O(S log S) plus the
    pairs found, instead of moving every box by every shift (O(S * na * nb): 2.6 million distances at 40 boxes a
    frame, 20 ms a pair)."""
    na, nb = len(a), len(b)
    shifts = (b[None, :, :2] - a[:, None, :2]).reshape(-1, 2)  # (na * nb, 2), row i * nb + j
    radius = (match_frac * 0.5 * (a[:, 2][:, None] + b[:, 2][None, :])).reshape(-1)
    if not len(shifts):
        return shifts, np.zeros(0, dtype=np.int64)
    owner = np.repeat(np.arange(na), nb)  # the box of a each difference moves
    tree = cKDTree(shifts)
    # a hair beyond the largest radius (the tree compares squared distances): the exact test below decides
    near = tree.sparse_distance_matrix(tree, float(radius.max()) * (1.0 + 1e-9) + 1e-12, output_type="coo_matrix")
    rows, cols = near.row, near.col
    keep = np.hypot(*(shifts[rows] - shifts[cols]).T) <= radius[cols]
    # the self pairs (distance 0) may be left out of the sparse matrix: every shift carries its own box
    pairs = np.unique(np.concatenate([rows[keep] * na + owner[cols[keep]], np.arange(len(shifts)) * na + owner]))
    return shifts, np.bincount(pairs // na, minlength=len(shifts))


def place_view_cuts(frames: list[tuple[Frame, ClockOffset | None]], detections: Detections,
                    settings: ViewCutSettings | None = None,
                    report: ViewCutReport | None = None) -> list[tuple[Frame, ClockOffset | None]]:
    """One video's frames (time order, as `agent.clock_offset.video_frames` gives them) with each view jump that
    a sharply turning telemetry interval hides put at the frame where the detections jump (see the module
    docstring). detections(frame) -> (boxes_xyxy, scores, class_ids). report: filled with what was found."""
    settings = settings or ViewCutSettings()
    report = report if report is not None else ViewCutReport()
    track = next((f.track for f, _ in frames if f.track is not None and f.pose is not None), None)
    if track is None or len(track.t) < 2:
        return frames
    values = track.values
    turn = np.maximum(np.abs(np.diff(values[:, 3])), np.abs(np.diff(values[:, 4])))
    sharp = np.flatnonzero((turn >= settings.min_turn_deg) & (np.diff(track.t) >= settings.min_interval_s))
    if not len(sharp):
        return frames
    # each posed frame's time on the telemetry clock
    tau = np.array([f.t + (off.offset_s if off is not None else 0.0) if f.pose is not None else math.nan
                    for f, off in frames])
    out = list(frames)
    cache: dict[int, NDArray] = {}
    compared: dict[tuple[int, int], tuple[float, float]] = {}

    def centres(k: int) -> NDArray:
        if k not in cache:
            cache[k] = _centres(*detections(frames[k][0]), settings)
        return cache[k]

    def compare(j: int, k: int) -> tuple[float, float]:
        """(continuity, pan) of frames j and k, each pair searched once (candidate windows overlap)."""
        if (j, k) not in compared:
            compared[(j, k)] = _compare(centres(j), centres(k), settings.match_frac)
        return compared[(j, k)]

    for i in sharp:
        t0, t1 = track.t[i], track.t[i + 1]
        # the search reaches half an interval beyond the samples: stamps truncated to whole seconds or a lag the
        # clock-offset estimate left can put the jump's frames just outside the interval
        ext = settings.reach * (t1 - t0)
        with np.errstate(invalid="ignore"):
            hidden = int(np.count_nonzero((tau > t0) & (tau < t1)))
            inside = np.flatnonzero((tau > t0 - ext) & (tau < t1 + ext))
        if not hidden:
            continue  # every frame has a sample of its own side of the jump
        report.intervals += 1
        if hidden < settings.min_frames:
            report.too_few_frames += 1
            continue  # too few frames between the samples to tell a cut from a turn
        # each frame k of the interval (and the one after it: the cut may fall on either end) against the last
        # frame before it with two boxes or more (blur empties the frames of a jump)
        conts: dict[int, tuple[int, float]] = {}
        # frames a jump's blur may empty between the old view and the new one: _LOOKAHEAD, or max_gap_s at the
        # interval's frame rate
        gap = max(_LOOKAHEAD, math.ceil(settings.max_gap_s * hidden / (t1 - t0)))
        for k in range(max(int(inside[0]), 1), min(int(inside[-1]) + 2, len(frames))):
            prev = next((j for j in range(k - 1, max(k - 2 - gap, -1), -1) if len(centres(j)) >= 2), None)
            if prev is not None and max(len(centres(prev)), len(centres(k))) >= settings.min_boxes:
                conts[k] = (prev, compare(prev, k)[0])
        if not conts:
            continue
        # the image pan per frame a smooth turn through the interval would show: a cut needs a still view beside it
        camera = frames[int(inside[0])][0].camera
        pitch = math.radians(min(max(float(values[i, 4]), 0.0), 90.0))
        turn_deg = max(abs(float(values[i + 1, 3] - values[i, 3])) * math.cos(pitch),
                       abs(float(values[i + 1, 4] - values[i, 4])))
        still_px = settings.still_frac * math.sqrt(camera.fx * camera.fy) * math.radians(turn_deg) / hidden
        cut = _find_cut(conts, centres, compare, len(frames), settings, still_px, gap)
        if cut is None:
            continue
        report.cuts += 1
        before, after = values[i], values[i + 1]
        for k in inside.tolist():
            frame, off = out[k]
            if frame.pose is None:
                continue
            v = before if k < cut else after
            pose = replace(frame.pose, heading_deg=float(v[3] % 360.0), pitch_deg=float(min(max(v[4], 0.0), 90.0)))
            out[k] = (replace(frame, pose=pose), off)
    return out


def _find_cut(conts: dict[int, tuple[int, float]], centres: Callable[[int], NDArray],
              compare: Callable[[int, int], tuple[float, float]], n_frames: int, settings: ViewCutSettings,
              still_px: float, gap: int = _LOOKAHEAD) -> int | None:
    """The frame of an interval where the view jumped, or None.

    conts: each candidate frame's previous frame with boxes and its continuity with it; compare(j, k): frames j
    and k's (continuity, pan); gap: how many frames a jump's blur may empty (the previous frame with boxes was
    looked for that far back). A candidate continues at most max_continuity of that frame; the new view shows
    within gap frames of that frame (blur through a whole sweep empties many more); the frame with boxes after
    the candidate does not continue the earlier frame either (else it is a dropout); and one side of it is a
    steady view: the mean continuity of the _SIDE frame pairs just before it, or of those just after it (pairs
    with a frame of fewer than two boxes, as blur leaves, do not count), is at least cut_margin above the
    candidate's (a view of false positives alone continues nothing, anywhere), and still: its median pan (`pan`)
    at most still_px (a smooth sweep's frames continue each other too, shifted). Of the candidates that qualify,
    the one with the steadiest side."""

    def steady(js: range) -> float:
        # pairs of frames with two boxes or more each: their continuity and pan
        pairs = [compare(j - 1, j) for j in js
                 if 1 <= j < n_frames and min(len(centres(j - 1)), len(centres(j))) >= 2]
        if not pairs:
            return math.nan
        if float(np.median([p for _, p in pairs])) > still_px:
            return math.nan  # the view pans through the interval: a turn, not a still view beside a cut
        return float(np.mean([c for c, _ in pairs]))

    best, best_side = None, -math.inf
    for cut, (prev, c) in conts.items():
        if not c <= settings.max_continuity:
            continue
        after = next((j for j in range(cut + 1, min(cut + 1 + gap, n_frames)) if len(centres(j))), None)
        if after is None:
            if not len(centres(cut)):
                continue  # no view after it for a while: blur through a sweep, not a jump's few frames
        elif compare(prev, after)[0] > settings.max_continuity:
            continue  # the view goes on after it: a dropout, not a jump
        elif not len(centres(cut)) and after - prev > gap + 1:
            continue  # the old view's last boxes and the new view's first further apart than a jump's blur
        side = np.nanmax([steady(range(prev - _SIDE + 1, prev + 1)), steady(range(cut + 1, cut + 1 + _SIDE)),
                          -math.inf])
        if side >= c + settings.cut_margin and side > best_side:
            best, best_side = cut, float(side)
    return best

"""`uavmm tune`: fit the memory map's parameters and the size filter on an annotated set, under a rule of evidence.

The paper tuned its memory-map parameters on validation sets; this does the same for a user's own flights. Two
choices are made, each judged by the same rule and each reported as acted or stood down:

1. The size filter: fitted from the ground-truth boxes (`agent.size_filter_fit`); its bands replace those of the
   starting filter (the built-in priors, or the `--config` file's) for the classes it fitted, the others keep theirs.
2. The memory-map settings: a coordinate search over a small grid of each (evidence per second, forgetting
   half-life, Gaussian radius, boost weight; values relative to the defaults, so it adapts to any frame rate)
   maximising AP50 (pycocotools' interpolation), starting from the defaults (or `--config`).

The rule of evidence: a move (each search step, the filter, the final result) is taken only when its AP50 gain is
positive, at least ``min_gain`` points and at least Z = 2 standard deviations of the paired block-bootstrap
distribution of the gain. The bootstrap resamples time blocks (BLOCK_S = 2 s of one video: four default half-lives
of the memory, so a block's evidence barely reaches the next; frames 33 ms apart are one observation, not thirty),
and a set of fewer than MIN_UNITS = 8 blocks has no noise estimate worth the name: the choice stands down.

With two or more videos the choice is also made on half of them (videos[0::2], the size filter fitted on those
alone) and must carry over to the others; one video of at least 2 x MIN_UNITS blocks is split in time instead
(first half / second half). The held-out gain confirms a choice already made at Z = 2, on half the data: it must
be positive, at least ``min_gain`` and at least Z_HELD_OUT = 1 standard deviation of its own bootstrap (2 sd there
threw away a real gain, +0.63 +- 0.43 held out and +1.5 on an independent simulated set of 7,743 boxes; a choice
with no real effect still fails 1 sd about 5 times in 6). Where no held-out check can test a choice, its in-sample
gain must reach Z_UNCHECKED = 3 standard deviations. A choice that stands down keeps what it started from, and the
report says why, with the blocks and ground-truth boxes behind it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.boost import results_to_coco, run_pipeline
from agent.coco_metrics import _evaluated, load_images
from agent.dataset import Candidates, Dataset, PoseProblem, iter_video_frames
from agent.params_file import make_params
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.size_filter_fit import fit_from_dataset
from shared.geo import Camera

__all__ = ["BLOCK_S", "MIN_UNITS", "SEARCH_SPACE", "Z", "Z_HELD_OUT", "Z_UNCHECKED", "Evidence", "TuneResult", "ap50",
           "decide", "judge", "tune"]

log = logging.getLogger(__name__)

#: (setting, factors of the default value tried). Memory settings are in MemoryMapConfig.
SEARCH_SPACE: tuple[tuple[str, tuple[float, ...]], ...] = (
    ("gain_per_s", (0.25, 0.5, 1.0, 2.0, 4.0)),
    ("half_life_s", (0.25, 0.5, 1.0, 2.0, 4.0)),
    ("radius_m", (0.5, 0.75, 1.0, 1.5)),
    ("boost_weight", (0.5, 1.0, 2.0)),
)
_MEMORY_SETTINGS = {f.name for f in dataclasses.fields(PipelineConfig().memory)}

#: The rule of evidence (module docstring): resampling unit, fewest units, gain in bootstrap sd.
BLOCK_S = 2.0
MIN_UNITS = 8
Z = 2.0
Z_HELD_OUT = 1.0
Z_UNCHECKED = 3.0
RESAMPLES = 400
_RECALL_THRESHOLDS = np.linspace(0.0, 1.0, 101)  # pycocotools' recThrs
_ROWS_AT_ONCE = 50  # bootstrap rows per pass of the AP computation (memory: rows x detections floats)


@dataclass(frozen=True, slots=True)
class TuneResult:
    """What `tune` found: the config, the size filter to write (None: built-in priors) and the report."""

    config: PipelineConfig
    size_filter: SizeFilter | None
    report: dict[str, Any]

    def params(self) -> dict[str, Any]:
        """The parameters file (agent.params_file) of this result."""
        return make_params(_settings_of(self.config), self.size_filter, self.report)


@dataclass(frozen=True, slots=True)
class Evidence:
    """One choice's evidence: its AP50 gain (points), the gain's bootstrap sd, the time blocks and ground-truth
    boxes it rests on, the gain the rule asked for and whether it was met (``acted``); ``why`` says it in words."""

    gain: float
    sd: float
    units: int
    boxes: int
    needed: float
    acted: bool
    why: str

    def to_report(self) -> dict[str, Any]:
        def r(x: float) -> float | None:
            return round(x, 2) if math.isfinite(x) else None
        return {"gain": r(self.gain), "sd": r(self.sd), "needed": r(self.needed), "blocks": self.units,
                "boxes": self.boxes, "acted": self.acted, "why": self.why}


def judge(gain: float, boot_gains: NDArray[np.float64], units: int, boxes: int, *, z: float,
          min_gain: float) -> Evidence:
    """The rule of evidence on one move: gain (AP50 points) of the move on the set, boot_gains (R,) its gain on R
    block-bootstrap resamples of the set (NaN rows ignored); units: time blocks, boxes: ground-truth boxes. Acts when
    units >= MIN_UNITS and gain > 0, >= min_gain and >= z * sd."""
    if units < MIN_UNITS:
        return Evidence(gain, math.nan, units, boxes, math.nan, False,
                        f"too little data: {units} time block(s) of {BLOCK_S:g} s, {boxes} boxes (needs "
                        f"{MIN_UNITS} blocks)")
    finite = boot_gains[np.isfinite(boot_gains)]
    sd = float(np.std(finite, ddof=1)) if len(finite) > 1 else math.nan
    needed = max(min_gain, z * sd) if math.isfinite(sd) else math.inf
    acted = gain > 0 and gain >= needed
    sign = "beats" if acted else "does not beat"
    why = (f"gain {gain:+.2f} AP50 {sign} {z:g} sd = {z * sd:.2f} (floor {min_gain:g}) on {boxes} boxes, "
           f"{units} blocks")
    return Evidence(gain, sd, units, boxes, needed, acted, why)


def decide(in_sample: Evidence, check_moved: bool, held: Evidence | None, no_check: str | None) -> tuple[bool, str]:
    """Whether a choice is applied, and why. in_sample: its evidence on the whole set (judged at Z); check_moved:
    whether the same choice made on the tuning part moved; held: that move's evidence on the held-out part (judged
    at Z_HELD_OUT; None when it did not move or there is no check); no_check: why there is no held-out check (None
    when there is one). Applied when it passed in sample and either carried over to the held-out part or, with
    nothing held out to test it, its in-sample gain reaches Z_UNCHECKED sd."""
    if not in_sample.acted:
        return False, f"stood down: {in_sample.why}"
    if no_check is None and check_moved and held is not None:
        if held.acted:
            return True, f"acted: {in_sample.why}; carried over to the held-out part ({held.why})"
        return False, f"stood down: the choice made on the tuning part did not carry over ({held.why})"
    reason = no_check or "the choice made on the tuning part alone stood down"
    strong = in_sample.gain >= Z_UNCHECKED * in_sample.sd
    verdict = "reaches" if strong else "is below"
    text = f"no held-out check ({reason}): in sample the gain {in_sample.gain:+.2f} {verdict} {Z_UNCHECKED:g} sd = " \
           f"{Z_UNCHECKED * in_sample.sd:.2f} ({in_sample.boxes} boxes, {in_sample.units} blocks)"
    return strong, f"{'acted' if strong else 'stood down'}: {text}"


def _settings_of(config: PipelineConfig) -> dict[str, Any]:
    """The searched settings of config, as a pipeline config file holds them."""
    memory = {name: getattr(config.memory, name) for name, _ in SEARCH_SPACE if name in _MEMORY_SETTINGS}
    flat = {name: getattr(config, name) for name, _ in SEARCH_SPACE if name not in _MEMORY_SETTINGS}
    return {"memory": memory, **flat}


def _with(config: PipelineConfig, name: str, value: float) -> PipelineConfig:
    change: dict[str, Any] = {name: value}
    if name in _MEMORY_SETTINGS:
        return dataclasses.replace(config, memory=dataclasses.replace(config.memory, **change))
    return dataclasses.replace(config, **change)


def _value(config: PipelineConfig, name: str) -> float:
    return float(getattr(config.memory, name) if name in _MEMORY_SETTINGS else getattr(config, name))


@dataclass(frozen=True, slots=True)
class _Dets:
    """One run's detections as pycocotools matched them (IoU 0.5, all areas, 100 per image), per category in its
    ranking order: image index (D,) int, true positive (D,) bool, counted false positive (D,) bool; and gt (C, I)
    the counted ground-truth boxes per category and image."""

    per_class: tuple[tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]], ...]
    gt: NDArray[np.float64]


def ap50(dets: _Dets, weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """AP50 in percent for each row of weights (R, I): image i counted weights[r, i] times (0 leaves it out; a row
    of ones is pycocotools' AP50: 101-point interpolated precision, mean over the categories with ground truth).
    Returns (R,); 0 for a row without any ground truth."""
    rows = weights.shape[0]
    total, classes = np.zeros(rows), np.zeros(rows)
    for (image, tp, fp), gt in zip(dets.per_class, dets.gt, strict=True):
        npig = weights @ gt
        present = npig > 0
        q = np.zeros(rows)
        n = len(image)
        for lo in range(0, rows if n else 0, _ROWS_AT_ONCE):
            w = weights[lo:lo + _ROWS_AT_ONCE][:, image]
            tps, fps = np.cumsum(w * tp, axis=1), np.cumsum(w * fp, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                recall = tps / npig[lo:lo + _ROWS_AT_ONCE, None]
            precision = tps / (fps + tps + np.spacing(1))
            envelope = np.maximum.accumulate(precision[:, ::-1], axis=1)[:, ::-1]
            for k in range(len(w)):
                if present[lo + k]:
                    at = np.searchsorted(recall[k], _RECALL_THRESHOLDS, side="left")
                    q[lo + k] = np.where(at < n, envelope[k, np.minimum(at, n - 1)], 0.0).mean()
        total += np.where(present, q, 0.0)
        classes += present
    return np.divide(100.0 * total, classes, out=np.zeros(rows), where=classes > 0)


@dataclass(frozen=True, slots=True)
class _Part:
    """Scored images of a scorer: mask (I,) bool, their time blocks (units) and boxes, and weights (RESAMPLES, I)
    the block-bootstrap counts of each image (0 outside the part)."""

    name: str
    mask: NDArray[np.bool_]
    units: int
    boxes: int
    weights: NDArray[np.float64]


class _Scorer:
    """AP50 (percent) of configs on a set of videos: one pipeline run per (config, size filter), cached; parts of
    its images are scored from the same runs."""

    def __init__(self, dataset: Dataset, candidates: Candidates, camera: Camera, video_ids: list[int],
                 times: dict[int, float] | None = None) -> None:
        self.dataset, self.candidates, self.camera, self.video_ids = dataset, candidates, camera, video_ids
        self.image_ids = [image.id for v in video_ids for image in dataset.videos[v]]
        self._index = {image_id: i for i, image_id in enumerate(self.image_ids)}
        self.gt = load_images(dataset.coco)
        self._cat_ids = sorted(int(c["id"]) for c in self.gt.get("categories") or [])
        gt = np.zeros((len(self._cat_ids), len(self.image_ids)))
        cat_index = {c: k for k, c in enumerate(self._cat_ids)}
        for a in self.gt["annotations"]:  # pycocotools' counted boxes: not crowd, area within 'all'
            i, k = self._index.get(int(a["image_id"])), cat_index.get(int(a["category_id"]))
            area = a["area"] if "area" in a else float(a["bbox"][2]) * float(a["bbox"][3])
            if i is not None and k is not None and not a.get("iscrowd", 0) and 0 <= area <= 1e10:
                gt[k, i] += 1
        self._gt = gt
        times = times or {}
        blocks = np.zeros(len(self.image_ids), np.int64)
        for n, v in enumerate(video_ids):
            ts = [times.get(image.id, 0.0) for image in dataset.videos[v]]
            for image, t in zip(dataset.videos[v], ts, strict=True):
                blocks[self._index[image.id]] = n * 10**6 + int((t - ts[0]) // BLOCK_S)
        self.blocks = blocks
        self._dets: dict[tuple[PipelineConfig, int], _Dets] = {}
        self._filters: list[SizeFilter | None] = []  # kept alive: the cache is keyed by their id
        self._ap: dict[tuple[PipelineConfig, int, str, bool], NDArray[np.float64]] = {}
        self._parts: dict[str, _Part] = {}
        self.runs = 0

    def part(self, name: str, mask: NDArray[np.bool_] | None = None) -> _Part:
        """The part of the images in mask (default all), its blocks, boxes and bootstrap weights (fixed seed: every
        config is scored on the same resamples, so gains are paired); made once per name."""
        if name in self._parts:
            return self._parts[name]
        mask = np.ones(len(self.image_ids), bool) if mask is None else mask
        labels, unit_of = np.unique(self.blocks[mask], return_inverse=True)
        units = len(labels)
        counts = np.zeros((RESAMPLES, units))
        if units:
            picks = np.random.default_rng(0).integers(0, units, size=(RESAMPLES, units))
            np.add.at(counts, (np.arange(RESAMPLES)[:, None], picks), 1.0)
        weights = np.zeros((RESAMPLES, len(self.image_ids)))
        weights[:, mask] = counts[:, unit_of]
        self._parts[name] = _Part(name, mask, units, int(self._gt[:, mask].sum()), weights)
        return self._parts[name]

    def _run(self, config: PipelineConfig, size_filter: SizeFilter | None) -> _Dets:
        key = (config, id(size_filter))
        if key not in self._dets:
            results: list[dict[str, Any]] = []
            run_pipeline(self.dataset, self.candidates, self.camera, config, size_filter, video_ids=self.video_ids,
                         on_frame=lambda frame, res: results.extend(results_to_coco(frame.image.id, res)))
            self._filters.append(size_filter)
            self._dets[key] = self._matched(results)
            self.runs += 1
        return self._dets[key]

    def _matched(self, results: list[dict[str, Any]]) -> _Dets:
        """pycocotools' per-image matching of results, gathered per category in its ranking order (score, then
        image id, then rank in the image; a stable sort as its accumulate does)."""
        per_class: list[tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]] = []
        empty = (np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, bool))
        ids = sorted(self.image_ids)
        results = [dict(r) for r in results]
        ev = _evaluated(self.gt, results, ids) if results and ids else None
        for k in range(len(self._cat_ids)):
            if ev is None:
                per_class.append(empty)
                continue
            n_img, n_area = len(ev.params.imgIds), len(ev.params.areaRng)
            image, score, tp, fp = [], [], [], []
            for i, image_id in enumerate(ev.params.imgIds):
                e = ev.evalImgs[k * n_area * n_img + i]  # area 'all' is the first range
                if e is None or not len(e["dtScores"]):
                    continue
                matched, ignored = e["dtMatches"][0] != 0, e["dtIgnore"][0].astype(bool)
                image += [self._index[int(image_id)]] * len(matched)
                score += list(e["dtScores"])
                tp += list(matched & ~ignored)
                fp += list(~matched & ~ignored)
            order = np.argsort(-np.asarray(score, np.float64), kind="mergesort")
            per_class.append((np.asarray(image, np.int64)[order], np.asarray(tp, bool)[order],
                              np.asarray(fp, bool)[order]))
        return _Dets(tuple(per_class), self._gt)

    def ap(self, config: PipelineConfig, size_filter: SizeFilter | None, part: _Part, *,
           resampled: bool = False) -> NDArray[np.float64]:
        """AP50 of config on the part: (1,) as scored, or (RESAMPLES,) on its bootstrap resamples."""
        key = (config, id(size_filter), part.name, resampled)
        if key not in self._ap:
            weights = part.weights if resampled else part.mask[None, :].astype(np.float64)
            self._ap[key] = ap50(self._run(config, size_filter), weights)
        return self._ap[key]

    def evidence(self, part: _Part, new: tuple[PipelineConfig, SizeFilter | None],
                 old: tuple[PipelineConfig, SizeFilter | None], *, z: float, min_gain: float) -> Evidence:
        """The rule of evidence on moving from old to new (config, size filter) on the part."""
        gain = float(self.ap(*new, part)[0] - self.ap(*old, part)[0])
        if part.units < MIN_UNITS or gain <= 0 or gain < min_gain:
            boot = np.full(RESAMPLES, np.nan)  # no move either way: spare the bootstrap
            if part.units >= MIN_UNITS:
                return Evidence(gain, math.nan, part.units, part.boxes, min_gain, False,
                                f"gain {gain:+.2f} AP50 below the floor {min_gain:g} ({part.boxes} boxes, "
                                f"{part.units} blocks)")
        else:
            boot = self.ap(*new, part, resampled=True) - self.ap(*old, part, resampled=True)
        return judge(gain, boot, part.units, part.boxes, z=z, min_gain=min_gain)


def _search(scorer: _Scorer, part: _Part, start: PipelineConfig, size_filter: SizeFilter | None, *, min_gain: float,
            passes: int, progress: Callable[[str], None] | None,
            label: str = "") -> tuple[PipelineConfig, list[dict[str, Any]], str]:
    """Coordinate search over SEARCH_SPACE from start on the part; a step is taken only when the rule of evidence
    (at Z) holds for it. Returns (best config, the steps taken with their evidence, the best try not taken)."""
    defaults = PipelineConfig()
    best = start
    steps: list[dict[str, Any]] = []
    closest, closest_gain = "none tried", -math.inf
    for pass_no in range(passes):
        moved = False
        for name, factors in SEARCH_SPACE:
            default = _value(defaults, name)
            for factor in factors:
                value = round(default * factor, 6)
                if math.isclose(value, _value(best, name)):
                    continue
                candidate = _with(best, name, value)
                ev = scorer.evidence(part, (candidate, size_filter), (best, size_filter), z=Z, min_gain=min_gain)
                ap, was = _ap_of(scorer, candidate, size_filter, part), _ap_of(scorer, best, size_filter, part)
                if progress:
                    needs = f" (needs {ev.needed:+.2f})" if ev.gain > 0 and math.isfinite(ev.needed) else ""
                    progress(f"{label}pass {pass_no + 1}: {name}={value:g} AP50 {ap:.2f} (best {was:.2f}){needs}"
                             f"{' taken' if ev.acted else ''}")
                if ev.acted:
                    steps.append({"setting": name, "value": value, "AP50": round(ap, 2), "was": round(was, 2),
                                  "evidence": ev.to_report()})
                    best, moved = candidate, True
                elif ev.gain > closest_gain:
                    closest, closest_gain = f"the best try not taken, {name}={value:g}: {ev.why}", ev.gain
        if not moved:
            break
    return best, steps, closest


def _ap_of(scorer: _Scorer, config: PipelineConfig, size_filter: SizeFilter | None, part: _Part) -> float:
    """AP50 (percent) of config on the part, as scored."""
    return float(scorer.ap(config, size_filter, part)[0])


@dataclass(frozen=True, slots=True)
class _Split:
    """The held-out check's two parts: tuned on one, scored on the other (each with its scorer)."""

    tune_scorer: _Scorer
    tune_part: _Part
    held_scorer: _Scorer
    held_part: _Part
    tune_image_ids: frozenset[int]
    report: dict[str, Any]
    no_check: str | None  # why the check cannot judge (a part under MIN_UNITS blocks), else None


def _split(dataset: Dataset, candidates: Candidates, camera: Camera, scorer: _Scorer,
           times: dict[int, float]) -> _Split | None:
    """Two or more videos: videos[0::2] against videos[1::2]; one video: the first half of its time blocks against
    the second half (one scorer: the pipeline runs the whole flight, the parts score their own frames)."""
    videos = scorer.video_ids
    if len(videos) >= 2:
        tune_on, score_on = list(videos[0::2]), list(videos[1::2])
        tune_scorer = _Scorer(dataset, candidates, camera, tune_on, times)
        held_scorer = _Scorer(dataset, candidates, camera, score_on, times)
        tune_part, held_part = tune_scorer.part("tune"), held_scorer.part("held")
        report: dict[str, Any] = {"split": "videos", "tuned_on_videos": tune_on, "scored_on_videos": score_on}
        tune_ids = frozenset(tune_scorer.image_ids)
    else:
        labels = np.unique(scorer.blocks)
        if len(labels) < 2:
            return None
        first = scorer.blocks < labels[(len(labels) + 1) // 2]
        tune_part, held_part = scorer.part("tune", first), scorer.part("held", ~first)
        tune_scorer = held_scorer = scorer
        seconds = float(labels[(len(labels) + 1) // 2]) * BLOCK_S  # one video: its labels are its block numbers
        report = {"split": "time", "tuned_on": f"video {videos[0]}, its first {seconds:g} s",
                  "scored_on": f"video {videos[0]} after {seconds:g} s",
                  "tuned_on_videos": list(videos), "scored_on_videos": list(videos)}
        tune_ids = frozenset(i for i, m in zip(scorer.image_ids, first, strict=True) if m)
    report.update({"tune_blocks": tune_part.units, "tune_boxes": tune_part.boxes,
                   "held_blocks": held_part.units, "held_boxes": held_part.boxes})
    small = min(tune_part.units, held_part.units)
    no_check = None if small >= MIN_UNITS else f"a part has {small} time blocks, needs {MIN_UNITS}"
    return _Split(tune_scorer, tune_part, held_scorer, held_part, tune_ids, report, no_check)


def _with_priors(fitted: SizeFilter, start: SizeFilter) -> SizeFilter:
    """The fitted bands over the start filter's: fitted classes take theirs, the others keep the start's, and the
    start's k (a `fit-size-filter --k 2` file stays at 2 for the classes the fit did not touch)."""
    return SizeFilter({**start.bands, **fitted.bands}, start.k)


def _tune_filter(images_path: str | Path, camera_path: str | Path, base: PipelineConfig, start: SizeFilter,
                 start_name: str, scorer: _Scorer, everything: _Part, split: _Split | None, no_check: str | None,
                 min_gain: float) -> tuple[SizeFilter, SizeFilter, dict[str, Any]]:
    """Fit the size filter and judge it against start: (filter for the result, filter for the held-out check's
    tuning part, report)."""
    report: dict[str, Any] = {"start": start_name, "used": start_name}
    try:
        fitted, per_class = fit_from_dataset(images_path, camera_path, anchor=base.anchor, terrain=base.terrain)
    except ValueError as exc:
        report.update({"fit": f"not fitted: {exc}", "decision": "stood down: nothing fitted"})
        return start, start, report
    candidate = _with_priors(fitted, start)
    ev = scorer.evidence(everything, (base, candidate), (base, start), z=Z, min_gain=min_gain)
    report.update({"fit": per_class, "AP50_start_filter": round(_ap_of(scorer, base, start, everything), 2),
                   "AP50_fitted": round(_ap_of(scorer, base, candidate, everything), 2), "evidence": ev.to_report()})
    report["AP50_builtin" if start_name == "built-in priors" else "AP50_start_file"] = report["AP50_start_filter"]
    check_filter, moved, held = start, False, None
    if split is not None:
        try:  # fitted on the tuning part alone: the held-out part's ground truth stays out of it
            part_fit, _ = fit_from_dataset(images_path, camera_path, anchor=base.anchor, terrain=base.terrain,
                                           image_ids=split.tune_image_ids)
        except ValueError as exc:
            report["holdout"] = {"fit": f"not fitted on the tuning part: {exc}"}
        else:
            part_candidate = _with_priors(part_fit, start)
            part_ev = split.tune_scorer.evidence(split.tune_part, (base, part_candidate), (base, start), z=Z,
                                                 min_gain=min_gain)
            moved = part_ev.acted
            report["holdout"] = {"tuning_part": part_ev.to_report()}
            if moved:
                check_filter = part_candidate
                held = split.held_scorer.evidence(split.held_part, (base, part_candidate), (base, start),
                                                  z=Z_HELD_OUT, min_gain=min_gain)
                report["holdout"]["held_out"] = held.to_report()
    acted, why = decide(ev, moved, held, no_check)
    report["decision"] = why
    if not acted:
        return start, check_filter, report
    fitted_classes = sorted(fitted.bands)
    others = sorted(set(start.bands) - set(fitted.bands))
    report["used"] = f"fitted ({', '.join(fitted_classes)}); {start_name} for {', '.join(others) or 'no other class'}"
    return candidate, check_filter, report


def _check_inputs(dataset: Dataset, candidates: Candidates, camera: Camera, source: str,
                  candidates_source: str) -> dict[int, float]:
    """Refuse what cannot be tuned on (ValueError naming the file); returns each image's frame time (s)."""
    annotations = dataset.coco.get("annotations")
    if not isinstance(annotations, list) or not annotations:
        raise ValueError(f"{source}: no 'annotations': tuning needs ground-truth boxes")
    problems: list[PoseProblem] = []
    times: dict[int, float] = {}
    with_pose = 0
    for v in dataset.videos:
        for frame in iter_video_frames(dataset, camera, v, problems=problems):
            times[frame.image.id] = frame.t
            with_pose += frame.pose is not None
    if not with_pose:
        first = f" (first problem: {problems[0]})" if problems else ""
        raise ValueError(f"{source}: no frame has usable meta (GPS, altitude, gimbal pitch, heading): the memory "
                         f"map works on the ground and cannot be tuned without telemetry{first}")
    counts = {image_id: len(scores) for image_id, (_, scores, _) in candidates.by_image.items()}
    total = sum(counts.values())
    if not total:
        raise ValueError(f"{candidates_source}: no candidates (an empty list, or every entry skipped): tuning needs "
                         "the detector's boxes on the annotated frames")
    annotated = {int(a["image_id"]) for a in load_images(dataset.coco)["annotations"]}
    if not any(counts.get(image_id, 0) for image_id in annotated):
        raise ValueError(f"{candidates_source}: none of its {total} candidates is on an annotated image of {source}: "
                         "nothing to tune on (do the files belong together?)")
    return times


def tune(images_path: str | Path, candidates_path: str | Path, camera_path: str | Path, *,
         base: PipelineConfig | None = None, start_filter: SizeFilter | None = None, fit_size_filter: bool = True,
         min_gain: float = 0.2, passes: int = 2, holdout: bool = True,
         progress: Callable[[str], None] | None = None) -> TuneResult:
    """Fit the size filter and search the memory-map settings on an annotated dataset, under the rule of evidence.

    base: the starting config (default: the built-in defaults; `--config` of the command); its terrain (`--dem`)
    is the ground of every run, the size filter's fits and the held-out check included. start_filter: the size
    filter to start from (None: the built-in priors; a `--config` PARAMS.json's), kept and written unless the fit
    beats it. holdout: judge every choice also on a held-out part (module docstring). What is written stands
    down to the start (config, filter) where the evidence is weak; ``report`` says which choice acted and why.
    ValueError for a dataset without annotations or usable meta, and for candidates that are empty or on no
    annotated image, naming the file.
    """
    dataset = Dataset.load(images_path)
    candidates = Candidates.load(candidates_path, dataset)
    camera = Camera.from_spec(camera_path)
    times = _check_inputs(dataset, candidates, camera, str(images_path), str(candidates_path))
    base = base or PipelineConfig()
    start = start_filter or SizeFilter.builtin()
    start_name = "built-in priors" if start_filter is None else "the --config file's"
    videos = sorted(dataset.videos)
    scorer = _Scorer(dataset, candidates, camera, videos, times)
    everything = scorer.part("all")
    split = _split(dataset, candidates, camera, scorer, times) if holdout else None
    no_check = "--no-holdout" if not holdout else (
        "one time block: nothing to hold out" if split is None else split.no_check)
    if fit_size_filter and base.use_size_filter:
        size_filter, check_filter, filter_report = _tune_filter(images_path, camera_path, base, start, start_name,
                                                                scorer, everything, split, no_check, min_gain)
    else:
        size_filter = check_filter = start
        why = "--no-size-filter-fit" if not fit_size_filter else "the size filter is off (use_size_filter false)"
        filter_report = {"start": start_name, "used": start_name, "decision": f"not fitted: {why}"}
    searched, steps, closest = _search(scorer, everything, base, size_filter, min_gain=min_gain, passes=passes,
                                       progress=progress)
    in_sample = scorer.evidence(everything, (searched, size_filter), (base, size_filter), z=Z, min_gain=min_gain)
    moved, held, holdout_report = False, None, None
    if split is not None:
        part_tuned, _, _ = _search(split.tune_scorer, split.tune_part, base, check_filter, min_gain=min_gain,
                                   passes=passes, progress=progress, label="held-out check: ")
        hs, hp = split.held_scorer, split.held_part
        holdout_report = {
            **split.report,
            "AP50_no_memory": round(_ap_of(hs, dataclasses.replace(base, use_memory=False), check_filter, hp), 2),
            "AP50_start": round(_ap_of(hs, base, check_filter, hp), 2),
            "AP50_tuned": round(_ap_of(hs, part_tuned, check_filter, hp), 2), "settings": _settings_of(part_tuned)}
        moved = part_tuned != base
        if moved:
            held = hs.evidence(hp, (part_tuned, check_filter), (base, check_filter), z=Z_HELD_OUT,
                               min_gain=min_gain)
            holdout_report["evidence"] = held.to_report()
    acted, why = decide(in_sample, moved, held, no_check) if searched != base else (
        False, f"stood down: no step beat its noise ({closest})")
    final = searched if acted else base

    def score(config: PipelineConfig) -> float:
        return round(_ap_of(scorer, config, size_filter, everything), 2)

    report: dict[str, Any] = {
        "images": str(images_path), "videos": len(videos), "images_scored": len(scorer.image_ids),
        "boxes": everything.boxes, "time_blocks": everything.units, "metric": "AP50 (pycocotools, percent)",
        "rule": {"z": Z, "z_held_out": Z_HELD_OUT, "z_without_held_out_check": Z_UNCHECKED, "min_gain": min_gain,
                 "block_s": BLOCK_S, "min_blocks": MIN_UNITS, "resamples": RESAMPLES},
        "size_filter": filter_report,
        "AP50_no_memory": score(dataclasses.replace(base, use_memory=False)), "AP50_start": score(base),
        "AP50_searched": score(searched), "AP50_tuned": score(final),
        "steps": steps, "searched_settings": _settings_of(searched), "settings": _settings_of(final),
        "settings_acted": acted, "settings_decision": why, "evidence": in_sample.to_report(),
        "no_held_out_check": no_check, "pipeline_runs": scorer.runs + (
            0 if split is None or split.tune_scorer is scorer else split.tune_scorer.runs + split.held_scorer.runs),
    }
    if holdout_report is not None:
        report["holdout"] = holdout_report
    written_filter = None if size_filter is start and start_filter is None else size_filter
    return TuneResult(final, written_filter, report)

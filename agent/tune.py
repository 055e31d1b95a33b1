"""`uavmm tune`: fit the memory map's parameters and the size filter on an annotated set.

The paper tuned its memory-map parameters on validation sets; this does the same for a user's own
flights. The size filter is fitted from the ground-truth boxes (`agent.size_filter_fit`) and kept only
when it scores at least as well as the built-in priors. Then a coordinate search over a small grid of
each parameter (evidence per second, forgetting half-life, Gaussian radius, boost weight; values
relative to the defaults, so it adapts to any frame rate) maximises AP50 (pycocotools), starting from
the defaults and moving only for a gain of at least ``min_gain`` AP50 points (a smaller one is noise on
one flight). With two or more videos a held-out check tunes on half of them and scores the other half,
so the report says whether the tuned values carry over.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent.boost import results_to_coco, run_pipeline
from agent.coco_metrics import coco_detection_metrics
from agent.dataset import Candidates, Dataset, iter_video_frames
from agent.params_file import make_params
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.size_filter_fit import fit_from_dataset
from shared.geo import Camera

__all__ = ["SEARCH_SPACE", "TuneResult", "tune"]

log = logging.getLogger(__name__)

#: (setting, factors of the default value tried). Memory settings are in MemoryMapConfig.
SEARCH_SPACE: tuple[tuple[str, tuple[float, ...]], ...] = (
    ("gain_per_s", (0.25, 0.5, 1.0, 2.0, 4.0)),
    ("half_life_s", (0.25, 0.5, 1.0, 2.0, 4.0)),
    ("radius_m", (0.5, 0.75, 1.0, 1.5)),
    ("boost_weight", (0.5, 1.0, 2.0)),
)
_MEMORY_SETTINGS = {f.name for f in dataclasses.fields(PipelineConfig().memory)}


@dataclass(frozen=True, slots=True)
class TuneResult:
    """What `tune` found: the config, the size filter kept (None: built-in priors) and the report."""

    config: PipelineConfig
    size_filter: SizeFilter | None
    report: dict[str, Any]

    def params(self) -> dict[str, Any]:
        """The parameters file (agent.params_file) of this result."""
        return make_params(_settings_of(self.config), self.size_filter, self.report)


def _settings_of(config: PipelineConfig) -> dict[str, Any]:
    """The searched settings of config, as a pipeline config file holds them."""
    memory = {name: getattr(config.memory, name) for name, _ in SEARCH_SPACE if name in _MEMORY_SETTINGS}
    flat = {name: getattr(config, name) for name, _ in SEARCH_SPACE if name not in _MEMORY_SETTINGS}
    return {"memory": memory, **flat}


def _with(config: PipelineConfig, name: str, value: float) -> PipelineConfig:
    if name in _MEMORY_SETTINGS:
        return dataclasses.replace(config, memory=dataclasses.replace(config.memory, **{name: value}))
    return dataclasses.replace(config, **{name: value})


def _value(config: PipelineConfig, name: str) -> float:
    return float(getattr(config.memory, name) if name in _MEMORY_SETTINGS else getattr(config, name))


class _Scorer:
    """AP50 (percent) of a config on a set of videos, cached per (config, size filter)."""

    def __init__(self, dataset: Dataset, candidates: Candidates, camera: Camera, video_ids: list[int]) -> None:
        self.dataset, self.candidates, self.camera, self.video_ids = dataset, candidates, camera, video_ids
        self.image_ids = [image.id for v in video_ids for image in dataset.videos[v]]
        self._cache: dict[tuple[PipelineConfig, int], float] = {}
        self.runs = 0

    def __call__(self, config: PipelineConfig, size_filter: SizeFilter | None) -> float:
        key = (config, id(size_filter))
        if key not in self._cache:
            results: list[dict[str, Any]] = []
            run_pipeline(self.dataset, self.candidates, self.camera, config, size_filter, video_ids=self.video_ids,
                         on_frame=lambda frame, res: results.extend(results_to_coco(frame.image.id, res)))
            metrics = coco_detection_metrics(self.dataset.coco, results, image_ids=self.image_ids)
            self._cache[key] = round(100.0 * metrics["AP50"], 2)
            self.runs += 1
        return self._cache[key]


def _search(score: Callable[[PipelineConfig], float], start: PipelineConfig, *, min_gain: float, passes: int,
            progress: Callable[[str], None] | None) -> tuple[PipelineConfig, float, list[dict[str, Any]]]:
    """Coordinate search over SEARCH_SPACE from start; returns (best config, its AP50, the steps taken)."""
    defaults = PipelineConfig()
    best, best_ap = start, score(start)
    steps: list[dict[str, Any]] = []
    for pass_no in range(passes):
        moved = False
        for name, factors in SEARCH_SPACE:
            default = _value(defaults, name)
            for factor in factors:
                value = round(default * factor, 6)
                if math.isclose(value, _value(best, name)):
                    continue
                candidate = _with(best, name, value)
                ap = score(candidate)
                if progress:
                    progress(f"pass {pass_no + 1}: {name}={value:g} AP50 {ap:.2f} (best {best_ap:.2f})")
                if ap >= best_ap + min_gain:
                    steps.append({"setting": name, "value": value, "AP50": ap, "was": best_ap})
                    best, best_ap, moved = candidate, ap, True
        if not moved:
            break
    return best, best_ap, steps


def _check_inputs(dataset: Dataset, camera: Camera, source: str) -> None:
    annotations = dataset.coco.get("annotations")
    if not isinstance(annotations, list) or not annotations:
        raise ValueError(f"{source}: no 'annotations': tuning needs ground-truth boxes")
    problems: list[str] = []
    with_pose = sum(frame.pose is not None for v in dataset.videos
                    for frame in iter_video_frames(dataset, camera, v, problems=problems))
    if not with_pose:
        first = f" (first problem: {problems[0]})" if problems else ""
        raise ValueError(f"{source}: no frame has usable meta (GPS, altitude, gimbal pitch, heading): the memory "
                         f"map works on the ground and cannot be tuned without telemetry{first}")


def tune(images_path: str | Path, candidates_path: str | Path, camera_path: str | Path, *,
         base: PipelineConfig | None = None, fit_size_filter: bool = True, min_gain: float = 0.2,
         passes: int = 2, holdout: bool = True,
         progress: Callable[[str], None] | None = None) -> TuneResult:
    """Fit the size filter and search the memory-map settings on an annotated dataset.

    base: the starting config (default: the built-in defaults; `--config` of the command); its terrain (`--dem`)
    is the ground of every run, the size filter's fit and the held-out check included. holdout: with
    two or more videos, also tune on the even-positioned videos and score the odd ones (reported as
    ``holdout``; the returned config is always tuned on every video). ValueError for a dataset without
    annotations or without any usable meta, naming the file.
    """
    dataset = Dataset.load(images_path)
    candidates = Candidates.load(candidates_path, dataset)
    camera = Camera.from_spec(camera_path)
    _check_inputs(dataset, camera, str(images_path))
    base = base or PipelineConfig()
    videos = sorted(dataset.videos)
    scorer = _Scorer(dataset, candidates, camera, videos)
    builtin = SizeFilter.builtin()
    size_filter: SizeFilter | None = None
    filter_report: dict[str, Any] = {"used": "built-in priors"}
    if fit_size_filter and base.use_size_filter:
        try:
            fitted, per_class = fit_from_dataset(images_path, camera_path, anchor=base.anchor, terrain=base.terrain)
        except ValueError as exc:
            filter_report["fit"] = f"not fitted: {exc}"
        else:
            ap_builtin, ap_fitted = scorer(base, builtin), scorer(base, fitted)
            filter_report.update({"fit": per_class, "AP50_builtin": ap_builtin, "AP50_fitted": ap_fitted})
            if ap_fitted >= ap_builtin:
                size_filter, filter_report["used"] = fitted, "fitted"
    chosen_filter = size_filter or builtin
    baseline_ap = scorer(dataclasses.replace(base, use_memory=False), chosen_filter)
    start_ap = scorer(base, chosen_filter)
    best, best_ap, steps = _search(lambda c: scorer(c, chosen_filter), base, min_gain=min_gain, passes=passes,
                                   progress=progress)
    report: dict[str, Any] = {
        "images": str(images_path), "videos": len(videos), "images_scored": len(scorer.image_ids),
        "metric": "AP50 (pycocotools, percent)", "size_filter": filter_report,
        "AP50_no_memory": baseline_ap, "AP50_start": start_ap, "AP50_tuned": best_ap, "steps": steps,
        "settings": _settings_of(best), "pipeline_runs": scorer.runs,
    }
    if holdout and len(videos) >= 2:
        report["holdout"] = _holdout(dataset, candidates, camera, videos, base, chosen_filter, min_gain, passes)
    return TuneResult(best, size_filter, report)


def _holdout(dataset: Dataset, candidates: Candidates, camera: Camera, videos: Sequence[int], base: PipelineConfig,
             size_filter: SizeFilter, min_gain: float, passes: int) -> dict[str, Any]:
    """Tune on videos[0::2], score on videos[1::2]: does the tuning carry over to another flight?"""
    tune_on, score_on = list(videos[0::2]), list(videos[1::2])
    tuner = _Scorer(dataset, candidates, camera, tune_on)
    tuned, _, _ = _search(lambda c: tuner(c, size_filter), base, min_gain=min_gain, passes=passes, progress=None)
    held = _Scorer(dataset, candidates, camera, score_on)
    return {
        "tuned_on_videos": tune_on, "scored_on_videos": score_on,
        "AP50_no_memory": held(dataclasses.replace(base, use_memory=False), size_filter),
        "AP50_start": held(base, size_filter), "AP50_tuned": held(tuned, size_filter),
        "settings": _settings_of(tuned),
    }

"""`uavmm eval`: the paper's tables on simulated data, baseline beside memory map.

Generates (or reuses) datasets per scenario and seed, runs the pipelines in-process and scores them
with the standard tools (pycocotools for detection), then writes JSON and Markdown reports.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.boost import results_to_coco, run_pipeline
from agent.dataset import Candidates, Dataset
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from shared.files import listed_names, write_chunks_atomic
from shared.geo import Camera

log = logging.getLogger(__name__)

#: The operating point: the baseline's precision at this score threshold (a deployment's output; the
#: paper's "recall after NMS", 86-88 % for its baselines). Every variant's recall is read off its own
#: precision-recall curve at that same precision, so boosting cannot buy recall with precision.
OPERATING_THRESHOLD = 0.25


@dataclass(frozen=True, slots=True)
class Variant:
    """A named pipeline configuration to evaluate."""

    name: str
    config: PipelineConfig


def default_variants() -> list[Variant]:
    base = PipelineConfig()
    return [Variant("baseline", dataclasses.replace(base, use_memory=False)), Variant("memory map", base)]


def ablation_variants() -> list[Variant]:
    """Single-parameter sweeps around the defaults, plus the filter and boost switched off."""
    base = PipelineConfig()
    mem = base.memory
    paper_memory = dataclasses.replace(mem, radius_m=6.0, stamp="sum", gain_per_s=0.6)
    out = [
        Variant("paper rule (c + p, every box adds, r 6 m)",
                dataclasses.replace(base, boost_mode="add", memory=paper_memory, fragment_iou=0.0)),
        Variant("baseline, no size filter", dataclasses.replace(base, use_memory=False, use_size_filter=False)),
        Variant("memory map, no size filter", dataclasses.replace(base, use_size_filter=False)),
        Variant("memory map, anchor=center", dataclasses.replace(base, anchor="center")),
        Variant("memory map, stamp=sum", dataclasses.replace(base, memory=dataclasses.replace(mem, stamp="sum"))),
        Variant("memory map, boost_mode=add", dataclasses.replace(base, boost_mode="add")),
        Variant("memory map, every box boosted (fragment_iou=0)", dataclasses.replace(base, fragment_iou=0.0)),
    ]
    for half_life in (0.25, 0.5, 2.0, 4.0):
        out.append(Variant(f"half_life_s={half_life}",
                           dataclasses.replace(base, memory=dataclasses.replace(mem, half_life_s=half_life))))
    for radius in (2.0, 6.0, 9.0):
        out.append(Variant(f"radius_m={radius}",
                           dataclasses.replace(base, memory=dataclasses.replace(mem, radius_m=radius))))
    for gain in (mem.gain_per_s / 4, mem.gain_per_s / 2, mem.gain_per_s * 2, mem.gain_per_s * 4):
        out.append(Variant(f"gain_per_s={gain:g}",
                           dataclasses.replace(base, memory=dataclasses.replace(mem, gain_per_s=gain))))
    for w in (0.5, 2.0):
        out.append(Variant(f"boost_weight={w}", dataclasses.replace(base, boost_weight=w)))
    return out


def ensure_dataset(scenario: str, seed: int, frames: int | None, noise_scale: float, cache_dir: Path) -> Path:
    """Path of a simulated dataset, generated once per (scenario, seed, frames, noise) and reused."""
    from sim.dataset import write_dataset

    tag = f"{scenario}-s{seed}-f{frames or 'default'}-n{noise_scale:g}"
    out = cache_dir / tag
    if not (out / "images.json").exists():
        write_dataset(scenario, out, seed=seed, frames=frames, noise_scale=noise_scale, progress=False)
    return out


def evaluate_detection(data_dir: Path, variants: Iterable[Variant], *,
                       size_filter: SizeFilter | None = None) -> dict[str, dict[str, Any]]:
    """AP50 / AR@100 (pycocotools), pre-NMS recall and pipeline FPS of each variant on one dataset."""
    from sim.metrics import (
        coco_detection_metrics,
        pr_curve,
        prenms_recall,
        recall_at_precision,
        threshold_at_precision,
    )

    dataset = Dataset.load(data_dir / "images.json")
    raw_candidates = json.loads((data_dir / "pre_nms.json").read_text())
    candidates = Candidates.from_list(raw_candidates, dataset, source=str(data_dir / "pre_nms.json"))
    camera = Camera.from_file(data_dir / "camera.json")
    recall = prenms_recall(dataset.coco, raw_candidates)
    out: dict[str, dict[str, Any]] = {}
    base_precision: float | None = None
    for variant in variants:
        results: list[dict[str, Any]] = []
        stats = run_pipeline(dataset, candidates, camera, variant.config, size_filter,
                             on_frame=lambda f, r, acc=results: acc.extend(results_to_coco(f.image.id, r)))
        metrics = coco_detection_metrics(dataset.coco, results)
        curve = pr_curve(dataset.coco, results)
        k = int(np.searchsorted(-curve["scores"], -OPERATING_THRESHOLD, side="right"))
        p_op = float(curve["precision"][k - 1]) if k else 1.0
        if base_precision is None:  # the first variant (the baseline) sets the operating precision
            base_precision = p_op
        ms = stats["pipeline_ms_per_frame"]
        # COCO AR@100 of what a deployment outputs: each variant's detections down to the score at which it
        # reaches the baseline's operating precision (AR over all candidates cannot move with re-scoring).
        s_op = threshold_at_precision(curve, base_precision)
        ar_op = coco_detection_metrics(dataset.coco, [r for r in results if r["score"] >= s_op])["AR100"]
        out[variant.name] = {
            "AP50": 100 * metrics["AP50"], "AR100": 100 * metrics["AR100"], "AR_op": 100 * ar_op,
            "P_op": 100 * base_precision, "R_op": 100 * recall_at_precision(curve, base_precision),
            "prenms_recall": 100 * recall, "pipeline_ms_per_frame": ms,
            "size_filtered": stats["size_filtered"], "candidates": stats["candidates"],
        }
    return out


#: Offset of the seed whose flight the fitted size filter is learnt from (never the scored flight).
FIT_SEED_OFFSET = 1000


def evaluate_fitted_filter(scenario: str, seed: int, frames: int | None, noise_scale: float, cache_dir: Path,
                           data_dir: Path) -> dict[str, dict[str, Any]]:
    """Baseline and memory map with the size filter fitted (`uavmm fit-size-filter`, `uavmm tune`) on another
    flight of the scenario (seed + FIT_SEED_OFFSET), scored on ``data_dir``: rows of `evaluate_detection`."""
    from agent.size_filter_fit import fit_from_dataset

    fit_dir = ensure_dataset(scenario, seed + FIT_SEED_OFFSET, frames, noise_scale, cache_dir)
    fitted, _ = fit_from_dataset(fit_dir / "images.json", fit_dir / "camera.json")
    base = PipelineConfig()
    variants = [Variant("baseline, fitted size filter", dataclasses.replace(base, use_memory=False)),
                Variant("memory map, fitted size filter", base)]
    return evaluate_detection(data_dir, variants, size_filter=fitted)


def size_filter_table(data_dir: Path, config: PipelineConfig | None = None,
                      size_filter: SizeFilter | None = None) -> dict[str, int]:
    """The paper's Table I: candidates the size filter removes, split into true and false positives.

    A removed candidate is a true positive when it overlaps a ground-truth box of its class in its
    image with IoU >= 0.5.
    """
    from agent.boxes import box_anchor_points
    from agent.dataset import iter_video_frames
    from agent.pipeline import DetectionPipeline
    from shared.geo import pixel_to_local

    config = config or PipelineConfig()
    dataset = Dataset.load(data_dir / "images.json")
    candidates = Candidates.load(data_dir / "pre_nms.json", dataset)
    camera = Camera.from_file(data_dir / "camera.json")
    gt: dict[int, list[tuple[int, list[float]]]] = {}
    for a in dataset.coco.get("annotations", []):
        gt.setdefault(a["image_id"], []).append((a["category_id"], a["bbox"]))
    counts = {"candidates": 0, "removed": 0, "removed_true_positives": 0, "removed_false_positives": 0}
    for video_id in dataset.videos:
        pipe = DetectionPipeline(camera, dataset.categories, config, size_filter=size_filter)
        frames = list(iter_video_frames(dataset, camera, video_id))
        # the filter as the pipeline applies it: its prior checked on (and centred on) the video's confident boxes
        pipe.prime((frame.pose, frame.camera, *candidates.get(frame.image.id)) for frame in frames)
        for frame in frames:
            boxes, _, cids = candidates.get(frame.image.id)
            counts["candidates"] += len(cids)
            if frame.pose is None or not len(cids):
                continue
            pipe.camera = frame.camera
            east, north, _ = pixel_to_local(box_anchor_points(boxes, config.anchor, frame.pose.pitch_deg),
                                            frame.camera, frame.pose, max_range_m=config.range_limit_m)
            removed = ~pipe.plausible(boxes, cids, east, north, frame.pose)
            if not removed.any():
                continue
            tp = np.zeros(int(removed.sum()), dtype=bool)
            rb, rc = boxes[removed], cids[removed]
            for cat, (x, y, w, h) in gt.get(frame.image.id, []):
                ix = np.clip(np.minimum(rb[:, 2], x + w) - np.maximum(rb[:, 0], x), 0, None)
                iy = np.clip(np.minimum(rb[:, 3], y + h) - np.maximum(rb[:, 1], y), 0, None)
                inter = ix * iy
                union = (rb[:, 2] - rb[:, 0]) * (rb[:, 3] - rb[:, 1]) + w * h - inter
                tp |= (rc == cat) & (inter >= 0.5 * union)
            counts["removed"] += len(tp)
            counts["removed_true_positives"] += int(tp.sum())
            counts["removed_false_positives"] += int((~tp).sum())
    return counts


def _mean_sd(values: list[float]) -> tuple[float, float]:
    return (statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0)


def run_eval(scenarios: list[str], seeds: list[int], *, frames: int | None = None,
             noise_scales: tuple[float, ...] = (1.0, 2.0), ablations: bool = False,
             out_dir: Path = Path("out/eval"), progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Evaluate every scenario x seed x noise level; returns the report dict (also written to out_dir)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / "data"
    variants = default_variants() + (ablation_variants() if ablations else [])
    rows: list[dict[str, Any]] = []
    size_filter: dict[str, dict[str, int]] = {}
    jobs = [(s, seed, k) for s in scenarios for k in noise_scales for seed in seeds]
    t0 = time.perf_counter()
    for i, (scenario, seed, noise) in enumerate(jobs):
        if progress:
            progress(f"[{i + 1}/{len(jobs)}] {scenario} seed={seed} noise x{noise:g}")
        data_dir = ensure_dataset(scenario, seed, frames, noise, cache)
        # Ablations only at the default noise, to keep the run short.
        vs = variants if noise == 1.0 else default_variants()
        for name, m in evaluate_detection(data_dir, vs).items():
            rows.append({"scenario": scenario, "seed": seed, "noise_scale": noise, "variant": name, **m})
        if noise == 1.0:  # the size filter `uavmm tune` fits, from another flight of the scenario
            for name, m in evaluate_fitted_filter(scenario, seed, frames, noise, cache, data_dir).items():
                rows.append({"scenario": scenario, "seed": seed, "noise_scale": noise, "variant": name, **m})
        if noise == noise_scales[0]:
            table = size_filter[scenario] = size_filter.get(scenario, {})
            for k, v in size_filter_table(data_dir).items():
                table[k] = table.get(k, 0) + v
    summary = summarise(rows)
    report = {"scenarios": scenarios, "seeds": seeds, "frames": frames, "noise_scales": list(noise_scales),
              "rows": rows, "summary": summary, "size_filter": size_filter,
              "seconds": round(time.perf_counter() - t0, 1)}
    write_reports(out_dir, report, markdown_report(report))
    return report


#: What `uavmm eval` writes in its --out folder (and the same in each task's subfolder): the reports (report.json
#: first), the dataset cache (a folder per dataset) and the subfolders of the other tasks and of --real.
EVAL_REPORTS = ("report.json", "report.md")
EVAL_CACHE = "data"
EVAL_TASK_FOLDERS = ("tracking", "coop", "anomaly", "real")


def require_eval_folder(out: Path) -> None:
    """ValueError (one line) when the folder `out` holds files that are not an earlier `uavmm eval`'s: anything but
    the reports (report.md only beside report.json, which is written first), a dataset cache ``data/`` of folders
    and the tasks' subfolders holding the same; hidden names (.DS_Store, temporaries) do not count. A new or empty
    folder, or an earlier eval's (a re-run reuses its cache and replaces its reports), passes: another's files are
    not ours to mix with or write over. For callers that ask before the work (`uavmm eval`)."""
    foreign = _foreign_names(out)
    if foreign:
        raise ValueError(f"output directory {out} holds files that are not an earlier uavmm eval's "
                         f"({listed_names(foreign)}): give "
                         "a new or empty folder, or an earlier eval's")


def _foreign_names(folder: Path, prefix: str = "") -> list[str]:
    """The visible names under `folder` (``prefix`` + name) that `require_eval_folder` does not take for an eval's."""
    if not folder.is_dir():
        return []
    foreign = []
    for path in sorted(p for p in folder.iterdir() if not p.name.startswith(".")):
        name = path.name
        if name in EVAL_REPORTS and path.is_file():
            if name == "report.md" and not (folder / "report.json").is_file():
                foreign.append(prefix + name)
        elif name == EVAL_CACHE and path.is_dir():
            foreign += [f"{prefix}{name}/{p.name}" for p in sorted(path.iterdir())
                        if not p.name.startswith(".") and not p.is_dir()]
        elif name in EVAL_TASK_FOLDERS and path.is_dir():
            foreign += _foreign_names(path, f"{prefix}{name}/")
        else:
            foreign.append(prefix + name)
    return foreign


def write_reports(out_dir: Path, report: dict[str, Any], markdown: str) -> None:
    """Write ``report.json`` (the report) and ``report.md`` (``markdown``, made before either is written) to
    out_dir, each whole or not at all (`shared.files.write_chunks_atomic`): an interrupted or killed run leaves the
    previous pair as it was, never half a file. Used by `uavmm eval`'s reports (scenarios, domains, real data)."""
    text = json.dumps(report, indent=1)
    write_chunks_atomic(out_dir / "report.json", [text])
    write_chunks_atomic(out_dir / "report.md", [markdown])


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and spread over seeds per (scenario, noise, variant), with deltas to the baseline."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["noise_scale"], r["variant"]), []).append(r)
    out = []
    for (scenario, noise, variant), rs in groups.items():
        base = groups.get((scenario, noise, "baseline"), [])
        ap, ap_sd = _mean_sd([r["AP50"] for r in rs])
        ar, ar_sd = _mean_sd([r["AR100"] for r in rs])
        r_op = statistics.fmean(r["R_op"] for r in rs)
        ar_op = statistics.fmean(r["AR_op"] for r in rs)
        b_ar_op = statistics.fmean(r["AR_op"] for r in base) if base else float("nan")
        p_op = statistics.fmean(r["P_op"] for r in rs)
        b_r_op = statistics.fmean(r["R_op"] for r in base) if base else float("nan")
        b_p_op = statistics.fmean(r["P_op"] for r in base) if base else float("nan")
        b_ap = statistics.fmean(r["AP50"] for r in base) if base else float("nan")
        b_ar = statistics.fmean(r["AR100"] for r in base) if base else float("nan")
        out.append({
            "scenario": scenario, "noise_scale": noise, "variant": variant, "seeds": len(rs),
            "AP50": ap, "AP50_sd": ap_sd, "AR100": ar, "AR100_sd": ar_sd,
            "dAP50": ap - b_ap, "dAR100": ar - b_ar,
            "AR_op": ar_op, "dAR_op": ar_op - b_ar_op,
            "R_op": r_op, "P_op": p_op, "dR_op": r_op - b_r_op, "dP_op": p_op - b_p_op,
            "prenms_recall": statistics.fmean(r["prenms_recall"] for r in rs),
            "pipeline_ms_per_frame": statistics.fmean(r["pipeline_ms_per_frame"] for r in rs),
            "size_filtered": sum(r["size_filtered"] for r in rs),
        })
    return out


def markdown_report(report: dict[str, Any]) -> str:
    lines = [
        "# uavmm eval: video object detection (simulated data)", "",
        f"Seeds {report['seeds']}; frames per video: {report['frames'] or 'scenario default'}; "
        "mean +- sd over seeds. AP50 and AR@100 by pycocotools (all areas).", "",
        f"R@op: recall (IoU 0.5) at the operating precision P@op = the baseline's precision at score "
        f">= {OPERATING_THRESHOLD:g} (a deployment's output; the paper's recall after NMS), read off each "
        "variant's own precision-recall curve. AR@op: COCO AR@100 (IoU 0.5:0.95) of the detections a variant "
        "keeps down to that operating point (AR@100 over all detections cannot move when only scores change).",
        "",
        "| scenario | noise | variant | AP50 | AR@100 | dAP50 | dAR | AR@op | dAR@op | P@op | R@op | dR@op "
        "| pre-NMS recall | ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in report["summary"]:
        lines.append(
            f"| {s['scenario']} | x{s['noise_scale']:g} | {s['variant']} | {s['AP50']:.1f} +- {s['AP50_sd']:.1f} | "
            f"{s['AR100']:.1f} +- {s['AR100_sd']:.1f} | {s['dAP50']:+.1f} | {s['dAR100']:+.1f} | "
            f"{s['AR_op']:.1f} | {s['dAR_op']:+.1f} | "
            f"{s['P_op']:.1f} | {s['R_op']:.1f} | {s['dR_op']:+.1f} | "
            f"{s['prenms_recall']:.1f} | {s['pipeline_ms_per_frame']:.2f} |"
        )
    if report.get("size_filter"):
        lines += ["", "Distance-size filter (the paper's Table I): candidates removed, true vs false positives "
                  "(IoU >= 0.5 with a ground-truth box), summed over seeds.", "",
                  "| scenario | candidates | removed | removed % | false positives | true positives |",
                  "|---|---|---|---|---|---|"]
        for scenario, t in report["size_filter"].items():
            pct = 100 * t["removed"] / max(t["candidates"], 1)
            lines.append(f"| {scenario} | {t['candidates']} | {t['removed']} | {pct:.1f} | "
                         f"{t['removed_false_positives']} | {t['removed_true_positives']} |")
    return "\n".join(lines) + "\n"


def stderr_progress(message: str) -> None:
    """Progress lines go to stderr, so stdout keeps only the results."""
    sys.stderr.write(message + "\n")
    sys.stderr.flush()

"""`uavmm eval --real`: a real COCO + meta file and a detector's results on it, per class: the detector's own
AP50/AR, the pipeline with memory off, our defaults, and the paper's literal rule, from one run.

The detector's results are the pipeline's candidates as they are (a final, thresholded output or pre-NMS
candidates alike); "memory off" is the same size filter and NMS without boosting; "paper rule" is
`sim.domain_eval.paper_rule_config`. Every figure is pycocotools' AP at IoU 0.5 and AR@100 on the file's
own ground truth; what each adaptive stage of our run did is reported beside (agent.stage_report).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

from agent.boost import results_to_coco, run_pipeline
from agent.candidates import SCORE_ROUNDING, scores_outside_unit_error
from agent.coco_metrics import per_class_metrics
from agent.dataset import Candidates, Dataset, dataset_files, read_json
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.stage_report import stage_lines
from shared.geo import Camera
from sim.domain_eval import paper_rule_config
from sim.evaluate import write_reports

__all__ = ["DETECTOR", "MEMORY_OFF", "OURS", "PAPER", "real_files", "run_real_eval"]

DETECTOR, MEMORY_OFF, OURS, PAPER = "detector", "memory off", "ours", "paper rule"


def real_files(path: str | Path, detections: str | Path | None,
               camera: str | Path | None) -> tuple[Path, Path, str | Path]:
    """(images, detections, camera spec) of `uavmm eval --real PATH` (`agent.dataset.dataset_files`)."""
    return dataset_files(path, detections, camera)


def _numeric_results(raw: Any) -> list[dict[str, Any]]:
    """The detector's results as pycocotools scores them: ids and score as numbers, as the candidate loader reads
    them (agent.candidates: "3464", "1", "0.5859" are read there). Scored raw, a string category_id gave the detector
    0 AP50 beside the variants' 87.5 (a gain of +88), a string image_id or score a pycocotools traceback. Entries the
    loader refuses never get here (it runs first); the list as it is when it is not one. Only the boxes the loader
    keeps (4 finite numbers, w and h > 0): the detector is scored on the entries every variant gets."""
    if not isinstance(raw, list):
        return raw  # type: ignore[no-any-return]
    out = []
    for r in raw:
        try:
            entry = {**r, "image_id": int(r["image_id"]), "category_id": int(r["category_id"]),
                     "score": float(r["score"]), "bbox": [float(v) for v in r["bbox"]]}
        except (KeyError, TypeError, ValueError):
            continue
        box = entry["bbox"]
        if len(box) == 4 and all(math.isfinite(v) for v in box) and box[2] > 0 and box[3] > 0:
            out.append(entry)
    return out


def _scored(entries: list[dict[str, Any]], source: str | Path) -> list[dict[str, Any]]:
    """The entries with a score in [0, 1], as the loader keeps them (a NaN or infinite score skipped: detectors emit
    them). A finite score outside [0, 1] refuses the file: the pipeline would drop it and the variants would be
    scored on a part of what the detector is scored on (611 boosted scores above 1 read as boat 86.2 -> 27.4)."""
    error = scores_outside_unit_error([e["score"] for e in entries], str(source),
                                      "and the detector would be scored on more than the variants")
    if error is not None:
        raise error
    # rounding just outside [0, 1] clipped into it, as the candidates' loader does (SCORE_ROUNDING)
    return [{**e, "score": min(max(e["score"], 0.0), 1.0)} if not 0.0 <= e["score"] <= 1.0 else e
            for e in entries if -SCORE_ROUNDING <= e["score"] <= 1.0 + SCORE_ROUNDING]


def run_real_eval(images_path: str | Path, detections_path: str | Path, camera_spec: str | Path, *,
                  config: PipelineConfig | None = None, size_filter: SizeFilter | None = None,
                  out_dir: Path | None = None, terrain: Any = None) -> dict[str, Any]:
    """Score the four variants; returns the report (also report.json/report.md in out_dir when given).

    config, size_filter: our variant's settings (default PipelineConfig() and the built-in priors), e.g. a
    `uavmm tune` parameters file; memory off is the same with use_memory False. terrain: the ground (`--dem`,
    agent.dem.Terrain) every variant puts the boxes on, the paper's rule too (geometry, not a rule's choice);
    None: flat ground.
    """
    t0 = time.perf_counter()
    coco = read_json(images_path, "images")
    dataset = Dataset.from_dict(coco, source=str(images_path))
    candidates = Candidates.load(detections_path, dataset)
    camera = Camera.from_spec(camera_spec)
    raw = _scored(_numeric_results(read_json(detections_path, "detections")), detections_path)
    ours = config or PipelineConfig()
    variants = {MEMORY_OFF: dataclasses.replace(ours, use_memory=False), OURS: ours, PAPER: paper_rule_config()}
    if terrain is not None:
        variants = {name: dataclasses.replace(cfg, terrain=terrain) for name, cfg in variants.items()}
    metrics = {DETECTOR: per_class_metrics(coco, raw)}
    stats: dict[str, dict[str, Any]] = {}
    for name, cfg in variants.items():
        results: list[dict[str, Any]] = []
        stats[name] = run_pipeline(dataset, candidates, camera, cfg, size_filter,
                                   on_frame=lambda frame, res, out=results: out.extend(
                                       results_to_coco(frame.image.id, res)))
        metrics[name] = per_class_metrics(coco, results)
    classes = list(metrics[DETECTOR])
    rows = []
    for cls in classes:
        row: dict[str, Any] = {"class": cls, "gt": int(metrics[DETECTOR][cls]["gt"])}
        for name, m in metrics.items():
            row[f"AP50 {name}"] = round(100 * m.get(cls, {}).get("AP50", 0.0), 2)
            row[f"AR100 {name}"] = round(100 * m.get(cls, {}).get("AR100", 0.0), 2)
        row["gain"] = round(row[f"AP50 {OURS}"] - row[f"AP50 {DETECTOR}"], 2)
        row["paper gain"] = round(row[f"AP50 {PAPER}"] - row[f"AP50 {DETECTOR}"], 2)
        rows.append(row)
    ours_stats = stats[OURS]
    report = {"images": str(images_path), "detections": str(detections_path), "camera": str(camera_spec),
              "frames": ours_stats["frames"], "videos": len(dataset.videos),
              "frames_without_pose": ours_stats["frames_without_pose"],
              "frames_without_pose_by_reason": ours_stats["frames_without_pose_by_reason"],
              "skipped_detections": {k: v for k, v in candidates.skipped.items() if v}, "rows": rows,
              "stages": ours_stats["stages"], "seconds": round(time.perf_counter() - t0, 2)}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_reports(out_dir, report, markdown_real_report(report))
    return report


def markdown_real_report(report: dict[str, Any]) -> str:
    """The report as a markdown table per class (AP50 / AR@100), the stage decisions below it."""
    names = (DETECTOR, MEMORY_OFF, OURS, PAPER)
    lines = [f"Real data: {report['images']} with {report['detections']}, camera {report['camera']} "
             f"({report['videos']} videos, {report['frames']} frames, {report['frames_without_pose']} without pose)",
             "", "AP50 / AR@100 per class (pycocotools); gain = ours - detector.", "",
             "| class | boxes | " + " | ".join(names) + " | gain | paper gain |",
             "|---|---|" + "---|" * (len(names) + 2)]
    for row in report["rows"]:
        cells = [f"{row[f'AP50 {n}']:.1f} / {row[f'AR100 {n}']:.1f}" for n in names]
        lines.append(f"| {row['class']} | {row['gt']} | " + " | ".join(cells)
                     + f" | {row['gain']:+.1f} | {row['paper gain']:+.1f} |")
    skipped = report.get("skipped_detections") or {}
    if skipped:
        lines += ["", "Detections skipped by every column (the detector's too): "
                  + ", ".join(f"{k} {v}" for k, v in skipped.items())]
    reasons = report.get("frames_without_pose_by_reason") or {}
    if reasons:
        lines += ["", "Frames without pose: " + ", ".join(f"{k} {v}" for k, v in reasons.items())]
    lines += ["", "What our run's adaptive stages did (per video, per class of a video for the size filter):", ""]
    lines += [f"- {line}" for line in stage_lines(report.get("stages") or {})]
    return "\n".join(lines) + "\n"

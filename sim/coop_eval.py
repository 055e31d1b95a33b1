"""`uavmm eval --tasks coop`: two UAVs sharing a joint memory map, against each UAV on its own.

The `coop` scenario's UAVs run in lockstep in-process; every publish period their memory-map tiles,
quantised to bytes as on the wire, are fused with the fusion server's own rule (mean over the UAVs
covering a cell) and handed back as each UAV's joint layer: the same data path as over Zenoh.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agent.boost import results_to_coco
from agent.dataset import Candidates, Dataset, iter_video_frames
from agent.memory_map import JointLayer
from agent.pipeline import DetectionPipeline, PipelineConfig
from fusion_server.rules import get_fusion_rule
from shared.geo import Camera

PUBLISH_PERIOD_S = 0.2  # the agent's default 5 Hz
SCORE_THRESHOLD = 0.25  # "reported to the user": the operating threshold of sim.evaluate


def _fuse(pipes: dict[str, DetectionPipeline], rule_name: str) -> dict[tuple[str, int, int], np.ndarray]:
    """Joint tiles (cls, x, y) -> (n, n) float32 from every UAV's current window."""
    rule = get_fusion_rule(rule_name)
    stacks: dict[tuple[str, int, int], list[np.ndarray]] = defaultdict(list)
    for pipe in pipes.values():
        for cls in pipe.memory.classes:
            for x, y, values in pipe.memory.tiles(cls):
                stacks[(cls, x, y)].append(np.clip(np.rint(values * 255.0), 0, 255).astype(np.uint8))
    return {key: rule(np.stack(layers)).astype(np.float32) / 255.0 for key, layers in stacks.items()}


def run_coop(data_dir: Path, config: PipelineConfig, *, share: bool, rule: str = "mean") -> dict[int, list[dict]]:
    """Run both UAVs of a simultaneous dataset; returns COCO results per video id."""
    dataset = Dataset.load(data_dir / "images.json")
    candidates = Candidates.load(data_dir / "pre_nms.json", dataset)
    camera = Camera.from_file(data_dir / "camera.json")
    uav_of = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    joints = {vid: JointLayer(ttl_s=2.0) for vid in dataset.videos}
    pipes = {vid: DetectionPipeline(camera, dataset.categories, config, joint=joints[vid] if share else None)
             for vid in dataset.videos}
    iters = {vid: iter_video_frames(dataset, camera, vid) for vid in dataset.videos}
    results: dict[int, list[dict]] = {vid: [] for vid in dataset.videos}
    next_publish: float | None = None
    while iters:
        step = {}
        for vid in list(iters):
            frame = next(iters[vid], None)
            if frame is None:
                del iters[vid]
            else:
                step[vid] = frame
        if not step:
            break
        for vid, frame in step.items():
            pipes[vid].camera = frame.camera
            res = pipes[vid].process(*candidates.get(frame.image.id), frame.pose, frame.t)
            results[vid].extend(results_to_coco(frame.image.id, res))
        t = max(f.t for f in step.values())
        if share and (next_publish is None or t >= next_publish):
            # what each UAV receives now is what the server fused from the tiles just published
            for (cls, x, y), values in _fuse({uav_of.get(v, str(v)): p for v, p in pipes.items()}, rule).items():
                for joint in joints.values():
                    joint.update(cls, x, y, values, t)
            next_publish = t + PUBLISH_PERIOD_S
    return results


def _hidden_ground_truth(data_dir: Path, dataset: Dataset) -> dict[str, Any]:
    """COCO ground truth of each video's annotations plus its hidden (occluded) objects' boxes."""
    truth = json.loads((data_dir / "truth.json").read_text())
    hidden = truth.get("occluded_boxes", [])
    tid_cat = {a["track_id"]: a["category_id"] for a in dataset.coco["annotations"]}
    next_id = max((a["id"] for a in dataset.coco["annotations"]), default=0) + 1
    extra = []
    for i, h in enumerate(hidden):
        x, y, w, hgt = h["bbox"]
        extra.append({"id": next_id + i, "image_id": h["image_id"], "category_id": tid_cat.get(h["track_id"], 1),
                      "bbox": [x, y, w, hgt], "area": w * hgt, "iscrowd": 0, "track_id": h["track_id"],
                      "hidden": True})
    return {**dataset.coco, "annotations": dataset.coco["annotations"] + extra}, extra


def _hidden_detected(results: list[dict], hidden: list[dict]) -> float:
    """Fraction of hidden-object boxes matched (IoU >= 0.5) by a detection scoring >= SCORE_THRESHOLD."""
    by_image: dict[int, list[list[float]]] = defaultdict(list)
    for r in results:
        if r["score"] >= SCORE_THRESHOLD:
            by_image[r["image_id"]].append(r["bbox"])
    hit = 0
    for h in hidden:
        x, y, w, hh = h["bbox"]
        for bx, by, bw, bh in by_image.get(h["image_id"], []):
            iw = max(0.0, min(x + w, bx + bw) - max(x, bx))
            ih = max(0.0, min(y + hh, by + bh) - max(y, by))
            inter = iw * ih
            if inter >= 0.5 * (w * hh + bw * bh - inter):
                hit += 1
                break
    return hit / len(hidden) if hidden else float("nan")


def evaluate_coop(data_dir: Path) -> list[dict[str, Any]]:
    """Per UAV: baseline, own memory map, memory map + joint map; AP50 with and without hidden objects."""
    from sim.metrics import coco_detection_metrics

    dataset = Dataset.load(data_dir / "images.json")
    gt_hidden, hidden = _hidden_ground_truth(data_dir, dataset)
    base = PipelineConfig()
    runs = {
        "baseline": run_coop(data_dir, dataclasses.replace(base, use_memory=False), share=False),
        "own memory map": run_coop(data_dir, base, share=False),
        "memory map + joint map": run_coop(data_dir, base, share=True),
    }
    rows = []
    videos = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    for vid, uav in videos.items():
        image_ids = [im.id for im in dataset.videos[vid]]
        id_set = set(image_ids)
        hidden_v = [h for h in hidden if h["image_id"] in id_set]
        for name, per_video in runs.items():
            res = per_video[vid]
            rows.append({
                "uav": uav, "variant": name, "hidden_boxes": len(hidden_v),
                "AP50": 100 * coco_detection_metrics(dataset.coco, res, image_ids=image_ids)["AP50"],
                "AP50_with_hidden": 100 * coco_detection_metrics(gt_hidden, res, image_ids=image_ids)["AP50"],
                "hidden_detected": 100 * _hidden_detected(res, hidden_v) if hidden_v else float("nan"),
            })
    return rows


def run_coop_eval(seeds: list[int], *, frames: int | None = None, out_dir: Path = Path("out/eval/coop"),
                  progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Evaluate `coop` over seeds; writes report.json and report.md to out_dir."""
    from sim.evaluate import ensure_dataset

    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for i, seed in enumerate(seeds):
        if progress:
            progress(f"[{i + 1}/{len(seeds)}] coop seed={seed}")
        data_dir = ensure_dataset("coop", seed, frames, 1.0, out_dir / "data")
        rows += [{"seed": seed, **r} for r in evaluate_coop(data_dir)]
    summary = []
    keys = sorted({(r["uav"], r["variant"]) for r in rows}, key=lambda k: (k[0], list(_ORDER).index(k[1])))
    for uav, variant in keys:
        rs = [r for r in rows if r["uav"] == uav and r["variant"] == variant]
        summary.append({"uav": uav, "variant": variant, **{
            m: statistics.fmean(r[m] for r in rs if r[m] == r[m]) if any(r[m] == r[m] for r in rs) else float("nan")
            for m in ("AP50", "AP50_with_hidden", "hidden_detected")}})
    report = {"seeds": seeds, "frames": frames, "rows": rows, "summary": summary,
              "seconds": round(time.perf_counter() - t0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    lines = ["# uavmm eval: cooperative detection (scenario coop, two UAVs)", "",
             f"Seeds {seeds}, mean. uav1's view of the hidden people is blocked by a tree in every frame. "
             "AP50 by pycocotools on each UAV's frames; 'with hidden' adds the hidden people's boxes to the "
             f"ground truth; 'hidden detected' = share of their boxes found with score >= {SCORE_THRESHOLD}. "
             "Joint map: the fusion server's mean rule over both UAVs' byte-quantised tiles at 5 Hz.", "",
             "| uav | variant | AP50 | AP50 with hidden | hidden detected % |", "|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['uav']} | {s['variant']} | {s['AP50']:.1f} | {s['AP50_with_hidden']:.1f} | "
                     f"{s['hidden_detected']:.1f} |")
    (out_dir / "report.md").write_text("\n".join(lines) + "\n")
    return report


_ORDER = ("baseline", "own memory map", "memory map + joint map")

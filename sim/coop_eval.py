"""`uavmm eval --tasks coop`: two UAVs sharing a joint memory map, against each UAV on its own.

The `coop` scenario's UAVs run in lockstep in-process on the wire's data path: every publish period
each UAV's memory-map tiles go through the agent's tile encoder (`agent.tile_updates.TileChangeTracker`:
byte-quantised, unchanged tiles refreshed every second) and its camera footprint through its state
message (`agent.node.state_message`); the fusion server's own `fusion_server.joint_map.JointMap`
(rule and coverage as on the server, on the frame clock) fuses them, and the joint tiles it would
publish become each UAV's joint layer.
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
from agent.node import state_message
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.tile_updates import TileChangeTracker
from agent.tracking import GpsTracker
from agent.tracking_io import memory_evidence
from fusion_server.joint_map import JointMap
from fusion_server.rules import get_fusion_rule
from shared.geo import Camera
from shared.tilecodec import decode_tile

PUBLISH_PERIOD_S = 0.2  # the agent's default 5 Hz
SCORE_THRESHOLD = 0.25  # "reported to the user": the operating threshold of sim.evaluate
JOINT_TTL_S = 2.0  # the fusion server's default --ttl-s
TILE_MIN_VALUE = 0.05  # the agent's default tile_min_value


class CoopFusion:
    """The agents' publishing and the fusion server's joint map, driven by the frame clock.

    rule: a `fusion_server.rules` name; coverage: "footprint" or "tile" (`JointMap`).
    """

    def __init__(self, uavs: list[str], classes: list[str], pipes: dict[str, DetectionPipeline], *,
                 rule: str = "mean", coverage: str = "footprint") -> None:
        self.now = 0.0
        grid = next(iter(pipes.values())).grid
        self.joint = JointMap(grid, get_fusion_rule(rule), JOINT_TTL_S, 1.0 / PUBLISH_PERIOD_S, coverage=coverage,
                              clock=lambda: self.now, wall=lambda: self.now)
        self.pipes = pipes
        self.footprints: dict[str, tuple] = {}  # uav -> footprint of its latest state message
        self.senders = {uav: TileChangeTracker(uav, classes, grid, min_value=TILE_MIN_VALUE, clock=lambda: self.now)
                        for uav in uavs}

    def publish(self, t: float, poses: dict[str, tuple]) -> list[tuple[str, int, int, np.ndarray | None]]:
        """One publish cycle at frame time t: every UAV's tiles and footprint in, joint tiles out.

        poses: uav -> (pose, camera) of its latest frame with a pose. Returns (cls, x, y, values or
        None for a dropped tile) of the joint tiles published now, values (n, n) float32 in [0, 1].
        """
        self.now = t
        for uav, sender in self.senders.items():
            pipe = self.pipes[uav]
            for cls, x, y, payload in sender.messages(pipe.memory, t):
                message = decode_tile(payload)
                values = np.rint(message.values * np.float32(255.0)).astype(np.uint8)
                self.joint.put(uav, (cls, message.z, x, y), values, message.t, message.seq)
            if uav in poses:
                pose, camera = poses[uav]
                state = state_message(uav, t, pose, camera, range_m=pipe.config.range_limit_m)
                self.joint.put_footprint(uav, state.footprint)
                self.footprints[uav] = state.footprint
        updates, _ = self.joint.step()
        out = []
        for update in updates:
            cls, _, x, y = update.key
            out.append((cls, x, y, None if update.tile is None
                        else update.tile.values.astype(np.float32) / np.float32(255.0)))
        return out


def run_coop(data_dir: Path, config: PipelineConfig, *, share: bool, rule: str = "mean",
             coverage: str = "footprint", track_boxes: dict[int, list[list[float]]] | None = None
             ) -> dict[int, list[dict]]:
    """Run both UAVs of a simultaneous dataset; returns COCO results per video id.

    share: give each UAV the joint map (fusion `rule` with `coverage`, see `CoopFusion`).
    track_boxes: when given, each UAV also runs the GPS tracker (defaults) and this dict receives, per
    image id, the boxes [x, y, w, h] of the confirmed tracks matched in that frame.
    """
    dataset = Dataset.load(data_dir / "images.json")
    candidates = Candidates.load(data_dir / "pre_nms.json", dataset)
    camera = Camera.from_file(data_dir / "camera.json")
    uav_of = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    for vid in dataset.videos:
        uav_of.setdefault(vid, str(vid))
    joints = {vid: JointLayer(ttl_s=JOINT_TTL_S) for vid in dataset.videos}
    pipes = {vid: DetectionPipeline(camera, dataset.categories, config, joint=joints[vid] if share else None)
             for vid in dataset.videos}
    fusion = CoopFusion([uav_of[v] for v in pipes], list(dict.fromkeys(dataset.categories.values())),
                        {uav_of[v]: p for v, p in pipes.items()}, rule=rule, coverage=coverage) if share else None
    trackers = {vid: GpsTracker(None, dataset.categories, evidence_at=memory_evidence(pipes[vid]))
                for vid in dataset.videos} if track_boxes is not None else {}
    # live agents: each frame keeps the telemetry sample it carries (no look-ahead to later samples)
    iters = {vid: iter_video_frames(dataset, camera, vid, at_frame_time=False) for vid in dataset.videos}
    results: dict[int, list[dict]] = {vid: [] for vid in dataset.videos}
    poses: dict[str, tuple] = {}
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
            if track_boxes is not None:
                tracks = trackers[vid].update(res, frame.pose, frame.t, frame.camera, pose_t=frame.pose_t)
                track_boxes[frame.image.id] = [[b[0], b[1], b[2] - b[0], b[3] - b[1]] for b in
                                               (tr.box_xyxy for tr in tracks if tr.confirmed and tr.matched)]
            if frame.pose is not None:
                poses[uav_of[vid]] = (frame.pose, frame.camera)
        t = max(f.t for f in step.values())
        if fusion is not None and (next_publish is None or t >= next_publish):
            # what each UAV receives now is what the server fused from the tiles just published
            for cls, x, y, values in fusion.publish(t, poses):
                for joint in joints.values():
                    joint.update(cls, x, y, np.zeros((joint.grid.n,) * 2, np.float32) if values is None else values, t)
            # and each UAV hears the others' state messages (their footprints) of this cycle
            for vid, joint in joints.items():
                for uav, footprint in fusion.footprints.items():
                    if uav != uav_of[vid]:
                        joint.put_footprint(uav, footprint, t)
            next_publish = t + PUBLISH_PERIOD_S
    return results


def _hidden_ground_truth(data_dir: Path, dataset: Dataset, *, ignore: bool = False) -> tuple[dict[str, Any], list]:
    """COCO ground truth of each video's annotations plus its hidden (occluded) objects' boxes.

    ignore: add the hidden boxes as COCO crowd regions (iscrowd 1): a detection on one is neither a
    true nor a false positive.
    """
    truth = json.loads((data_dir / "truth.json").read_text())
    hidden = truth.get("occluded_boxes", [])
    tid_cat = {a["track_id"]: a["category_id"] for a in dataset.coco["annotations"]}
    next_id = max((a["id"] for a in dataset.coco["annotations"]), default=0) + 1
    extra = []
    for i, h in enumerate(hidden):
        x, y, w, hgt = h["bbox"]
        extra.append({"id": next_id + i, "image_id": h["image_id"], "category_id": tid_cat.get(h["track_id"], 1),
                      "bbox": [x, y, w, hgt], "area": w * hgt, "iscrowd": int(ignore), "track_id": h["track_id"],
                      "hidden": True})
    return {**dataset.coco, "annotations": dataset.coco["annotations"] + extra}, extra


def _hidden_detected(results: list[dict], hidden: list[dict]) -> float:
    """Fraction of hidden-object boxes matched (IoU >= 0.5) by a detection scoring >= SCORE_THRESHOLD."""
    by_image: dict[int, list[list[float]]] = defaultdict(list)
    for r in results:
        if r["score"] >= SCORE_THRESHOLD:
            by_image[r["image_id"]].append(r["bbox"])
    return _hidden_hit_rate(by_image, hidden)


def _hidden_hit_rate(by_image: dict[int, list[list[float]]], hidden: list[dict]) -> float:
    """Fraction of hidden-object boxes matched (IoU >= 0.5) by one of their image's boxes [x, y, w, h]."""
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


def evaluate_coop(data_dir: Path, *, variants: tuple[str, ...] | None = None, track: bool = True
                  ) -> list[dict[str, Any]]:
    """Per UAV: baseline, own memory map, joint map boosting only, joint map + joint detections (or the
    `variants` of these named).

    Metrics: AP50 with the hidden objects as ground truth (does the UAV report everything in its view?),
    AP50 with them as ignore regions, AP50 without them (a detection of one is a false positive), and
    the share of hidden-object boxes detected; with `track`, the share the GPS tracker's confirmed tracks hold
    (NaN without).
    """
    from sim.metrics import coco_detection_metrics

    dataset = Dataset.load(data_dir / "images.json")
    gt_hidden, hidden = _hidden_ground_truth(data_dir, dataset)
    gt_ignored, _ = _hidden_ground_truth(data_dir, dataset, ignore=True)
    base = PipelineConfig()
    configs = {
        "baseline": (dataclasses.replace(base, use_memory=False), False),
        "own memory map": (base, False),
        "joint map boosting": (dataclasses.replace(base, joint_detections=False), True),
        "joint map + joint detections": (base, True),
    }
    if variants is not None:
        unknown = sorted(set(variants) - set(_ORDER))
        if unknown:
            raise ValueError(f"evaluate_coop: unknown variant(s) {', '.join(unknown)}; valid: {', '.join(_ORDER)}")
    runs, tracked = {}, {}
    for name, (config, share) in configs.items():
        if variants is not None and name not in variants:
            continue
        tracked[name] = {}
        runs[name] = run_coop(data_dir, config, share=share, track_boxes=tracked[name] if track else None)
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
                "AP50": 100 * coco_detection_metrics(gt_hidden, res, image_ids=image_ids)["AP50"],
                "AP50_hidden_ignored": 100 * coco_detection_metrics(gt_ignored, res, image_ids=image_ids)["AP50"],
                "AP50_hidden_as_fp": 100 * coco_detection_metrics(dataset.coco, res, image_ids=image_ids)["AP50"],
                "hidden_detected": 100 * _hidden_detected(res, hidden_v) if hidden_v else float("nan"),
                "hidden_tracked": (100 * _hidden_hit_rate(tracked[name], hidden_v) if hidden_v and track
                                   else float("nan")),
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
            for m in _METRICS}})
    report = {"seeds": seeds, "frames": frames, "rows": rows, "summary": summary,
              "seconds": round(time.perf_counter() - t0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    lines = ["# uavmm eval: cooperative detection (scenario coop, two UAVs)", "",
             f"Seeds {seeds}, mean. A tree line hides resting people (and passing walkers) from the far, "
             "oblique uav1 for the whole flight; uav2, closer, sees them. "
             "AP50 by pycocotools on each UAV's frames with the hidden people's boxes as ground truth "
             "(does the UAV report everything in its view?); 'hidden ignored': their boxes are COCO crowd "
             "(ignore) regions; 'hidden as FP': left out, so detecting them counts as a false positive; "
             f"'hidden detected' = share of their boxes found with score >= {SCORE_THRESHOLD}; 'hidden "
             "tracked' = share matched (IoU >= 0.5) by the box of a confirmed GPS-tracker track matched in "
             "that frame. "
             "Joint map: the fusion server's JointMap (mean rule; a UAV covers the cells of its camera "
             "footprints of the last 2 s) over both UAVs' tiles as the agent encodes them, at 5 Hz; "
             "'joint detections': the peaks of the other UAV's evidence in view that no detection explains "
             "promote a weak real candidate or carry this UAV's last sighting of the object "
             "(agent.joint_detections).", "",
             "| uav | variant | AP50 | AP50 hidden ignored | AP50 hidden as FP | hidden detected % | "
             "hidden tracked % |", "|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['uav']} | {s['variant']} | {s['AP50']:.1f} | {s['AP50_hidden_ignored']:.1f} | "
                     f"{s['AP50_hidden_as_fp']:.1f} | {s['hidden_detected']:.1f} | {s['hidden_tracked']:.1f} |")
    (out_dir / "report.md").write_text("\n".join(lines) + "\n")
    return report


_ORDER = ("baseline", "own memory map", "joint map boosting", "joint map + joint detections")
_METRICS = ("AP50", "AP50_hidden_ignored", "AP50_hidden_as_fp", "hidden_detected", "hidden_tracked")

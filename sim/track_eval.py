"""Tracking evaluation on simulated data: our GPS tracker beside a pixel-space tracker (norfair).

Scores with TrackEval's HOTA, CLEAR (MOTA, IDSW, Frag) and Identity (IDF1) metrics on per-sequence
arrays built here, counts long-term re-identifications: objects that leave the view and come
back with their old id, and measures the ground error of our tracker's reported positions
(`sim.position_error`). `run_track_eval` writes report.json and report.md like `sim.evaluate`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from agent.boxes import box_iou
from agent.dataset import Candidates, Dataset, Frame
from agent.file_frames import prepared_frames
from agent.frame_result import FrameResult
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.pixel_tracker import (  # noqa: F401  (NODEPS_INSTALL, PixelTracker: re-exported, as before)
    NODEPS_INSTALL,
    PixelBaselineConfig,
    PixelTracker,
)
from agent.pixel_tracker import import_baseline as _import_baseline
from agent.size_filter import SizeFilter
from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking_io import frame_time_s
from shared.geo import Camera, GroundSurface
from sim.position_error import format_metres, frame_position_errors, mean_known, summarise_position_errors

log = logging.getLogger(__name__)

#: Minimum IoU for a tracker box to match a ground-truth box (CLEAR, Identity and the re-ID count).
MATCH_IOU = 0.5


# ---------------------------------------------------------------------------------------------
# The pixel-space baseline
# ---------------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------------
# Running the trackers
# ---------------------------------------------------------------------------------------------

@dataclass
class SequenceTracks:
    """One tracker's output on one video: per frame index, ids (K,), boxes_xyxy (K, 4), scores (K,);
    latlon: per frame index, the reported ground positions (K, 2) lat, lon in degrees (our GPS tracker
    only; empty for a tracker without ground positions)."""

    frames: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    seconds: float = 0.0
    reidentified: int = 0
    latlon: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class TrackingVariant:
    """A detector pipeline configuration plus a tracker: `kind` is "gps" (ours) or "pixel" (norfair)."""

    name: str
    pipeline: PipelineConfig
    kind: str = "gps"
    tracker: TrackerConfig | None = None
    pixel: PixelBaselineConfig = field(default_factory=PixelBaselineConfig)


def default_tracking_variants() -> list[TrackingVariant]:
    """Ours with the memory map (with and without the detections' appearance descriptors), ours on
    single-frame detections, and norfair on the same ones."""
    base = PipelineConfig()
    single = dataclasses.replace(base, use_memory=False)
    return [
        # norfair does not use poses: the telemetry as stamped (the size filter is the only pose user)
        TrackingVariant("norfair (pixel IoU)", dataclasses.replace(single, estimate_clock_offset=False), kind="pixel"),
        TrackingVariant("GPS tracker, no memory", single, kind="gps"),
        TrackingVariant("GPS tracker + memory map, motion only", base, kind="gps",
                        tracker=TrackerConfig(use_appearance=False)),
        TrackingVariant("GPS tracker + memory map", base, kind="gps"),
    ]


def pipeline_frames(dataset: Dataset, candidates: Candidates, camera: Camera, video_id: int,
                    config: PipelineConfig, size_filter: SizeFilter | None = None
                    ) -> list[tuple[Frame, FrameResult, float, GroundSurface | None]]:
    """The pipeline's result for every frame of a video, with the frame time the tracker uses (s) and the terrain
    the frame's boxes were put on (`--dem`; None: flat ground): computed once, then given to every tracker
    variant."""
    pipe = DetectionPipeline(camera, dataset.categories, config, size_filter=size_filter)
    out: list[tuple[Frame, FrameResult, float, GroundSurface | None]] = []
    t_prev = -np.inf
    for frame, _ in prepared_frames(dataset, camera, video_id, candidates, config, pipe):
        if pipe.camera != frame.camera:
            pipe.camera = frame.camera
        boxes, scores, cids = candidates.get(frame.image.id)
        result = pipe.process(boxes, scores, cids, frame.pose, frame.t, candidates.get_embeddings(frame.image.id))
        t_prev = max(frame_time_s(frame), t_prev)
        out.append((frame, result, t_prev, pipe.terrain_for(frame.pose)))
    return out


def run_tracker_on_frames(frames: list[tuple[Frame, FrameResult, float, GroundSurface | None]],
                          variant: TrackingVariant,
                          class_names: dict[int, str], fps: float) -> SequenceTracks:
    """Run one variant's tracker over pipeline results already computed for a video."""
    seq = SequenceTracks()
    t0 = time.perf_counter()
    if variant.kind == "pixel":
        pix = PixelTracker(variant.pixel, fps)
        for frame, result, _, _ in frames:
            ids, boxes, scores = pix.update(result.boxes_xyxy.astype(np.float64), result.scores.astype(np.float64),
                                            result.class_ids)
            seq.frames[frame.image.frame_index] = (ids, boxes, scores)
    elif variant.kind == "gps":
        tracker = GpsTracker(variant.tracker, class_names)
        for frame, result, t, terrain in frames:
            tracks = tracker.report(tracker.update(result, frame.pose, t, frame.camera, pose_t=frame.pose_t,
                                                   pose_retimed=frame.pose_retimed, terrain=terrain))
            seq.frames[frame.image.frame_index] = (
                np.array([tr.id for tr in tracks], dtype=np.int64),
                np.array([tr.box_xyxy for tr in tracks], dtype=np.float64).reshape(-1, 4),
                np.array([tr.score for tr in tracks], dtype=np.float64))
            seq.latlon[frame.image.frame_index] = np.array([(tr.lat, tr.lon) for tr in tracks],
                                                           dtype=np.float64).reshape(-1, 2)
        seq.reidentified = tracker.n_reidentified
    else:
        raise ValueError(f"unknown tracker kind {variant.kind!r}; valid: gps, pixel")
    seq.seconds = time.perf_counter() - t0
    return seq


# ---------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------

@dataclass
class SequenceTruth:
    """Ground truth of one video.

    frames: per frame index, track ids (K,) and boxes_xyxy (K, 4) of the visible objects;
    ignore: per frame index, (track ids (M,), boxes_xyxy (M, 4)) of objects in view but hidden
    (behind trees: a detector may still see them; like MOTChallenge's distractors, tracker boxes on
    them count neither as true nor as false positives); fps: frame rate; latlon: per frame index, the
    visible objects' true positions (K, 2) lat, lon in degrees, rows as in `frames` (NaN where the
    annotation has none; empty when not known).
    """

    frames: dict[int, tuple[np.ndarray, np.ndarray]]
    fps: float
    ignore: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    latlon: dict[int, np.ndarray] = field(default_factory=dict)


def _xywh_to_xyxy(boxes: list[list[float]]) -> np.ndarray:
    b = np.array(boxes, dtype=np.float64).reshape(-1, 4)
    return np.column_stack([b[:, :2], b[:, :2] + b[:, 2:]])


def sequence_truth(dataset: Dataset, video_id: int, fps: float = 30.0,
                   hidden: list[dict[str, Any]] | None = None) -> SequenceTruth:
    """Per-frame ground truth of a video from the COCO annotations (``track_id``, ``bbox``, and the true
    ``lat``, ``lon`` of simulated datasets).

    hidden: truth.json's ``occluded_boxes`` ({image_id, track_id, bbox}), the ignore regions.
    """
    images = {im.id: im.frame_index for im in dataset.videos[video_id]}
    per_frame: dict[int, list[tuple[int, list[float], tuple[float, float]]]] = {f: [] for f in images.values()}
    for a in dataset.coco.get("annotations", []):
        f = images.get(a["image_id"])
        if f is not None and not a.get("iscrowd", 0):
            per_frame[f].append((int(a["track_id"]), a["bbox"], (_coordinate(a, "lat"), _coordinate(a, "lon"))))
    frames = {f: (np.array([i for i, _, _ in items], dtype=np.int64), _xywh_to_xyxy([b for _, b, _ in items]))
              for f, items in per_frame.items()}
    latlon = {f: np.array([p for _, _, p in items], dtype=np.float64).reshape(-1, 2) for f, items in per_frame.items()}
    hidden_frame: dict[int, list[tuple[int, list[float]]]] = {}
    for o in hidden or []:
        f = images.get(o["image_id"]) if "image_id" in o else None
        if f is not None:
            hidden_frame.setdefault(f, []).append((int(o["track_id"]), o["bbox"]))
    ignore = {f: (np.array([i for i, _ in items], dtype=np.int64), _xywh_to_xyxy([b for _, b in items]))
              for f, items in hidden_frame.items()}
    return SequenceTruth(frames, fps, ignore, latlon)


def _coordinate(annotation: dict[str, Any], key: str) -> float:
    value = annotation.get(key)
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else float("nan")


def _matchable(iou: np.ndarray) -> np.ndarray:
    """IoU with pairs below MATCH_IOU zeroed before the assignment, as TrackEval does: a pair too weak to match must
    not steer which boxes the others take (a hidden object's 0.4 pair took a visible one's box, HOTA 63.2 -> 47.4)."""
    return np.where(iou >= MATCH_IOU - np.finfo(float).eps, iou, 0.0)


def drop_ignored(truth: SequenceTruth, tracks: SequenceTracks) -> SequenceTracks:
    """Remove tracker boxes that match a hidden object rather than a visible one (TrackEval's
    MOTChallenge preprocessing for distractors: Hungarian on IoU >= MATCH_IOU over all objects)."""
    out = SequenceTracks(dict(tracks.frames), tracks.seconds, tracks.reidentified, dict(tracks.latlon))
    for f, (_, i_boxes) in truth.ignore.items():
        if f not in tracks.frames or not len(i_boxes):
            continue
        t_ids, t_boxes, t_scores = tracks.frames[f]
        if not len(t_ids):
            continue
        g_boxes = np.vstack([truth.frames.get(f, (None, np.zeros((0, 4))))[1], i_boxes])
        n_vis = len(g_boxes) - len(i_boxes)
        iou = _matchable(box_iou(g_boxes, t_boxes))
        r, c = linear_sum_assignment(-iou)
        drop = c[(iou[r, c] > 0) & (r >= n_vis)]
        keep = np.ones(len(t_ids), dtype=bool)
        keep[drop] = False
        out.frames[f] = (t_ids[keep], t_boxes[keep], t_scores[keep])
        if f in tracks.latlon:
            out.latlon[f] = tracks.latlon[f][keep]
    return out


def position_errors(truth: SequenceTruth, tracks: SequenceTracks) -> np.ndarray:
    """(P,) metres between the reported and the true ground position of every (frame, track) matched to a
    ground-truth box (`sim.position_error.frame_position_errors`); empty without ground positions."""
    out = [np.zeros(0)]
    for f, t_latlon in tracks.latlon.items():
        if f not in truth.frames or f not in truth.latlon or f not in tracks.frames:
            continue
        out.append(frame_position_errors(truth.frames[f][1], truth.latlon[f], tracks.frames[f][1], t_latlon,
                                         min_iou=MATCH_IOU))
    return np.concatenate(out)


def trackeval_data(truth: SequenceTruth, tracks: SequenceTracks) -> dict[str, Any]:
    """The per-sequence dict TrackEval's metrics take (ids relabelled 0..n-1, IoU similarities)."""
    frame_ids = sorted(truth.frames)
    gt_all = np.unique(np.concatenate([truth.frames[f][0] for f in frame_ids] + [np.zeros(0, np.int64)]))
    tr_all = np.unique(np.concatenate([tracks.frames.get(f, (np.zeros(0, np.int64),))[0] for f in frame_ids]
                                      + [np.zeros(0, np.int64)]))
    gt_ids, tr_ids, sims = [], [], []
    n_gt = n_tr = 0
    for f in frame_ids:
        g_ids, g_boxes = truth.frames[f]
        t_ids, t_boxes, _ = tracks.frames.get(f, (np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(0)))
        gt_ids.append(np.searchsorted(gt_all, g_ids).astype(int))
        tr_ids.append(np.searchsorted(tr_all, t_ids).astype(int))
        sims.append(box_iou(g_boxes, t_boxes))
        n_gt += len(g_ids)
        n_tr += len(t_ids)
    return {"num_timesteps": len(frame_ids), "num_gt_ids": len(gt_all), "num_tracker_ids": len(tr_all),
            "num_gt_dets": n_gt, "num_tracker_dets": n_tr, "gt_ids": gt_ids, "tracker_ids": tr_ids,
            "similarity_scores": sims, "seq": "seq"}


def _metrics() -> tuple[Any, Any, Any]:
    metrics = _import_baseline("trackeval.metrics", "tracking metrics (HOTA, MOTA, IDF1 by TrackEval)")
    HOTA, CLEAR, Identity = metrics.HOTA, metrics.CLEAR, metrics.Identity

    with contextlib.redirect_stdout(io.StringIO()):
        return (HOTA(), CLEAR({"THRESHOLD": MATCH_IOU, "PRINT_CONFIG": False}),
                Identity({"THRESHOLD": MATCH_IOU, "PRINT_CONFIG": False}))


def mot_metrics(sequences: list[dict[str, Any]]) -> dict[str, float]:
    """HOTA, DetA, AssA, MOTA, IDF1 (percent), IDs, Frag, FP, FN over sequences (TrackEval's combination)."""
    hota, clear, ident = _metrics()
    res: dict[str, list[dict[str, Any]]] = {"hota": [], "clear": [], "ident": []}
    for data in sequences:
        res["hota"].append(hota.eval_sequence(data))
        res["clear"].append(clear.eval_sequence(data))
        res["ident"].append(ident.eval_sequence(data))
    h = hota.combine_sequences({str(i): r for i, r in enumerate(res["hota"])})
    c = clear.combine_sequences({str(i): r for i, r in enumerate(res["clear"])})
    d = ident.combine_sequences({str(i): r for i, r in enumerate(res["ident"])})
    return {"HOTA": 100 * float(np.mean(h["HOTA"])), "DetA": 100 * float(np.mean(h["DetA"])),
            "AssA": 100 * float(np.mean(h["AssA"])), "MOTA": 100 * float(c["MOTA"]), "IDF1": 100 * float(d["IDF1"]),
            "IDs": int(c["IDSW"]), "Frag": int(c["Frag"]), "FP": int(c["CLR_FP"]), "FN": int(c["CLR_FN"])}


def frame_matches(truth: SequenceTruth, tracks: SequenceTracks) -> dict[int, dict[int, int]]:
    """Per frame index, ground-truth track id -> tracker id (Hungarian on IoU >= MATCH_IOU)."""
    out: dict[int, dict[int, int]] = {}
    for f, (g_ids, g_boxes) in truth.frames.items():
        t_ids, t_boxes, _ = tracks.frames.get(f, (np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(0)))
        if not len(g_ids) or not len(t_ids):
            continue
        iou = _matchable(box_iou(g_boxes, t_boxes))
        r, c = linear_sum_assignment(-iou)
        ok = iou[r, c] > 0
        out[f] = {int(g_ids[i]): int(t_ids[j]) for i, j in zip(r[ok], c[ok], strict=True)}
    return out


def reid_events(truth: SequenceTruth, tracks: SequenceTracks, *, min_gap_s: float = 1.0, horizon_s: float = 30.0,
                window_s: float = 3.0, occluded: dict[int, set[int]] | None = None) -> dict[str, int]:
    """Count objects that leave the view and come back, and how many keep their id.

    An event is a gap of min_gap_s..horizon_s in a ground-truth track's annotated frames (the object
    was out of view, or hidden when `occluded` is None). It is scored when the tracker followed the
    object within window_s before the gap and picked it up within window_s after: kept when the id
    after equals the id before.

    occluded: track id -> frame indices where the object was in view but hidden (truth.json); gaps
    mostly of such frames are not "left the view" and are skipped.

    Returns
    -------
    dict
        ``events`` (gaps), ``scored`` (followed before and after), ``kept`` (same id).
    """
    matches = frame_matches(truth, tracks)
    by_track: dict[int, list[int]] = {}
    for f in sorted(truth.frames):
        for gid in truth.frames[f][0]:
            by_track.setdefault(int(gid), []).append(f)
    fps = truth.fps
    min_gap, horizon, window = round(min_gap_s * fps), horizon_s * fps, round(window_s * fps)
    events = scored = kept = 0
    for gid, frames in by_track.items():
        for a, b in zip(frames[:-1], frames[1:], strict=True):
            if b - a <= min_gap or b - a > horizon:
                continue
            if occluded is not None and len(occluded.get(gid, set()) & set(range(a + 1, b))) > (b - a - 1) / 2:
                continue
            events += 1
            before = next((matches[f][gid] for f in range(a, a - window, -1) if gid in matches.get(f, {})), None)
            after = next((matches[f][gid] for f in range(b, b + window) if gid in matches.get(f, {})), None)
            if before is None or after is None:
                continue
            scored += 1
            kept += before == after
    return {"events": events, "scored": scored, "kept": kept}


# ---------------------------------------------------------------------------------------------
# One dataset, many variants
# ---------------------------------------------------------------------------------------------

def _hidden_boxes(data_dir: Path) -> list[dict[str, Any]]:
    truth_path = data_dir / "truth.json"
    if not truth_path.exists():
        return []
    return list(json.loads(truth_path.read_text()).get("occluded_boxes", []))


def _occluded_frames(truth: SequenceTruth) -> dict[int, set[int]]:
    out: dict[int, set[int]] = {}
    for f, (ids, _) in truth.ignore.items():
        for i in ids:
            out.setdefault(int(i), set()).add(f)
    return out


def evaluate_tracking(data_dir: Path, variants: Iterable[TrackingVariant], *, fps: float = 30.0,
                      reid_horizon_s: float = 30.0, size_filter: SizeFilter | None = None) -> dict[str, dict[str, Any]]:
    """MOT metrics and re-ID counts of each variant on one simulated dataset (all its videos)."""
    dataset = Dataset.load(data_dir / "images.json")
    candidates = Candidates.load(data_dir / "pre_nms.json", dataset)
    camera = Camera.from_file(data_dir / "camera.json")
    variants = list(variants)
    by_variant: dict[str, dict[str, Any]] = {v.name: {"seqs": [], "reid": [], "seconds": 0.0, "frames": 0,
                                                       "reidentified": 0, "pos_err": []} for v in variants}
    pipelines: dict[PipelineConfig, list[TrackingVariant]] = {}
    for v in variants:
        pipelines.setdefault(v.pipeline, []).append(v)
    hidden = _hidden_boxes(data_dir)
    for video_id in dataset.videos:
        truth = sequence_truth(dataset, video_id, fps, hidden)
        occluded = _occluded_frames(truth)
        for pipe_cfg, vs in pipelines.items():
            frames = pipeline_frames(dataset, candidates, camera, video_id, pipe_cfg, size_filter)
            for v in vs:
                seq = drop_ignored(truth, run_tracker_on_frames(frames, v, dataset.categories, fps))
                acc = by_variant[v.name]
                acc["seqs"].append(trackeval_data(truth, seq))
                acc["reid"].append(reid_events(truth, seq, horizon_s=reid_horizon_s, occluded=occluded))
                acc["seconds"] += seq.seconds
                acc["frames"] += len(frames)
                acc["reidentified"] += seq.reidentified
                acc["pos_err"].append(position_errors(truth, seq))
    kinds = {v.name: v.kind for v in variants}
    out: dict[str, dict[str, Any]] = {}
    for name, acc in by_variant.items():
        m = mot_metrics(acc["seqs"])
        reid = {k: sum(r[k] for r in acc["reid"]) for k in ("events", "scored", "kept")}
        # ground error of the reported positions, pooled over the videos; a pixel tracker has none (None)
        pos = (summarise_position_errors(np.concatenate(acc["pos_err"])) if kinds[name] == "gps"
               else {"pos_err_m": None, "pos_err_p90_m": None, "pos_err_n": None})
        out[name] = {**m, "reid_events": reid["events"], "reid_scored": reid["scored"], "reid_kept": reid["kept"],
                     "tracker_ms_per_frame": 1000 * acc["seconds"] / max(acc["frames"], 1),
                     "reidentified": acc["reidentified"], **pos}
    return out


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------

_METRICS = ("HOTA", "DetA", "AssA", "MOTA", "IDF1", "IDs", "Frag", "FP", "FN")


def run_track_eval(scenarios: list[str], seeds: list[int], frames: int | None = None,
                   out_dir: Path = Path("out/eval-tracking"), progress: Callable[[str], None] | None = None, *,
                   variants: list[TrackingVariant] | None = None) -> dict[str, Any]:
    """Evaluate tracking on every scenario x seed; returns the report (also report.json/.md in out_dir).

    Datasets are simulated once and cached in out_dir/data (`sim.evaluate.ensure_dataset`).
    """
    from sim.evaluate import ensure_dataset

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    variants = variants or default_tracking_variants()
    rows: list[dict[str, Any]] = []
    jobs = [(s, seed) for s in scenarios for seed in seeds]
    t0 = time.perf_counter()
    for i, (scenario, seed) in enumerate(jobs):
        if progress:
            progress(f"[{i + 1}/{len(jobs)}] tracking {scenario} seed={seed}")
        data_dir = ensure_dataset(scenario, seed, frames, 1.0, out_dir / "data")
        for name, m in evaluate_tracking(data_dir, variants).items():
            rows.append({"scenario": scenario, "seed": seed, "variant": name, **m})
    report = {"scenarios": scenarios, "seeds": seeds, "frames": frames, "rows": rows,
              "summary": summarise_tracking(rows, baseline=variants[0].name),
              "seconds": round(time.perf_counter() - t0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    (out_dir / "report.md").write_text(markdown_tracking_report(report))
    return report


def summarise_tracking(rows: list[dict[str, Any]], baseline: str) -> list[dict[str, Any]]:
    """Mean over seeds per (scenario, variant); re-ID rate pooled over seeds; IDs change vs baseline; ground
    error of the reported positions (`pos_err_m`, `pos_err_p90_m`): mean over seeds of each seed's figure,
    None for a tracker without ground positions."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["variant"]), []).append(r)
    out = []
    for (scenario, variant), rs in groups.items():
        s: dict[str, Any] = {"scenario": scenario, "variant": variant, "seeds": len(rs)}
        for k in _METRICS:
            s[k] = statistics.fmean(r[k] for r in rs)
        s["HOTA_sd"] = statistics.stdev([r["HOTA"] for r in rs]) if len(rs) > 1 else 0.0
        for k in ("reid_events", "reid_scored", "reid_kept"):
            s[k] = sum(r[k] for r in rs)
        s["reid_rate"] = 100 * s["reid_kept"] / s["reid_scored"] if s["reid_scored"] else float("nan")
        s["tracker_ms_per_frame"] = statistics.fmean(r["tracker_ms_per_frame"] for r in rs)
        for k in ("pos_err_m", "pos_err_p90_m"):
            s[k] = mean_known([r.get(k) for r in rs])
        base = groups.get((scenario, baseline))
        if base:
            b_ids = statistics.fmean(r["IDs"] for r in base)
            s["IDs_change_pct"] = 100 * (s["IDs"] - b_ids) / b_ids if b_ids else float("nan")
        out.append(s)
    return out


def markdown_tracking_report(report: dict[str, Any]) -> str:
    """The summary as a Markdown table."""
    lines = [
        "# uavmm eval: multi-object tracking (simulated data)", "",
        f"Seeds {report['seeds']}; frames per video: {report['frames'] or 'scenario default'}; mean over seeds "
        "(HOTA +- sd). TrackEval 1.3.0 HOTA / CLEAR / Identity at IoU 0.5. Re-ID: objects that left the view "
        "(1-30 s) and were tracked before and after, kept = same id (pooled over seeds). Pos err: metres between "
        "a reported track's ground position and the truth of the object its box matches (IoU >= 0.5), median "
        "and 90th percentile (ours only: norfair reports no ground positions).", "",
        "| scenario | tracker | HOTA | DetA | AssA | MOTA | IDF1 | IDs | dIDs | Frag | re-ID kept | ms/frame | "
        "pos err m | pos err p90 m |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in report["summary"]:
        d_ids = s.get("IDs_change_pct")
        d_ids_text = "-" if d_ids is None or d_ids != d_ids else f"{d_ids:+.0f} %"
        lines.append(
            f"| {s['scenario']} | {s['variant']} | {s['HOTA']:.1f} +- {s['HOTA_sd']:.1f} | {s['DetA']:.1f} | "
            f"{s['AssA']:.1f} | {s['MOTA']:.1f} | {s['IDF1']:.1f} | {s['IDs']:.1f} | {d_ids_text} | {s['Frag']:.1f} | "
            f"{s['reid_kept']}/{s['reid_scored']} ({s['reid_rate']:.0f} %) | {s['tracker_ms_per_frame']:.2f} | "
            f"{format_metres(s.get('pos_err_m'))} | {format_metres(s.get('pos_err_p90_m'))} |")
    return "\n".join(lines) + "\n"

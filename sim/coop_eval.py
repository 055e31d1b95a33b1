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
from agent.dataset import Candidates, Dataset
from agent.file_frames import prepared_frames
from agent.memory_map import JointLayer
from agent.node import state_message, tracks_message
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.tile_updates import TileChangeTracker
from agent.track_lending import TrackLending
from agent.tracking import GpsTracker
from agent.tracking_io import memory_evidence
from fusion_server.joint_map import JointMap
from fusion_server.rules import get_fusion_rule
from shared.geo import Camera, Pose
from shared.messages import JointTracksMessage, TracksMessage
from shared.tilecodec import decode_tile
from sim.coop_peaks import PEAK_BAR_M, PeakSampler, standing_objects
from sim.coop_registration import RegistrationRecord, registration_errors
from sim.cross_uav import CROSS_METRICS, CrossUavRecorder, cross_uav_metrics, frame_clock_tracker
from sim.position_error import summarise_position_errors
from sim.terrain_eval import DEM_SUFFIX, terrain_of
from sim.track_eval import (
    SequenceTracks,
    SequenceTruth,
    drop_ignored,
    mot_metrics,
    position_errors,
    sequence_truth,
    trackeval_data,
)

PUBLISH_PERIOD_S = 0.2  # the agent's default 5 Hz
SCORE_THRESHOLD = 0.25  # "reported to the user": the operating threshold of sim.evaluate
JOINT_TTL_S = 2.0  # the fusion server's default --ttl-s
BOTH = "both"  # the peak rows of the objects any UAV sees
TRACK_FPS = 30.0  # the simulator's frame rate (HOTA's per-frame truth)
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
                state = state_message(uav, t, pose, camera, range_m=pipe.config.range_limit_m,
                                      terrain=pipe.terrain_for(pose))
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
             coverage: str = "footprint", track_boxes: dict[int, list[list[float]]] | None = None,
             dem: bool = False, on_publish: Callable[[float, JointMap, list[int]], None] | None = None,
             tracks_out: dict[int, SequenceTracks] | None = None,
             registration_out: dict[int, list[RegistrationRecord]] | None = None,
             size_filter: SizeFilter | None = None,
             on_tracks: Callable[[int, int, TracksMessage], None] | None = None,
             poses_out: dict[int, dict[float, tuple[Pose, Camera]]] | None = None) -> dict[int, list[dict]]:
    """Run both UAVs of a simultaneous dataset; returns COCO results per video id.

    share: give each UAV the joint map (fusion `rule` with `coverage`, see `CoopFusion`).
    track_boxes: when given, each UAV also runs the GPS tracker (defaults) and this dict receives, per
    image id, the boxes [x, y, w, h] of the confirmed tracks matched in that frame.
    tracks_out: when given, each UAV also runs the GPS tracker and this dict receives per video id the tracks
    it reports (`GpsTracker.report`: MOT rows and their ground positions) for `sim.track_eval`'s metrics.
    dem: georeference on the dataset's DEM (dem.npz) with each UAV's take-off elevation from truth.json
    (`sim.terrain_eval.terrain_of`), as `--dem FILE --takeoff-elevation-m` does; else over flat earth.
    on_publish: with share, called after each publish cycle with its time, the fusion server's joint map and
    the image ids of the frames just processed (e.g. `sim.coop_peaks.PeakSampler`).
    registration_out: with share, receives per video id each frame's joint registration estimate and telemetry
    correction (`sim.coop_registration.registration_errors` compares them with the truth).
    size_filter: every UAV's fitted size filter (a `uavmm tune` parameters file's; None: the built-in priors).
    on_tracks: when given, each UAV also runs the GPS tracker and this receives, every frame in time order, the
    video id, the frame index and the tracks message its agent would publish then (`agent.node.tracks_message`;
    e.g. `sim.cross_uav.CrossUavRecorder`, the fusion server's global tracks).
    poses_out: receives per video id the pose and camera each frame with a pose was given, by frame time rounded
    to 0.1 ms (`sim.coop_registration.registration_errors` compares them with the truth).
    Each UAV reads its recording as `uavmm agent --dataset` does (`agent.file_frames.prepared_frames`: the
    telemetry stages on the whole video, its pipeline primed on it).
    """
    dataset = Dataset.load(data_dir / "images.json")
    candidates = Candidates.load(data_dir / "pre_nms.json", dataset)
    camera = Camera.from_file(data_dir / "camera.json")
    uav_of = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    for vid in dataset.videos:
        uav_of.setdefault(vid, str(vid))
    configs = {vid: dataclasses.replace(config, terrain=terrain_of(data_dir, vid)) if dem else config
               for vid in dataset.videos}
    joints = {vid: JointLayer(ttl_s=JOINT_TTL_S) for vid in dataset.videos}
    pipes = {vid: DetectionPipeline(camera, dataset.categories, configs[vid], size_filter=size_filter,
                                    joint=joints[vid] if share else None)
             for vid in dataset.videos}
    fusion = CoopFusion([uav_of[v] for v in pipes], list(dict.fromkeys(dataset.categories.values())),
                        {uav_of[v]: p for v, p in pipes.items()}, rule=rule, coverage=coverage) if share else None
    # the fusion server's global tracks as each agent receives them, for lending a partner's confidence along them
    server = ServerTracks() if share and any(c.track_lending > 0 for c in configs.values()) else None
    lending = {vid: TrackLending(uav_of[vid], configs[vid].track_lending) for vid in dataset.videos} if server else {}
    trackers = {vid: GpsTracker(None, dataset.categories, evidence_at=memory_evidence(pipes[vid]))
                for vid in dataset.videos} if server is not None or any(
        x is not None for x in (track_boxes, tracks_out, on_tracks)) else {}
    if tracks_out is not None:
        tracks_out.update({vid: SequenceTracks() for vid in dataset.videos})
    # as `uavmm agent --dataset` reads a recording: the telemetry stages over the whole video, the pipeline primed
    iters = {vid: iter([frame for frame, _ in prepared_frames(dataset, camera, vid, candidates, configs[vid],
                                                              pipes[vid])])
             for vid in dataset.videos}
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
            if registration_out is not None and frame.pose is not None:
                offset = pipes[vid].joint_registration_offset_px()
                if offset is not None:
                    c = res.correction
                    registration_out.setdefault(vid, []).append(
                        (frame.t, *offset, c.east_m if c is not None else 0.0, c.north_m if c is not None else 0.0))
            if trackers:
                tracks = trackers[vid].update(res, frame.pose, frame.t, frame.camera, pose_t=frame.pose_t,
                                              pose_retimed=frame.pose_retimed,
                                              terrain=pipes[vid].terrain_for(frame.pose))
                if server is not None:  # as `uavmm agent` writes its detections: after the tracker, lent
                    res = lending[vid].apply(res, tracks, server.joint, frame.t)
                    server.latest[vid] = tracks_message(uav_of[vid], frame.t, tracks, pipes[vid].class_names)
                if track_boxes is not None:
                    track_boxes[frame.image.id] = [[b[0], b[1], b[2] - b[0], b[3] - b[1]] for b in
                                                   (tr.box_xyxy for tr in tracks if tr.confirmed and tr.matched)]
                if tracks_out is not None:
                    _record_tracks(tracks_out[vid], frame.image.frame_index, trackers[vid].report(tracks))
                if on_tracks is not None:
                    on_tracks(vid, frame.image.frame_index,
                              tracks_message(uav_of[vid], frame.t, tracks, pipes[vid].class_names))
            results[vid].extend(results_to_coco(frame.image.id, res))
            if frame.pose is not None:
                poses[uav_of[vid]] = (frame.pose, frame.camera)
                if poses_out is not None:
                    poses_out.setdefault(vid, {})[round(frame.t, 4)] = (frame.pose, frame.camera)
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
            if server is not None:  # each agent's tracks message of this cycle, and the server's answer
                server.publish(t, lending)
            if on_publish is not None:
                on_publish(t, fusion.joint, [f.image.id for f in step.values()])
            next_publish = t + PUBLISH_PERIOD_S
    return results


class ServerTracks:
    """The fusion server's global tracker (`uavmm fusion`'s defaults) on the frame clock of an in-process run:
    `latest` holds each UAV's newest tracks message; `publish` sends them (each agent's publish cycle), tells each
    UAV's TrackLending what it reported, and makes `joint` the ``joint/tracks`` message the agents then hold."""

    def __init__(self) -> None:
        self.now = float("-inf")
        self.tracker = frame_clock_tracker(lambda: self.now)
        self.latest: dict[int, TracksMessage] = {}
        self.joint: JointTracksMessage | None = None

    def publish(self, t: float, lending: dict[int, TrackLending]) -> None:
        self.now = max(self.now, t)
        self.tracker.expire(self.now)
        for vid, msg in self.latest.items():
            self.tracker.update(msg, self.now)
            lending[vid].reported(msg)
        self.latest = {}
        self.joint = self.tracker.joint_message()


def _record_tracks(seq: SequenceTracks, frame_index: int, reported: list) -> None:
    """One frame's reported tracks as `sim.track_eval.run_tracker_on_frames` keeps them."""
    seq.frames[frame_index] = (np.array([tr.id for tr in reported], dtype=np.int64),
                               np.array([tr.box_xyxy for tr in reported], dtype=np.float64).reshape(-1, 4),
                               np.array([tr.score for tr in reported], dtype=np.float64))
    seq.latlon[frame_index] = np.array([(tr.lat, tr.lon) for tr in reported], dtype=np.float64).reshape(-1, 2)


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


def _variants(terrain: bool, base: PipelineConfig) -> list[tuple[str, PipelineConfig, bool, bool]]:
    """(name, config, share, dem) of each run: the four variants over flat earth, and with the DEM over a terrain;
    base: the memory map's settings (the defaults, or `--config`)."""
    flat = [
        ("baseline", dataclasses.replace(base, use_memory=False), False),
        ("own memory map", base, False),
        ("joint map boosting", dataclasses.replace(base, joint_detections=False), True),
        ("joint map + joint detections", base, True),
    ]
    out = [(name, config, share, False) for name, config, share in flat]
    if terrain:
        out += [(name + DEM_SUFFIX, config, share, True) for name, config, share in flat]
    return out


def evaluate_coop(data_dir: Path, config: PipelineConfig | None = None, *, variants: tuple[str, ...] | None = None,
                  track: bool = True, size_filter: SizeFilter | None = None,
                  cross_rows: list[dict[str, Any]] | None = None,
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per UAV: baseline, own memory map, joint map boosting only, joint map + joint detections (over a terrain
    each also with the DEM, `+ DEM`); and the joint map's peaks against the truth for the variants that share.

    Metrics: AP50 with the hidden objects as ground truth (does the UAV report everything in its view?),
    AP50 with them as ignore regions, AP50 without them (a detection of one is a false positive), and
    the share of hidden-object boxes detected. Peaks (`sim.coop_peaks`): the joint map's object candidates as
    the REST API's /v1/objects finds them, once a second, matched to the objects standing in view. The joint
    registration against the truth (`sim.coop_registration`, variants with joint detections over flat ground):
    registration_offset_px, the others' evidence's median offset in this UAV's image, and registration_left_px,
    what the registration leaves of it.
    config: the variants' settings (default PipelineConfig()). variants: run only these of the names (the DEM
    variants follow their flat names); track: run the GPS tracker (hidden tracked, HOTA, IDs and track position
    error; NaN without); size_filter: a fitted size filter for every variant (None: the built-in priors).
    cross_rows: with track, receives per variant the fusion server's global ids over all UAVs
    (`sim.cross_uav.cross_uav_metrics`: one id per object across UAVs, against each UAV's ids kept apart).
    Returns (rows per UAV and variant, rows per sharing variant with the peak figures).
    """
    from sim.metrics import coco_detection_metrics

    dataset = Dataset.load(data_dir / "images.json")
    gt_hidden, hidden = _hidden_ground_truth(data_dir, dataset)
    gt_ignored, _ = _hidden_ground_truth(data_dir, dataset, ignore=True)
    standing = standing_objects(data_dir, dataset.coco["annotations"], dataset.categories)
    seen: dict[int, set[int]] = defaultdict(set)
    for a in dataset.coco["annotations"]:  # what some UAV sees: an object hidden from all has no evidence
        seen[a["image_id"]].add(a["track_id"])
    videos = {v["id"]: v.get("uav", str(v["id"])) for v in dataset.coco.get("videos", [])}
    uav_of_image = {im.id: videos.get(vid, str(vid)) for vid, images in dataset.videos.items() for im in images}
    if variants is not None:
        unknown = sorted(set(variants) - set(_ORDER))
        if unknown:
            raise ValueError(f"evaluate_coop: unknown variant(s) {', '.join(unknown)}; valid: {', '.join(_ORDER)}")
    runs, peak_rows = {}, []
    recorders: dict[str, CrossUavRecorder | None] = {}
    tracked: dict[str, dict[int, list[list[float]]]] = {}
    sequences: dict[str, dict[int, SequenceTracks]] = {}
    registration: dict[str, dict[str, dict[str, float]]] = {}
    terrain = (data_dir / "dem.npz").exists()
    for name, variant, share, dem in _variants(terrain, config or PipelineConfig()):
        if variants is not None and name.removesuffix(DEM_SUFFIX) not in variants:
            continue
        tracked[name], sequences[name] = {}, {}
        # the joint map is the same with and without joint detections (they add boxes, not evidence):
        # its peaks are measured with the default variant
        sampler = PeakSampler(standing, seen, uav_of_image) if share and variant.joint_detections else None
        # the registration's truth is computed over flat ground (sim.coop_registration): not over a terrain
        records: dict[int, list[RegistrationRecord]] | None = {} if sampler is not None and not terrain else None
        given: dict[int, dict[float, tuple[Pose, Camera]]] | None = {} if records is not None else None
        recorders[name] = CrossUavRecorder() if track and cross_rows is not None else None
        runs[name] = run_coop(data_dir, variant, share=share, track_boxes=tracked[name] if track else None, dem=dem,
                              on_publish=sampler, tracks_out=sequences[name] if track else None,
                              registration_out=records, size_filter=size_filter, on_tracks=recorders[name],
                              poses_out=given)
        if records is not None:
            registration[name] = registration_errors(data_dir, records, given)
        if sampler is not None:  # the objects any UAV sees, and those each sees
            for uav in (BOTH, *sorted(set(uav_of_image.values()))):
                peak_rows.append({"variant": name, "uav": uav, "standing_objects": len(standing),
                                  **sampler.summary(None if uav == BOTH else uav)})
    rows = []
    truths: dict[int, SequenceTruth] = {}
    kept: dict[str, dict[int, SequenceTracks]] = defaultdict(dict)  # the tracks without those on hidden objects
    for vid, uav in videos.items():
        image_ids = [im.id for im in dataset.videos[vid]]
        id_set = set(image_ids)
        hidden_v = [h for h in hidden if h["image_id"] in id_set]
        # hidden objects: distractors, as in tracking
        truth = sequence_truth(dataset, vid, TRACK_FPS, hidden_v) if track else None
        for name, per_video in runs.items():
            res = per_video[vid]
            mot = pos = None
            if truth is not None:
                seq = kept[name][vid] = drop_ignored(truth, sequences[name][vid])
                truths[vid] = truth
                mot = mot_metrics([trackeval_data(truth, seq)])
                pos = summarise_position_errors(position_errors(truth, seq))
            rows.append({
                "uav": uav, "variant": name, "hidden_boxes": len(hidden_v),
                "AP50": 100 * coco_detection_metrics(gt_hidden, res, image_ids=image_ids)["AP50"],
                "AP50_hidden_ignored": 100 * coco_detection_metrics(gt_ignored, res, image_ids=image_ids)["AP50"],
                "AP50_hidden_as_fp": 100 * coco_detection_metrics(dataset.coco, res, image_ids=image_ids)["AP50"],
                "hidden_detected": 100 * _hidden_detected(res, hidden_v) if hidden_v else float("nan"),
                "hidden_tracked": (100 * _hidden_hit_rate(tracked[name], hidden_v) if hidden_v and track
                                   else float("nan")),
                "HOTA": mot["HOTA"] if mot else float("nan"), "IDs": mot["IDs"] if mot else 0,
                "pos_err_m": float("nan") if pos is None or pos["pos_err_m"] is None else pos["pos_err_m"],
                # the joint registration against the truth (sim.coop_registration), variants with joint detections
                "registration_offset_px": registration.get(name, {}).get(uav, {}).get("offset_px", float("nan")),
                "registration_left_px": registration.get(name, {}).get(uav, {}).get("left_px", float("nan")),
            })
    for name, recorder in recorders.items():
        if recorder is not None and cross_rows is not None:
            cross_rows.append({"variant": name, **cross_uav_metrics(truths, kept[name], recorder.gids,
                                                                     recorder.first_look_gids)})
    return rows, peak_rows


def run_coop_eval(seeds: list[int], *, frames: int | None = None, out_dir: Path = Path("out/eval/coop"),
                  progress: Callable[[str], None] | None = None, scenarios: tuple[str, ...] = ("coop",),
                  noise_scales: tuple[float, ...] = (1.0,), config: PipelineConfig | None = None,
                  size_filter: SizeFilter | None = None) -> dict[str, Any]:
    """Evaluate simultaneous scenarios (`coop`; `coop-slope`, over a terrain, also with the DEM) over seeds and
    telemetry noise scales; writes report.json and report.md to out_dir. config: the variants' settings
    (`uavmm eval --tasks coop --config PARAMS.json`; default PipelineConfig()); size_filter: the fitted size
    filter such a parameters file carries (None: the built-in priors), recorded in the report."""
    from sim.coop_report import coop_markdown
    from sim.evaluate import ensure_dataset

    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows, peak_rows, cross_rows = [], [], []
    jobs = [(sc, noise, seed) for sc in scenarios for noise in noise_scales for seed in seeds]
    for i, (scenario, noise, seed) in enumerate(jobs):
        if progress:
            progress(f"[{i + 1}/{len(jobs)}] {scenario} seed={seed} noise x{noise:g}")
        data_dir = ensure_dataset(scenario, seed, frames, noise, out_dir / "data")
        cross: list[dict[str, Any]] = []
        det, peaks = evaluate_coop(data_dir, config, size_filter=size_filter, cross_rows=cross)
        tag = {"scenario": scenario, "noise_scale": noise, "seed": seed}
        rows += [{**tag, **r} for r in det]
        peak_rows += [{**tag, **r} for r in peaks]
        cross_rows += [{**tag, **r} for r in cross]
    summary = _mean_rows(rows, ("scenario", "noise_scale", "uav", "variant"), _METRICS)
    peak_summary = _mean_rows(peak_rows, ("scenario", "noise_scale", "variant", "uav"), _PEAK_METRICS)
    cross_summary = _mean_rows(cross_rows, ("scenario", "noise_scale", "variant"), CROSS_METRICS)
    report = {"scenarios": list(scenarios), "seeds": seeds, "noise_scales": list(noise_scales), "frames": frames,
              **settings_record(config, size_filter),
              "rows": rows, "summary": summary, "peak_rows": peak_rows, "peak_summary": peak_summary,
              "cross_rows": cross_rows, "cross_summary": cross_summary,
              "acceptance": slope_acceptance(summary, peak_summary),
              "seconds": round(time.perf_counter() - t0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    (out_dir / "report.md").write_text(coop_markdown(report))
    return report


def settings_record(config: PipelineConfig | None, size_filter: SizeFilter | None) -> dict[str, Any]:
    """A report's record of what --config changed: config_overrides and the fitted size filter (or None)."""
    return {"config_overrides": config_overrides(config),
            "size_filter": None if size_filter is None else size_filter.to_dict()}


def config_overrides(config: PipelineConfig | None) -> dict[str, Any]:
    """The settings of config that differ from the defaults (JSON values; repr where a value is not one)."""
    if config is None:
        return {}
    default = PipelineConfig()
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if value != getattr(default, f.name):
            out[f.name] = value if isinstance(value, (bool, int, float, str, type(None))) else repr(value)
    return out


def _mean_rows(rows: list[dict[str, Any]], keys: tuple[str, ...], metrics: tuple[str, ...]) -> list[dict[str, Any]]:
    """Per distinct value of keys (in the order rows first have them, variants in _ORDER), the mean over seeds
    of each metric, NaNs left out (NaN when all are)."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    first: dict[tuple[str, Any], int] = {}  # each key's values in the order the rows first have them
    for r in rows:
        for k in keys:
            first.setdefault((k, r[k]), len(first))
    order = sorted(groups, key=lambda g: tuple(_variant_rank(v) if k == "variant" else first[(k, v)]
                                               for k, v in zip(keys, g, strict=True)))
    out = []
    for group in order:
        rs = groups[group]
        out.append({**dict(zip(keys, group, strict=True)), **{
            m: statistics.fmean(r[m] for r in rs if r[m] == r[m]) if any(r[m] == r[m] for r in rs) else float("nan")
            for m in metrics}})
    return out


def _variant_rank(name: str) -> int:
    dem = name.endswith(DEM_SUFFIX)
    base = name[:-len(DEM_SUFFIX)] if dem else name
    return _ORDER.index(base) + (len(_ORDER) if dem else 0) if base in _ORDER else 2 * len(_ORDER)


def slope_acceptance(summary: list[dict[str, Any]], peak_summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The bars of two UAVs over a terrain, per scenario and noise scale with DEM rows: the joint map's median
    peak error with the DEM <= PEAK_BAR_M (joint map + joint detections; over the objects each UAV sees), and
    each UAV's AP50 and HOTA with the DEM not below flat earth (every variant that has a DEM twin).
    [{criterion, value, bar, ok}]."""
    out: list[dict[str, Any]] = []
    joint = "joint map + joint detections"
    for p in peak_summary:
        if p["variant"] == joint + DEM_SUFFIX and p.get("uav", BOTH) != BOTH and p["peak_err_m"] == p["peak_err_m"]:
            out.append({"criterion": f"{p['scenario']} x{p['noise_scale']:g} {p['uav']}: joint-map peak error "
                                     "with DEM, median m",
                        "value": p["peak_err_m"], "bar": f"<= {PEAK_BAR_M:g}", "ok": p["peak_err_m"] <= PEAK_BAR_M})
    by = {(s["scenario"], s["noise_scale"], s["uav"], s["variant"]): s for s in summary}
    for (scenario, noise, uav, variant), s in by.items():
        if not variant.endswith(DEM_SUFFIX):
            continue
        flat = by.get((scenario, noise, uav, variant[:-len(DEM_SUFFIX)]))
        if flat is None:
            continue
        for metric in ("AP50", "HOTA"):
            gain = s.get(metric, float("nan")) - flat.get(metric, float("nan"))
            if gain == gain:
                out.append({"criterion": f"{scenario} x{noise:g} {uav} {variant[:-len(DEM_SUFFIX)]}: {metric} with "
                                         "DEM - flat", "value": gain, "bar": ">= 0", "ok": gain >= 0})
    return out


_ORDER = ("baseline", "own memory map", "joint map boosting", "joint map + joint detections")
_METRICS = ("AP50", "AP50_hidden_ignored", "AP50_hidden_as_fp", "hidden_detected", "hidden_tracked", "HOTA", "IDs",
            "pos_err_m")
_PEAK_METRICS = ("peak_err_m", "peak_err_p90_m", "objects_with_peak", "objects_within_bar", "extra_peaks",
                 "standing_objects")

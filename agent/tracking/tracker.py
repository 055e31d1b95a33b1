"""The tracker: one frame at a time, the stages (association, re-identification, track life) run in order
on the track tables, and every active track comes out as a `TrackOutput`.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.frame_result import FrameResult
from agent.stage_report import StageReport
from agent.tracking import registration, reid
from agent.tracking.association import (
    associate_centres,
    associate_ground,
    associate_image,
    associate_iou,
    expected_boxes,
    frame_detections,
    fresh_in_image,
    ground_duplicates,
    note_image_offsets,
    resolve_alternatives,
)
from agent.tracking.config import TrackerConfig
from agent.tracking.far_points import fill_far_points, measure_image_shift, place_far_tracks, placed_rows
from agent.tracking.gimbal_rates import GimbalRates
from agent.tracking.lifecycle import birth, decay_unseen_quality, merge_duplicates, reanchor, retire
from agent.tracking.model import FloatArray, MotionModels, ground_measurement_cov, predict_constant_velocity
from agent.tracking.registration import (
    correction_jacobian,
    correction_offset,
    fit_pose_correction,
    image_pairs,
    track_offset,
)
from agent.tracking.state import EvidenceFn, FrameDetections, TrackState
from agent.tracking.view_jump import ViewJumpGuard
from shared.geo import Camera, GroundSurface, Pose, latlon_to_local, local_to_latlon

__all__ = ["GpsTracker", "TrackOutput"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TrackOutput:
    """One track's state after a frame.

    Attributes
    ----------
    id : int
        Track id, unique per tracker, starting at 1; a re-identified object gets its old id back.
    cls : int
        Class (category) id.
    box_xyxy : tuple of 4 float
        Image box, pixels: the detection matched in this frame, else the last matched one.
    lat, lon : float
        Filtered ground position, degrees; NaN without one (no pose yet, or a loose far track).
    vel_en : tuple of 2 float
        Filtered ground velocity (east, north), m/s.
    score : float
        Boosted confidence of the last matched detection.
    confirmed : bool
        Confirmed (matched in `confirm_hits` frames, or re-identified).
    matched : bool
        A detection was assigned to this track in this frame.
    hits : int
        Frames matched so far.
    time_since_update_s : float
        Seconds since the last matched detection (0 when matched).
    reidentified : bool
        The track was revived from the re-ID memory in this frame.
    quality : float
        Running mean of the detector's own confidence (raw score) over the matched detections.
    loose : bool
        The ground position comes from loose far points only, beyond the tracker's reach
        (`TrackerConfig.far_loose_gate`): tens to hundreds of metres off, so lat / lon are NaN (no GeoJSON or KML
        feature, not sent to the fusion server); the MOT rows have the track.
    """

    id: int
    cls: int
    box_xyxy: tuple[float, float, float, float]
    lat: float
    lon: float
    vel_en: tuple[float, float]
    score: float
    confirmed: bool
    matched: bool
    hits: int = 0
    time_since_update_s: float = 0.0
    reidentified: bool = False
    quality: float = 0.0
    loose: bool = False


class GpsTracker:
    """Multi-object tracker on the ground plane with long-term re-identification.

    Parameters
    ----------
    config : TrackerConfig, optional
    class_names : dict, optional
        Class id -> name, to look up each class's motion model (`TrackerConfig.class_motion`).
    evidence_at : callable, optional
        (class id, lat (N,), lon (N,)) -> (N,) memory-map evidence; with
        `TrackerConfig.reid_min_evidence` > 0 a re-identification needs that much evidence.
    first_id : int
        Id of the first new track (1, as MOTChallenge counts); the live agent starts each run elsewhere
        so ids stay unique across restarts (`agent.node.run_first_track_id`).

    Use one tracker per video; `update` must be called with non-decreasing times.
    """

    def __init__(self, config: TrackerConfig | None = None, class_names: dict[int, str] | None = None,
                 *, evidence_at: EvidenceFn | None = None, first_id: int = 1) -> None:
        if isinstance(first_id, bool) or not isinstance(first_id, int) or not 0 <= first_id < 2**62:
            raise ValueError(f"first_id must be an int in 0..2**62-1, got {first_id!r}")
        config = config or TrackerConfig()
        self.base_config = config
        self._intervals: deque[float] = deque(maxlen=9)  # recent frame intervals (s), for the frame floors
        self.class_names = dict(class_names or {})
        self._state = TrackState(config=config, motion=MotionModels(config, self.class_names),
                                 evidence_at=evidence_at, next_id=first_id)
        self._t: float | None = None
        self._rates = GimbalRates()  # turn rates from pose changes (telemetry often slower than the frames)
        #: The common offset (east, north) metres the last frame's ground points were moved by to meet the
        #: predicted tracks (TrackerConfig.register_tracks), None when none was applied.
        self.last_offset_en: tuple[float, float] | None = None
        #: The pose correction (east m, north m, heading deg, pitch deg) the last frame's ground points were
        #: moved by (TrackerConfig.image_register), None when none was found.
        self.last_correction: tuple[float, float, float, float] | None = None
        self._correction = np.zeros(4)
        #: What the tracks have not followed yet of the last registered correction (TrackerConfig.carry_correction).
        self._pending = np.zeros(4)
        #: True when the last frame's ground points were moved by that carried part (no registration of its own).
        self.last_correction_carried = False
        self._log_scale = 0.0  # log of the smoothed residual scale of registered frames
        self._scale_t: float | None = None
        self._uav_en = (0.0, 0.0)
        self._ground: tuple[Pose, GroundSurface | None] | None = None  # the last registered frame's pose, terrain
        self._level: float | None = None  # running mean of the frames' top raw scores (report_level_ref)
        self._jump = ViewJumpGuard()
        #: rows of the last frame's result with a ground point, the pipeline's or the tracker's own beyond the
        #: pipeline's range (agent.tracking.far_points); None for a frame without a pose. n_far_points: those so far.
        self.last_grounded: NDArray[np.bool_] | None = None
        self.n_far_points = 0

    # ----------------------------------------------------------------------------- views
    @property
    def config(self) -> TrackerConfig:
        """The tracker's settings in use: those given at construction (`base_config`), their windows floored to
        the measured frame interval (`TrackerConfig.at_frame_interval`; unchanged at 24 fps and faster)."""
        return self._state.config

    def _follow_frame_interval(self, dt: float) -> None:
        """Track the median frame interval and floor the config's windows to it."""
        if dt <= 0:
            return
        self._intervals.append(dt)
        median = float(np.median(self._intervals))
        config = self.base_config.at_frame_interval(median)
        if config is not self._state.config and config != self._state.config:
            self._state.config = config

    @property
    def evidence_at(self) -> EvidenceFn | None:
        """The memory-map evidence lookup re-identification asks, or None."""
        return self._state.evidence_at

    @property
    def frames_in_jump(self) -> int:
        """Frames so far inside a view jump (`TrackerConfig.jump_rate_deg_s`) whose boxes were not used."""
        return self._jump.frames - self._jump.followed - self._jump.agreed

    def stage_reports(self) -> list[StageReport]:
        """What the tracker's adaptive parts did in this video (agent.stage_report): the view-jump guard."""
        return [self._jump.report(self.config)]

    @property
    def n_reidentified(self) -> int:
        """Re-identifications so far (lost tracks that got their id back and were confirmed)."""
        return self._state.n_reidentified

    @property
    def origin(self) -> tuple[float, float] | None:
        """(lat, lon) degrees of the local east/north frame, None before the first pose."""
        return self._state.origin

    @property
    def tracks(self) -> list[TrackOutput]:
        """Active tracks (tentative and confirmed, matched or coasting) after the last update."""
        return self._outputs()

    @property
    def lost_tracks(self) -> list[TrackOutput]:
        """Tracks in the re-ID memory: the position each entered it with (its coasted prediction then, not its last
        measured one; moved with the telemetry corrections since), its velocity and the time since its last hit
        (time_since_update_s)."""
        lost = self._state.lost
        if not len(lost) or self._state.origin is None:
            return []
        lat, lon = local_to_latlon(lost["pos"][:, 0], lost["pos"][:, 1], *self._state.origin)
        now = self._t if self._t is not None else 0.0
        return [
            TrackOutput(int(lost["id"][i]), int(lost["cls"][i]), _box_tuple(lost["box"][i]), float(lat[i]),
                        float(lon[i]), (float(lost["vel"][i, 0]), float(lost["vel"][i, 1])),
                        float(lost["score"][i]), True, False, int(lost["hits"][i]),
                        float(now - lost["t_hit"][i]), False, float(lost["quality"][i]))
            for i in range(len(lost)) if not lost["claimed"][i]  # claimed: on probation among the active
        ]

    def report(self, tracks: list[TrackOutput]) -> list[TrackOutput]:
        """The tracks to report for a frame (MOT rows): confirmed, matched in this frame, and with a
        `quality` of at least `report_threshold` (`TrackerConfig.report_quality`, or less with
        report_level_ref set)."""
        q = self.report_threshold
        return [tr for tr in tracks if tr.confirmed and tr.matched and tr.quality >= q]

    @property
    def report_threshold(self) -> float:
        """The quality a track needs to be reported now: `TrackerConfig.report_quality`, scaled by the
        detector's running score level relative to report_level_ref when that is set (a blurred sweep or
        an under-confident detector lowers every score, the clutter's with the objects')."""
        cfg = self.config
        if cfg.report_level_ref <= 0 or self._level is None:
            return cfg.report_quality
        return cfg.report_quality * min(1.0, self._level / cfg.report_level_ref)

    # ----------------------------------------------------------------------------- update
    def update(self, result: FrameResult, pose: Pose | None, t: float, camera: Camera, *, pose_t: float | None = None,
               pose_retimed: bool = False, terrain: GroundSurface | None = None) -> list[TrackOutput]:
        """Advance to time t and associate one frame's detections.

        Parameters
        ----------
        result : FrameResult
            The pipeline's detections of the frame (boxes, boosted scores, classes, lat/lon, NaN where not).
        pose : Pose or None
            The frame's camera pose; None without metadata: tracks coast and detections are matched
            by image IoU with each track's last box (no ground positions, no new tracks).
        t : float
            Frame time, seconds; earlier than the previous frame is treated as the same time.
        camera : Camera
            The camera (its focal length scales the pixel error on the ground).
        pose_t : float, optional
            Time the pose was measured (the telemetry's stamp), seconds; default t. While the gimbal turns,
            detections are rotated about the UAV by turn rate * (t - pose_t + `telemetry_latency_s`).
        pose_retimed : bool
            The pose was already interpolated at the frame's time (agent.clock_offset.retime_frames, whose
            offset stands for the telemetry's latency): no turn compensation. Extrapolating it once more by
            telemetry_latency_s turned the frame's points by a turn rate differentiated from per-frame
            heading jitter (25 deg/s 1-sigma at 0.6 deg and 30 Hz) and counted the latency twice.
        terrain : GroundSurface, optional
            The detections' ground (`--dem`: DetectionPipeline.terrain_for); the in-view test of tracks uses it.

        Returns
        -------
        list of TrackOutput
            Every active track (tentative and confirmed, matched or coasting).
        """
        if not math.isfinite(t):
            raise ValueError(f"t must be finite seconds, got {t!r}")
        dt = 0.0 if self._t is None else t - self._t
        if dt < 0:
            log.debug("time went back by %.3f s; treating the frame as simultaneous", -dt)
            dt = 0.0
            t = self._t if self._t is not None else t
        self._t = t
        self._follow_frame_interval(dt)
        state = self._state
        act = state.active
        act.cols["matched"][:] = False
        act.cols["reid"][:] = False
        act.cols["strong"][:] = False
        act.cols["det_row"][:] = -1
        if len(act) and dt > 0:
            accel, _ = state.motion.accel_and_cap(act["cls"])
            predict_constant_velocity(act["x"], act["P"], dt, accel)

        dets = frame_detections(result, self.config)
        self._observe_level(dets.raw)
        if dets.emb is not None:
            state.ensure_descriptor_columns(dets.emb.shape[1])
        if pose is None:
            self.last_grounded = None
            associate_iou(state, dets, t, np.ones(len(dets.scores), dtype=bool))
        else:
            pose_t = t if pose_t is None or not math.isfinite(pose_t) else pose_t
            self._rates.update(pose, pose_t, t)
            state.heading_now = self._rates.smoothed_heading(pose.heading_deg, dt, self.config.heading_smoothing_s)
            reanchor(state, pose)
            if terrain is None:  # flat ground: what lies beyond the pipeline's range, within the error model's reach
                self.n_far_points += int(fill_far_points(dets, pose, camera, result.correction, self.config).sum())
            self.last_grounded = np.isfinite(dets.lat) & np.isfinite(dets.lon)
            # The telemetry's heading is older than the frame (by t - pose_t, plus telemetry_latency_s unless the
            # pose was retimed): the frame's points are turned about the UAV by the heading change since.
            lag_s = max(t - pose_t, 0.0) + (0.0 if pose_retimed else self.config.telemetry_latency_s)
            cap = self.config.max_heading_correction_deg
            turn_deg = max(-cap, min(cap, self._rates.heading_deg_s * lag_s))
            # in a view jump the pose does not place (agent.tracking.view_jump) the tracks coast: no match, birth, re-ID
            if self._jump.usable(state, dets, pose, turn_deg, t, camera, terrain):
                undo = None if self.config.use_pipeline_correction or result.correction is None else (
                    float(result.correction.east_m), float(result.correction.north_m))
                self._frame_with_pose(dets, pose, t, camera, turn_deg=turn_deg, dt=dt, undo_en=undo, terrain=terrain)
                merge_duplicates(state, t)
                decay_unseen_quality(state, pose, camera, terrain)
        note_image_offsets(state, t)
        reid.settle_probation(state)
        retire(state, t, camera)
        act = state.active
        act.cols["shown"] |= act["confirmed"] & act["matched"] & (act["quality"] >= self.report_threshold)
        return self._outputs()

    def _observe_level(self, raw: NDArray) -> None:
        """Follow the detector's score level: the mean of the frame's report_level_top_k highest raw scores
        (0 without detections), averaged over frames at quality_rate like a track's quality."""
        cfg = self.config
        if cfg.report_level_ref <= 0:
            return
        top = np.sort(raw[np.isfinite(raw)])[::-1][:cfg.report_level_top_k]  # a NaN score would stick
        level = float(top.mean()) if len(top) else 0.0
        self._level = level if self._level is None else self._level + cfg.quality_rate * (level - self._level)

    # ----------------------------------------------------------------------------- stages
    def _frame_with_pose(self, dets: FrameDetections, pose: Pose, t: float, camera: Camera,
                         turn_deg: float, dt: float, undo_en: tuple[float, float] | None = None,
                         terrain: GroundSurface | None = None) -> None:
        cfg = self.config
        state = self._state
        assert state.origin is not None
        geo = np.isfinite(dets.lat) & np.isfinite(dets.lon)
        dets.geo = geo
        anchored: tuple[float, float, float, float] | None = None
        carried = False
        if geo.any():
            k = int(geo.sum())  # the alternatives past a terrain edge (NaN: none) go along as k more rows
            lat, lon = dets.lat[geo], dets.lon[geo]
            if dets.alt_latlon is not None:
                lat, lon = np.r_[lat, dets.alt_latlon[geo, 0]], np.r_[lon, dets.alt_latlon[geo, 1]]
            e, n = latlon_to_local(lat, lon, *state.origin)
            if undo_en is not None:  # back to the telemetry's own ground points (use_pipeline_correction off)
                e, n = e - undo_en[0], n - undo_en[1]
            uav_e, uav_n = (float(v) for v in latlon_to_local(pose.lat, pose.lon, *state.origin))
            rel_e, rel_n = e - uav_e, n - uav_n
            # turn the ground points about the UAV by turn_deg (a flat-ground projection rotates with the heading)
            delta = math.radians(turn_deg)
            if delta:
                c, s = math.cos(delta), math.sin(delta)
                rel_e, rel_n = rel_e * c + rel_n * s, -rel_e * s + rel_n * c
            if len(rel_e) > k:
                dets.alt = np.full((len(geo), 2), np.nan)
                dets.alt[geo] = np.column_stack([rel_e[k:] - rel_e[:k], rel_n[k:] - rel_n[:k]])
                rel_e, rel_n = rel_e[:k], rel_n[:k]
            dets.z[geo, 0], dets.z[geo, 1] = rel_e + uav_e, rel_n + uav_n
            if dets.alt is not None and resolve_alternatives(state, dets, cfg.max_gate_m).any():
                rel_e, rel_n = dets.z[geo, 0] - uav_e, dets.z[geo, 1] - uav_n
            self.last_offset_en = None
            self.last_correction = None
            state.image_steady = False
            rate = abs(self._rates.heading_deg_s)
            heading_sd = math.hypot(cfg.heading_sigma_deg, rate * cfg.timing_sigma_s)
            pitch_sd = math.hypot(cfg.pitch_sigma_deg, abs(self._rates.pitch_deg_s) * cfg.timing_sigma_s)
            focal = math.sqrt(camera.fx * camera.fy)
            rel = np.column_stack([rel_e, rel_n])
            # the error models' height: the pose's over flat ground, each point's effective one over a terrain
            h: float | FloatArray = pose.height_m if dets.view_h is None else registration.model_heights(
                dets.view_h[geo], pose.height_m)
            self.last_correction_carried = False
            if cfg.image_register:
                anchored = self._apply_image_registration(dets, t, geo, rel, h, focal, heading_sd, pitch_sd)
                if anchored is None and cfg.carry_correction and np.any(self._pending):
                    carried = self._carry_correction(dets, geo, rel, h)
                if anchored is not None or carried:
                    self._uav_en = (uav_e, uav_n)
            # a turning gimbal rotates the ground points about the UAV (not a common shift): not then
            if anchored is None and cfg.register_tracks \
                    and abs(self._rates.lp_heading_deg_s) <= cfg.register_max_turn_deg_s:
                act = state.active
                confirmed = act["confirmed"] & (t - act["t_hit"] <= cfg.max_coast_s)
                strong = geo & ~dets.used & (dets.scores >= cfg.match_score)
                if confirmed.sum() >= cfg.register_min_pairs and strong.sum() >= cfg.register_min_pairs:
                    offset = track_offset(dets.z[strong], act["x"][confirmed, :2], cfg.register_gate_m,
                                          cfg.register_min_pairs)
                    if offset is not None:
                        dets.z[geo] += offset
                        self.last_offset_en = offset
            if anchored is None:
                dets.R[geo] = ground_measurement_cov(
                    rel_e, rel_n, h, focal, position_sigma_m=cfg.position_sigma_m,
                    heading_sigma_deg=heading_sd, pitch_sigma_deg=pitch_sd, height_sigma_m=cfg.height_sigma_m,
                    pixel_sigma_px=cfg.pixel_sigma_px, max_sigma_m=cfg.max_measurement_sigma_m)

        if cfg.duplicate_raw_ratio > 0 and geo.sum() > 1:
            dets.used |= ground_duplicates(dets.z, dets.R, dets.raw, dets.cls, geo & ~dets.used,
                                           cfg.duplicate_chi2, cfg.duplicate_raw_ratio)

        # 1. strong detections, confirmed tracks first (they own their object), then tentative ones;
        # 2. weak detections to confirmed tracks left over. Loose far points start tracks, but are not associated
        # by on the ground (agent.tracking.far_points).
        tight = geo if dets.loose is None else geo & ~dets.loose
        measure_image_shift(state, dets, t)  # far views: the camera's motion in the image, before the boxes are taken
        confirmed = state.active["confirmed"].copy()
        strong = tight & ~dets.used & (dets.scores >= cfg.match_score)
        if cfg.image_first_iou > 0:
            associate_image(state, dets, strong, t, confirmed, cfg.image_first_iou)
            strong &= ~dets.used
        associate_ground(state, dets, strong, t, confirmed)
        strong &= ~dets.used
        associate_ground(state, dets, strong, t, ~confirmed)
        weak = tight & ~dets.used & (dets.scores >= cfg.low_score)
        if weak.any():
            associate_ground(state, dets, weak, t, confirmed)
        # Detections without a ground point to associate by follow in the image: loose far points by their box
        # centres, those without any point (at the horizon, over a DEM beyond the pipeline's range) by IoU.
        far = ~tight & ~dets.used & (dets.scores >= cfg.match_score)
        if dets.loose is not None and (far & dets.loose).any():
            associate_centres(state, dets, t, far & dets.loose, cfg.far_loose_gate)
        if (far & ~geo).any():
            associate_iou(state, dets, t, far & ~geo)
        # 3. re-identification from the lost-track memory (at once, or deferred: reid.resolve_pending).
        # Free detections and young tracks whose id nobody has seen yet compete for the lost ids.
        cand = placed_rows(dets) & ~dets.used & (dets.entry >= cfg.reid_score)
        young = reid.unreported(state, dets, t)
        if cfg.reid_delay_s <= 0 and (cand.any() or len(young)) and len(state.lost):
            if state.evidence_at is not None and cfg.reid_min_evidence > 0:
                young_rows = np.zeros(len(cand), dtype=bool)
                young_rows[state.active["det_row"][young]] = True
                ok = reid.evidence_ok(state, cand | young_rows, dets.cls, dets.lat, dets.lon)
                cand &= ok
                young = young[ok[state.active["det_row"][young]]]
            reid.reidentify(state, dets, cand, t, young)
        # 4. births.
        cand = geo & ~dets.used & (dets.entry >= cfg.birth_score)
        if cand.any():
            birth(state, dets, cand, t)
        place_far_tracks(state, dets)
        if cfg.reid_delay_s > 0:
            reid.resolve_pending(state, t)
        if anchored is not None or carried:
            self._ground = (pose, terrain)
            self._follow_telemetry(dt, carried=carried)

    def _apply_image_registration(self, dets: FrameDetections, t: float, geo: NDArray[np.bool_], rel: FloatArray,
                                  h: float | FloatArray, focal_px: float, heading_sd_deg: float,
                                  pitch_sd_deg: float) -> tuple[float, float, float, float] | None:
        """Register the frame in the image (`_register_in_image`) and, when that worked, move its ground points
        by the correction and give them what is left of the telemetry's error: the correction's own
        uncertainty at each point, the pixel error and the floor as noisy as the pairs' residuals showed
        (smoothed over registered_scale_s), and registered_error_scale of the unregistered model's
        telemetry part. Returns the correction (east m, north m, heading deg, pitch deg) or None."""
        cfg = self.config
        fit = self._register_in_image(dets, t, geo, rel, h, focal_px, heading_sd_deg, pitch_sd_deg)
        if fit is None:
            return None
        correction, cov, scale = fit
        J = correction_jacobian(rel, h)
        dets.z[geo] += correction_offset(rel, h, correction, J)
        a = 1.0 if self._scale_t is None else 1.0 - math.exp(-max(t - self._scale_t, 0.0)
                                                           / max(cfg.registered_scale_s, 1e-6))
        self._log_scale += a * (math.log(scale) - self._log_scale)
        self._scale_t = t
        floor = cfg.registered_floor_m ** 2 * np.eye(2)
        dets.R[geo] = math.exp(self._log_scale) * (self._pixel_cov(rel, h, focal_px) + floor) \
            + J @ cov @ J.transpose(0, 2, 1)
        if cfg.registered_error_scale > 0:
            k = cfg.registered_error_scale
            dets.R[geo] += ground_measurement_cov(
                rel[:, 0], rel[:, 1], h, focal_px, position_sigma_m=k * cfg.position_sigma_m,
                heading_sigma_deg=k * heading_sd_deg, pitch_sigma_deg=k * pitch_sd_deg,
                height_sigma_m=k * cfg.height_sigma_m, pixel_sigma_px=0.0, max_sigma_m=cfg.max_measurement_sigma_m)
        self._correction = correction
        out = (float(correction[0]), float(correction[1]), math.degrees(correction[2]), math.degrees(correction[3]))
        self.last_correction = out
        self.last_offset_en = out[:2]
        log.debug("t=%.3f registered in the image: east %.2f north %.2f m, heading %.2f pitch %.2f deg", t, *out)
        return out

    def _pixel_cov(self, rel: FloatArray, h: float | FloatArray, focal_px: float) -> FloatArray:
        """(N, 2, 2) ground error of points (N, 2) relative to the UAV from the pixel error alone; h: the height
        of the error model (scalar or per point)."""
        cfg = self.config
        return ground_measurement_cov(rel[:, 0], rel[:, 1], h, focal_px, position_sigma_m=0.0,
                                      heading_sigma_deg=0.0, pitch_sigma_deg=0.0, height_sigma_m=0.0,
                                      pixel_sigma_px=cfg.pixel_sigma_px, max_sigma_m=cfg.max_measurement_sigma_m)

    def _register_in_image(self, dets: FrameDetections, t: float, geo: NDArray[np.bool_], rel: FloatArray,
                           h: float | FloatArray, focal_px: float, heading_sd_deg: float,
                           pitch_sd_deg: float) -> tuple[FloatArray, FloatArray, float] | None:
        """The frame's pose correction (east m, north m, heading rad, pitch rad) and its covariance, from its
        confident detections and the confirmed tracks they overlap in the image (TrackerConfig.image_register);
        None when the image pairs too few. rel: (G, 2) the geo detections' points relative to the UAV."""
        cfg = self.config
        act = self._state.active
        need = cfg.image_register_min_pairs
        row_of = np.full(len(geo), -1)
        row_of[geo] = np.arange(int(geo.sum()))
        strong = np.flatnonzero(geo & ~dets.used & (dets.scores >= cfg.match_score))
        if not len(act) or not len(strong):
            return None
        ti = np.flatnonzero(act["confirmed"])
        ti = ti[fresh_in_image(self._state, ti, t)]
        if not len(ti):
            return None
        pt, pd = image_pairs(expected_boxes(self._state, ti, t), act["cls"][ti], dets.boxes[strong],
                             dets.cls[strong], cfg.image_register_iou)
        # the image shows a track where it was expected: the camera did not move unlike the telemetry says
        # (at the start of a turn the telemetry lags, and every box leaves its expected place at once)
        self._state.image_steady = len(pt) >= 1
        if cfg.image_register_alone and len(ti) == 1:
            need = 1  # the one object followed: its own pair (the image says it stayed, whatever the GPS says)
        if len(pt) < need:
            return None
        ti, di = ti[pt], strong[pd]
        rel_pairs = rel[row_of[di]]
        h_pairs = np.asarray(h, dtype=np.float64)[row_of[di]] if np.ndim(h) else h
        S = act["P"][ti, :2, :2] + self._pixel_cov(rel_pairs, h_pairs, focal_px) \
            + cfg.registered_floor_m ** 2 * np.eye(2)
        prior = np.array([cfg.register_position_sd_m, cfg.register_position_sd_m,
                          math.radians(cfg.register_angle_scale * heading_sd_deg),
                          math.radians(cfg.register_angle_scale * pitch_sd_deg)])
        fit = fit_pose_correction(rel_pairs, act["x"][ti, :2] - dets.z[di], S, h_pairs, prior,
                                  cfg.gate_chi2, need, robust_scale=cfg.registered_scale_s > 0)
        return None if fit is None else (fit[0], fit[1], fit[3])

    def _carry_correction(self, dets: FrameDetections, geo: NDArray[np.bool_], rel: FloatArray,
                          h: float | FloatArray) -> bool:
        """A frame the image could not register: move its ground points by what the tracks have not yet followed
        of the last registered correction (`_pending`; TrackerConfig.carry_correction). The tracks sit that far
        from the telemetry's frame, whatever this frame's telemetry says, so the raw points would miss them by
        it (a 4-decimal GPS error of 7 m stays 7 m between two GPS steps). Not while the gimbal turns faster than
        register_max_turn_deg_s (low-pass rate): then the angle part was the telemetry's lag, which does not
        last. Returns True when applied."""
        if abs(self._rates.lp_heading_deg_s) > self.config.register_max_turn_deg_s:
            return False  # a turning gimbal: the correction's angle part was the telemetry's lag, not lasting
        dets.z[geo] += correction_offset(rel, h, self._pending)
        out = (float(self._pending[0]), float(self._pending[1]), math.degrees(self._pending[2]),
               math.degrees(self._pending[3]))
        self.last_correction = out
        self.last_offset_en = out[:2]
        self.last_correction_carried = True
        return True

    def _follow_telemetry(self, dt: float, *, carried: bool = False) -> None:
        """Move the tracks and the re-ID memory toward the telemetry's frame by the frame's pose correction
        (carried: by the part of the last one still pending), with time constant track_follow_s (what stays
        is measured again in the next frame, or carried to it)."""
        tau = self.config.track_follow_s
        gain = 1.0 if tau <= 0 else 1.0 - math.exp(-max(dt, 0.0) / tau)
        base = self._pending if carried else self._correction
        self._pending = (1.0 - gain) * base
        if gain <= 0 or self._ground is None:
            return
        state = self._state
        uav = np.asarray(self._uav_en)
        p = gain * base
        # the heights of the flat model: the pose's, or each track's effective one over a terrain (--dem)
        for pts in (state.active.cols["x"][:, :2], state.lost.cols["pos"]):
            if len(pts):
                pts += correction_offset(pts - uav, registration.point_heights(pts - uav, *self._ground), -p)

    def _outputs(self) -> list[TrackOutput]:
        act = self._state.active
        n = len(act)
        if not n:
            return []
        if self._state.origin is not None:
            lat, lon = local_to_latlon(act["x"][:, 0], act["x"][:, 1], *self._state.origin)
            # a loose far track's point may be hundreds of metres off: no position is reported for it
            lat, lon = np.where(act["loose"], np.nan, lat), np.where(act["loose"], np.nan, lon)
        else:
            lat = lon = np.full(n, np.nan)
        now = self._t if self._t is not None else 0.0
        # Python scalars column by column: building 1,000 outputs stays ~1 ms.
        cols = zip(act["id"].tolist(), act["cls"].tolist(), map(tuple, act["box"].tolist()), lat.tolist(),
                   lon.tolist(), map(tuple, act["x"][:, 2:].tolist()), act["score"].tolist(),
                   act["confirmed"].tolist(), act["matched"].tolist(), act["hits"].tolist(),
                   (now - act["t_hit"]).tolist(), act["reid"].tolist(), act["quality"].tolist(),
                   act["loose"].tolist(), strict=True)
        return [TrackOutput(*c) for c in cols]


def _box_tuple(box: NDArray) -> tuple[float, float, float, float]:
    return (float(box[0]), float(box[1]), float(box[2]), float(box[3]))

"""Per-frame detection pipeline: georeference pre-NMS boxes, size filter, memory-map boost, NMS.

Arrays in, arrays out: the same code serves `uavmm boost`, the tracker and the live agent.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from agent._kernels import georeference_and_filter, small_distinct
from agent.boxes import anchor_fraction, box_anchor_points, nms, unboost_fragments
from agent.dem import DemCoverage, takeoff_terrain
from agent.frame_result import FrameResult
from agent.joint_boost import registered_joint_evidence
from agent.joint_detections import JointCarry, JointRegistration, add_joint_detections
from agent.memory_map import JointLayer, MemoryMap, boost_scores
from agent.pipeline_config import PipelineConfig
from agent.score_calibration import ScoreCalibration
from agent.size_filter import SizeBand, SizeFilter, _warn_unfiltered, slant_and_depression
from agent.size_filter_check import SizeFilterCheck
from agent.stage_report import StageReport
from agent.telemetry_correction import GroundCorrection, GroundOffsetEstimator, register_offset
from shared.geo import (
    Camera,
    Pose,
    horizon_dip_deg,
    latlon_to_local,
    local_to_latlon,
    meridian_radius_m,
    pixel_to_local,
    prime_vertical_radius_m,
)
from shared.terrain import Terrain, edge_alternatives, effective_height_m, footprint_scale, pixel_to_terrain
from shared.tiles import TileGrid

log = logging.getLogger(__name__)

#: Bins of the size filter's sure bounds (SizeBand.sure_bounds): at 1,024 nearly every box is decided
#: by them, ~10x cheaper than the exact test at its own depression.
SURE_BINS = 1024
#: Observation time credited to the first frame of a video (no previous frame to measure from).
FIRST_FRAME_INTERVAL_S = 1.0 / 30.0


def distinct_ids(ids: NDArray) -> NDArray:
    """Sorted distinct values of an (N,) id array, as np.unique.

    Class ids span a few values: marking them in a compiled pass (agent._kernels.small_distinct) is ~30x
    faster than np.unique's sort at 5,000 boxes; other dtypes and wide ranges fall back to np.unique.
    """
    if len(ids) == 0 or ids.dtype.kind != "i":
        return np.unique(ids)
    found, ok = small_distinct(np.ascontiguousarray(ids, dtype=np.int64), 4096)
    return found.astype(ids.dtype, copy=False) if ok else np.unique(ids)


class DetectionPipeline:
    """Stateful per-video pipeline: one memory map per class, optionally a joint layer.

    class_names: category id -> class name (one map per class name).
    """

    def __init__(self, camera: Camera, class_names: dict[int, str], config: PipelineConfig | None = None,
                 *, size_filter: SizeFilter | None = None, joint: JointLayer | None = None,
                 grid: TileGrid | None = None) -> None:
        self.camera = camera
        self.class_names = dict(class_names)
        self.config = config or PipelineConfig()
        self.size_filter = size_filter if size_filter is not None else SizeFilter.builtin()
        self.grid = grid or TileGrid()
        self.memory = MemoryMap(self.config.memory, self.grid)
        self.joint = joint
        self._size_check = SizeFilterCheck(self.size_filter, self.config.size_check_settings())
        self._classes_seen: set[str] = set()  # classes with candidates in this video, for the reports
        cfg = self.config
        if joint is not None and cfg.joint_register_boost and (not cfg.joint_detections or cfg.joint_mode == "local"):
            log.warning("joint_register_boost does nothing here: it needs the joint detections' registration "
                        "(joint_detections %s, joint_mode %s)", cfg.joint_detections, cfg.joint_mode)

    @property
    def active_size_filter(self) -> SizeFilter:
        """The size filter as applied: the priors of the classes whose check against the data passed
        (agent.size_filter_check); the others pass unfiltered."""
        check = self._size_check
        if check.size_filter is not self.size_filter:  # a caller swapped the filter: check it afresh
            check = self._size_check = SizeFilterCheck(self.size_filter, self.config.size_check_settings())
        return check.active

    def prime(self, frames: Iterable[tuple[Pose | None, Camera, NDArray, NDArray, NDArray]]) -> None:
        """Let the adaptive stages judge their evidence on a whole video before its first frame (files):
        frames: (pose, camera, boxes_xyxy, scores, class_ids) per frame. The size filter's check and the
        score calibration's input check decide on it and observe no more."""
        calibration = self._calibration()
        for pose, camera, boxes, scores, cids in frames:
            scores = np.asarray(scores, dtype=np.float32).reshape(-1)
            if calibration is not None:
                calibration.check.observe(scores)
            if pose is not None and self.config.use_size_filter and len(scores):
                saved, self.camera = self.camera, camera
                try:
                    self._observe_sizes(np.asarray(boxes, dtype=np.float32).reshape(-1, 4), scores,
                                        np.asarray(cids, dtype=np.int64).reshape(-1), pose)
                finally:
                    self.camera = saved
        self._size_check.freeze()
        if calibration is not None:
            calibration.check.freeze()

    def _observe_sizes(self, boxes: NDArray[np.float32], conf: NDArray[np.float32], cids: NDArray[np.int64],
                       pose: Pose, ground: tuple[NDArray, NDArray, NDArray | None, NDArray] | None = None) -> None:
        """Show the size filter's check the frame's confident boxes and what the full prior says of them.
        ground: the boxes' ground_points when already known (over a terrain: marched once per frame)."""
        check = self._size_check
        if check.frozen:
            return
        sure = np.flatnonzero(conf >= check.settings.min_score)
        if not len(sure):
            return
        b, c = boxes[sure], cids[sure]
        if ground is None:
            east, north, up, valid = self.ground_points(b, pose)
        else:
            east, north, valid = ground[0][sure], ground[1][sure], ground[3][sure]
            up = None if ground[2] is None else ground[2][sure]
        if not valid.any():
            return
        b, c, east, north = b[valid], c[valid], east[valid], north[valid]
        slant, depression = slant_and_depression(east, north, None if up is None else up[valid], pose)
        diag = np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
        for cid in distinct_ids(c).tolist():
            name = self.class_names[cid]
            band = self.size_filter.bands.get(name)
            if band is None:
                continue
            sel = c == cid
            check.observe(name, self.size_filter.z_class(name, diag[sel], slant[sel], depression[sel],
                                                         self._focal_px))

    def terrain_for(self, pose: Pose | None) -> Terrain | None:
        """The terrain this video's boxes are georeferenced on (None: flat ground, or a frame without pose). A
        configured terrain without a take-off elevation takes the DEM's height under the video's first pose (the
        first one seen since `reset`): telemetry heights are above take-off, and a video starts over the take-off's
        ground unless --takeoff-elevation-m says otherwise. Off the DEM there, heights count from the ground below
        the UAV."""
        terrain = self.config.terrain
        if terrain is None or pose is None:
            return None
        if terrain.takeoff_elevation_m is not None:
            return terrain
        cached = self.__dict__.get("_video_terrain")
        if cached is None or cached[0] is not terrain:
            cached = self.__dict__["_video_terrain"] = (terrain, takeoff_terrain(terrain, pose))
        return cached[1]

    def ground_points(self, boxes_xyxy: NDArray, pose: Pose) -> tuple[NDArray, NDArray, NDArray | None, NDArray]:
        """Ground points of the boxes' anchors in the pose's local frame: east, north (N,) metres, up (N,) metres
        above the pose's height reference (None on flat ground: 0) and valid (N,) bool; NaN where not valid
        (no ground, or beyond the range limit)."""
        uv = box_anchor_points(boxes_xyxy, self.config.anchor, pose.pitch_deg)
        terrain = self.terrain_for(pose)
        if terrain is None:
            east, north, valid = pixel_to_local(uv, self.camera, pose, max_range_m=self.config.range_limit_m)
            return east, north, None, valid
        return pixel_to_terrain(uv, self.camera, pose, terrain, max_range_m=self.config.range_limit_m)

    @property
    def _focal_px(self) -> float:
        # from the current camera: callers swap cameras when a video's resolution differs
        return math.sqrt(self.camera.fx * self.camera.fy)

    def reset(self) -> None:
        """Forget the memory, the telemetry correction, the joint registration and carried sightings and what the
        adaptive stages judged (start of another video)."""
        self.memory.reset()
        self.__dict__.pop("_video_terrain", None)
        self.__dict__.pop("_corrector", None)
        self.__dict__.pop("_score_calibration", None)
        self.__dict__.pop("_joint_registration", None)  # the previous video's offset and sightings
        self.__dict__.pop("_joint_carry", None)
        self.__dict__.pop("_dem_coverage", None)
        self._size_check = SizeFilterCheck(self.size_filter, self.config.size_check_settings())
        self._classes_seen = set()

    def process(self, boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray,
                pose: Pose | None, t: float, embeddings: NDArray | None = None) -> FrameResult:
        """Run one frame.

        boxes_xyxy: (N, 4) pre-NMS candidates in pixels; scores (N,) in [0, 1]; class_ids (N,)
        keys of class_names; pose: the frame's camera pose, or None when the frame has no
        metadata (then boxes pass through unboosted and the map is not updated); t: seconds;
        embeddings: optional (N, D) appearance descriptors, passed through to the kept boxes.
        """
        boxes = np.asarray(boxes_xyxy, dtype=np.float32).reshape(-1, 4)
        conf = np.asarray(scores, dtype=np.float32).reshape(-1)
        cids = np.asarray(class_ids, dtype=np.int64).reshape(-1)
        n = len(conf)
        if not (len(boxes) == n == len(cids)):
            raise ValueError(f"boxes ({len(boxes)}), scores ({n}) and class_ids ({len(cids)}) differ in length")
        present = distinct_ids(cids).tolist()
        unknown = set(present) - set(self.class_names)
        if unknown:
            raise ValueError(f"unknown class id(s) {sorted(unknown)}; known: {sorted(self.class_names)}")
        self._classes_seen.update(self.class_names[c] for c in present)
        cfg = self.config
        self.__dict__.setdefault("_dem_coverage", DemCoverage()).observe(cfg.terrain, pose)  # once a frame
        src: NDArray[np.int64] | None = None  # rows of the input still in play (None: all), for the embeddings
        if embeddings is not None:
            embeddings = np.asarray(embeddings, dtype=np.float32)
            embeddings = embeddings.reshape(n, embeddings.shape[-1] if embeddings.ndim == 2 and n == 0 else -1)
        raw = conf
        correction: GroundCorrection | None = None
        n_filtered = 0
        n_geo = 0
        view_h: NDArray[np.float64] | None = None  # over a terrain: effective_height_m of the ground points
        stamp: NDArray[np.float64] | None = None  # over a terrain: the boxes' stamp radius factors (memory map)
        if pose is None or not n:
            lat = np.full(n, np.nan)
            lon = np.full(n, np.nan)
        else:
            observe = cfg.use_size_filter and not self._size_check.frozen
            # one compiled pass over flat ground, unless the lens distortion needs OpenCV's undistortion (or class
            # ids are sparse); over a terrain the rays are marched (shared.terrain)
            if cfg.terrain is None and self.camera.dist is None and self._band_tables() is not None:
                if observe:
                    self._observe_sizes(boxes, conf, cids, pose)
                lat, lon, valid, ok = self._georeference_and_filter(boxes, cids, present, pose)
            else:
                east, north, up, valid = self.ground_points(boxes, pose)
                if observe:
                    self._observe_sizes(boxes, conf, cids, pose, (east, north, up, valid))
                ok = self.plausible(boxes, cids, east, north, pose, up_m=up) if cfg.use_size_filter else None
                lat, lon = local_to_latlon(east, north, pose.lat, pose.lon)  # NaN where not valid
                terrain = self.terrain_for(pose)
                if up is not None and terrain is not None:
                    grad = terrain.gradient(east, north, pose)  # one bilinear lookup for both
                    view_h = effective_height_m(east, north, up, pose, terrain, grad)
                    if cfg.use_memory and cfg.memory.terrain_stamp != "off":
                        stamp = cfg.memory.stamp_scales(footprint_scale(east, north, up, pose, terrain, grad))
            if ok is not None:
                n_filtered = int(n - np.count_nonzero(ok))
                if n_filtered:
                    # integer takes: a boolean index costs ~2x (~6x on (N, 4))
                    src = np.flatnonzero(ok)
                    boxes = np.take(boxes, src, axis=0)
                    raw, cids, lat, lon, valid = raw[src], cids[src], lat[src], lon[src], valid[src]
                    view_h = None if view_h is None else view_h[src]
                    stamp = None if stamp is None else stamp[src]
            n_geo = int(np.count_nonzero(valid))
        calibration = self._calibration()
        # the detector's scores at the reference temperature (per box: after the filter, on fewer boxes)
        conf = raw if calibration is None else calibration.apply(raw)
        boosted = conf.copy()
        on_map = None  # over a terrain with a correction: the points in the maps' frame (_boost_and_update)
        if pose is not None and n and cfg.use_memory:
            boosted, lat, lon, correction, on_map = self._boost_and_update(conf, boosted, cids, present, valid, lat,
                                                                           lon, pose, t, boxes, stamp)
        keep = nms(boxes, boosted, cids, cfg.nms_iou, cfg.score_threshold, cfg.max_detections)
        if cfg.fragment_iou > 0 and len(keep) > 1:
            keep = unboost_fragments(boxes, conf, boosted, cids, keep, cfg.fragment_iou, cfg.score_threshold)
        if calibration is not None:
            calibration.observe(t, raw[keep])
        result = FrameResult(boxes[keep], boosted[keep], conf[keep], cids[keep], lat[keep], lon[keep],
                             n, n_filtered, n_geo,
                             None if embeddings is None else embeddings[keep if src is None else src[keep]],
                             correction=correction, view_height_m=None if view_h is None else view_h[keep],
                             alt_latlon=None if view_h is None or pose is None or not cfg.edge_probe
                             else self._alternatives(boxes[keep], lat[keep], lon[keep], pose, correction))
        if (self.joint is not None and cfg.use_memory and cfg.joint_detections and cfg.joint_mode != "local"
                and pose is not None):
            if correction is not None and (correction.east_m or correction.north_m):
                # the maps hold corrected ground points: project them with the pose moved the same way
                pose = correction.moved(pose)
            result = self._with_joint_detections(result, pose, t, None if on_map is None else
                                                 (on_map[0][keep], on_map[1][keep]))
        return result

    def stage_reports(self) -> list[StageReport]:
        """What the adaptive per-frame stages did in this video (agent.stage_report): the size filter per
        class, the score calibration, the telemetry correction."""
        cfg = self.config
        out: list[StageReport] = []
        if cfg.use_size_filter:
            out += self._size_check.reports(sorted(self._classes_seen))
        calibration = self._calibration()
        if calibration is not None:
            out.append(calibration.report())
        corrector = self.__dict__.get("_corrector")
        if corrector is not None:
            out.append(corrector[1].report())
        return out + ([c.report()] if (c := self.__dict__.get("_dem_coverage")) is not None and c.on + c.off else [])

    def _calibration(self) -> ScoreCalibration | None:
        """The video's score calibration (agent.score_calibration), None when off or without the memory map."""
        cfg = self.config
        if not (cfg.use_memory and cfg.calibrate_scores):
            return None
        cached = self.__dict__.get("_score_calibration")
        if cached is None or cached[0] is not cfg:  # rebuilt when the config object changes
            cached = self.__dict__["_score_calibration"] = (cfg, ScoreCalibration(cfg.calibration_settings()))
        return cached[1]

    def joint_registration_offset_px(self) -> tuple[float, float] | None:
        """The joint registration's current image offset of the other UAVs' evidence from this UAV's detections,
        (x, y) pixels (agent.joint_detections.JointRegistration); None before the first frame with joint detections."""
        registration = self.__dict__.get("_joint_registration")
        if registration is None:
            return None
        ox, oy = registration.offset()
        return ox * self._focal_px, oy * self._focal_px

    def _with_joint_detections(self, result: FrameResult, pose: Pose, t: float,
                               on_map: tuple[NDArray, NDArray] | None = None) -> FrameResult:
        """The frame's detections plus the joint map's (agent.joint_detections); on_map: their points in the
        maps' frame where it is not result.lat/lon (over a terrain with a correction)."""
        assert self.joint is not None
        registration = self.__dict__.setdefault("_joint_registration", JointRegistration.from_config(self.config))
        carry = self.__dict__.setdefault("_joint_carry", JointCarry.from_config(self.config))
        if self.memory.t is None or t < self.memory.t:
            registration.reset()
            carry.reset()
        return add_joint_detections(result, pose, t, config=self.config, joint=self.joint, memory=self.memory,
                                    camera=self.camera, class_names=self.class_names,
                                    size_filter=self.active_size_filter, terrain=self.terrain_for(pose),
                                    registration=registration, carry=carry if self.config.joint_carry_s > 0 else None,
                                    on_map=on_map)

    def _georeference_and_filter(self, boxes: NDArray[np.float32], cids: NDArray[np.int64], present: list[int],
                                 pose: Pose, *, exact_only: bool = False
                                 ) -> tuple[NDArray, NDArray, NDArray, NDArray | None]:
        """pixel_to_local and local_to_latlon of the boxes' anchors and plausible(), fused in agent._kernels
        (the same to float rounding). Returns lat, lon, valid and the filter's decision (None: filter off).
        exact_only: decide every box by the exact test, not the sure bounds (the reference they must equal).
        """
        cfg = self.config
        cam = self.camera
        tables = self._band_tables()
        assert tables is not None
        lo, band_of_class, knots, curves, n_knots, sure = tables
        if exact_only:  # bounds that decide nothing
            sure = np.broadcast_to(np.array([0.0, np.inf, -np.inf, np.inf]), sure.shape).copy()
        if not cfg.use_size_filter:
            band_of_class = band_of_class[:0]
        else:
            for cid in present:  # as SizeFilter.accept_class does for a class without a band
                if band_of_class[cid - lo] < 0 and self.class_names[cid] not in self.size_filter.bands:
                    _warn_unfiltered(self.class_names[cid])
        # the radii shared.geo.local_to_latlon divides by
        origin = np.array([pose.lat, pose.lon, float(meridian_radius_m(pose.lat)),
                           float(prime_vertical_radius_m(pose.lat)) * math.cos(math.radians(pose.lat))])
        lat, lon, valid, ok = georeference_and_filter(
            boxes, cids, anchor_fraction(cfg.anchor, pose.pitch_deg), np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            np.ascontiguousarray(pose.R_world_from_cam, dtype=np.float64),
            math.sin(math.radians(horizon_dip_deg(pose.height_m))), float(pose.height_m),
            float(cfg.range_limit_m), origin, lo, band_of_class, knots, curves, n_knots, sure,
            float(self.active_size_filter.k), self._focal_px)
        return lat, lon, valid, ok if cfg.use_size_filter else None

    def _band_tables(self) -> tuple[int, NDArray[np.int64], NDArray, NDArray, NDArray[np.int64], NDArray] | None:
        """The size filter's bands as tables for agent._kernels.georeference_and_filter, per class id.

        (class_lo, band_of_class[id - class_lo] (-1: no band), knots (B, K), curves (B, 4, K), n_knots (B,),
        sure bounds (B, SURE_BINS, 4)), rebuilt when the size filter or the classes change; None when the
        class ids span over 65,536.
        """
        size_filter = self.active_size_filter
        cached = self.__dict__.get("_bands")
        if cached is not None and cached[0] is size_filter and cached[1] == self.class_names:
            return cached[2]
        ids = sorted(self.class_names)
        lo = ids[0] if ids else 0
        if ids and ids[-1] - lo >= 65536:
            return None
        band_of_class = np.full(ids[-1] - lo + 1 if ids else 0, -1, dtype=np.int64)
        bands: list[SizeBand] = []
        for cid in ids:
            band = size_filter.bands.get(self.class_names[cid])
            if band is not None:
                band_of_class[cid - lo] = len(bands)
                bands.append(band)
        k = max([len(b.depression_deg) for b in bands], default=1)
        knots = np.zeros((len(bands), k))
        curves = np.zeros((len(bands), 4, k))
        for row, band in enumerate(bands):
            xp = np.array(band.depression_deg)
            knots[row, :len(xp)] = xp
            for c, fp in enumerate((np.array(band.mean_log_m), np.array(band.std_log))):
                curves[row, c, :len(fp)] = fp
                curves[row, 2 + c, :len(fp) - 1] = (fp[1:] - fp[:-1]) / (xp[1:] - xp[:-1])  # as np.interp does
        n_knots = np.array([len(b.depression_deg) for b in bands], dtype=np.int64)
        sure = np.array([b.sure_bounds(size_filter.k, SURE_BINS) for b in bands]).reshape(len(bands), SURE_BINS, 4)
        result = (lo, band_of_class, knots, curves, n_knots, sure)
        self.__dict__["_bands"] = (size_filter, dict(self.class_names), result)
        return result

    def plausible(self, boxes_xyxy: NDArray, class_ids: NDArray, east_m: NDArray, north_m: NDArray,
                  pose: Pose, *, up_m: NDArray | None = None) -> NDArray[np.bool_]:
        """The size filter's decision per box, (N,) bool; boxes without a ground point pass.

        east_m, north_m: (N,) ground point of each box's anchor (pixel_to_local), NaN where none; up_m: (N,)
        its height above the pose's reference on a terrain (ground_points), None on flat ground.
        """
        slant, depression = slant_and_depression(east_m, north_m, up_m, pose)
        diag = np.hypot(boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1])
        ok = np.ones(len(diag), dtype=bool)
        active = self.active_size_filter
        for cid in distinct_ids(np.asarray(class_ids)):
            name = self.class_names[int(cid)]
            if name not in active.bands:  # stood down for this class (or no prior at all)
                if name not in self.size_filter.bands:
                    _warn_unfiltered(name)
                continue
            sel = class_ids == cid
            ok[sel] = active.accept_class(name, diag[sel], slant[sel], depression[sel], self._focal_px)
        return ok

    def _correct(self, conf: NDArray, cids: NDArray, idx: NDArray, gx: NDArray, gy: NDArray, pose: Pose,
                 t: float) -> GroundCorrection | None:
        """This frame's ground correction (agent.telemetry_correction): the offset that lays its confident
        boxes (rows idx, global cells gx, gy) onto the memory map, smoothed; None when switched off."""
        cfg = self.config
        if not cfg.correct_telemetry:
            return None
        cached = self.__dict__.get("_corrector")
        if cached is None or cached[0] is not cfg:  # rebuilt when the config object changes
            cached = self.__dict__["_corrector"] = (cfg, GroundOffsetEstimator(cfg.correction_settings()))
        est = cached[1]
        s = est.settings
        c = conf if len(idx) == len(conf) else conf[idx]
        strong = np.flatnonzero(c >= s.min_score)
        measurement = None
        support = 0.0
        if len(strong) >= s.min_points and self.memory.classes:
            if len(strong) > s.max_points:  # the most confident ones (argpartition: linear time)
                strong = strong[np.argpartition(-c[strong], s.max_points - 1)[:s.max_points]]
            cell_m = self.memory.cell_m
            # the offset is searched within search_m of the raw telemetry: bounded, it cannot run away
            sx, sy = gx[strong], gy[strong]
            radius = max(1, int(round(s.search_m / cell_m)))
            scid = cids[idx[strong]]
            strong_classes = sorted(set(scid.tolist()))  # a few dozen ids at most: no numpy round trips
            if len(strong_classes) == 1:
                patches = self.memory.patches(self.class_names[strong_classes[0]], sx, sy, radius)
            else:
                patches = np.zeros((len(strong), 2 * radius + 1, 2 * radius + 1), dtype=np.float32)
                for cid in strong_classes:
                    sel = scid == cid
                    patches[sel] = self.memory.patches(self.class_names[cid], sx[sel], sy[sel], radius)
            near = None
            if s.local_m > 0:  # around the current correction first (cells; y grows southward)
                east, north = est.expected_en
                near = (east / cell_m, -north / cell_m, s.local_m / cell_m)
            dx, dy, support = register_offset(patches, c[strong], near=near, near_support=s.min_support)
            if support < s.min_support:
                est.count("low support")
            elif max(abs(dx), abs(dy)) >= radius - 0.5:
                est.count("at the search bound")  # the best offset may lie beyond: not applied
            else:
                measurement = (dx * cell_m, -dy * cell_m)
                est.count("measured")
        else:
            est.count("too few boxes")
        corr = est.update(t, measurement, int(len(strong)), support)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("t=%.3f correction east %.2f north %.2f m (measured %s, %d boxes, support %.2f)", t,
                      corr.east_m, corr.north_m, corr.measured, corr.points, corr.support)
        return corr

    def _boost_and_update(self, conf, boosted, cids, present: list[int], valid, lat, lon, pose: Pose, t: float,
                          boxes: NDArray, stamp: NDArray | None = None):
        """Boost with the map from before this frame, then stamp; the frame's ground points moved by the
        telemetry correction first (over a terrain the map's cells are marched again from the pose moved by it; the
        returned points stay moved, which the tracker undoes). present: the frame's class ids, ascending (cids holds
        no others); boxes: the candidates (for the joint registration, _registered_cells); stamp: their stamp radius
        factors over a terrain (MemoryMapConfig.stamp_scales) or None. Returns boosted, lat, lon
        (corrected), the correction (or None) and the marched points (lat, lon) the map used, or None."""
        cfg = self.config
        first = self.memory.t is None
        on_map = None
        dt = self.memory.advance(t, pose.lat, pose.lon)
        # Observation time this update stands for: the frame interval, capped after gaps.
        step_s = min(FIRST_FRAME_INTERVAL_S if first else dt, cfg.memory.max_step_s)
        if not valid.any():
            return boosted, lat, lon, self._correct(conf, cids, np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
                                                    pose, t), None
        idx = np.flatnonzero(valid)
        everywhere = len(idx) == len(valid)  # every box has a ground point (the usual case): no gathers
        gx, gy = self.grid.latlon_to_cell(lat, lon) if everywhere else self.grid.latlon_to_cell(lat[idx], lon[idx])
        correction = self._correct(conf, cids, idx, gx, gy, pose, t)
        if correction is not None and (correction.east_m or correction.north_m):
            cell_m = self.memory.cell_m
            gx = gx + correction.east_m / cell_m
            gy = gy - correction.north_m / cell_m
            moved = correction.moved(pose)
            lat = lat + (moved.lat - pose.lat)
            lon = lon + (moved.lon - pose.lon)
            if self.terrain_for(pose) is not None:  # the map's cells: rays marched again from the UAV moved as much
                rows = slice(None) if everywhere else idx
                mlat, mlon, _ = self._marched_where_hit(boxes[rows], moved, lat[rows], lon[rows])
                on_map = mlat, mlon
                if not everywhere:  # the boxes without a ground point keep their NaN
                    on_map = lat.copy(), lon.copy()
                    on_map[0][idx], on_map[1][idx] = mlat, mlon
                gx, gy = self.grid.latlon_to_cell(mlat, mlon)
        vcids = cids if everywhere else cids[idx]
        spots = self._registered_cells(boxes, idx, pose, correction)
        # The update uses the detector's confidence, not the boosted one (paper IV).
        gain = cfg.memory.gain_per_s * step_s if cfg.memory.gain_per_frame is None else cfg.memory.gain_per_frame
        for cid in present:
            name = self.class_names[cid]
            if len(present) == 1:
                rows, gxs, gys = idx, gx, gy
            else:
                sel = vcids == cid
                rows = idx[sel]
                if not len(rows):  # no ground point of this class
                    continue
                gxs, gys = gx[sel], gy[sel]
            p = self.memory.values_at(name, gxs, gys)
            absent = None
            if self.joint is not None and cfg.joint_mode != "local":
                pj = self.joint.values_at(name, gxs, gys, t)
                if spots is not None:  # the partners' evidence where the joint registration puts it
                    sx, sy = spots[0][rows], spots[1][rows]
                    ok = np.isfinite(sx)
                    if ok.any():
                        pj[ok], on = registered_joint_evidence(
                            self.joint, self.memory, name, p[ok], sx[ok], sy[ok], t, cover_uavs=cfg.joint_cover_uavs,
                            absent_value=cfg.joint_absent_value)
                        absent = np.zeros(len(rows), bool)
                        absent[ok] = on
                if cfg.joint_mode == "max":
                    p = np.maximum(p, pj)
                elif cfg.joint_mode == "joint":
                    p = np.where(pj > 0, pj, p)
                else:
                    p = 0.5 * (p + pj)
            c = conf[rows]
            b = boost_scores(c, p, cfg.boost_mode, cfg.boost_weight, cfg.logodds_scale)
            if absent is not None and cfg.joint_absent_logit > 0 and cfg.boost_mode == "logodds" and absent.any():
                # a partner covers the spot and sees nothing there: its evidence against, in log-odds
                b[absent] = boost_scores(b[absent], np.float32(-1.0), "logodds", cfg.joint_absent_logit, 1.0)
            boosted[rows] = b
            self.memory.add(name, gxs, gys, gain * c, None if stamp is None else stamp[rows])
        return boosted, lat, lon, correction, on_map

    def _alternatives(self, boxes: NDArray, lat: NDArray, lon: NDArray, pose: Pose,
                      correction: GroundCorrection | None) -> NDArray[np.float64]:
        """(K, 2) lat, lon of each box's second ground point where its ray passes a terrain edge within edge_probe
        of its height (shared.terrain.edge_alternatives), corrected as the boxes' points are; NaN rows where none."""
        terrain = self.terrain_for(pose)
        assert terrain is not None  # asked with view heights only: over a terrain
        moved = pose if correction is None else correction.moved(pose)
        shift = np.array([moved.lat - pose.lat, moved.lon - pose.lon])
        east, north = latlon_to_local(lat - shift[0], lon - shift[1], pose.lat, pose.lon)
        ae, an = edge_alternatives(box_anchor_points(boxes, self.config.anchor, pose.pitch_deg),
                                   self.config.edge_probe * (boxes[:, 3] - boxes[:, 1]), self.camera, pose,
                                   terrain, east, north, max_range_m=self.config.range_limit_m)
        return np.column_stack(local_to_latlon(ae, an, pose.lat, pose.lon)) + shift

    def _registered_cells(self, boxes: NDArray, idx: NDArray[np.int64], pose: Pose,
                          correction: GroundCorrection | None) -> tuple[NDArray, NDArray] | None:
        """Global cells (gx, gy), (N,) each with NaN where none, of where the joint registration puts the partners'
        evidence of the candidates idx (agent.joint_boost): each anchor moved by the registration's image offset,
        put on the ground and corrected as the candidates' own cells are (moved by the telemetry correction; over a
        terrain marched from the UAV it moves, where that hits). None without a joint layer, joint
        detections (the registration is theirs), joint_register_boost, or an offset yet."""
        cfg = self.config
        registration = self.__dict__.get("_joint_registration")
        if self.joint is None or registration is None or not cfg.joint_register_boost or not len(idx):
            return None
        dx, dy = registration.offset()
        if not (dx or dy):
            return None
        shifted = boxes[idx] + np.float32(self._focal_px) * np.array([dx, dy, dx, dy], np.float32)
        east, north, _, ok = self.ground_points(shifted, pose)
        if correction is not None:
            east, north = east + correction.east_m, north + correction.north_m
        sla, slo = local_to_latlon(east, north, pose.lat, pose.lon)  # NaN where no hit
        if correction is not None and (correction.east_m or correction.north_m) and self.terrain_for(pose) is not None:
            sla, slo, hit = self._marched_where_hit(shifted, correction.moved(pose), sla, slo)
            ok = ok | hit
        gx = np.full(len(boxes), np.nan)
        gy = np.full(len(boxes), np.nan)
        if ok.any():
            gx[idx[ok]], gy[idx[ok]] = self.grid.latlon_to_cell(sla[ok], slo[ok])
        return gx, gy

    def _marched_where_hit(self, boxes: NDArray, moved: Pose, lat: NDArray, lon: NDArray
                           ) -> tuple[NDArray, NDArray, NDArray[np.bool_]]:
        """The boxes' ground points (lat, lon) marched from `moved` (over a terrain: the pose moved by the telemetry
        correction) where the rays hit, lat / lon as given elsewhere; and where they hit."""
        east, north, _, hit = self.ground_points(boxes, moved)
        mlat, mlon = local_to_latlon(east, north, moved.lat, moved.lon)
        return np.where(hit, mlat, lat), np.where(hit, mlon, lon), hit


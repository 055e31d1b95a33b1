"""Per-frame detection pipeline: georeference pre-NMS boxes, size filter, memory-map boost, NMS.

Arrays in, arrays out: the same code serves `uavmm boost`, the tracker and the live agent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from agent._kernels import georeference_and_filter, nms_ranked, rank_keys
from agent.memory_map import JointLayer, MemoryMap, MemoryMapConfig
from agent.size_filter import SizeFilter, _warn_unfiltered
from shared.geo import (
    Camera,
    Pose,
    horizon_dip_deg,
    local_to_latlon,
    meridian_radius_m,
    pixel_to_local,
    prime_vertical_radius_m,
)
from shared.tiles import TileGrid

ANCHORS = ("auto", "center", "bottom")
JOINT_MODES = ("max", "local", "joint", "mean")
BOOST_MODES = ("add", "logodds")
#: Observation time credited to the first frame of a video (no previous frame to measure from).
FIRST_FRAME_INTERVAL_S = 1.0 / 30.0


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Pipeline parameters (defaults: the best measured on the simulator; see docs/memory-map.md).

    boost_weight: c_hat = c + boost_weight * p (paper: 1).
    boost_mode: "add" (the paper: c + w p) or "logodds" (logit(c_hat) = logit(c) + w * logodds_scale * p:
        a Bayesian update that moves mid-confidence boxes most and keeps c_hat in (0, 1)).
    use_memory: False gives the single-frame baseline (same filter and NMS, no boosting).
    use_size_filter: apply the distance-size filter.
    anchor: where on a box its ground point is: "center" (the paper), "bottom" (feet of an upright
        object) or "auto" (from the bottom at grazing views to the centre at nadir).
    joint_mode: how a joint map from the fusion server combines with the local one for boosting:
        "max" (default), "local" (ignore it), "joint" (only it where fresh), "mean".
    max_range_m: boxes whose ground point is farther from the UAV are not georeferenced (default:
        half the memory window).
    nms_iou: IoU threshold of class-wise NMS; score_threshold: minimum output score;
    max_detections: per frame, highest scores first (COCO evaluates 100).
    joint_detections: with a joint layer, use_memory and joint_mode other than "local", add detections for the
        other UAVs' evidence in this view that no detection of the frame explains (agent.joint_detections;
        flagged in FrameResult.from_joint). joint_min_value: the others' evidence a peak needs;
        joint_gate_m: ground distance within which a kept box explains (or is promoted by) a peak (an
        angular gate around the peak's pixel applies too, agent.joint_detections.PEAK_GATE_RAD);
        joint_cover_uavs: UAVs assumed to cover a joint cell when this UAV's own evidence is taken out
        of the joint mean (1: use the joint value as is); joint_prior_score: the confidence a joint
        detection is credited with before the boost by the others' evidence (see joint_score; 0.5: a
        promoted weak box ranks with confident detections, as it was right in ~88 % of cases on `coop`);
        joint_synth_factor: multiplies the score of boxes synthesised where no real candidate exists
        (their pixel position carries the cross-UAV georeferencing error: on `coop` at 80 m they overlapped
        the object in 4 of ~1,200 cases; default 0 = only promote and carry real candidates).
        joint_carry_s: for this long after this UAV last saw an object the others' evidence points at (a
        promoted or confident box), a frame with no box for it reports the last one moved on by its image
        velocity (agent.joint_detections.JointCarry; 0 = off), scored the peak's times joint_carry_factor.
    """

    memory: MemoryMapConfig = field(default_factory=MemoryMapConfig)
    boost_weight: float = 1.0
    boost_mode: str = "logodds"
    logodds_scale: float = 4.0
    use_memory: bool = True
    use_size_filter: bool = True
    anchor: str = "auto"
    joint_mode: str = "max"
    max_range_m: float | None = None
    nms_iou: float = 0.5
    score_threshold: float = 0.001
    max_detections: int = 100
    joint_detections: bool = True
    joint_min_value: float = 0.3
    joint_gate_m: float = 3.0
    joint_cover_uavs: int = 2
    joint_prior_score: float = 0.5
    joint_synth_factor: float = 0.0
    joint_carry_s: float = 0.5
    joint_carry_factor: float = 0.8

    def __post_init__(self) -> None:
        if self.anchor not in ANCHORS:
            raise ValueError(f"anchor must be one of {', '.join(ANCHORS)}, got {self.anchor!r}")
        if self.boost_mode not in BOOST_MODES:
            raise ValueError(f"boost_mode must be one of {', '.join(BOOST_MODES)}, got {self.boost_mode!r}")
        if self.joint_mode not in JOINT_MODES:
            raise ValueError(f"joint_mode must be one of {', '.join(JOINT_MODES)}, got {self.joint_mode!r}")
        if not (0.0 < self.nms_iou <= 1.0):
            raise ValueError(f"nms_iou must be in (0, 1], got {self.nms_iou!r}")
        if not math.isfinite(self.boost_weight) or self.boost_weight < 0:
            raise ValueError(f"boost_weight must be >= 0, got {self.boost_weight!r}")
        if self.max_detections < 1:
            raise ValueError(f"max_detections must be >= 1, got {self.max_detections!r}")
        if not (0.0 < self.joint_min_value <= 1.0):
            raise ValueError(f"joint_min_value must be in (0, 1], got {self.joint_min_value!r}")
        if not (math.isfinite(self.joint_gate_m) and self.joint_gate_m >= 0):
            raise ValueError(f"joint_gate_m must be >= 0, got {self.joint_gate_m!r}")
        if self.joint_cover_uavs < 1:
            raise ValueError(f"joint_cover_uavs must be >= 1, got {self.joint_cover_uavs!r}")
        if not (0.0 < self.joint_prior_score < 1.0):
            raise ValueError(f"joint_prior_score must be in (0, 1), got {self.joint_prior_score!r}")
        if not (0.0 <= self.joint_synth_factor <= 1.0):
            raise ValueError(f"joint_synth_factor must be in [0, 1], got {self.joint_synth_factor!r}")
        if not (math.isfinite(self.joint_carry_s) and self.joint_carry_s >= 0):
            raise ValueError(f"joint_carry_s must be >= 0, got {self.joint_carry_s!r}")
        if not (0.0 <= self.joint_carry_factor <= 1.0):
            raise ValueError(f"joint_carry_factor must be in [0, 1], got {self.joint_carry_factor!r}")

    @property
    def range_limit_m(self) -> float:
        return self.memory.window_m / 2.0 if self.max_range_m is None else self.max_range_m


@dataclass(frozen=True, slots=True)
class FrameResult:
    """Detections of one frame after NMS, highest score first.

    boxes_xyxy (K, 4) float32 pixels; scores (K,) float32 boosted confidences (may exceed 1);
    raw_scores (K,) the detector's; class_ids (K,) int; lat, lon (K,) float64 ground points (NaN
    where not georeferenced); counts: candidates in, dropped by the size filter, georeferenced;
    embeddings (K, D) float32 appearance descriptors of the kept boxes (NaN rows: none) or None;
    from_joint (K,) bool: True for detections the joint map added or promoted (agent.joint_detections),
    or None when the frame had no joint detections step (no joint layer).
    """

    boxes_xyxy: NDArray[np.float32]
    scores: NDArray[np.float32]
    raw_scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    n_candidates: int
    n_size_filtered: int
    n_georeferenced: int
    embeddings: NDArray[np.float32] | None = None
    from_joint: NDArray[np.bool_] | None = None

    def __len__(self) -> int:
        return len(self.scores)


def distinct_ids(ids: NDArray) -> NDArray:
    """Sorted distinct values of an (N,) id array, as np.unique.

    Class ids span a few values: counting them is ~8x faster than np.unique's hashing at 5,000
    boxes; other dtypes and wide ranges fall back to np.unique.
    """
    if len(ids) == 0 or ids.dtype.kind != "i":
        return np.unique(ids)
    lo, hi = int(ids.min()), int(ids.max())
    if hi - lo >= 4096:
        return np.unique(ids)
    return (np.flatnonzero(np.bincount(ids - lo)) + lo).astype(ids.dtype, copy=False)


def anchor_fraction(anchor: str, pitch_deg: float) -> float:
    """Height of a box's ground point in the box, 0 (top edge) to 1 (bottom edge)."""
    if anchor == "center":
        return 0.5
    if anchor == "bottom":
        return 1.0
    # upright objects stand on their box's bottom edge at grazing views, centred at nadir
    return 0.5 + 0.5 * math.cos(math.radians(pitch_deg))


def box_anchor_points(boxes_xyxy: NDArray, anchor: str, pitch_deg: float) -> NDArray[np.float64]:
    """(N, 4) boxes -> (N, 2) pixel of each box's ground point."""
    return anchor_points(boxes_xyxy, anchor_fraction(anchor, pitch_deg))


def anchor_points(boxes_xyxy: NDArray, frac: float) -> NDArray[np.float64]:
    """(N, 4) boxes -> (N, 2) pixels at the middle of each box, frac of its height down (anchor_fraction)."""
    x1, y1, x2, y2 = (boxes_xyxy[:, i].astype(np.float64) for i in range(4))
    return np.column_stack([(x1 + x2) / 2.0, y1 + frac * (y2 - y1)])


def nms(boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray, iou: float,
        score_threshold: float, max_detections: int) -> NDArray[np.int64]:
    """Class-wise greedy NMS; indices of the kept boxes, highest score first, at most max_detections.

    boxes_xyxy (N, 4) pixels (float32 or float64; other dtypes are taken as float64), scores (N,),
    class_ids (N,) int; iou and score_threshold >= 0 (ValueError otherwise, as OpenCV asserts).
    Boxes with score <= score_threshold (float32 compare) are dropped; equal scores rank by index.
    The same boxes in the same order as cv2.dnn.NMSBoxesBatched over all N boxes, in OpenCV's Rect2d
    arithmetic (NaN, empty and negative-size boxes included), from a compiled kernel
    (agent._kernels.nms_ranked) that stops at max_detections and compares each box only with the kept
    boxes it may intersect: ~0.07 ms at 5,000 clustered candidates.
    """
    if not (iou >= 0 and score_threshold >= 0):
        raise ValueError(f"nms needs iou >= 0 and score_threshold >= 0, got {iou!r} and {score_threshold!r}")
    n = len(scores)
    if n == 0 or max_detections < 1:
        return np.zeros(0, dtype=np.int64)
    scores = np.ascontiguousarray(scores, dtype=np.float32).reshape(-1)
    boxes = np.asarray(boxes_xyxy)
    boxes = np.ascontiguousarray(boxes, dtype=np.float32 if boxes.dtype == np.float32 else np.float64).reshape(-1, 4)
    cids = np.ascontiguousarray(class_ids, dtype=np.int64).reshape(-1)
    keys = np.sort(rank_keys(scores, float(score_threshold)))  # numpy's sort is SIMD: ~15x numba's
    return nms_ranked(boxes, keys, cids, float(iou), int(max_detections))


def boost_scores(conf: NDArray, evidence: NDArray, boost_mode: str, boost_weight: float,
                 logodds_scale: float) -> NDArray:
    """Boosted confidences of candidates with confidence `conf` at cells holding memory `evidence`.

    "add" (the paper): c + w p; "logodds": sigmoid(logit(c) + w * logodds_scale * p), c clipped to
    [1e-6, 1 - 1e-6]. Same dtype as the inputs.
    """
    if boost_mode == "add":
        return conf + boost_weight * evidence
    cc = np.clip(conf, 1e-6, 1 - 1e-6)
    logit = np.log(cc / (1 - cc)) + boost_weight * logodds_scale * evidence
    return 1.0 / (1.0 + np.exp(-logit))


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

    @property
    def _focal_px(self) -> float:
        # from the current camera: callers swap cameras when a video's resolution differs
        return math.sqrt(self.camera.fx * self.camera.fy)

    def reset(self) -> None:
        """Forget the memory (start of another video)."""
        self.memory.reset()

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
        cfg = self.config
        src = np.arange(n)  # rows of the input still in play (for the embeddings)
        if embeddings is not None:
            embeddings = np.asarray(embeddings, dtype=np.float32).reshape(n, -1)
        boosted = conf.copy()
        n_filtered = 0
        n_geo = 0
        if pose is None or not n:
            lat = np.full(n, np.nan)
            lon = np.full(n, np.nan)
        else:
            # one compiled pass, unless the lens distortion needs OpenCV's undistortion (or class ids are sparse)
            if self.camera.dist is None and self._band_tables() is not None:
                lat, lon, valid, ok = self._georeference_and_filter(boxes, cids, present, pose)
            else:
                east, north, valid = pixel_to_local(box_anchor_points(boxes, cfg.anchor, pose.pitch_deg),
                                                    self.camera, pose, max_range_m=cfg.range_limit_m)
                ok = self.plausible(boxes, cids, east, north, pose) if cfg.use_size_filter else None
                lat, lon = local_to_latlon(east, north, pose.lat, pose.lon)  # NaN where not valid
            if ok is not None:
                n_filtered = int(n - np.count_nonzero(ok))
                if n_filtered:
                    # np.compress: a boolean index on (N, 4) costs ~6x more
                    boxes = np.compress(ok, boxes, axis=0)
                    conf, boosted, cids, src = conf[ok], boosted[ok], cids[ok], src[ok]
                    lat, lon, valid = lat[ok], lon[ok], valid[ok]
            n_geo = int(np.count_nonzero(valid))
            if cfg.use_memory:
                boosted = self._boost_and_update(conf, boosted, cids, valid, lat, lon, pose, t)
        keep = nms(boxes, boosted, cids, cfg.nms_iou, cfg.score_threshold, cfg.max_detections)
        result = FrameResult(boxes[keep], boosted[keep], conf[keep], cids[keep], lat[keep], lon[keep],
                             n, n_filtered, n_geo, None if embeddings is None else embeddings[src[keep]])
        if (self.joint is not None and cfg.use_memory and cfg.joint_detections and cfg.joint_mode != "local"
                and pose is not None):
            result = self._with_joint_detections(result, pose, t)
        return result

    def _with_joint_detections(self, result: FrameResult, pose: Pose, t: float) -> FrameResult:
        """The frame's detections plus the joint map's (agent.joint_detections, which builds on this module)."""
        from agent.joint_detections import JointCarry, JointRegistration, add_joint_detections

        registration = self.__dict__.setdefault("_joint_registration", JointRegistration())
        carry = self.__dict__.setdefault("_joint_carry", JointCarry(self.config.joint_carry_s))
        if self.memory.t is None or t < self.memory.t:
            registration.reset()
            carry.reset()
        return add_joint_detections(self, result, pose, t, registration,
                                    carry if self.config.joint_carry_s > 0 else None)

    def _georeference_and_filter(self, boxes: NDArray[np.float32], cids: NDArray[np.int64], present: list[int],
                                 pose: Pose) -> tuple[NDArray, NDArray, NDArray, NDArray | None]:
        """pixel_to_local and local_to_latlon of the boxes' anchors and plausible(), fused in agent._kernels
        (the same to float rounding). Returns lat, lon, valid and the filter's decision (None: filter off).
        """
        cfg = self.config
        cam = self.camera
        tables = self._band_tables()
        assert tables is not None
        lo, band_of_class, knots, curves, n_knots = tables
        if not cfg.use_size_filter:
            band_of_class = band_of_class[:0]
        else:
            for cid in present:  # as SizeFilter.accept_class does for a class without a band
                if band_of_class[cid - lo] < 0:
                    _warn_unfiltered(self.class_names[cid])
        # the radii shared.geo.local_to_latlon divides by
        origin = np.array([pose.lat, pose.lon, float(meridian_radius_m(pose.lat)),
                           float(prime_vertical_radius_m(pose.lat)) * math.cos(math.radians(pose.lat))])
        lat, lon, valid, ok = georeference_and_filter(
            boxes, cids, anchor_fraction(cfg.anchor, pose.pitch_deg), np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            np.ascontiguousarray(pose.R_world_from_cam, dtype=np.float64),
            math.sin(math.radians(horizon_dip_deg(pose.height_m))), float(pose.height_m),
            float(cfg.range_limit_m), origin, lo, band_of_class, knots, curves, n_knots, float(self.size_filter.k),
            self._focal_px)
        return lat, lon, valid, ok if cfg.use_size_filter else None

    def _band_tables(self) -> tuple[int, NDArray[np.int64], NDArray, NDArray, NDArray[np.int64]] | None:
        """The size filter's bands as tables for agent._kernels.georeference_and_filter, per class id.

        (class_lo, band_of_class[id - class_lo] (-1: no band), knots (B, K), curves (B, 4, K), n_knots (B,)),
        rebuilt when the size filter or the classes change; None when the class ids span over 65,536.
        """
        cached = self.__dict__.get("_bands")
        if cached is not None and cached[0] is self.size_filter and cached[1] == self.class_names:
            return cached[2]
        ids = sorted(self.class_names)
        lo = ids[0] if ids else 0
        if ids and ids[-1] - lo >= 65536:
            return None
        band_of_class = np.full(ids[-1] - lo + 1 if ids else 0, -1, dtype=np.int64)
        bands = []
        for cid in ids:
            band = self.size_filter.bands.get(self.class_names[cid])
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
        result = (lo, band_of_class, knots, curves, n_knots)
        self.__dict__["_bands"] = (self.size_filter, dict(self.class_names), result)
        return result

    def plausible(self, boxes_xyxy: NDArray, class_ids: NDArray, east_m: NDArray, north_m: NDArray,
                  pose: Pose) -> NDArray[np.bool_]:
        """The size filter's decision per box, (N,) bool; boxes without a ground point pass.

        east_m, north_m: (N,) ground point of each box's anchor (pixel_to_local), NaN where none.
        """
        slant = np.sqrt(east_m**2 + north_m**2 + pose.height_m**2)
        depression = np.degrees(np.arcsin(pose.height_m / slant))
        diag = np.hypot(boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1])
        ok = np.ones(len(diag), dtype=bool)
        for cid in distinct_ids(np.asarray(class_ids)):
            sel = class_ids == cid
            ok[sel] = self.size_filter.accept_class(self.class_names[int(cid)], diag[sel], slant[sel],
                                                    depression[sel], self._focal_px)
        return ok

    def _boost_and_update(self, conf, boosted, cids, valid, lat, lon, pose: Pose, t: float):
        cfg = self.config
        first = self.memory.t is None
        dt = self.memory.advance(t, pose.lat, pose.lon)
        # Observation time this update stands for: the frame interval, capped after gaps.
        step_s = min(FIRST_FRAME_INTERVAL_S if first else dt, cfg.memory.max_step_s)
        if not valid.any():
            return boosted
        idx = np.flatnonzero(valid)
        gx, gy = self.grid.latlon_to_cell(lat[idx], lon[idx])
        vcids = cids[idx]
        for cid in distinct_ids(vcids):
            name = self.class_names[int(cid)]
            sel = vcids == cid
            p = self.memory.values_at(name, gx[sel], gy[sel])
            if self.joint is not None and cfg.joint_mode != "local":
                pj = self.joint.values_at(name, gx[sel], gy[sel], t)
                if cfg.joint_mode == "max":
                    p = np.maximum(p, pj)
                elif cfg.joint_mode == "joint":
                    p = np.where(pj > 0, pj, p)
                else:
                    p = 0.5 * (p + pj)
            c = conf[idx[sel]]
            boosted[idx[sel]] = boost_scores(c, p, cfg.boost_mode, cfg.boost_weight, cfg.logodds_scale)
            # The update uses the detector's confidence, not the boosted one (paper IV).
            self.memory.add(name, gx[sel], gy[sel], cfg.memory.gain_per_s * step_s * c)
        return boosted

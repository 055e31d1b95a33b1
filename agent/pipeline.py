"""Per-frame detection pipeline: georeference pre-NMS boxes, size filter, memory-map boost, NMS.

Arrays in, arrays out: the same code serves `uavmm boost`, the tracker and the live agent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.memory_map import JointLayer, MemoryMap, MemoryMapConfig
from agent.size_filter import SizeFilter
from shared.geo import Camera, Pose, local_to_latlon, pixel_to_local
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

    @property
    def range_limit_m(self) -> float:
        return self.memory.window_m / 2.0 if self.max_range_m is None else self.max_range_m


@dataclass(frozen=True, slots=True)
class FrameResult:
    """Detections of one frame after NMS, highest score first.

    boxes_xyxy (K, 4) float32 pixels; scores (K,) float32 boosted confidences (may exceed 1);
    raw_scores (K,) the detector's; class_ids (K,) int; lat, lon (K,) float64 ground points (NaN
    where not georeferenced); counts: candidates in, dropped by the size filter, georeferenced.
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

    def __len__(self) -> int:
        return len(self.scores)


def box_anchor_points(boxes_xyxy: NDArray, anchor: str, pitch_deg: float) -> NDArray[np.float64]:
    """(N, 4) boxes -> (N, 2) pixel of each box's ground point."""
    x1, y1, x2, y2 = (boxes_xyxy[:, i].astype(np.float64) for i in range(4))
    if anchor == "center":
        frac = 0.5
    elif anchor == "bottom":
        frac = 1.0
    else:  # upright objects stand on their box's bottom edge at grazing views, centred at nadir
        frac = 0.5 + 0.5 * math.cos(math.radians(pitch_deg))
    return np.column_stack([(x1 + x2) / 2.0, y1 + frac * (y2 - y1)])


def nms(boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray, iou: float,
        score_threshold: float, max_detections: int) -> NDArray[np.int64]:
    """Class-wise greedy NMS (OpenCV); indices of the kept boxes, highest score first, at most max_detections.

    Greedy NMS decides each box from the higher-scoring boxes alone, so the first K kept boxes of
    the top-M scores are exactly the first K kept overall: NMS runs on the top 8K scores and only
    widens (4x) when fewer than K survive.
    """
    n = len(scores)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    scores = np.asarray(scores, dtype=np.float32)
    xywh = np.column_stack([boxes_xyxy[:, 0], boxes_xyxy[:, 1],
                            boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1]])
    m = min(n, 8 * max_detections)
    while True:
        top = np.argpartition(-scores, m - 1)[:m] if m < n else np.arange(n)
        keep = cv2.dnn.NMSBoxesBatched(xywh[top].astype(np.float32).tolist(), scores[top].tolist(),
                                       class_ids[top].astype(np.int32).tolist(), score_threshold, iou)
        keep = top[np.asarray(keep, dtype=np.int64).reshape(-1)]
        if len(keep) >= max_detections or m >= n:
            break
        # Too few survivors (boosting lifts whole clusters): widen 4x (doubling ran NMS 2.4 times per
        # frame at 5,000 candidates; all boxes at once costs the full NMS).
        m = min(n, 4 * m)
    keep = keep[np.argsort(-scores[keep], kind="stable")]
    return keep[:max_detections]


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
                pose: Pose | None, t: float) -> FrameResult:
        """Run one frame.

        boxes_xyxy: (N, 4) pre-NMS candidates in pixels; scores (N,) in [0, 1]; class_ids (N,)
        keys of class_names; pose: the frame's camera pose, or None when the frame has no
        metadata (then boxes pass through unboosted and the map is not updated); t: seconds.
        """
        boxes = np.asarray(boxes_xyxy, dtype=np.float32).reshape(-1, 4)
        conf = np.asarray(scores, dtype=np.float32).reshape(-1)
        cids = np.asarray(class_ids, dtype=np.int64).reshape(-1)
        n = len(conf)
        if not (len(boxes) == n == len(cids)):
            raise ValueError(f"boxes ({len(boxes)}), scores ({n}) and class_ids ({len(cids)}) differ in length")
        unknown = set(np.unique(cids).tolist()) - set(self.class_names)
        if unknown:
            raise ValueError(f"unknown class id(s) {sorted(unknown)}; known: {sorted(self.class_names)}")
        cfg = self.config
        lat = np.full(n, np.nan)
        lon = np.full(n, np.nan)
        boosted = conf.copy()
        n_filtered = 0
        n_geo = 0
        if pose is not None and n:
            east, north, valid = pixel_to_local(box_anchor_points(boxes, cfg.anchor, pose.pitch_deg),
                                                self.camera, pose, max_range_m=cfg.range_limit_m)
            if cfg.use_size_filter:
                ok = self.plausible(boxes, cids, east, north, pose)
                n_filtered = int((~ok).sum())
                if n_filtered:
                    boxes, conf, boosted, cids = boxes[ok], conf[ok], boosted[ok], cids[ok]
                    east, north, valid = east[ok], north[ok], valid[ok]
                    lat, lon = lat[ok], lon[ok]
            n_geo = int(valid.sum())
            lat_v, lon_v = local_to_latlon(east[valid], north[valid], pose.lat, pose.lon)
            lat[valid], lon[valid] = lat_v, lon_v
            if cfg.use_memory:
                boosted = self._boost_and_update(conf, boosted, cids, valid, lat, lon, pose, t)
        keep = nms(boxes, boosted, cids, cfg.nms_iou, cfg.score_threshold, cfg.max_detections)
        return FrameResult(boxes[keep], boosted[keep], conf[keep], cids[keep], lat[keep], lon[keep],
                           n, n_filtered, n_geo)

    def plausible(self, boxes_xyxy: NDArray, class_ids: NDArray, east_m: NDArray, north_m: NDArray,
                  pose: Pose) -> NDArray[np.bool_]:
        """The size filter's decision per box, (N,) bool; boxes without a ground point pass.

        east_m, north_m: (N,) ground point of each box's anchor (pixel_to_local), NaN where none.
        """
        slant = np.sqrt(east_m**2 + north_m**2 + pose.height_m**2)
        depression = np.degrees(np.arcsin(pose.height_m / slant))
        diag = np.hypot(boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1])
        ok = np.ones(len(diag), dtype=bool)
        for cid in np.unique(class_ids):
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
        for cid in np.unique(vcids):
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
            if cfg.boost_mode == "add":
                boosted[idx[sel]] = c + cfg.boost_weight * p
            else:
                cc = np.clip(c, 1e-6, 1 - 1e-6)
                logit = np.log(cc / (1 - cc)) + cfg.boost_weight * cfg.logodds_scale * p
                boosted[idx[sel]] = 1.0 / (1.0 + np.exp(-logit))
            # The update uses the detector's confidence, not the boosted one (paper IV).
            self.memory.add(name, gx[sel], gy[sel], cfg.memory.gain_per_s * step_s * c)
        return boosted

"""Detections from the joint map: what the other UAVs see inside this UAV's view, projected back into it.

The paper's cooperative claim (section V-D): "a UAV whose view is occluded still detects and tracks the
object". Boosting can only raise candidates the detector produced; an object behind a tree in this view
often has none. Here every peak of the other UAVs' evidence inside the camera footprint that no
confident detection of this frame explains becomes a detection: a weak real box near the peak is
promoted, otherwise a box is synthesised at the peak's projection with the class's size prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.boxes import anchor_fraction, anchor_points, box_iou, nms, outranked_overlaps
from agent.frame_result import FrameResult
from agent.joint_registration import JointRegistration
from agent.memory_map import JointLayer, MemoryMap, boost_scores
from agent.pipeline_config import PipelineConfig
from agent.size_filter import NOMINAL_DIMENSIONS_M, SizeFilter
from shared.geo import (
    Camera,
    GroundSurface,
    Pose,
    footprint_local,
    latlon_to_local,
    latlon_to_pixel,
    local_to_latlon,
    pixel_to_local,
)
from shared.tiles import TileGrid

__all__ = ["UPRIGHT_DIMENSIONS_M", "JointCarry", "JointDetections", "JointRegistration", "add_joint_detections",
           "find_joint_detections", "joint_score", "others_evidence"]

#: Nominal width, depth, height (m) of classes whose boxes are not square: the aspect of a synthesised
#: box (its size comes from the size filter's band). The dimensions behind agent.size_filter's priors.
UPRIGHT_DIMENSIONS_M: dict[str, tuple[float, float, float]] = {
    cls: (w, d, h) for cls, (w, d, h, _) in NOMINAL_DIMENSIONS_M.items()}
#: Gaussian standard deviation (m) that orders tied maxima of a plateau, its middle first.
_TIE_SMOOTHING_M = 1.0
_KERNEL = np.ones((3, 3), np.uint8)
#: The settings' defaults (the tuning constants of this module are PipelineConfig.joint_* fields).
_DEFAULTS = PipelineConfig()


@dataclass(frozen=True, slots=True)
class JointDetections:
    """What the joint map adds to one frame.

    promoted: (P,) indices into the frame's kept detections whose score is raised to promoted_scores (P,).
    boxes_xyxy (M, 4) float32 synthesised boxes, scores (M,) float32, class_ids (M,) int64, lat, lon (M,)
    float64 ground points of the peaks they stand for.
    """

    promoted: NDArray[np.int64]
    promoted_scores: NDArray[np.float32]
    boxes_xyxy: NDArray[np.float32]
    scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]

    @staticmethod
    def empty() -> JointDetections:
        return JointDetections(np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, 4), np.float32),
                               np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return len(self.promoted) + len(self.scores)


def others_evidence(joint: NDArray, own: NDArray, cover_uavs: int,
                    others_cover: NDArray | None = None) -> NDArray[np.float32]:
    """The other UAVs' mean evidence, taking this UAV's own contribution out of the joint mean.

    joint, own: (N,) values in [0, 1] of the joint map (mean over the UAVs covering a cell) and of this
    UAV's own map. With k UAVs covering a cell (this one included) the others' mean is
    (k * joint - own) / (k - 1), clipped to [0, 1]. others_cover (N,): how many other UAVs cover each
    cell (JointLayer.others_cover, from their footprints); where none does the joint value is this
    UAV's own evidence and the others' is 0. Without it, `cover_uavs` is the k assumed everywhere
    (k <= 1 returns joint unchanged): with k = 2 (one partner) and an occluded UAV (own ~ 0) this
    undoes the mean's halving of the partner's evidence, but in cells no partner covers it returns
    this UAV's own evidence as the others'.
    """
    joint = np.asarray(joint, dtype=np.float32)
    own = np.asarray(own, dtype=np.float32)
    if others_cover is not None:
        others = np.asarray(others_cover, dtype=np.float32)
        k = others + 1
        return np.where(others > 0, np.clip((k * joint - own) / np.maximum(others, 1), 0.0, 1.0),
                        0.0).astype(np.float32)
    if cover_uavs <= 1:
        return joint.copy()
    k1 = np.float32(cover_uavs)
    return np.clip((k1 * joint - own) / (k1 - 1), 0.0, 1.0).astype(np.float32)


def joint_score(evidence: NDArray, prior_score: float, boost_mode: str, boost_weight: float,
                logodds_scale: float) -> NDArray[np.float32]:
    """Score of a detection that rests on the others' evidence alone, (N,) float32.

    The pipeline's own boost applied to a candidate of confidence `prior_score` at a cell with memory
    `evidence` (N,): "logodds": sigmoid(logit(prior) + w * scale * evidence); "add": prior + w * evidence.
    So it ranks like a detector candidate of that confidence boosted by the same map: with the defaults
    (prior 0.5, w 1, scale 6) evidence 0.3 gives 0.86, 0.5 gives 0.95 and 1 gives 0.998.
    """
    e = np.asarray(evidence, dtype=np.float64)
    return boost_scores(np.full(e.shape, prior_score), e, boost_mode, boost_weight, logodds_scale).astype(np.float32)


def _footprint_cells(grid: TileGrid, camera: Camera, pose: Pose, range_m: float,
                     terrain: GroundSurface | None) -> tuple[int, int, int, int]:
    """(gx0, gy0, width, height) global cells of the view's footprint's bounding box, a cell of margin around.
    terrain: the footprint is cast onto it (a view over falling ground reaches farther than over flat)."""
    poly = footprint_local(camera, pose, max_range_m=range_m, samples_per_edge=8, terrain=terrain)
    lat, lon = local_to_latlon(poly[:, 0], poly[:, 1], pose.lat, pose.lon)
    wrapped_gx, gy = grid.latlon_to_cell_index(lat, lon)
    world = grid.world_cells
    # unwrapped about the footprint's first vertex (float64)
    gx = wrapped_gx + world * np.round((float(wrapped_gx[0]) - wrapped_gx) / world)
    if gx.min() < 0:
        gx = gx + world  # the block's columns in [0, world) where it does not straddle
    gx0, gy0 = int(gx.min()) - 1, int(gy.min()) - 1
    if gx0 < 0 or int(gx.max()) + 1 >= world:
        # a view across the antimeridian: its columns wrap, which the joint layer's block does not (as one block it
        # was the width of the world, 57.7 GiB, every frame): no joint detections for such a view
        return 0, 0, 0, 0
    return gx0, gy0, int(gx.max()) - gx0 + 2, int(gy.max()) - gy0 + 2


def _view_peaks(joint: JointLayer, memory: MemoryMap, cls: str, window: tuple[int, int, int, int], pose: Pose,
                t: float, min_value: float, cover_uavs: int, smoothing_m: float) -> tuple[NDArray, NDArray, NDArray]:
    """Peaks of the other UAVs' evidence of one class inside the footprint's bounding box (`_footprint_cells`).

    Returns global cells (gx, gy float64, cell centres) and others' evidence (float32) of the local
    maxima (3 x 3) of `others_evidence` (with the other UAVs' coverage when the joint layer has their
    footprints, cover_uavs otherwise) with evidence >= min_value, strongest first. The evidence is
    smoothed by a Gaussian of smoothing_m (m, standard deviation) before looking for the maxima.
    """
    grid: TileGrid = joint.grid
    gx0, gy0, width, height = window
    values = joint.window(cls, gx0, gy0, width, height, t)
    # others' evidence <= cover_uavs / (cover_uavs - 1) * joint: cells below that bound cannot pass
    floor = min_value * (1.0 - 1.0 / cover_uavs) if cover_uavs > 1 else min_value
    empty = np.zeros(0)
    if values.size == 0 or float(values.max()) < floor:
        return empty, empty, empty.astype(np.float32)
    rows, cols = np.nonzero(values >= floor)
    others = np.zeros_like(values)
    cover = joint.others_cover(gx0, gy0, values.shape[1], values.shape[0], t)
    others[rows, cols] = others_evidence(values[rows, cols],
                                         memory.values_at(cls, cols + gx0 + 0.5, rows + gy0 + 0.5), cover_uavs,
                                         None if cover is None else cover[rows, cols])
    # Maps clip at 1, so a steadily seen object (or a group, or a walker's trail) is a plateau. Smoothed by
    # smoothing_m (0.25 m) its inner cells stay tied maxima, so that the caller's suppression keeps one peak per
    # joint_gate_m of a wide plateau; ties are ordered by the evidence smoothed over _TIE_SMOOTHING_M, so the
    # first peak kept is the plateau's middle (not the first cell in row order).
    cell_m = float(grid.cell_size_m(pose.lat))
    smooth = cv2.GaussianBlur(others, (0, 0), smoothing_m / cell_m)
    rows, cols = np.nonzero((smooth >= cv2.dilate(smooth, _KERNEL)) & (others >= min_value))
    evidence = others[rows, cols]
    middle = cv2.GaussianBlur(others, (0, 0), _TIE_SMOOTHING_M / cell_m)[rows, cols]
    order = np.lexsort((-middle, -evidence))
    return cols[order] + gx0 + 0.5, rows[order] + gy0 + 0.5, evidence[order]


def _box_at(anchor_uv: NDArray, cls: str, east: NDArray, north: NDArray, pose: Pose, focal_px: float,
            size_filter: SizeFilter, anchor_frac: float) -> NDArray[np.float32]:
    """(N, 4) boxes whose anchor point (anchor_frac down the box) is anchor_uv (N, 2), sized by the prior."""
    slant = np.sqrt(east**2 + north**2 + pose.height_m**2)
    dep = np.degrees(np.arcsin(pose.height_m / slant))
    band = size_filter.bands.get(cls)
    dims = UPRIGHT_DIMENSIONS_M.get(cls)
    d = np.radians(dep)
    if dims is not None:
        width_m, vertical_m = np.full(len(dep), dims[0]), dims[2] * np.cos(d) + dims[1] * np.sin(d)
    else:
        width_m = vertical_m = np.ones(len(dep))
    diag_m = np.exp(band.mean_std(dep)[0]) if band is not None else np.hypot(width_m, vertical_m)
    scale = diag_m / np.hypot(width_m, vertical_m) * focal_px / slant
    w, h = width_m * scale, vertical_m * scale
    u, v = anchor_uv[:, 0], anchor_uv[:, 1]
    return np.column_stack([u - w / 2, v - anchor_frac * h, u + w / 2, v + (1 - anchor_frac) * h]).astype(np.float32)


def _suppress_near(east: NDArray, north: NDArray, radius_m: float) -> NDArray[np.intp]:
    """Indices of points (given strongest first) with no earlier kept point within radius_m."""
    keep: list[int] = []
    for i in range(len(east)):
        if not keep or np.min(np.hypot(east[keep] - east[i], north[keep] - north[i])) >= radius_m:
            keep.append(i)
    return np.array(keep, dtype=np.intp)


@dataclass(slots=True)
class _Anchor:
    cid: int
    box: NDArray[np.float64]  # (4,) xyxy, moved by velocity since t_seen
    east: float  # ground point at the last observation, metres from origin (JointCarry.origin)
    north: float
    t_seen: float
    velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))  # pixels per second
    sightings: int = 1  # frames in a row (overlapping boxes) this object was seen here


class JointCarry:
    """Where this UAV last saw each object the others' evidence points at, predicted to this frame.

    A peak of the others' evidence carries their georeferencing error into this view (~1.5 m, tens of
    pixels at long range, see find_joint_detections), but this UAV's own last detection of the object
    (a promoted weak candidate, or a confident box) is in the right place. An occluded object's weak
    candidates come and go from frame to frame; between them, the last box stands for it for up to
    carry_s, as long as the others still see the object there. Each remembered box moves with its own
    image velocity, an alpha-beta filter over its sightings (alpha `blend`, beta `velocity_gain`):
    a still camera and a resting person give ~0, a sweep or a walker its steady drift. Measured on
    `coop`, estimating the camera's motion from the frame's confident detections instead (their boxes
    jitter by several pixels, most are walkers) moved the carried boxes farther from the objects than
    not moving them at all.

    carry_s, match_iou, blend, velocity_gain: PipelineConfig.joint_carry_s, joint_carry_match_iou,
    joint_carry_blend and joint_carry_velocity_gain (their defaults).
    """

    def __init__(self, carry_s: float = _DEFAULTS.joint_carry_s, *, match_iou: float = _DEFAULTS.joint_carry_match_iou,
                 blend: float = _DEFAULTS.joint_carry_blend,
                 velocity_gain: float = _DEFAULTS.joint_carry_velocity_gain) -> None:
        self.carry_s = carry_s
        self.match_iou = match_iou
        self.blend = blend
        self.velocity_gain = velocity_gain
        self.anchors: list[_Anchor] = []
        self.origin: tuple[float, float] | None = None
        self._t: float | None = None

    @classmethod
    def from_config(cls, config: PipelineConfig) -> JointCarry:
        """The carry with the joint_carry_* settings of a PipelineConfig."""
        return cls(config.joint_carry_s, match_iou=config.joint_carry_match_iou, blend=config.joint_carry_blend,
                   velocity_gain=config.joint_carry_velocity_gain)

    def reset(self) -> None:
        self.anchors.clear()
        self.origin = None
        self._t = None

    def advance(self, t: float, pose: Pose) -> None:
        """Move the anchors to frame t (UAV at pose) and forget those last seen more than carry_s ago."""
        prev, self._t = self._t, t
        if self.origin is None:
            self.origin = (pose.lat, pose.lon)
        self.anchors = [a for a in self.anchors if 0.0 <= t - a.t_seen <= self.carry_s]
        if prev is not None and t > prev:
            for a in self.anchors:
                a.box = a.box + np.tile(a.velocity * (t - prev), 2)

    def _local(self, lat: NDArray, lon: NDArray) -> tuple[NDArray, NDArray]:
        assert self.origin is not None
        east, north = latlon_to_local(np.asarray(lat, np.float64), np.asarray(lon, np.float64), *self.origin)
        return np.atleast_1d(east), np.atleast_1d(north)

    def observe(self, cid: int, box: NDArray, lat: float, lon: float, t: float, gate_m: float) -> None:
        """This frame shows the object at `box` (ground point lat, lon): it replaces anchors within gate_m."""
        east, north = self._local(np.array([lat]), np.array([lon]))
        e, n = float(east[0]), float(north[0])
        new = np.asarray(box, np.float64).reshape(4).copy()
        velocity = np.zeros(2)
        sightings = 1
        same = [a for a in self.anchors if a.cid == cid and math.hypot(a.east - e, a.north - n) <= gate_m]
        if same:
            last = min(same, key=lambda a: math.hypot(a.east - e, a.north - n))
            if box_iou(last.box, new)[0, 0] >= self.match_iou:
                # the same object: a detector's boxes jitter around it, so blend with the prediction
                # and let the miss nudge the velocity
                miss = (new[:2] + new[2:] - last.box[:2] - last.box[2:]) / 2
                dt = t - last.t_seen
                velocity = last.velocity + (self.velocity_gain * miss / dt if dt > 0 else 0.0)
                new = self.blend * new + (1.0 - self.blend) * last.box
                sightings = last.sightings + 1
        self.anchors = [a for a in self.anchors if not any(a is b for b in same)]
        self.anchors.append(_Anchor(cid, new, e, n, t, velocity, sightings))

    def nearest(self, cid: int, lat: float, lon: float, gate_m: float, exclude: set[int]) -> int | None:
        """Index of the anchor of class cid nearest to lat, lon within gate_m (not in exclude), or None."""
        if self.origin is None:
            return None
        east, north = self._local(np.array([lat]), np.array([lon]))
        best, best_d = None, gate_m
        for i, a in enumerate(self.anchors):
            if a.cid == cid and i not in exclude:
                d = math.hypot(a.east - float(east[0]), a.north - float(north[0]))
                if d <= best_d:
                    best, best_d = i, d
        return best


def find_joint_detections(*, joint: JointLayer, memory: MemoryMap, camera: Camera, pose: Pose, t: float,
                          class_names: dict[int, str], size_filter: SizeFilter, config: PipelineConfig,
                          kept_scores: NDArray, kept_class_ids: NDArray, kept_lat: NDArray, kept_lon: NDArray,
                          kept_boxes: NDArray | None = None, registration: JointRegistration | None = None,
                          carry: JointCarry | None = None, terrain: GroundSurface | None = None) -> JointDetections:
    """Peaks of the other UAVs' evidence in this view that this frame's detections do not explain.

    terrain: the ground the peaks lie on when they are projected into the image (None: flat ground).

    Settings from `config` (PipelineConfig): range_m = range_limit_m, anchor_frac from anchor, and
    joint_min_value, joint_gate_m, joint_cover_uavs, joint_prior_score, the boost settings (the log-odds
    scale is PipelineConfig.joint_scale),
    joint_peak_smoothing_m, joint_peak_gate_across_rad / _down_rad, joint_register_score,
    joint_synth_factor, joint_carry_gate, joint_carry_min_sightings, joint_carry_match_iou and
    joint_carry_factor (named without their joint_ prefix below).
    For each class: local maxima of the others' evidence (`others_evidence` of the joint layer and this
    UAV's memory, cover_uavs; smoothed by peak_smoothing_m) >= min_value inside the camera footprint cut
    at range_m; peaks within gate_m of a stronger one are dropped. The peaks are projected into the image
    (latlon_to_pixel; behind the camera, above the horizon or outside the image: skipped); with a
    `registration`, the kept detections scoring >= register_score (with kept_boxes) update it and its
    image offset moves the peaks onto where this UAV sees the objects (their ground points follow the
    moved pixels). They are scored by `joint_score` (prior_score and the pipeline's boost settings). A
    kept detection of the class is near a peak when its ground point (kept_lat/kept_lon (K,), NaN = none)
    is within gate_m or, with kept_boxes, its anchor pixel within the peak_gate ellipse (half-axes
    across / down in focal lengths) around the peak's pixel. A near one that scores at least the peak's
    score explains it; otherwise the best-scoring weaker near box is promoted to the peak's score, and
    with none a box is synthesised: its anchor (anchor_frac down the box, the pipeline's convention) at
    the peak's pixel, its diagonal from the size filter's band at the peak's range and depression, its
    aspect from UPRIGHT_DIMENSIONS_M (square for other classes), and its score is the peak's times
    synth_factor: its ground point is right, but its pixel position carries the cross-UAV
    georeferencing error left after registration (tens of pixels at 80 m on `coop`), so it rarely
    overlaps the object's image box (0 drops them).
    With a `carry` (already advanced to this frame) and kept_boxes (K, 4): every kept box that explains
    or is promoted by a peak is remembered there, and a peak with neither gets, before synthesis, the
    box of the nearest remembered sighting within carry_gate x gate_m seen in at least
    carry_min_sightings frames (predicted to this frame by its image velocity; JointCarry), scored the
    peak's times carry_factor; and a peak with a remembered sighting promotes, in preference, a weaker
    kept box on that sighting's spot (IoU >= carry_match_iou) wherever its ground point is.
    """
    cfg = config
    range_m, anchor_frac = cfg.range_limit_m, anchor_fraction(cfg.anchor, pose.pitch_deg)
    min_value, gate_m, cover_uavs = cfg.joint_min_value, cfg.joint_gate_m, cfg.joint_cover_uavs
    synth_factor, carry_factor = cfg.joint_synth_factor, cfg.joint_carry_factor
    focal_px = math.sqrt(camera.fx * camera.fy)
    # the angular gate's half-axes, (across, down) pixels
    gate_px = focal_px * np.asarray((cfg.joint_peak_gate_across_rad, cfg.joint_peak_gate_down_rad))
    kept_cids = np.asarray(kept_class_ids)
    kept_scores = np.asarray(kept_scores)
    k_east, k_north = latlon_to_local(np.asarray(kept_lat, np.float64), np.asarray(kept_lon, np.float64),
                                      pose.lat, pose.lon)
    k_east, k_north = np.atleast_1d(k_east), np.atleast_1d(k_north)
    promoted: dict[int, float] = {}
    boxes, scores, cids, lats, lons = [], [], [], [], []
    window = _footprint_cells(joint.grid, camera, pose, range_m, terrain)  # once a frame: every class's window
    for cid, cls in class_names.items():
        pgx, pgy, evidence = _view_peaks(joint, memory, cls, window, pose, t, min_value, cover_uavs,
                                         cfg.joint_peak_smoothing_m)
        if len(evidence) == 0:
            continue
        plat, plon = joint.grid.cell_to_latlon(pgx, pgy)
        east, north = latlon_to_local(plat, plon, pose.lat, pose.lon)
        keep = _suppress_near(east, north, gate_m)
        east, north, evidence = east[keep], north[keep], evidence[keep]
        mine = np.flatnonzero((kept_cids == cid) & np.isfinite(k_east))
        mine_uv = None if kept_boxes is None else anchor_points(
            np.asarray(kept_boxes, np.float64)[mine].reshape(-1, 4), anchor_frac)
        uv, valid = latlon_to_pixel(*local_to_latlon(east, north, pose.lat, pose.lon), camera, pose, terrain=terrain)
        if registration is not None:
            if mine_uv is not None:
                is_sure = kept_scores[mine] >= cfg.joint_register_score
                sure = mine[is_sure]
                registration.update(t, np.column_stack([east, north]), np.column_stack([k_east[sure], k_north[sure]]),
                                    uv / focal_px, mine_uv[is_sure] / focal_px)
            dx, dy = registration.offset()
            if dx or dy:
                uv = uv - focal_px * np.array([dx, dy])
                east, north, on_ground = pixel_to_local(uv, camera, pose, terrain=terrain)
                valid &= on_ground
        plat, plon = local_to_latlon(east, north, pose.lat, pose.lon)
        with np.errstate(invalid="ignore"):
            valid &= np.hypot(east, north) <= range_m
        with np.errstate(invalid="ignore"):
            valid &= (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        score = joint_score(evidence, cfg.joint_prior_score, cfg.boost_mode, cfg.boost_weight,
                            cfg.joint_scale)
        carried: set[int] = set()
        for i in np.flatnonzero(valid):
            close = np.hypot(k_east[mine] - east[i], k_north[mine] - north[i]) <= gate_m
            if mine_uv is not None:
                du, dv = ((mine_uv - uv[i]) / gate_px).T
                close |= du * du + dv * dv <= 1.0
            near = mine[close]
            j = None if carry is None else carry.nearest(cid, float(plat[i]), float(plon[i]),
                                                         cfg.joint_carry_gate * gate_m, carried)
            seen = None
            if len(near) and float(np.max(kept_scores[near])) >= score[i]:
                seen = int(near[np.argmax(kept_scores[near])])  # this frame already reports it as confidently
            else:
                # this class's boxes not yet promoted, all weaker than the peak here
                free = np.array([k for k in mine.tolist() if k not in promoted and kept_scores[k] < score[i]],
                                dtype=np.intp)
                weaker = free[np.isin(free, near)]
                if j is not None and carry is not None and kept_boxes is not None and len(free):
                    # where this UAV last saw the object, a weak box is it wherever it puts it on the ground
                    # (the gate spans several objects at long range and misses some of the object's own
                    # boxes: a few pixels there are metres along the line of sight)
                    spot = free[box_iou(carry.anchors[j].box, kept_boxes[free])[0] >= cfg.joint_carry_match_iou]
                    if len(spot):
                        weaker = spot
                if len(weaker):
                    seen = int(weaker[np.argmax(kept_scores[weaker])])
                    promoted[seen] = float(score[i])
            if seen is not None:
                if carry is not None and kept_boxes is not None:
                    carry.observe(cid, kept_boxes[seen], float(kept_lat[seen]), float(kept_lon[seen]), t, gate_m)
                continue
            if j is not None and carry is not None and carry_factor > 0 \
                    and carry.anchors[j].sightings >= cfg.joint_carry_min_sightings:
                carried.add(j)
                boxes.append(carry.anchors[j].box.astype(np.float32).reshape(1, 4))
                scores.append(score[i] * carry_factor)
            elif synth_factor > 0:
                boxes.append(_box_at(uv[i:i + 1], cls, east[i:i + 1], north[i:i + 1], pose, focal_px, size_filter,
                                     anchor_frac))
                scores.append(score[i] * synth_factor)
            else:
                continue
            cids.append(cid)
            lats.append(plat[i])
            lons.append(plon[i])
    if not promoted and not boxes:
        return JointDetections.empty()
    p_idx = np.array(sorted(promoted), dtype=np.int64)
    return JointDetections(
        p_idx, np.array([promoted[int(j)] for j in p_idx], dtype=np.float32),
        np.concatenate(boxes).astype(np.float32) if boxes else np.zeros((0, 4), np.float32),
        np.array(scores, dtype=np.float32), np.array(cids, dtype=np.int64),
        np.array(lats, dtype=np.float64), np.array(lons, dtype=np.float64))


def add_joint_detections(result: FrameResult, pose: Pose, t: float, *, config: PipelineConfig, joint: JointLayer,
                         memory: MemoryMap, camera: Camera, class_names: dict[int, str], size_filter: SizeFilter,
                         registration: JointRegistration | None = None,
                         carry: JointCarry | None = None, terrain: GroundSurface | None = None,
                         on_map: tuple[NDArray, NDArray] | None = None) -> FrameResult:
    """`result` (a frame's kept detections) with the joint map's detections merged in. on_map: the kept
    detections' ground points (lat, lon) in the maps' frame where they differ from result.lat/lon (over a terrain
    the pipeline stamps points marched from the pose moved by its correction; result.lat/lon are moved by it).

    Uses the pipeline's parts (`agent.pipeline.DetectionPipeline`): the joint layer, this UAV's own
    memory, the camera, class names, size filter and PipelineConfig (joint_* settings, boost settings,
    anchor); `registration` carries the offset estimate across frames and `carry` the last sightings of
    the objects the others see (advanced to this frame here).
    Promoted boxes get the joint score; synthesised ones have raw score 0 (no detector candidate) and
    NaN embeddings. A class-wise NMS over the union (kept boxes do not suppress each other again) drops
    weak real boxes a joint box covers, and keeps the output highest score first and at most
    max_detections. The fragment rule (PipelineConfig.fragment_iou) applies to the joint boxes: one that a
    higher-scoring box of its class overlaps by that IoU loses what the joint map gave it (a promoted box its
    promotion, a carried or synthesised one its place). from_joint (K,) bool marks the joint ones (all False
    when the joint map added nothing).
    """
    cfg = config
    if carry is not None:
        carry.advance(t, pose)
    found = find_joint_detections(
        joint=joint, memory=memory, camera=camera, pose=pose, t=t, class_names=class_names,
        size_filter=size_filter, config=cfg, kept_scores=result.scores, kept_class_ids=result.class_ids,
        kept_lat=result.lat if on_map is None else on_map[0], kept_lon=result.lon if on_map is None else on_map[1],
        kept_boxes=result.boxes_xyxy, registration=registration,
        carry=carry, terrain=terrain)
    k = len(result)
    flags = np.zeros(k, dtype=bool)
    if len(found) == 0:
        return replace(result, from_joint=flags)
    scores = result.scores.copy()
    scores[found.promoted] = np.maximum(scores[found.promoted], found.promoted_scores)
    flags[found.promoted] = True
    m = len(found.scores)
    emb = result.embeddings
    if emb is not None and m:
        emb = np.concatenate([emb, np.full((m, emb.shape[1]), np.nan, np.float32)])
    boxes = np.concatenate([result.boxes_xyxy, found.boxes_xyxy])
    all_scores = np.concatenate([scores, found.scores]).astype(np.float32)
    cids = np.concatenate([result.class_ids, found.class_ids])
    if cfg.fragment_iou > 0 and len(boxes) > 1:
        # the fragment rule holds for the joint map's scores too: a promoted, carried or synthesised box that a
        # higher-scoring box of its class overlaps by fragment_iou is a piece of that object, not another one: a
        # promoted box keeps its own score, an added one goes (score 0: NMS drops it). One pass, as the rule on
        # the kept boxes; a promoted box is remembered by the carry before this (find_joint_detections)
        fragment = outranked_overlaps(boxes, all_scores, cfg.fragment_iou, cids,  # the joint rows only
                                      rows=np.flatnonzero(np.concatenate([flags, np.ones(m, dtype=bool)])))
        if fragment.any():
            own = np.concatenate([result.scores, np.zeros(m, np.float32)]).astype(np.float32)
            all_scores[fragment] = own[fragment]  # in place: the scores stay float32
            flags &= ~fragment[:k]
    keep = nms(boxes, all_scores, cids, cfg.nms_iou, cfg.score_threshold, cfg.max_detections)
    return replace(
        result, boxes_xyxy=boxes[keep], scores=all_scores[keep],
        raw_scores=np.concatenate([result.raw_scores, np.zeros(m, np.float32)])[keep], class_ids=cids[keep],
        lat=np.concatenate([result.lat, found.lat])[keep], lon=np.concatenate([result.lon, found.lon])[keep],
        embeddings=None if emb is None else emb[keep],
        from_joint=np.concatenate([flags, np.ones(m, dtype=bool)])[keep],
        view_height_m=None if result.view_height_m is None else np.concatenate([result.view_height_m,
                                                                               np.full(m, np.nan)])[keep],
        alt_latlon=None if result.alt_latlon is None else np.concatenate([result.alt_latlon,
                                                                         np.full((m, 2), np.nan)])[keep])

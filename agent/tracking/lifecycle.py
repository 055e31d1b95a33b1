"""Track life: births from free detections, merging two tracks on one object, quality of tracks in view
but not detected, and retirement (tentative ones die; confirmed ones go to the re-ID memory).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from agent.boxes import box_iou
from agent.tracking.assignment import near_pairs
from agent.tracking.association import expected_boxes
from agent.tracking.far_points import placed_rows
from agent.tracking.model import mahalanobis2_and_logdet, sigma_max
from agent.tracking.state import FrameDetections, Table, TrackState
from shared.geo import Camera, GroundSurface, Pose, latlon_to_local, local_to_latlon, local_to_pixel

__all__ = ["at_image_border", "birth", "decay_unseen_quality", "in_image", "merge_duplicates", "reanchor", "retire"]

log = logging.getLogger(__name__)


def at_image_border(boxes_xyxy: NDArray, width_px: float, height_px: float, margin_px: float) -> NDArray[np.bool_]:
    """(N, 4) xyxy pixel boxes -> (N,) bool: the box comes within margin_px of an image border
    (an object partly out of view, about to leave or just entering). NaN boxes: False."""
    b = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        return (b[:, 0] <= margin_px) | (b[:, 1] <= margin_px) | (b[:, 2] >= width_px - margin_px) \
            | (b[:, 3] >= height_px - margin_px)


def birth(state: TrackState, dets: FrameDetections, det_mask: NDArray[np.bool_], t: float) -> None:
    """Free detections (det_mask) start tentative tracks, strongest first, unless they lie next to a track
    of their class, overlap a box taken in this frame or a stronger newborn (NMS leftovers)."""
    cfg = state.config
    act = state.active
    order = np.flatnonzero(det_mask)
    order = order[np.argsort(-dets.entry[order], kind="stable")]
    # Not next to a track of the class (on the ground), nor overlapping a box taken in this frame:
    # such detections are leftovers around an object the tracker already follows.
    free = np.ones(len(order), dtype=bool)
    if len(act):
        gate = math.sqrt(cfg.birth_suppress_chi2)
        ti, oj = near_pairs(act["x"][:, :2], gate * sigma_max(act["P"][:, :2, :2]), dets.z[order],
                            gate * sigma_max(dets.R[order]))
        same = act["cls"][ti] == dets.cls[order[oj]]
        ti, oj = ti[same], oj[same]
        dj = order[oj]
        d2, _ = mahalanobis2_and_logdet(dets.z[dj] - act["x"][ti, :2], act["P"][ti, :2, :2] + dets.R[dj])
        # Not by a point beyond the far reach; within it, one followed in the image (far_image_sigma_m) beside a
        # track on the ground is still a leftover around its object.
        if dets.unplaced is not None:
            d2 = np.where(dets.unplaced[dj], np.inf, d2)
        free[oj[d2 <= cfg.birth_suppress_chi2]] = False
        taken = act["matched"]
        if taken.any():
            iou = box_iou(act["box"][taken], dets.boxes[order])
            same = act["cls"][taken][:, None] == dets.cls[order][None, :]
            free &= ~((iou >= cfg.birth_suppress_iou) & same).any(axis=0)
    born: list[int] = []
    for j in order[free]:  # strongest first; each newborn suppresses the weaker ones around it
        if born:
            b = np.asarray(born)
            same = dets.cls[b] == dets.cls[j]
            if same.any():
                if box_iou(dets.boxes[j][None], dets.boxes[b[same]]).max() >= cfg.birth_suppress_iou:
                    continue
                near = b[same]
                d2, _ = mahalanobis2_and_logdet(dets.z[j][None] - dets.z[near], dets.R[near] + dets.R[j][None])
                if (dets.loose is None or not dets.loose[j]) and d2.min() <= cfg.birth_suppress_chi2:
                    continue
        born.append(int(j))
    if not born:
        return
    b = np.asarray(born, dtype=np.int64)
    n = len(b)
    x = np.zeros((n, 4))
    x[:, :2] = dets.z[b]
    P = np.zeros((n, 4, 4))
    P[:, :2, :2] = dets.R[b]
    P[:, 2:, 2:] = state.motion.initial_velocity_cov(dets.cls[b])
    ids = np.arange(state.next_id, state.next_id + n, dtype=np.int64)
    state.next_id += n
    # With lost tracks of its class around, a new track may turn out to be an old one.
    pending = np.zeros(n, dtype=bool)
    loose = np.zeros(n, bool) if dets.loose is None else dets.loose[b]
    if cfg.reid_delay_s > 0 and len(state.lost):  # not by a ground position beyond the far reach
        pending = np.isin(dets.cls[b], state.lost["cls"]) & placed_rows(dets)[b]
    act.append(id=ids, cls=dets.cls[b], x=x, P=P, box=dets.boxes[b], score=dets.scores[b],
               hits=np.ones(n, np.int64), support=np.ones(n, np.int64), t_hit=np.full(n, t),
               t_born=np.full(n, t), t_shadow=np.full(n, np.nan), confirmed=~pending & (cfg.confirm_hits <= 1),
               matched=np.ones(n, bool), reid=np.zeros(n, bool), strong=dets.raw[b] >= cfg.confirm_score,
               R_last=dets.R[b], quality=dets.raw[b], heading_hit=np.full(n, state.heading_now),
               pending=pending, probation=np.zeros(n, bool), shown=np.zeros(n, bool), det_row=b,
               loose=loose,
               **({} if dets.emb is None else {"emb": dets.emb[b]}))
    dets.used[b] = True


def decay_unseen_quality(state: TrackState, pose: Pose, camera: Camera, terrain: GroundSurface | None = None) -> None:
    """A track in view without a detection counts as a zero in its quality: persistent clutter
    that the detector reports in part of the frames, or weakly, falls below report_quality. terrain: the
    ground the tracks stand on (`--dem`; in view where their terrain point projects into the frame)."""
    act = state.active
    miss = np.flatnonzero(~act["matched"])
    if not len(miss) or state.origin is None:
        return
    _, inside = in_image(state, act["x"][miss, :2], pose, camera, terrain, state.config.unseen_margin)
    act.cols["quality"][miss[inside]] *= 1.0 - state.config.quality_rate


def in_image(state: TrackState, en: NDArray, pose: Pose, camera: Camera, terrain: GroundSurface | None = None,
             margin: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Pixels (N, 2) of ground points en (N, 2), metres in the tracker's local frame, seen from pose (on `terrain`
    when given), and whether each lies in the image at least margin (a share of its width and height) from its
    border. Needs the local frame's origin (state.origin)."""
    assert state.origin is not None
    uav_e, uav_n = (float(v) for v in latlon_to_local(pose.lat, pose.lon, *state.origin))
    uv, ok = local_to_pixel(en[:, 0] - uav_e, en[:, 1] - uav_n, camera, pose, terrain=terrain)
    mu, mv = margin * camera.width, margin * camera.height
    return uv, ok & (uv[:, 0] >= mu) & (uv[:, 0] <= camera.width - mu) & (uv[:, 1] >= mv) \
        & (uv[:, 1] <= camera.height - mv)


def merge_duplicates(state: TrackState, t: float) -> None:
    """Two confirmed tracks on one object (they share its detections, taking turns): after
    `merge_after_s` of being within `merge_chi2` of a track with more hits, its velocity within
    `merge_velocity_chi2` of that track's, a track is dropped."""
    if state.config.merge_edge_twins > 0 and (state.edge_twins or state.edge_twins_now):
        _merge_edge_twins(state)
    cfg = state.config
    act = state.active
    conf = np.flatnonzero(act["confirmed"])
    shadowed = np.zeros(len(act), dtype=bool)
    idle = np.zeros(len(act), dtype=bool)  # next to a duplicate, neither took a detection: no evidence either way
    if len(conf) >= 2:
        pos = act["x"][conf, :2]
        pairs = cKDTree(pos).query_pairs(cfg.merge_max_m, output_type="ndarray")
        if len(pairs):
            i, j = conf[pairs[:, 0]], conf[pairs[:, 1]]
            same = act["cls"][i] == act["cls"][j]
            # Two convincing detections in one frame: two objects, whatever their distance.
            same &= ~(act["strong"][i] & act["strong"][j])
            # Taking turns needs a turn: two tracks coasting side by side (out of view, their
            # covariances growing) are no evidence of a duplicate; a frame where neither took a detection
            # (an object the detector missed) keeps the count of one that is (cfg.merge_keep_idle).
            turn = act["matched"][i] | act["matched"][j]
            i_idle, j_idle = i[same & ~turn], j[same & ~turn]
            same &= turn
            i, j = i[same], j[same]
            diff = act["x"][i, :2] - act["x"][j, :2]
            # Tracks that take turns on one object's detections differ by about a measurement error.
            S = act["P"][i, :2, :2] + act["P"][j, :2, :2] + 0.5 * (act["R_last"][i] + act["R_last"][j])
            d2, _ = mahalanobis2_and_logdet(diff, S)
            close = d2 <= cfg.merge_chi2
            if cfg.merge_velocity_chi2 > 0 and close.any():
                # two objects passing each other (walkers crossing) move apart: their velocities differ
                dv2, _ = mahalanobis2_and_logdet(act["x"][i, 2:] - act["x"][j, 2:],
                                                 act["P"][i, 2:, 2:] + act["P"][j, 2:, 2:])
                close &= dv2 <= cfg.merge_velocity_chi2
            i, j = i[close], j[close]
            shadowed[_weaker(act, i, j)] = True
            if cfg.merge_keep_idle and len(i_idle):
                idle[i_idle] = idle[j_idle] = True
    t_shadow = act.cols["t_shadow"]
    t_shadow[~shadowed & ~idle] = np.nan
    t_shadow[shadowed & np.isnan(t_shadow)] = t
    merged = shadowed & (t - t_shadow >= cfg.merge_after_s)
    if merged.any():
        log.debug("merged duplicate track(s) %s", act["id"][merged].tolist())
        act.keep(~merged)


def _weaker(act: Table, i: NDArray[np.int64], j: NDArray[np.int64]) -> NDArray[np.int64]:
    """Of each pair of active rows (i[k], j[k]) on one object, the duplicate to drop: the track with fewer hits
    (ties: the newer id)."""
    j_weaker = (act["hits"][j] < act["hits"][i]) | ((act["hits"][j] == act["hits"][i]) & (act["id"][j] > act["id"][i]))
    return np.where(j_weaker, j, i)


def _merge_edge_twins(state: TrackState) -> None:
    """Two confirmed tracks of a class that detections placed one on each side of a terrain edge in merge_edge_twins
    frames (TrackState.edge_twins), never both taking a detection in such a frame, follow one object: in the next
    such frame the one with fewer hits (the newer on ties) is dropped. A frame where both took one marks two objects
    for good. Pairs of tracks no longer active are forgotten."""
    act = state.active
    row = {int(i): k for k, i in enumerate(act["id"].tolist())}
    for key in [k for k in state.edge_twins if k[0] not in row or k[1] not in row]:
        del state.edge_twins[key]
    drop = np.zeros(len(act), dtype=bool)
    for ia, ib in sorted(state.edge_twins_now):
        a, b = row.get(ia), row.get(ib)
        if a is None or b is None or drop[a] or drop[b] or state.edge_twins.get((ia, ib), 0) < 0:
            continue
        if act["matched"][a] and act["matched"][b]:
            state.edge_twins[(ia, ib)] = -1
            continue
        n = state.edge_twins[(ia, ib)] = state.edge_twins.get((ia, ib), 0) + 1
        if n >= state.config.merge_edge_twins and act["confirmed"][a] and act["confirmed"][b] \
                and act["cls"][a] == act["cls"][b]:
            drop[_weaker(act, np.array([a]), np.array([b]))] = True
            del state.edge_twins[(ia, ib)]
    state.edge_twins_now.clear()
    if drop.any():
        log.debug("merged edge twin track(s) %s", act["id"][drop].tolist())
        act.keep(~drop)


def retire(state: TrackState, t: float, camera: Camera | None = None) -> None:
    """Tentative tracks unmatched too long die; confirmed ones go to the re-ID memory, at once
    when their object left the view through the image border (`exit_margin_px`)."""
    cfg = state.config
    act = state.active
    if len(act):
        idle = t - act["t_hit"]
        conf = act["confirmed"]
        drop = (conf & (idle > cfg.max_coast_s)) | (~conf & (idle > cfg.tentative_coast_s))
        if camera is not None and cfg.exit_margin_px >= 0:
            boxes = act["box"]
            if cfg.exit_expected:
                # where the track's image motion (a sweep streams every box out of the view) has taken it
                boxes = expected_boxes(state, np.arange(len(act)), t)
            drop |= conf & (idle > cfg.exit_coast_s) & at_image_border(
                boxes, camera.width, camera.height, cfg.exit_margin_px)
        # A tentative track not confirmed soon lives on boosted leftovers around some object.
        drop |= ~conf & (t - act["t_born"] > cfg.confirm_window_s + cfg.reid_delay_s)
        to_lost = drop & conf
        if to_lost.any() and cfg.reid_horizon_s > 0:
            state.lost.append(id=act["id"][to_lost], cls=act["cls"][to_lost], pos=act["x"][to_lost][:, :2],
                              vel=act["x"][to_lost][:, 2:], Ppos=act["P"][to_lost][:, :2, :2],
                              box=act["box"][to_lost], score=act["score"][to_lost], hits=act["hits"][to_lost],
                              support=act["support"][to_lost], t_hit=act["t_hit"][to_lost],
                              quality=act["quality"][to_lost], claimed=np.zeros(int(to_lost.sum()), bool),
                              **({"emb": act["emb"][to_lost]} if "emb" in act.cols else {}))
        failed = drop & act["probation"]
        if failed.any() and len(state.lost):
            # A revival that was not confirmed: the object's memory entry is free again, unchanged.
            state.lost.cols["claimed"][np.isin(state.lost["id"], act["id"][failed])] = False
        if drop.any():
            act.keep(~drop)
    if len(state.lost):
        state.lost.keep(t - state.lost["t_hit"] <= cfg.reid_horizon_s)


def reanchor(state: TrackState, pose: Pose) -> None:
    """Put the local frame's origin at the UAV when it has flown more than `reanchor_m` from it (the first pose
    sets it), the tracks and the re-ID memory moved along."""
    if state.origin is None:
        state.origin = (pose.lat, pose.lon)
        return
    e, n = latlon_to_local(pose.lat, pose.lon, *state.origin)
    if math.hypot(float(e), float(n)) <= state.config.reanchor_m:
        return
    old, new = state.origin, (pose.lat, pose.lon)
    for table, key in ((state.active, "x"), (state.lost, "pos")):
        if len(table):
            pos = table.cols[key]
            lat, lon = local_to_latlon(pos[:, 0], pos[:, 1], *old)
            pos[:, 0], pos[:, 1] = latlon_to_local(lat, lon, *new)
    state.origin = new
    log.debug("re-anchored the local frame at %.6f, %.6f", *new)

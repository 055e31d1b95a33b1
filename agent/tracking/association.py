"""Association: one frame's detections, with the NMS leftovers set aside, matched to the active tracks on
the ground (Mahalanobis gate, negative log-likelihood cost) or, without a ground point, by image IoU.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agent.boxes import box_iou, paired_iou
from agent.frame_result import FrameResult
from agent.tracking.appearance import blend_descriptors, descriptor_distance, unit_rows
from agent.tracking.assignment import gated_assignment, near_pairs, sparse_assignment
from agent.tracking.config import TrackerConfig
from agent.tracking.model import FloatArray, kalman_update, mahalanobis2_and_logdet, sigma_max
from agent.tracking.state import FrameDetections, Table, TrackState

__all__ = ["associate_centres", "associate_ground", "associate_image", "associate_iou", "duplicate_mask",
           "expected_boxes", "fresh_in_image", "frame_detections", "ground_duplicates", "image_cost", "mark_hit",
           "note_image_offsets", "resolve_alternatives"]


def frame_detections(result: FrameResult, config: TrackerConfig) -> FrameDetections:
    """The pipeline's result as the stages use it: float64 columns, the entry score and score cost, the
    image duplicates already set aside (`used`), no ground points yet (`geo` False), unit descriptors.

    ValueError when the result's arrays differ in length.
    """
    boxes = np.asarray(result.boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(result.scores, dtype=np.float64).reshape(-1)
    raw = np.asarray(result.raw_scores, dtype=np.float64).reshape(-1)
    class_ids = np.asarray(result.class_ids, dtype=np.int64).reshape(-1)
    n = len(scores)
    alt = None if result.alt_latlon is None else np.asarray(result.alt_latlon, dtype=np.float64)
    if not (len(boxes) == len(raw) == len(class_ids) == n) or (alt is not None and alt.shape != (n, 2)):
        raise ValueError(f"FrameResult arrays differ in length: boxes {len(boxes)}, scores {n}, "
                         f"raw_scores {len(raw)}, class_ids {len(class_ids)}"
                         + ("" if alt is None else f", alt_latlon {alt.shape} (want ({n}, 2))"))
    return FrameDetections(
        boxes=boxes, scores=scores, raw=raw, entry=raw if config.birth_on_raw else scores,
        score_cost=-config.score_weight * np.log(np.clip(raw, 1e-3, None)), cls=class_ids,
        lat=np.asarray(result.lat, dtype=np.float64).reshape(-1),
        lon=np.asarray(result.lon, dtype=np.float64).reshape(-1),
        used=duplicate_mask(boxes, scores, class_ids, config.duplicate_iou, config.duplicate_ioa),
        z=np.full((n, 2), np.nan), R=np.zeros((n, 2, 2)), geo=np.zeros(n, dtype=bool),
        emb=unit_rows(result.embeddings, n) if config.use_appearance and result.embeddings is not None else None,
        view_h=None if result.view_height_m is None else np.asarray(result.view_height_m, np.float64).reshape(-1),
        alt_latlon=alt)


def duplicate_mask(boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray, iou: float,
                   ioa: float) -> NDArray[np.bool_]:
    """Which detections duplicate a higher-scoring one of the same class in the image.

    boxes_xyxy (N, 4) pixels, scores (N,), class_ids (N,). A box is a duplicate when its IoU with a
    stronger box (not itself a duplicate) is >= iou, or their intersection covers >= ioa of the
    smaller of the two. Returns (N,) bool, True for duplicates (greedy, strongest first).
    """
    n = len(scores)
    dup = np.zeros(n, dtype=bool)
    if n < 2:
        return dup
    order = np.argsort(-np.asarray(scores), kind="stable")
    b = np.asarray(boxes_xyxy, dtype=np.float64)[order]
    c = np.asarray(class_ids)[order]
    centre = 0.5 * (b[:, :2] + b[:, 2:])
    half_diag = 0.5 * np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    i, j = near_pairs(centre, half_diag, centre, half_diag)
    keep = (i > j) & (c[i] == c[j])  # i weaker than j (later in score order)
    i, j = i[keep], j[keep]
    if not len(i):
        return dup
    inter = np.clip(np.minimum(b[i, 2], b[j, 2]) - np.maximum(b[i, 0], b[j, 0]), 0.0, None) \
        * np.clip(np.minimum(b[i, 3], b[j, 3]) - np.maximum(b[i, 1], b[j, 1]), 0.0, None)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area[i] + area[j] - inter
    overlap = (inter > 0) & ((inter >= iou * union) | (inter >= ioa * np.minimum(area[i], area[j])))
    i, j = i[overlap], j[overlap]
    stronger: dict[int, list[int]] = {}
    for a_, b_ in zip(i.tolist(), j.tolist(), strict=True):
        stronger.setdefault(a_, []).append(b_)
    dup_sorted = np.zeros(n, dtype=bool)
    for k in sorted(stronger):
        # duplicates of duplicates are judged against the kept boxes only
        if not dup_sorted[stronger[k]].all():
            dup_sorted[k] = True
    dup[order] = dup_sorted
    return dup


def ground_duplicates(z: FloatArray, R: FloatArray, raw: FloatArray, class_ids: NDArray, candidates: NDArray[np.bool_],
                      chi2: float, raw_ratio: float) -> NDArray[np.bool_]:
    """Detections that duplicate a much more confident one of their class on the ground.

    z (N, 2) ground points, metres; R (N, 2, 2) their covariances; raw (N,) detector confidences;
    candidates (N,) bool: the rows to consider. Row j is a duplicate of row i when both are
    candidates of one class, (z_j - z_i) is within `chi2` (squared Mahalanobis, R_i + R_j) and
    raw_j < raw_ratio * raw_i. Returns (N,) bool.
    """
    out = np.zeros(len(raw), dtype=bool)
    idx = np.flatnonzero(candidates)
    if len(idx) < 2:
        return out
    radius = math.sqrt(chi2) * sigma_max(R[idx])
    i, j = near_pairs(z[idx], radius, z[idx], radius)
    i, j = idx[i], idx[j]
    keep = (raw[i] < raw_ratio * raw[j]) & (class_ids[i] == class_ids[j])
    i, j = i[keep], j[keep]
    d2, _ = mahalanobis2_and_logdet(z[i] - z[j], R[i] + R[j])
    out[i[d2 <= chi2]] = True
    return out


def resolve_alternatives(state: TrackState, dets: FrameDetections, max_m: float) -> NDArray[np.bool_]:
    """Detections with a second ground point past a terrain edge (dets.alt) take it as their point where it lies
    nearer an active track of their class than the first one does (within max_m metres), within that track's gate
    (gate_chi2 under its covariance and its last measurement's) and no detection whose box does not overlap this
    one has its first point nearer that track (another object's track is no magnet, whether its own detection is
    there or missed; a duplicate box of the same object is no blocker). Swapped in place (dets.alt then steps back
    to the first point), so that every stage sees the side the tracker follows: a box at a bank's lip lands on
    either level from frame to frame. The error model keeps the first point's effective height (dets.view_h).
    Returns (N,) bool: the swapped rows."""
    swap = np.zeros(len(dets.z), dtype=bool)
    act = state.active
    if dets.alt is None or not len(act):
        return swap
    geo = np.flatnonzero(dets.geo)
    di = geo[np.isfinite(dets.alt[geo, 0])]
    if not len(di):
        return swap
    alt_pts = dets.z[di] + dets.alt[di]
    first, first_track = _nearest_tracks(act, dets.z[di], dets.cls[di], max_m)
    alt_d, alt_track = _nearest_tracks(act, alt_pts, dets.cls[di], max_m)
    _note_edge_twins(state, dets.z[di], alt_pts, first_track, alt_track)
    cand = np.flatnonzero((alt_track >= 0) & (alt_d < first))
    cand = cand[_in_track_gate(state, alt_pts[cand], alt_track[cand])]  # no far magnet
    for k in cand:
        j, t = di[k], alt_track[k]
        # a detection of another object (no overlap in the image) nearer the track: the track is that object's
        near = geo[(dets.cls[geo] == dets.cls[j]) & (np.hypot(*(dets.z[geo] - act["x"][t, :2]).T) < alt_d[k])]
        near = near[near != j]
        swap[j] = not len(near) or bool((box_iou(dets.boxes[j][None], dets.boxes[near])[0] > 0).all())
    dets.z[swap], dets.alt[swap] = dets.z[swap] + dets.alt[swap], -dets.alt[swap]
    return swap


def _note_edge_twins(state: TrackState, first: FloatArray, alt: FloatArray, first_track: NDArray[np.int64],
                     alt_track: NDArray[np.int64]) -> None:
    """The pairs of track ids with a detection whose first point lies in one track's gate and whose alternative in
    the other's (state.edge_twins_now, this frame's; lifecycle.merge_duplicates counts them): one box explains both
    tracks, one person on two sides of an edge."""
    act = state.active
    both = np.flatnonzero((first_track >= 0) & (alt_track >= 0) & (first_track != alt_track))
    if not len(both):
        return
    a, b = first_track[both], alt_track[both]
    inside = _in_track_gate(state, first[both], a) & _in_track_gate(state, alt[both], b)
    for ia, ib in zip(act["id"][a[inside]].tolist(), act["id"][b[inside]].tolist(), strict=True):
        state.edge_twins_now.add((min(ia, ib), max(ia, ib)))


def _in_track_gate(state: TrackState, points: FloatArray, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
    """(K,) bool: points[k] lies within active track rows[k]'s gate (gate_chi2 under the track's covariance and its
    last measurement's, as a detection of it would be judged)."""
    act = state.active
    if not len(rows):
        return np.zeros(0, dtype=bool)
    d2, _ = mahalanobis2_and_logdet(points - act["x"][rows, :2], act["P"][rows, :2, :2] + act["R_last"][rows])
    return d2 <= state.config.gate_chi2


def _nearest_tracks(act: Table, points: FloatArray, cls: NDArray, max_m: float
                    ) -> tuple[FloatArray, NDArray[np.int64]]:
    """Within max_m metres and of the points' class: each point's distance to its nearest active track (inf: none)
    and that track's row (-1: none)."""
    ti, pj = near_pairs(act["x"][:, :2], np.full(len(act), max_m), points, np.zeros(len(points)))
    same = act["cls"][ti] == cls[pj]
    ti, pj = ti[same], pj[same]
    d = np.hypot(points[pj, 0] - act["x"][ti, 0], points[pj, 1] - act["x"][ti, 1])
    per_point = np.full(len(points), np.inf)
    track = np.full(len(points), -1, dtype=np.int64)
    order = np.lexsort((d, pj))  # by point, nearest first
    first = order[np.r_[True, pj[order][1:] != pj[order][:-1]]] if len(order) else order
    per_point[pj[first]], track[pj[first]] = d[first], ti[first]
    return per_point, track


def associate_ground(state: TrackState, dets: FrameDetections, det_mask: NDArray[np.bool_], t: float,
                     track_mask: NDArray[np.bool_]) -> None:
    """Assign detections (det_mask) to unmatched tracks (track_mask) on the ground and update those tracks.

    Pairs within the Mahalanobis gate and the hard cap cost the negative log-likelihood of the ground
    distance plus the score, image and appearance terms; `sparse_assignment` picks the pairs.
    """
    cfg = state.config
    act = state.active
    track_mask = track_mask & ~act["matched"]
    if not len(act) or not track_mask.any() or not det_mask.any():
        return
    ti = np.flatnonzero(track_mask)
    di = np.flatnonzero(det_mask)
    # Candidate pairs within the gate's longest axis (and the hard cap) only: large scenes stay sparse.
    gate = math.sqrt(cfg.gate_chi2)
    t_rad = np.minimum(gate * sigma_max(act["P"][ti, :2, :2]), cfg.max_gate_m)
    d_rad = np.minimum(gate * sigma_max(dets.R[di]), cfg.max_gate_m)
    pi, pj = near_pairs(act["x"][ti, :2], t_rad, dets.z[di], d_rad)
    tr, dt_ = ti[pi], di[pj]
    keep = act["cls"][tr] == dets.cls[dt_]
    tr, dt_ = tr[keep], dt_[keep]
    diff = dets.z[dt_] - act["x"][tr, :2]
    d2, logdet = mahalanobis2_and_logdet(diff, act["P"][tr, :2, :2] + dets.R[dt_])
    keep = (d2 <= cfg.gate_chi2) & (np.hypot(diff[:, 0], diff[:, 1]) <= cfg.max_gate_m)
    if state.image_steady and cfg.image_gate > 0 and keep.any():
        keep[keep] = _image_gate(state, tr[keep], dets.boxes[dt_[keep]], t)
    tr, dt_, d2, logdet = tr[keep], dt_[keep], d2[keep], logdet[keep]
    # Negative log-likelihood: distance, the track's own uncertainty (relative to the detection's,
    # so uncertain tracks pay for their wide gates), the detector's confidence, the image overlap.
    _, logdet_r = mahalanobis2_and_logdet(diff[keep], dets.R[dt_])
    cost = d2 + (logdet - logdet_r) + dets.score_cost[dt_]
    if cfg.image_weight > 0:
        cost += cfg.image_weight * image_cost(state, tr, dets.boxes[dt_], t)
    if cfg.appearance_weight > 0 and dets.emb is not None and len(tr):
        app, _ = descriptor_distance(act["emb"][tr], dets.emb[dt_])
        cost += cfg.appearance_weight * app
    r, c = sparse_assignment(tr, dt_, cost, unassigned_cost=cfg.pair_max_cost)
    if len(r):
        _, speed_cap = state.motion.accel_and_cap(act["cls"][r])
        act.cols["x"][r], act.cols["P"][r] = kalman_update(act["x"][r], act["P"][r], dets.z[c], dets.R[c], speed_cap)
        mark_hit(state, r, dets, c, t)


def fresh_in_image(state: TrackState, ti: NDArray[np.int64], t: float) -> NDArray[np.bool_]:
    """(K,) bool: the image still shows track ti[k] about where it was last seen (matched within
    image_max_age_s, the heading turned by at most image_max_turn_deg since)."""
    cfg = state.config
    act = state.active
    turned = np.abs((state.heading_now - act["heading_hit"][ti] + 180.0) % 360.0 - 180.0)
    return (t - act["t_hit"][ti] <= cfg.image_max_age_s) & (turned <= cfg.image_max_turn_deg)


def expected_boxes(state: TrackState, ti: NDArray[np.int64], t: float) -> FloatArray:
    """(K, 4) xyxy pixels: where track ti[k] is expected in the image at time t, its last box moved by its
    image velocity since it was matched (`TrackerConfig.image_velocity`; else, or unknown: the last box)."""
    act = state.active
    boxes = act["box"][ti]
    if not state.config.image_velocity or not len(ti):
        return boxes
    vel = act["vel_img"][ti]
    shift = np.where(np.isfinite(vel), vel, 0.0) * (t - act["t_hit"][ti])[:, None]
    return boxes + np.concatenate([shift, shift], axis=1)


def _image_gate(state: TrackState, ti: NDArray[np.int64], boxes: FloatArray, t: float) -> NDArray[np.bool_]:
    """(K,) bool: box k is where the image can show track ti[k]. For a track matched within image_gate_age_s
    while the heading turned by at most image_max_turn_deg, the box centre must lie within (image_gate +
    image_gate_growth_per_s * seconds since) times the two boxes' mean size (square root of the area) of
    the track's expected box; other tracks pass. Only used in frames whose image the
    registration found steady (`TrackState.image_steady`): ground gates of narrow cameras span hundreds
    of pixels, wide enough to chain a track through the detector's scattered false positives."""
    cfg = state.config
    ok = np.ones(len(ti), dtype=bool)
    act = state.active
    age = t - act["t_hit"][ti]
    turned = np.abs((state.heading_now - act["heading_hit"][ti] + 180.0) % 360.0 - 180.0)
    held = (age <= cfg.image_gate_age_s) & (turned <= cfg.image_max_turn_deg)
    if held.any():
        a, b = expected_boxes(state, ti[held], t), boxes[held]
        size = 0.5 * (np.sqrt(np.abs((a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])))
                      + np.sqrt(np.abs((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]))))
        dist = 0.5 * np.hypot(a[:, 0] + a[:, 2] - b[:, 0] - b[:, 2], a[:, 1] + a[:, 3] - b[:, 1] - b[:, 3])
        ok[held] = dist <= size * (cfg.image_gate + cfg.image_gate_growth_per_s * age[held])
    return ok


def image_cost(state: TrackState, ti: NDArray[np.int64], boxes: FloatArray, t: float) -> FloatArray:
    """(K,) 1 - overlap of track ti[k]'s expected box with boxes[k] where the image still shows the track
    where it was (`fresh_in_image`); 0.5 elsewhere (no image evidence either way). The overlap is the IoU,
    or with `TrackerConfig.image_overlap` "giou", in a frame whose image the registration paired with the
    tracks (`TrackState.image_steady`), the generalised IoU (cost in [0, 2], growing with the distance between
    boxes that do not overlap). Where a shake moved the whole image, the distance is the shake's: IoU then."""
    cost = np.full(len(ti), 0.5)
    fresh = fresh_in_image(state, ti, t)
    if fresh.any():
        generalised = state.config.image_overlap == "giou" and state.image_steady
        cost[fresh] = 1.0 - paired_iou(expected_boxes(state, ti[fresh], t), boxes[fresh], generalised=generalised)
    return cost


def associate_image(state: TrackState, dets: FrameDetections, det_mask: NDArray[np.bool_], t: float,
                    track_mask: NDArray[np.bool_], iou_min: float) -> None:
    """First round where the image is the better cue: tracks (track_mask) the image still shows
    (`fresh_in_image`) take the detections (det_mask) that overlap their expected box by IoU >= iou_min
    (optimal assignment on IoU, one class), whatever the ground says. A pair whose ground point is within
    the gate updates the track's filter; one beyond it (a telemetry error the registration did not remove)
    only moves its box, and the filter coasts."""
    cfg = state.config
    act = state.active
    ti = np.flatnonzero(track_mask & ~act["matched"])
    ti = ti[fresh_in_image(state, ti, t)]
    di = np.flatnonzero(det_mask & ~dets.used)
    if not len(ti) or not len(di):
        return
    iou = box_iou(expected_boxes(state, ti, t), dets.boxes[di])
    allowed = (iou >= iou_min) & (act["cls"][ti][:, None] == dets.cls[di][None, :])
    r, c = gated_assignment(-iou, allowed)
    if not len(r):
        return
    tr, dr = ti[r], di[c]
    diff = dets.z[dr] - act["x"][tr, :2]
    d2, _ = mahalanobis2_and_logdet(diff, act["P"][tr, :2, :2] + dets.R[dr])
    upd = dets.geo[dr] & (d2 <= cfg.gate_chi2)
    if upd.any():
        u, z = tr[upd], dr[upd]
        _, speed_cap = state.motion.accel_and_cap(act["cls"][u])
        act.cols["x"][u], act.cols["P"][u] = kalman_update(act["x"][u], act["P"][u], dets.z[z], dets.R[z], speed_cap)
    mark_hit(state, tr, dets, dr, t)


def associate_centres(state: TrackState, dets: FrameDetections, t: float, det_mask: NDArray[np.bool_],
                      gate: float) -> None:
    """Match detections (det_mask) to tracks by the distance of their box centres from each track's expected
    centre, in the two boxes' mean sizes (square root of the area), within `gate`: far boxes are a few pixels wide
    and one pixel of jitter halves their IoU. The expected centre is the last one, or with `far_shift_radius` that
    moved by the image's common motion since (`far_points.measure_image_shift`). A pair whose ground point lies
    within the track's gate updates its filter (a loose far point, `far_points.fill_far_points`, still says how the
    object moves); others coast."""
    act = state.active
    cfg = state.config
    det_mask = det_mask & ~dets.used & (dets.scores >= cfg.low_score)
    ti = np.flatnonzero(~act["matched"])
    di = np.flatnonzero(det_mask)
    if not len(ti) or not len(di):
        return
    prev, boxes = act["box"][ti], dets.boxes[di]
    size_t = np.sqrt(np.prod(np.maximum(prev[:, 2:] - prev[:, :2], 1.0), axis=1))
    size_d = np.sqrt(np.prod(np.maximum(boxes[:, 2:] - boxes[:, :2], 1.0), axis=1))
    size = 0.5 * (size_t[:, None] + size_d[None, :])
    expected = 0.5 * (prev[:, :2] + prev[:, 2:])
    centres = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    same = act["cls"][ti][:, None] == dets.cls[di][None, :]
    if cfg.far_shift_radius > 0:
        expected = expected + np.nan_to_num(state.image_motion.offset_at(t) - act["img_offset"][ti])
    step = centres[None, :, :] - expected[:, None, :]
    dist = np.hypot(step[..., 0], step[..., 1]) / size
    r, c = gated_assignment(dist, (dist <= gate) & same)
    if not len(r):
        return
    tr, dr = ti[r], di[c]
    d2, _ = mahalanobis2_and_logdet(dets.z[dr] - act["x"][tr, :2], act["P"][tr, :2, :2] + dets.R[dr])
    upd = dets.geo[dr] & (d2 <= cfg.gate_chi2)
    if upd.any():
        u, z = tr[upd], dr[upd]
        _, speed_cap = state.motion.accel_and_cap(act["cls"][u])
        act.cols["x"][u], act.cols["P"][u] = kalman_update(act["x"][u], act["P"][u], dets.z[z], dets.R[z], speed_cap)
    mark_hit(state, tr, dets, dr, t)


def note_image_offsets(state: TrackState, t: float) -> None:
    """The tracks matched (or born) in the frame at time t keep the image's common offset then
    (`image_motion.ImageMotion`): their boxes are expected moved by the image's motion since."""
    act = state.active
    if len(act):
        act.cols["img_offset"][act["matched"]] = state.image_motion.offset_at(t)


def associate_iou(state: TrackState, dets: FrameDetections, t: float, det_mask: NDArray[np.bool_]) -> None:
    """Match detections (det_mask) to tracks by IoU with each track's last box; the ground state only coasts."""
    act = state.active
    det_mask = det_mask & ~dets.used & (dets.scores >= state.config.low_score)
    track_mask = ~act["matched"]
    if not len(act) or not det_mask.any() or not track_mask.any():
        return
    ti = np.flatnonzero(track_mask)
    di = np.flatnonzero(det_mask)
    iou = box_iou(act["box"][ti], dets.boxes[di])
    allowed = (iou >= state.config.iou_threshold) & (act["cls"][ti][:, None] == dets.cls[di][None, :])
    r, c = gated_assignment(-iou, allowed)
    if len(r):
        mark_hit(state, ti[r], dets, di[c], t)


def mark_hit(state: TrackState, ti: NDArray[np.int64], dets: FrameDetections, di: NDArray[np.int64],
             t: float) -> None:
    """Active tracks ti took detections di at time t: their box, score, counts, quality and descriptor."""
    act = state.active
    if state.config.image_velocity:
        # image velocity of the box centre from the last matched box (px/s), averaged over matches
        gap = t - act["t_hit"][ti]
        step = 0.5 * (dets.boxes[di, :2] + dets.boxes[di, 2:] - act["box"][ti, :2] - act["box"][ti, 2:])
        ok = (gap > 0) & (gap <= state.config.image_max_age_s)
        new = np.where(ok[:, None], step / np.where(ok, gap, 1.0)[:, None], np.nan)
        old = act["vel_img"][ti]
        a = state.config.image_velocity_ema
        act.cols["vel_img"][ti] = np.where(np.isfinite(old) & ok[:, None], a * old + (1.0 - a) * new, new)
    act.cols["box"][ti] = dets.boxes[di]
    act.cols["score"][ti] = dets.scores[di]
    act.cols["hits"][ti] += 1
    # Only convincing detections confirm a track: boosted leftovers around an object do not.
    strong = dets.raw[di] >= state.config.confirm_score
    act.cols["quality"][ti] += state.config.quality_rate * (dets.raw[di] - act["quality"][ti])
    act.cols["support"][ti] += strong
    act.cols["strong"][ti] = strong
    if dets.geo[di].all():
        act.cols["R_last"][ti] = dets.R[di]
    act.cols["t_hit"][ti] = t
    act.cols["heading_hit"][ti] = state.heading_now
    if dets.emb is not None:
        act.cols["emb"][ti] = blend_descriptors(act["emb"][ti], dets.emb[di], state.config.appearance_ema)
    act.cols["matched"][ti] = True
    act.cols["det_row"][ti] = di
    act.cols["loose"][ti] &= ~dets.geo[di] | (dets.loose is not None and dets.loose[di])
    act.cols["confirmed"][ti] |= (act["support"][ti] >= state.config.confirm_hits) & ~act["pending"][ti]
    dets.used[di] = True

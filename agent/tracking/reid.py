"""Re-identification: lost tracks remembered for `reid_horizon_s` give their ids back to the detections
(or young unreported tracks) that match them, on probation until confirmed like a new track.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from agent.tracking.appearance import blend_descriptors, cosine_distance, descriptor_distance
from agent.tracking.assignment import gated_assignment
from agent.tracking.far_points import placed_rows
from agent.tracking.model import FloatArray, mahalanobis2_and_logdet, sigma_max
from agent.tracking.state import FrameDetections, TrackState
from shared.geo import local_to_latlon

__all__ = ["evidence_ok", "predict_lost", "reidentify", "resolve_pending", "return_offset", "settle_probation",
           "unreported"]

log = logging.getLogger(__name__)


def predict_lost(state: TrackState, t: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Where the lost tracks are at time t on the ground: positions (L, 2) (each moved on by its class's damped
    velocity, `ClassMotion.persistence_s`, the speed capped), covariances (L, 2, 2) (grown by
    `reid_spread_mps` per second lost) and times lost (L,) seconds."""
    lost = state.lost
    lost_for = np.maximum(t - lost["t_hit"], 0.0)
    speed_cap, spread, tau = state.motion.reid_arrays(lost["cls"])
    vel = lost["vel"]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    vel = vel * np.minimum(1.0, speed_cap / np.maximum(speed, 1e-9))[:, None]
    pred = lost["pos"] + vel * (tau * (1.0 - np.exp(-lost_for / tau)))[:, None]
    cov = lost["Ppos"] + ((spread * lost_for) ** 2)[:, None, None] * np.eye(2)
    return pred, cov, lost_for


def return_offset(pred: FloatArray, pred_cls: NDArray[np.int64], z: FloatArray, cls: NDArray[np.int64], *,
                  max_offset_m: float, inlier_m: float, min_inliers: int) -> FloatArray | None:
    """The common shift (2,) metres that lays returning ground points z (K, 2) of classes cls (K,) onto the
    lost tracks' predictions pred (L, 2) of classes pred_cls (L,), or None.

    A view that comes back brings its objects back together, and the telemetry's error has changed since they
    left (another GPS and heading error, a registration the tracks followed in the meantime): every returning
    point then sits metres from its prediction in the same direction, and neighbours swap ids. Each pair of a
    point and a prediction within max_offset_m proposes a shift; the shift that lays the most points within
    inlier_m of a prediction wins (counted one to one at most: min of points and predictions near), if it lays
    at least min_inliers and two more than no shift; it is refined to the median of its inliers' differences.
    """
    if min_inliers <= 0 or len(pred) < min_inliers or len(z) < min_inliers:
        return None
    same = pred_cls[:, None] == cls[None, :]
    diff = pred[:, None, :] - z[None, :, :]  # (L, K, 2): the shift that lays point k onto prediction l
    li, ki = np.nonzero(same & (np.hypot(diff[..., 0], diff[..., 1]) <= max_offset_m))
    if len(li) < min_inliers:
        return None
    step = max(1, len(li) // 400)  # a bounded number of proposals in crowded frames
    shifts = np.vstack([np.zeros((1, 2)), diff[li[::step], ki[::step]]])  # (M, 2), no shift first
    resid = diff[None] - shifts[:, None, None, :]
    near = (np.hypot(resid[..., 0], resid[..., 1]) <= inlier_m) & same[None]  # (M, L, K)
    count = np.minimum(near.any(axis=1).sum(axis=1), near.any(axis=2).sum(axis=1))
    best = int(np.argmax(count))  # ties: the first, so no shift when it does as well
    if count[best] < min_inliers or count[best] < count[0] + 2:
        return None
    d = np.hypot(resid[best, ..., 0], resid[best, ..., 1])
    d = np.where(near[best], d, np.inf)
    l_best = np.argmin(d, axis=0)  # each point's nearest prediction under the winning shift
    k_in = np.flatnonzero(np.isfinite(d[l_best, np.arange(len(z))]))
    return np.median(diff[l_best[k_in], k_in], axis=0)


def _lost_match(state: TrackState, z: FloatArray, R: FloatArray, cls: NDArray[np.int64], t: float,
                emb: FloatArray | None = None) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """Cost (d2 + logdet, + the appearance term) and gate of every lost track against ground points
    z (K, 2) with covariances R (K, 2, 2) and descriptors emb (K, D) at time t; also the lost
    tracks' times lost (L,)."""
    cfg = state.config
    lost = state.lost
    speed_cap, _, _ = state.motion.reid_arrays(lost["cls"])
    pred, cov, lost_for = predict_lost(state, t)
    S = cov[:, None] + R[None, :]
    diff = z[None, :, :] - pred[:, None, :]
    d2, logdet = mahalanobis2_and_logdet(diff, S)
    dist = np.hypot(diff[..., 0], diff[..., 1])
    # However uncertain the telemetry, the object cannot have gone farther than its speed allows.
    meas_sd = np.sqrt(np.maximum(R[:, 0, 0] + R[:, 1, 1], 0.0))
    reach = (speed_cap * lost_for + 3.0 * np.sqrt(np.trace(lost["Ppos"], axis1=1, axis2=2)))[:, None]
    allowed = (d2 <= cfg.reid_gate_chi2) & (dist <= reach + 3.0 * meas_sd[None, :])
    allowed &= (lost["cls"][:, None] == cls[None, :]) & ~lost["claimed"][:, None]
    cost = d2 + logdet
    if emb is not None and "emb" in lost.cols:
        app, known = descriptor_distance(lost["emb"][:, None, :], emb[None, :, :])
        cost = cost + cfg.reid_appearance_weight * app
        allowed &= ~known | (app <= cfg.reid_appearance_gate)
    return cost, allowed, lost_for


def resolve_pending(state: TrackState, t: float) -> None:
    """Deferred re-identification: new tracks that have been followed for `reid_delay_s` take
    the id of the lost track they match best. All pending tracks enter one optimal assignment
    (an object that came into view a little later may be the better match), but only those old
    enough are decided."""
    cfg = state.config
    act = state.active
    pend = act["pending"]
    if not pend.any():
        return
    ready = pend & (t - act["t_born"] >= cfg.reid_delay_s)
    if not len(state.lost):
        _settle(state, ready)
        return
    if not ready.any():
        return
    ki = np.flatnonzero(pend)
    cost, allowed, lost_for = _lost_match(state, act["x"][ki, :2], act["P"][ki, :2, :2], act["cls"][ki], t,
                                          act["emb"][ki] if "emb" in act.cols else None)
    if state.evidence_at is not None and cfg.reid_min_evidence > 0 and state.origin is not None:
        lat, lon = local_to_latlon(act["x"][ki, 0], act["x"][ki, 1], *state.origin)
        allowed &= evidence_ok(state, np.ones(len(ki), dtype=bool), act["cls"][ki], lat, lon)[None, :]
    r, c = gated_assignment(cost, allowed)
    now = ready[ki[c]]
    r, k = r[now], ki[c[now]]
    if len(r):
        lost = state.lost
        act.cols["id"][k] = lost["id"][r]
        act.cols["hits"][k] += lost["hits"][r]
        act.cols["support"][k] += lost["support"][r]
        act.cols["confirmed"][k] = True
        act.cols["reid"][k] = True
        act.cols["pending"][k] = False
        keep = np.ones(len(lost), dtype=bool)
        keep[r] = False
        lost.keep(keep)
        state.n_reidentified += len(r)
        log.debug("re-identified %d track(s) after %s s", len(r), np.round(lost_for[r], 2).tolist())
    _settle(state, act["pending"] & ready)


def _settle(state: TrackState, mask: NDArray[np.bool_]) -> None:
    """Pending tracks that matched no lost track become ordinary new tracks."""
    act = state.active
    act.cols["pending"][mask] = False
    act.cols["confirmed"][mask] = act["support"][mask] >= state.config.confirm_hits


def unreported(state: TrackState, dets: FrameDetections, t: float) -> NDArray[np.int64]:
    """Indices of active tracks that may still take a lost track's id (`reid_unreported_s`): born
    within that time, id never reported or not reported now (quality below report_quality), not
    pending or on probation, and holding in this frame a georeferenced detection within the far reach with entry
    score >= reid_score (its row: the "det_row" column)."""
    cfg = state.config
    act = state.active
    if cfg.reid_unreported_s <= 0 or not len(act) or not len(state.lost):
        return np.zeros(0, np.int64)
    row = act["det_row"]
    ok = act["matched"] & (row >= 0) & ~act["probation"] & ~act["pending"] \
        & (t - act["t_born"] <= cfg.reid_unreported_s)
    ok &= ~act["shown"] | (act["quality"] < cfg.report_quality)
    k = np.flatnonzero(ok)
    r = row[k]
    grounded = placed_rows(dets)[r]  # a point beyond the far reach: not by it
    return k[grounded & (dets.entry[r] >= cfg.reid_score)]


def reidentify(state: TrackState, dets: FrameDetections, det_mask: NDArray[np.bool_], t: float,
               young: NDArray[np.int64] | None = None) -> None:
    """Revive lost tracks on free detections (det_mask) and hand lost ids to young unreported
    tracks (active indices `young`, judged on their detection of this frame), in one assignment."""
    cfg = state.config
    lost = state.lost
    di = np.flatnonzero(det_mask)
    young = np.zeros(0, np.int64) if young is None else young
    cand = np.concatenate([di, state.active["det_row"][young]])
    z = dets.z[cand]
    pred, pred_cov, _ = predict_lost(state, t)
    # a shift is measurable only against predictions sharper than its inlier radius (a swimmer lost for
    # seconds, not a walker who may have turned anywhere within metres)
    sharp = ~lost["claimed"] & (sigma_max(pred_cov) <= cfg.reid_offset_inlier_m)
    shift = return_offset(pred[sharp], lost["cls"][sharp], z, dets.cls[cand],
                          max_offset_m=cfg.reid_offset_max_m, inlier_m=cfg.reid_offset_inlier_m,
                          min_inliers=cfg.reid_offset_min_inliers)
    if shift is not None:
        log.debug("returning points shifted by %s m onto the lost tracks", np.round(shift, 2).tolist())
        z = z + shift
        state.n_return_shifts += 1
    cost, allowed, lost_for = _lost_match(state, z, dets.R[cand], dets.cls[cand], t,
                                          None if dets.emb is None else dets.emb[cand])
    shown = state.active["shown"][young]
    if shown.any():
        # A young track whose id was reported (now below report_quality) gives it up only for a lost
        # track that its detection looks more like than like the track itself (both descriptors known).
        if dets.emb is None or "emb" not in lost.cols:
            allowed[:, len(di):] &= ~shown[None, :]
        else:
            own = cosine_distance(state.active["emb"][young], dets.emb[cand[len(di):]])
            app = cosine_distance(lost["emb"][:, None, :], dets.emb[cand[len(di):]][None, :, :])
            with np.errstate(invalid="ignore"):
                allowed[:, len(di):] &= ~shown[None, :] | (app < own[None, :])
    r, c = gated_assignment(cost + dets.score_cost[cand][None, :], allowed)
    adopt = c >= len(di)
    if adopt.any():
        _adopt(state, young[c[adopt] - len(di)], r[adopt], dets, t)
    r, c = r[~adopt], c[~adopt]
    if not len(r):
        return
    rows = di[c]
    n = len(r)
    x = np.zeros((n, 4))
    x[:, :2] = dets.z[rows]
    P = np.zeros((n, 4, 4))
    P[:, :2, :2] = dets.R[rows]
    P[:, 2:, 2:] = state.motion.initial_velocity_cov(lost["cls"][r])
    # Provisional: the revived track must be confirmed like a new one (confirm_hits convincing
    # detections within confirm_window_s); until then the memory entry stays, claimed, and comes
    # back unchanged if the track dies (a false positive must not take, or move, an object's id).
    strong = dets.raw[rows] >= cfg.confirm_score
    extra: dict[str, FloatArray] = {}
    if "emb" in lost.cols:
        extra["emb"] = lost["emb"][r] if dets.emb is None \
            else blend_descriptors(lost["emb"][r], dets.emb[rows], cfg.appearance_ema)
    state.active.append(id=lost["id"][r], cls=lost["cls"][r], x=x, P=P, box=dets.boxes[rows],
                        score=dets.scores[rows], hits=lost["hits"][r] + 1, support=strong.astype(np.int64),
                        t_hit=np.full(n, t), t_born=np.full(n, t), t_shadow=np.full(n, np.nan),
                        confirmed=strong & (cfg.confirm_hits <= 1), matched=np.ones(n, bool),
                        reid=np.zeros(n, bool), strong=strong, R_last=dets.R[rows],
                        quality=lost["quality"][r], heading_hit=np.full(n, state.heading_now),
                        pending=np.zeros(n, bool), probation=np.ones(n, bool), shown=np.ones(n, bool),
                        det_row=rows, loose=np.zeros(n, bool), **extra)
    lost.cols["claimed"][r] = True
    dets.used[rows] = True
    log.debug("revived %d track(s) on probation after %s s", n, np.round(lost_for[r], 2).tolist())


def _adopt(state: TrackState, k: NDArray[np.int64], r: NDArray[np.int64], dets: FrameDetections, t: float) -> None:
    """Young unreported tracks k take the ids of lost tracks r: on probation like a revival (the
    confirmation starts again from this frame's detection; the memory entry stays, claimed)."""
    cfg = state.config
    act, lost = state.active, state.lost
    rows = act["det_row"][k]
    strong = dets.raw[rows] >= cfg.confirm_score
    log.debug("young track(s) %s take lost id(s) %s on probation", act["id"][k].tolist(), lost["id"][r].tolist())
    act.cols["id"][k] = lost["id"][r]
    act.cols["hits"][k] += lost["hits"][r]
    act.cols["support"][k] = strong
    act.cols["confirmed"][k] = strong & (cfg.confirm_hits <= 1)
    act.cols["probation"][k] = True
    act.cols["shown"][k] = True
    act.cols["t_born"][k] = t
    act.cols["t_shadow"][k] = np.nan
    act.cols["quality"][k] = lost["quality"][r]
    if "emb" in lost.cols:
        act.cols["emb"][k] = lost["emb"][r] if dets.emb is None \
            else blend_descriptors(lost["emb"][r], dets.emb[rows], cfg.appearance_ema)
    lost.cols["claimed"][r] = True


def settle_probation(state: TrackState) -> None:
    """Revived tracks that are now confirmed keep their old id for good: their memory entries
    are dropped and their support carried over."""
    act = state.active
    done = act["probation"] & act["confirmed"]
    if not done.any():
        return
    lost = state.lost
    k = np.flatnonzero(done)
    act.cols["probation"][k] = False
    act.cols["reid"][k] = True
    entry = lost["claimed"] & np.isin(lost["id"], act["id"][k])
    if entry.any():
        support = dict(zip(lost["id"][entry].tolist(), lost["support"][entry].tolist(), strict=True))
        act.cols["support"][k] += np.array([support.get(i, 0) for i in act["id"][k].tolist()], dtype=np.int64)
        lost.keep(~entry)
    state.n_reidentified += len(k)
    log.debug("re-identified track(s) %s", act["id"][k].tolist())


def evidence_ok(state: TrackState, cand: NDArray[np.bool_], cls: NDArray[np.int64], lat: FloatArray,
                lon: FloatArray) -> NDArray[np.bool_]:
    """Which candidate rows (cand (N,) with classes cls, at lat/lon (N,)) lie where the memory map holds at
    least `reid_min_evidence` (asks `state.evidence_at`, which must be set)."""
    assert state.evidence_at is not None
    ok = np.zeros(len(cand), dtype=bool)
    for cid in np.unique(cls[cand]):
        sel = cand & (cls == cid)
        values = np.asarray(state.evidence_at(int(cid), lat[sel], lon[sel]), dtype=np.float64)
        ok[sel] = values >= state.config.reid_min_evidence
    return ok

"""Ground points for the boxes the pipeline left without one because they lie beyond its range.

The pipeline georeferences boxes up to its range limit (the memory map's half-window, 150 m by default): farther
boxes boost nothing and used to start no track, so a low view of the sea (17 m up at 1.6 deg, 60 m at 10 deg: two of
the eight real dev videos) gave an empty MOT file. The tracker places them itself, on flat ground and with the
pipeline's telemetry correction, as far as its own error model can: where the along-ray error of a pitch error of
`TrackerConfig.pitch_sigma_deg` (slant^2 / h * d_beta) stays within `far_reach_sigma_m`. Beyond that reach ground
points are too loose to associate by (a simulated view at 400-550 m: HOTA 3-14 on the ground against an image
tracker's 14-17). Such boxes get a loose point, marked `FrameDetections.loose`, out to the horizon: it starts a
track and moves it where it agrees, but they are associated in the image (`TrackerConfig.far_loose_gate`), where
a frame with such points first measures the image's common motion (`measure_image_shift`, `far_shift_radius`).
Measured on simulated far views (docs/tracking.md, "Far views").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agent.boxes import box_anchor_points
from agent.telemetry_correction import GroundCorrection
from agent.tracking.config import TrackerConfig
from agent.tracking.image_motion import FloatArray, common_shift
from agent.tracking.state import FrameDetections, TrackState
from shared.geo import Camera, Pose, horizon_distance_m, local_to_latlon, pixel_to_local

__all__ = ["fill_far_points", "far_reach_m", "measure_image_shift", "place_far_tracks", "placed_rows"]


def far_reach_m(config: TrackerConfig, height_m: float, sigma_m: float | None = None) -> float:
    """The horizontal range (m) within which a ground point's along-ray error, slant^2 / h * d_beta for a pitch error
    d_beta = pitch_sigma_deg, is at most sigma_m (default far_reach_sigma_m); 0 when far_reach_sigma_m is 0 (off) or
    the height is not positive; inf without a pitch error."""
    if config.far_reach_sigma_m <= 0 or not height_m > 0:
        return 0.0
    d_beta = math.radians(config.pitch_sigma_deg)
    if d_beta <= 0:
        return math.inf
    sigma = config.far_reach_sigma_m if sigma_m is None else sigma_m
    return math.sqrt(max(sigma * height_m / d_beta - height_m * height_m, 0.0))


def fill_far_points(dets: FrameDetections, pose: Pose, camera: Camera, correction: GroundCorrection | None,
                    config: TrackerConfig) -> NDArray[np.bool_]:
    """Give the rows of dets without a ground point one within `far_reach_m` (flat ground, the anchor
    `config.far_anchor`, the pose moved by the pipeline's correction as its own points are), and with
    `far_loose_gate` a loose one beyond it (dets.unplaced); those and the points beyond the (shorter) image reach
    of `far_image_sigma_m` are followed in the image (dets.loose); dets.lat / lon are replaced by copies (the
    FrameResult's arrays are not written). Returns (N,) bool: the rows filled."""
    filled = np.zeros(len(dets.lat), dtype=bool)
    miss = ~(np.isfinite(dets.lat) & np.isfinite(dets.lon))
    reach = far_reach_m(config, pose.height_m)
    if not miss.any() or reach <= 0:
        return filled
    moved = pose if correction is None else correction.moved(pose)
    uv = box_anchor_points(dets.boxes[miss], config.far_anchor, pose.pitch_deg)
    loose_on = config.far_loose_gate > 0 and not math.isinf(reach)
    # no farther than the visible horizon: a flat-ground point beyond it lies past the earth's curve (a gimbal near
    # level put loose points 1e9 m out, and the tracker's k-d tree overflowed: the contract audit of 1 Dec 2026)
    east, north, ok = pixel_to_local(uv, camera, moved, max_range_m=horizon_distance_m(pose.height_m)
                                     if math.isinf(reach) or loose_on else reach)
    if not ok.any():
        return filled
    if loose_on:
        dist = np.hypot(east[ok], north[ok])
        image_reach = reach if config.far_image_sigma_m <= 0 else min(
            reach, far_reach_m(config, pose.height_m, config.far_image_sigma_m))
        dets.loose, dets.unplaced = np.zeros(len(dets.lat), dtype=bool), np.zeros(len(dets.lat), dtype=bool)
        dets.loose[np.flatnonzero(miss)[ok]] = dist > image_reach
        dets.unplaced[np.flatnonzero(miss)[ok]] = dist > reach
    lat, lon = local_to_latlon(east[ok], north[ok], moved.lat, moved.lon)
    rows = np.flatnonzero(miss)[ok]
    dets.lat, dets.lon = dets.lat.copy(), dets.lon.copy()
    dets.lat[rows], dets.lon[rows] = lat, lon
    filled[rows] = True
    return filled


def measure_image_shift(state: TrackState, dets: FrameDetections, t: float) -> FloatArray | None:
    """In a frame with loose far points (and `far_shift_radius` on), measure the image's common motion before the
    association (`image_motion`): the shift from every track's expected box centre (its last one moved by the
    common motion since) to the frame's boxes (of its class, not set aside, from low_score) that the most tracks
    agree on, within far_shift_radius box sizes and agreeing within far_loose_gate sizes. All tracks vote, those
    followed on the ground too: the camera moves them alike. state.image_motion moves to time t by it (by its
    rate alone when too few agree, for up to image_max_age_s). Returns the shift (2,) px, or None when nothing was
    measured."""
    cfg = state.config
    act = state.active
    if cfg.far_shift_radius <= 0 or dets.loose is None or not dets.loose.any():
        return None
    di = np.flatnonzero(~dets.used & (dets.scores >= cfg.low_score))
    ti = np.flatnonzero(t - act["t_hit"] <= cfg.image_max_age_s)  # seen lately: still where expected
    shift = None
    if len(ti) and len(di):
        prev, boxes = act["box"][ti], dets.boxes[di]
        expected = 0.5 * (prev[:, :2] + prev[:, 2:]) + np.nan_to_num(
            state.image_motion.offset_at(t) - act["img_offset"][ti])
        shift = common_shift(expected, np.sqrt(np.prod(np.maximum(prev[:, 2:] - prev[:, :2], 1.0), axis=1)),
                             act["cls"][ti], 0.5 * (boxes[:, :2] + boxes[:, 2:]),
                             np.sqrt(np.prod(np.maximum(boxes[:, 2:] - boxes[:, :2], 1.0), axis=1)), dets.cls[di],
                             cfg.far_shift_radius, cfg.far_loose_gate, cfg.far_shift_min_tracks)
    state.image_motion.update(t, shift, cfg.far_shift_rate_gain, cfg.image_max_age_s)
    return shift


def place_far_tracks(state: TrackState, dets: FrameDetections) -> None:
    """Tracks that took a point followed in the image (dets.loose) but within the far reach (not dets.unplaced) have
    a position to report again (TrackOutput.loose False), as with a point the ground associates."""
    if dets.unplaced is None or dets.loose is None:
        return
    act = state.active
    k = np.flatnonzero(act["matched"] & (act["det_row"] >= 0))
    rows = act["det_row"][k]
    act.cols["loose"][k[dets.geo[rows] & dets.loose[rows] & ~dets.unplaced[rows]]] = False


def placed_rows(dets: FrameDetections) -> NDArray[np.bool_]:
    """(N,) bool: the rows with a ground point within the far reach (dets.geo, not dets.unplaced). Those followed in
    the image within that reach (`far_image_sigma_m`) still re-identify lost tracks, hand young tracks lost ids and
    are kept from starting a track beside one on the ground: a person behind trees on grass comes back in a place
    the ground still tells (docs/tracking.md, "Far views in the image")."""
    return dets.geo if dets.unplaced is None else dets.geo & ~dets.unplaced

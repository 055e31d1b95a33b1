"""Ground points for the boxes the pipeline left without one because they lie beyond its range.

The pipeline georeferences boxes up to its range limit (the memory map's half-window, 150 m by default): farther
boxes boost nothing and used to start no track, so a low view of the sea (17 m up at 1.6 deg, 60 m at 10 deg: two of
the eight real dev videos) gave an empty MOT file. The tracker places them itself, on flat ground and with the
pipeline's telemetry correction, as far as its own error model can: where the along-ray error of a pitch error of
`TrackerConfig.pitch_sigma_deg` (slant^2 / h * d_beta) stays within `far_reach_sigma_m`. Beyond that reach ground
points are too loose to associate by (a simulated view at 400-550 m: HOTA 3-14 on the ground against an image
tracker's 14-17). Such boxes get a loose point, marked `FrameDetections.loose`, out to the horizon: it starts a
track and moves it where it agrees, but they are associated in the image (`TrackerConfig.far_loose_gate`).
Measured on simulated far views (docs/tracking.md, "Far views").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agent.boxes import box_anchor_points
from agent.telemetry_correction import GroundCorrection
from agent.tracking.config import TrackerConfig
from agent.tracking.state import FrameDetections
from shared.geo import Camera, Pose, local_to_latlon, pixel_to_local

__all__ = ["fill_far_points", "far_reach_m"]


def far_reach_m(config: TrackerConfig, height_m: float) -> float:
    """The horizontal range (m) within which a ground point's along-ray error, slant^2 / h * d_beta for a pitch error
    d_beta = pitch_sigma_deg, is at most far_reach_sigma_m; 0 when off or the height is not positive; inf without a
    pitch error."""
    if config.far_reach_sigma_m <= 0 or not height_m > 0:
        return 0.0
    d_beta = math.radians(config.pitch_sigma_deg)
    if d_beta <= 0:
        return math.inf
    return math.sqrt(max(config.far_reach_sigma_m * height_m / d_beta - height_m * height_m, 0.0))


def fill_far_points(dets: FrameDetections, pose: Pose, camera: Camera, correction: GroundCorrection | None,
                    config: TrackerConfig) -> NDArray[np.bool_]:
    """Give the rows of dets without a ground point one within `far_reach_m` (flat ground, the anchor
    `config.far_anchor`, the pose moved by the pipeline's correction as its own points are), and with
    `far_loose_gate` a loose one beyond it (dets.loose); dets.lat / lon are replaced by copies (the FrameResult's
    arrays are not written). Returns (N,) bool: the rows filled."""
    filled = np.zeros(len(dets.lat), dtype=bool)
    miss = ~(np.isfinite(dets.lat) & np.isfinite(dets.lon))
    reach = far_reach_m(config, pose.height_m)
    if not miss.any() or reach <= 0:
        return filled
    moved = pose if correction is None else correction.moved(pose)
    uv = box_anchor_points(dets.boxes[miss], config.far_anchor, pose.pitch_deg)
    loose_on = config.far_loose_gate > 0 and not math.isinf(reach)
    east, north, ok = pixel_to_local(uv, camera, moved, max_range_m=None if math.isinf(reach) or loose_on else reach)
    if not ok.any():
        return filled
    if loose_on:
        dets.loose = np.zeros(len(dets.lat), dtype=bool)
        dets.loose[np.flatnonzero(miss)[ok]] = np.hypot(east[ok], north[ok]) > reach
    lat, lon = local_to_latlon(east[ok], north[ok], moved.lat, moved.lon)
    rows = np.flatnonzero(miss)[ok]
    dets.lat, dets.lon = dets.lat.copy(), dets.lon.copy()
    dets.lat[rows], dets.lon[rows] = lat, lon
    filled[rows] = True
    return filled

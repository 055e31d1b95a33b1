"""Ground-truth image boxes: project each object's 3-D box with the TRUE pose and decide its visibility.

All projections go through `shared.geo` (`latlon_to_local`, `local_to_pixel`); a corner at height z above
the ground is projected as a ground point seen from a camera z metres lower (an exact translation). Over a
terrain (`shared.terrain`) the objects stand on its surface and may hide behind it (`terrain_hidden`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from shared.geo import Camera, Pose, latlon_to_local, local_to_pixel
from shared.terrain import Terrain

#: An object is in view when at least this fraction of its box area lies inside the image.
MIN_INSIDE_FRACTION = 0.5
#: ... and its clipped box is at least this many pixels wide and high.
MIN_SIZE_PX = 4.0


@dataclass(frozen=True, slots=True)
class ProjectedBoxes:
    """Projected boxes of N objects in one frame.

    Attributes
    ----------
    boxes_xyxy : (N, 4) float64
        Unclipped pixel boxes (NaN where `valid` is False).
    clipped_xyxy : (N, 4) float64
        Boxes clipped to the image.
    ground_uv : (N, 2) float64
        Pixel of each object's ground centre (NaN if behind the camera / beyond the horizon).
    valid : (N,) bool
        Every corner lies in front of the camera and below the horizon.
    in_view : (N,) bool
        Valid, at least MIN_INSIDE_FRACTION of the box inside the image, and the clipped box at least
        MIN_SIZE_PX in both directions.
    """

    boxes_xyxy: np.ndarray
    clipped_xyxy: np.ndarray
    ground_uv: np.ndarray
    valid: np.ndarray
    in_view: np.ndarray


def box_corners_local(east_m: np.ndarray, north_m: np.ndarray, yaw_deg: np.ndarray,
                      width_m: float, depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Footprint corners of yawed rectangles: (N,) centres -> (N, 4) east, (N, 4) north metres."""
    yaw = np.radians(yaw_deg)[:, None]
    fwd_e, fwd_n = np.sin(yaw), np.cos(yaw)
    right_e, right_n = np.cos(yaw), -np.sin(yaw)
    sr = np.array([-0.5, 0.5, 0.5, -0.5])[None, :] * width_m
    sf = np.array([-0.5, -0.5, 0.5, 0.5])[None, :] * depth_m
    return (east_m[:, None] + sr * right_e + sf * fwd_e, north_m[:, None] + sr * right_n + sf * fwd_n)


def project_objects(lat: np.ndarray, lon: np.ndarray, yaw_deg: np.ndarray, box_m: tuple[float, float, float],
                    camera: Camera, pose: Pose, *, terrain: Terrain | None = None) -> ProjectedBoxes:
    """Project N objects' 3-D boxes into the image of `camera` at `pose`.

    Parameters
    ----------
    lat, lon : (N,) float
        Ground centres of the objects, degrees.
    yaw_deg : (N,) float
        Direction each object faces (its depth axis), clockwise from north.
    box_m : (width_m, depth_m, height_m)
        Box size in metres (height above the ground).
    camera, pose : shared.geo.Camera, shared.geo.Pose
        The TRUE pose.
    terrain : shared.terrain.Terrain, optional
        The ground the objects stand on (each footprint corner on its surface); None: flat.

    Returns
    -------
    ProjectedBoxes
    """
    n = len(lat)
    east, north = latlon_to_local(lat, lon, pose.lat, pose.lon)
    east, north = np.atleast_1d(east), np.atleast_1d(north)
    ce, cn = box_corners_local(east, north, np.asarray(yaw_deg, dtype=np.float64), box_m[0], box_m[1])
    uv_bot, ok_bot = local_to_pixel(ce.ravel(), cn.ravel(), camera, pose, terrain=terrain)
    top_height = pose.height_m - box_m[2]
    if top_height > 0.0:
        uv_top, ok_top = local_to_pixel(ce.ravel(), cn.ravel(), camera, replace(pose, height_m=top_height),
                                        terrain=terrain)
    else:  # the camera is below the box tops: nothing is reliably projectable
        uv_top, ok_top = np.full_like(uv_bot, np.nan), np.zeros_like(ok_bot)
    uv = np.concatenate([uv_bot.reshape(n, 4, 2), uv_top.reshape(n, 4, 2)], axis=1)
    valid = np.concatenate([ok_bot.reshape(n, 4), ok_top.reshape(n, 4)], axis=1).all(axis=1)
    ground_uv, ok_ground = local_to_pixel(east, north, camera, pose, terrain=terrain)
    valid &= ok_ground
    with np.errstate(invalid="ignore"):
        boxes = np.column_stack([uv[:, :, 0].min(axis=1), uv[:, :, 1].min(axis=1),
                                 uv[:, :, 0].max(axis=1), uv[:, :, 1].max(axis=1)]) if n else np.zeros((0, 4))
    boxes[~valid] = np.nan
    clipped = clip_boxes(boxes, camera.width, camera.height)
    with np.errstate(invalid="ignore"):
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        cw = clipped[:, 2] - clipped[:, 0]
        ch = clipped[:, 3] - clipped[:, 1]
        in_view = valid & (cw >= MIN_SIZE_PX) & (ch >= MIN_SIZE_PX) & (cw * ch >= MIN_INSIDE_FRACTION * area)
    return ProjectedBoxes(boxes, clipped, ground_uv, valid, in_view)


def terrain_hidden(lat: np.ndarray, lon: np.ndarray, centre_height_m: float, pose: Pose,
                   terrain: Terrain) -> np.ndarray:
    """(N,) bool: the line of sight from the camera to each object's centre (centre_height_m above the ground
    at lat, lon degrees) meets the terrain before it (a hill in between). Objects off the DEM count as hidden."""
    east, north = (np.atleast_1d(a) for a in latlon_to_local(lat, lon, pose.lat, pose.lon))
    rel = np.column_stack([east, north, terrain.up_m(east, north, pose) + centre_height_m - pose.height_m])
    dist = np.linalg.norm(rel, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        e, n, up, valid = terrain.intersect_rays(rel / dist[:, None], pose)
        hit = np.sqrt(e * e + n * n + (up - pose.height_m) ** 2)
        return ~np.isfinite(dist) | (valid & (hit < dist - 0.05))


def clip_boxes(boxes_xyxy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 4) xyxy boxes clipped to [0, width] x [0, height] (NaN stays NaN)."""
    out = boxes_xyxy.copy()
    out[:, 0::2] = np.clip(out[:, 0::2], 0.0, float(width))
    out[:, 1::2] = np.clip(out[:, 1::2], 0.0, float(height))
    return out

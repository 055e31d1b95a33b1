"""The messages an agent publishes about itself (DESIGN.md section 4): its state (pose, camera, the footprint on the
ground) and its tracks (the confirmed ones with a ground position). Built by `agent.node.AgentNode` each publish
cycle, and by the in-process evaluations that stand in for agents (`sim.coop_eval`)."""

from __future__ import annotations

import math

from agent.tracking import TrackOutput
from shared.geo import Camera, GroundSurface, Pose, footprint_latlon
from shared.messages import CameraInfo, StateMessage, TrackItem, TracksMessage

__all__ = ["publishable_tracks", "state_message", "tracks_message"]

#: The longitude a footprint vertex past the antimeridian is held at (just inside it, on the UAV's side).
_EDGE_LON = 180.0 - 1e-7


def _this_side(lon: float, uav_lon: float) -> float:
    """A footprint vertex's longitude held on the UAV's side of the antimeridian (a vertex past it, wrapped to the
    other sign, at the line): the server fills the polygon vertex by vertex, and across the line it covered the
    rest of the world."""
    if abs(lon) > 90.0 and abs(uav_lon) > 90.0 and (lon < 0.0) != (uav_lon < 0.0):
        return math.copysign(_EDGE_LON, uav_lon)
    return min(max(lon, -_EDGE_LON), _EDGE_LON)


def state_message(uav: str, t: float, pose: Pose, camera: Camera, *, range_m: float,
                  footprint_points: int = 32, terrain: GroundSurface | None = None) -> StateMessage:
    """The state message of a UAV at time t (seconds) with its camera pose.

    The footprint is the image border cast on the ground up to ``range_m`` (the pipeline's
    georeferencing range), ``footprint_points`` vertices ``(lat, lon)``; heading is sent in [0, 360).
    terrain: the pipeline's terrain (`--dem`): the border is cast onto it (shared.geo.footprint_latlon).
    """
    polygon = footprint_latlon(camera, pose, max_range_m=range_m, samples_per_edge=footprint_points // 4,
                               terrain=terrain)
    return StateMessage(
        uav=uav, t=t, lat=pose.lat, lon=pose.lon, height_m=pose.height_m, pitch_deg=pose.pitch_deg,
        heading_deg=pose.heading_deg % 360.0,
        # past the antimeridian kept on the UAV's side (the server fills a polygon vertex by vertex: wrapped, one
        # straddling the line would cover the rest of the world; past 180 the message was refused)
        footprint=tuple((float(a), _this_side(float(b), pose.lon)) for a, b in polygon),
        camera=CameraInfo(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy,
                          cx=camera.cx, cy=camera.cy),
    )


def publishable_tracks(tracks: list[TrackOutput]) -> list[TrackOutput]:
    """The tracks an agent reports: confirmed (also while coasting) with a finite ground position that is not
    loose (a far track placed only beyond the tracker's reach, `TrackOutput.loose`)."""
    return [tr for tr in tracks if tr.confirmed and not tr.loose and math.isfinite(tr.lat) and math.isfinite(tr.lon)]


def tracks_message(uav: str, t: float, tracks: list[TrackOutput], class_names: dict[int, str]) -> TracksMessage:
    """A tracks message of the publishable tracks; scores (boosted, may exceed 1) are clipped to [0, 1]."""
    items = tuple(
        TrackItem(id=tr.id, cls=class_names.get(tr.cls, str(tr.cls)), lat=tr.lat, lon=tr.lon,
                  score=min(max(tr.score, 0.0), 1.0), vel_en=(tr.vel_en[0], tr.vel_en[1]))
        for tr in publishable_tracks(tracks)
    )
    return TracksMessage(uav=uav, t=t, tracks=items)

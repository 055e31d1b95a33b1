"""Frames of a dataset's video whose meta lacks a field (agent.dataset.iter_video_frames): the pose interpolated
between the others' samples, the aircraft's compass heading where the gimbal's is missing, the meta's own zoom.

A frame whose meta lacks only its pitch, heading or height lies between samples of its video that say where the
camera was, as they do for every frame at its time (`bridged_pose`). Far from those, a frame without the gimbal's
heading can take the aircraft's compass heading, turned by the median difference of the frames that have both
(`gimbal_less_compass`). A null meta stays without pose (DESIGN.md 6).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from agent.telemetry_clock import TelemetryTrack
from shared.geo import Pose
from shared.telemetry.seadronessee import compass_heading_of, is_flight_log_meta

__all__ = ["BRIDGE_MAX_S", "PARTIAL_META", "bridged_pose", "gimbal_less_compass", "meta_hfov", "plus"]

#: Reasons a frame's own meta gives no record though the frame may lie between others' samples (`bridged_pose`).
PARTIAL_META = frozenset({"no pitch", "no heading", "no height"})
#: Longest interval (s) between the samples either side across which such a frame is given the interpolated pose.
BRIDGE_MAX_S = 3.0


def bridged_pose(track: TelemetryTrack | None, t: float, reason: str | None) -> Pose | None:
    """The pose at time t interpolated between the video's samples, for a frame whose meta lacks one field (its
    problem's `reason` in `PARTIAL_META`), when samples lie on both sides at most BRIDGE_MAX_S apart; else None."""
    if track is None or reason not in PARTIAL_META or len(track.t) < 2:
        return None
    k = int(np.searchsorted(track.t, t))
    if k == 0 or k >= len(track.t) or track.t[k] - track.t[k - 1] > BRIDGE_MAX_S:
        return None
    lat, lon, height, heading, pitch = (float(v) for v in track.at(t)[0])
    return Pose(lat, lon, max(height, 0.1), min(max(pitch, 0.0), 90.0), heading, 0.0)


def plus(t: float | None, dt: float) -> float | None:
    """t + dt, None when t is."""
    return None if t is None else t + dt


def meta_hfov(meta: Mapping[str, Any] | None) -> float | None:
    """A meta's own field of view (``hfov_deg``, a zoom lens's frame as `uavmm detect` writes it, read in the
    gps_latitude layout only, as there), else None."""
    if not isinstance(meta, Mapping) or is_flight_log_meta(meta):
        return None
    value = meta.get("hfov_deg")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value < 180.0:
        return None
    return float(value)


def gimbal_less_compass(metas: Sequence[Mapping[str, Any] | None], headings: Sequence[float | None]) -> float | None:
    """The gimbal's heading less the aircraft's compass heading (degrees, the median of the differences taken the
    short way) over the frames that have both (`headings`: each frame's gimbal heading, None without), for frames
    that have only the compass and lie too far from the others' samples to be interpolated; None when none has
    both."""
    diffs = [((h - c + 180.0) % 360.0) - 180.0 for meta, h in zip(metas, headings, strict=True)
             if h is not None and (c := compass_heading_of(meta)) is not None]
    return float(np.median(diffs)) if diffs else None

"""The gimbal's turn rates as the tracker follows them from the frames' poses (agent.tracking.tracker)."""

from __future__ import annotations

import math

from shared.geo import Pose

__all__ = ["GimbalRates"]


class GimbalRates:
    """Signed heading and pitch rates (deg/s) from successive distinct poses, and a low-pass heading.

    Telemetry is often sample-and-hold at a lower rate than the frames, so a rate is the change between two
    distinct poses over the time between their stamps (the frames' times when the poses carry no usable clock),
    and it falls to 0 when no new pose came for max(0.25 s, two pose intervals): the gimbal holds still. The
    low-pass heading (time constant `heading_smoothing_s`) has its own rate, quiet under per-frame jitter.
    """

    def __init__(self) -> None:
        self._pose_ref: Pose | None = None
        self._t_pose_ref = 0.0
        self._t_frame_ref = 0.0
        self._pose_interval_s = 0.0
        self.heading_deg_s = 0.0
        self.pitch_deg_s = 0.0
        self._heading_lp: float | None = None
        self.lp_heading_deg_s = 0.0  # turn rate of the low-pass heading

    def update(self, pose: Pose, pose_t: float, t: float) -> None:
        """Take the frame's pose (stamped pose_t, the frame at t)."""
        ref = self._pose_ref
        if ref is None:
            self._pose_ref, self._t_pose_ref, self._t_frame_ref = pose, pose_t, t
            return
        if pose.heading_deg != ref.heading_deg or pose.pitch_deg != ref.pitch_deg:
            interval = pose_t - self._t_pose_ref
            if interval <= 1e-3:  # no usable pose clock: the frames' one
                interval = max(t - self._t_frame_ref, 1e-3)
            d_heading = (pose.heading_deg - ref.heading_deg + 180.0) % 360.0 - 180.0
            self.heading_deg_s = d_heading / interval
            self.pitch_deg_s = (pose.pitch_deg - ref.pitch_deg) / interval
            self._pose_interval_s = interval
            self._pose_ref, self._t_pose_ref, self._t_frame_ref = pose, pose_t, t
        elif t - self._t_frame_ref > max(0.25, 2.0 * self._pose_interval_s):
            self.heading_deg_s = self.pitch_deg_s = 0.0  # no new telemetry for a while: the gimbal holds still

    def smoothed_heading(self, heading_deg: float, dt: float, tau_s: float) -> float:
        """The low-pass heading after a frame dt seconds on (time constant tau_s; 0: none), degrees in [0, 360)."""
        prev = self._heading_lp
        if prev is None or tau_s <= 0:
            self._heading_lp = heading_deg
        else:
            a = 1.0 - math.exp(-max(dt, 0.0) / tau_s)
            step = a * ((heading_deg - prev + 180.0) % 360.0 - 180.0)
            self._heading_lp = (prev + step) % 360.0
            if dt > 0:
                self.lp_heading_deg_s = step / dt
        return self._heading_lp

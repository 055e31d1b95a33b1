"""View jumps: frames whose pose cannot place their boxes because the gimbal jumped and the telemetry shows the
jump smeared over several frames (`TrackerConfig.jump_rate_deg_s`); the tracker does not use them.
"""

from __future__ import annotations

from collections import deque

from agent.tracking.config import TrackerConfig

__all__ = ["ViewJumpGuard"]


class ViewJumpGuard:
    """Judges, frame by frame, whether the camera is in a view jump.

    A frame is in a jump when its pose turned faster than `TrackerConfig.jump_rate_deg_s` (heading or pitch: the
    change since the pose at least `jump_window_s` older, divided by the time between them, so per-frame jitter
    and sample-and-hold steps do not count as a turn), and so is every frame up to `jump_settle_s` after the last
    such one. A gimbal that jumps 60 deg between two frames shows in a 10 Hz log interpolated to the frames as a
    turn over ~6 frames, tens of degrees off the image: the boxes of the new view, placed on the ground with the
    old heading, took the old view's tracks (and their lost ids) where they landed.
    """

    def __init__(self) -> None:
        self._recent: deque[tuple[float, float, float]] = deque()  # (t, heading, pitch) of the last frames
        self._t_jump: float | None = None  # time of the last frame whose pose turned at a jump's rate
        #: Frames judged in a jump so far.
        self.frames = 0

    def in_jump(self, heading_deg: float, pitch_deg: float, t: float, config: TrackerConfig) -> bool:
        """Record the frame's pose (degrees) at time t (seconds, non-decreasing) and say whether the frame is in
        a view jump (always False with `config.jump_rate_deg_s` 0)."""
        if config.jump_rate_deg_s <= 0:
            return False
        recent = self._recent
        recent.append((t, heading_deg, pitch_deg))
        while len(recent) > 2 and recent[1][0] <= t - config.jump_window_s:
            recent.popleft()  # keep one pose at least jump_window_s old as the reference
        t_ref, heading_ref, pitch_ref = recent[0]
        turn = max(abs((heading_deg - heading_ref + 180.0) % 360.0 - 180.0), abs(pitch_deg - pitch_ref))
        if turn / max(t - t_ref, config.jump_window_s) > config.jump_rate_deg_s:
            self._t_jump = t
        jump = self._t_jump is not None and t - self._t_jump <= config.jump_settle_s
        self.frames += jump
        return jump

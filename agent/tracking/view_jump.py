"""View jumps: frames whose pose cannot place their boxes because the gimbal jumped and the telemetry shows the
jump smeared over several frames (`TrackerConfig.jump_rate_deg_s`); the tracker does not use them, unless the
pose places the tracks on the frame's boxes after all (`TrackerConfig.jump_agree_min`) or the image moved since
the last frame as the pose did (`TrackerConfig.jump_motion_min`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from agent.stage_report import StageReport
from agent.tracking.config import TrackerConfig
from agent.tracking.lifecycle import in_image
from agent.tracking.state import FrameDetections, TrackState
from shared.geo import Camera, GroundSurface, Pose, latlon_to_pixel, pixel_to_latlon

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
        #: The last frame with jump_motion_min confident boxes (`follows`): time, box centres and diagonals (N, 3),
        #: pose, terrain.
        self._last: tuple[float, NDArray, Pose, GroundSurface | None] | None = None
        #: Frames judged in a jump so far, and those of them used after all (`follows`, `agrees`).
        self.frames = 0
        self.followed = 0
        self.agreed = 0

    def usable(self, state: TrackState, dets: FrameDetections, pose: Pose, turn_deg: float, t: float,
               camera: Camera, terrain: GroundSurface | None = None) -> bool:
        """Whether the tracker may use the frame's boxes: it is not in a view jump (`in_jump`), or its pose places
        its view after all: the image moved since the last frame with boxes as the pose did (`follows`), or the
        pose turned by the telemetry's age (turn_deg, as the frame's points are) puts the tracks on its boxes
        (`agrees`)."""
        cfg = state.config
        motion = cfg.jump_motion_min > 0 and cfg.jump_rate_deg_s > 0
        centres = _centres(dets, cfg.match_score) if motion else None
        ok = not self.in_jump(pose.heading_deg, pose.pitch_deg, t, cfg)
        if not ok and centres is not None:
            ok = self.follows(centres, pose, t, camera, cfg, terrain)
        if not ok and cfg.jump_agree_min > 0:
            ok = self.agrees(state, dets, replace(pose, heading_deg=(pose.heading_deg + turn_deg) % 360.0), t, camera,
                             terrain)
        if centres is not None and len(centres) >= cfg.jump_motion_min:
            self._last = (t, centres, pose, terrain)  # a frame with fewer would leave the next one nothing to check
        return ok

    def report(self, config: TrackerConfig) -> StageReport:
        """What the guard did so far (agent.stage_report): the frames in view jumps it held back and those a
        stand-down used after all; stood down when the telemetry showed no jump (or the guard is off)."""
        if config.jump_rate_deg_s <= 0:
            return StageReport("view-jump guard", False, "off (jump_rate_deg_s 0)")
        if not self.frames:
            return StageReport("view-jump guard", False, "no view jump in the telemetry")
        used = self.followed + self.agreed
        why = f"{self.frames - used} frames in view jumps held back"
        if config.jump_motion_min > 0 or config.jump_agree_min > 0:
            why += (f", {used} used after all ({self.followed} moving as the pose did, {self.agreed} with the"
                    " tracks on their boxes)")
        return StageReport("view-jump guard", True, why)

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

    def follows(self, now: NDArray, pose: Pose, t: float, camera: Camera, config: TrackerConfig,
                terrain: GroundSurface | None = None) -> bool:
        """Whether a frame in a jump, its confident boxes now (`_centres`), moved in the image as its pose did
        (`TrackerConfig.jump_motion_min`): the confident boxes of the last frame with at least jump_motion_min of
        them (at most jump_agree_age_s before), put on the ground with that frame's pose and projected with this
        one's, fall (centre within jump_motion_tol of the two boxes' mean diagonal) on at least jump_motion_min of
        this frame's and jump_agree_frac of the fewer, and on no fewer than the boxes where they were (an image
        standing still) do. The test is differential: a pose that lags the view by a steady delay passes through
        a turn the log follows, and the frames that settle after a jump pass as soon as the pose and the image
        both hold still. A jump the telemetry smears fails: the image steady while the pose turns, or the image
        jumping while the pose barely moves."""
        last = self._last
        if config.jump_motion_min <= 0 or last is None or not 0.0 <= t - last[0] <= config.jump_agree_age_s:
            return False
        if len(now) < config.jump_motion_min:
            return False
        _, before, pose_before, terrain_before = last
        lat, lon, ok = pixel_to_latlon(before[:, :2], camera, pose_before, terrain=terrain_before)
        if ok.sum() < config.jump_motion_min:
            return False
        uv, seen = latlon_to_pixel(lat[ok], lon[ok], camera, pose, terrain=terrain)
        moved, before = np.column_stack([uv, before[ok, 2]])[seen], before[ok][seen]
        inside = (moved[:, 0] >= 0) & (moved[:, 0] <= camera.width) & (moved[:, 1] >= 0) \
            & (moved[:, 1] <= camera.height)
        moved, before = moved[inside], before[inside]
        if len(moved) < config.jump_motion_min:
            return False
        on = _on(moved, now, config.jump_motion_tol)
        follow = (on >= config.jump_motion_min and on >= config.jump_agree_frac * min(len(moved), len(now))
                  and on >= _on(before, now, config.jump_motion_tol))
        self.followed += follow
        return follow

    def agrees(self, state: TrackState, dets: FrameDetections, pose: Pose, t: float, camera: Camera,
               terrain: GroundSurface | None = None) -> bool:
        """Whether a frame in a jump places its view after all (`TrackerConfig.jump_agree_min`): the tracks its
        pose projects into the image (over `terrain` when given) lie on enough of its boxes scoring >= match_score
        (not image duplicates). A pose tens of degrees off puts the tracks hundreds of pixels from their
        objects; a pose the log follows through a turn puts them on them. The re-ID memory's tracks are moved on
        with their last velocity (on the tuning jump domains that agreed more often, and scored better, than the
        re-ID's damped prediction: HOTA +0.65 against +0.20 over the guard alone)."""
        cfg = state.config
        act = state.active
        if cfg.jump_agree_min <= 0 or state.origin is None:
            return False
        fresh = np.flatnonzero(t - act["t_hit"] <= cfg.jump_agree_age_s)
        lost = state.lost
        back = np.flatnonzero(~lost["claimed"] & (t - lost["t_hit"] <= cfg.jump_agree_lost_s))  # not on probation
        away = (t - lost["t_hit"][back])[:, None]
        pts = np.vstack([act["x"][fresh, :2], lost["pos"][back] + lost["vel"][back] * away])  # moved on linearly
        det = _confident(dets, cfg.match_score)
        if min(len(pts), len(det)) < cfg.jump_agree_min:
            return False
        uv, inside = in_image(state, pts, pose, camera, terrain)
        uv = uv[inside]
        if len(uv) < cfg.jump_agree_min:
            return False
        b = dets.boxes[det]
        m = 0.5 * np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
        on = ((uv[None, :, 0] >= (b[:, 0] - m)[:, None]) & (uv[None, :, 0] <= (b[:, 2] + m)[:, None])
              & (uv[None, :, 1] >= (b[:, 1] - m)[:, None]) & (uv[None, :, 1] <= (b[:, 3] + m)[:, None]))
        agree = _mutual(on) >= max(cfg.jump_agree_min, cfg.jump_agree_frac * min(len(uv), len(det)))
        self.agreed += agree
        return agree


def _confident(dets: FrameDetections, min_score: float) -> NDArray[np.intp]:
    """Rows of the frame's boxes scoring >= min_score that are not image duplicates set aside."""
    return np.flatnonzero(~dets.used & (dets.scores >= min_score))


def _mutual(on: NDArray[np.bool_]) -> int:
    """How many pairs an (A, B) "lies on" matrix supports, counted the way fewer are: the rows on some column or
    the columns on some row, whichever is less (a box of a crowd may find several)."""
    return min(int(on.any(axis=1).sum()), int(on.any(axis=0).sum()))


def _centres(dets: FrameDetections, min_score: float) -> NDArray:
    """(N, 3) centre x, y and diagonal (pixels) of the frame's confident boxes (`_confident`)."""
    b = dets.boxes[_confident(dets, min_score)].astype(np.float64)
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2,
                            np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])])


def _on(a: NDArray, b: NDArray, tol: float) -> int:
    """How many of two frames' boxes (rows: centre x, y, diagonal) lie on one of the other's, centres within tol
    of the two boxes' mean diagonal (`_mutual`)."""
    return _mutual(np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
                   <= tol * 0.5 * (a[:, None, 2] + b[None, :, 2]))

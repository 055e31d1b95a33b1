"""Video/telemetry clock offset, estimated from the detections themselves, and frames re-timed by it.

A drone's telemetry stamps can run ahead of or behind its video (0.3 s is common on real logs). While the
gimbal sweeps at 30-80 deg/s that puts 10-20 deg of heading error on every ground point. The offset d is
the one that makes the ground positions of the confident detections most consistent between nearby
frames when the telemetry is interpolated at frame time + d (the world is static or slow at the scale of
a fraction of a second; a wrong d moves the ground points of two frames apart whenever the turn rate
changed between them). It is searched within +-`search_s` (a grid, refined by a parabola) on a sliding window of
the past frames, updated only when the window turned enough to be informative, smoothed, bounded, and it falls back
to the configured latency until then. Interpolating at t + d needs the telemetry up to `search_s` after
each frame: files (`uavmm track`, evaluations) have it; a live feed would have to delay by that much.
Arrays in, arrays out: no I/O.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from agent.boxes import nms
from agent.dataset import Candidates, Dataset, Frame, PoseProblem, VideoTelemetry, iter_video_frames
from agent.telemetry_dequantize import describe_quanta
from shared.geo import Camera, GroundSurface, Pose, latlon_to_local, pixel_to_local

__all__ = ["ClockOffset", "ClockOffsetEstimator", "ClockOffsetSettings", "HeadingTrack", "retime_frames",
           "video_frames"]

log = logging.getLogger(__name__)


#: The two-pass estimate weighs windows within this many memory_s of a frame, frames this many at a time.
_TWO_PASS_REACH = 7.0
_TWO_PASS_CHUNK = 1024


@dataclass(frozen=True, slots=True)
class ClockOffsetSettings:
    """Settings of the clock-offset estimate.

    fallback_s: the offset used before (and instead of) an estimate, seconds: 0, the telemetry as stamped
    (an offset is applied only where it was measured; 0.05 s, the simulator's latency, was the default
    until real files showed it applied to every frame of flights it was never measured on).
    search_s: the estimate stays within +-search_s, seconds. coarse_step_s: step of the grid of offsets
    over +-search_s (the minimum is refined by a parabola through the best three). window_s: frames of this many past
    seconds are compared. lags_s: a frame is compared with the frames this many seconds earlier (the
    nearest one). update_every_s: how often the window is searched. min_rate_change_deg_s: a window is
    informative only when the interpolated turn rate differs by at least this much between some compared
    frames (a constant turn moves all frames alike: no information). min_points: confident detections a
    compared pair needs. trim_m: a point's distance to its nearest neighbour counts at most this much.
    min_contrast: the best cost must be below this fraction of the median over the grid. memory_s: the
    informative windows' cost curves (each divided by its median) are summed with this forgetting time
    constant, and the measurement is the minimum of the sum; min_windows: informative windows needed
    before the first measurement. smoothing_s: time constant of the exponential smoothing of the
    measurements; max_slew: the applied offset moves by at most this many seconds per update second (0:
    unlimited). min_score, max_points: detections at least this confident (the detector's score) take
    part, at most this many per frame.
    two_pass: files (`retime_frames`) are searched twice: the first pass collects every informative
    window's cost curve over the whole video, the second gives each frame the minimum of the curves
    weighted by exp(-|t - t_window| / memory_s), the windows after it included (a clip is re-timed from
    its first frame, not once the online estimate has caught up; smoothing_s and max_slew then do not
    apply). With fewer than min_windows informative windows in the video every frame keeps the
    fallback. False: the online (causal) estimate alone, as a live feed would have it.
    """

    fallback_s: float = 0.0
    search_s: float = 1.0
    coarse_step_s: float = 0.05
    window_s: float = 3.0
    lags_s: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8)
    update_every_s: float = 0.25
    min_rate_change_deg_s: float = 15.0
    min_points: int = 2
    trim_m: float = 3.0
    min_contrast: float = 0.95
    smoothing_s: float = 0.25
    memory_s: float = 10.0
    min_windows: int = 3
    max_slew: float = 0.1
    min_score: float = 0.5
    max_points: int = 16
    two_pass: bool = True

    def __post_init__(self) -> None:
        for name in ("search_s", "coarse_step_s", "window_s", "update_every_s", "trim_m", "memory_s"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise ValueError(f"clock offset {name} must be a finite number > 0, got {value!r}")
        if not math.isfinite(self.fallback_s) or abs(self.fallback_s) > self.search_s:
            raise ValueError(f"clock offset fallback_s must be within +-search_s ({self.search_s}), "
                             f"got {self.fallback_s!r}")
        if not self.lags_s or any(not math.isfinite(v) or v <= 0 for v in self.lags_s):
            raise ValueError(f"clock offset lags_s must be positive seconds, got {self.lags_s!r}")
        if not 0 < self.min_contrast <= 1:
            raise ValueError(f"clock offset min_contrast must be in (0, 1], got {self.min_contrast!r}")


@dataclass(frozen=True, slots=True)
class ClockOffset:
    """The clock offset applied to one frame: offset_s (telemetry interpolated at frame time + it);
    measured: a new measurement was taken at this frame; informative: the window used turned enough."""

    offset_s: float
    measured: bool = False
    informative: bool = False


class HeadingTrack:
    """The telemetry's gimbal heading and pitch against its own clock, for interpolation.

    stamps_s (M,) increasing seconds, heading_deg, pitch_deg (M,). `at(t)` returns (heading in [0, 360),
    pitch) interpolated linearly (heading unwrapped), held at the ends; `rate_at(t)` the heading rate
    (deg/s) of the segment containing t.
    """

    def __init__(self, stamps_s: NDArray, heading_deg: NDArray, pitch_deg: NDArray) -> None:
        t = np.asarray(stamps_s, dtype=np.float64)
        order = np.argsort(t, kind="stable")
        self.t = t[order]
        self.h = np.degrees(np.unwrap(np.radians(np.asarray(heading_deg, dtype=np.float64)[order])))
        self.p = np.asarray(pitch_deg, dtype=np.float64)[order]

    @classmethod
    def from_frames(cls, frames: Iterable[Frame]) -> HeadingTrack:
        """The distinct telemetry samples behind the frames' poses: the video's track on the frame clock
        (agent.telemetry_clock) when the frames carry it, else the frames' pose stamps (pose_t, else frame
        time)."""
        frames = list(frames)
        track = next((fr.track for fr in frames if fr.track is not None), None)
        if track is not None and len(track):
            return cls(track.t, track.column("heading_deg"), track.column("pitch_deg"))
        seen: dict[float, tuple[float, float]] = {}
        for fr in frames:
            if fr.pose is None:
                continue
            stamp = fr.pose_t if fr.pose_t is not None and math.isfinite(fr.pose_t) else fr.t
            seen.setdefault(round(stamp, 6), (fr.pose.heading_deg, fr.pose.pitch_deg))
        stamps = np.array(sorted(seen), dtype=np.float64)
        return cls(stamps, np.array([seen[s][0] for s in stamps]), np.array([seen[s][1] for s in stamps]))

    def __len__(self) -> int:
        return len(self.t)

    def heading_unwrapped(self, t: NDArray | float) -> NDArray:
        """Unwrapped heading (deg) at times t (any shape)."""
        return np.asarray(np.interp(t, self.t, self.h))

    def at(self, t: float) -> tuple[float, float]:
        """(heading in [0, 360), pitch) degrees at time t."""
        return float(np.interp(t, self.t, self.h)) % 360.0, float(np.interp(t, self.t, self.p))

    def rate_at(self, t: NDArray | float) -> NDArray:
        """Heading rate (deg/s) of the telemetry segment containing t (0 with fewer than 2 samples)."""
        if len(self.t) < 2:
            return np.zeros(np.shape(t))
        i = np.clip(np.searchsorted(self.t, t) - 1, 0, len(self.t) - 2)
        return (self.h[i + 1] - self.h[i]) / np.maximum(self.t[i + 1] - self.t[i], 1e-3)


def _rotate(rel: NDArray, delta_deg: NDArray) -> NDArray:
    """Rotate (..., N, 2) east/north points clockwise (a heading increase) by delta (..., N) degrees."""
    d = np.radians(delta_deg)
    c, s = np.cos(d), np.sin(d)
    return np.stack([rel[..., 0] * c + rel[..., 1] * s, -rel[..., 0] * s + rel[..., 1] * c], axis=-1)


class ClockOffsetEstimator:
    """Per-video state: a window of past frames' confident ground points and the smoothed offset.

    Feed frames in time order with `add` (ground points relative to the UAV as the raw telemetry put
    them, the UAV position in a fixed local frame, the raw heading and the frame time); `offset_at`
    returns the offset to apply to that frame, updating the estimate when due.
    """

    def __init__(self, track: HeadingTrack, settings: ClockOffsetSettings | None = None) -> None:
        self.settings = settings or ClockOffsetSettings()
        self.track = track
        self.offset_s = self.settings.fallback_s
        # (time, ground points minus the UAV, UAV position, raw heading, frame number)
        self._frames: deque[tuple[float, NDArray, NDArray, float, int]] = deque()
        self._added = 0
        # cost curve over the offset grid of each compared frame pair (earlier, later frame number): a pair
        # is searched once, not in every window that holds it (windows overlap 12-fold)
        self._pair_cost: dict[tuple[int, int], NDArray] = {}
        self._t_update: float | None = None
        self._t_measured: float | None = None
        self._grid = np.arange(-self.settings.search_s, self.settings.search_s + 1e-9, self.settings.coarse_step_s)
        self._acc = np.zeros(len(self._grid))
        self._n_informative = 0
        #: every informative window's (time, cost curve divided by its median), for the second pass
        self.windows: list[tuple[float, NDArray]] = []

    def add(self, t: float, rel_en: NDArray, uav_en: NDArray, heading_deg: float) -> None:
        """Remember one frame: rel_en (N, 2) ground points minus the UAV (m, raw telemetry), uav_en (2,)."""
        self._frames.append((t, np.asarray(rel_en, dtype=np.float64).reshape(-1, 2),
                             np.asarray(uav_en, dtype=np.float64).reshape(2), float(heading_deg), self._added))
        self._added += 1
        while self._frames and self._frames[0][0] < t - self.settings.window_s:
            self._frames.popleft()

    def offset_at(self, t: float) -> ClockOffset:
        """The smoothed offset for the frame at t (searching the window when due)."""
        s = self.settings
        if self._t_update is not None and t - self._t_update < s.update_every_s:
            return ClockOffset(self.offset_s)
        self._t_update = t
        found = self.measure()
        if found is None or not found[1]:
            return ClockOffset(self.offset_s, False, found is not None and found[1])
        curve, _ = found
        self.windows.append((t, curve))
        # accumulate the informative windows' normalised cost curves (memory_s), the argmin of the sum
        dt = 0.0 if self._t_measured is None else t - self._t_measured
        self._acc = self._acc * math.exp(-dt / s.memory_s) + curve
        self._n_informative += 1
        self._t_measured = t
        if self._n_informative < s.min_windows:
            return ClockOffset(self.offset_s, False, True)
        measured = _parabolic_argmin(self._grid, self._acc)
        a = 1.0 if s.smoothing_s <= 0 else 1.0 - math.exp(-max(dt, s.update_every_s) / s.smoothing_s)
        step = a * (measured - self.offset_s)
        if s.max_slew > 0:  # a wrong early measurement cannot throw the offset far before more evidence comes
            step = float(np.clip(step, -s.max_slew * s.update_every_s, s.max_slew * s.update_every_s))
        self.offset_s = float(np.clip(self.offset_s + step, -s.search_s, s.search_s))
        log.debug("t=%.3f clock offset measured %.3f s, applied %.3f s", t, measured, self.offset_s)
        return ClockOffset(self.offset_s, True, True)

    def smoothed_at(self, times: NDArray) -> NDArray | None:
        """The two-sided estimate at each time (s): the minimum (parabola-refined) of the informative
        windows' curves weighted by exp(-|t - t_window| / memory_s); None with fewer than min_windows."""
        if len(self.windows) < max(self.settings.min_windows, 1):
            return None
        t_w = np.array([w[0] for w in self.windows])
        curves = np.stack([w[1] for w in self.windows])  # (W, D)
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        reach = _TWO_PASS_REACH * self.settings.memory_s  # weights beyond are < 1e-3 of a window at the frame
        out = np.empty(len(times))
        for lo in range(0, len(times), _TWO_PASS_CHUNK):  # (chunk, W) weights: bounded memory on long flights
            t = times[lo:lo + _TWO_PASS_CHUNK]
            a, b = np.searchsorted(t_w, [t.min() - reach, t.max() + reach])
            if b <= a:  # no window near these frames: the nearest ones decide
                a, b = max(0, min(a, len(t_w) - 1)), max(1, min(a + 1, len(t_w)))
            weights = np.exp(-np.abs(t[:, None] - t_w[None, a:b]) / self.settings.memory_s)
            acc = weights @ curves[a:b]  # (chunk, D)
            out[lo:lo + len(t)] = [_parabolic_argmin(self._grid, row) for row in acc]
        return out

    def _pairs(self) -> list[tuple[int, int]]:
        s = self.settings
        times = np.array([f[0] for f in self._frames])
        pairs = []
        for j in range(len(times)):
            if len(self._frames[j][1]) < s.min_points:
                continue
            for lag in s.lags_s:
                k = int(np.argmin(np.abs(times - (times[j] - lag))))
                if k < j and abs(times[j] - times[k] - lag) <= 0.5 * lag and len(self._frames[k][1]) >= s.min_points:
                    pairs.append((k, j))
        return sorted(set(pairs))

    def measure(self) -> tuple[NDArray, bool] | None:
        """Search the window: (cost (D,) over the offset grid divided by its median, informative), None
        without enough points."""
        s = self.settings
        pairs = self._pairs()
        if not pairs or len(self.track) < 2:
            return None
        frames = list(self._frames)
        t_frames = np.array([f[0] for f in frames])
        ks, js = np.array(pairs).T
        rate_change = float(np.abs(self.track.rate_at(t_frames[js] + self.offset_s)
                                   - self.track.rate_at(t_frames[ks] + self.offset_s)).max())
        if rate_change < s.min_rate_change_deg_s:
            return np.ones(len(self._grid)), False  # a steady (or no) turn says nothing: skip the search

        # offsets that send a frame beyond the telemetry's span would compare held (clamped) headings
        inside = (t_frames.min() + self._grid >= self.track.t[0]) & (t_frames.max() + self._grid <= self.track.t[-1])
        if inside.sum() < 3:
            return None
        first = frames[0][4]  # pairs with a frame that left the window are not needed again
        self._pair_cost = {key: curve for key, curve in self._pair_cost.items() if key[0] >= first}
        total = np.zeros(len(self._grid))
        for k, j in pairs:
            key = (frames[k][4], frames[j][4])
            curve = self._pair_cost.get(key)
            if curve is None:
                curve = self._pair_cost[key] = _pair_curve(self.track, self._grid, s.trim_m, frames[k], frames[j])
            total += curve
        c = np.ones(len(self._grid))
        c[inside] = total[inside]
        c[inside] /= max(float(np.median(c[inside])), 1e-12)
        c[~inside] = 1.0
        informative = rate_change >= s.min_rate_change_deg_s and float(c.min()) < s.min_contrast
        log.debug("clock offset window: best %.2f s, cost/median %.3f, rate change %.0f deg/s",
                  self._grid[int(np.argmin(c))], float(c.min()), rate_change)
        return c, bool(informative)


def _pair_curve(track: HeadingTrack, grid: NDArray, trim_m: float,
                earlier: tuple[float, NDArray, NDArray, float, int],
                later: tuple[float, NDArray, NDArray, float, int]) -> NDArray:
    """Sum over the later frame's points of the squared distance (capped at trim_m) to the nearest point of
    the earlier frame, both turned about their UAV by the heading change each offset of the grid implies."""
    placed = []
    for t, rel, uav, h_raw, _ in (earlier, later):
        delta = (track.heading_unwrapped(t + grid) - h_raw + 180.0) % 360.0 - 180.0  # (D,)
        placed.append(_rotate(np.broadcast_to(rel, (len(grid), *rel.shape)), np.repeat(delta[:, None], len(rel), 1))
                      + uav)  # (D, N, 2)
    p, q = placed
    d = np.hypot(q[:, :, None, 0] - p[:, None, :, 0], q[:, :, None, 1] - p[:, None, :, 1])  # (D, Nq, Np)
    nearest = np.minimum(d.min(axis=2), trim_m)
    return np.einsum("dn,dn->d", nearest, nearest)


def _parabolic_argmin(grid: NDArray, values: NDArray) -> float:
    """The minimum of values over an evenly spaced grid, refined by a parabola through the best three."""
    i = int(np.argmin(values))
    if 0 < i < len(grid) - 1:
        left, mid, right = values[i - 1], values[i], values[i + 1]
        den = left - 2.0 * mid + right
        if den > 0:
            return float(grid[i] + 0.5 * (left - right) / den * (grid[1] - grid[0]))
    return float(grid[i])


def frame_points(frame: Frame, boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray,
                 settings: ClockOffsetSettings, terrain: GroundSurface | None = None) -> NDArray:
    """Ground points (N, 2) east/north metres relative to the point below the UAV, raw telemetry, of the
    frame's confident candidates (NMS'd, bottom-centre anchors, at most max_points); (0, 2) without pose.
    terrain: the rays meet it instead of flat ground (`--dem`)."""
    if frame.pose is None or not len(scores):
        return np.zeros((0, 2))
    keep = np.flatnonzero(np.asarray(scores) >= settings.min_score)
    if not len(keep):
        return np.zeros((0, 2))
    kept = nms(np.asarray(boxes_xyxy)[keep], np.asarray(scores)[keep], np.asarray(class_ids)[keep], 0.5, 0.0,
               settings.max_points)
    idx = keep[kept]
    b = np.asarray(boxes_xyxy, dtype=np.float64)[idx]
    uv = np.stack([(b[:, 0] + b[:, 2]) / 2.0, b[:, 3]], axis=1)
    e, n, valid = pixel_to_local(uv, frame.camera, frame.pose, terrain=terrain)
    return np.stack([e[valid], n[valid]], axis=1)


def retime_frames(frames: list[Frame], candidates: Callable[[Frame], tuple[NDArray, NDArray, NDArray]],
                  settings: ClockOffsetSettings | None = None, *,
                  windows_out: list[int] | None = None,
                  terrain_for: Callable[[Pose], GroundSurface | None] | None = None
                  ) -> list[tuple[Frame, ClockOffset | None]]:
    """The video's frames with poses re-timed by the online clock-offset estimate.

    frames: one video's frames in time order; candidates(frame) -> (boxes_xyxy (K, 4), scores (K,),
    class_ids (K,)) of the frame's detections. Each frame's offset comes from the frames before it (and the
    telemetry up to search_s after it) or, with settings.two_pass (the default), from the whole video's
    informative windows weighted by their distance in time; its pose gets the heading and pitch
    interpolated at t + offset (with the video's telemetry track, agent.telemetry_clock: the whole pose)
    and pose_t = t. Frames without pose are returned unchanged with None. windows_out: the number of
    informative windows found is appended (the estimate's evidence; below min_windows it stood down and
    every frame keeps fallback_s). terrain_for(pose): the terrain the detections' ground points lie on
    (DetectionPipeline.terrain_for with `--dem`); None: flat ground.
    """
    settings = settings or ClockOffsetSettings()
    track = HeadingTrack.from_frames(frames)
    est = ClockOffsetEstimator(track, settings)
    origin: tuple[float, float] | None = None
    online: list[ClockOffset | None] = []
    for fr in frames:
        if fr.pose is None or len(track) < 2:
            online.append(None)
            continue
        if origin is None:
            origin = (fr.pose.lat, fr.pose.lon)
        online.append(est.offset_at(fr.t))
        uav = np.array([float(v) for v in latlon_to_local(fr.pose.lat, fr.pose.lon, *origin)])
        terrain = None if terrain_for is None else terrain_for(fr.pose)
        est.add(fr.t, frame_points(fr, *candidates(fr), settings, terrain), uav, fr.pose.heading_deg)
    offsets = online
    if windows_out is not None:
        windows_out.append(len(est.windows))
    if settings.two_pass:
        posed = [i for i, off in enumerate(online) if off is not None]
        smoothed = est.smoothed_at(np.array([frames[i].t for i in posed])) if posed else None
        if smoothed is not None:
            lo, hi = -settings.search_s, settings.search_s
            offsets = list(online)
            for i, value in zip(posed, smoothed, strict=True):
                first = online[i]
                offsets[i] = ClockOffset(float(np.clip(value, lo, hi)), first is not None and first.measured, True)
            log.debug("clock offset (two passes over %d informative windows): %.3f .. %.3f s", len(est.windows),
                      float(smoothed.min()), float(smoothed.max()))
    out: list[tuple[Frame, ClockOffset | None]] = []
    for fr, off in zip(frames, offsets, strict=True):
        if off is None or fr.pose is None:
            out.append((fr, None))
            continue
        if fr.track is not None and len(fr.track):  # the whole pose at t + offset (positions too)
            lat, lon, height, heading, pitch = (float(v) for v in fr.track.at(fr.t + off.offset_s)[0])
            pose = Pose(lat, lon, max(height, 0.1), min(max(pitch, 0.0), 90.0), heading, fr.pose.roll_deg)
        else:
            heading, pitch = track.at(fr.t + off.offset_s)
            pose = Pose(fr.pose.lat, fr.pose.lon, fr.pose.height_m, min(max(pitch, 0.0), 90.0), heading,
                        fr.pose.roll_deg)
        out.append((replace(fr, pose=pose, pose_t=fr.t, pose_retimed=True), off))
    return out


def video_frames(dataset: Dataset, camera: Camera, video_id: int, candidates: Candidates,
                 settings: ClockOffsetSettings | None, *, problems: list[PoseProblem] | None = None,
                 dequantize: bool = False, at_frame_time: bool = True, report: VideoTelemetry | None = None,
                 terrain_for: Callable[[Pose], GroundSurface | None] | None = None
                 ) -> list[tuple[Frame, ClockOffset | None]]:
    """One video's frames (`iter_video_frames`: telemetry on the frame clock, unusable meta appended to
    problems, quantised GPS and altitude made continuous when dequantize, poses at the frames' times unless
    not at_frame_time), re-timed by the clock-offset estimate when settings are given (`retime_frames`; its
    detections: the candidates), else as they are, with None. report: filled as `iter_video_frames` does,
    with the clock offset's informative windows. terrain_for: as `retime_frames` takes it."""
    info = report if report is not None else VideoTelemetry()
    frames = list(iter_video_frames(dataset, camera, video_id, problems=problems, dequantize=dequantize,
                                    at_frame_time=at_frame_time, report=info))
    if info.quanta or info.holds:
        log.info("video %s: telemetry (%s) made continuous", video_id, describe_quanta(info.quanta, info.holds))
    if settings is None:
        return [(f, None) for f in frames]
    windows: list[int] = []
    out = retime_frames(frames, lambda f: candidates.get(f.image.id), settings, windows_out=windows,
                        terrain_for=terrain_for)
    info.offset_windows = windows[0] if windows else 0
    return out

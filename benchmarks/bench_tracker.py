"""Per-frame cost of the GPS tracker with 10 / 100 / 1000 tracks.

A synthetic scene: N people on a ground grid below a hovering UAV, each detected in every
frame (box, score, lat/lon with noise), walking slowly; the tracker is warmed up until every object
has a confirmed track, then one `GpsTracker.update` is timed per frame. Baselines measured in the
same run: `scipy.optimize.linear_sum_assignment` on an N x N cost matrix (the assignment alone) and
norfair's pixel-space tracker on the same boxes (up to 100 objects; it is pure Python).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from agent.frame_result import FrameResult
from agent.tracking import GpsTracker
from benchmarks.timing import median_time_s
from shared.geo import Camera, Pose, local_to_latlon

DESCRIPTION = ("GpsTracker.update ms/frame at 10/100/1000 tracks vs linear_sum_assignment and norfair; track "
               "lending's cost vs the tracker")

_CAMERA = Camera(width=3840, height=2160, fx=2985.0, fy=2985.0, cx=1920.0, cy=1080.0)
_POSE = Pose(lat=48.53, lon=9.06, height_m=200.0, pitch_deg=90.0, heading_deg=0.0)
_FPS = 30.0


class _Scene:
    """N walkers on an 8 m grid below the UAV (200 m, nadir); `frame()` advances 1/30 s.

    Boxes are a fixed linear map of the ground positions (5 px per metre), so that every object has
    its own box however many there are; the tracker does not check them against the geometry.
    """

    def __init__(self, n: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        side = math.ceil(math.sqrt(n))
        gx, gy = np.meshgrid(np.arange(side) - (side - 1) / 2, np.arange(side))
        self.east = 8.0 * gx.ravel()[:n]
        self.north = 8.0 * (gy.ravel()[:n] - (side - 1) / 2)
        angle = rng.uniform(0, 2 * np.pi, n)
        self.vel = 0.3 * np.column_stack([np.sin(angle), np.cos(angle)])
        self.rng = rng
        self.t = 1.7e9
        self.n = n

    def frame(self) -> tuple[FrameResult, float]:
        self.t += 1.0 / _FPS
        self.east += self.vel[:, 0] / _FPS
        self.north += self.vel[:, 1] / _FPS
        u, v = 1920.0 + 5.0 * self.east, 1080.0 - 5.0 * self.north
        boxes = np.column_stack([u - 10, v - 15, u + 10, v + 15]).astype(np.float32)
        noise = self.rng.normal(0, 0.3, (self.n, 2))
        lat, lon = local_to_latlon(self.east + noise[:, 0], self.north + noise[:, 1], _POSE.lat, _POSE.lon)
        scores = np.full(self.n, 0.9, np.float32)
        result = FrameResult(boxes, scores, scores.copy(), np.ones(self.n, np.int64), lat, lon, self.n, 0, self.n)
        return result, self.t


def _frames_per_call(n: int) -> int:
    return max(1, 2000 // max(n, 1))


def _tracker_ms(n: int) -> tuple[float, int]:
    scene = _Scene(n)
    tracker = GpsTracker(class_names={1: "person"})
    for _ in range(10):  # birth and confirmation
        result, t = scene.frame()
        tracker.update(result, _POSE, t, _CAMERA)
    confirmed = sum(tr.confirmed for tr in tracker.tracks)
    k = _frames_per_call(n)
    # Frames are made beforehand: only update() is timed (7 calls: warm-up, calibration, 5 samples).
    frames = iter([scene.frame() for _ in range(8 * k)])

    def step() -> None:
        for _ in range(k):
            result, t = next(frames)
            tracker.update(result, _POSE, t, _CAMERA)

    return 1000 * median_time_s(step, repeat=5, min_time_s=0.0) / k, confirmed


def _lending_ms(n: int) -> float:
    """`TrackLending.apply` ms/frame when every one of n confirmed tracks shares its global track with another UAV
    that reports it at 0.97 (each detection's score moves): a new joint/tracks message every 6 frames (5 Hz)."""
    from agent.track_lending import TrackLending
    from shared.messages import JointTrackItem, JointTracksMessage, TrackItem, TracksMessage

    scene = _Scene(n)
    tracker = GpsTracker(class_names={1: "person"})
    for _ in range(10):
        result, t = scene.frame()
        tracks = tracker.update(result, _POSE, t, _CAMERA)
    lending = TrackLending("uav1", 0.5)
    lending.reported(TracksMessage(uav="uav1", t=t, tracks=tuple(
        TrackItem(tr.id, "person", float(tr.lat), float(tr.lon), 0.9, (0.0, 0.0)) for tr in tracks)))
    k = _frames_per_call(n)
    frames = []
    for i in range(8 * k):
        result, t = scene.frame()
        frames.append((result, tracker.update(result, _POSE, t, _CAMERA), t, JointTracksMessage(t=t, tracks=tuple(
            JointTrackItem(gid=tr.id, cls="person", lat=float(tr.lat), lon=float(tr.lon), score=0.97, vel_en=(0.0, 0.0),
                           members=(("uav1", tr.id), ("uav2", tr.id))) for tr in tracks)) if i % 6 == 0 else None))
    it = iter(frames)
    joint = None

    def step() -> None:
        nonlocal joint
        for _ in range(k):
            result, tracks, t, msg = next(it)
            joint = msg or joint
            lending.apply(result, tracks, joint, t)

    return 1000 * median_time_s(step, repeat=5, min_time_s=0.0) / k


def _lsa_ms(n: int) -> float:
    cost = np.random.default_rng(1).random((n, n))
    return 1000 * median_time_s(lambda: linear_sum_assignment(cost), repeat=5)


def _norfair_ms(n: int) -> float | None:
    try:
        from norfair import Detection, Tracker
    except ImportError:
        return None
    scene = _Scene(n)
    tracker = Tracker(distance_function="iou", distance_threshold=0.7, hit_counter_max=30, initialization_delay=2)

    def detections(result: FrameResult) -> list:
        return [Detection(b.reshape(2, 2).astype(np.float64), scores=np.full(2, 0.9)) for b in result.boxes_xyxy]

    for _ in range(10):
        tracker.update(detections(scene.frame()[0]))
    k = _frames_per_call(n)
    frames = iter([detections(scene.frame()[0]) for _ in range(8 * k)])

    def step() -> None:
        for _ in range(k):
            tracker.update(next(frames))

    return 1000 * median_time_s(step, repeat=5, min_time_s=0.0) / k


def _descriptor_us_per_box(side_px: int, n_boxes: int = 100) -> float:
    """`hsv_histogram_descriptors` cost per box (us) on a 1920 x 1080 frame, boxes side_px x 2 side_px."""
    from agent.tracking.appearance import hsv_histogram_descriptors

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    x = rng.uniform(0, 1920 - side_px, n_boxes)
    y = rng.uniform(0, 1080 - 2 * side_px, n_boxes)
    boxes = np.column_stack([x, y, x + side_px, y + 2 * side_px])
    return 1e6 * median_time_s(lambda: hsv_histogram_descriptors(image, boxes), repeat=5) / n_boxes


def run(quick: bool = False) -> list[dict[str, Any]]:
    """Rows: tracker ms/frame per size, with the assignment and norfair baselines; the appearance
    extractor's cost per box."""
    rows: list[dict[str, Any]] = []
    for side in (16, 48, 128):
        rows.append({"case": f"hsv_histogram_descriptors, {side}x{2 * side} px boxes", "value":
                     _descriptor_us_per_box(side), "unit": "us/box"})
    for n in (10, 100) if quick else (10, 100, 1000):
        ms, confirmed = _tracker_ms(n)
        lsa = _lsa_ms(n)
        rows.append({"case": f"linear_sum_assignment {n}x{n}", "value": lsa, "unit": "ms/frame"})
        rows.append({"case": f"GpsTracker.update, {n} tracks ({confirmed} confirmed)", "value": ms,
                     "unit": "ms/frame", "baseline_name": "linear_sum_assignment", "ratio": ms / lsa})
        nf = _norfair_ms(n) if n <= 100 else None
        if nf is not None:  # the simple strong baseline of the same run, and ours against it (subject / baseline)
            rows.append({"case": f"norfair Tracker.update (IoU), {n} objects", "value": nf, "unit": "ms/frame"})
            rows.append({"case": f"GpsTracker.update, {n} tracks, against norfair", "value": ms, "unit": "ms/frame",
                         "baseline_name": "norfair Tracker.update", "ratio": ms / nf})
        if n <= 100:  # a partner's confidence lent to every track (agent.track_lending), against the tracker
            lent = _lending_ms(n)
            rows.append({"case": f"TrackLending.apply, {n} tracks all lent", "value": lent, "unit": "ms/frame",
                         "baseline_name": "GpsTracker.update", "ratio": lent / ms})
    return rows

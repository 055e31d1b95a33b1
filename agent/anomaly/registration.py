"""Frame-to-ground registration for the anomaly layer: telemetry homographies made consistent by image alignment.

Telemetry alone places a frame on the ground with a few pixels of jitter (GPS 0.3 m, heading 0.5 deg, pitch
0.3 deg, 10 Hz sample-and-hold): enough to smear objects of a few pixels across the layer and to read the
layer back beside them. `GroundRegistration` predicts each frame's ground homography from the previous one
and the image motion between them (OpenCV's ECC on a coarse level, started from the better of the telemetry's
relative motion and the previous frame's image motion), and pulls it a little towards the telemetry's each
frame (a complementary filter), so it follows the images from frame to frame and the telemetry over seconds.
On open water the image motion is that of the water's surface, which drifts with the waves: the filter also
estimates that drift (a velocity on the ground, from the telemetry's steady pull) and takes it out of the
prediction (an alpha-beta filter). While the view sweeps the ground fast the telemetry's placement is only as
good as its timing (a 10 Hz sample held for three frames, a latency): the pull is weighted down by the share
of the telemetry's error that its timing adds at that speed. Without a usable image alignment it falls back to
the telemetry.

Over a terrain (`--dem`) the registration stays on flat homographies, and the ground layer uses only its
difference to the telemetry's own homography, as a correction in the image applied to the cells projected on
the terrain (`agent.anomaly.terrain_view`). Both are homographies to well under a pixel: between consecutive
frames the UAV moves a few decimetres, so the relief's parallax is small, and the telemetry's errors are mostly
of attitude, which move every point of the image by one homography whatever its height. Measured on the `hills`
DEM (12 m of relief; 1080p, in pixels of the 640-wide working scale): the image motion between consecutive
frames departs from the best homography by 0.04-0.08 px RMS (at most 0.16-0.39 px; 0.13-0.24 px RMS over three
frames) at 8-15 m/s and 12-30 m above the take-off, and the telemetry's errors (GPS 0.3 m, heading 0.5 deg,
pitch 0.3 deg) as an image homography leave 0.013 px RMS (median over 20 poses; at most 0.31 px at a point),
against ECC's own alignment noise on its 320-pixel level. The drift estimate is then that of the ground, ~0.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose, ground_to_image_homography, latlon_to_local

#: Frame interval assumed when update() is not given the frame times (seconds).
DEFAULT_FRAME_S = 1.0 / 30.0
#: Interval between fresh telemetry samples assumed until one is measured (seconds; 10 Hz).
DEFAULT_TELEMETRY_S = 0.1


def _ncc(a: NDArray[np.uint8], b: NDArray[np.uint8], mask: NDArray[np.bool_]) -> float:
    """Normalised cross-correlation of two images over mask (ECC's own criterion); -1 with too few pixels."""
    x, y = a[mask].astype(np.float64), b[mask].astype(np.float64)
    if x.size < 16:
        return -1.0
    x -= x.mean()
    y -= y.mean()
    d = math.sqrt(float((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / d) if d > 0 else -1.0


class GroundRegistration:
    """Per frame: the (3, 3) homography from ground metres (east/north of a reference point fixed for the
    sequence) to full-resolution image pixels.

    Parameters
    ----------
    ecc_width : int
        Width of the coarse frames ECC aligns (pixels).
    pull : float
        Share of the gap to the telemetry's placement closed each frame (0.05: a time constant of ~20 frames).
    iterations : int
        ECC iterations.
    drift_gain : float, optional
        The alpha-beta filter's beta: share of the gap that feeds the drift velocity each frame (default
        pull ** 2 / (2 - pull), the critically damped choice for alpha = pull; 0 turns the drift estimate off).
    telemetry_noise_m : float
        Placement error of the telemetry while the view is still (metres): the pull and the drift are weighted
        by telemetry_noise_m^2 / (telemetry_noise_m^2 + (sweep speed x telemetry interval)^2), the share of the
        telemetry's error that is not its timing. The interval is measured online (time between fresh
        samples: a sample-and-hold stream repeats its pose). None: always the full pull.
    """

    def __init__(self, ecc_width: int = 320, pull: float = 0.05, iterations: int = 30,
                 drift_gain: float | None = None, telemetry_noise_m: float | None = 0.5) -> None:
        if not 0 < pull <= 1:
            raise ValueError(f"pull must be in (0, 1], got {pull!r}")
        beta = pull ** 2 / (2.0 - pull) if drift_gain is None else float(drift_gain)
        if not (math.isfinite(beta) and 0 <= beta < 1):
            raise ValueError(f"drift_gain must be in [0, 1), got {drift_gain!r}")
        if telemetry_noise_m is not None and not (math.isfinite(telemetry_noise_m) and telemetry_noise_m > 0):
            raise ValueError(f"telemetry_noise_m must be > 0 or None, got {telemetry_noise_m!r}")
        self.ecc_width, self.pull, self.iterations, self.drift_gain = int(ecc_width), float(pull), int(iterations), beta
        self.telemetry_noise_m = telemetry_noise_m
        self.failures = 0
        self.reset()

    def reset(self) -> None:
        """A new video."""
        self._ref: tuple[float, float] | None = None
        self._prev: tuple[NDArray[np.uint8], NDArray[np.float64], Camera] | None = None
        self._tel_prev = np.eye(3)
        self._motion_prev: NDArray[np.float64] | None = None  # previous frame's image motion (full-res pixels)
        self._t_prev: float | None = None
        #: Estimated drift of what the images align on (the water's surface), metres/second east, north.
        self.drift_mps = np.zeros(2)
        #: Measured interval between fresh telemetry samples (seconds).
        self.telemetry_interval_s = DEFAULT_TELEMETRY_S
        self._last_pose: Pose | None = None
        self._last_fresh_t: float | None = None
        self._placed: NDArray[np.float64] | None = None  # the previous frame's ground anchors (metres)

    def _telemetry(self, camera: Camera, pose: Pose) -> NDArray[np.float64]:
        if self._ref is None:
            self._ref = (pose.lat, pose.lon)
        east, north = latlon_to_local(pose.lat, pose.lon, *self._ref)
        shift = np.array([[1.0, 0.0, -float(east)], [0.0, 1.0, -float(north)], [0.0, 0.0, 1.0]])
        return ground_to_image_homography(camera, pose) @ shift  # reference metres -> pixels

    def to_pose_local(self, world_to_image: NDArray[np.float64], pose: Pose) -> NDArray[np.float64]:
        """The homography from metres east/north of the pose's own position to pixels."""
        assert self._ref is not None
        east, north = latlon_to_local(pose.lat, pose.lon, *self._ref)
        return world_to_image @ np.array([[1.0, 0.0, float(east)], [0.0, 1.0, float(north)], [0.0, 0.0, 1.0]])

    def update(self, frame_bgr: NDArray[np.uint8], camera: Camera, pose: Pose, row0: int,
               t: float | None = None) -> NDArray[np.float64]:
        """Register a frame: returns its reference-metres -> pixel homography.

        row0: first image row that sees the ground within range (the anchor points of the pull lie below it).
        t: the frame's time (seconds), for the drift; consecutive frames DEFAULT_FRAME_S apart when None.
        """
        k = min(1.0, self.ecc_width / frame_bgr.shape[1])
        size = (max(16, int(round(frame_bgr.shape[1] * k))), max(16, int(round(frame_bgr.shape[0] * k))))
        grey = np.asarray(cv2.cvtColor(cv2.resize(frame_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2GRAY),
                          dtype=np.uint8)
        dt = DEFAULT_FRAME_S
        if t is not None and self._t_prev is not None and t > self._t_prev:
            dt = min(t - self._t_prev, 0.2)
        self._t_prev = t if t is not None else self._t_prev
        if t is not None and pose != self._last_pose:  # a fresh telemetry sample
            if self._last_fresh_t is not None and t > self._last_fresh_t:
                self.telemetry_interval_s += 0.1 * (min(t - self._last_fresh_t, 1.0) - self.telemetry_interval_s)
            self._last_fresh_t = t
        self._last_pose = pose
        tel = self._telemetry(camera, pose)
        prev = self._prev
        g = tel
        motion = None
        # the same frame size: a zoom lens's new focal length (a new camera each frame, agent.field_of_view) is in
        # the telemetry homographies, and the image motion between two frames of it is a homography still
        if prev is not None and (prev[2].width, prev[2].height) == (camera.width, camera.height) \
                and row0 < camera.height - 2:
            prev_grey, prev_g, _ = prev
            s = np.diag([k, k, 1.0])
            mask = np.zeros_like(grey)
            mask[int(row0 * k):] = 255
            # previous-frame pixels -> current pixels: the telemetry of both frames, or the previous frame's own
            # image motion (a steady turn under 10 Hz sample-and-hold telemetry: its relative motion is 0, 0 and
            # then three frames' worth), whichever aligns the frames better
            h_tel = tel @ np.linalg.inv(self._tel_prev)
            start = self._best_start([h_tel] if self._motion_prev is None else [h_tel, self._motion_prev],
                                     grey, prev_grey, mask, s)
            warp = (s @ np.linalg.inv(start) @ np.linalg.inv(s)).astype(np.float32)  # current -> previous
            warp /= warp[2, 2]
            try:
                _, warp = cv2.findTransformECC(grey, prev_grey, warp, cv2.MOTION_HOMOGRAPHY,
                                               (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.iterations, 1e-5),
                                               mask, 3)
                h = np.linalg.inv(np.linalg.inv(s) @ warp.astype(np.float64) @ s)  # previous -> current pixels
                motion = h / h[2, 2]
                g = self._blend(motion @ prev_g, tel, camera, row0, dt)
            except cv2.error:
                self.failures += 1
                g = tel
        if motion is None:
            self._placed = None
        self._motion_prev = motion
        self._prev = (grey, g, camera)
        self._tel_prev = tel
        return g / g[2, 2]

    @staticmethod
    def _best_start(starts: list[NDArray[np.float64]], grey: NDArray[np.uint8], prev_grey: NDArray[np.uint8],
                    mask: NDArray[np.uint8], s: NDArray[np.float64]) -> NDArray[np.float64]:
        """The candidate image motion (previous -> current full-res pixels) under which the previous coarse frame
        matches the current one best (normalised cross-correlation below the cut)."""
        if len(starts) == 1:
            return starts[0]
        size = (grey.shape[1], grey.shape[0])
        best, best_score = starts[0], -2.0
        for h in starts:
            m = s @ h @ np.linalg.inv(s)  # coarse previous -> coarse current
            warped = np.asarray(cv2.warpPerspective(prev_grey, m, size, flags=cv2.INTER_LINEAR), dtype=np.uint8)
            seen = cv2.warpPerspective(np.full_like(prev_grey, 255), m, size, flags=cv2.INTER_NEAREST)
            score = _ncc(grey, warped, (mask > 0) & (seen > 0))
            if score > best_score:
                best, best_score = h, score
        return best

    def _blend(self, predicted: NDArray[np.float64], tel: NDArray[np.float64], camera: Camera, row0: int,
               dt: float = DEFAULT_FRAME_S) -> NDArray[np.float64]:
        """Move the predicted placement, shifted by the estimated drift, a share of `pull` towards the telemetry's
        on four ground anchor points; what is left of the gap feeds the drift (alpha-beta filter). The share is
        `pull` while the view is still and less while it sweeps the ground fast (`telemetry_noise_m`)."""
        top = min(max(row0 + 0.25 * (camera.height - row0), 0.0), camera.height - 1.0)
        px = np.array([[0.1 * camera.width, top], [0.9 * camera.width, top],
                       [0.9 * camera.width, camera.height - 1.0], [0.1 * camera.width, camera.height - 1.0]])
        ground_pred = cv2.perspectiveTransform(px[None], np.linalg.inv(predicted))[0]
        ground_tel = cv2.perspectiveTransform(px[None], np.linalg.inv(tel))[0]
        if not (np.isfinite(ground_pred).all() and np.isfinite(ground_tel).all()):
            self._placed = None
            return tel
        weight = 1.0
        if self.telemetry_noise_m is not None and self._placed is not None:
            # how fast the anchors sweep the ground, and the placement error the telemetry's timing adds at that
            sweep_mps = float(np.linalg.norm(ground_pred - self._placed, axis=1).mean()) / dt
            timing_m = sweep_mps * self.telemetry_interval_s
            weight = self.telemetry_noise_m ** 2 / (self.telemetry_noise_m ** 2 + timing_m ** 2)
        # the images follow the water: a point the previous frame placed is now dt * drift further on
        ground_pred = ground_pred + self.drift_mps * dt
        gap = ground_tel - ground_pred
        target = ground_pred + self.pull * weight * gap
        self.drift_mps = self.drift_mps + (self.drift_gain * weight / dt) * gap.mean(axis=0)
        self._placed = target
        g = cv2.getPerspectiveTransform(target.astype(np.float32), px.astype(np.float32)).astype(np.float64)
        if not np.isfinite(g).all() or math.isclose(float(np.linalg.det(g)), 0.0, abs_tol=1e-18):
            self._placed = None
            return tel
        return g

"""Frame-to-ground registration for the anomaly layer: telemetry homographies made consistent by image alignment.

Telemetry alone places a frame on the ground with a few pixels of jitter (GPS 0.3 m, heading 0.5 deg, pitch
0.3 deg, 10 Hz sample-and-hold): enough to smear objects of a few pixels across the layer and to read the
layer back beside them. `GroundRegistration` predicts each frame's ground homography from the previous one
and the image motion between them (telemetry's relative motion refined by OpenCV's ECC on a coarse level),
and pulls it a little towards the telemetry's each frame (a complementary filter), so it follows the images
from frame to frame and the telemetry over seconds. Without a usable image alignment it falls back to the
telemetry.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose, ground_to_image_homography, latlon_to_local


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
    """

    def __init__(self, ecc_width: int = 320, pull: float = 0.05, iterations: int = 30) -> None:
        if not 0 < pull <= 1:
            raise ValueError(f"pull must be in (0, 1], got {pull!r}")
        self.ecc_width, self.pull, self.iterations = int(ecc_width), float(pull), int(iterations)
        self.failures = 0
        self.reset()

    def reset(self) -> None:
        """A new video."""
        self._ref: tuple[float, float] | None = None
        self._prev: tuple[NDArray[np.uint8], NDArray[np.float64], Camera] | None = None
        self._tel_prev = np.eye(3)

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

    def update(self, frame_bgr: NDArray[np.uint8], camera: Camera, pose: Pose, row0: int) -> NDArray[np.float64]:
        """Register a frame: returns its reference-metres -> pixel homography.

        row0: first image row that sees the ground within range (the anchor points of the pull lie below it).
        """
        k = min(1.0, self.ecc_width / frame_bgr.shape[1])
        size = (max(16, int(round(frame_bgr.shape[1] * k))), max(16, int(round(frame_bgr.shape[0] * k))))
        grey = cv2.cvtColor(cv2.resize(frame_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2GRAY)
        tel = self._telemetry(camera, pose)
        prev = self._prev
        g = tel
        if prev is not None and prev[2] == camera and row0 < camera.height - 2:
            prev_grey, prev_g, _ = prev
            s = np.diag([k, k, 1.0])
            # previous-frame pixels -> current pixels, first from the telemetry of both frames
            h_tel = tel @ np.linalg.inv(self._tel_prev)
            warp = (s @ np.linalg.inv(h_tel) @ np.linalg.inv(s)).astype(np.float32)  # current -> previous
            warp /= warp[2, 2]
            mask = np.zeros_like(grey)
            mask[int(row0 * k):] = 255
            try:
                _, warp = cv2.findTransformECC(grey, prev_grey, warp, cv2.MOTION_HOMOGRAPHY,
                                               (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.iterations, 1e-5),
                                               mask, 3)
                h = np.linalg.inv(np.linalg.inv(s) @ warp.astype(np.float64) @ s)  # previous -> current pixels
                predicted = h @ prev_g
                g = self._blend(predicted, tel, camera, row0)
            except cv2.error:
                self.failures += 1
                g = tel
        self._prev = (grey, g, camera)
        self._tel_prev = tel
        return g / g[2, 2]

    def _blend(self, predicted: NDArray[np.float64], tel: NDArray[np.float64], camera: Camera, row0: int
               ) -> NDArray[np.float64]:
        """Move the predicted placement a `pull` share towards the telemetry's, on four ground anchor points."""
        top = min(max(row0 + 0.25 * (camera.height - row0), 0.0), camera.height - 1.0)
        px = np.array([[0.1 * camera.width, top], [0.9 * camera.width, top],
                       [0.9 * camera.width, camera.height - 1.0], [0.1 * camera.width, camera.height - 1.0]])
        ground_pred = cv2.perspectiveTransform(px[None], np.linalg.inv(predicted))[0]
        ground_tel = cv2.perspectiveTransform(px[None], np.linalg.inv(tel))[0]
        if not (np.isfinite(ground_pred).all() and np.isfinite(ground_tel).all()):
            return tel
        target = ground_pred + self.pull * (ground_tel - ground_pred)
        g = cv2.getPerspectiveTransform(target.astype(np.float32), px.astype(np.float32)).astype(np.float64)
        if not np.isfinite(g).all() or math.isclose(float(np.linalg.det(g)), 0.0, abs_tol=1e-18):
            return tel
        return g

"""Per-frame anomaly heatmaps: the interface every method implements, the classic methods and their registry.

A method turns one BGR frame into a float32 heatmap in [0, 1] at its working scale (the frame area-downscaled
to ``work_width`` pixels across): high where the frame looks unlike water/meadow. The classic methods are the
paper's baselines (Table III): frame differencing after ego-motion compensation, mean and median filter
residuals, and OpenCV's MOG2 background model; the learned one (`agent.anomaly.autoencoder`) registers here
too. `agent.anomaly.registry` looks methods up by name.
"""

from __future__ import annotations

import logging
import math
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

FloatImage = NDArray[np.float32]
#: Working width (pixels) of every method unless told otherwise: 1080p is area-downscaled by 3.
DEFAULT_WORK_WIDTH = 640
#: Robust z-score scale of the heat: heat = tanh(z / DEFAULT_Z_MAX) (normalise_robust).
DEFAULT_Z_MAX = 8.0


class AnomalyMethod(Protocol):
    """What every heatmap method offers.

    ``heatmap(frame_bgr, image_to_world=None)`` returns (h, w) float32 in [0, 1] for an (H, W, 3) uint8 BGR
    frame, where w = ``work_width`` (or W if the frame is narrower) and h = round(H * w / W): the frame's own
    aspect at the working scale. ``image_to_world`` is the frame's (3, 3) homography from full-resolution
    pixels to ground metres (east, north) about a point fixed for the sequence (from telemetry, see
    `agent.anomaly.detector`); methods that compare frames use it to undo the camera's motion, the others
    ignore it. ``reset()`` forgets the previous frames (a new video).
    """

    name: str
    work_width: int

    def heatmap(self, frame_bgr: NDArray[np.uint8], image_to_world: NDArray[np.float64] | None = None) -> FloatImage:
        ...

    def reset(self) -> None:
        ...


def work_size(width: int, height: int, work_width: int) -> tuple[int, int]:
    """(w, h) of the working image for a (width x height) frame: at most work_width across, aspect kept."""
    if width <= work_width:
        return width, height
    return work_width, max(1, int(round(height * work_width / width)))


def to_work(frame_bgr: NDArray[np.uint8], work_width: int) -> NDArray[np.uint8]:
    """The frame area-downscaled to the working size (a view of the frame when it is small already)."""
    if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
        raise ValueError(f"frame must be (H, W, 3) BGR, got shape {frame_bgr.shape}")
    w, h = work_size(frame_bgr.shape[1], frame_bgr.shape[0], work_width)
    if (w, h) == (frame_bgr.shape[1], frame_bgr.shape[0]):
        return frame_bgr
    return np.asarray(cv2.resize(frame_bgr, (w, h), interpolation=cv2.INTER_AREA), dtype=np.uint8)


def normalise_robust(residual: FloatImage, z_max: float = DEFAULT_Z_MAX, valid: NDArray[np.bool_] | None = None
                     ) -> FloatImage:
    """Map a residual image to [0, 1] by its robust z-score z = (r - median) / (1.4826 MAD): tanh(max(z, 0) / z_max).

    tanh, not a clip at z_max: the strongest responses keep their order (a clip tied every pixel above z_max at
    1, 1.3 % of a sea frame, so neither a ranking of the frame nor the ground layer could tell a swimmer from a
    whitecap there); below z_max / 2 it is within 8 % of the linear z / z_max.

    The median and MAD come from every 4th pixel of each 4th row (inside ``valid`` when given), so a frame
    costs ~0.5 ms at 640x360 and the scale is the same for every frame of a steady scene.
    """
    sample = residual[::4, ::4] if valid is None else residual[::4, ::4][valid[::4, ::4]]
    if sample.size == 0:
        return np.zeros_like(residual, dtype=np.float32)
    med = float(np.median(sample))
    mad = float(np.median(np.abs(sample - med))) * 1.4826
    scale = max(mad, 1e-3 * max(abs(med), 1.0), 1e-6) * z_max
    out = (residual - np.float32(med)) * np.float32(1.0 / scale)
    np.maximum(out, 0.0, out=out)
    np.tanh(out, out=out)
    if valid is not None:
        out[~valid] = 0.0
    return out.astype(np.float32, copy=False)


def _colour_residual(a: NDArray, b: NDArray) -> FloatImage:
    """Per-pixel max over the channels of |a - b| (uint8 or float inputs of equal shape) as float32."""
    diff = cv2.absdiff(a, b)
    if diff.ndim == 3:
        diff = diff.max(axis=2)
    return diff.astype(np.float32, copy=False)


# ---------------------------------------------------------------------------------------------------- classic

class FilterResidual:
    """Spatial anomaly: how much each pixel differs from its neighbourhood's mean or median (Table III's
    mean filter). ``kind`` "mean" (box filter) or "median"; ``kernel_px`` the filter's size at the working
    scale (odd), a few times the objects' size there."""

    def __init__(self, kind: str = "median", kernel_px: int = 9, work_width: int = DEFAULT_WORK_WIDTH,
                 blur_sigma_px: float = 1.0, z_max: float = DEFAULT_Z_MAX) -> None:
        if kind not in ("mean", "median"):
            raise ValueError(f"FilterResidual kind must be mean or median, got {kind!r}")
        if kernel_px < 3 or kernel_px % 2 == 0:
            raise ValueError(f"kernel_px must be an odd number >= 3, got {kernel_px!r}")
        self.name, self.kind, self.kernel_px = kind, kind, int(kernel_px)
        self.work_width, self.blur_sigma_px, self.z_max = int(work_width), float(blur_sigma_px), float(z_max)

    def heatmap(self, frame_bgr: NDArray[np.uint8], image_to_world: NDArray[np.float64] | None = None) -> FloatImage:
        small = to_work(frame_bgr, self.work_width)
        if self.kind == "median":
            # medianBlur takes uint8 for kernels > 5: the exact filter, ~2 ms at 640x360
            background = cv2.medianBlur(small, self.kernel_px)
        else:
            background = cv2.blur(small, (self.kernel_px, self.kernel_px))
        residual = _colour_residual(small, background)
        if self.blur_sigma_px > 0:
            residual = np.asarray(cv2.GaussianBlur(residual, (0, 0), self.blur_sigma_px), dtype=np.float32)
        return normalise_robust(residual, self.z_max)

    def reset(self) -> None:
        """Stateless: nothing to forget."""


class Mog2:
    """OpenCV's Gaussian-mixture background model (MOG2) on the working frames; its foreground probability
    (foreground 1, shadow 0.5) blurred. It assumes a still camera: on a moving UAV it flags the moving
    background, which is why the paper's GMM scores lowest."""

    name = "mog2"

    def __init__(self, work_width: int = DEFAULT_WORK_WIDTH, history: int = 60, var_threshold: float = 16.0,
                 blur_sigma_px: float = 2.0) -> None:
        self.work_width, self.history, self.var_threshold = int(work_width), int(history), float(var_threshold)
        self.blur_sigma_px = float(blur_sigma_px)
        self.reset()

    def reset(self) -> None:
        """A fresh background model."""
        self._model = cv2.createBackgroundSubtractorMOG2(history=self.history, varThreshold=self.var_threshold,
                                                         detectShadows=True)

    def heatmap(self, frame_bgr: NDArray[np.uint8], image_to_world: NDArray[np.float64] | None = None) -> FloatImage:
        small = to_work(frame_bgr, self.work_width)
        mask = self._model.apply(small)  # 0 background, 127 shadow, 255 foreground
        heat = mask.astype(np.float32) * np.float32(1.0 / 255.0)
        if self.blur_sigma_px > 0:
            heat = np.asarray(cv2.GaussianBlur(heat, (0, 0), self.blur_sigma_px), dtype=np.float32)
        return np.clip(heat, 0.0, 1.0)


class FrameDifference:
    """Temporal anomaly: |frame - previous frame warped onto it|, the previous frame registered by the
    ground homographies of the two frames' telemetry (``image_to_world``), refined by OpenCV's ECC on a
    coarse level; without telemetry ECC alone from the identity. Pixels the previous frame did not see
    score 0. ``register``: "telemetry+ecc" (default), "telemetry" or "ecc"."""

    name = "diff"
    REGISTRATIONS = ("telemetry+ecc", "telemetry", "ecc")

    def __init__(self, work_width: int = DEFAULT_WORK_WIDTH, register: str = "telemetry+ecc",
                 ecc_width: int = 160, ecc_iterations: int = 30, blur_sigma_px: float = 1.5,
                 z_max: float = DEFAULT_Z_MAX) -> None:
        if register not in self.REGISTRATIONS:
            raise ValueError(f"FrameDifference register must be one of {', '.join(self.REGISTRATIONS)}, "
                             f"got {register!r}")
        self.work_width, self.register, self.ecc_width = int(work_width), register, int(ecc_width)
        self.ecc_iterations, self.blur_sigma_px, self.z_max = int(ecc_iterations), float(blur_sigma_px), float(z_max)
        self.ecc_failures = 0
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame."""
        self._prev: NDArray[np.uint8] | None = None
        self._prev_g: NDArray[np.float64] | None = None

    def _homography(self, image_to_world: NDArray[np.float64] | None, prev_g: NDArray[np.float64] | None,
                    scale: float, prev_grey: NDArray[np.uint8], grey: NDArray[np.uint8]) -> NDArray[np.float64]:
        """Working-scale homography taking previous-frame pixels to current-frame pixels."""
        s = np.diag([scale, scale, 1.0])
        h = np.eye(3)
        if "telemetry" in self.register and image_to_world is not None and prev_g is not None:
            h = s @ np.linalg.solve(image_to_world, prev_g) @ np.linalg.inv(s)
            h /= h[2, 2]
        if "ecc" in self.register:
            h = self._refine(h, prev_grey, grey)
        return h

    def _refine(self, h: NDArray[np.float64], prev_grey: NDArray[np.uint8], grey: NDArray[np.uint8]
                ) -> NDArray[np.float64]:
        k = min(1.0, self.ecc_width / grey.shape[1])
        size = (max(8, int(round(grey.shape[1] * k))), max(8, int(round(grey.shape[0] * k))))
        a = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        b = cv2.resize(prev_grey, size, interpolation=cv2.INTER_AREA)
        s = np.diag([k, k, 1.0])
        # ECC's warp maps template (current) coordinates into the input (previous): the inverse of h
        warp = (s @ np.linalg.inv(h) @ np.linalg.inv(s)).astype(np.float32)
        warp /= warp[2, 2]
        try:  # the ignore: the cv2 stubs refuse inputMask None next to gaussFiltSize; OpenCV takes it (no mask)
            _, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_HOMOGRAPHY,  # type: ignore[call-overload]
                                           (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.ecc_iterations,
                                            1e-4), None, 3)
        except cv2.error:
            self.ecc_failures += 1
            return h
        refined = np.linalg.inv(np.linalg.inv(s) @ warp.astype(np.float64) @ s)
        return refined / refined[2, 2]

    def heatmap(self, frame_bgr: NDArray[np.uint8], image_to_world: NDArray[np.float64] | None = None) -> FloatImage:
        small = to_work(frame_bgr, self.work_width)
        scale = small.shape[1] / frame_bgr.shape[1]
        grey = np.asarray(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        prev, prev_g = self._prev, self._prev_g
        self._prev = small
        self._prev_g = None if image_to_world is None else np.asarray(image_to_world, dtype=np.float64)
        if prev is None or prev.shape != small.shape or (self.register == "telemetry" and
                                                          (image_to_world is None or prev_g is None)):
            return np.zeros(small.shape[:2], dtype=np.float32)
        prev_grey = np.asarray(cv2.cvtColor(prev, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        h = self._homography(image_to_world, prev_g, scale, prev_grey, grey)
        size = (small.shape[1], small.shape[0])
        warped = cv2.warpPerspective(prev, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        seen = cv2.warpPerspective(np.full(small.shape[:2], 255, np.uint8), h, size, flags=cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_CONSTANT)
        valid = cv2.erode(seen, np.ones((5, 5), np.uint8)) > 0
        residual = _colour_residual(small, warped)
        residual[~valid] = 0.0  # before blurring: the unseen border must not bleed into its neighbours
        if self.blur_sigma_px > 0:
            residual = np.asarray(cv2.GaussianBlur(residual, (0, 0), self.blur_sigma_px), dtype=np.float32)
        return normalise_robust(residual, self.z_max, valid)


def check_heatmap(heat: NDArray, frame_shape: tuple[int, ...]) -> None:
    """Raise ValueError unless heat is a finite float32 (h, w) map in [0, 1] with the frame's aspect."""
    if heat.dtype != np.float32 or heat.ndim != 2:
        raise ValueError(f"heatmap must be 2-D float32, got {heat.dtype} {heat.shape}")
    if not math.isclose(heat.shape[1] / frame_shape[1], heat.shape[0] / frame_shape[0], rel_tol=0.05, abs_tol=0.02):
        raise ValueError(f"heatmap {heat.shape} does not have the frame's aspect {frame_shape[:2]}")

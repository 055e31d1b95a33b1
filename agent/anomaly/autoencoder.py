"""The learned heatmap method: a small convolutional autoencoder run by onnxruntime; anomaly = reconstruction error.

The network (trained on rendered sea frames by `uavmm anomaly-train`, docs/anomaly.md) squeezes the working
frame through a bottleneck at 1/8 of its resolution and rebuilds it; water and meadow come back, small
objects it never learnt to draw do not. The trained model ships in this package (`DEFAULT_MODEL`), so the
method runs without PyTorch.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.anomaly.methods import DEFAULT_WORK_WIDTH, DEFAULT_Z_MAX, FloatImage, normalise_robust, to_work

log = logging.getLogger(__name__)

#: The shipped model (trained on rendered sea frames; `uavmm anomaly-train` writes a new one).
DEFAULT_MODEL = Path(__file__).with_name("sea_autoencoder.onnx")
#: The network's input and output sizes must be multiples of this (three stride-2 stages).
STRIDE = 8


class OnnxAutoencoder:
    """Reconstruction-error heatmaps from an ONNX autoencoder.

    The model takes ``(1, 3, h, w)`` float32 BGR in [0, 1] (h, w multiples of 8) and returns the same shape.
    The heat is the per-pixel colour error |x - x_hat| (max over channels), blurred and normalised by its
    robust z-score (`agent.anomaly.methods.normalise_robust`).

    Parameters
    ----------
    model : path, optional
        ONNX file (default: the shipped sea model). ValueError when it is missing or not an autoencoder.
    work_width : int
        Working width in pixels.
    threads : int
        onnxruntime intra-op threads.
    """

    name = "autoencoder"

    def __init__(self, model: str | Path | None = None, work_width: int = DEFAULT_WORK_WIDTH, threads: int = 2,
                 blur_sigma_px: float = 1.0, z_max: float = DEFAULT_Z_MAX) -> None:
        import onnxruntime as ort

        path = Path(model) if model is not None else DEFAULT_MODEL
        if not path.is_file():
            raise ValueError(f"autoencoder model {path} does not exist (train one with `uavmm anomaly-train`)")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ValueError(f"autoencoder model {path} cannot be loaded by onnxruntime: {exc}") from None
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1 or len(inputs[0].shape) != 4:
            raise ValueError(f"autoencoder model {path} must take one (1, 3, H, W) input and return an image")
        self._input = inputs[0].name
        self.model_path = path
        self.work_width, self.blur_sigma_px, self.z_max = int(work_width), float(blur_sigma_px), float(z_max)

    def reset(self) -> None:
        """Stateless: nothing to forget."""

    def reconstruct(self, small_bgr: NDArray[np.uint8]) -> NDArray[np.float32]:
        """The model's reconstruction of a working-size BGR frame: (h, w, 3) float32 in [0, 1]."""
        h, w = small_bgr.shape[:2]
        # a mirrored margin of one stride all round (the network's zero padding spoils the outermost pixels),
        # then up to multiples of the stride
        m = STRIDE
        ph, pw = (-(h + 2 * m)) % STRIDE, (-(w + 2 * m)) % STRIDE
        padded = cv2.copyMakeBorder(small_bgr, m, m + ph, m, m + pw, cv2.BORDER_REFLECT_101)
        x = np.ascontiguousarray(padded.transpose(2, 0, 1)[None], dtype=np.float32) * np.float32(1.0 / 255.0)
        y = self._session.run(None, {self._input: x})[0]
        if y.shape != x.shape:
            raise ValueError(f"autoencoder {self.model_path} returned {y.shape} for an input of {x.shape}")
        return np.ascontiguousarray(y[0, :, m:m + h, m:m + w].transpose(1, 2, 0))

    def heatmap(self, frame_bgr: NDArray[np.uint8], image_to_world: NDArray[np.float64] | None = None) -> FloatImage:
        small = to_work(frame_bgr, self.work_width)
        recon = self.reconstruct(small)
        err = np.abs(small.astype(np.float32) * np.float32(1.0 / 255.0) - recon).max(axis=2)
        if self.blur_sigma_px > 0:
            err = cv2.GaussianBlur(err, (0, 0), self.blur_sigma_px)
        return normalise_robust(err, self.z_max)

"""Letterbox: an image resized with its aspect ratio kept and padded to the network input, as ultralytics
does, and the inverse mapping of boxes back to the original pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PAD_VALUE", "LetterboxTransform", "letterbox"]

PAD_VALUE = 114  # ultralytics' letterbox grey


@dataclass(frozen=True, slots=True)
class LetterboxTransform:
    """How an image was placed in the network input: ``u_in = u * scale_x + pad_left``.

    Attributes
    ----------
    scale_x, scale_y : float
        Resized size over original size per axis (``new_w / width``, ``new_h / height``): the
        actual scales of the resized content, which differ from the nominal gain by rounding.
    pad_left, pad_top : int
        Pixels of padding before the content, in input pixels.
    width, height : int
        Original image size in pixels.
    """

    scale_x: float
    scale_y: float
    pad_left: int
    pad_top: int
    width: int
    height: int

    def unmap_boxes(self, boxes_xyxy: np.ndarray) -> np.ndarray:
        """Map (N, 4) float boxes from input pixels back to original pixels, clipped to the image.

        Subtracts the padding, divides by the per-axis scale and clips x to [0, width] and y to
        [0, height] (pixel-edge coordinates). Returns a new (N, 4) float32 array.
        """
        boxes = np.asarray(boxes_xyxy, dtype=np.float32)
        offset = np.array([self.pad_left, self.pad_top, self.pad_left, self.pad_top], np.float32)
        inv_scale = np.array(
            [1 / self.scale_x, 1 / self.scale_y, 1 / self.scale_x, 1 / self.scale_y], np.float32
        )
        out = (boxes - offset) * inv_scale
        upper = np.array([self.width, self.height, self.width, self.height], np.float32)
        return np.clip(out, 0.0, upper, out=out)


def letterbox(
    image: np.ndarray,
    new_shape: tuple[int, int],
    *,
    stride: int = 32,
    auto: bool = False,
    pad_value: int = PAD_VALUE,
) -> tuple[np.ndarray, LetterboxTransform]:
    """Resize keeping the aspect ratio and pad, as ultralytics' ``LetterBox`` (scale-up allowed).

    Parameters
    ----------
    image : np.ndarray
        (H, W, C) uint8 image.
    new_shape : (int, int)
        Target (height, width) in pixels.
    stride : int
        With ``auto``, the padded size is the smallest multiple of ``stride`` holding the content.
    auto : bool
        Minimal stride-aligned padding (rectangular inference, dynamic-shape models only) instead
        of padding to ``new_shape``.
    pad_value : int
        Grey level of the padding (114 as in ultralytics).

    Returns
    -------
    padded : np.ndarray
        (H', W', C) uint8, the content centred: the odd pixel of padding, if any, goes to the
        bottom/right (ultralytics' ``round(d -/+ 0.1)``).
    transform : LetterboxTransform
        The mapping, for :meth:`LetterboxTransform.unmap_boxes`.
    """
    height, width = image.shape[:2]
    gain = min(new_shape[0] / height, new_shape[1] / width)
    # at least one pixel, so that extreme aspect ratios (e.g. 1 x 5000) still resize
    new_w, new_h = max(int(round(width * gain)), 1), max(int(round(height * gain)), 1)
    dw, dh = new_shape[1] - new_w, new_shape[0] - new_h
    if auto:
        dw, dh = dw % stride, dh % stride
    left, right = int(round(dw / 2 - 0.1)), int(round(dw / 2 + 0.1))
    top, bottom = int(round(dh / 2 - 0.1)), int(round(dh / 2 + 0.1))
    resized = image if (new_w, new_h) == (width, height) else cv2.resize(
        image, (new_w, new_h), interpolation=cv2.INTER_LINEAR
    )
    padded = cv2.copyMakeBorder(
        resized, top, bottom, left, right, cv2.BORDER_CONSTANT, value=(pad_value,) * 3
    )
    transform = LetterboxTransform(
        scale_x=new_w / width, scale_y=new_h / height, pad_left=left, pad_top=top, width=width, height=height
    )
    return padded, transform

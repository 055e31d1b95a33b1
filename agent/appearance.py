"""Appearance descriptors of detection boxes for re-identification (colour histograms of the crop).

A cheap, model-free stand-in for a re-ID network (DeepSORT's CNN): the hue-saturation histogram of the
box crop in HSV, which separates clothing colours and is insensitive to brightness. The output feeds
`DetectionPipeline.process(..., embeddings=)` and so `GpsTracker` (docs/tracking.md, "Appearance").
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

#: Hue x saturation bins of `hsv_histogram_descriptors` (descriptor length = their product).
HUE_BINS, SAT_BINS = 8, 4


def hsv_histogram_descriptors(image_bgr: NDArray[np.uint8], boxes_xyxy: NDArray, *, hue_bins: int = HUE_BINS,
                              sat_bins: int = SAT_BINS, min_side_px: float = 4.0) -> NDArray[np.float32]:
    """Unit hue-saturation histograms of box crops.

    image_bgr: (H, W, 3) uint8 frame (OpenCV's BGR order); boxes_xyxy: (N, 4) pixels. The central 80 %
    of each box is used (the edges are mostly background). Dark and grey pixels (value < 32 or
    saturation < 24 of 255) carry no hue and are left out. Returns (N, hue_bins * sat_bins) float32
    rows of unit length; NaN rows for boxes smaller than min_side_px or without a coloured pixel.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    out = np.full((len(boxes), hue_bins * sat_bins), np.nan, np.float32)
    if not len(boxes):
        return out
    h, w = image_bgr.shape[:2]
    cx, cy = 0.5 * (boxes[:, 0] + boxes[:, 2]), 0.5 * (boxes[:, 1] + boxes[:, 3])
    hw, hh = 0.4 * (boxes[:, 2] - boxes[:, 0]), 0.4 * (boxes[:, 3] - boxes[:, 1])
    x0 = np.clip(np.floor(cx - hw), 0, w).astype(int)
    x1 = np.clip(np.ceil(cx + hw), 0, w).astype(int)
    y0 = np.clip(np.floor(cy - hh), 0, h).astype(int)
    y1 = np.clip(np.ceil(cy + hh), 0, h).astype(int)
    for i in range(len(boxes)):  # one small crop per box: cv2.calcHist is the cost
        if x1[i] - x0[i] < min_side_px * 0.8 or y1[i] - y0[i] < min_side_px * 0.8:
            continue
        hsv = cv2.cvtColor(np.ascontiguousarray(image_bgr[y0[i]:y1[i], x0[i]:x1[i]]), cv2.COLOR_BGR2HSV)
        mask = cv2.inRange(hsv, (0, 24, 32), (180, 255, 255))
        hist = cv2.calcHist([hsv], [0, 1], mask, [hue_bins, sat_bins], [0, 180, 0, 256]).reshape(-1)
        norm = float(np.linalg.norm(hist))
        if norm > 0:
            out[i] = hist / norm
    return out

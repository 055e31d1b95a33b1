"""Appearance for re-identification: colour descriptors of detection boxes, and how tracks compare and
remember them (cosine distance, a moving average of unit descriptors).

The descriptor is a cheap, model-free stand-in for a re-ID network (DeepSORT's CNN): the hue-saturation
histogram of the box crop in HSV, which separates clothing colours and is insensitive to brightness. It
feeds `DetectionPipeline.process(..., embeddings=)` and so `GpsTracker` (docs/tracking.md, "Appearance").
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.frame_result import FrameResult

__all__ = ["HUE_BINS", "SAT_BINS", "blend_descriptors", "cosine_distance", "descriptor_distance",
           "hsv_histogram_descriptors", "unit_rows", "with_image_descriptors"]

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------
# Describing boxes
# ---------------------------------------------------------------------------------------------

#: Hue x saturation bins of `hsv_histogram_descriptors` (descriptor length = their product).
HUE_BINS, SAT_BINS = 8, 4
#: Pixels with less saturation or value (0..255) carry no usable hue and are left out.
MIN_SATURATION, MIN_VALUE = 24, 32


def _circular_hue_weights(hue_bins: int) -> NDArray[np.float32]:
    """(180, hue_bins) share of each OpenCV hue value in each bin: linear between the two nearest bin
    centres ((k + 0.5) * 180 / hue_bins), wrapping around (hue 179 is next to hue 0)."""
    p = np.arange(180, dtype=np.float64) * hue_bins / 180.0 - 0.5
    k0 = np.floor(p)
    frac = p - k0
    k0 = k0.astype(np.int64) % hue_bins
    w = np.zeros((180, hue_bins), np.float32)
    w[np.arange(180), k0] += 1.0 - frac
    w[np.arange(180), (k0 + 1) % hue_bins] += frac
    return w


def hsv_histogram_descriptors(image_bgr: NDArray[np.uint8], boxes_xyxy: NDArray, *, hue_bins: int = HUE_BINS,
                              sat_bins: int = SAT_BINS, min_side_px: float = 4.0) -> NDArray[np.float32]:
    """Unit hue-saturation histograms of box crops.

    image_bgr: (H, W, 3) uint8 frame (OpenCV's BGR order); boxes_xyxy: (N, 4) pixels. The central 80 %
    of each box is used (the edges are mostly background). Dark and grey pixels (value < 32 or
    saturation < 24 of 255) carry no hue and are left out. Hue is circular (OpenCV: 0..180, red at both
    ends): each pixel is shared linearly between the two nearest hue bin centres, wrapping around, so a
    red at hue 1 and one at hue 178 land in the same bins and a hue on a bin edge does not flip bins with
    noise. Saturation uses hard bins. Returns (N, hue_bins * sat_bins) float32 rows of unit length
    (row-major hue x saturation); NaN rows for boxes smaller than min_side_px, outside the image or
    without a coloured pixel.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    n_bins = hue_bins * sat_bins
    out = np.full((len(boxes), n_bins), np.nan, np.float32)
    if not len(boxes):
        return out
    h, w = image_bgr.shape[:2]
    cx, cy = 0.5 * (boxes[:, 0] + boxes[:, 2]), 0.5 * (boxes[:, 1] + boxes[:, 3])
    hw, hh = 0.4 * (boxes[:, 2] - boxes[:, 0]), 0.4 * (boxes[:, 3] - boxes[:, 1])
    with np.errstate(invalid="ignore"):
        x0 = np.clip(np.floor(np.nan_to_num(cx - hw)), 0, w).astype(int)
        x1 = np.clip(np.ceil(np.nan_to_num(cx + hw)), 0, w).astype(int)
        y0 = np.clip(np.floor(np.nan_to_num(cy - hh)), 0, h).astype(int)
        y1 = np.clip(np.ceil(np.nan_to_num(cy + hh)), 0, h).astype(int)
    fold = _circular_hue_weights(hue_bins)  # (180, hue_bins): exact per-pixel soft assignment, by hue value
    for i in range(len(boxes)):  # one small crop per box: OpenCV's colour conversion and histogram are the cost
        if x1[i] - x0[i] < min_side_px * 0.8 or y1[i] - y0[i] < min_side_px * 0.8:
            continue
        hsv = cv2.cvtColor(np.ascontiguousarray(image_bgr[y0[i]:y1[i], x0[i]:x1[i]]), cv2.COLOR_BGR2HSV)
        mask = cv2.inRange(hsv, (0, MIN_SATURATION, MIN_VALUE), (180, 255, 255))
        fine = cv2.calcHist([hsv], [0, 1], mask, [180, sat_bins], [0, 180, 0, 256])  # (180, sat_bins)
        hist = (fold.T @ fine).reshape(-1)
        norm = float(np.linalg.norm(hist))
        if norm > 0:
            out[i] = hist / norm
    return out


def with_image_descriptors(result: FrameResult, image_bgr: NDArray[np.uint8] | None) -> FrameResult:
    """The pipeline's result with `hsv_histogram_descriptors` of its kept boxes from the frame image.

    Only the kept boxes (after NMS, at most `max_detections`) are described: the candidates before NMS are
    ten to a hundred times more. Descriptors that came with the candidates (pre_nms.json ``embedding``) win:
    only their NaN rows are filled, and only when they have the HSV descriptor's length (a descriptor of
    another kind is never mixed in). image_bgr None, or an empty result: the result unchanged.
    """
    if image_bgr is None or not len(result):
        return result
    have = result.embeddings
    n_dim = HUE_BINS * SAT_BINS
    if have is None:
        return dataclasses.replace(result, embeddings=hsv_histogram_descriptors(image_bgr, result.boxes_xyxy))
    missing = ~np.isfinite(have).all(axis=1)
    if not missing.any() or have.shape[1] != n_dim:
        return result
    filled = have.copy()
    filled[missing] = hsv_histogram_descriptors(image_bgr, result.boxes_xyxy[missing])
    return dataclasses.replace(result, embeddings=filled)


# ---------------------------------------------------------------------------------------------
# Comparing and remembering descriptors
# ---------------------------------------------------------------------------------------------

def unit_rows(emb: NDArray, n: int) -> FloatArray | None:
    """(n, D) descriptors scaled to unit length; rows that are not finite or zero become NaN (None when D = 0)."""
    e = np.asarray(emb, dtype=np.float64)
    # (0, D) stays (0, D): reshape(0, -1) cannot infer D (frames whose every box was removed)
    e = e.reshape(n, e.shape[-1] if e.ndim == 2 and n == 0 else -1)
    if not e.shape[1]:
        return None
    norm = np.linalg.norm(e, axis=1, keepdims=True)
    ok = np.isfinite(norm) & (norm > 1e-12)
    return np.where(ok, e / np.where(ok, norm, 1.0), np.nan)


def cosine_distance(a: FloatArray, b: FloatArray) -> FloatArray:
    """1 - cosine similarity of unit rows a (..., D) and b (..., D) (broadcast); NaN where either is NaN."""
    return 1.0 - np.einsum("...d,...d->...", a, b)


def descriptor_distance(track_emb: FloatArray, det_emb: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Cosine distance of paired rows and whether both have a descriptor (else the distance is 0)."""
    d = cosine_distance(track_emb, det_emb)
    known = np.isfinite(d)
    return np.where(known, d, 0.0), known


def blend_descriptors(old: FloatArray, new: FloatArray, past_weight: float) -> FloatArray:
    """Per-row moving average of unit descriptors, renormalised (either side NaN: the other one).

    old, new (..., D); past_weight: weight of old (`TrackerConfig.appearance_ema`).
    """
    a = past_weight
    old_ok = np.isfinite(old).all(axis=-1, keepdims=True)
    new_ok = np.isfinite(new).all(axis=-1, keepdims=True)
    mix = a * np.where(old_ok, old, 0.0) + (1.0 - a) * np.where(new_ok, new, 0.0)
    mix = np.where(old_ok & ~new_ok, old, np.where(~old_ok & new_ok, new, mix))
    norm = np.linalg.norm(mix, axis=-1, keepdims=True)
    return np.where(old_ok | new_ok, mix / np.maximum(norm, 1e-12), np.nan)

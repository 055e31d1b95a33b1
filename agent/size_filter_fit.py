"""Fit the distance-size filter from a COCO dataset with meta (`uavmm fit-size-filter`).

Ground-truth boxes are georeferenced with their frame's pose; each gives (depression, log metric size).
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from agent.boxes import box_anchor_points
from agent.dataset import Dataset, iter_video_frames
from agent.size_filter import SizeFilter, fit_band
from shared.geo import Camera, pixel_to_local


def box_geometry(boxes_xyxy: np.ndarray, camera: Camera, pose, anchor: str = "auto") -> tuple[np.ndarray, ...]:
    """(N, 4) boxes -> slant range (m), depression (deg), diagonal (px), each (N,); NaN without ground."""
    east, north, _ = pixel_to_local(box_anchor_points(boxes_xyxy, anchor, pose.pitch_deg), camera, pose)
    slant = np.sqrt(east**2 + north**2 + pose.height_m**2)
    depression = np.degrees(np.arcsin(pose.height_m / slant))
    diag = np.hypot(boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1])
    return slant, depression, diag


def fit_from_dataset(images_path: str | Path, camera_path: str | Path, *, k: float = 3.0,
                     anchor: str = "auto", min_samples: int = 20) -> tuple[SizeFilter, dict[str, dict[str, Any]]]:
    """Fit a SizeFilter from the dataset's annotations; returns it and a per-class report."""
    dataset = Dataset.load(images_path)
    camera = Camera.from_spec(camera_path)
    anns = dataset.coco.get("annotations")
    if not isinstance(anns, list) or not anns:
        raise ValueError(f"{images_path}: no 'annotations' to fit from")
    by_image: dict[int, list[dict]] = defaultdict(list)
    for i, a in enumerate(anns):
        if not isinstance(a, dict) or "image_id" not in a or "bbox" not in a or "category_id" not in a:
            raise ValueError(f"{images_path}: annotations[{i}] needs image_id, category_id and bbox")
        by_image[a["image_id"]].append(a)
    samples: dict[str, tuple[list[float], list[float]]] = defaultdict(lambda: ([], []))
    for video_id in dataset.videos:
        for frame in iter_video_frames(dataset, camera, video_id):
            if frame.pose is None or frame.image.id not in by_image:
                continue
            image_anns = by_image[frame.image.id]
            xywh = np.array([a["bbox"] for a in image_anns], dtype=np.float64)
            xyxy = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]])
            slant, dep, diag = box_geometry(xyxy, frame.camera, frame.pose, anchor)
            f = math.sqrt(frame.camera.fx * frame.camera.fy)
            log_size = np.log(np.maximum(diag, 1e-6) * slant / f)
            for a, d, y in zip(image_anns, dep, log_size, strict=True):
                name = dataset.categories.get(a["category_id"])
                if name is not None and np.isfinite(d) and np.isfinite(y):
                    samples[name][0].append(float(d))
                    samples[name][1].append(float(y))
    bands = {}
    report: dict[str, dict[str, Any]] = {}
    for name, (dep, y) in sorted(samples.items()):
        if len(y) < min_samples:
            report[name] = {"samples": len(y), "fitted": False}
            continue
        band = fit_band(dep, y, min_samples=min_samples)
        bands[name] = band
        lo, hi = band.bounds_m([30.0, 60.0, 90.0], k)
        report[name] = {
            "samples": len(y), "fitted": True,
            "median_size_m": round(float(np.exp(np.median(y))), 3),
            "band_m_at_30_60_90_deg": [f"{a:.2f}-{b:.2f}" for a, b in zip(lo, hi, strict=True)],
        }
    if not bands:
        raise ValueError(f"{images_path}: no class has {min_samples} georeferenced annotations to fit")
    return SizeFilter(bands, k), report

"""Fit the distance-size filter from a COCO dataset with meta (`uavmm fit-size-filter`).

Ground-truth boxes are georeferenced with their frame's pose; each gives (depression, log metric size). Over a
terrain (`--dem`) the range and depression are the camera's to the ray's first hit on the DEM, as in the pipeline.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Collection
from pathlib import Path
from typing import Any

import numpy as np

from agent.boxes import box_anchor_points
from agent.dataset import Dataset, iter_video_frames
from agent.dem import takeoff_terrain
from agent.size_filter import HELD_OUT_FOLDS, MIN_UNITS, SizeFilter, fit_class, slant_and_depression
from shared.geo import Camera, Pose, pixel_to_local
from shared.terrain import Terrain, pixel_to_terrain


def box_geometry(boxes_xyxy: np.ndarray, camera: Camera, pose: Pose, anchor: str = "auto", *,
                 terrain: Terrain | None = None) -> tuple[np.ndarray, ...]:
    """(N, 4) boxes -> slant range (m), depression (deg), diagonal (px), each (N,); NaN without ground.

    terrain: the anchors' rays meet it (their first hit, no range limit) instead of flat ground, and range and
    depression are to that point (`agent.size_filter.slant_and_depression`, as the pipeline's size filter takes
    them); a terrain without a take-off elevation counts heights from the DEM below the UAV (see
    `shared.terrain.Terrain`; `fit_from_dataset` gives each video its first pose's, as the pipeline does)."""
    uv = box_anchor_points(boxes_xyxy, anchor, pose.pitch_deg)
    if terrain is None:
        east, north, _ = pixel_to_local(uv, camera, pose)
        up = None
    else:
        east, north, up, _ = pixel_to_terrain(uv, camera, pose, terrain)
    slant, depression = slant_and_depression(east, north, up, pose)
    diag = np.hypot(boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1])
    return slant, depression, diag


def fit_from_dataset(images_path: str | Path, camera_path: str | Path, *, k: float = 3.0,
                     anchor: str = "auto", min_samples: int = 20, terrain: Terrain | None = None,
                     image_ids: Collection[int] | None = None, left_out: dict[str, int] | None = None,
                     ) -> tuple[SizeFilter, dict[str, dict[str, Any]]]:
    """Fit a SizeFilter from the dataset's annotations; returns it and a per-class report (the evidence of each
    class, `agent.size_filter.fit_class`). ValueError naming each class's reason when none could be fitted.

    Each class is fitted and checked on its own evidence: its objects are the annotations' track ids within a
    video, or where the file has none (SeaDronesSee's detection sets) the videos; a class in one video only, whose
    frames show two or more of it at once, in five parts of that video's time (`_time_parts`); a class with fewer than
    min_samples boxes or 2 objects gets no band (its report says why). Annotations marked ``iscrowd`` or
    ``ignore`` (regions, not one object's box) are not fitted on. left_out (when given) is filled with the boxes
    not fitted on: crowd_or_ignore_regions, frames_without_pose, without_ground_point.
    terrain: georeference the boxes on this DEM (`--dem`) instead of flat ground; without a take-off elevation
    each video takes the DEM's height under its first pose (`agent.dem.takeoff_terrain`, as the pipeline does).
    image_ids: fit on the annotations of these images only (`uavmm tune`'s held-out check keeps the held-out
    frames' ground truth out of its fit); the poses still come from every frame of their videos. The bands hold
    only the classes fitted: `uavmm tune` keeps its start filter's for the others, `uavmm fit-size-filter` writes
    the built-in prior of every built-in class it did not fit; a class a `--size-filter FILE` lacks passes
    unfiltered (the run's summary names it).
    """
    dataset = Dataset.load(images_path)
    camera = Camera.from_spec(camera_path)
    anns = dataset.coco.get("annotations")
    if not isinstance(anns, list) or not anns:
        raise ValueError(f"{images_path}: no 'annotations' to fit from")
    by_image: dict[int, list[dict]] = defaultdict(list)
    regions = 0
    for i, a in enumerate(anns):
        if not isinstance(a, dict) or "image_id" not in a or "bbox" not in a or "category_id" not in a:
            raise ValueError(f"{images_path}: annotations[{i}] needs image_id, category_id and bbox")
        if a.get("iscrowd") or a.get("ignore"):  # a crowd or an ignore region: no single object's size
            regions += 1
            continue
        by_image[a["image_id"]].append(a)
    samples: dict[str, tuple[list[float], list[float], list[str]]] = defaultdict(lambda: ([], [], []))
    untracked: dict[tuple[str, int], list[tuple[float, int, int]]] = defaultdict(list)  # (t, image, sample)
    no_ground = no_pose = 0
    for video_id in dataset.videos:
        video_terrain: Terrain | None = None
        for frame in iter_video_frames(dataset, camera, video_id):
            wanted = frame.image.id in by_image and (image_ids is None or frame.image.id in image_ids)
            if frame.pose is None:
                no_pose += len(by_image[frame.image.id]) if wanted else 0
                continue
            if terrain is not None and video_terrain is None:
                video_terrain = takeoff_terrain(terrain, frame.pose)
            if not wanted:
                continue
            image_anns = by_image[frame.image.id]
            xywh = np.array([a["bbox"] for a in image_anns], dtype=np.float64)
            xyxy = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]])
            slant, dep, diag = box_geometry(xyxy, frame.camera, frame.pose, anchor, terrain=video_terrain)
            f = math.sqrt(frame.camera.fx * frame.camera.fy)
            log_size = np.log(np.maximum(diag, 1e-6) * slant / f)
            for a, d, y in zip(image_anns, dep, log_size, strict=True):
                name = dataset.categories.get(a["category_id"])
                if name is None:
                    continue
                if not (np.isfinite(d) and np.isfinite(y)):
                    no_ground += 1
                    continue
                track = a.get("track_id")
                samples[name][0].append(float(d))
                samples[name][1].append(float(y))
                samples[name][2].append(f"{video_id}" if track is None else f"{video_id}/{track}")
                if track is None:
                    untracked[(name, video_id)].append((frame.t, frame.image.id, len(samples[name][2]) - 1))
    for (name, video_id), seen in untracked.items():
        if len(set(samples[name][2])) < MIN_UNITS:  # one video: parts of its time are the only held-out units
            _time_parts(samples[name][2], video_id, seen)
    bands = {}
    report: dict[str, dict[str, Any]] = {}
    for name, (dep_deg, log_sizes, units) in sorted(samples.items()):
        band, evidence = fit_class(dep_deg, log_sizes, units, k=k, min_samples=min_samples)
        kinds = {"tracks" if "/" in u else "parts of videos" if "@" in u else "videos" for u in units}
        unit = " and ".join(sorted(kinds))
        report[name] = {"fitted": band is not None, **evidence, "objects_are": unit}
        if band is None:
            continue
        bands[name] = band
        lo, hi = band.bounds_m([30.0, 60.0, 90.0], k)
        report[name].update({
            "median_size_m": round(float(np.exp(np.median(log_sizes))), 3),
            "band_m_at_30_60_90_deg": [f"{a:.2f}-{b:.2f}" if band.measured([d])[0] else "not measured"
                                       for a, b, d in zip(lo, hi, (30.0, 60.0, 90.0), strict=True)],
        })
    counts = {"crowd_or_ignore_regions": regions, "frames_without_pose": no_pose, "without_ground_point": no_ground}
    if left_out is not None:
        left_out.update(counts)
    if not bands:
        why = "; ".join(f"{n}: {r['why']}" for n, r in report.items()) or "no annotated box with a ground point"
        raise ValueError(f"{images_path}: no class could be fitted ({why}; boxes left out: {left_out_text(counts)})")
    return SizeFilter(bands, k), report


def _time_parts(units: list[str], video_id: int, seen: list[tuple[float, int, int]]) -> None:
    """The units of a class seen in one video only, without track ids: where a frame shows two or more of its boxes
    (so the video shows several objects of the class), HELD_OUT_FOLDS contiguous parts of its time ("VIDEO@PART"),
    each left out of the fit in turn (`agent.size_filter.fit_class`; a weaker check than whole videos, which see
    other objects: those are the units whenever there are several); else the video stays one unit (its boxes may
    all be one object's). Without this a single annotated video without track ids never fitted a band."""
    if max(Counter(image for _, image, _ in seen).values()) < 2:
        return
    times = np.array([t for t, _, _ in seen], dtype=np.float64)
    lo, span = float(times.min()), float(np.ptp(times))
    parts = np.zeros(len(times), np.int64) if span <= 0 else \
        np.minimum((HELD_OUT_FOLDS * (times - lo) / span).astype(np.int64), HELD_OUT_FOLDS - 1)
    for (_, _, at), part in zip(seen, parts, strict=True):
        units[at] = f"{video_id}@{part}"


def left_out_text(counts: dict[str, int]) -> str:
    """`fit_from_dataset`'s left_out counts in words, e.g. "3 crowd or ignore regions, 12 on frames without a pose"."""
    words = {"crowd_or_ignore_regions": "crowd or ignore regions",
             "frames_without_pose": "on frames without a pose (meta missing or unusable)",
             "without_ground_point": "without a ground point (at or above the horizon)"}
    return ", ".join(f"{v} {words.get(k, k)}" for k, v in counts.items() if v) or "none"

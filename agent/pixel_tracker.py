"""A tracker in the image alone: norfair on box corners with its Kalman filter, set up like SORT without appearance.

The evaluation's pixel-space baseline (`sim.track_eval`), and `uavmm track`'s fallback for a video none of whose
frames has a pose (no usable meta: the GPS tracker starts no track without a ground point, and such a video had an
empty MOT file; `agent.tracking_io.track_video`). norfair is an evaluation package installed with --no-deps
(requirements-nodeps.txt; `make setup` does): without it the fallback stands down with a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.tracking import TrackOutput

__all__ = ["NODEPS_INSTALL", "PixelBaselineConfig", "PixelTracker", "import_baseline"]


@dataclass(frozen=True, slots=True)
class PixelBaselineConfig:
    """norfair in image space, set up like DeepSORT/SORT without appearance.

    det_score: detections below are not given to the tracker; iou_distance: norfair's IoU distance
    threshold (1 - IoU, 0.7 accepts IoU > 0.3); max_age_s: a track survives this long unmatched
    (norfair's hit_counter_max in frames at the video's rate); init_frames: hits before a track is
    reported (norfair initialization_delay + 1).
    """

    det_score: float = 0.4
    iou_distance: float = 0.7
    max_age_s: float = 1.0
    init_frames: int = 3


#: the evaluation-only packages pip cannot install with their declared dependencies (they pin numpy<2 or
#: would replace the headless OpenCV); the Makefile installs them with --no-deps from requirements-nodeps.txt
NODEPS_INSTALL = "pip install --no-deps trackeval==1.3.0 norfair==2.3.0 tabulate rich filterpy"


def import_baseline(module: str, what: str) -> Any:
    """Import an evaluation-only package, or raise ImportError saying in one line how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(f"{what} needs the {module.split('.')[0]} package, which plain `pip install` of uavmm "
                          f"does not bring (its declared dependencies would break the headless OpenCV): run "
                          f"`{NODEPS_INSTALL}` (or `make setup`, which does)") from None


class PixelTracker:
    """norfair's Tracker on box corners with its Kalman filter, one instance per video.

    `update(boxes_xyxy (K, 4), scores (K,), class_ids (K,))` returns the reported tracks of the frame
    as (ids (M,) int, boxes (M, 4), scores (M,)): tracks that are initialised and took a detection
    in this frame, with that detection's box (as our tracker reports).
    """

    def __init__(self, config: PixelBaselineConfig, fps: float) -> None:
        norfair = import_baseline("norfair", "the pixel-tracker baseline (norfair)")

        self.config = config
        self.last_rows = np.zeros(0, dtype=np.int64)
        # at low frame rates (2 fps) max_age_s is fewer frames than init_frames: norfair needs its delay below
        # the counter's maximum, so the age is floored to init_frames
        hits = max(1, round(config.max_age_s * fps), config.init_frames)
        self._tracker = norfair.Tracker(distance_function="iou", distance_threshold=config.iou_distance,
                                hit_counter_max=hits, initialization_delay=min(max(0, config.init_frames - 1),
                                                                               hits - 1))

    def update(self, boxes_xyxy: np.ndarray, scores: np.ndarray,
               class_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        from norfair import Detection

        keep = np.flatnonzero(scores >= self.config.det_score)
        dets = [Detection(boxes_xyxy[k].reshape(2, 2).astype(np.float64), scores=np.full(2, float(scores[k])),
                          label=int(class_ids[k]), data=int(k)) for k in keep]
        objects = self._tracker.update(dets)
        this_frame = {id(d) for d in dets}
        ids, rows = [], []
        for obj in objects:
            det = obj.last_detection
            if det is not None and id(det) in this_frame:
                ids.append(obj.id)
                rows.append(det.data)
        idx = np.asarray(rows, dtype=np.int64)
        self.last_rows = idx  # the rows of the frame's boxes the reported tracks took (their classes, ...)
        return np.asarray(ids, dtype=np.int64), boxes_xyxy[idx].reshape(-1, 4), scores[idx].reshape(-1)


class ImageOnlyTracks:
    """Tracks in the image of a video's frames while none has had a pose (`uavmm track`'s fallback, module
    docstring): fed frame by frame, they are the video's rows only when no frame of it had a pose. The pixel
    tracker is made at the second frame, its age in frames from the first two frames' interval; `unavailable`
    says why not when norfair is missing."""

    def __init__(self, config: PixelBaselineConfig | None = None) -> None:
        self.config = config or PixelBaselineConfig()
        self.rows: list[tuple[int, int, float, Any]] = []  # (frame_index, image_id, t, TrackOutput)
        self.unavailable: str | None = None
        self._tracker: PixelTracker | None = None
        self._first: tuple[int, int, float, Any] | None = None

    def add(self, frame_index: int, image_id: int, t: float, result: Any) -> None:
        """One frame without a pose: (frame index, image id, time s, its `FrameResult`)."""
        if self.unavailable is not None:
            return
        if self._tracker is None:
            if self._first is None:
                self._first = (frame_index, image_id, t, result)
                return
            dt = t - self._first[2]
            fps = min(max(1.0 / dt, 1.0), 60.0) if dt > 0 else 30.0
            try:
                self._tracker = PixelTracker(self.config, fps)
            except ImportError as exc:
                self.unavailable = str(exc)
                return
            self._feed(*self._first)
        self._feed(frame_index, image_id, t, result)

    def _feed(self, frame_index: int, image_id: int, t: float, result: Any) -> None:
        assert self._tracker is not None
        ids, boxes, scores = self._tracker.update(np.asarray(result.boxes_xyxy, dtype=np.float64),
                                                  np.asarray(result.scores, dtype=np.float64),
                                                  np.asarray(result.class_ids))
        classes = np.asarray(result.class_ids)[self._tracker.last_rows]
        raw = np.asarray(result.raw_scores)[self._tracker.last_rows]
        for tid, cls, box, score, quality in zip(ids.tolist(), classes.tolist(), boxes.tolist(), scores.tolist(),
                                                 raw.tolist(), strict=True):
            out = TrackOutput(int(tid), int(cls), tuple(box), math.nan, math.nan, (math.nan, math.nan), float(score),
                              True, True, 1, 0.0, False, float(quality), False)
            self.rows.append((frame_index, image_id, t, out))

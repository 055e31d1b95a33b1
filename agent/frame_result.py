"""One frame's detections after the pipeline: the value the pipeline produces, the joint detections extend
and the tracker consumes (boxes, boosted and raw scores, classes, ground points, descriptors).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.telemetry_correction import GroundCorrection

__all__ = ["FrameResult"]


@dataclass(frozen=True, slots=True)
class FrameResult:
    """Detections of one frame after NMS, highest score first.

    boxes_xyxy (K, 4) float32 pixels; scores (K,) float32 boosted confidences (may exceed 1);
    raw_scores (K,) the detector's; class_ids (K,) int; lat, lon (K,) float64 ground points (NaN
    where not georeferenced); counts: candidates in, dropped by the size filter, georeferenced;
    embeddings (K, D) float32 appearance descriptors of the kept boxes (NaN rows: none) or None;
    from_joint (K,) bool: True for detections the joint map added or promoted (agent.joint_detections),
    or None when the frame had no joint detections step (no joint layer); correction: the telemetry
    correction applied to the frame's ground points (agent.telemetry_correction.GroundCorrection), None
    when none ran (no pose, no memory map, or switched off); view_height_m (K,) over a terrain: the flat-ground
    height with the same along-ray error at each ground point (shared.terrain.effective_height_m; NaN: none),
    for error models written for flat ground; None over flat ground (the pose's height). alt_latlon (K, 2) over a
    terrain: a second ground point (lat, lon) where the box's ray passes an edge of the terrain near its anchor
    (PipelineConfig.edge_probe; NaN rows: none); None without a terrain or pose, or with edge_probe 0.
    """

    boxes_xyxy: NDArray[np.float32]
    scores: NDArray[np.float32]
    raw_scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    n_candidates: int
    n_size_filtered: int
    n_georeferenced: int
    embeddings: NDArray[np.float32] | None = None
    from_joint: NDArray[np.bool_] | None = None
    correction: GroundCorrection | None = None
    view_height_m: NDArray[np.float64] | None = None
    alt_latlon: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.scores)

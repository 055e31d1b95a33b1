"""Settings of the per-frame detection pipeline: memory map, boosting, size filter, NMS, and the joint map's
part (boosting with it and the detections it adds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from agent.boxes import ANCHORS
from agent.memory_map import MemoryMapConfig

__all__ = ["BOOST_MODES", "JOINT_MODES", "PipelineConfig"]

JOINT_MODES = ("max", "local", "joint", "mean")
BOOST_MODES = ("add", "logodds")


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Pipeline parameters (defaults: the best measured on the simulator; see docs/memory-map.md).

    boost_weight: c_hat = c + boost_weight * p (paper: 1).
    boost_mode: "add" (the paper: c + w p) or "logodds" (logit(c_hat) = logit(c) + w * logodds_scale * p:
        a Bayesian update that moves mid-confidence boxes most and keeps c_hat in (0, 1)).
    use_memory: False gives the single-frame baseline (same filter and NMS, no boosting).
    use_size_filter: apply the distance-size filter.
    anchor: where on a box its ground point is: "center" (the paper), "bottom" (feet of an upright
        object) or "auto" (from the bottom at grazing views to the centre at nadir).
    joint_mode: how a joint map from the fusion server combines with the local one for boosting:
        "max" (default), "local" (ignore it), "joint" (only it where fresh), "mean".
    max_range_m: boxes whose ground point is farther from the UAV are not georeferenced (default:
        half the memory window).
    nms_iou: IoU threshold of class-wise NMS; score_threshold: minimum output score;
    max_detections: per frame, highest scores first (COCO evaluates 100).
    joint_detections: with a joint layer, use_memory and joint_mode other than "local", add detections for the
        other UAVs' evidence in this view that no detection of the frame explains (agent.joint_detections;
        flagged in FrameResult.from_joint). joint_min_value: the others' evidence a peak needs;
        joint_gate_m: ground distance within which a kept box explains (or is promoted by) a peak (an
        angular gate around the peak's pixel applies too, agent.joint_detections.PEAK_GATE_RAD);
        joint_cover_uavs: UAVs assumed to cover a joint cell when this UAV's own evidence is taken out
        of the joint mean (1: use the joint value as is); joint_prior_score: the confidence a joint
        detection is credited with before the boost by the others' evidence (see joint_score; 0.5: a
        promoted weak box ranks with confident detections, as it was right in ~88 % of cases on `coop`);
        joint_synth_factor: multiplies the score of boxes synthesised where no real candidate exists
        (their pixel position carries the cross-UAV georeferencing error: on `coop` at 80 m they overlapped
        the object in 4 of ~1,200 cases; default 0 = only promote and carry real candidates).
        joint_carry_s: for this long after this UAV last saw an object the others' evidence points at (a
        promoted or confident box), a frame with no box for it reports the last one moved on by its image
        velocity (agent.joint_detections.JointCarry; 0 = off), scored the peak's times joint_carry_factor.
    """

    memory: MemoryMapConfig = field(default_factory=MemoryMapConfig)
    boost_weight: float = 1.0
    boost_mode: str = "logodds"
    logodds_scale: float = 4.0
    use_memory: bool = True
    use_size_filter: bool = True
    anchor: str = "auto"
    joint_mode: str = "max"
    max_range_m: float | None = None
    nms_iou: float = 0.5
    score_threshold: float = 0.001
    max_detections: int = 100
    joint_detections: bool = True
    joint_min_value: float = 0.3
    joint_gate_m: float = 3.0
    joint_cover_uavs: int = 2
    joint_prior_score: float = 0.5
    joint_synth_factor: float = 0.0
    joint_carry_s: float = 0.5
    joint_carry_factor: float = 0.8

    def __post_init__(self) -> None:
        if self.anchor not in ANCHORS:
            raise ValueError(f"anchor must be one of {', '.join(ANCHORS)}, got {self.anchor!r}")
        if self.boost_mode not in BOOST_MODES:
            raise ValueError(f"boost_mode must be one of {', '.join(BOOST_MODES)}, got {self.boost_mode!r}")
        if self.joint_mode not in JOINT_MODES:
            raise ValueError(f"joint_mode must be one of {', '.join(JOINT_MODES)}, got {self.joint_mode!r}")
        if not (0.0 < self.nms_iou <= 1.0):
            raise ValueError(f"nms_iou must be in (0, 1], got {self.nms_iou!r}")
        if not math.isfinite(self.boost_weight) or self.boost_weight < 0:
            raise ValueError(f"boost_weight must be >= 0, got {self.boost_weight!r}")
        if self.max_detections < 1:
            raise ValueError(f"max_detections must be >= 1, got {self.max_detections!r}")
        if not (0.0 < self.joint_min_value <= 1.0):
            raise ValueError(f"joint_min_value must be in (0, 1], got {self.joint_min_value!r}")
        if not (math.isfinite(self.joint_gate_m) and self.joint_gate_m >= 0):
            raise ValueError(f"joint_gate_m must be >= 0, got {self.joint_gate_m!r}")
        if self.joint_cover_uavs < 1:
            raise ValueError(f"joint_cover_uavs must be >= 1, got {self.joint_cover_uavs!r}")
        if not (0.0 < self.joint_prior_score < 1.0):
            raise ValueError(f"joint_prior_score must be in (0, 1), got {self.joint_prior_score!r}")
        if not (0.0 <= self.joint_synth_factor <= 1.0):
            raise ValueError(f"joint_synth_factor must be in [0, 1], got {self.joint_synth_factor!r}")
        if not (math.isfinite(self.joint_carry_s) and self.joint_carry_s >= 0):
            raise ValueError(f"joint_carry_s must be >= 0, got {self.joint_carry_s!r}")
        if not (0.0 <= self.joint_carry_factor <= 1.0):
            raise ValueError(f"joint_carry_factor must be in [0, 1], got {self.joint_carry_factor!r}")

    @property
    def range_limit_m(self) -> float:
        return self.memory.window_m / 2.0 if self.max_range_m is None else self.max_range_m

"""Boosting with the other UAVs' evidence where the joint registration puts it (issue 30, part 2).

Each UAV's map sits where its own telemetry puts the objects, so the same person lies metres apart in two
UAVs' maps. On `coop-glare` (seed 0, the weaker UAV's candidates scoring >= 0.5) the partner's own map holds
0.13 on average at this UAV's cell of a detection and 0.85 within 3 m of it: the maps are 4.6 m apart there
(the best common shift, 1.9 m west and 4.3 m south, against 1.7 and 4.0 m from the joint registration). Read
at this UAV's boxes, the joint map (the mean over the UAVs covering a cell) then holds this UAV's own
evidence, halved, and little of the partner's.

The joint registration (agent.joint_detections.JointRegistration) measures that offset in the image, from
the joint map's peaks and this UAV's confident detections. Here each candidate's partner evidence is read
where it lies: at the ground point of the candidate's anchor moved by the registered offset. There the
others' share of the joint mean (`others_evidence`) stands beside this UAV's own evidence at the candidate,
averaged over the UAVs covering the spot. Where a partner's footprint covers the registered spot and it
holds (next to) nothing there, the candidate is something that UAV does not see: `absent` marks it (the
pipeline lowers its log-odds by PipelineConfig.joint_absent_logit).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from agent.joint_detections import others_evidence
from agent.memory_map import JointLayer, MemoryMap

__all__ = ["registered_joint_evidence"]


def registered_joint_evidence(joint: JointLayer, memory: MemoryMap, cls: str, own: NDArray, gx: NDArray,
                              gy: NDArray, t: float, *, cover_uavs: int,
                              absent_value: float) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The joint evidence of N candidates of class `cls` read with their partner evidence where it lies.

    own: (N,) this UAV's evidence at the candidates' own cells (its memory map before this frame); gx, gy: (N,)
    global cells (finite) of the candidates' registered spots. Returns (evidence (N,) float32: (own + k o) /
    (1 + k), with o the others' mean evidence at the registered spot (`others_evidence` of the joint layer and
    this UAV's memory there) and k the other UAVs whose fresh footprints cover it (JointLayer.others_cover;
    without footprints, cover_uavs - 1 are assumed), and absent (N,) bool: a partner's fresh footprint covers
    the spot and o < absent_value; never without footprints).
    """
    gx = np.asarray(gx, dtype=np.float64)
    gy = np.asarray(gy, dtype=np.float64)
    own = np.asarray(own, dtype=np.float32)
    if not len(gx):
        return np.zeros(0, np.float32), np.zeros(0, bool)
    at_spot = joint.values_at(cls, gx, gy, t)
    own_there = memory.values_at(cls, gx, gy)
    ix = np.floor(gx).astype(np.int64)
    iy = np.floor(gy).astype(np.int64)
    x0, y0 = int(ix.min()), int(iy.min())
    cover = joint.others_cover(x0, y0, int(ix.max()) - x0 + 1, int(iy.max()) - y0 + 1, t)
    covering = None if cover is None else cover[iy - y0, ix - x0].astype(np.float32)
    others = others_evidence(at_spot, own_there, cover_uavs, covering)
    k = np.full(len(gx), np.float32(max(cover_uavs - 1, 0))) if covering is None else covering
    evidence = ((own + k * others) / (1.0 + k)).astype(np.float32)
    if covering is None:  # no partner's footprint known: nothing tells where a partner looks
        return evidence, np.zeros(len(gx), bool)
    return evidence, (covering > 0) & (others < np.float32(absent_value))

"""The agent's simulated source: one UAV of a simulator scenario, frame by frame, as a `FrameSource`
(`uavmm agent --sim SCENARIO`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np

from agent.sources import SourceFrame, pose_from_meta
from sim.simulator import Simulation

__all__ = ["SimSource"]

log = logging.getLogger(__name__)


class SimSource:
    """One UAV of a simulator scenario, frame by frame.

    Parameters
    ----------
    scenario : str or sim.scenarios.Scenario
        A `sim.scenarios` name (ValueError listing the valid ones otherwise) or a scenario object.
    seed : int
        Simulation seed: agents flying UAVs of one scenario must use the same seed to share a world.
    uav_index : int
        Which of the scenario's flights this agent flies, 0-based (``coop`` has two simultaneous
        UAVs; in the other scenarios each flight is a separate video over its own world).
    frames : int, optional
        Frames of the flight (default: the scenario's).
    noise_scale : float
        Telemetry noise multiplier.

    Candidates and pose come from the simulated detector and the NOISY telemetry (the meta a real
    UAV would log); the true pose is not used.
    """

    def __init__(self, scenario, *, seed: int = 0, uav_index: int = 0, frames: int | None = None,
                 noise_scale: float = 1.0) -> None:
        self.sim = Simulation(scenario, seed=seed, frames=frames, noise_scale=noise_scale)
        n = len(self.sim.videos)
        if isinstance(uav_index, bool) or not isinstance(uav_index, int) or not 0 <= uav_index < n:
            uavs = ", ".join(f"{i}={v.uav}" for i, v in enumerate(self.sim.videos))
            raise ValueError(f"uav_index must be in 0..{n - 1} for scenario {self.sim.scenario.name!r} ({uavs}), "
                             f"got {uav_index!r}")
        self.video = self.sim.videos[uav_index]
        self.name = f"sim:{self.sim.scenario.name}:{self.video.name}"
        self.camera = self.sim.camera
        self.class_names = {int(c["id"]): str(c["name"]) for c in self.sim.categories}
        self.fps = self.sim.scenario.fps
        self.problems = 0

    def frames(self) -> Iterator[SourceFrame]:
        """Frames of the chosen flight; the other flights of the scenario are simulated and skipped."""
        index = 0
        group_of = {v.id: v.group for v in self.sim.videos}
        for fs in self.sim.frames():
            if fs.video_id != self.video.id:
                if index and group_of[fs.video_id] != self.video.group:
                    break  # our flight is over; the flights of later groups follow
                continue
            pose, pose_t, problem = pose_from_meta(fs.meta, fs.frame_index)
            if problem is not None:
                self.problems += 1
                log.debug("frame %d: unusable meta: %s", fs.frame_index, problem)
            c = fs.candidates
            xywh = np.asarray(c.boxes_xywh, dtype=np.float32).reshape(-1, 4)
            boxes = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]]).astype(np.float32)
            yield SourceFrame(index, float(fs.t), pose, pose_t, boxes, np.asarray(c.scores, np.float32),
                              np.asarray(c.category_ids, np.int64), self.camera, c.embeddings)
            index += 1

    def close(self) -> None:
        """Nothing to release."""

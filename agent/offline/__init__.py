"""Offline processing of a recorded flight (`uavmm detect`): the agent's chain over a video with its telemetry,
no network, written as COCO, MOTChallenge, GeoJSON, KML and an annotated video.

`run` drives the frames, `outputs` builds and writes the files, `annotate` draws the video.
"""

from agent.offline.run import DetectOptions, prepare_out_dir, run_detect

__all__ = ["DetectOptions", "prepare_out_dir", "run_detect"]

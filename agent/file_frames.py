"""One video of a file made ready for the pipeline: telemetry on the frame clock, poses re-timed, and the
pipeline's adaptive stages shown the whole video before its first frame.

The frame drivers of files (`uavmm boost`, `uavmm track`, the evaluations) share this; a live feed cannot
look ahead and runs the same stages online.
"""

from __future__ import annotations

from agent.clock_offset import ClockOffset, video_frames
from agent.dataset import Candidates, Dataset, Frame, PoseProblem, VideoTelemetry
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera

__all__ = ["prepared_frames"]


def prepared_frames(dataset: Dataset, camera: Camera, video_id: int, candidates: Candidates, config: PipelineConfig,
                    pipe: DetectionPipeline | None = None, *, problems: list[PoseProblem] | None = None,
                    report: VideoTelemetry | None = None) -> list[tuple[Frame, ClockOffset | None]]:
    """The video's frames as `agent.clock_offset.video_frames` gives them with the config's telemetry settings
    (time zone, interpolation at frame time, dequantisation, clock offset), and `pipe` primed on them
    (`DetectionPipeline.prime`: the size filter's check and the score calibration's input check decide on
    the whole video). problems and report: as `video_frames` fills them."""
    frames = video_frames(dataset, camera, video_id, candidates, config.clock_offset_settings(), problems=problems,
                          dequantize=config.dequantize_telemetry, at_frame_time=config.telemetry_at_frame_time,
                          report=report)
    if pipe is not None:
        pipe.prime((frame.pose, frame.camera, *candidates.get(frame.image.id)) for frame, _ in frames)
    return frames

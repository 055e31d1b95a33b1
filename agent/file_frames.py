"""One video of a file made ready for the pipeline: telemetry on the frame clock, poses re-timed, and the
pipeline's adaptive stages shown the whole video before its first frame.

The frame drivers of files (`uavmm boost`, `uavmm track`, the evaluations) share this; a live feed cannot
look ahead and runs the same stages online.
"""

from __future__ import annotations

from agent.clock_offset import ClockOffset, ClockOffsetSettings, video_frames
from agent.dataset import Candidates, Dataset, Frame, PoseProblem, VideoTelemetry
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.stage_report import StageReport
from agent.view_cuts import ViewCutReport, place_view_cuts
from shared.geo import Camera

__all__ = ["prepared_frames", "telemetry_reports"]


def prepared_frames(dataset: Dataset, camera: Camera, video_id: int, candidates: Candidates, config: PipelineConfig,
                    pipe: DetectionPipeline | None = None, *, problems: list[PoseProblem] | None = None,
                    report: VideoTelemetry | None = None) -> list[tuple[Frame, ClockOffset | None]]:
    """The video's frames as `agent.clock_offset.video_frames` gives them with the config's telemetry settings
    (time zone, interpolation at frame time, dequantisation, clock offset), view jumps that sparse telemetry
    smears put where the detections jump (`agent.view_cuts`, with config.view_cuts), and `pipe` primed on them
    (`DetectionPipeline.prime`: the size filter's check and the score calibration's input check decide on
    the whole video). problems and report: as `video_frames` fills them."""
    info = report if report is not None else VideoTelemetry()
    # over a --dem terrain the clock-offset estimate puts the detections on it, as the pipeline does
    terrain_for = pipe.terrain_for if pipe is not None and config.terrain is not None else None
    frames = video_frames(dataset, camera, video_id, candidates, config.clock_offset_settings(), problems=problems,
                          dequantize=config.dequantize_telemetry, at_frame_time=config.telemetry_at_frame_time,
                          report=info, terrain_for=terrain_for)
    if config.view_cuts:
        cuts = ViewCutReport()
        frames = place_view_cuts(frames, lambda f: candidates.get(f.image.id), report=cuts)
        info.view_cuts = (cuts.intervals, cuts.cuts, cuts.too_few_frames)
    if pipe is not None:
        pipe.prime((frame.pose, frame.camera, *candidates.get(frame.image.id)) for frame, _ in frames)
    return frames


def telemetry_reports(info: VideoTelemetry, offset_settings: ClockOffsetSettings | None) -> list[StageReport]:
    """The decisions of one video's telemetry stages (agent.telemetry_clock, agent.telemetry_dequantize,
    agent.clock_offset) as stage reports."""
    clock = info.clock
    out = []
    if clock.frames:
        if clock.zone_offset_s:
            out.append(StageReport("time zone", True, f"{clock.zone_offset_s / 3600:+g} h removed from the stamps"))
        else:
            out.append(StageReport("time zone", False, clock.reason or "stamps and frames on one clock"))
        if info.at_frame_time:
            whole = ", stamps at whole seconds" if clock.whole_seconds else ""
            held = ", sample and hold" if clock.held_frames else ""
            out.append(StageReport("telemetry at frame time", clock.samples >= 2,
                                   f"interpolated between the telemetry's samples{whole}{held}"
                                   if clock.samples >= 2 else "one telemetry sample"))
        out.append(StageReport("dequantize", bool(info.quanta),
                               ", ".join(f"{k} {v:g}" for k, v in info.quanta.items()) or "no quantised coordinate"))
    if offset_settings is not None and clock.frames:
        need = offset_settings.min_windows
        acted = info.offset_windows >= need
        out.append(StageReport("clock offset", acted,
                               f"measured on {info.offset_windows} turning windows" if acted else
                               f"{info.offset_windows} of {need} turning windows needed: telemetry as stamped"))
    if info.view_cuts is not None and clock.frames:
        out.append(ViewCutReport(*info.view_cuts).stage_report())
    return out

"""One video of a file made ready for the pipeline: telemetry on the frame clock, poses re-timed, and the
pipeline's adaptive stages shown the whole video before its first frame.

The frame drivers of files (`uavmm boost`, `uavmm track`, the evaluations, and through `look_ahead` the two passes of
`uavmm detect`, agent.offline.two_pass) share this; a live feed cannot look ahead and runs the same stages online.
"""

from __future__ import annotations

from collections.abc import Callable

from numpy.typing import NDArray

from agent.clock_offset import ClockOffset, ClockOffsetSettings, retime_frames, video_frames
from agent.dataset import Candidates, Dataset, Frame, PoseProblem, VideoTelemetry
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.stage_report import StageReport
from agent.telemetry_dequantize import dequantize_report
from agent.view_cuts import ViewCutReport, place_view_cuts
from shared.geo import Camera

__all__ = ["look_ahead", "look_ahead_reports", "prepared_frames", "telemetry_reports"]


def prepared_frames(dataset: Dataset, camera: Camera, video_id: int, candidates: Candidates, config: PipelineConfig,
                    pipe: DetectionPipeline | None = None, *, problems: list[PoseProblem] | None = None,
                    report: VideoTelemetry | None = None) -> list[tuple[Frame, ClockOffset | None]]:
    """The video's frames as `agent.clock_offset.video_frames` gives them with the config's telemetry settings
    (time zone, interpolation at frame time, dequantisation), then `look_ahead` on them (clock offset, view cuts,
    `pipe` primed). problems and report: as `video_frames` fills them."""
    info = report if report is not None else VideoTelemetry()
    frames = [frame for frame, _ in video_frames(
        dataset, camera, video_id, candidates, None, problems=problems, dequantize=config.dequantize_telemetry,
        at_frame_time=config.telemetry_at_frame_time, report=info)]
    return look_ahead(frames, lambda f: candidates.get(f.image.id), config, pipe, info)


def look_ahead(frames: list[Frame], detections: Callable[[Frame], tuple[NDArray, NDArray, NDArray]],
               config: PipelineConfig, pipe: DetectionPipeline | None = None,
               info: VideoTelemetry | None = None) -> list[tuple[Frame, ClockOffset | None]]:
    """The stages that look at a whole video before its first frame (a file's, `uavmm boost` / `track` / `detect`):
    the clock offset re-times the poses with config's settings (`agent.clock_offset.retime_frames`; over a `--dem`
    terrain the detections lie on `pipe`'s), view jumps that sparse telemetry smears are put where the detections
    jump (`agent.view_cuts`, with config.view_cuts), and `pipe` is primed on them (`DetectionPipeline.prime`: the size
    filter's check and the score calibration's input check decide on the whole video). frames: one video's, in time
    order; detections(frame) -> (boxes_xyxy, scores, class_ids). info: the clock offset's windows and the view cuts
    are recorded in it (`look_ahead_reports`)."""
    info = info if info is not None else VideoTelemetry()
    settings = config.clock_offset_settings()
    out: list[tuple[Frame, ClockOffset | None]]
    if settings is None:
        out = [(frame, None) for frame in frames]
    else:
        terrain_for = pipe.terrain_for if pipe is not None and config.terrain is not None else None
        windows: list[int] = []
        out = retime_frames(frames, detections, settings, windows_out=windows, terrain_for=terrain_for)
        info.offset_windows = windows[0] if windows else 0
    if config.view_cuts:
        cuts = ViewCutReport()
        out = place_view_cuts(out, detections, report=cuts)
        info.view_cuts = (cuts.intervals, cuts.cuts, cuts.too_few_frames)
    if pipe is not None:
        pipe.prime((frame.pose, frame.camera, *detections(frame)) for frame, _ in out)
    return out


def telemetry_reports(info: VideoTelemetry, offset_settings: ClockOffsetSettings | None) -> list[StageReport]:
    """The decisions of one video's telemetry stages (agent.telemetry_clock, agent.telemetry_dequantize,
    agent.clock_offset, agent.view_cuts) as stage reports."""
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
        out.append(dequantize_report(info.quanta, info.dequantize_off, info.holds))
        out += look_ahead_reports(info, offset_settings)
    if info.compass_frames:
        out.append(StageReport("compass heading", True, "frames without gimbal_heading took the aircraft's "
                                                        "compass_heading"))
    if info.bridged_frames:
        out.append(StageReport("partial meta", True, "frames whose meta lacks pitch, heading or height took the pose "
                                                     "interpolated between the others' samples"))
    return out


def look_ahead_reports(info: VideoTelemetry, offset_settings: ClockOffsetSettings | None) -> list[StageReport]:
    """What `look_ahead` did in one video (info as it filled it) as stage reports: the clock offset (when
    offset_settings, the config's, say it ran) and the view cuts."""
    out = []
    if offset_settings is not None:
        need = offset_settings.min_windows
        acted = info.offset_windows >= need
        out.append(StageReport("clock offset", acted,
                               f"measured on {info.offset_windows} turning windows" if acted else
                               f"{info.offset_windows} of {need} turning windows needed: telemetry as stamped"))
    if info.view_cuts is not None:
        out.append(ViewCutReport(*info.view_cuts).stage_report())
    return out

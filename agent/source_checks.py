"""Checks of a video's telemetry that warn (the video source's, `agent.sources`): telemetry that does not span the
video (a KLV field of view: `agent.field_of_view`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from agent.video_decode import VideoReader

__all__ = ["check_span"]

log = logging.getLogger("agent.sources")  # the video source's warnings, under its name


def check_span(video: Path, telemetry: Path, reader: VideoReader, start_s: float, end_s: float,
                max_gap_s: float) -> None:
    """Warn when the telemetry and the video plainly do not belong together: the video runs on past the telemetry
    (its last frames get no pose), or, for a DJI SRT (written per video, as long as it), the SRT runs on far past
    the video (a clip cut from a longer recording given the recording's SRT: every frame takes the pose of the
    recording's first seconds). start_s, end_s: the telemetry's first and last record in video time (s)."""
    if reader.frame_count is None:
        return
    duration = reader.frame_count / reader.fps
    if duration > end_s + max_gap_s:
        log.warning("telemetry %s ends %.1f s into the video but %s lasts %.1f s: its last %.1f s get no pose",
                    telemetry.name, end_s, video.name, duration, duration - max(end_s, 0.0))
    elif telemetry.suffix.lower() == ".srt" and end_s - duration > max(2.0, 0.1 * duration):
        log.warning("the SRT %s runs %.1f s but %s lasts %.1f s: a clip cut from a longer recording? Its frames are "
                    "put on the SRT's first %.1f s; give the SRT written with this clip, or --telemetry-offset-s (the "
                    "SRT's time of the clip's first frame)", telemetry.name, end_s - start_s, video.name, duration,
                    duration)

"""Checks of a video's telemetry that warn (the video source's, `agent.sources`): a KLV field of view unlike the
camera file's, and telemetry that does not span the video."""

from __future__ import annotations

import logging
import statistics
from pathlib import Path
from typing import TYPE_CHECKING

from shared.geo import Camera

if TYPE_CHECKING:
    from agent.video_decode import VideoReader

__all__ = ["camera_hfov_deg", "check_klv_field_of_view", "check_span"]

log = logging.getLogger("agent.sources")  # the video source's warnings, under its name


def camera_hfov_deg(camera: str | Path) -> float | None:
    """The horizontal field of view of a camera file or preset, None when it cannot be read (the video source says
    why when it loads the camera, after the telemetry's checks)."""
    try:
        cam = Camera.from_spec(camera)
    except (ValueError, OSError):
        return None
    return cam.hfov_deg


def check_klv_field_of_view(path: str | Path, hfovs: list[float], camera_hfov_deg: float) -> None:
    """Warn when the KLV's horizontal fields of view (deg) differ from the camera file's by more than 15 % or vary by
    more than that during the flight: a zoom lens, whose focal length the camera file does not follow (a box's
    ground point scales with it: 40 m where the truth is 4 m at 8 against 65 deg in a probe)."""
    if not hfovs:
        return
    lo, mid, hi = min(hfovs), statistics.median(hfovs), max(hfovs)
    if abs(mid / camera_hfov_deg - 1.0) > 0.15 or hi / lo > 1.15:
        log.warning("telemetry %s: the KLV's horizontal field of view is %.1f deg (%.1f .. %.1f over the flight) where "
                    "the camera's is %.1f deg: a zoom lens? Every frame is projected with the camera file's focal "
                    "length (the KLV's field of view is not applied): give a camera file for the zoom in use",
                    path, mid, lo, hi, camera_hfov_deg)


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

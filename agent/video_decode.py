"""The frames of a video file with their own times, as the container stamps them.

Drone and phone videos are often not a steady frame rate: encoders stall and drop frames, phones and some DJI
firmware record a variable rate, and a transport stream recorded from a live link starts mid-GOP, so that the
frames before the first key frame never decode. A frame's time taken as its index over the nominal rate then
drifts from the frame's own (hundreds of milliseconds, metres on the ground, with no sign of it). Here every
frame's time is its presentation time (OpenCV's ``CAP_PROP_POS_MSEC`` after the read, the stream's start
subtracted), and only where the container gives none that increases is the frame placed one nominal interval
after the one before.

A frame that does not decode (a damaged packet) does not end the video: reading goes on, the frame's number
is kept for it, and the frames after it keep their own times; what was lost is counted and said once at the
end. Rotation metadata is not applied: the frames come as the sensor recorded them, which is what a camera
file describes.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["RAW_STREAM_SUFFIXES", "DecodedFrame", "VideoDecodeReport", "VideoReader", "check_video_fps"]

log = logging.getLogger(__name__)

#: Elementary video streams (no container): their frames carry no times, and FFmpeg takes the rate from the stream's
#: timing information or, without it, guesses 25 frames/s.
RAW_STREAM_SUFFIXES = (".h264", ".264", ".avc", ".h265", ".265", ".hevc")
#: The rate FFmpeg assumes for a raw stream that states none.
_FFMPEG_GUESSED_FPS = 25.0

#: Reads that fail in a row before the video counts as ended, when the container announces no frame count or
#: the announced frames are past (a damaged packet costs one read; H.264 decodes on after it).
MAX_FAILED_READS = 8
#: ... and while frames the container announces are still to come (two seconds at 30 frames/s).
MAX_FAILED_READS_BEFORE_END = 64
#: Intervals between frames measured before a step of several counts as frames missing.
_INTERVALS_NEEDED = 3
#: A first decoded frame up to this far into the video is numbered by its time (past it, by the failed reads only:
#: a container whose times do not start near 0).
_FIRST_FRAME_BY_TIME_S = 60.0
#: A step between two frames off the video's recent interval (times the frames it spans) by more than this share of
#: it counts as irregular (a variable frame rate).
_IRREGULAR_INTERVALS = 0.5


def check_video_fps(path: Path, fps: float) -> float:
    """`fps` (the commands' --video-fps) for the video `path`: ValueError unless it is a raw stream (which has no
    frame times) and fps is within (0, 1000]."""
    if path.suffix.lower() not in RAW_STREAM_SUFFIXES:
        raise ValueError(f"--video-fps applies to a raw {'/'.join(RAW_STREAM_SUFFIXES)} stream, which has no frame "
                         f"times; {path.name} is a container with its own")
    if not (math.isfinite(fps) and 0.0 < fps <= 1000.0):
        raise ValueError(f"--video-fps {fps!r} must be frames per second within (0, 1000]")
    return float(fps)


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """index: the frame's number in the video (frames that failed to decode keep theirs); t: its time in the
    video (seconds, the container's presentation time); image: (H, W, 3) uint8 BGR."""

    index: int
    t: float
    image: NDArray[np.uint8]


@dataclass(slots=True)
class VideoDecodeReport:
    """What reading a video met: frames decoded, reads that failed (first_failed: the first such frame's number),
    frames placed on the nominal rate for want of a container time, frames left out whose time went back (a
    decoder's after a damaged packet), frame numbers without a frame (skipped;
    first_skipped: the first), steps between frames off the video's recent interval by more than half of it
    (irregular; max_off_grid_s: the largest such difference, seconds, at frame worst_frame)."""

    decoded: int = 0
    failed: int = 0
    first_failed: int | None = None
    untimed: int = 0
    out_of_order: int = 0
    irregular: int = 0
    skipped: int = 0
    first_skipped: int | None = None
    max_off_grid_s: float = 0.0
    worst_frame: int | None = None


class VideoReader:
    """A video file read by OpenCV: its nominal rate and announced frame count, and its frames with their times.

    fps: the container's nominal rate (30 when it gives none), or the rate given for a raw stream (`fps`, the
    commands' `--video-fps`: a raw .h264/.h265 stream has no frame times, so its frames are placed 1/fps apart);
    frame_count: the frames it announces (None when it does not say, e.g. a transport stream); width, height: the
    frames' size as stored; rotation_deg: the rotation metadata that is not applied (0 without). Raises ValueError
    when OpenCV cannot open the file, or for `fps` beside a container (which has its own frame times) or not > 0.
    A raw stream read at FFmpeg's guess of 25 frames/s (no `fps`) is warned about: its frames would drift from
    their times by 20 % at 30 frames/s.
    """

    def __init__(self, path: str | Path, fps: float | None = None) -> None:
        import cv2

        self.path = Path(path)
        given_fps = fps
        capture = self._open()
        try:
            fps = float(capture.get(cv2.CAP_PROP_FPS))
            count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            self.width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
            self.height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            rotation = float(capture.get(cv2.CAP_PROP_ORIENTATION_META))
        finally:
            capture.release()
        self.fps = fps if math.isfinite(fps) and fps > 0 else 30.0
        raw = self._raw = self.path.suffix.lower() in RAW_STREAM_SUFFIXES
        if given_fps is not None:
            self.fps = check_video_fps(self.path, given_fps)
        elif raw and self.fps == _FFMPEG_GUESSED_FPS:
            log.warning("video %s is a raw stream without frame times nor a stated rate: its frames are placed 1/25 s "
                        "apart (FFmpeg's guess); give --video-fps, the rate it was recorded at (at 30 frames/s a "
                        "frame a minute in would be put 12 s late)", self.path.name)
        self.frame_count: int | None = count if count > 0 else None
        self.rotation_deg = int(rotation) % 360 if math.isfinite(rotation) else 0
        if self.rotation_deg:
            log.info("video %s carries a %d deg rotation in its metadata: its frames are read as recorded (%dx%d), "
                     "as the camera file describes the sensor", self.path.name, self.rotation_deg, self.width,
                     self.height)
        self.report = VideoDecodeReport()

    def _open(self):  # -> cv2.VideoCapture
        import cv2

        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise ValueError(f"video file {self.path} cannot be opened by OpenCV")
        capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)  # frames as the sensor recorded them
        return capture

    def first_image(self) -> NDArray[np.uint8] | None:
        """The first frame that decodes (None: none within the first reads)."""
        capture = self._open()
        try:  # as many failed reads as `frames` takes at the start (a video whose first frames are damaged)
            for _ in range(MAX_FAILED_READS_BEFORE_END if self.frame_count else MAX_FAILED_READS):
                ok, image = capture.read()
                if ok and image is not None:
                    return image
            return None
        finally:
            capture.release()

    def frames(self) -> Iterator[DecodedFrame]:
        """Every frame in presentation order with its time and number (the module docstring); the report is filled as
        it goes and said when the last frame is read (failed reads, skipped numbers, fewer frames than announced).

        A frame's number is one more than the frame before's, and more where its time steps by several of the
        video's recent intervals (their median, once three are known; the container's nominal rate can be far off):
        a frame the decoder drops inside a read (a damaged packet in a transport stream or a B-frame stream) leaves
        its number out instead of shifting every later frame's. Without times (or before three intervals are
        known) a read that failed counts as a frame.
        """
        import cv2

        report = self.report = VideoDecodeReport()
        capture = self._open()
        period = 1.0 / self.fps
        index, failed_in_row = -1, 0
        intervals: deque[float] = deque(maxlen=15)  # the recent steps between frames' times, per frame number
        prev_t: float | None = None
        last_pos: float | None = None  # the container's time of the frame before, as it gave it
        try:
            while True:
                ok, image = capture.read()
                if not ok or image is None:
                    failed_in_row += 1
                    announced_left = self.frame_count is not None and index + failed_in_row < self.frame_count
                    if failed_in_row >= (MAX_FAILED_READS_BEFORE_END if announced_left else MAX_FAILED_READS):
                        break
                    continue  # a damaged frame, or the end: only a frame read after it tells
                # a raw stream's times are FFmpeg's own (0, or a guessed rate): every frame one interval on
                pos = math.nan if self._raw else float(capture.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
                valid = math.isfinite(pos) and pos >= 0.0
                timed = valid and (prev_t is None or pos > prev_t)
                if timed:
                    t = pos
                elif valid and last_pos is not None and pos < last_pos:
                    # a time going back: a frame a decoder puts out of order after a damaged packet (its image is
                    # an older frame's or garbled); not a frame of this place in the video
                    report.out_of_order += 1
                    continue
                else:  # no container time that increases: one nominal interval after the frame before
                    t = 0.0 if prev_t is None else prev_t + period * (1 + failed_in_row)
                    report.untimed += 1
                if valid:
                    last_pos = pos
                if prev_t is None:
                    # the first frame that decodes: after the failed reads before it, or where its time puts it (a
                    # damaged first key frame takes the frames up to the next one with it, reads that fail or not);
                    # it was numbered 0 and every later frame shifted by as many
                    number = failed_in_row
                    if timed and t < _FIRST_FRAME_BY_TIME_S:
                        number = max(number, round(t / period))
                elif timed and len(intervals) >= _INTERVALS_NEEDED:
                    # frames missing where the time steps by several of the video's recent intervals
                    recent = statistics.median(intervals)
                    steps = max(1, round((t - prev_t) / recent))
                    number = index + steps  # a failed read that left no gap in the times took no frame's place
                    off = abs(t - prev_t - steps * recent)
                    if off > report.max_off_grid_s:
                        report.max_off_grid_s, report.worst_frame = off, number
                    if off > _IRREGULAR_INTERVALS * recent:
                        report.irregular += 1
                    intervals.append((t - prev_t) / steps)
                else:
                    number = index + 1 + failed_in_row
                    if timed:
                        intervals.append((t - prev_t) / (1 + failed_in_row))
                missing = number - index - 1 - failed_in_row  # numbers without a frame nor a failed read
                if missing > 0:
                    report.skipped += missing
                    if report.first_skipped is None:
                        report.first_skipped = index + 1
                if failed_in_row:  # the failed reads were frames of the video after all
                    report.failed += failed_in_row
                    if report.first_failed is None:
                        report.first_failed = index + 1
                    failed_in_row = 0
                prev_t, index = t, number
                report.decoded += 1
                yield DecodedFrame(number, t, image)
        finally:
            capture.release()
        self._say(report)

    def _say(self, report: VideoDecodeReport) -> None:
        name = self.path.name
        if report.irregular:
            log.info("video %s: frame times are irregular (a variable frame rate: %d steps between frames off the "
                     "recent interval, by up to %.3f s at frame %s); each frame is placed at its own container time",
                     name, report.irregular, report.max_off_grid_s, report.worst_frame)
        if report.untimed:
            log.info("video %s: %d of %d frames had no container time that increases: placed 1/%.3f s after the "
                     "frame before", name, report.untimed, report.decoded, self.fps)
        if report.skipped:
            log.info("video %s: %d frame number(s) have no frame (the first is %d): frames dropped when recording, "
                     "or lost in decoding; the frames after keep their own times and numbers", name, report.skipped,
                     report.first_skipped)
        if report.failed or report.out_of_order:
            what = [f"{report.failed} frame(s) could not be decoded, the first is frame {report.first_failed},"
                    ] if report.failed else []
            what += [f"{report.out_of_order} came out of order"] if report.out_of_order else []
            log.warning("video %s: %s (a damaged file?): they are skipped, the frames after them keep their own times",
                        name, " and ".join(what).rstrip(","))
        if self.frame_count is not None and report.decoded < 0.9 * self.frame_count:
            # a transport stream's count is its duration times the rate: frames before the first key frame of a
            # recording begun mid-GOP count there, so without failed reads this is no sign of damage
            log.log(logging.WARNING if report.failed or report.out_of_order else logging.INFO,
                    "video %s: %d frames decoded of the %d its container announces", name, report.decoded,
                    self.frame_count)

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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["DecodedFrame", "VideoDecodeReport", "VideoReader"]

log = logging.getLogger(__name__)

#: Reads that fail in a row before the video counts as ended, when the container announces no frame count or
#: the announced frames are past (a damaged packet costs one read; H.264 decodes on after it).
MAX_FAILED_READS = 8
#: ... and while frames the container announces are still to come (two seconds at 30 frames/s).
MAX_FAILED_READS_BEFORE_END = 64
#: A frame whose time is off the nominal grid (index / fps from the first frame) by more than this many frame
#: intervals makes the report say the video's frame times are irregular.
_IRREGULAR_INTERVALS = 0.5


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
    frames placed on the nominal rate for want of a container time, and the largest gap between a frame's
    container time and its index over the nominal rate (seconds)."""

    decoded: int = 0
    failed: int = 0
    first_failed: int | None = None
    untimed: int = 0
    max_off_grid_s: float = 0.0
    worst_frame: int | None = None


class VideoReader:
    """A video file read by OpenCV: its nominal rate and announced frame count, and its frames with their times.

    fps: the container's nominal rate (30 when it gives none); frame_count: the frames it announces (None when it
    does not say, e.g. a transport stream); width, height: the frames' size as stored; rotation_deg: the
    rotation metadata that is not applied (0 without). Raises ValueError when OpenCV cannot open the file.
    """

    def __init__(self, path: str | Path) -> None:
        import cv2

        self.path = Path(path)
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
        try:
            for _ in range(MAX_FAILED_READS):
                ok, image = capture.read()
                if ok and image is not None:
                    return image
            return None
        finally:
            capture.release()

    def frames(self) -> Iterator[DecodedFrame]:
        """Every frame in presentation order with its time (the module docstring); the report is filled as it goes
        and said in one warning when the last frame is read (failed reads, far fewer frames than announced)."""
        import cv2

        report = self.report = VideoDecodeReport()
        capture = self._open()
        period = 1.0 / self.fps
        index, failed_in_row = 0, 0
        prev_t: float | None = None
        first_t = 0.0
        try:
            while True:
                ok, image = capture.read()
                if not ok or image is None:
                    failed_in_row += 1
                    announced_left = self.frame_count is not None and index < self.frame_count
                    if failed_in_row >= (MAX_FAILED_READS_BEFORE_END if announced_left else MAX_FAILED_READS):
                        break
                    # a damaged frame, or the end: only a frame read after it tells (then it counts as failed)
                    index += 1
                    continue
                if failed_in_row:  # the failed reads were frames of the video after all
                    report.failed += failed_in_row
                    if report.first_failed is None:
                        report.first_failed = index - failed_in_row
                    failed_in_row = 0
                pos = float(capture.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
                if math.isfinite(pos) and pos >= 0.0 and (prev_t is None or pos > prev_t):
                    t = pos
                else:  # no container time that increases: one nominal interval after the frame before
                    t = 0.0 if prev_t is None else prev_t + period
                    report.untimed += 1
                if prev_t is None:
                    first_t = t
                off = abs(t - (first_t + index * period))
                if off > report.max_off_grid_s:
                    report.max_off_grid_s, report.worst_frame = off, index
                prev_t = t
                report.decoded += 1
                yield DecodedFrame(index, t, image)
                index += 1
        finally:
            capture.release()
        self._say(report)

    def _say(self, report: VideoDecodeReport) -> None:
        name = self.path.name
        if report.max_off_grid_s > _IRREGULAR_INTERVALS / self.fps:
            log.info("video %s: frame times are irregular (variable frame rate or dropped frames: frame %s is %.3f s "
                     "off its index over %.3f frames/s); each frame is placed at its own container time", name,
                     report.worst_frame, report.max_off_grid_s, self.fps)
        if report.untimed:
            log.info("video %s: %d of %d frames had no container time that increases: placed 1/%.3f s after the "
                     "frame before", name, report.untimed, report.decoded, self.fps)
        if report.failed:
            log.warning("video %s: %d frame(s) could not be decoded (the first is frame %d; a damaged file?): they "
                        "are skipped, the frames after them keep their own times", name, report.failed,
                        report.first_failed)
        if self.frame_count is not None and report.decoded < 0.9 * self.frame_count:
            log.warning("video %s: %d frames decoded of the %d its container announces", name, report.decoded,
                        self.frame_count)

"""Frames for `uavmm anomaly`: the images of a dataset (images.json) or a video with its telemetry, each with
its pose, time and camera; no detector involved. Bad input raises ValueError with one line naming it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose
from shared.telemetry import interpolate


@dataclass(frozen=True, slots=True, eq=False)
class AnomalyInput:
    """One frame: image_id (COCO id; the frame index for videos), video (id or 0), its BGR pixels, time (s),
    pose (None without telemetry) and the camera fitted to its size."""

    image_id: int
    video: int
    image: NDArray[np.uint8]
    t: float
    pose: Pose | None
    camera: Camera


def dataset_frames(images_json: str | Path, camera: Camera) -> Iterator[AnomalyInput]:
    """Every image of a COCO/SeaDronesSee images.json, video by video in frame order; the image files are read
    relative to the file's folder. ValueError when one is missing or unreadable."""
    from agent.dataset import Dataset, image_file, iter_video_frames, read_image

    path = Path(images_json)
    ds = Dataset.load(path)
    for video_id in ds.videos:
        # the poses each frame carries, as the anomaly layer was measured with (docs/anomaly.md)
        for frame in iter_video_frames(ds, camera, video_id, at_frame_time=False):
            pixels = read_image(path.parent, frame.image)
            if pixels is None:
                where = image_file(path.parent, frame.image) or frame.image.file_name
                raise ValueError(f"image {frame.image.id} ({where}) is missing or cannot be read")
            if (pixels.shape[1], pixels.shape[0]) != (frame.camera.width, frame.camera.height):
                raise ValueError(f"image {frame.image.id} is {pixels.shape[1]}x{pixels.shape[0]} but images.json "
                                 f"says {frame.camera.width}x{frame.camera.height}")
            yield AnomalyInput(frame.image.id, video_id, pixels, frame.t, frame.pose, frame.camera)


class VideoFrames:
    """A video file (OpenCV) with its telemetry interpolated to the frame times: any file `agent.sources.
    video_telemetry` reads (``.srt``, ``.csv``, SeaDronesSee ``.json``, ``.tlog``, ``.ulg``, KLV in ``.ts`` /
    ``.m2ts`` / ``.mts`` or raw ``.klv``), or the word ``klv`` for the KLV inside the video (a transport stream).
    A frame is at ``telemetry_offset_s`` + its time in the video (its container time: a variable frame rate or
    dropped frames keep each frame's own, `agent.video_decode`); without it at the telemetry time of video time 0
    the file tells (KLV in a transport stream, by its PTS), else where the log starts recording (AirData's
    isVideo), else the first record's time (`agent.sources.video_start_time`, as the video source of agent and detect).

    GPS written with 3 to 5 decimals and altitude in whole or half metres are made continuous when dequantize
    (`agent.sources.dequantized`, as the detector's video source does).

    Checked at construction, each a one-line ValueError: the video opens and has frames, the camera's aspect
    matches the frames, and the telemetry covers the video's duration (within ``max_gap_s``).
    """

    def __init__(self, video: str | Path, telemetry: str | Path, camera: Camera, *,
                 telemetry_offset_s: float | None = None, max_gap_s: float = 1.0,
                 height_m: float | None = None, height_offset_m: float | None = None,
                 pitch_deg: float | None = None, heading_deg: float | None = None,
                 system_id: int | None = None, utc_offset_h: float | None = None,
                 video_fps: float | None = None, dequantize: bool = True) -> None:
        from agent.field_of_view import field_of_view_track
        from agent.sources import dequantized, resolve_video_telemetry, video_start_time, video_telemetry
        from agent.video_decode import VideoReader, check_video_fps

        telemetry = resolve_video_telemetry(telemetry, video)
        for what, p in (("video", video), ("telemetry", telemetry)):
            if not Path(p).is_file():
                raise ValueError(f"{what} file {p} does not exist")
        self.path = Path(video)
        if video_fps is not None:
            check_video_fps(self.path, video_fps)  # before the file is opened: its own message
        try:
            self.reader = VideoReader(self.path, fps=video_fps)  # a raw stream's rate (--video-fps)
            first = self.reader.first_image()
        except ValueError:
            first = None
        if first is None:
            raise ValueError(f"video file {self.path} cannot be read by OpenCV (not a video, or no frames)")
        self.fps = self.reader.fps
        count = self.reader.frame_count or 0
        self.camera = camera.fitted_to(first.shape[1], first.shape[0], source=f"the frames of {self.path}")
        # without gimbal angles (and no --pitch-deg / --heading-deg) the frames have no pose: the per-frame
        # heatmap still runs, so the file is not refused (need_angles off: a warning says why)
        records, video_start_t = video_telemetry(telemetry, height_m=height_m, height_offset_m=height_offset_m,
                                                 pitch_deg=pitch_deg, heading_deg=heading_deg, system_id=system_id,
                                                 utc_offset_h=utc_offset_h, video=video)
        if Path(str(telemetry)).suffix.lower() == ".json":  # SeaDronesSee: each meta at its own video frame
            from agent.json_video import on_video_frames

            records, video_start_t = on_video_frames(records, self.fps, telemetry)
        self.pitch_deg, self.heading_deg = pitch_deg, heading_deg
        self.records = sorted(records, key=lambda r: r.t)
        #: the quanta made continuous per coordinate (`agent.sources.dequantized`; {}: none), None when off; the
        #: coordinates held between updates, interpolated: their update periods (seconds)
        self.quanta: dict[str, float] | None = None
        self.holds: dict[str, float] = {}
        if dequantize:
            self.records, self.quanta, self.holds = dequantized(self.records, telemetry)
        self._record_t = np.array([r.t for r in self.records], dtype=np.float64)
        self.height_m = height_m
        self.offset_s = video_start_time(self.records, telemetry, telemetry_offset_s=telemetry_offset_s,
                                         video_start_t=video_start_t)
        self.max_gap_s = float(max_gap_s)
        #: The field of view per frame when the telemetry's changes (a zoom lens, `agent.field_of_view`), else None.
        self.field_of_view = field_of_view_track(telemetry, self.records, self.camera)
        duration = max(count - 1, 0) / self.fps
        t0, t1 = self.records[0].t, self.records[-1].t
        if self.offset_s < t0 - max_gap_s or self.offset_s + duration > t1 + max_gap_s:
            raise ValueError(f"telemetry {telemetry} covers {t1 - t0:.1f} s ({t0 - self.offset_s:+.1f} s .. "
                             f"{t1 - self.offset_s:+.1f} s of video time) but the video {self.path.name} lasts "
                             f"{duration:.1f} s: give the telemetry file recorded with it")

    def __iter__(self) -> Iterator[AnomalyInput]:
        """The frames with their poses; a frame is at offset_s + its time in the video (its container time,
        `agent.video_decode.VideoReader`), its id its number in the video."""
        from agent.sources import records_around

        for frame in self.reader.frames():
            t = self.offset_s + frame.t
            # the records around t only: interpolating the whole log per frame cost 163 ms a frame an hour in
            window = records_around(self.records, self._record_t, t, t, self.max_gap_s)
            tel = interpolate(window, np.array([t]), extrapolate_s=self.max_gap_s,
                              max_gap_s=self.max_gap_s)[0] if window else None
            pose = None
            if tel is not None:
                try:
                    # --pitch-deg / --heading-deg fill what a record lacks, never replace it (as agent, detect)
                    pose = tel.to_pose(self.pitch_deg, self.heading_deg, height_m=self.height_m, replace=False)
                except ValueError:
                    pose = None
            camera = self.camera if self.field_of_view is None else self.field_of_view.camera_at(t)
            yield AnomalyInput(frame.index, 0, frame.image, t, pose, camera)

"""Frame sources of the live agent: what a source gives (`FrameSource`, `SourceFrame`), and the source that
reads a video + telemetry + model (a dataset directory's is `agent.dataset_source.DatasetSource`).

Each source yields :class:`SourceFrame` objects (time, pose or None, pre-NMS candidates, camera) in
time order and knows its class names; pacing to real time is the agent's job (`agent.node`). The
simulated source (`sim.source.SimSource`) lives with the simulator, which builds on the agent: the
product never imports its test bench.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from shared.geo import Camera, Pose
from shared.telemetry import Telemetry, from_seadronessee_meta, interpolate, recording_start
from shared.telemetry.recording import no_start_placement

if TYPE_CHECKING:
    from agent.detector import Detections
    from agent.slicing import SliceGrid
    from agent.stage_report import StageReport
    from agent.telemetry_clock import TelemetryTrack
    from shared.telemetry import KlvReport

log = logging.getLogger(__name__)
#: Flight controllers' logs (MAVLink, PX4): they start at connection or arming and may say when recording started.
FLIGHT_LOG_SUFFIXES = (".tlog", ".ulg")


__all__ = [
    "DATASET_FILES",
    "FrameSource",
    "SourceFrame",
    "KLV_IN_VIDEO",
    "VideoSource",
    "dequantized",
    "load_video_telemetry",
    "pose_from_meta",
    "resolve_video_telemetry",
    "video_start_time",
    "video_telemetry",
]

#: Files a dataset directory must hold (the layout `uavmm sim --out` writes).
DATASET_FILES = ("images.json", "pre_nms.json", "camera.json")


@dataclass(frozen=True, slots=True, eq=False)
class SourceFrame:
    """One frame ready for the pipeline.

    Attributes
    ----------
    index : int
        0-based frame index within the source.
    t : float
        Frame time, seconds, on the source's clock (UNIX epoch for the simulator and for datasets
        with dates); non-decreasing.
    pose : Pose or None
        Camera pose from the frame's telemetry; None when the frame has none (no memory-map help).
    pose_t : float or None
        Time the telemetry behind ``pose`` was measured, seconds (None without pose).
    boxes_xyxy : (N, 4) float32
        Pre-NMS candidate boxes, pixels.
    scores : (N,) float32
        Detector confidences in [0, 1].
    class_ids : (N,) int64
        Keys of the source's ``class_names``.
    camera : Camera
        Intrinsics of this frame (datasets may rescale per image size).
    embeddings : (N, D) float32 or None
        Appearance descriptors that came with the candidates (pre_nms.json ``embedding``; NaN rows: none).
    image : (H, W, 3) uint8 or None
        The frame's pixels (BGR) when the source has them (video; datasets whose image files exist): the
        agent describes the kept boxes' appearance from them (`agent.tracking.appearance.with_image_descriptors`).
    image_id : int or None
        The frame's COCO image id when it comes from a dataset (``images.json``), else None: the
        agent's ``--detections-out`` names frames by it (by ``index`` otherwise).
    """

    index: int
    t: float
    pose: Pose | None
    pose_t: float | None
    boxes_xyxy: NDArray[np.float32]
    scores: NDArray[np.float32]
    class_ids: NDArray[np.int64]
    camera: Camera
    embeddings: NDArray[np.float32] | None = None
    image: NDArray[np.uint8] | None = None
    image_id: int | None = None
    #: The pose is the telemetry at the frame's own time (interpolated, or re-timed by the clock-offset estimate):
    #: the tracker adds no latency compensation (GpsTracker.update(pose_retimed=True)).
    pose_retimed: bool = False
    #: The frame's ``frame_index`` in its dataset (images.json), which `--tracks-out` numbers frames by as `uavmm
    #: track` does; None: ``index``.
    frame_index: int | None = None


class FrameSource(Protocol):
    """What the agent needs from a source: a name, class names, a camera and the frames."""

    name: str
    class_names: dict[int, str]
    camera: Camera

    def frames(self) -> Iterator[SourceFrame]:
        """Yield the frames in time order (each call starts again from the first frame)."""
        ...

    def close(self) -> None:
        """Release files and models (idempotent)."""
        ...


def pose_from_meta(meta: dict | None, frame_index: int | None = None) -> tuple[Pose | None, float | None, str | None]:
    """Pose and telemetry time from a SeaDronesSee ``meta`` dict: (pose, pose_t, problem).

    meta None gives (None, None, None); unusable meta (missing gimbal angles, values out of range)
    gives (None, None, problem text) instead of raising.
    """
    if meta is None:
        return None, None, None
    try:
        tel = from_seadronessee_meta(meta, frame_index)
        assert tel is not None
        return tel.to_pose(), tel.t, None
    except ValueError as exc:
        return None, None, str(exc)


# ---------------------------------------------------------------------------------------------
# Video file + telemetry + ONNX model
# ---------------------------------------------------------------------------------------------

#: ``--telemetry klv``: the MISB ST 0601 KLV metadata inside the ``--video`` file (an MPEG transport stream).
KLV_IN_VIDEO = "klv"


def resolve_video_telemetry(telemetry: str | Path, video: str | Path) -> str | Path:
    """The telemetry file: `video` itself for the word ``klv`` (ValueError unless it is a ``.ts``, ``.m2ts`` or
    ``.mts`` file), else `telemetry` unchanged."""
    from shared.telemetry import KLV_FILE_SUFFIXES

    if str(telemetry).lower() != KLV_IN_VIDEO:
        return telemetry
    suffixes = [s for s in KLV_FILE_SUFFIXES if s != ".klv"]
    if Path(video).suffix.lower() not in suffixes:
        raise ValueError(f"--telemetry klv reads the KLV metadata of an MPEG transport stream ({', '.join(suffixes)})"
                         f", not {video}: give the KLV or telemetry file with --telemetry FILE")
    return video


def load_video_telemetry(path: str | Path, *, height_m: float | None = None, height_offset_m: float | None = None,
                         pitch_deg: float | None = None, heading_deg: float | None = None,
                         need_angles: bool = False) -> list[Telemetry]:
    """Telemetry records of a video, checked for what georeferencing needs (`video_telemetry`'s records)."""
    return video_telemetry(path, height_m=height_m, height_offset_m=height_offset_m, pitch_deg=pitch_deg,
                           heading_deg=heading_deg, need_angles=need_angles)[0]


def records_around(records: list[Telemetry], record_t: NDArray[np.float64], t_first: float, t_last: float,
                   max_gap_s: float) -> list[Telemetry]:
    """The sorted records (times record_t) that interpolating to [t_first, t_last] with `max_gap_s` needs: those
    within max_gap_s and one more on each side, so a frame's cost does not grow with the log."""
    lo = max(int(np.searchsorted(record_t, t_first - max_gap_s, side="left")) - 1, 0)
    hi = int(np.searchsorted(record_t, t_last + max_gap_s, side="right")) + 1
    return records[lo:hi]


def video_telemetry(path: str | Path, *, height_m: float | None = None, height_offset_m: float | None = None,
                    pitch_deg: float | None = None, heading_deg: float | None = None,
                    need_angles: bool = False, system_id: int | None = None,
                    utc_offset_h: float | None = None, video: str | Path | None = None
                    ) -> tuple[list[Telemetry], float | None]:
    """Telemetry records of a video, checked for what georeferencing needs, and the telemetry time of video time 0.

    Parameters
    ----------
    path : path
        ``.srt`` (DJI), ``.csv``, SeaDronesSee ``.json``, MAVLink ``.tlog``, PX4 ``.ulg``, MISB ST 0601 KLV in an
        MPEG-TS video (``.ts``, ``.m2ts``, ``.mts``) or raw ``.klv`` (`shared.telemetry.read_telemetry`). For SRT the
        skipped blocks and the GPS resolution (decimals, step in metres) are logged, for KLV the skipped packets.
    height_m : float, optional
        Height above the ground in metres for records without one (`Telemetry.to_pose`); must be > 0.
    height_offset_m : float, optional
        Metres added to every height the file gives, e.g. minus the ground elevation for altitude above sea
        level (DJI ``abs_alt``, the KLV sensor altitude); not for SeaDronesSee ``.json``.
    pitch_deg, heading_deg : float, optional
        The gimbal angles (`--pitch-deg`, `--heading-deg`) for records without them: a file with none in any
        record needs them when ``need_angles`` (the video source: else ValueError; other callers, which also work
        without a pose, get a warning); given beside a file that logs them in every record, they are not used (a
        warning says so).
    system_id : int, optional
        The MAVLink system id of the vehicle in a ``.tlog`` that holds several (`--mavlink-system-id`; default: the
        one with the most positions, a warning names the others); ValueError for another kind of file.
    utc_offset_h : float, optional
        Hours a DJI SRT's date lines are ahead of UTC (`--telemetry-utc-offset-h`: DJI writes the drone's local
        time without a zone; 2 for CEST); None reads them as UTC. ValueError for another kind of file.
    video : path, optional
        The video the telemetry is for: of a SeaDronesSee ``.json`` holding several videos, the one named like it
        is read (`agent.json_video.read_video_json`; its records keep their frame numbers for `on_video_frames`).

    Returns
    -------
    records : list of Telemetry
    video_start_t : float or None
        The telemetry time of the video's first frame when the file tells it (KLV in a transport stream: from
        the PTS of the samples and the video; DJI SRT: from the first usable block's subtitle timing,
        `SrtReport.video_start_t`; a ``.tlog`` / ``.ulg``: where the log says the camera started recording,
        `shared.telemetry.recording.LogRecording.start_t`), else None.

    Raises
    ------
    ValueError
        One line naming the file: when the reader rejects it, it holds no records, ``height_offset_m`` is
        given for SeaDronesSee JSON (whose altitude is already above the water), or records have no height
        and ``height_m`` is not given (the line says to pass ``--height-m`` or ``--height-offset-m``), or no
        record has a gimbal pitch (heading) and ``pitch_deg`` (``heading_deg``) is not given.
    """
    from shared.telemetry import (
        KLV_FILE_SUFFIXES,
        read_klv_report,
        read_srt_report,
        read_telemetry,
        read_tlog_report,
        read_ulog_report,
    )

    suffix = Path(path).suffix.lower()
    if height_m is not None and not (math.isfinite(height_m) and height_m > 0.0):
        raise ValueError(f"--height-m {height_m!r} must be a height above the ground > 0 m")
    kw: dict[str, Any] = {} if height_offset_m is None else {"height_offset_m": float(height_offset_m)}
    if system_id is not None:
        if suffix != ".tlog":
            raise ValueError(f"--mavlink-system-id applies to a MAVLink .tlog or a udp:HOST:PORT stream, not {path}")
        kw["system_id"] = int(system_id)
    if utc_offset_h is not None:
        if suffix != ".srt":
            raise ValueError(f"--telemetry-utc-offset-h applies to a DJI .srt (whose dates are local time), not {path}")
        if not (math.isfinite(utc_offset_h) and -14.0 <= utc_offset_h <= 14.0):
            raise ValueError(f"--telemetry-utc-offset-h {utc_offset_h!r} must be hours within -14 .. 14")
        kw["utc_offset_s"] = float(utc_offset_h) * 3600.0
    if kw and suffix == ".json":
        raise ValueError(f"--height-offset-m applies to .srt and .csv telemetry, not {path} (SeaDronesSee altitude "
                         "is already height above the water)")
    above_sea_level_only, sea_level_name, video_start_t = 0, "abs_alt", None
    klv: KlvReport | None = None
    if suffix == ".srt":
        report = read_srt_report(path, **kw)
        records, video_start_t = report.on_video_clock(), report.video_start_t  # joined clips: the video's clock
        above_sea_level_only = report.heights_above_sea_level_only
        log.info("telemetry %s: %d records from %d blocks (%d skipped); GPS with %s decimals, steps of %.2g m",
                 path, len(records), report.blocks, len(report.skipped), report.gps_decimals,
                 report.gps_step_m or float("nan"))
    elif suffix in KLV_FILE_SUFFIXES:
        klv = read_klv_report(path, **kw)  # logs what it skipped
        records, video_start_t = klv.records, klv.video_start_t
        above_sea_level_only, sea_level_name = klv.heights_above_sea_level_only, "KLV sensor altitude, no frame centre"
    elif suffix in FLIGHT_LOG_SUFFIXES:  # a flight controller's log: where it says the camera started recording
        flight_log = (read_tlog_report if suffix == ".tlog" else read_ulog_report)(path, **kw)
        records, video_start_t = flight_log.records, flight_log.recording.start_t
    elif suffix == ".json":
        from agent.json_video import read_video_json

        records = read_video_json(path, video)
    else:
        records = read_telemetry(path, **kw)
    if not records:
        raise ValueError(f"telemetry file {path} holds no records")
    missing = sum(r.height_m is None for r in records)
    if missing and height_m is None:
        if above_sea_level_only:
            raise ValueError(
                f"telemetry file {path} gives only altitude above sea level ({sea_level_name}) in "
                f"{above_sea_level_only} of {len(records)} records: pass --height-offset-m=-(ground elevation in "
                "metres), or a fixed --height-m METRES above the ground")
        raise ValueError(f"telemetry file {path} has no height above ground in {missing} of {len(records)} records: "
                         "pass --height-m METRES (the flight's height above the ground)")
    if missing:
        log.info("telemetry %s: %d of %d records have no height: using --height-m %g", path, missing, len(records),
                 height_m)
    elif height_m is not None:
        log.warning("telemetry %s: every record has a height: --height-m %g is not used", path, height_m)
    # KLV sends the angles and still gives none: say why (a nadir camera on a tilted platform looks past nadir)
    why_no_angles = "" if klv is None else "".join(
        f" ({n} with the camera above the horizon or past nadir, {m} with the platform's attitude out of range)"
        for n, m in [(klv.no_pitch, klv.attitude_out_of_range)] if n or m)
    for field, flag, value, what in (("pitch_deg", "--pitch-deg", pitch_deg, "the camera's depression below the "
                                      "horizon, 90 = straight down"),
                                     ("heading_deg", "--heading-deg", heading_deg, "the camera's compass heading")):
        missing = sum(getattr(r, field) is None for r in records)
        name = "pitch" if field == "pitch_deg" else "heading"
        if missing == len(records) and value is None:
            if need_angles:
                raise ValueError(f"telemetry file {path} has no gimbal {name} in any of its {len(records)} records"
                                 f"{why_no_angles}: pass {flag} DEG ({what})")
            log.warning("telemetry %s has no gimbal %s in any record: no frame has a pose (no ground layer); pass %s",
                        path, name, flag)
        if not missing and value is not None:
            log.warning("telemetry %s: every record has a gimbal %s: %s %g is not used", path, name, flag, value)
        elif missing and value is not None:
            log.info("telemetry %s: %d of %d records have no gimbal %s: using %s %g", path, missing, len(records),
                     name, flag, value)
    return records, video_start_t


def dequantized(records: list[Telemetry], telemetry: str | Path
                ) -> tuple[list[Telemetry], dict[str, float], dict[str, float]]:
    """`agent.telemetry_dequantize.dequantize_records` on a video's records (sorted by time), logged when it acts:
    (records, quanta, holds). telemetry: the file's name for the log line."""
    from agent.telemetry_dequantize import dequantize_records, describe_quanta

    records, quanta, holds = dequantize_records(records)
    if quanta or holds:
        log.info("telemetry %s: %s made continuous", telemetry, describe_quanta(quanta, holds))
    return records, quanta, holds


def video_start_time(records: list[Telemetry], telemetry: str | Path, *, telemetry_offset_s: float | None = None,
                     video_start_t: float | None = None) -> float:
    """Telemetry time (s) of video time 0 (`--telemetry-offset-s`, the same for every command reading a video).

    records: the video's telemetry sorted by time (not empty). telemetry_offset_s: the user's value, used as given.
    video_start_t: what the file tells (`video_telemetry`: KLV in a transport stream by its PTS, an SRT by its
    subtitle timing). Without either:
    where the log says the camera started recording (AirData's isVideo; the first such start when it marks
    several, with a warning), else the first record's time (for a flight controller's ``.tlog`` / ``.ulg``, which
    starts well before the video, with a warning). telemetry: the name used in the log lines.
    """
    if telemetry_offset_s is not None:
        return float(telemetry_offset_s)
    suffix = Path(str(telemetry)).suffix.lower()
    if video_start_t is not None:  # the file's own video clock: KLV's PTS, an SRT's subtitle timing, a log's start
        clock = {".srt": "the SRT's subtitle timing", ".json": "the JSON's frame numbers", **dict.fromkeys(
            FLIGHT_LOG_SUFFIXES, "the log's camera recording start")}.get(suffix, "the KLV PTS")
        starts = recording_start(records)[1] if suffix in FLIGHT_LOG_SUFFIXES else 0
        (log.warning if starts > 1 else log.info)(
            "telemetry %s: video time 0 is telemetry time %.3f (from %s%s)", telemetry, video_start_t, clock,
            f"; it marks {starts} recordings: the video is taken to be the first, pass --telemetry-offset-s for "
            "another" if starts > 1 else "")
        return video_start_t
    start, starts = recording_start(records)
    if start is None:
        if suffix in FLIGHT_LOG_SUFFIXES:  # it starts at connection or arming: seconds to minutes before the video
            log.warning("telemetry %s: %s", telemetry, no_start_placement(records))
        return records[0].t
    if starts > 1:
        log.warning("telemetry %s marks %d recordings: the video is taken to be the first (t=%.3f); pass "
                    "--telemetry-offset-s for another", telemetry, starts, start)
    else:
        log.info("telemetry %s: the video starts where the log starts recording (t=%.3f)", telemetry, start)
    return start


class VideoSource:
    """A video file read with OpenCV, its telemetry interpolated to the frame times, an ONNX detector.

    Parameters
    ----------
    video : path
        Anything ``cv2.VideoCapture`` opens (a file; a stream URL works too but has no telemetry sync).
    telemetry : path or str
        ``.srt`` (DJI), ``.csv``, SeaDronesSee ``.json``, MAVLink ``.tlog``, PX4 ``.ulg``, KLV (``.ts``, ``.m2ts``,
        ``.mts``, ``.klv``; `shared.telemetry.read_telemetry`), the word ``klv`` for the KLV metadata inside
        `video` (an MPEG transport stream), or a live MAVLink stream ``udp:HOST:PORT``.
    model : path
        ONNX YOLO model with raw (pre-NMS) output (`agent.detector.OnnxYoloDetector`).
    camera : path
        Camera JSON; rescaled when the video's frame size differs.
    telemetry_offset_s : float, optional
        Telemetry time of video time 0, seconds (default: what the telemetry says: KLV in a transport stream
        by its PTS, a log that marks the recording (AirData's isVideo, a flight controller's camera messages)
        where it starts; else the first record's time).
    class_names : path or list, optional
        Overrides the model's class names.
    conf_threshold : float
        Lowest candidate confidence kept from the detector.
    max_gap_s : float
        Frames farther than this from any telemetry record get no pose (before the first, after the last, and
        inside a gap of the log, e.g. a radio dropout).
    pitch_deg, heading_deg : float, optional
        Fixed gimbal angles for telemetry without them.
    height_m, height_offset_m : float, optional
        As in `load_video_telemetry`.
    providers : sequence of str
        onnxruntime execution providers (`agent.detector.resolve_providers`).
    slices : agent.slicing.SliceGrid, optional
        Run the detector on overlapping tiles of each frame (`agent.slicing.SlicedDetector`).
    slice_full_frame : bool
        With ``slices``: also run on the whole frame for objects larger than the overlap.
    telemetry_timeout_s : float
        A live MAVLink stream (``telemetry`` = ``udp:HOST:PORT``, `agent.mavlink_feed`) must deliver a position
        within this many seconds, else ValueError.
    system_id, utc_offset_h : optional
        As in `video_telemetry`.
    video_fps : float, optional
        The frame rate of a raw ``.h264`` / ``.h265`` stream, which has no frame times (`agent.video_decode`); a
        ValueError beside a container.
    dequantize : bool
        A telemetry file's GPS written with 3 to 5 decimals and altitude in whole or half metres made continuous
        (`agent.telemetry_dequantize.dequantize_records`; `PipelineConfig.dequantize_telemetry`); what it found is
        `quanta` (None for a live stream, or when off).
    """

    def __init__(self, video: str | Path, telemetry: str | Path, model: str | Path, camera: str | Path, *,
                 telemetry_offset_s: float | None = None, class_names=None, conf_threshold: float = 0.01,
                 max_gap_s: float = 1.0, pitch_deg: float | None = None, heading_deg: float | None = None,
                 height_m: float | None = None, height_offset_m: float | None = None,
                 providers: Sequence[str] = ("CPUExecutionProvider",), slices: SliceGrid | None = None,
                 slice_full_frame: bool = True, telemetry_timeout_s: float = 10.0,
                 system_id: int | None = None, utc_offset_h: float | None = None,
                 video_fps: float | None = None, dequantize: bool = True) -> None:
        from agent.detector import OnnxYoloDetector
        from agent.field_of_view import LiveFieldOfView, field_of_view_track
        from agent.mavlink_feed import MavlinkUdpFeed, is_live_telemetry
        from agent.slicing import SlicedDetector
        from agent.source_checks import check_span
        from agent.video_decode import VideoReader

        live = is_live_telemetry(telemetry)  # udp:HOST:PORT: MAVLink from the flight controller
        telemetry = resolve_video_telemetry(telemetry, video)
        files = [("video", video), ("model", model)] + ([] if live else [("telemetry", telemetry)])
        for what, path in files:
            if not Path(path).is_file():
                raise ValueError(f"{what} file {path} does not exist")
        self.video_path = Path(video)
        #: The live MAVLink stream (None for a telemetry file).
        self.feed: MavlinkUdpFeed | None = None
        self.records: list[Telemetry] = []
        video_start_t: float | None = None
        if not live:
            self.records, video_start_t = video_telemetry(telemetry, height_m=height_m, height_offset_m=height_offset_m,
                                                          pitch_deg=pitch_deg, heading_deg=heading_deg,
                                                          need_angles=True, system_id=system_id,
                                                          utc_offset_h=utc_offset_h, video=video)
        self.height_m = height_m
        self.camera_file = Camera.from_spec(camera)  # a camera file or a preset name
        self.reader = VideoReader(self.video_path, fps=video_fps)  # video_fps: a raw stream's rate (--video-fps)
        width, height = self.reader.width, self.reader.height
        #: Frames the container announces (None when it does not say, e.g. a stream).
        self.frame_count: int | None = self.reader.frame_count
        self.fps = self.reader.fps
        if Path(str(telemetry)).suffix.lower() == ".json":  # SeaDronesSee: each meta at its own video frame
            from agent.json_video import on_video_frames

            self.records, video_start_t = on_video_frames(self.records, self.fps, telemetry)
        same_size = (width, height) in ((0, 0), (self.camera_file.width, self.camera_file.height))
        self.camera = self.camera_file if same_size else self.camera_file.fitted_to(width, height,
                                                                                      source=f"the frames of {video}")
        # a camera file at another resolution: the same field of view, fine, but the user should know (a preset has
        # no size of its own: it is made at the frames' size)
        if not same_size and self.camera_file.preset is None:
            log.warning("camera %s is %dx%d but the frames of %s are %dx%d: using it scaled to the frames",
                        camera, self.camera_file.width, self.camera_file.height, self.video_path.name, width, height)
        self.detector: Callable[[NDArray[np.uint8]], Detections] = OnnxYoloDetector(
            model, class_names=class_names, conf_threshold=conf_threshold, providers=providers)
        self.class_names = dict(enumerate(self.detector.class_names))  # type: ignore[attr-defined]
        if slices is not None:
            self.detector = SlicedDetector(self.detector, slices, full_frame=slice_full_frame)
        if live:  # last: nothing after this may fail with the port bound
            self.feed = MavlinkUdpFeed(str(telemetry), system_id=system_id, height_offset_m=height_offset_m or 0.0)
            try:
                self.records = self.feed.start(telemetry_timeout_s)
            except BaseException:
                self.feed.close()
                raise
            log.info("telemetry %s: live MAVLink, first record at t=%.3f", telemetry, self.records[0].t)
        self.records.sort(key=lambda r: r.t)
        #: the quanta made continuous per coordinate ({}: none found), None when not looked for; the coordinates
        #: held between updates, interpolated: their update periods (seconds)
        self.quanta: dict[str, float] | None = None
        self.holds: dict[str, float] = {}
        if dequantize and not live:
            self.records, self.quanta, self.holds = dequantized(self.records, telemetry)
        self._record_t = np.array([r.t for r in self.records], dtype=np.float64)
        self.telemetry_offset_s = video_start_time(self.records, telemetry, telemetry_offset_s=telemetry_offset_s,
                                                   video_start_t=video_start_t)
        self.max_gap_s = float(max_gap_s)
        self.pitch_deg = pitch_deg
        self.heading_deg = heading_deg
        self.name = f"video:{self.video_path.name}"
        self.problems = 0
        #: The field of view per frame when the telemetry's changes (a zoom lens, `agent.field_of_view`), else None.
        self.field_of_view = None if live else field_of_view_track(telemetry, self.records, self.camera)
        self.live_field_of_view = LiveFieldOfView(str(telemetry)) if live else None
        if not live and self.records:
            check_span(self.video_path, Path(telemetry), self.reader, self._record_t[0] - self.telemetry_offset_s,
                        self._record_t[-1] - self.telemetry_offset_s, self.max_gap_s)

    def _pose(self, tel: Telemetry | None, *, count: bool = True) -> Pose | None:
        """The record's pose, None when it makes none (counted in `problems` and warned once, when count)."""
        if tel is None:
            return None
        try:  # --pitch-deg / --heading-deg fill what a record lacks, never replace what it logs
            return tel.to_pose(self.pitch_deg, self.heading_deg, height_m=self.height_m, replace=False)
        except ValueError as exc:
            if not count:
                return None
            self.problems += 1
            if self.problems == 1:
                log.warning("telemetry of %s: no pose at t=%.3f: %s (further frames without a pose are counted in the "
                            "summary)", self.name, tel.t, exc)
            else:
                log.debug("no pose at t=%.3f: %s", tel.t, exc)
            return None

    def poses_at(self, times: NDArray[np.float64]) -> list[tuple[Pose | None, float | None]]:
        """Poses interpolated to telemetry times (N,) -> [(pose or None, pose time or None)].

        Only the records bracketing the times are interpolated, so long flights cost the same per frame. With a
        live stream this first waits (bounded) for the records that bracket the times.
        """
        if self.feed is not None:  # only the records around the times: the stream's whole list grows all flight
            self.feed.wait_for(float(times[0]), float(times[-1]) + min(self.max_gap_s, 0.2))
            records = self.feed.records_between(float(times[0]) - self.max_gap_s, float(times[-1]) + self.max_gap_s)
        else:
            records = records_around(self.records, self._record_t, float(times[0]), float(times[-1]), self.max_gap_s)
        if not records:
            return [(None, None)] * len(times)
        out: list[tuple[Pose | None, float | None]] = []
        for t, tel in zip(times, interpolate(records, times, extrapolate_s=self.max_gap_s, max_gap_s=self.max_gap_s),
                          strict=True):
            pose = self._pose(tel)
            out.append((pose, float(t) if pose is not None else None))
        return out

    def frames(self) -> Iterator[SourceFrame]:
        """Decode and detect every frame of the video; a frame is at telemetry time offset + its time in the video
        (its container time, `agent.video_decode.VideoReader`: a variable frame rate, dropped frames and a stream
        begun mid-GOP keep each frame's own time). Its index is its number in the video."""
        for frame in self.reader.frames():
            t = self.telemetry_offset_s + frame.t
            pose, pose_t = self.poses_at(np.array([t]))[0]
            image = frame.image
            if (image.shape[1], image.shape[0]) != (self.camera.width, self.camera.height):
                self.camera = self.camera_file.fitted_to(image.shape[1], image.shape[0], source="the video's frames")
            dets = self.detector(image)
            camera = self.camera
            if self.field_of_view is not None:
                camera = self.field_of_view.camera_at(t, self.camera)
            elif self.feed is not None and self.live_field_of_view is not None:
                camera = self.live_field_of_view.camera_at(t, self.feed.records_between(t - 1.0, t + 1.0), camera)
            yield SourceFrame(frame.index, t, pose, pose_t, dets.boxes_xyxy, dets.scores,
                              dets.class_ids.astype(np.int64), camera, image=image)

    def telemetry_track(self) -> TelemetryTrack | None:
        """The telemetry's poses as a track on the frames' clock (`agent.telemetry_clock.TelemetryTrack`: what
        the clock-offset estimate re-times poses on and the view cuts search), None for a live stream (no look
        ahead) or fewer than two records with a pose. Records at one time: the first; records at (0, 0), a
        logger's "no GPS fix": left out, as `shared.telemetry.interpolate` leaves them."""
        from agent.telemetry_clock import TelemetryTrack

        if self.feed is not None:
            return None
        t: list[float] = []
        rows: list[tuple[float, float, float, float, float]] = []
        for record in self.records:
            if (t and record.t <= t[-1]) or not record.has_fix:  # as `interpolate` leaves it out
                continue
            pose = self._pose(record, count=False)  # the frames' problems are counted as they come
            if pose is None:
                continue
            t.append(record.t)
            rows.append((pose.lat, pose.lon, pose.height_m, pose.heading_deg, pose.pitch_deg))
        return TelemetryTrack(np.array(t), np.array(rows)) if len(t) >= 2 else None

    def stage_reports(self) -> list[StageReport]:
        """What reading the telemetry file did, as stage reports (`agent.stage_report`): the dequantisation (for a
        telemetry file; "off" when turned off; nothing for a live stream)."""
        from agent.telemetry_dequantize import DEQUANTIZE_OFF, dequantize_report

        if self.feed is not None:
            return []
        if self.quanta is None:
            return [dequantize_report({}, DEQUANTIZE_OFF)]
        return [dequantize_report(self.quanta, holds=self.holds)]

    def images(self) -> Iterator[tuple[int, NDArray[np.uint8]]]:
        """Decode the video again, without the detector: (frame index, image) as `frames` numbers them."""
        for frame in self.reader.frames():
            yield frame.index, frame.image

    def close(self) -> None:
        """Drop the model session and stop a live telemetry stream."""
        self.detector = None  # type: ignore[assignment]
        if self.feed is not None:
            self.feed.close()

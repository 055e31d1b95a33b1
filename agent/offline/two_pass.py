"""`uavmm detect` reads a recording as a file: the detector over the whole video first, then the file stages.

A recorded flight can be looked ahead in, as `uavmm boost` and `uavmm track` do with a dataset
(`agent.file_frames`). Pass one runs the detector on every frame and keeps the pre-NMS candidates in a temporary
file beside the outputs (`CandidateSpool`: 28 bytes a candidate, e.g. ~0.8 GB for an hour at 30 frames/s with 300
candidates a frame; nothing of it held in memory, removed at the end). Then, as for a dataset:

- the clock-offset estimate (`agent.clock_offset.retime_frames`) re-times every pose by the lag between the
  telemetry and the frames that the detections show, and stands down (keeping its fallback) on too few
  informative windows;
- view jumps hidden between sparse telemetry samples (a 1 Hz log interpolates a 60 deg jump into a one-second
  turn) are cut where the detections jump (`agent.view_cuts`);
- the size filter's check and the score calibration judge the whole video before its first frame
  (`DetectionPipeline.prime`) instead of warming up on its first frames.

These are `agent.file_frames.look_ahead`, the dataset path's own. Pass two decodes the video again (the
appearance descriptors and the annotated video need the pixels; decoding costs a fraction of the detector) and runs
the memory map and the tracker on the stored candidates. A live MAVLink stream cannot be looked ahead in: it runs in
one pass, as the live agent does.
"""

from __future__ import annotations

import errno
import logging
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.clock_offset import ClockOffset
from agent.dataset import Frame, ImageRecord, VideoTelemetry
from agent.file_frames import look_ahead, look_ahead_reports
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.sources import SourceFrame
from agent.stage_report import StageReport

log = logging.getLogger(__name__)

__all__ = ["CandidateSpool", "FilePasses", "can_look_ahead"]

#: bytes a candidate takes in the spool: class id (int64), box (4 float32), score (float32)
_ROW = 8 + 16 + 4


class CandidateSpool:
    """Pre-NMS candidates of a video's frames in an unnamed temporary file (gone when closed or the process
    ends), read back by frame position. Not thread-safe."""

    def __init__(self, directory: str | Path) -> None:
        self._dir = Path(directory)
        # unbuffered: a frame's candidates are one write, its failure (a full disk) seen at that frame
        self._file = tempfile.TemporaryFile(prefix=".uavmm-candidates-", dir=directory, buffering=0)
        self._where: list[tuple[int, int]] = []  # (byte offset, candidates) per added frame
        self._end = 0

    def __len__(self) -> int:
        return len(self._where)

    @property
    def nbytes(self) -> int:
        """Bytes written so far."""
        return self._end

    def add(self, boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray) -> None:
        """Append one frame's candidates: boxes (N, 4), scores (N,), class ids (N,)."""
        boxes = np.ascontiguousarray(boxes_xyxy, dtype=np.float32).reshape(-1, 4)
        n = len(boxes)
        scores = np.ascontiguousarray(scores, dtype=np.float32).reshape(-1)
        cids = np.ascontiguousarray(class_ids, dtype=np.int64).reshape(-1)
        if len(scores) != n or len(cids) != n:
            raise ValueError(f"candidates disagree in length: {n} boxes, {len(scores)} scores, {len(cids)} class ids")
        data = cids.tobytes() + boxes.tobytes() + scores.tobytes()  # 8-byte fields first: aligned reads
        try:
            self._file.seek(self._end)
            if self._file.write(data) != len(data):
                raise OSError(errno.ENOSPC, "short write")
        except OSError as exc:  # a full disk, most likely: say what wrote there and how to do without
            raise OSError(exc.errno, f"the candidates of pass one could not be kept in {self._dir} after "
                                     f"{self._end / 2 ** 20:.0f} MiB ({exc.strerror or exc}); --one-pass needs no "
                                     "such file") from exc
        self._where.append((self._end, n))
        self._end += n * _ROW

    def get(self, i: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        """Frame i's (boxes (N, 4) float32, scores (N,) float32, class ids (N,) int64), fresh arrays."""
        offset, n = self._where[i]
        self._file.seek(offset)
        raw = self._file.read(n * _ROW)
        if len(raw) != n * _ROW:
            raise OSError(f"candidate spool: frame {i} read {len(raw)} of {n * _ROW} bytes")
        cids = np.frombuffer(raw, np.int64, n, 0).copy()
        boxes = np.frombuffer(raw, np.float32, 4 * n, 8 * n).reshape(n, 4).copy()
        scores = np.frombuffer(raw, np.float32, n, 24 * n).copy()
        return boxes, scores, cids

    def close(self) -> None:
        self._file.close()


def can_look_ahead(source: Any) -> str | None:
    """None when `source` can be read in two passes (`agent.sources.VideoSource` over a telemetry file), else why
    not."""
    if not callable(getattr(source, "telemetry_track", None)) or not callable(getattr(source, "images", None)):
        return f"{getattr(source, 'name', 'the source')} cannot be read twice"
    if getattr(source, "feed", None) is not None:
        return "live telemetry stream: no look ahead"
    return None


@dataclass
class FilePasses:
    """Pass one over a video source and the file stages on it; `frames` then yields pass two's frames.

    source: a `VideoSource` (`can_look_ahead`); spool_dir: where the candidates wait between the passes.
    """

    source: Any
    config: PipelineConfig
    spool_dir: Path
    detector_s: float = 0.0
    #: frames of pass two whose image the second decode did not give (never, unless the decoder numbers differently)
    missing_images: int = 0
    reports: list[StageReport] = field(default_factory=list)
    _frames: list[tuple[Frame, ClockOffset | None]] = field(default_factory=list)
    _spool: CandidateSpool | None = None

    def __len__(self) -> int:
        """Frames pass one read."""
        return len(self._frames)

    def detect(self, pipe: DetectionPipeline, max_frames: int | None,
               progress: Callable[[int, int | None], None] | None, total: int | None) -> None:
        """Pass one: the detector over every frame (up to max_frames), candidates to the spool; then the stages that
        look at the whole video, as for a dataset (`agent.file_frames.look_ahead`: clock offset, view cuts, `pipe`
        primed)."""
        spool = self._spool = CandidateSpool(self.spool_dir)
        track = self.source.telemetry_track()
        frames: list[Frame] = []
        it = iter(self.source.frames())
        while max_frames is None or len(frames) < max_frames:
            t0 = time.perf_counter()
            sf = next(it, None)
            self.detector_s += time.perf_counter() - t0
            if sf is None:
                break
            if sf.embeddings is not None:
                raise ValueError(f"{self.source.name}: candidates with embeddings cannot be read in two passes")
            spool.add(sf.boxes_xyxy, sf.scores, sf.class_ids)
            record = ImageRecord(id=len(frames), width=sf.camera.width, height=sf.camera.height, video_id=0,
                                 frame_index=sf.index, date_time=None, meta=None)
            frames.append(Frame(record, sf.pose, sf.t, sf.camera, sf.pose_t, track=track))
            if progress is not None:
                progress(len(frames), total)
        info = VideoTelemetry()
        self._frames = look_ahead(frames, lambda frame: spool.get(frame.image.id), self.config, pipe, info)
        self.reports = look_ahead_reports(info, self.config.clock_offset_settings())

    def frames(self) -> Iterator[SourceFrame]:
        """Pass two: each frame with its prepared pose, its stored candidates and its pixels decoded again."""
        assert self._spool is not None
        spool = self._spool
        images = iter(self.source.images())
        pending: tuple[int, NDArray[np.uint8]] | None = next(images, None)
        for frame, _ in self._frames:
            index = frame.image.frame_index
            while pending is not None and pending[0] < index:  # frames pass one did not reach (never, in order)
                pending = next(images, None)
            image = pending[1] if pending is not None and pending[0] == index else None
            boxes, scores, cids = spool.get(frame.image.id)
            if image is None:
                self.missing_images += 1
                if self.missing_images == 1:
                    log.warning("%s: the second decode gave no image for frame %d (its appearance is not described; "
                                "further frames counted in the summary)", self.source.name, index)
            yield SourceFrame(index, frame.t, frame.pose, frame.pose_t, boxes, scores, cids, frame.camera,
                              image=image, pose_retimed=frame.pose_retimed)

    def close(self) -> None:
        if self._spool is not None:
            self._spool.close()

"""The annotated video of `uavmm detect --render-video`: the frames with the detections, the tracks (box, id,
class, a short trail on the ground) and a small north-up inset of the memory map around the UAV.

Trails are the tracks' recent *ground* positions projected into the current frame with its pose, so they stay
on the ground while the camera moves (pixel positions of earlier frames would drift with the camera); a frame
without pose falls back to the tracks' recent box centres.
"""

from __future__ import annotations

import math
import os
from collections import deque
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from agent.frame_result import FrameResult
from agent.memory_map import MemoryMap
from agent.tracking import TrackOutput
from shared.files import new_temporary
from shared.geo import Camera, Pose, footprint_latlon, latlon_to_pixel

__all__ = ["MP4_FOURCC", "VideoAnnotator"]

#: Codec of the MP4 (OpenCV's built-in MPEG-4 Part 2 encoder: always present, decoded everywhere).
MP4_FOURCC = "mp4v"
_WHITE = (255, 255, 255)
_BLACK = (0, 0, 0)


def _track_colour(track_id: int) -> tuple[int, int, int]:
    """A stable, saturated BGR colour per track id (golden-ratio hues)."""
    hue = int((track_id * 0.618033988749895 % 1.0) * 179)
    hsv = np.array([[[hue, 220, 255]]], dtype=np.uint8)
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


class VideoAnnotator:
    """Draw frames and write them to an MP4 (through a temporary file renamed by `close`).

    Parameters
    ----------
    path : Path
        The MP4 to write.
    fps : float
        Frame rate of the output (the input video's).
    width, height : int
        Frame size; frames of another size are resized to it.
    class_names : dict
        Category id -> name, for the labels.
    trail_s : float
        Length of the trails, seconds.
    inset_fraction : float
        Edge of the memory-map inset as a fraction of the frame's shorter side (0 = no inset).
    range_m : float
        Ground range of the footprint drawn in the inset, metres.
    """

    def __init__(self, path: Path, fps: float, width: int, height: int, class_names: dict[int, str], *,
                 trail_s: float = 2.0, inset_fraction: float = 0.28, range_m: float = 300.0) -> None:
        self.path = Path(path)
        self.size = (int(width), int(height))
        self.class_names = dict(class_names)
        self.trail_s = float(trail_s)
        self.inset_px = int(round(inset_fraction * min(width, height)))
        self.range_m = float(range_m)
        # a new hidden name beside the output, its suffix kept (OpenCV picks the container from it): never a file or
        # a link already there, never another run's
        self._tmp, fd = new_temporary(self.path, suffix=f".tmp{self.path.suffix}")  # OpenCV opens it by name
        os.close(fd)
        self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter.fourcc(*MP4_FOURCC), float(fps), self.size)
        if not self._writer.isOpened():
            self._tmp.unlink(missing_ok=True)
            raise OSError(f"OpenCV cannot write an MP4 video at {self.path}")
        self._history: dict[int, deque[tuple[float, float, float, float, float]]] = {}  # t, lat, lon, u, v
        self.frames = 0

    # ---- per frame -----------------------------------------------------------------------------
    def write(self, image: NDArray[np.uint8], t: float, camera: Camera, pose: Pose | None, result: FrameResult,
              tracks: list[TrackOutput], memory: MemoryMap | None = None) -> None:
        """Draw one frame (`draw`) and append it to the video."""
        self._writer.write(self.draw(image, t, camera, pose, result, tracks, memory))
        self.frames += 1

    def draw(self, image: NDArray[np.uint8], t: float, camera: Camera, pose: Pose | None, result: FrameResult,
             tracks: list[TrackOutput], memory: MemoryMap | None = None) -> NDArray[np.uint8]:
        """The annotated frame at the video's size, (H, W, 3) uint8 BGR; remembers the tracks for their trails.

        image: (H, W, 3) uint8 BGR (not modified); result: the pipeline's kept detections; tracks: the
        tracks to show (reported ones); memory: the pipeline's memory map for the inset (None: no inset).
        """
        canvas = image.copy()
        self._remember(t, tracks)
        for x1, y1, x2, y2 in result.boxes_xyxy:
            cv2.rectangle(canvas, (int(x1), int(y1)), (int(x2), int(y2)), (200, 200, 200), 1, cv2.LINE_AA)
        self._draw_trails(canvas, camera, pose, tracks)
        for tr in tracks:
            colour = _track_colour(tr.id)
            x1, y1, x2, y2 = (int(round(v)) for v in tr.box_xyxy)
            cv2.rectangle(canvas, (x1, y1), (x2, y2), colour, 2, cv2.LINE_AA)
            label = f"{tr.id} {self.class_names.get(tr.cls, tr.cls)} {min(tr.score, 1.0):.2f}"
            _text(canvas, label, (x1, max(y1 - 4, 10)), colour)
        head = f"{_clock(t)}  frame {self.frames}  detections {len(result)}  tracks {len(tracks)}" + (
            "" if pose else "  (no telemetry)")
        _text(canvas, head, (6, 16), _WHITE)
        if memory is not None and pose is not None and self.inset_px >= 48:
            self._draw_inset(canvas, memory, camera, pose, tracks)
        if (canvas.shape[1], canvas.shape[0]) != self.size:
            canvas = np.asarray(cv2.resize(canvas, self.size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
        return canvas

    def _remember(self, t: float, tracks: list[TrackOutput]) -> None:
        for tr in tracks:
            x1, y1, x2, y2 = tr.box_xyxy
            trail = self._history.setdefault(tr.id, deque())
            trail.append((t, tr.lat, tr.lon, 0.5 * (x1 + x2), y2))
        for tid in list(self._history):
            trail = self._history[tid]
            while trail and trail[0][0] < t - self.trail_s:
                trail.popleft()
            if not trail:
                del self._history[tid]

    def _draw_trails(self, canvas: NDArray[np.uint8], camera: Camera, pose: Pose | None,
                     tracks: list[TrackOutput]) -> None:
        for tr in tracks:
            trail = self._history.get(tr.id)
            if not trail or len(trail) < 2:
                continue
            pts = np.array(trail, dtype=np.float64)
            if pose is not None and np.isfinite(pts[:, 1:3]).all():
                uv, valid = latlon_to_pixel(pts[:, 1], pts[:, 2], camera, pose)
                uv = uv[valid]
            else:
                uv = pts[:, 3:5]
            if len(uv) >= 2:
                poly = np.clip(np.round(uv), -10_000, 10_000).astype(np.int32).reshape(-1, 1, 2)
                cv2.polylines(canvas, [poly], False, _track_colour(tr.id), 2, cv2.LINE_AA)

    def _draw_inset(self, canvas: NDArray[np.uint8], memory: MemoryMap, camera: Camera, pose: Pose,
                    tracks: list[TrackOutput]) -> None:
        """The memory map (max over classes) north-up in the top-right corner, with the UAV, its footprint
        and the tracks."""
        size = memory.size_cells
        if size == 0:
            return
        layers = [memory.layer(cls) for cls in memory.classes]
        values = np.zeros((size, size), np.float32)
        for layer in layers:
            if layer is not None and layer.shape == values.shape:
                np.maximum(values, layer, out=values)
        s = self.inset_px
        # square root: weak evidence (a few frames of one candidate) stays visible beside saturated cells
        heat = cv2.applyColorMap((np.sqrt(np.clip(values, 0.0, 1.0)) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
        inset = np.asarray(cv2.resize(heat, (s, s), interpolation=cv2.INTER_AREA), dtype=np.uint8)
        scale = s / size
        grid = memory.grid
        gx0, gy0 = memory.origin

        def to_inset(lat: NDArray, lon: NDArray) -> NDArray[np.int32]:
            gx, gy = grid.latlon_to_cell(lat, lon)
            cells = grid.world_cells
            col = (np.asarray(gx) - gx0 + cells / 2) % cells - cells / 2
            row = np.asarray(gy) - gy0
            return np.round(np.column_stack([col, row]) * scale).astype(np.int32)

        foot = footprint_latlon(camera, pose, max_range_m=self.range_m, samples_per_edge=8)
        if np.isfinite(foot).all() and len(foot) >= 3:
            cv2.polylines(inset, [to_inset(foot[:, 0], foot[:, 1]).reshape(-1, 1, 2)], True, (255, 255, 0), 1,
                          cv2.LINE_AA)
        for tr in tracks:
            if math.isfinite(tr.lat) and math.isfinite(tr.lon):
                u, v = to_inset(np.array([tr.lat]), np.array([tr.lon]))[0]
                cv2.circle(inset, (int(u), int(v)), 3, _track_colour(tr.id), -1, cv2.LINE_AA)
        u, v = to_inset(np.array([pose.lat]), np.array([pose.lon]))[0]
        cv2.drawMarker(inset, (int(u), int(v)), _WHITE, cv2.MARKER_TRIANGLE_UP, 9, 2)
        cv2.arrowedLine(inset, (s - 12, 26), (s - 12, 8), _WHITE, 2, tipLength=0.4)
        _text(inset, "N", (s - 26, 20), _WHITE)
        cv2.rectangle(inset, (0, 0), (s - 1, s - 1), _WHITE, 1)
        h, w = canvas.shape[:2]
        if s + 8 <= min(h, w):
            canvas[4:4 + s, w - s - 4:w - 4] = inset

    # ---- end -----------------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the file and move it into place (idempotent)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None  # type: ignore[assignment]
            self._tmp.replace(self.path)

    def abort(self) -> None:
        """Drop the partial file (a failed run leaves no video)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None  # type: ignore[assignment]
        self._tmp.unlink(missing_ok=True)


def _clock(t: float) -> str:
    """UTC time of day for UNIX times, else seconds on the telemetry's own clock."""
    if t > 1e9:
        stamp = datetime.fromtimestamp(t, timezone.utc)
        return stamp.strftime("%H:%M:%S.") + f"{stamp.microsecond // 10000:02d} UTC"
    return f"t={t:.2f} s"


def _text(image: NDArray[np.uint8], text: str, org: tuple[int, int], colour: tuple[int, int, int]) -> None:
    """A label on a dark box, readable on any background (an outline drawn thicker drifts: Hershey glyphs
    advance by the stroke width)."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
    x, y = org
    cv2.rectangle(image, (x - 2, y - h - 2), (x + w + 2, y + base), _BLACK, -1)
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)

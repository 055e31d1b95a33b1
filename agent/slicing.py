"""Sliced inference for small objects in large frames: run the detector on overlapping tiles of the frame
and merge their pre-NMS candidates into one set, as if one detector had seen the whole frame at full resolution.

A 4K frame letterboxed to a 640-pixel network input shrinks a 20-pixel swimmer to 3 pixels; cut into 2 x 2
tiles it keeps 6. The memory map needs each object's candidates once (every candidate adds evidence), so the
merge is a partition, not a union:

- each pixel belongs to one tile's *core* (the overlaps are split down the middle); a tile keeps the candidates
  whose centre lies in its core and whose box does not touch an inner tile edge (cut off by the tile);
- an object no larger than the overlap lies whole inside the tile that owns its centre, so it is seen whole
  exactly once;
- with ``full_frame`` (default) the detector also runs on the whole frame and contributes the candidates larger
  than the overlap (objects no tile sees whole), while tiles contribute only those up to the overlap.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.detector import Detections

__all__ = ["SliceGrid", "SliceWindow", "SlicedDetector"]


@dataclass(frozen=True, slots=True)
class SliceWindow:
    """One tile of a frame: the pixels it covers ``x0:x1, y0:y1`` and the core it owns (float bounds)."""

    x0: int
    y0: int
    x1: int
    y1: int
    core_x0: float
    core_y0: float
    core_x1: float
    core_y1: float


def _axis(length: int, n: int, overlap: float) -> list[tuple[int, int, float, float]]:
    """(start, end, core start, core end) of n tiles along an axis of `length` pixels."""
    size = length / (n - (n - 1) * overlap)
    step = size * (1.0 - overlap)
    spans = []
    for i in range(n):
        start = int(round(i * step))
        end = length if i == n - 1 else min(length, int(round(i * step + size)))
        spans.append((start, end))
    out = []
    for i, (start, end) in enumerate(spans):
        core0 = 0.0 if i == 0 else 0.5 * (start + spans[i - 1][1])
        core1 = float(length) if i == n - 1 else 0.5 * (end + spans[i + 1][0])
        out.append((start, end, core0, core1))
    return out


@dataclass(frozen=True, slots=True)
class SliceGrid:
    """Cut a frame into ``cols x rows`` tiles overlapping by ``overlap`` of a tile's size.

    cols, rows >= 1 (1 x 1 is the whole frame); overlap in [0, 0.5).
    """

    cols: int
    rows: int
    overlap: float = 0.2

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 16:
                raise ValueError(f"SliceGrid.{name} must be an integer in 1..16, got {value!r}")
        if not (isinstance(self.overlap, int | float) and math.isfinite(self.overlap) and 0 <= self.overlap < 0.5):
            raise ValueError(f"SliceGrid.overlap must be in [0, 0.5) of a tile, got {self.overlap!r}")

    @classmethod
    def parse(cls, text: str, overlap: float = 0.2) -> SliceGrid:
        """'2x2' (columns x rows) -> SliceGrid; ValueError naming the text otherwise."""
        parts = text.lower().split("x")
        try:
            cols, rows = (int(p) for p in parts)
        except ValueError:
            raise ValueError(f"--slices must look like 2x2 (columns x rows), got {text!r}") from None
        return cls(cols, rows, overlap)

    def windows(self, width: int, height: int) -> list[SliceWindow]:
        """The tiles of a width x height frame, row by row from the top-left one."""
        xs = _axis(width, self.cols, self.overlap)
        ys = _axis(height, self.rows, self.overlap)
        return [SliceWindow(x0, y0, x1, y1, cx0, cy0, cx1, cy1) for (y0, y1, cy0, cy1) in ys
                for (x0, x1, cx0, cx1) in xs]

    def overlap_px(self, width: int, height: int) -> tuple[float, float]:
        """The overlap of neighbouring tiles in pixels (x, y); inf along an axis with one tile."""
        def along(length: int, n: int) -> float:
            return math.inf if n == 1 else self.overlap * length / (n - (n - 1) * self.overlap)

        return along(width, self.cols), along(height, self.rows)


class SlicedDetector:
    """A detector run on the tiles of a `SliceGrid` (and the whole frame): one merged candidate set.

    Parameters
    ----------
    detector : callable
        (H, W, 3) uint8 BGR -> `Detections` in that image's pixels (e.g. `agent.detector.OnnxYoloDetector`).
    grid : SliceGrid
    full_frame : bool
        Also run on the whole frame for the objects larger than the overlap (see the module docstring).

    ``class_names`` is the wrapped detector's. Calling it costs ``cols * rows`` (+1) inferences.
    """

    def __init__(self, detector: Callable[[np.ndarray], Detections], grid: SliceGrid, *,
                 full_frame: bool = True) -> None:
        if full_frame and grid.overlap == 0 and (grid.cols, grid.rows) != (1, 1):
            # beside the full frame a tile keeps the boxes no larger than the overlap: at 0 none (all the cost of the
            # tiles for the whole frame's candidates alone)
            raise ValueError("--slice-overlap 0 beside the full frame keeps no tile's candidate (a tile keeps the "
                             "boxes no larger than the overlap): give an overlap (0.2), or --no-full-frame")
        self.detector = detector
        self.grid = grid
        self.full_frame = bool(full_frame)

    @property
    def class_names(self) -> list[str]:
        return list(self.detector.class_names)  # type: ignore[attr-defined]

    def __call__(self, image_bgr: np.ndarray) -> Detections:
        """Candidates of the whole frame, boxes in frame pixels; no NMS (the pipeline does it)."""
        height, width = image_bgr.shape[:2]
        over_x, over_y = self.grid.overlap_px(width, height)
        parts = []
        for win in self.grid.windows(width, height):
            dets = self.detector(image_bgr[win.y0:win.y1, win.x0:win.x1])
            if not len(dets):
                continue
            boxes = dets.boxes_xyxy + np.array([win.x0, win.y0, win.x0, win.y0], np.float32)
            cx = 0.5 * (boxes[:, 0] + boxes[:, 2])
            cy = 0.5 * (boxes[:, 1] + boxes[:, 3])
            keep = (cx >= win.core_x0) & (cx < win.core_x1) & (cy >= win.core_y0) & (cy < win.core_y1)
            # a box touching an edge the tile shares with a neighbour was cut off by the tile
            if win.x0 > 0:
                keep &= boxes[:, 0] > win.x0 + 0.5
            if win.x1 < width:
                keep &= boxes[:, 2] < win.x1 - 0.5
            if win.y0 > 0:
                keep &= boxes[:, 1] > win.y0 + 0.5
            if win.y1 < height:
                keep &= boxes[:, 3] < win.y1 - 0.5
            if self.full_frame:  # larger objects come from the whole frame
                keep &= ((boxes[:, 2] - boxes[:, 0]) <= over_x) & ((boxes[:, 3] - boxes[:, 1]) <= over_y)
            parts.append(Detections(boxes[keep], dets.scores[keep], dets.class_ids[keep]))
        if self.full_frame:
            whole = self.detector(image_bgr)
            large = ((whole.boxes_xyxy[:, 2] - whole.boxes_xyxy[:, 0]) > over_x) | (
                (whole.boxes_xyxy[:, 3] - whole.boxes_xyxy[:, 1]) > over_y)
            parts.append(whole.select(large))
        return Detections.concat(parts)

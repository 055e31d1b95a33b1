"""Sliced inference (agent.slicing): the tiles' geometry, and the merge that sees every object whole and once."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.detector import Detections
from agent.slicing import SlicedDetector, SliceGrid


def blob_detector(image: np.ndarray) -> Detections:
    """A real (if simple) detector: one box per bright connected component, score 0.9."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    n, _labels, stats, _ = cv2.connectedComponentsWithStats((grey > 128).astype(np.uint8))
    boxes = [[x, y, x + w, y + h] for x, y, w, h, _area in stats[1:n]]
    return Detections(np.array(boxes, np.float32).reshape(-1, 4), np.full(len(boxes), 0.9, np.float32),
                      np.zeros(len(boxes), np.int32))


blob_detector.class_names = ["person"]  # type: ignore[attr-defined]


@settings(max_examples=60, deadline=None)
@given(width=st.integers(32, 4000), height=st.integers(32, 3000), cols=st.integers(1, 5), rows=st.integers(1, 5),
       overlap=st.floats(0.0, 0.45))
def test_every_pixel_is_in_one_core_and_each_core_inside_its_tile(width, height, cols, rows, overlap):
    grid = SliceGrid(cols, rows, overlap)
    wins = grid.windows(width, height)
    assert len(wins) == cols * rows
    for w in wins:
        assert 0 <= w.x0 <= w.core_x0 < w.core_x1 <= w.x1 <= width
        assert 0 <= w.y0 <= w.core_y0 < w.core_y1 <= w.y1 <= height
    xs = np.linspace(0, width - 1e-6, 97)
    ys = np.linspace(0, height - 1e-6, 89)
    owners = np.zeros((len(ys), len(xs)), int)
    for w in wins:
        owners += np.outer((ys >= w.core_y0) & (ys < w.core_y1), (xs >= w.core_x0) & (xs < w.core_x1))
    assert (owners == 1).all()
    # an object no larger than the overlap, centred in a core, lies whole inside that tile
    ox, oy = grid.overlap_px(width, height)
    for w in wins:
        if cols > 1:
            assert w.core_x0 - w.x0 >= ox / 2 - 1 or w.x0 == 0
            assert w.x1 - w.core_x1 >= ox / 2 - 1 or w.x1 == width


@pytest.mark.parametrize("full_frame", [True, False])
def test_objects_on_tile_borders_are_detected_whole_and_once(full_frame):
    image = np.zeros((360, 640, 3), np.uint8)
    grid = SliceGrid(2, 2, 0.25)
    win = grid.windows(640, 360)[0]
    small = [(100, 60, 20, 30), (win.x1 - 10, 100, 16, 24), (300, win.y1 - 12, 18, 22),
             (int(win.core_x1) - 8, int(win.core_y1) - 8, 16, 16)]  # inside, on the x edge, y edge, the corner
    for x, y, w, h in small:
        image[y:y + h, x:x + w] = 255
    dets = SlicedDetector(blob_detector, grid, full_frame=full_frame)(image)
    got = sorted(tuple(int(round(v)) for v in box) for box in dets.boxes_xyxy)
    assert got == sorted((x, y, x + w, y + h) for x, y, w, h in small)


def test_an_object_larger_than_the_overlap_comes_from_the_whole_frame():
    image = np.zeros((360, 640, 3), np.uint8)
    image[100:260, 250:400] = 255  # 150 x 160 px across all four tiles; the overlap is ~ 76 x 43 px
    grid = SliceGrid(2, 2, 0.2)
    with_full = SlicedDetector(blob_detector, grid)(image)
    assert [tuple(b) for b in with_full.boxes_xyxy.astype(int)] == [(250, 100, 400, 260)]
    tiles_only = SlicedDetector(blob_detector, grid, full_frame=False)(image)
    assert len(tiles_only) == 0  # every tile sees it cut: none is kept (documented: --no-full-frame)


def test_slice_grid_parses_and_refuses_bad_text():
    assert SliceGrid.parse("3x2") == SliceGrid(3, 2, 0.2)
    with pytest.raises(ValueError, match="must look like 2x2"):
        SliceGrid.parse("2by2")
    with pytest.raises(ValueError, match="overlap"):
        SliceGrid(2, 2, 0.6)
    with pytest.raises(ValueError, match="cols"):
        SliceGrid(0, 2)

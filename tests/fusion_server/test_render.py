"""Heatmap PNG tiles at the grid's zoom and by resampling, bbox parsing and cell windows."""

import cv2
import numpy as np
import pytest

from fusion_server.joint_map import JointTile
from fusion_server.render import heatmap_png, parse_bbox, tile_bytes, tile_values, window_for_bbox
from shared.tiles import TileGrid

GRID = TileGrid()
X, Y = 137822, 91483


def joint(values: np.ndarray, x: int = X, y: int = Y) -> JointTile:
    return JointTile("person", 18, x, y, values.astype(np.uint8), 0.0, 1, b"", (), 0.0)


def lookup(tiles):
    def tiles_in_range(cls, x0, x1, y0, y1):
        return [t for t in tiles if cls == t.cls and x0 <= t.x <= x1 and y0 <= t.y <= y1]

    return tiles_in_range


def test_native_zoom_is_the_tile_itself():
    values = np.random.default_rng(0).integers(0, 256, (256, 256))
    out = tile_values(lookup([joint(values)]), GRID, "person", 18, X, Y)
    np.testing.assert_allclose(out, values / 255.0, atol=1e-6)


def test_lower_zoom_takes_the_max_or_mean_of_each_block():
    values = np.zeros((256, 256))
    values[10, 10] = 255
    out = tile_values(lookup([joint(values)]), GRID, "person", 17, X // 2, Y // 2, agg="max")
    r, c = (Y % 2) * 128 + 5, (X % 2) * 128 + 5
    assert out[r, c] == 1.0 and out.sum() == 1.0
    mean = tile_values(lookup([joint(values)]), GRID, "person", 17, X // 2, Y // 2, agg="mean")
    assert mean[r, c] == pytest.approx(0.25)


def test_very_low_zoom_keeps_a_single_hot_cell_visible():
    values = np.zeros((256, 256))
    values[0, 0] = 200
    out = tile_values(lookup([joint(values)]), GRID, "person", 6, X >> 12, Y >> 12)
    assert out.max() == pytest.approx(200 / 255)


def test_higher_zoom_crops_and_upsamples_nearest():
    values = np.zeros((256, 256))
    values[128, 128] = 255  # the top-left cell of the south-east quarter
    out = tile_values(lookup([joint(values)]), GRID, "person", 19, 2 * X + 1, 2 * Y + 1)
    assert out[:2, :2].min() == 1.0 and out[2:, :].max() == 0.0 and out[:, 2:].max() == 0.0


def test_png_is_transparent_where_zero_and_coloured_elsewhere():
    values = np.zeros((256, 256), np.float32)
    values[5:10, 5:10] = 0.9
    png = cv2.imdecode(np.frombuffer(heatmap_png(values), np.uint8), cv2.IMREAD_UNCHANGED)
    assert png.shape == (256, 256, 4)
    assert png[0, 0, 3] == 0 and png[7, 7, 3] > 200


@pytest.mark.parametrize(("z", "x", "y", "agg", "cmap"), [(25, 0, 0, "max", "inferno"), (2, 4, 0, "max", "inferno"),
                                                          (2, 0, -1, "max", "inferno"), (18, X, Y, "sum", "inferno"),
                                                          (18, X, Y, "max", "rainbow")])
def test_bad_tile_requests_raise_value_error(z, x, y, agg, cmap):
    with pytest.raises(ValueError):
        tile_bytes(lookup([]), GRID, "person", z, x, y, agg=agg, cmap=cmap)


@pytest.mark.parametrize("text", ["1,2,3", "a,b,c,d", "10,0,5,1", "0,10,1,5", "0,0,200,1", "0,-89,1,1", "nan,0,1,1"])
def test_bad_bboxes_are_refused(text):
    with pytest.raises(ValueError):
        parse_bbox(text)


def test_window_covers_the_bbox():
    box = parse_bbox("9.27,47.67,9.271,47.671")
    window = window_for_bbox(GRID, box)
    lat, lon = window.centres_latlon()
    assert lat.min() < 47.6701 and lat.max() > 47.6709
    assert 150 < window.width < 200 and 220 < window.height < 280  # ~75 m x 111 m at ~0.4 m cells

"""Object candidates: peaks of the joint map, across tile borders, plateaus and suppression."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_server.joint_map import JointTile
from fusion_server.peaks import find_peaks, peaks_geojson
from fusion_server.render import parse_bbox
from shared.tiles import TileGrid

GRID = TileGrid()
X, Y = 137822, 91483


def bump(row: float, col: float, peak: float = 200.0, sigma: float = 3.0) -> np.ndarray:
    r = np.arange(256)[:, None] - row
    c = np.arange(256)[None, :] - col
    return peak * np.exp(-0.5 * (r**2 + c**2) / sigma**2)


def tile(values: np.ndarray, x: int = X, y: int = Y) -> JointTile:
    return JointTile("person", 18, x, y, np.rint(values).astype(np.uint8), 0.0, 1, b"", (), 0.0)


def test_each_bump_gives_one_peak_at_its_cell():
    tiles = [tile(bump(40, 50) + bump(200, 100, peak=120))]
    peaks = find_peaks(tiles, GRID, min_score=0.3)
    assert [(round(p.gy - Y * 256 - 0.5), round(p.gx - X * 256 - 0.5)) for p in peaks] == [(40, 50), (200, 100)]
    assert peaks[0].score == 200 / 255
    assert len(find_peaks(tiles, GRID, min_score=0.6)) == 1


def test_a_bump_on_a_tile_border_is_one_peak():
    values = bump(100, 256.0, peak=200)  # centred on the border between X and X + 1
    west = tile(values[:, :256])
    east_values = bump(100, 0.0, peak=200)
    east = tile(east_values, x=X + 1)
    peaks = find_peaks([west, east], GRID, min_score=0.3)
    assert len(peaks) == 1


def test_plateau_is_one_peak_at_its_centre():
    values = np.zeros((256, 256))
    values[10:13, 20:25] = 150
    peaks = find_peaks([tile(values)], GRID, min_score=0.1)
    assert len(peaks) == 1
    assert peaks[0].gx - X * 256 == 22.5 and peaks[0].gy - Y * 256 == 11.5


def test_bbox_filters_and_geojson_shape():
    peaks = find_peaks([tile(bump(40, 50))], GRID, min_score=0.3)
    p = peaks[0]
    inside = parse_bbox(f"{p.lon - 1e-5},{p.lat - 1e-5},{p.lon + 1e-5},{p.lat + 1e-5}")
    outside = parse_bbox(f"{p.lon + 1e-3},{p.lat},{p.lon + 2e-3},{p.lat + 1e-3}")
    assert len(find_peaks([tile(bump(40, 50))], GRID, 0.3, bbox=inside)) == 1
    assert find_peaks([tile(bump(40, 50))], GRID, 0.3, bbox=outside) == []
    feature = peaks_geojson(peaks)["features"][0]
    assert feature["geometry"]["coordinates"] == [p.lon, p.lat]
    assert feature["properties"] == {"cls": "person", "score": round(200 / 255, 4)}


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), min_byte=st.integers(1, 255))
def test_the_peaks_of_a_tile_are_labelled_as_over_the_whole_tile(seed, min_byte):
    """_tile_peaks labels the maxima only in their span (for speed): the same peaks, in the same order (ties keep
    it through the score sort), as OpenCV's labels over the whole tile, and the plateaus' centroids scipy finds."""
    import cv2
    from scipy import ndimage

    from fusion_server.peaks import _tile_peaks

    rng = np.random.default_rng(seed)
    padded = np.zeros((258, 258), np.uint8)
    yy, xx = np.mgrid[0:258, 0:258]
    for _ in range(rng.integers(0, 5)):
        cy, cx = rng.integers(0, 258, 2)
        padded = np.maximum(padded, (rng.integers(30, 256) * np.exp(
            -((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * rng.uniform(0.5, 6.0) ** 2))).astype(np.uint8))
    if rng.random() < 0.5:  # plateaus and lone cells
        r, c = rng.integers(1, 250, 2)
        padded[r:r + rng.integers(1, 6), c:c + rng.integers(1, 6)] = rng.integers(1, 256)
        padded[rng.integers(0, 258, 20), rng.integers(0, 258, 20)] = rng.integers(0, 256, 20)
    cols, rows, values = _tile_peaks(padded, min_byte)
    mask = ((padded == cv2.dilate(padded, np.ones((3, 3), np.uint8))) & (padded >= min_byte))[1:-1, 1:-1]
    count, labels, _, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    assert np.allclose(cols, centroids[1:, 0]) and np.allclose(rows, centroids[1:, 1])
    found, n = ndimage.label(mask, structure=np.ones((3, 3)))
    assert n == len(values) == count - 1
    if n:
        reference = np.array(ndimage.center_of_mass(mask, found, range(1, n + 1)))  # (row, col)
        ours = sorted(zip(np.round(cols, 6).tolist(), np.round(rows, 6).tolist(), strict=True))
        assert sorted(map(tuple, np.round(reference[:, ::-1], 6).tolist())) == ours
        assert np.all(values >= min_byte)

"""Object candidates: peaks of the joint map, across tile borders, plateaus and suppression."""

import numpy as np

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

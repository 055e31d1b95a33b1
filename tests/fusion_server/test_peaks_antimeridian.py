"""Fused objects (joint-map peaks) across the antimeridian: tile x = 2**z - 1 and x = 0 are neighbours like any two
tiles, so one object whose evidence straddles 180 deg is one object (it was two, one on each side)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_server.joint_map import JointMap
from fusion_server.peaks import Peak, find_peaks
from fusion_server.rules import get_fusion_rule
from shared.tiles import EARTH_RADIUS_M, CellWindow, TileGrid
from tests.netutil import wait_until

GRID = TileGrid()
SIDE, N, WORLD = GRID.tiles_per_side, GRID.n, GRID.world_cells
#: Fiji's tile row (the antimeridian crosses the islands at ~16.5 deg S).
Y = int(GRID.tile_of(-16.5, 179.9)[1])


def joint_map() -> JointMap:
    return JointMap(GRID, get_fusion_rule("mean"), 60.0, 100.0, clock=lambda: 0.0, wall=lambda: 1e9)


def objects_window(gx0: int, objects: list[tuple[float, float, float, float]]) -> list[tuple[int, int, np.ndarray]]:
    """Tiles (x, y, (n, n) uint8) of Gaussian objects (col, row inside the window, peak value 0..1, sigma cells)
    drawn on the 2-tile wide window of tile row Y whose west column is gx0 (wrapping at the world's east edge, as
    the agents' windows do): the same objects give the same cells wherever the window is."""
    window = CellWindow(gx0=gx0 % WORLD, gy0=Y * N, width=2 * N, height=N, grid=GRID)
    cols = np.arange(window.width, dtype=np.float64)[None, :] + 0.5
    rows = np.arange(window.height, dtype=np.float64)[:, None] + 0.5
    values = np.zeros(window.shape)
    for col, row, peak, sigma in objects:
        values = np.maximum(values, peak * np.exp(-0.5 * ((cols - col) ** 2 + (rows - row) ** 2) / sigma**2))
    return window.split(np.rint(values * 255.0).astype(np.uint8))


def wrapped(gx: float) -> float:
    """gx as an offset in cells from the antimeridian (negative: west of it)."""
    return (gx + WORLD / 2) % WORLD - WORLD / 2


def peaks_of(tiles: list[tuple[int, int, np.ndarray]], min_score: float = 0.3) -> list[Peak]:
    joint = joint_map()
    for seq, (x, y, values) in enumerate(tiles, 1):
        assert joint.put("uav-a", ("person", GRID.z, x, y), values, t=0.0, seq=seq) is None
    joint.step()
    return find_peaks(joint.tiles("person"), GRID, min_score)


def ground_m(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    """Great-circle distance (haversine), metres."""
    p0, p1, dl = math.radians(lat0), math.radians(lat1), math.radians(lon1 - lon0)
    h = math.sin((p1 - p0) / 2) ** 2 + math.cos(p0) * math.cos(p1) * math.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))


@settings(max_examples=40, deadline=None)
@given(offset=st.floats(-6.0, 6.0), row=st.floats(20.0, 230.0), peak=st.floats(0.6, 1.0), sigma=st.floats(1.5, 4.0))
def test_an_object_straddling_the_antimeridian_is_one_object_where_it_is(offset, row, peak, sigma):
    """An object `offset` cells east of 180 deg (west of it when negative): its evidence spans both tiles. It came out
    twice, one peak on each side of the line, 180 deg apart in a raw longitude difference."""
    objects = [(N + offset, row, peak, sigma)]  # in the window from the last tile's west edge
    peaks = peaks_of(objects_window(WORLD - N, objects))
    assert len(peaks) == 1
    found = peaks[0]
    assert -180.0 <= found.lon < 180.0
    gy = Y * N + row
    assert abs(wrapped(found.gx) - offset) <= 1.0 and abs(found.gy - gy) <= 1.0  # the cell of the object's top
    lat, lon = (float(v) for v in GRID.cell_to_latlon(offset % WORLD, gy))
    assert ground_m(found.lat, found.lon, lat, lon) <= 1.5 * float(GRID.cell_size_m(lat))
    # what the same object gives across an ordinary tile border
    ordinary = peaks_of(objects_window(1000 * N, objects))
    assert [(p.score, p.gx - 1001 * N, p.gy) for p in ordinary] == [(found.score, wrapped(found.gx), found.gy)]


@settings(max_examples=20, deadline=None)
@given(west=st.floats(3.0, 40.0), east=st.floats(3.0, 40.0))
def test_two_objects_apart_across_the_antimeridian_stay_two(west, east):
    """Suppression measures around the world: objects `west` and `east` cells either side of the line, 6 cells
    apart or more (2 cells or 0.8 m is one object), are both kept."""
    peaks = peaks_of(objects_window(WORLD - N, [(N - west, 128.0, 0.9, 1.5), (N + east, 128.0, 0.8, 1.5)]))
    assert len(peaks) == 2
    assert sorted(wrapped(p.gx) for p in peaks) == pytest.approx([-west, east], abs=1.0)


def test_a_bbox_ending_at_the_antimeridian_sees_the_tile_across_it():
    """/v1/objects with a bbox asks the joint map for the bbox's tiles and one tile of margin: the margin did not
    wrap, so an object just east of 180 deg left its western tail as an object inside a bbox west of the line."""
    joint = joint_map()
    for seq, (x, y, values) in enumerate(objects_window(WORLD - N, [(N + 2.5, 100.5, 0.8, 2.0)]), 1):
        joint.put("uav-a", ("person", GRID.z, x, y), values, t=0.0, seq=seq)
    joint.step()
    assert {(t.x, t.y) for t in joint.tiles_in_range("person", SIDE - 2, SIDE, Y - 1, Y + 1)} == {(SIDE - 1, Y),
                                                                                                  (0, Y)}
    assert {(t.x, t.y) for t in joint.tiles_in_range("person", -1, 1, Y, Y)} == {(SIDE - 1, Y), (0, Y)}
    assert len(joint.tiles_in_range("person", -5, SIDE + 5, Y - 20, Y + 20)) == 2  # more than a world: each once


# ---- over HTTP: the real server, fed by a fake agent over Zenoh ----------------------------------------------------

@pytest.fixture
def patient_server(server_factory):
    return server_factory(ttl_s=30.0)


def test_objects_over_http_report_a_straddling_object_once_and_no_tail_in_a_bbox(patient_server, http_of,
                                                                                   agent_factory):
    agent = agent_factory("uav-fiji")
    gx, gy = 1.7, Y * N + 100.5  # 1.7 cells east of the line; its tail crosses into the last tile
    tiles = objects_window(WORLD - N, [(N + gx, gy - Y * N, 0.9, 2.5)])
    for x, y, values in tiles:
        agent.tile(values.astype(np.float32) / 255.0, x=x, y=y)
    wait_until(lambda: len(patient_server.joint.tiles("person")) == 2)
    http = http_of(patient_server)
    features = http.get("/v1/objects", params={"cls": "person", "min_score": 0.3}).json()["features"]
    assert len(features) == 1
    lon, lat = features[0]["geometry"]["coordinates"]
    want_lat, want_lon = (float(v) for v in GRID.cell_to_latlon(gx, gy))
    assert -180.0 <= lon < 0.0 and ground_m(lat, lon, want_lat, want_lon) <= 1.5 * float(GRID.cell_size_m(lat))
    west = f"179.9999,{want_lat - 1e-4},180,{want_lat + 1e-4}"
    east = f"-180,{want_lat - 1e-4},-179.9999,{want_lat + 1e-4}"
    assert http.get("/v1/objects", params={"bbox": west, "min_score": 0.3}).json()["features"] == []
    assert len(http.get("/v1/objects", params={"bbox": east, "min_score": 0.3}).json()["features"]) == 1

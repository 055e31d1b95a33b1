"""Drones near the antimeridian and far north (a helper's live audit with real processes; each case failed before):
the agent's tile subscriptions and view window wrap or stand down, its state footprint stays on its side of the line,
global tracks average across the line, and objects of the joint map are told apart in metres, not Web Mercator
cells."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.joint_detections import _footprint_cells
from agent.joint_window import window_tiles
from fusion_server.association import weighted_lon
from fusion_server.global_tracks import GlobalTracker
from fusion_server.joint_map import JointTile
from fusion_server.peaks import find_peaks
from shared.geo import Camera, Pose
from shared.messages import TrackItem, TracksMessage
from shared.tiles import TileGrid

GRID = TileGrid()


def test_the_agents_tile_window_wraps_at_the_antimeridian():
    """A window touching the world's east edge asked for tile 2**18 (no key holds it: the agent stopped)."""
    side, n = GRID.tiles_per_side, GRID.n
    tiles = window_tiles((GRID.world_cells - 300, 1000), 600, n, tiles_per_side=side)
    assert all(0 <= x < side for x, _ in tiles)
    assert {x for x, _ in tiles} == {side - 3, side - 2, side - 1, 0, 1, 2}
    assert window_tiles((10, 0), 600, n, tiles_per_side=side) >= {(side - 1, 0), (0, 0)}  # west of x 0: the east edge


def test_a_view_across_the_antimeridian_gives_a_joint_window_on_its_side_or_none():
    """As one block a view straddling the line was 67 million cells wide (57.7 GiB, every frame): none then. A view
    wholly past the line is the block on that side (the third read found it dropped too)."""
    camera = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)
    straddling = _footprint_cells(GRID, camera, Pose(lat=-16.5, lon=179.99999, height_m=40.0, pitch_deg=60.0,
                                                     heading_deg=0.0), 150.0, None)
    assert straddling == (0, 0, 0, 0)
    past = _footprint_cells(GRID, camera, Pose(lat=-16.5, lon=179.99995, height_m=40.0, pitch_deg=30.0,
                                               heading_deg=90.0), 150.0, None)
    assert 0 <= past[0] < 1000 and 0 < past[2] < 2000  # columns just east of the line, in [0, world)
    beside = _footprint_cells(GRID, camera, Pose(lat=-16.5, lon=179.99, height_m=40.0, pitch_deg=60.0,
                                                 heading_deg=270.0), 150.0, None)
    assert 0 < beside[2] < 2000 and 0 < beside[3] < 2000


@pytest.mark.parametrize(("lon", "heading"), [(179.9999, 90.0), (-179.9999, 270.0)])
def test_a_state_footprint_past_the_antimeridian_stays_on_the_uavs_side(lon, heading):
    """A footprint corner at 180.0002 made the state message be refused (the agent stopped); wrapped, the server
    would fill the polygon the long way round the world: held just inside the line instead."""
    from agent.node import state_message

    camera = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)
    pose = Pose(lat=-16.5, lon=lon, height_m=40.0, pitch_deg=60.0, heading_deg=heading)
    message = state_message("uav1", 1.7e9, pose, camera, range_m=150.0)
    lons = [b for _, b in message.footprint]
    assert all(-180.0 < b < 180.0 for b in lons) and all(np.sign(b) == np.sign(lon) for b in lons)


@given(st.floats(-180.0, 179.999), st.lists(st.floats(-1e-3, 1e-3), min_size=1, max_size=5))
def test_a_weighted_mean_of_nearby_longitudes_stays_near_them(base, offsets):
    lons = [((base + d + 180.0) % 360.0) - 180.0 for d in offsets]
    mean = weighted_lon(np.ones(len(lons)), lons)
    assert -180.0 <= mean < 180.0
    assert abs((mean - lons[0] + 180.0) % 360.0 - 180.0) <= 2e-3


def test_a_global_track_seen_on_both_sides_of_the_line_stays_there():
    """Two UAVs' local tracks 0.6 m apart across the antimeridian: the global track was put at longitude 0."""
    tracker = GlobalTracker(clock=lambda: 100.0, wall=lambda: 1.7e9)
    for uav, lon in (("uavA", 179.999997), ("uavB", -179.999997)):
        tracker.update(TracksMessage(uav=uav, t=1.7e9, tracks=(TrackItem(id=1, cls="person", lat=-16.5, lon=lon,
                                                                          score=0.9, vel_en=(0.0, 0.0)),)))
    (record,) = tracker.records()
    assert len(record.members) == 2 and abs(abs(record.lon) - 180.0) < 1e-5


def _tile(values: np.ndarray, x: int, y: int) -> JointTile:
    return JointTile("person", 18, x, y, np.rint(values).astype(np.uint8), 0.0, 1, b"", (), 0.0)


@pytest.mark.parametrize(("lat", "apart_m", "objects"),
                         [(79.0, 0.5, 1), (79.0, 1.5, 2), (48.5, 0.5, 1), (48.5, 1.5, 2)])
def test_objects_of_the_joint_map_are_told_apart_in_metres(lat, apart_m, objects):
    """At 79 deg N a cell is 0.11 m: two cells of suppression left one person as several objects (76 against 11 at
    48.5 deg for the same flight)."""
    gx, gy = GRID.latlon_to_cell_index(np.array([lat]), np.array([15.0]))
    x, y = int(gx[0]) // 256, int(gy[0]) // 256
    cells = apart_m / float(GRID.cell_size_m(lat))
    r, c = np.arange(256)[:, None], np.arange(256)[None, :]
    values = np.zeros((256, 256))
    for col in (100.0, 100.0 + cells):
        values = np.maximum(values, 200.0 * np.exp(-0.5 * ((r - 128) ** 2 + (c - col) ** 2) / 0.6**2))
    assert len(find_peaks([_tile(values, x, y)], GRID, min_score=0.3)) == objects


def test_the_anomaly_layers_dem_map_steps_east_across_the_antimeridian():
    """With longitudes wrapped, 1 m east of a UAV 0.5 m west of the line is at -180: the DEM map took that as a step
    of 360 deg, -3.8e7 columns a metre, and the anomaly layer saw no cell (the fourth read)."""
    from agent.anomaly.terrain_view import TerrainCells
    from shared.terrain import ElevationGrid

    grid = ElevationGrid(np.zeros((10, 10)), lat0_deg=-16.49, lon0_deg=179.99, lat_step_deg=-0.002,
                         lon_step_deg=0.002)
    for lon in (179.99, 179.9999995):
        affine = TerrainCells(grid).local_to_dem(Pose(lat=-16.5, lon=lon, height_m=40.0, pitch_deg=60.0,
                                                      heading_deg=0.0))
        metre = 1.0 / (0.002 * 111_320.0 * np.cos(np.radians(16.5)))
        assert affine[0, 0] == pytest.approx(metre, rel=0.01)

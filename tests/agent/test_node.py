"""The agent's pure parts: tile change detection and byte budget, state/tracks messages, the gid
extension of the tracks message, global id adoption, settings validation."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from agent.global_ids import GlobalIdAdopter
from agent.memory_map import MemoryMap, MemoryMapConfig
from agent.node import AgentSettings, run_first_track_id, state_message, tracks_message
from agent.tile_updates import TileChangeTracker
from agent.tracking import GpsTracker, TrackOutput
from agent.zenoh_io import encode_tracks_with_gid
from shared.geo import Camera, Pose, local_to_latlon
from shared.messages import JointTrackItem, JointTracksMessage, decode_state, decode_tracks, encode_state
from shared.tilecodec import decode_tile
from shared.tiles import TileGrid

GRID = TileGrid()
LAT, LON = 48.53, 9.06
CAMERA = Camera(width=1920, height=1080, fx=1500.0, fy=1500.0, cx=960.0, cy=540.0)
POSE = Pose(lat=LAT, lon=LON, height_m=30.0, pitch_deg=60.0, heading_deg=10.0)


class FakeClock:
    """A settable monotonic clock for the pure classes (they take a clock argument)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def memory_with_blob(value: float = 1.0) -> MemoryMap:
    # the paper's stamp (6 m, summed) so the tile geometry does not follow tuned defaults
    memory = MemoryMap(MemoryMapConfig(radius_m=6.0, stamp="sum"))
    memory.advance(0.0, LAT, LON)
    gx, gy = GRID.latlon_to_cell(LAT, LON)
    memory.add("person", [gx], [gy], [value])
    return memory


# ---- tiles ---------------------------------------------------------------------------------------
def test_tiles_cover_the_whole_window_for_every_class_including_empty_ones():
    clock = FakeClock()
    tracker = TileChangeTracker("uav1", ["person", "swimmer"], GRID, clock=clock)
    memory = memory_with_blob()
    sent = tracker.messages(memory, 1000.0)
    decoded = [decode_tile(payload) for *_, payload in sent]
    people = [m for m in decoded if m.cls == "person"]
    swimmers = [m for m in decoded if m.cls == "swimmer"]
    assert len(people) == len(swimmers) == len(memory.tiles("person")) >= 4
    assert all(m.uav == "uav1" and m.t == 1000.0 and m.z == 18 and m.n == 256 for m in decoded)
    assert sum(m.values.max() > 0 for m in people) >= 1
    assert sum(m.values.max() == 0 for m in people) >= 1  # "I cover this tile and see nothing"
    assert all(m.values.max() == 0 for m in swimmers)
    x, y = (int(v) for v in GRID.tile_of(LAT, LON))
    assert max(m.values.max() for m in people if (m.x, m.y) == (x, y)) == pytest.approx(1.0)


def test_unchanged_tiles_wait_for_the_refresh_and_sequence_numbers_grow_per_tile():
    clock = FakeClock()
    tracker = TileChangeTracker("uav1", ["person"], GRID, refresh_s=1.0, clock=clock)
    memory = memory_with_blob()
    first = {(c, x, y): decode_tile(p).seq for c, x, y, p in tracker.messages(memory, 1.0)}
    clock.now = 0.5
    assert tracker.messages(memory, 1.5) == []  # nothing changed, refresh not due
    gx, gy = GRID.latlon_to_cell(LAT, LON)
    memory.add("person", [gx + 50], [gy], [0.5])  # one tile changes
    changed = tracker.messages(memory, 2.0)
    assert len(changed) == 1
    key = changed[0][:3]
    assert decode_tile(changed[0][3]).seq == first[key] + 1
    clock.now = 1.0
    refreshed = {(c, x, y): decode_tile(p).seq for c, x, y, p in tracker.messages(memory, 2.5)}
    assert set(refreshed) == set(first) - {key}  # the others are refreshed after refresh_s
    assert all(refreshed[k] == first[k] + 1 for k in refreshed)
    assert (tracker.n_changed, tracker.n_refreshed) == (len(first) + 1, len(first) - 1)


def test_min_value_drops_the_gaussian_tails():
    memory = memory_with_blob()
    full = TileChangeTracker("u", ["person"], GRID).messages(memory, 0.0)
    cut = TileChangeTracker("u", ["person"], GRID, min_value=0.2).messages(memory, 0.0)
    nonzero_full = sum(int((decode_tile(p).values > 0).sum()) for *_, p in full)
    nonzero_cut = sum(int((decode_tile(p).values > 0).sum()) for *_, p in cut)
    assert 0 < nonzero_cut < nonzero_full
    assert min(decode_tile(p).values[decode_tile(p).values > 0].min(initial=1) for *_, p in cut) >= 0.2 - 1e-6


def test_byte_budget_defers_tiles_and_sends_the_stalest_first():
    clock = FakeClock()
    budget = 30_000.0  # the empty tiles' refreshes are ~4 kB/s of it
    tracker = TileChangeTracker("u", ["person", "swimmer"], GRID, budget_bytes_per_s=budget, refresh_s=0.5,
                                clock=clock)
    memory = memory_with_blob()
    gx, gy = GRID.latlon_to_cell(LAT, LON)
    diagonal = np.arange(-300, 300, 7.0)
    memory.add("person", gx + diagonal, gy + diagonal, np.ones(len(diagonal)))  # evidence across several tiles
    all_tiles = {(c, x, y) for c in ("person", "swimmer") for x, y, _ in memory.tiles("person")}
    sent_at: dict[tuple, list[float]] = {k: [] for k in all_tiles}
    total = 0
    for _ in range(200):  # 20 s at 10 cycles a second
        for cls, x, y, payload in tracker.messages(memory, clock.now):
            sent_at[(cls, x, y)].append(clock.now)
            total += len(payload)
        clock.now += 0.1
    assert tracker.n_deferred > 0
    # the long-run rate stays within the budget (plus the one second saved up and one tile of overdraft)
    largest = max(len(p) for *_, p in TileChangeTracker("u", ["person"], GRID).messages(memory, 0.0))
    assert total <= budget * (clock.now + 1.0) + largest
    # yet every tile keeps being refreshed, round robin; the empty ones (60 bytes) always on time
    empty = {(cls, x, y) for cls in ("person", "swimmer") for x, y, v in memory.tiles(cls) if v.max() == 0}
    with_evidence = all_tiles - empty
    assert len(with_evidence) >= 3 and len(empty) >= 3
    counts = [len(sent_at[k]) for k in with_evidence]
    assert min(counts) >= 2 and max(counts) - min(counts) <= 2
    for key in empty:
        assert max(np.diff(sent_at[key])) <= 0.5 + 0.1 + 1e-9


def test_budget_must_be_positive():
    with pytest.raises(ValueError, match="budget_bytes_per_s"):
        TileChangeTracker("u", [], GRID, budget_bytes_per_s=0.0)


# ---- state and tracks ------------------------------------------------------------------------------
def test_state_message_has_the_footprint_and_camera():
    msg = decode_state(encode_state(state_message("uav1", 5.0, POSE, CAMERA, range_m=150.0, footprint_points=32)))
    assert (msg.uav, msg.t, msg.lat, msg.lon, msg.height_m, msg.pitch_deg) == ("uav1", 5.0, LAT, LON, 30.0, 60.0)
    assert len(msg.footprint) == 32
    lats = np.array([p[0] for p in msg.footprint])
    assert np.all(np.abs(lats - LAT) < 0.002)  # within ~150 m
    assert (msg.camera.width, msg.camera.fx) == (1920, 1500.0)
    assert 0 <= state_message("u", 0.0, Pose(LAT, LON, 30.0, 60.0, -20.0), CAMERA, range_m=100).heading_deg < 360


def test_state_message_footprint_follows_the_terrain():
    """Over a DEM (`--dem`) the footprint is cast onto the terrain: ground rising ahead ends it sooner."""
    from shared.terrain import ElevationGrid, Terrain
    axis = np.arange(-200.0, 201.0, 2.0)
    _, north = np.meshgrid(axis, axis[::-1])
    grid = ElevationGrid.from_local(300.0 + 0.3 * north, LAT, LON, west_m=-200.0, north_m=200.0, cell_m=2.0)
    pose = Pose(lat=LAT, lon=LON, height_m=30.0, pitch_deg=40.0, heading_deg=0.0)
    flat = state_message("uav1", 1.0, pose, CAMERA, range_m=150.0)
    hilly = state_message("uav1", 1.0, pose, CAMERA, range_m=150.0, terrain=Terrain(grid, 300.0))
    far_flat = max(p[0] for p in flat.footprint)
    far_hilly = max(p[0] for p in hilly.footprint)
    assert far_hilly < far_flat - 10.0 / 111_000  # the far edge is more than 10 m nearer


def track(track_id: int, lat: float, lon: float, *, cls: int = 1, score: float = 1.4, confirmed: bool = True):
    return TrackOutput(track_id, cls, (0.0, 0.0, 1.0, 1.0), lat, lon, (0.5, -0.5), score, confirmed, True)


def test_tracks_message_reports_confirmed_tracks_with_scores_clipped():
    tracks = [track(1, LAT, LON), track(2, LAT, LON, confirmed=False), track(3, float("nan"), float("nan"))]
    msg = tracks_message("uav1", 7.0, tracks, {1: "person"})
    assert [(i.id, i.cls, i.score, i.vel_en) for i in msg.tracks] == [(1, "person", 1.0, (0.5, -0.5))]


def test_gid_extension_decodes_with_the_shared_codec():
    msg = tracks_message("uav1", 7.0, [track(1, LAT, LON), track(2, LAT, LON + 1e-4)], {1: "person"})
    payload = encode_tracks_with_gid(msg, {1: 42})
    raw = msgpack.unpackb(payload)
    assert [t.get("gid") for t in raw["tracks"]] == [42, None]
    decoded = decode_tracks(payload)
    assert [t.id for t in decoded.tracks] == [1, 2] and decoded.uav == "uav1"


# ---- global id adoption ----------------------------------------------------------------------------
def joint(*items: tuple[int, str, float, float, list]) -> JointTracksMessage:
    return JointTracksMessage(t=0.0, tracks=tuple(
        JointTrackItem(gid=g, cls=c, lat=a, lon=b, score=0.9, vel_en=(0.0, 0.0), members=tuple(m))
        for g, c, a, b, m in items))


def offset(east_m: float, north_m: float = 0.0) -> tuple[float, float]:
    lat, lon = local_to_latlon(east_m, north_m, LAT, LON)
    return float(lat), float(lon)


def test_new_local_track_adopts_the_nearest_global_track_of_its_class_within_the_gate():
    clock = FakeClock()
    adopter = GlobalIdAdopter("uav2", gate_m=10.0, window_s=2.0, clock=clock)
    g = joint((7, "person", *offset(3.0), [("uav1", 4)]), (8, "person", *offset(6.0), [("uav1", 5)]),
              (9, "swimmer", *offset(0.5), [("uav1", 6)]), (10, "person", *offset(30.0), []))
    gids = adopter.update([(1, "person", *offset(0.0)), (2, "person", *offset(5.0))], g)
    assert gids == {1: 7, 2: 8}  # each global id once, closest pairs first; the swimmer is another class
    assert adopter.n_adopted_by_position == 2


def test_far_or_late_tracks_do_not_adopt_and_the_server_membership_wins():
    clock = FakeClock()
    adopter = GlobalIdAdopter("uav2", gate_m=10.0, window_s=2.0, clock=clock)
    assert adopter.update([(1, "person", *offset(0.0))], None) == {}
    clock.now = 3.0  # the track is older than the adoption window when global tracks first arrive
    assert adopter.update([(1, "person", *offset(0.0))], joint((7, "person", *offset(1.0), []))) == {}
    adopter2 = GlobalIdAdopter("uav2", gate_m=10.0, clock=clock)
    assert adopter2.update([(1, "person", *offset(0.0))], joint((7, "person", *offset(20.0), []))) == {}
    # the server lists (uav2, 1) as a member of global track 9: that is its id from now on
    assert adopter2.update([(1, "person", *offset(0.0))], joint((9, "person", *offset(20.0), [("uav2", 1)]))) == {1: 9}


def test_a_global_track_already_holding_another_of_our_tracks_is_not_adopted():
    adopter = GlobalIdAdopter("uav2", gate_m=10.0, clock=FakeClock())
    g = joint((7, "person", *offset(1.0), [("uav2", 5)]))
    assert adopter.update([(5, "person", *offset(1.0)), (6, "person", *offset(0.0))], g) == {5: 7}


# ---- settings --------------------------------------------------------------------------------------
@pytest.mark.parametrize(("kwargs", "message"), [
    ({"uav_id": "a/b"}, "uav_id must not contain '/'"),
    ({"uav_id": "joint"}, "reserved"),
    ({"publish_hz": 0}, "publish_hz"),
    ({"speed": -1}, "speed"),
    ({"tile_min_value": 1.0}, "tile_min_value"),
    ({"footprint_points": 30}, "footprint_points"),
    ({"prefix": "a/*"}, "prefix"),
    ({"grid_n": 512}, "n must be in"),
    ({"tile_budget_bytes_per_s": -5.0}, "tile_budget_bytes_per_s"),
])
def test_settings_fail_fast_naming_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        AgentSettings(**{"uav_id": "uav1", **kwargs})


# ---- local track ids unique per run --------------------------------------------------------------
def test_each_run_numbers_its_tracks_from_its_start_time_in_microseconds():
    t_ns = 1_767_225_600_123_456_789  # 2026-01-01
    first = run_first_track_id(t_ns)
    assert first == 1_767_225_600_123_456
    # a restart a second later begins a million ids on: more tracks than any run makes
    assert run_first_track_id(t_ns + 10**9) - first == 10**6
    # ids stay exact as JSON numbers (doubles) on the map page; valid in the tracks message
    assert first + 10**9 < 2**53
    assert 0 <= run_first_track_id() < 2**53


def test_tracker_first_id_rejects_values_outside_the_message_range():
    # disjoint ids per run are pinned by tests/e2e/test_agent_restart.py, ids from 1 by test_track_cli
    for bad in (-1, 2**62, 1.5, True):
        with pytest.raises(ValueError, match="first_id"):
            GpsTracker(first_id=bad)

"""Tables that lived as long as the process: the handover's ids of other shards, the gateway's regions, CoT's ended
tracks, the registry's forgotten ids and the joint map's footprint versions hold only what is still of use."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server import handover as handover_module
from fusion_server.cot import CotSender, CotTarget
from fusion_server.global_tracks import GlobalTracker, TrackRecord
from fusion_server.handover import MEMBER_KEEP_S, POSITION_KEEP_S, Handover
from fusion_server.joint_map import JointMap
from fusion_server.merged_tracks import MergedTracks
from fusion_server.rules import get_fusion_rule
from fusion_server.uav_registry import UavRegistry
from shared.keys import KeySpace, track_region
from shared.messages import JointTrackItem, JointTracksMessage, encode_joint_tracks
from shared.sharding import ShardSpec
from shared.tiles import TileGrid

NOW = 1_790_000_000.0


class Clock:
    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


# ---- handover: other shards' ids ----------------------------------------------------------------------------
class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(data)


def _foreign_region(grid: TileGrid, shard: ShardSpec) -> tuple[int, int, int]:
    xs, ys = grid.tile_of(np.array([48.0]), np.array([9.0]))
    z, x0, y0 = track_region(grid.z, int(xs[0]), int(ys[0]))
    return next((z, x0 + dx, y0) for dx in range(64) if not shard.owns(z, x0 + dx, y0))


def _handover(clock: Clock) -> tuple[Handover, KeySpace, tuple[int, int, int]]:
    keys, grid, shard = KeySpace(), TileGrid(), ShardSpec(index=0, count=2)
    tracker = GlobalTracker(clock=clock)
    return Handover(shard, keys, tracker, grid, clock=clock), keys, _foreign_region(grid, shard)


def _region_sample(keys: KeySpace, region: tuple[int, int, int], t: float, gids: list[int]) -> _Sample:
    items = tuple(JointTrackItem(gid=gid, cls="person", lat=48.0, lon=9.0, score=0.5, vel_en=(0.0, 0.0),
                                 members=(("uav1", gid),)) for gid in gids)
    return _Sample(keys.region_tracks(*region), encode_joint_tracks(JointTracksMessage(t=t, tracks=items)))


def test_handover_keeps_only_the_ids_within_their_windows_and_still_answers():
    clock = Clock()
    handover, keys, region = _handover(clock)
    for second in range(600):  # 10 minutes at 1 Hz; a new object every 10 s, each reported for 10 s
        clock.now = float(second)
        handover.on_region_tracks(_region_sample(keys, region, NOW + second, [1000 + second // 10]))
    assert handover.received == 600
    # before the fix every gid and member of the 10 minutes was kept (60 each) until 200,000 entries
    assert len(handover._recent) <= POSITION_KEEP_S + 1
    assert len(handover._by_member) <= MEMBER_KEEP_S / 10 + 1
    latest = 1000 + 599 // 10
    assert handover.adopt("uav1", latest, "person", 50.0, 9.0) == latest  # by its member
    assert handover.adopt("uav2", 7, "person", 48.0, 9.0) == latest  # by position, the gid seen last
    assert handover.adopt("uav2", 7, "car", 48.0, 9.0) is None
    assert handover.adopt("uav1", 1000, "person", 50.0, 9.0) is None  # 10 minutes old
    clock.now += MEMBER_KEEP_S + 1.0  # the other shard fell silent: asking forgets the rest
    assert handover.adopt("uav1", latest, "person", 48.0, 9.0) is None
    assert (len(handover._recent), len(handover._by_member)) == (0, 0)


def test_handover_max_entries_stays_a_hard_cap(monkeypatch):
    monkeypatch.setattr(handover_module, "MAX_ENTRIES", 5)
    clock = Clock()
    handover, keys, region = _handover(clock)
    handover.on_region_tracks(_region_sample(keys, region, NOW, list(range(1, 13))))
    assert len(handover._recent) == 5 and len(handover._by_member) == 5
    assert set(handover._recent) == set(range(8, 13))  # the oldest forgotten first


# ---- gateway: regions heard ---------------------------------------------------------------------------------
def _item(gid: int) -> JointTrackItem:
    return JointTrackItem(gid=gid, cls="person", lat=48.0, lon=9.0, score=0.5, vel_en=(0.0, 0.0),
                          members=(("uav1", gid),))


def test_merged_tracks_forget_regions_once_stale_and_keep_the_fresh_ones():
    clock = Clock()
    merged = MergedTracks(stale_s=3.0, clock=clock, wall=clock)
    for minute in range(120):  # a UAV over new ground: a new region a minute, an empty message for the last one
        clock.now = 60.0 * minute
        merged.put((16, 1000 + minute, 500), JointTracksMessage(t=clock.now, tracks=(_item(minute + 1),)))
        if minute:
            merged.put((16, 999 + minute, 500), JointTracksMessage(t=clock.now, tracks=()))
    # before the fix all 120 regions were kept (up to 65,536) and walked on every message
    assert len(merged._regions) == 2
    assert merged.regions() == {(16, 1119, 500): 0.0, (16, 1118, 500): 0.0}  # fresh ones, empty or not
    assert [r.gid for r in merged.records()] == [120]
    clock.now += 2.0
    merged.put((16, 5, 5), JointTracksMessage(t=clock.now, tracks=(_item(500),)))
    assert {r.gid for r in merged.records()} == {120, 500}  # 2 s old: still in the view
    clock.now += 2.0
    assert [r.gid for r in merged.records()] == [500]
    assert len(merged._regions) == 1
    ended = {r.gid for r in merged.records(include_ended=True) if r.ended is not None}
    assert 120 in ended
    merged.put((16, 1119, 500), JointTracksMessage(t=clock.now, tracks=(_item(120),)))  # the region is back
    assert {r.gid for r in merged.records()} == {120, 500}


# ---- CoT: ended tracks --------------------------------------------------------------------------------------
def _records(n_ended: int, rows: int) -> GlobalTracker:
    tracker = GlobalTracker()
    history = tuple((NOW + i, 48.0, 9.0) for i in range(rows))
    live = TrackRecord(gid=1, cls="person", lat=48.0, lon=9.0, score=0.7, vel_en=(1.0, 0.0), created=0.0,
                       last_update=1.0, members=(("uav1", 1),), history=history)
    ended = [TrackRecord(gid=g, cls="car", lat=48.0, lon=9.0, score=0.7, vel_en=(0.0, 0.0), created=0.0,
                         last_update=1.0, members=(("uav1", g),), ended=NOW + g, history=history)
             for g in range(2, n_ended + 2)]
    tracker.restore([live, *ended])
    return tracker


def test_cot_takes_records_and_converts_only_what_it_sends_without_history(monkeypatch):
    tracker = _records(n_ended=50, rows=100)
    by_features = CotSender(CotTarget("udp", "127.0.0.1", 9),
                            lambda: [r.to_geojson() for r in tracker.records(include_ended=True)], lambda: [],
                            clock=lambda: NOW)
    expected = by_features.events()
    converted: list[TrackRecord] = []
    to_geojson = TrackRecord.to_geojson

    def counting(record: TrackRecord) -> dict:
        converted.append(record)
        return to_geojson(record)

    monkeypatch.setattr(TrackRecord, "to_geojson", counting)
    sender = CotSender(CotTarget("udp", "127.0.0.1", 9), lambda: tracker.records(include_ended=True), lambda: [],
                       clock=lambda: NOW)
    assert sender.events() == expected  # the same events as from the features
    assert len(converted) == 51 and all(record.history == () for record in converted)
    converted.clear()
    second = sender.events()
    assert len(second) == 1 and [record.gid for record in converted] == [1]  # sent ended tracks: not even built


# ---- the registry's forgotten ids ---------------------------------------------------------------------------
def test_forgotten_uavs_are_bounded_without_a_database():
    clock = Clock()
    registry = UavRegistry(max_uavs=16, clock=clock, wall=lambda: NOW + clock.now)
    for i in range(100):  # a visitor every 5 minutes, forgotten an hour later; nobody drains (--no-db)
        registry.message(f"visitor{i}", "state", 300)
        clock.now += 300.0
        registry.forget_offline(3600.0)
    assert len(registry._uavs) == 12 and len(registry._forgotten) == 64 == registry.max_forgotten
    records, forgotten = registry.drain_changes()
    assert forgotten == sorted(f"visitor{i}" for i in range(88 - 64, 88))  # the newest 64 of the 88 forgotten
    assert [r.id for r in records] == sorted(f"visitor{i}" for i in range(88, 100))
    assert registry.drain_changes() == ([], [])


def test_forgotten_uavs_are_all_drained_when_persistence_keeps_up():
    clock = Clock()
    registry = UavRegistry(max_uavs=4, clock=clock, wall=lambda: NOW + clock.now)
    for i in range(4):
        registry.message(f"uav{i}", "state", 300)
    clock.now += 100.0
    assert sorted(registry.forget_offline(10.0)) == ["uav0", "uav1", "uav2", "uav3"]
    registry.message("uav2", "state", 300)  # back: not forgotten any more
    assert registry.drain_changes()[1] == ["uav0", "uav1", "uav3"]


# ---- the joint map's footprint versions ---------------------------------------------------------------------
GRID = TileGrid(18, 8)
KEY = ("person", 18, 100, 200)


def _layer(value: int) -> np.ndarray:
    return np.full((8, 8), value, dtype=np.uint8)


def _square(col0: float, col1: float) -> np.ndarray:
    """(4, 2) [lat, lon] polygon over KEY's tile columns [col0, col1), all rows."""
    gx = np.array([col0, col1, col1, col0]) + KEY[2] * GRID.n
    gy = np.array([0.0, 0.0, 8.0, 8.0]) + KEY[3] * GRID.n
    lat, lon = GRID.cell_to_latlon(gx, gy)
    return np.column_stack([lat, lon])


def test_a_uav_whose_footprints_go_stale_between_sweeps_leaves_no_version_and_comes_back_right():
    jm = JointMap(GRID, get_fusion_rule("mean"), 2.0, 1000.0, clock=lambda: 0.0, wall=lambda: NOW)
    assert jm.put_footprint("b", _square(4, 8), now=0.0)  # b looks at the right half
    jm.put("a", KEY, _layer(200), t=1.0, seq=1, now=0.5)
    jm.put("b", KEY, _layer(0), t=1.0, seq=1, now=0.5)
    jm.step(now=1.95)  # a sweep of old footprints: b's is still fresh
    assert (jm.get(KEY).values[0, 0], jm.get(KEY).values[0, 7]) == (200, 100)
    jm.put("a", KEY, _layer(210), t=2.0, seq=2, now=2.1)
    jm.step(now=2.1)  # fused before the next sweep: b's footprint went stale, its tile did not
    assert jm.get(KEY).values[0, 0] == 105  # b covers its whole tile again
    assert "b" not in jm._footprints and "b" not in jm._fp_versions  # the version went with the footprints
    assert jm.put_footprint("b", _square(0, 4), now=2.2)  # b back, looking at the left half now
    jm.step(now=2.2)
    values = jm.get(KEY).values
    assert (values[0, 0], values[0, 7]) == (105, 210)  # its new footprint, not a cached mask of the old one


@pytest.mark.parametrize("visitors", [30])
def test_visiting_uavs_leave_no_footprint_versions(visitors):
    grid = TileGrid()
    jm = JointMap(grid, get_fusion_rule("mean"), 2.0, 5.0, clock=lambda: 0.0, wall=lambda: NOW)
    lat, lon = 48.0, 9.0
    x, y = (int(v[0]) for v in grid.tile_of(np.array([lat]), np.array([lon])))
    key = ("person", grid.z, x, y)
    footprint = [(lat - 1e-4, lon - 1e-4), (lat - 1e-4, lon + 1e-4), (lat + 1e-4, lon + 1e-4),
                 (lat + 1e-4, lon - 1e-4)]
    idx, val = np.arange(10, dtype=np.uint16), np.full(10, 100, np.uint8)
    jm.put_many([("resident", key, idx, val, NOW, 1)], now=0.0)
    now = 0.0
    for i in range(1, visitors + 1):  # the audit's reproduction (/tmp/h1/small_leaks.py), a visitor at a time
        jm.put_footprint(f"visitor{i}", footprint, now=now)
        jm.put_many([(f"visitor{i}", key, idx, val, NOW + now, i)], now=now + 0.5)
        jm.step(now=now + 1.95)
        jm.put_many([("resident", key, idx, val, NOW + now + 2.1, i + 1)], now=now + 2.1)
        jm.step(now=now + 2.1)
        now += 300.0
        jm.put_many([("resident", key, idx, val, NOW + now, i + 2)], now=now)
        jm.step(now=now)
    assert jm._fp_versions.keys() <= jm._footprints.keys()
    assert len(jm._fp_versions) == 0

"""JointMap: fusion over the UAVs covering a tile, time to live, rate limit, drop with an empty tile."""

import numpy as np
import pytest

from fusion_server.joint_map import JointMap
from fusion_server.rules import get_fusion_rule
from shared.tilecodec import decode_tile
from shared.tiles import TileGrid

GRID = TileGrid(18, 8)
KEY = ("person", 18, 100, 200)


def layer(value: int) -> np.ndarray:
    return np.full((8, 8), value, dtype=np.uint8)


def make(ttl_s=2.0, max_hz=5.0, rule="mean", **kw) -> JointMap:
    return JointMap(GRID, get_fusion_rule(rule), ttl_s, max_hz, clock=lambda: 0.0, wall=lambda: 1e9, **kw)


def test_mean_where_two_cover_single_value_where_one_covers():
    jm = make()
    a = np.zeros((8, 8), np.uint8)
    a[:, :4] = 100
    b = np.zeros((8, 8), np.uint8)
    b[:, 2:] = 200
    jm.put("a", KEY, a, t=10.0, seq=1, now=0.0)
    jm.put("b", KEY, b, t=11.0, seq=1, now=0.0)
    updates, _ = jm.step(now=0.0)
    assert len(updates) == 1
    tile = updates[0].tile
    assert tile.uavs == ("a", "b")
    # a covers the tile everywhere (with zeros on the right), so the mean halves b's 200 there
    np.testing.assert_array_equal(tile.values[0], [50, 50, 150, 150, 100, 100, 100, 100])
    assert tile.t == 11.0
    msg = decode_tile(updates[0].payload)
    assert (msg.uav, msg.cls, msg.z, msg.x, msg.y, msg.n) == ("joint", "person", 18, 100, 200, 8)
    np.testing.assert_allclose(msg.values, tile.values / 255.0, atol=1e-6)


def test_tile_expires_after_ttl_and_the_drop_is_published_once_as_empty():
    jm = make(ttl_s=2.0)
    jm.put("a", KEY, layer(100), t=1.0, seq=1, now=0.0)
    jm.put("b", KEY, layer(200), t=1.0, seq=1, now=1.0)
    jm.step(now=1.0)
    assert jm.get(KEY).values[0, 0] == 150
    updates, _ = jm.step(now=2.5)  # a's tile (received at 0) expired at 2.0
    assert [u.tile.values[0, 0] for u in updates] == [200]
    updates, _ = jm.step(now=3.5)  # b's expired at 3.0: nobody covers the tile
    assert len(updates) == 1 and updates[0].tile is None
    empty = decode_tile(updates[0].payload)
    assert not empty.values.any()
    assert jm.get(KEY) is None
    assert jm.step(now=10.0)[0] == []


def test_publications_per_tile_are_rate_limited_and_not_lost():
    jm = make(max_hz=5.0)  # a token bucket: 5 per second on average, bursts of 2
    published = []
    for i, now in enumerate([0.0, 0.05, 0.1]):
        jm.put("a", KEY, layer(10 + i), t=float(i), seq=i + 1, now=now)
        updates, next_due = jm.step(now=now)
        published += [(now, int(u.tile.values[0, 0])) for u in updates]
    assert published == [(0.0, 10), (0.05, 11)]
    assert next_due is not None and abs(next_due - 0.2) < 1e-9  # 0.25 tokens at 0.1: 0.75 / 5 Hz to go
    updates, _ = jm.step(now=0.2)
    assert [u.tile.values[0, 0] for u in updates] == [12]
    assert updates[0].pending_since == 0.1


def test_a_tile_updated_at_max_hz_with_jitter_is_never_held_back():
    jm = make(max_hz=5.0)
    for k in range(50):
        now = 0.2 * k + (0.01 if k % 2 else -0.01)
        jm.put("a", KEY, layer(k % 200 + 1), t=float(k), seq=k + 1, now=now)
        assert len(jm.step(now=now)[0]) == 1


def test_unchanged_values_are_not_republished_until_the_refresh_time():
    jm = make(refresh_s=1.0)
    jm.put("a", KEY, layer(10), t=1.0, seq=1, now=0.0)
    first = jm.step(now=0.0)[0][0].tile
    jm.put("a", KEY, layer(10), t=2.0, seq=2, now=0.6)
    assert jm.step(now=0.6)[0] == []
    # a steady map is published again, so agents whose joint layer drops tiles after a TTL keep it
    jm.put("a", KEY, layer(10), t=3.0, seq=3, now=1.2)
    updates = jm.step(now=1.2)[0]
    assert len(updates) == 1 and updates[0].tile.seq > first.seq
    np.testing.assert_array_equal(updates[0].tile.values, first.values)
    jm.put("a", KEY, layer(10), t=4.0, seq=4, now=1.5)
    assert jm.step(now=1.5)[0] == []


def test_refresh_time_must_be_positive():
    with pytest.raises(ValueError, match="refresh_s must be > 0"):
        make(refresh_s=0.0)


def test_stale_and_repeated_tiles_are_refused_and_the_store_is_bounded():
    jm = make(max_uav_tiles=2)
    assert jm.put("a", KEY, layer(10), t=5.0, seq=5, now=0.0) is None
    assert jm.put("a", KEY, layer(10), t=5.0, seq=5, now=0.0) == "stale"
    assert jm.put("a", KEY, layer(10), t=4.0, seq=4, now=0.0) == "stale"
    # an agent restart resets seq but its clock moves on: accepted
    assert jm.put("a", KEY, layer(10), t=6.0, seq=0, now=0.0) is None
    assert jm.put("b", KEY, layer(10), t=1.0, seq=1, now=0.0) is None
    assert jm.put("c", KEY, layer(10), t=1.0, seq=1, now=0.0) == "too_many_tiles"


def test_restored_tiles_are_served_then_dropped_unless_covered():
    jm = make(ttl_s=1.0)
    jm.put("a", KEY, layer(10), t=1.0, seq=1, now=0.0)
    old = jm.step(now=0.0)[0][0].tile
    fresh = make(ttl_s=1.0)
    assert fresh.restore([old], keep_s=3.0, now=0.0) == 1
    assert fresh.get(KEY) is old
    assert fresh.step(now=2.0)[0] == []
    updates, _ = fresh.step(now=3.5)
    assert updates[0].tile is None and fresh.get(KEY) is None


def square(col0: float, row0: float, col1: float, row1: float) -> np.ndarray:
    """(4, 2) [lat, lon] polygon over KEY's tile cells [col0, col1) x [row0, row1) (cell edges)."""
    gx = np.array([col0, col1, col1, col0]) + KEY[2] * GRID.n
    gy = np.array([row0, row0, row1, row1]) + KEY[3] * GRID.n
    lat, lon = GRID.cell_to_latlon(gx, gy)
    return np.column_stack([lat, lon])


def test_a_uav_that_does_not_see_a_cell_does_not_dilute_the_mean_there():
    jm = make()
    jm.put("a", KEY, layer(200), t=1.0, seq=1, now=0.0)
    jm.put("b", KEY, layer(0), t=1.0, seq=1, now=0.0)
    assert jm.put_footprint("b", square(4, 0, 8, 8), now=0.0)  # b looks at the right half only
    jm.step(now=0.0)
    values = jm.get(KEY).values
    np.testing.assert_array_equal(values[:, :4], 200)  # only a covers the left half
    np.testing.assert_array_equal(values[:, 4:], 100)  # both cover the right half: the paper's mean


def test_tile_coverage_and_stale_footprints_count_the_whole_tile():
    jm = make(coverage="tile")
    jm.put("a", KEY, layer(200), t=1.0, seq=1, now=0.0)
    jm.put("b", KEY, layer(0), t=1.0, seq=1, now=0.0)
    assert not jm.put_footprint("b", square(4, 0, 8, 8), now=0.0)
    jm.step(now=0.0)
    np.testing.assert_array_equal(jm.get(KEY).values, 100)

    jm = make(ttl_s=2.0)
    jm.put_footprint("b", square(4, 0, 8, 8), now=0.0)
    jm.put("a", KEY, layer(200), t=1.0, seq=1, now=1.5)
    jm.put("b", KEY, layer(0), t=1.0, seq=1, now=1.5)
    jm.step(now=1.5)
    assert jm.get(KEY).values[0, 0] == 200
    jm.put("a", KEY, layer(210), t=2.0, seq=2, now=2.5)  # b's footprint (received at 0) has expired
    jm.step(now=2.5)
    assert jm.get(KEY).values[0, 0] == 105  # b sent no fresh footprint: it covers its whole tile again


def test_a_new_footprint_fuses_the_tiles_of_that_uav_again_and_bad_polygons_are_ignored():
    jm = make()
    jm.put("a", KEY, layer(200), t=1.0, seq=1, now=0.0)
    jm.put("b", KEY, layer(0), t=1.0, seq=1, now=0.0)
    jm.step(now=0.0)
    assert jm.get(KEY).values[0, 0] == 100
    assert jm.put_footprint("b", square(4, 0, 8, 8), now=1.0)
    updates, _ = jm.step(now=1.0)  # no new tile: the footprint alone changes the joint tile
    assert [u.tile.values[0, 0] for u in updates] == [200]
    assert not jm.put_footprint("b", square(0, 0, 1, 1)[:2], now=1.0)
    assert not jm.put_footprint("b", np.full((4, 2), np.nan), now=1.0)


def test_coverage_masks_and_footprints_are_freed_when_their_tiles_expire():
    # probe: masks per (uav, x, y) were kept after their tiles expired (RSS 993 -> 1,951 MB with two
    # fake UAVs and 3,000 tiles, never returned)
    jm = make(ttl_s=2.0)
    keys = [("person", 18, 100 + i, 200) for i in range(50)]
    for uav in ("a", "b"):
        for key in keys:
            jm.put(uav, key, layer(100), t=1.0, seq=1, now=0.0)
        jm.put_footprint(uav, square(0, 0, 4, 8), now=0.0)
    jm.step(now=0.0)
    stats = jm.stats()
    assert stats["coverage_masks"] == 100 and stats["footprints"] == 2
    jm.step(now=2.5)  # every tile and footprint is older than the TTL
    stats = jm.stats()
    assert (stats["uav_tiles"], stats["coverage_masks"], stats["footprints"]) == (0, 0, 0)
    # footprints of a UAV that never sends a tile are forgotten too
    for i in range(300):
        jm.put_footprint(f"ghost{i}", square(0, 0, 4, 8), now=3.0)
    assert jm.stats()["footprints"] == 300
    jm.step(now=5.5)
    assert jm.stats()["footprints"] == 0


def test_one_uav_cannot_take_the_whole_tile_store():
    jm = make(max_uav_tiles=100, max_tiles_per_uav=10)
    results = [jm.put("flood", ("person", 18, 100 + i, 200), layer(1), t=1.0, seq=1, now=0.0) for i in range(20)]
    assert results.count(None) == 10 and results.count("too_many_tiles") == 10
    assert jm.put("flood", ("person", 18, 100, 200), layer(2), t=2.0, seq=2, now=0.0) is None  # an update fits
    assert jm.put("honest", KEY, layer(50), t=1.0, seq=1, now=0.0) is None
    assert jm.uav_tile_counts() == {"flood": 10, "honest": 1}

"""Sharded fusion (`uavmm fusion --shard K/N`): region ownership, the split of tiles and tracks, and one
global id across a border (handover), with two real fusion servers on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.config import FusionSettings, ZenohOptions
from fusion_server.server import FusionServer
from shared.keys import KeySpace
from shared.sharding import ShardSpec, parse_shard, region_owner
from tests.fusion_server.fake_agent import GRID, LAT, LON, TILE_X, TILE_Y, FakeAgent, blob
from tests.netutil import free_port, wait_until

ZOOM = 16  # regions of 4 x 4 grid tiles, so a walk of a few hundred metres crosses a border


# ---- ownership ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(("text", "message"), [
    ("2", "is not K/N"), ("1/1", "shard index must be in 0..0"), ("-1/2", "is not K/N"),
    ("0/0", "shard count must be in 1..64"), ("0/65", "shard count must be in 1..64"), ("a/b", "is not K/N"),
    ("3/2", "must be in 0..1"),
])
def test_parse_shard_rejects(text, message):
    with pytest.raises(ValueError, match=message):
        parse_shard(text)


def test_parse_shard_and_grid_check():
    assert parse_shard(" 1 / 3 ") == ShardSpec(1, 3)
    with pytest.raises(ValueError, match="finer than the track regions"):
        ShardSpec(0, 2, 17).check_grid(18)
    ShardSpec(0, 2, 16).check_grid(18)
    with pytest.raises(ValueError, match="region zoom 17"):
        FusionSettings(shard_index=0, shard_count=2, region_zoom=17, db_path=None)


@given(st.integers(0, 2**18 - 1), st.integers(0, 2**18 - 1), st.integers(1, 16), st.integers(0, 16))
def test_every_tile_has_one_owner_and_a_region_one(x, y, count, zoom):
    specs = [ShardSpec(k, count, zoom) for k in range(count)]
    owners = [spec.owns(18, x, y) for spec in specs]
    assert sum(owners) == 1
    region = specs[0].region(18, x, y)
    assert region == (zoom, x >> (18 - zoom), y >> (18 - zoom))
    # the track region (zoom 16) of the tile lies in the same shard region, so it has the same owner
    assert specs[0].owner(16, x >> 2, y >> 2) == specs[0].owner(18, x, y) == region_owner(*region, count)


def test_regions_spread_over_shards():
    # a fleet packed into 8 x 8 neighbouring regions still lands on every shard, about evenly
    owners = [region_owner(14, 8600 + i, 5700 + j, 4) for i in range(8) for j in range(8)]
    counts = np.bincount(owners, minlength=4)
    assert counts.min() >= 8, counts


def test_shard_liveliness_keys():
    keys = KeySpace()
    assert keys.shard_alive(1, 3, 14) == "uavmm/v1/fusion/shards/3/1/14"
    assert keys.shard_alive("*", "*") == "uavmm/v1/fusion/shards/*/*/*"
    assert keys.parse_shard_alive("uavmm/v1/fusion/shards/3/1/14") == (1, 3)
    assert keys.parse_shard_token("uavmm/v1/fusion/shards/3/1/14") == (1, 3, 14)
    for bad in ("uavmm/v1/fusion/shards/3/3/14", "uavmm/v1/fusion/shards/3/1", "uavmm/v1/joint/tracks",
                "uavmm/v1/fusion/shards/03/1/14"):
        with pytest.raises(ValueError):
            keys.parse_shard_alive(bad)


# ---- two shards on loopback ------------------------------------------------------------------------------
def _tiles_by_owner(spec: ShardSpec) -> dict[int, tuple[int, int]]:
    """A grid tile near LAT/LON for each shard."""
    found: dict[int, tuple[int, int]] = {}
    for dx in range(0, 64, 4):
        for dy in range(0, 64, 4):
            x, y = TILE_X + dx, TILE_Y + dy
            found.setdefault(spec.owner(GRID.z, x, y), (x, y))
    assert len(found) == spec.count
    return found


@pytest.fixture
def shards(tmp_path):
    """Two shards (0/2 and 1/2, regions of zoom 16): a router listening on a free port, the other
    connected to it; yields (servers, port)."""
    port = free_port()
    servers = []

    def make(index: int) -> FusionServer:
        options = ZenohOptions(
            mode="router", listen=(f"tcp/127.0.0.1:{port if index == 0 else free_port()}",),
            connect=() if index == 0 else (f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
        settings = FusionSettings(zenoh=options, http_port=0, db_path=tmp_path / f"shard{index}.sqlite",
                                  ttl_s=1.0, shard_index=index, shard_count=2, region_zoom=ZOOM,
                                  track_hold_s=5.0)
        server = FusionServer(settings)
        servers.append(server)
        server.start()
        return server

    yield [make(0), make(1)], port
    for server in servers:
        server.close()


def test_each_shard_fuses_only_its_regions(shards):
    (s0, s1), port = shards
    spec = s0.settings.shard
    tiles = _tiles_by_owner(spec)
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        def fused():
            for x, y in tiles.values():
                agent.tile(blob(100, 100), x=x, y=y)
            have = [{(t.x, t.y) for t in s.joint.tiles("person")} for s in (s0, s1)]
            return have if all(have) else None

        have = wait_until(fused, 10.0, "both shards fusing")
        assert have[0] == {tiles[0]} and have[1] == {tiles[1]}

        def skipping():  # both hear the other's tiles and drop them by key
            for x, y in tiles.values():
                agent.tile(blob(100, 100), x=x, y=y)
            return s0.node.skipped > 0 and s1.node.skipped > 0

        wait_until(skipping, 5.0, "both shards dropping the other's tiles")
        assert [{(t.x, t.y) for t in s.joint.tiles("person")} for s in (s0, s1)] == [{tiles[0]}, {tiles[1]}]
        health = s1.cluster_health()
        assert health["shard"] == "1/2" and health["skipped_tiles"] == s1.node.skipped
    finally:
        agent.close()


def _walk_points(spec: ShardSpec, steps: int = 40) -> list[tuple[float, float]]:
    """A walk east from LAT/LON whose first half lies in a region of shard 0 and its second in shard 1."""
    lat = LAT
    lons = LON + np.arange(0, 0.05, 2e-5)
    xs, ys = GRID.tile_of(np.full(lons.shape, lat), lons)
    owners = [spec.owner(GRID.z, int(x), int(y)) for x, y in zip(xs, ys, strict=True)]
    for i in range(1, len(owners)):
        if owners[i - 1] == 0 and owners[i] == 1:
            return [(lat, float(lon)) for lon in lons[i - steps // 2: i + steps // 2]]
    raise AssertionError("no border from shard 0 to shard 1 east of LAT/LON")


def test_track_crossing_a_border_keeps_its_global_id(shards):
    (s0, s1), port = shards
    walk = _walk_points(s0.settings.shard)
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        for lat, lon in walk[: len(walk) // 2]:
            agent.tracks([(7, "person", lat, lon)])
            wait_until(lambda: len(s0.tracker) == 1, 5.0, "shard 0 tracking")
        (gid,) = [r.gid for r in s0.tracker.records()]
        assert gid % 2 == 1 and len(s1.tracker) == 0  # shard 0's ids: 1, 3, 5, ...
        wait_until(lambda: s1.node.handover.received > 0, 5.0, "shard 1 hearing shard 0's regions")
        for lat, lon in walk[len(walk) // 2:]:
            agent.tracks([(7, "person", lat, lon)])
        # shard 1 took the id over; shard 0 ended its copy once shard 1 published it
        wait_until(lambda: [r.gid for r in s1.tracker.records()] == [gid], 5.0, "shard 1 carrying the id")
        wait_until(lambda: len(s0.tracker) == 0, 5.0, "shard 0 handing the id over")
        assert s1.tracker.handovers["in"] == 1 and s0.tracker.handovers["out"] == 1
        ended = [r for r in s0.tracker.records(include_ended=True) if r.gid == gid]
        assert ended and ended[0].ended is not None
    finally:
        agent.close()


def test_new_ids_of_two_shards_never_collide(shards):
    (s0, s1), port = shards
    spec = s0.settings.shard
    tiles = _tiles_by_owner(spec)
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        # far apart objects (beyond the gate), some in each shard's region
        items = []
        for k, (x, y) in tiles.items():
            lat, lon = _center(x, y)
            items += [(10 * k + i, "person", lat + (i - 1) * 1.5e-4, lon) for i in range(3)]  # 17 m apart
        agent.tracks(items)
        wait_until(lambda: len(s0.tracker) + len(s1.tracker) == 6, 5.0, "six tracks over two shards")
        ids0 = {r.gid for r in s0.tracker.records()}
        ids1 = {r.gid for r in s1.tracker.records()}
        assert not ids0 & ids1 and all(g % 2 == 1 for g in ids0) and all(g % 2 == 0 for g in ids1)
    finally:
        agent.close()


def _center(x: int, y: int) -> tuple[float, float]:
    west, south, east, north = GRID.tile_bounds(x, y)
    return 0.5 * (south + north), 0.5 * (west + east)


def test_shard_health_and_metrics_over_http(shards):
    import httpx

    (s0, _), _ = shards
    with httpx.Client(base_url=s0.url.rstrip("/"), timeout=10.0) as http:
        health = http.get("/healthz").json()
        assert health["status"] == "ok" and health["shard"] == "0/2" and health["region_zoom"] == ZOOM
        text = http.get("/metrics").text
    assert "uavmm_fusion_shard_skipped_tiles_total" in text


def test_agent_routes_tiles_to_their_shard_by_bucket(shards):
    """A real AgentLink sees the shards' tokens and puts each tile on its bucket's key: Zenoh delivers
    it to its own shard only (nobody drops anything by key), and the shards fuse their own."""
    from agent.zenoh_config import ZenohOptions as AgentZenoh
    from agent.zenoh_config import agent_zenoh_config
    from agent.zenoh_io import AgentLink
    from shared.tilecodec import TileMessage, encode_tile

    (s0, s1), port = shards
    spec = s0.settings.shard
    tiles = _tiles_by_owner(spec)
    conf = agent_zenoh_config(AgentZenoh(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KeySpace(), "uav-b", GRID)
    assert link.open(timeout_s=10.0)
    try:
        x0, y0 = tiles[0]
        wait_until(lambda: "/shard/16/" in link.tile_key("person", x0, y0), 5.0, "the link seeing the shards")
        key0 = link.tile_key("person", x0, y0)
        assert key0 == KeySpace().uav_bucket_tile("uav-b", ZOOM, spec.bucket(GRID.z, x0, y0), "person", GRID.z, x0, y0)
        assert spec.bucket(GRID.z, x0, y0) % 2 == 0
        skipped = (s0.node.skipped, s1.node.skipped)
        seq = [0]

        def fused():
            messages = []
            for x, y in tiles.values():
                seq[0] += 1
                msg = TileMessage(uav="uav-b", cls="person", z=GRID.z, x=x, y=y, n=GRID.n, t=time.time(),
                                  seq=seq[0], values=blob(100, 100))
                messages.append(("tile", link.tile_key("person", x, y), encode_tile(msg)))
            link.submit(messages)
            have = [{(t.x, t.y) for t in s.joint.tiles("person")} for s in (s0, s1)]
            return have if all(have) else None

        assert wait_until(fused, 10.0, "both shards fusing") == [{tiles[0]}, {tiles[1]}]
        assert (s0.node.skipped, s1.node.skipped) == skipped  # routed by Zenoh, not dropped by the shards
        s1.close()  # the link's router: shard 0 stays; its token keeps the routing on
        time.sleep(0.5)
        assert "/shard/16/" in link.tile_key("person", x0, y0)
        s0.close()  # no shard left: DESIGN.md's plain tile keys again
        wait_until(lambda: link.tile_key("person", x0, y0) == KeySpace().uav_tile("uav-b", "person", GRID.z, x0, y0),
                   5.0, "the plain key once no shard is up")
    finally:
        link.close()


def test_another_uav_across_the_border_adopts_the_id_by_position(shards):
    (s0, s1), port = shards
    walk = _walk_points(s0.settings.shard, steps=2)  # the last point of shard 0, the first of shard 1 (~1.5 m)
    a = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    b = FakeAgent("uav-b", f"tcp/127.0.0.1:{port}")
    try:
        def tracked():
            a.tracks([(3, "person", *walk[0])])
            return [r.gid for r in s0.tracker.records()]

        (gid,) = wait_until(tracked, 5.0, "shard 0 tracking")
        wait_until(lambda: s1.node.handover.received > 0, 5.0, "shard 1 hearing shard 0's regions")
        b.tracks([(99, "person", *walk[1])])  # another UAV, another local id, 1.5 m away across the border
        wait_until(lambda: [r.gid for r in s1.tracker.records()] == [gid], 5.0, "shard 1 adopting by position")
        b.tracks([(99, "person", *walk[1]), (100, "boat", *walk[1])])  # another class: a new id of shard 1
        wait_until(lambda: len(s1.tracker) == 2, 5.0, "a new track")
        (new,) = {r.gid for r in s1.tracker.records()} - {gid}
        assert new % 2 == 0  # shard 1's own series
    finally:
        a.close()
        b.close()

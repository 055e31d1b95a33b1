"""The gateway of a sharded deployment (`uavmm gateway`): the whole map's REST API over two real shards on
loopback, global tracks merged from their regions and published on joint/tracks, shard liveliness and
degraded UAVs, malformed messages dropped and counted."""

from __future__ import annotations

import json
import time

import httpx
import pytest
import zenoh

from fusion_server import schemas
from fusion_server.config import FusionSettings, ZenohOptions
from fusion_server.gateway import Gateway
from fusion_server.merged_tracks import MergedTracks
from fusion_server.server import FusionServer
from shared.keys import KeySpace
from shared.messages import (
    CameraInfo,
    JointTrackItem,
    JointTracksMessage,
    StateMessage,
    decode_joint_tracks,
    encode_state,
)
from shared.sharding import ShardSpec
from tests.fusion_server.fake_agent import GRID, TILE_X, TILE_Y, FakeAgent, blob, client_config
from tests.netutil import free_port, wait_until

ZOOM = 16
KEYS = KeySpace()


def _tiles_by_owner(spec: ShardSpec) -> dict[int, tuple[int, int]]:
    found: dict[int, tuple[int, int]] = {}
    for dx in range(0, 64, 4):
        for dy in range(0, 64, 4):
            x, y = TILE_X + dx, TILE_Y + dy
            found.setdefault(spec.owner(GRID.z, x, y), (x, y))
    assert len(found) == spec.count
    return found


def _center(x: int, y: int) -> tuple[float, float]:
    west, south, east, north = GRID.tile_bounds(x, y)
    return 0.5 * (south + north), 0.5 * (west + east)


def _shard(index: int, port: int, tmp_path, **settings) -> FusionServer:
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port if index == 0 else free_port()}",),
                           connect=() if index == 0 else (f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    server = FusionServer(FusionSettings(zenoh=options, http_port=0, db_path=tmp_path / f"shard{index}.sqlite",
                                         ttl_s=1.0, shard_index=index, shard_count=2, region_zoom=ZOOM, **settings))
    server.start(http=False)
    return server


@pytest.fixture
def cluster(tmp_path):
    """Two shards (0/2 routing on a free port, 1/2 connected to it) and a gateway (a peer connected to
    shard 0, HTTP on a free port); yields (shards, gateway, port)."""
    port = free_port()
    shards = [_shard(0, port, tmp_path)]
    shards.append(_shard(1, port, tmp_path))
    options = ZenohOptions(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=2, region_zoom=ZOOM))
    gateway.start()
    try:
        yield shards, gateway, port
    finally:
        gateway.close()
        for shard in shards:
            shard.close()


def _get(gateway: Gateway, path: str) -> httpx.Response:
    return httpx.get(gateway.url.rstrip("/") + path, timeout=10)


def test_gateway_serves_both_shards_tiles_tracks_and_uavs(cluster):
    (s0, s1), gateway, port = cluster
    tiles = _tiles_by_owner(s0.settings.shard)
    agents = {k: FakeAgent(f"uav-{k}", f"tcp/127.0.0.1:{port}") for k in tiles}
    try:
        wait_until(lambda: gateway.cluster_health()["degraded"] is False, 10.0, "both shards up at the gateway")

        def published():
            for k, (x, y) in tiles.items():
                lat, lon = _center(x, y)
                agents[k].tile(blob(100, 100), x=x, y=y)
                agents[k].state(lat, lon)
                agents[k].tracks([(1, "person", lat, lon)])
            return len(gateway.tracker) == 2 and {(t.x, t.y) for t in gateway.joint.tiles("person")} == set(
                tiles.values())

        wait_until(published, 10.0, "the gateway seeing both shards' tiles and tracks")
        # REST: joint tiles index, objects and a map window of each shard's tile, tracks, UAVs
        index = _get(gateway, "/v1/joint/tiles?cls=person").json()
        assert {(t["x"], t["y"]) for t in index} == set(tiles.values())
        objects = _get(gateway, "/v1/objects?cls=person&min_score=0.3").json()["features"]
        assert len(objects) == 2
        for x, y in tiles.values():
            west, south, east, north = GRID.tile_bounds(x, y)
            body = _get(gateway, f"/v1/map?cls=person&bbox={west},{south},{east},{north}").json()
            assert max(max(row) for row in body["values"]) > 0.5
            png = _get(gateway, f"/v1/tiles/person/18/{x}/{y}.png")
            assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        tracks = _get(gateway, "/v1/tracks").json()["features"]
        gids = sorted(f["properties"]["gid"] for f in tracks)
        assert len(gids) == 2 and gids[0] % 2 != gids[1] % 2  # one id of each shard (K+1+iN)
        rows = wait_until(lambda: [r for r in _get(gateway, "/v1/uavs").json() if r["state"] is not None]
                          if len(_get(gateway, "/v1/uavs").json()) == 2 else None, 5.0, "two UAVs")
        for row in rows:
            schemas.Uav.model_validate(row)
            assert row["online"] and row["degraded"] is False
            assert row["shard"] == int(row["id"].split("-")[1])
        health = _get(gateway, "/healthz").json()
        schemas.Health.model_validate(health)
        assert health["status"] == "ok" and health["shards"]["0"]["status"] == "up"
        assert health["joint_tiles"] == 2 and health["global_tracks"] == 2
        assert health["classes"] == ["person"]
        assert "uavmm_gateway_shards_down 0" in _get(gateway, "/metrics").text
    finally:
        for agent in agents.values():
            agent.close()


def test_gateway_publishes_and_answers_joint_tracks(cluster):
    (s0, s1), gateway, port = cluster
    tiles = _tiles_by_owner(s0.settings.shard)
    listener = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    heard: list[bytes] = []
    sub = listener.declare_subscriber(KEYS.joint_tracks(), lambda s: heard.append(s.payload.to_bytes()))
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        items = [(k, "person", *_center(x, y)) for k, (x, y) in tiles.items()]

        def both():
            agent.tracks(items)
            return heard and len(decode_joint_tracks(heard[-1]).tracks) == 2

        wait_until(both, 10.0, "joint/tracks with the tracks of both shards")
        replies = list(listener.get(KEYS.joint_tracks(), timeout=5.0))
        answers = [r.ok for r in replies if r.ok is not None]
        # the gateway alone answers joint/tracks: shards do not when sharded
        assert len(answers) == 1
        assert {t.gid for t in decode_joint_tracks(answers[0].payload.to_bytes()).tracks} == gateway.tracker.gids()
    finally:
        sub.undeclare()
        agent.close()
        listener.close()


def test_dead_shard_degrades_its_uavs_and_health_and_the_other_keeps_serving(cluster):
    (s0, s1), gateway, port = cluster
    tiles = _tiles_by_owner(s0.settings.shard)
    agents = {k: FakeAgent(f"uav-{k}", f"tcp/127.0.0.1:{port}") for k in tiles}
    try:
        def published():
            for k, (x, y) in tiles.items():
                agents[k].tile(blob(100, 100), x=x, y=y)
                agents[k].state(*_center(x, y))
            return len(gateway.joint.tiles("person")) == 2 and gateway.cluster_health()["degraded"] is False

        wait_until(published, 10.0, "both shards serving")
        s1.close()  # its session ends: its liveliness token goes
        health = wait_until(lambda: (h := _get(gateway, "/healthz").json())["status"] == "degraded" and h, 5.0,
                            "healthz degraded")
        assert health["degraded"] is True and health["down"] == [1]
        assert health["shards"]["1"]["status"] == "down" and health["shards"]["0"]["status"] == "up"
        rows = {r["id"]: r for r in _get(gateway, "/v1/uavs").json()}
        assert rows["uav-1"]["degraded"] is True and rows["uav-0"]["degraded"] is False
        x, y = tiles[0]
        agents[0].tile(blob(100, 100), x=x, y=y)
        time.sleep(gateway.joint.cache_s)
        assert {(t.x, t.y) for t in gateway.joint.tiles("person")} == {tiles[0]}
        assert _get(gateway, f"/v1/tiles/person/18/{x}/{y}.png").status_code == 200
    finally:
        for agent in agents.values():
            agent.close()


def test_gateway_tracks_and_history_are_what_the_shard_itself_answers(tmp_path):
    """Issue 17: through the gateway every track showed as tracked (region messages said nothing of
    which members still report it) and its history started when the gateway did. Now the status comes
    in the region messages and the history from the shards' fusion/tracks queryable: /v1/tracks and
    /v1/history through the gateway are the shard's own answers."""
    port = free_port()
    quick = {"track_history_interval_s": 0.1, "track_hold_s": 60.0, "persist_interval_s": 0.1}
    shards = [_shard(0, port, tmp_path, **quick), _shard(1, port, tmp_path, **quick)]
    tiles = _tiles_by_owner(shards[0].settings.shard)
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    gateway: Gateway | None = None
    try:
        (owner, (x, y)), = [(k, tile) for k, tile in tiles.items() if k == 0]
        lat, lon = _center(x, y)
        for i in range(8):  # 1.6 s of reports before the gateway exists
            agent.tracks([(1, "person", lat + i * 1e-6, lon)])
            time.sleep(0.2)
        shard = shards[owner]
        assert len(shard.tracker.records()[0].history) >= 5
        options = ZenohOptions(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
        gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=2, region_zoom=ZOOM,
                                         track_history_interval_s=0.1))
        started = time.time()
        gateway.start()

        def tracked():
            agent.tracks([(1, "person", lat + 8e-6, lon)])
            features = _get(gateway, "/v1/tracks").json()["features"]
            return len(features) == 1 and features[0]["properties"]["status"] == "tracked" and features[0]

        feature = wait_until(tracked, 10.0, "the track through the gateway")
        assert feature["properties"]["active_members"] == [["uav-a", 1]]
        assert feature["properties"]["history"][0][0] < started - 1.0  # rows from before the gateway
        # the UAV stops reporting: the shard holds the track as lost, and the gateway says so
        wait_until(lambda: _get(gateway, "/v1/tracks").json()["features"][0]["properties"]["status"] == "lost",
                   5.0, "the held track lost through the gateway")

        def same(path: str, own):
            return lambda: (found := _get(gateway, path).json()) == own() or found

        wait_until(same("/v1/tracks", lambda: {"type": "FeatureCollection",
                                               "features": [r.to_geojson() for r in shard.tracker.records()]}),
                   5.0, "/v1/tracks as the shard lists its track")
        from fusion_server.replay import history_window

        t0 = feature["properties"]["history"][2][0]
        for query, since, until in (("", None, None), (f"?since={t0}&until={t0 + 0.5}", t0, t0 + 0.5),
                                    ("?cls=person&rows=true", None, None)):
            wait_until(same(f"/v1/history{query}", lambda s=since, u=until: json.loads(json.dumps(
                history_window(shard.history_tracks(since=s), s, u)))), 5.0, f"/v1/history{query} as the shard's")
        assert gateway.shard_tracks.queries >= 2
        assert "uavmm_gateway_track_queries_total" in _get(gateway, "/metrics").text
    finally:
        agent.close()
        if gateway is not None:
            gateway.close()
        for server in shards:
            server.close()


def test_malformed_region_tracks_and_states_are_dropped_and_counted(cluster):
    _, gateway, port = cluster
    bad = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    try:
        def sent():
            bad.put(KEYS.region_tracks(16, 1, 1), b"\x93not msgpack")
            bad.put(KEYS.uav_state("uav-x"), b"garbage")
            bad.put(KEYS.uav_state("uav-x"), json.dumps({"v": 1}).encode())
            reasons = gateway.metrics.rejected
            return {("region_tracks", "not_msgpack"), ("state", "not_msgpack")} <= set(reasons)

        wait_until(sent, 5.0, "the drops counted by kind")
        assert gateway.zenoh_open() and _get(gateway, "/healthz").status_code == 200
        assert len(gateway.tracker) == 0
    finally:
        bad.close()


# ---- merging without Zenoh ----------------------------------------------------------------------------------
class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _item(gid: int, lon: float) -> JointTrackItem:
    return JointTrackItem(gid=gid, cls="person", lat=47.0, lon=lon, score=0.9, vel_en=(0.0, 0.0),
                          members=(("uav-a", 1),))


def test_status_comes_from_the_region_message_and_an_older_shards_message_reads_as_tracked():
    clock = Clock()
    merged = MergedTracks(stale_s=3.0, clock=clock, wall=clock)
    members = (("uav-a", 1), ("uav-b", 2))
    held = JointTrackItem(3, "person", 47.0, 9.0, 0.9, (0.0, 0.0), members, active=())
    half = JointTrackItem(4, "person", 47.0, 9.1, 0.9, (0.0, 0.0), members, active=(1,))
    old = JointTrackItem(5, "person", 47.0, 9.2, 0.9, (0.0, 0.0), members)  # no active: an older shard
    merged.put((16, 1, 1), JointTracksMessage(t=10.0, tracks=(held, half, old)))
    records = {r.gid: r for r in merged.records()}
    assert [records[g].status for g in (3, 4, 5)] == ["lost", "tracked", "tracked"]
    assert records[4].active == (("uav-b", 2),) and records[5].active == members


def test_merge_newest_message_wins_and_stale_regions_drop_out():
    clock = Clock()
    merged = MergedTracks(stale_s=3.0, clock=clock, wall=clock)
    merged.put((16, 1, 1), JointTracksMessage(t=10.0, tracks=(_item(3, 9.0),)))
    merged.put((16, 2, 1), JointTracksMessage(t=11.0, tracks=(_item(3, 9.1), _item(4, 9.2))))
    records = {r.gid: r for r in merged.records()}
    assert records[3].lon == 9.1 and set(records) == {3, 4}  # the newer region's copy of gid 3
    clock.now += 2.0
    merged.put((16, 1, 1), JointTracksMessage(t=12.0, tracks=(_item(5, 9.3),)))
    clock.now += 2.0  # region (16, 2, 1) is 4 s old now
    assert {r.gid for r in merged.records()} == {5}
    ended = {r.gid: r for r in merged.records(include_ended=True) if r.ended is not None}
    assert set(ended) == {3, 4} and ended[3].status == "ended"
    merged.put((16, 2, 1), JointTracksMessage(t=15.0, tracks=(_item(4, 9.2),)))  # the shard is back
    assert {r.gid for r in merged.records()} == {4, 5}
    assert 4 not in {r.gid for r in merged.records(include_ended=True) if r.ended is not None}
    assert merged.joint_message().tracks == tuple(sorted((_item(4, 9.2), _item(5, 9.3)), key=lambda i: i.gid))


def test_tiles_are_asked_by_key_for_a_small_range_and_cached(cluster):
    (s0, _), gateway, port = cluster
    tiles = _tiles_by_owner(s0.settings.shard)
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        def both():
            for x, y in tiles.values():
                agent.tile(blob(100, 100), x=x, y=y)
            return all(gateway.joint.get(("person", GRID.z, x, y)) is not None for x, y in tiles.values())

        wait_until(both, 10.0, "each shard's tile asked for by key")
        x, y = tiles[1]
        tile = gateway.joint.get(("person", GRID.z, x, y))
        assert tile.values[100, 100] > 200 and tile.uavs == ()
        asked = gateway.joint.queries
        assert gateway.joint.get(("person", GRID.z, x, y)) is tile  # within the cache time: no query
        assert gateway.joint.queries == asked
        assert gateway.joint.get(("person", GRID.z, x + 1, y)) is None and gateway.joint.queries == asked + 1
        found = gateway.joint.tiles_in_range("person", x - 1, x + 1, y - 1, y + 1)  # 9 tiles: by key
        assert [(t.x, t.y) for t in found] == [(x, y)]
    finally:
        agent.close()


@pytest.mark.parametrize(("argv", "message"), [
    (["--shards", "0"], "shard count must be in 1.."),
    (["--shards", "1"], "--shards must be at least 2"),
    (["--shards", "2", "--region-zoom", "17"], "region zoom 17 is finer"),
    (["--shards", "2", "--http", "nohost"], "--http must be HOST:PORT"),
    (["--shards", "2", "--http", "0.0.0.0:0", "--cors-origin", "ftp://x"], "cors_origins"),
])
def test_gateway_cli_rejects_bad_flags(argv, message, capsys, monkeypatch):
    from uavmm.cli import main

    monkeypatch.delenv("UAVMM_HTTP_TOKEN", raising=False)
    assert main(["gateway", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("uavmm gateway: error:") and message in err


def test_gateway_without_shards_is_degraded_and_keeps_its_token():
    from fusion_server.http_auth import HttpToken

    token = "t" * 32
    options = ZenohOptions(mode="peer", listen=(f"tcp/127.0.0.1:{free_port()}",), multicast_scouting=False)
    settings = FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=3, region_zoom=ZOOM,
                              http_tokens=(HttpToken("ops", token),))
    with Gateway(settings) as gateway:
        gateway.start()
        health = _get(gateway, "/healthz").json()  # /healthz needs no token
        assert health["status"] == "degraded" and health["down"] == [0, 1, 2]
        assert {v["status"] for v in health["shards"].values()} == {"down"}
        assert _get(gateway, "/v1/tracks").status_code == 401
        answer = httpx.get(gateway.url + "v1/joint/tiles", headers={"Authorization": f"Bearer {token}"}, timeout=10)
        assert answer.status_code == 200 and answer.json() == []  # nobody to ask: an empty map, at once
        assert gateway.http_denied == {"no_token": 1}


def test_shard_watch_counts_only_its_shard_count():
    from fusion_server.gateway_node import ShardWatch

    clock = Clock()
    watch = ShardWatch(3, wall=clock)
    assert watch.down() == {0, 1, 2} and watch.status()["0"] == {"status": "down", "since": None, "changes": 0}
    watch.token(1, 3, True)
    watch.token(0, 2, True)  # a shard started with --shard 0/2: reported, not counted
    assert watch.down() == {0, 2} and watch.foreign == {"0/2": True}
    clock.now = 200.0
    watch.token(1, 3, False)
    watch.token(1, 3, False)  # a repeated DELETE changes nothing
    assert watch.status()["1"] == {"status": "down", "since": 200.0, "changes": 2}


def test_a_range_across_the_antimeridian_holds_the_tiles_on_both_sides(cluster):
    """x wraps as on a single server (JointMap.tiles_in_range): a range from the last column to one past it holds
    the first column's tile too (the gateway's range stopped at the line, and its /v1/objects missed an object's
    other half)."""
    _, gateway, port = cluster
    side = GRID.tiles_per_side
    y = 2 ** GRID.z * 9 // 20  # ~16 deg S: Fiji's row
    agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{port}")
    try:
        def both():
            for x in (side - 1, 0):
                agent.tile(blob(100, 100), x=x, y=y)
            return all(gateway.joint.get(("person", GRID.z, x, y)) is not None for x in (side - 1, 0))

        wait_until(both, 10.0, "the tiles on both sides of the antimeridian")
        assert sorted(t.x for t in gateway.joint.tiles_in_range("person", side - 1, side, y, y)) == [0, side - 1]
        assert sorted(t.x for t in gateway.joint.tiles_in_range("person", -1, 0, y, y)) == [0, side - 1]
        assert [t.x for t in gateway.joint.tiles_in_range("person", 0, 0, y, y)] == [0]
    finally:
        agent.close()


def test_a_uav_whose_clock_runs_ahead_is_followed_by_the_gateway_as_by_its_shard(cluster):
    """A UAV two minutes ahead: the gateway takes its steady lead as a shard does (it had dropped every state of
    it as t_in_future, so /v1/uavs had no position for it and no shard column)."""
    (s0, _), gateway, port = cluster
    x, y = _tiles_by_owner(s0.settings.shard)[0]
    lat, lon = _center(x, y)
    agent = FakeAgent("uav-ahead", f"tcp/127.0.0.1:{port}")
    camera = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
    try:
        def seen():
            agent.put(KEYS.uav_state(agent.uav), encode_state(StateMessage(
                uav=agent.uav, t=time.time() + 120.0, lat=lat, lon=lon, height_m=40.0, pitch_deg=60.0,
                heading_deg=90.0, footprint=((lat, lon), (lat + 1e-4, lon), (lat, lon + 1e-4)), camera=camera)))
            time.sleep(0.2)
            rows = {r["id"]: r for r in _get(gateway, "/v1/uavs").json()}
            return rows.get("uav-ahead", {}).get("state") and rows["uav-ahead"]

        row = wait_until(seen, 10.0, "the gateway taking the UAV's clock lead")
        assert row["clock_lead_s"] == pytest.approx(120.0, abs=1.0) and row["shard"] == 0
        assert row["state"]["t"] <= time.time() + 1.0  # moved onto the gateway's clock
        assert row["rejected"].get("t_in_future", 0) >= 4  # dropped until the evidence held, as before
        assert schemas.Uav.model_validate(row).clock_leads_s == {"state": pytest.approx(120.0, abs=1.0)}
        openapi = _get(gateway, "/openapi.json").json()["components"]["schemas"]["Uav"]["properties"]
        assert {"clock_lead_s", "clock_leads_s"} <= set(openapi)
    finally:
        agent.close()

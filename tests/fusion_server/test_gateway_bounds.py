"""The gateway (`uavmm gateway`) under load and hostile input: region messages cost what they carry, the tracks,
foreign shard tokens and joint/tracks messages it holds or sends are bounded, and /healthz does not wait for a
shard that does not answer."""

from __future__ import annotations

import threading
import time

import httpx
import pytest
import zenoh

from fusion_server.config import FusionSettings, ZenohOptions
from fusion_server.gateway import Gateway
from fusion_server.gateway_node import ShardWatch
from fusion_server.merged_tracks import MergedTracks
from shared.keys import KeySpace
from shared.messages import MAX_TRACKS, JointTrackItem, JointTracksMessage, decode_joint_tracks, encode_joint_tracks
from tests.fusion_server.fake_agent import client_config
from tests.netutil import free_port, wait_until

ZOOM = 16
KEYS = KeySpace()


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _items(first_gid: int, count: int, members: int = 1, held: bool = False) -> tuple[JointTrackItem, ...]:
    return tuple(JointTrackItem(gid=first_gid + i, cls="person", lat=47.6, lon=9.2 + i * 1e-5, score=0.9,
                                vel_en=(0.0, 0.0), active=() if held else None,
                                members=tuple((f"uav-{m:03d}", first_gid + i) for m in range(members)))
                 for i in range(count))


@pytest.fixture
def lone_gateway():
    """A gateway of 2 shards (none running) routing on a free port, and a client session on it."""
    port = free_port()
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=2, region_zoom=ZOOM))
    gateway.start()
    session = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    try:
        yield gateway, session
    finally:
        session.close()
        gateway.close()


# ---- merging: the cost of a message, the tracks held ------------------------------------------------------------
def _put_cost_s(regions: int, per_region: int = 100, puts: int = 60) -> float:
    """Least mean CPU time of this thread for one put into a view of ``regions`` regions of ``per_region`` tracks (3
    tries): a scaling check (~100 x before the fix, at most 4 x asked), on CPU time so that other processes' load
    (two test workers) does not move it."""
    clock = Clock()
    merged = MergedTracks(clock=clock, wall=clock)
    messages = [JointTracksMessage(t=100.0, tracks=_items(1 + r * per_region, per_region)) for r in range(regions)]
    for r, message in enumerate(messages):
        merged.put((16, r, 0), message)
    best = float("inf")
    for _ in range(3):
        started = time.thread_time()
        for i in range(puts):
            r = i % regions
            clock.now += 1e-3
            merged.put((16, r, 0), JointTracksMessage(t=clock.now, tracks=messages[r].tracks))
        best = min(best, (time.thread_time() - started) / puts)
    return best


def test_a_region_message_costs_its_own_tracks_not_every_region_of_the_map():
    """Each region message merged every track of every region again (under the lock, on the Zenoh thread): with
    10,000 tracks in 100 regions published twice a second, the gateway handled 37 of 202 region messages a second
    and tracks dropped out of its view. A message now costs the tracks it and the region's last message list."""
    few, many = _put_cost_s(2), _put_cost_s(200)
    assert many < 4 * few, f"a put into 200 regions took {many * 1e3:.2f} ms, into 2 regions {few * 1e3:.2f} ms"


def test_merged_view_after_puts_and_stale_regions_is_the_newest_copy_per_gid():
    clock = Clock()
    merged = MergedTracks(stale_s=3.0, clock=clock, wall=clock)
    a, b = (16, 1, 1), (16, 2, 1)
    merged.put(a, JointTracksMessage(t=10.0, tracks=_items(1, 2)))  # gids 1, 2
    merged.put(b, JointTracksMessage(t=11.0, tracks=_items(2, 2)))  # gids 2, 3: the newer copy of 2
    assert {r.gid: r.lon for r in merged.records()} == {1: 9.2, 2: 9.2, 3: 9.2 + 1e-5}
    version = merged.version
    merged.put(a, JointTracksMessage(t=10.0, tracks=_items(1, 2)))  # the same again: nothing changed
    assert merged.version == version
    clock.now += 2.0
    merged.put(a, JointTracksMessage(t=12.0, tracks=_items(1, 1)))  # gid 2 leaves a: b's copy stays
    assert {r.gid: r.lon for r in merged.records()} == {1: 9.2, 2: 9.2, 3: 9.2 + 1e-5}
    clock.now += 2.0  # b is 4 s old: its gids 2 and 3 end
    assert [r.gid for r in merged.records()] == [1]
    assert {r.gid for r in merged.records(include_ended=True) if r.ended is not None} == {2, 3}
    merged.put(b, JointTracksMessage(t=15.0, tracks=_items(3, 1)))  # b is back with gid 3
    assert [r.gid for r in merged.records()] == [1, 3]
    assert {r.gid for r in merged.records(include_ended=True) if r.ended is not None} == {2}
    assert merged._holders.keys() == {1, 3}


def test_tracks_held_over_all_regions_are_bounded_the_regions_heard_longest_ago_forgotten_first():
    """Every track of every region heard within 3 s was kept: 30 regions of 10,000 tracks held 300,000 (567 MB)."""
    clock = Clock()
    merged = MergedTracks(clock=clock, wall=clock, max_tracks=2 * MAX_TRACKS)
    for r in range(5):
        merged.put((16, r, 0), JointTracksMessage(t=100.0 + r, tracks=_items(1 + r * MAX_TRACKS, MAX_TRACKS)))
    assert len(merged) == 2 * MAX_TRACKS and set(merged.regions()) == {(16, 3, 0), (16, 4, 0)}
    assert merged.regions_evicted == 3
    assert len(merged._seen) <= 2 * MAX_TRACKS + 256 and len(merged._holders) == 2 * MAX_TRACKS
    with pytest.raises(ValueError, match="max_tracks"):
        MergedTracks(max_tracks=10)


def test_the_gateway_holds_at_most_twice_the_tracks_its_shards_may_list():
    options = ZenohOptions(mode="peer", multicast_scouting=False)
    gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=3, region_zoom=ZOOM))
    assert gateway.tracker.max_tracks == 2 * MAX_TRACKS * 3
    assert "uavmm_gateway_regions_evicted_total 0" in gateway.prometheus()


def test_shard_tracks_answers_too_old_to_reuse_are_forgotten():
    """Up to 64 answers stayed cached however old (reused for 0.5 s only): 60 distinct /v1/history windows of two
    shards' stored history (200 tracks of 600 rows each) held ~1 GB that nothing would read again."""
    from fusion_server.shard_tracks_client import ShardTracks

    clock = Clock()
    tracks = ShardTracks(KEYS, 2, clock=clock)
    asked: list[object] = []
    tracks._ask = lambda request: asked.append(request) or []  # type: ignore[method-assign]  # answered: no tracks
    for i in range(10):
        assert tracks.stored(None, 1.0e9 + i) == []
    assert tracks.stored(None, 1.0e9) == [] and len(asked) == 10 and len(tracks._cache) == 10  # reused while fresh
    clock.now += 1.0
    assert tracks.live() == []
    assert [request.source for request in tracks._cache] == ["live"]  # the old windows forgotten


# ---- joint/tracks: bounded as a fusion server's ------------------------------------------------------------------
def test_joint_tracks_message_is_bounded_in_bytes_tracked_first_and_the_rest_counted(lone_gateway):
    """The gateway's joint/tracks had no byte bound (a fusion server's is 1 MiB): shard-sized region messages merged
    into 8 MB messages, near what an agent refuses (8 MiB). Now fewer tracks go beyond the bound, tracked ones
    first, and the rest are counted in tracks_left_out as on a fusion server."""
    gateway, session = lone_gateway
    gateway.node.max_tracks_bytes = 20_000
    heard: list[bytes] = []
    sub = session.declare_subscriber(KEYS.joint_tracks(), lambda s: heard.append(s.payload.to_bytes()))
    try:
        held = encode_joint_tracks(JointTracksMessage(t=time.time(), tracks=_items(1, 200, members=4, held=True)))
        tracked = encode_joint_tracks(JointTracksMessage(t=time.time() - 5.0, tracks=_items(1001, 200, members=4)))
        assert len(held) + len(tracked) > 2 * gateway.node.max_tracks_bytes

        def published():
            session.put(KEYS.region_tracks(16, 1, 1), held)
            session.put(KEYS.region_tracks(16, 2, 1), tracked)
            return len(gateway.tracker) == 400 and heard and len(decode_joint_tracks(heard[-1]).tracks) > 0

        wait_until(published, 10.0, "a joint/tracks message of the merged tracks")
        time.sleep(1.2)  # published again at least once a second
        payload = heard[-1]
        message = decode_joint_tracks(payload)
        assert len(payload) <= 20_000 and 0 < len(message.tracks) < 400
        assert all(item.active is None for item in message.tracks)  # the tracked ones (newer held ones left out)
        assert gateway.metrics.tracks_left_out_total >= 400 - len(message.tracks)
        replies = [r.ok for r in session.get(KEYS.joint_tracks(), timeout=5.0) if r.ok is not None]
        assert replies and len(replies[0].payload.to_bytes()) <= 20_000
    finally:
        sub.undeclare()


# ---- region messages stamped in the future ---------------------------------------------------------------------
def _region_put(session: zenoh.Session, region: tuple[int, int, int], t: float, gid: int, lon: float) -> None:
    item = JointTrackItem(gid=gid, cls="person", lat=47.6, lon=lon, score=0.9, vel_en=(0.0, 0.0),
                          members=(("uav-a", 1),))
    session.put(KEYS.region_tracks(*region), encode_joint_tracks(JointTracksMessage(t=t, tracks=(item,))))


def test_a_region_message_stamped_beyond_the_clock_skew_does_not_win_its_ids_and_is_counted(lone_gateway):
    """The newest region message wins a global id: one message of any peer without the ACL (or of a shard whose
    clock runs an hour ahead) stamped an hour ahead showed its copy of the id at the gateway for 3 s, the honest
    shard's copy out of the view (for good when sent again each second). A region message whose t is more than
    --max-clock-skew-s ahead of the gateway's clock is now dropped and counted (t_in_future), as a UAV's state is."""
    gateway, session = lone_gateway
    honest, forged = (16, 1, 1), (16, 2, 1)

    def seen() -> bool:
        _region_put(session, honest, time.time(), 7, 9.2)
        return {r.gid: r.lon for r in gateway.tracker.records()} == {7: 9.2}

    wait_until(seen, 10.0, "the honest shard's copy of gid 7")
    for t in (time.time() + 3600.0, 1e300):
        _region_put(session, forged, t, 7, 10.0)
        _region_put(session, forged, t, 8, 10.0)
    wait_until(lambda: gateway.metrics.rejected.get(("region_tracks", "t_in_future"), 0) >= 4, 5.0,
               "the messages ahead counted")
    _region_put(session, honest, time.time(), 7, 9.2)
    wait_until(lambda: gateway.metrics.rejected.get(("region_tracks", "t_in_future"), 0) >= 4
               and gateway.tracker.regions().keys() == {honest}, 5.0, "the honest region heard again")
    assert {r.gid: r.lon for r in gateway.tracker.records()} == {7: 9.2}
    assert all(item.lon == 9.2 for item in gateway.tracker.joint_message().tracks)
    assert 'uavmm_fusion_rejected_total{kind="region_tracks",reason="t_in_future"} 4' in gateway.prometheus()


def test_a_shard_whose_clock_is_ahead_within_the_skew_keeps_its_tracks_at_the_gateway(lone_gateway):
    """The bound on region messages ahead leaves a shard whose clock runs a little ahead (20 s of the 30 s skew)
    working as before: its tracks are merged, and its newer copy wins an id two regions list during a handover."""
    gateway, session = lone_gateway

    def merged() -> bool:
        _region_put(session, (16, 1, 1), time.time(), 7, 9.2)
        _region_put(session, (16, 2, 1), time.time() + 20.0, 7, 9.3)
        return {r.gid: r.lon for r in gateway.tracker.records()} == {7: 9.3}

    wait_until(merged, 10.0, "the copy of the shard 20 s ahead")
    assert ("region_tracks", "t_in_future") not in gateway.metrics.rejected


def test_a_late_join_answer_stamped_beyond_the_clock_skew_is_dropped_too():
    """The region messages a gateway asks for when it starts pass the same bound as those it hears."""
    port = free_port()
    peer = zenoh.open(client_config(f"tcp/127.0.0.1:{port}", extra={"listen/endpoints": [f"tcp/127.0.0.1:{port}"],
                                                                    "connect/endpoints": []}))
    future = encode_joint_tracks(JointTracksMessage(t=time.time() + 3600.0, tracks=_items(7, 1)))
    answer = peer.declare_queryable(KEYS.region_tracks_all(),
                                    lambda query: query.reply(KEYS.region_tracks(16, 2, 1), future))
    options = ZenohOptions(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=2, region_zoom=ZOOM))
    try:
        gateway.start(http=False)
        assert (gateway.metrics.rejected.get(("region_tracks", "t_in_future")), len(gateway.tracker)) == (1, 0)
    finally:
        gateway.close()
        answer.undeclare()
        peer.close()


# ---- shard tokens of other deployments ---------------------------------------------------------------------------
def test_foreign_shard_tokens_are_bounded_and_gone_ones_forgotten_first():
    """Every token of another shard count stayed listed, gone or not: 20,000 of them made /healthz 398 kB."""
    watch = ShardWatch(2, 14)
    watch.token(0, 3, True, 14)  # a live misconfigured shard
    for i in range(1000):
        watch.token(i, 1000, True, 14)
        watch.token(i, 1000, False, 14)
    assert len(watch.foreign) == 64 and watch.foreign_forgotten == 1000 + 1 - 64
    assert watch.foreign["0/3"] is True  # the live one stays, gone ones went first


def test_a_shard_of_another_region_zoom_is_foreign_not_up(lone_gateway):
    """A shard started with another --region-zoom split the map differently, yet the gateway counted it up
    (status ok) and placed UAVs on shards by its own zoom. Now it is listed in foreign_shards and logged."""
    gateway, session = lone_gateway
    tokens = [session.liveliness().declare_token(KEYS.shard_alive(k, 2, ZOOM - 2)) for k in (0, 1)]
    try:
        health = wait_until(lambda: (h := httpx.get(gateway.url + "healthz", timeout=10).json()).get(
            "foreign_shards") and len(h["foreign_shards"]) == 2 and h, 5.0, "the tokens as foreign")
        assert health["foreign_shards"] == {f"0/2 zoom {ZOOM - 2}": True, f"1/2 zoom {ZOOM - 2}": True}
        assert health["status"] == "degraded" and health["down"] == [0, 1]
        good = session.liveliness().declare_token(KEYS.shard_alive(0, 2, ZOOM))
        wait_until(lambda: gateway.shards.down() == {1}, 5.0, "the shard of the right zoom up")
        good.undeclare()
    finally:
        for token in tokens:
            token.undeclare()


# ---- /healthz and a shard that does not answer ----------------------------------------------------------------
def test_healthz_does_not_wait_for_a_joint_tiles_query_nobody_answers(lone_gateway):
    """A queryable that never answers (a shard cut off until its lease ends, a peer's) held /healthz 4 s: its two
    summaries (classes, tile count) each asked the shards again, 2 s each. Now a summary waits at most 0.5 s
    and then gives the last answer, the query going on in the background; threads waiting for a query take its
    answer."""
    gateway, session = lone_gateway
    queries: list[zenoh.Query] = []
    silent = session.declare_queryable(KEYS.joint_tiles_all(), queries.append)
    try:
        time.sleep(0.3)
        # the first ever summary waits for its whole query (classes(): a gateway just started would otherwise answer
        # /v1/objects with nothing while a shard is slow); after that, at most 0.5 s; the tile count right after
        # the class list takes the answer that just ended, not a new query
        assert gateway.joint.classes() == set()
        asked = gateway.joint.queries
        assert gateway.joint.stats()["joint_tiles"] == 0 and gateway.joint.queries == asked
        assert httpx.get(gateway.url + "healthz", timeout=10).status_code == 200
        time.sleep(2.2)
        for attempt in range(2):
            asked = gateway.joint.queries
            started = time.monotonic()
            health = httpx.get(gateway.url + "healthz", timeout=10)
            took = time.monotonic() - started
            assert health.status_code == 200 and took < 1.5, f"/healthz took {took:.2f} s (attempt {attempt})"
            assert gateway.joint.queries - asked <= 1
            time.sleep(2.2)
        # a request that needs the tiles waits for the query running in the background, not for one more
        httpx.get(gateway.url + "healthz", timeout=10)
        asked = gateway.joint.queries
        assert httpx.get(gateway.url + "v1/joint/tiles", timeout=10).json() == []
        assert gateway.joint.queries == asked  # it took the running query's answer, asked nothing more
    finally:
        silent.undeclare()
    gateway.close()
    assert not [t for t in threading.enumerate() if t.name == "uavmm-gateway-joint"]


def test_close_ends_a_tile_query_a_silent_shard_holds(lone_gateway):
    """Probe: a /v1/tiles request waiting on a queryable that never answers (a frozen shard) held the gateway's
    SIGTERM for the query's 2 s: the wait iterated Zenoh's handler, which close() could not end. Now it ends within
    0.1 s of close(), with the tiles come so far (none); without close() the query still runs to its timeout."""
    gateway, session = lone_gateway
    held: list[zenoh.Query] = []  # a query dropped is answered (finished); held, it waits for its timeout
    silent = session.declare_queryable(KEYS.joint_tiles_all(), held.append)
    try:
        time.sleep(0.3)
        key = ("person", gateway.joint.grid.z, 5, 5)
        started = time.monotonic()
        assert gateway.joint.get(key) is None
        assert time.monotonic() - started >= 1.5  # the query ran to its timeout: nobody answered
        found: list = []
        waiting = threading.Thread(target=lambda: found.append(gateway.joint.get(("person", gateway.joint.grid.z,
                                                                                  6, 6))))
        waiting.start()
        time.sleep(0.3)
        started = time.monotonic()
        gateway.joint.close()
        waiting.join(5.0)
        assert not waiting.is_alive() and found == [None]
        assert time.monotonic() - started < 0.6
        asked = gateway.joint.queries
        assert gateway.joint.get(("person", gateway.joint.grid.z, 7, 7)) is None
        assert gateway.joint.queries == asked  # closed: asks nothing more, waits for nothing
    finally:
        silent.undeclare()


# ---- the command line ------------------------------------------------------------------------------------------
def test_gateway_cli_takes_the_tracks_rate_and_clock_skew_of_the_docs(monkeypatch):
    import argparse

    from uavmm import cmd_gateway

    parser = argparse.ArgumentParser()
    cmd_gateway.register(parser.add_subparsers())
    args = parser.parse_args(["gateway", "--shards", "2", "--tracks-max-hz", "2", "--max-clock-skew-s", "60"])
    settings = cmd_gateway.settings_from_args(args)
    assert settings.tracks_max_hz == 2.0 and settings.max_clock_skew_s == 60.0


@pytest.mark.parametrize(("argv", "message"), [
    (["--tracks-max-hz", "0"], "tracks_max_hz must be a finite number > 0"),
    (["--max-clock-skew-s", "nan"], "max_clock_skew_s must be a finite number > 0"),
])
def test_gateway_cli_rejects_bad_rates(argv, message, capsys, monkeypatch):
    from uavmm.cli import main

    monkeypatch.delenv("UAVMM_HTTP_TOKEN", raising=False)
    assert main(["gateway", "--shards", "2", *argv]) == 2
    assert message in capsys.readouterr().err


def test_gateway_serves_the_basemap_as_a_fusion_server_does(tmp_path):
    """The gateway serves the fusion server's page and routes, but ignored the basemap (no --basemap; /v1/basemap.json
    was 404 where a fusion server with the same settings answered)."""
    import argparse

    from tests.fusion_server.fake_agent import GRID
    from tests.fusion_server.test_basemap import LAT, LON, make_mbtiles
    from uavmm import cmd_gateway

    path = make_mbtiles(tmp_path / "ortho.mbtiles")
    parser = argparse.ArgumentParser()
    cmd_gateway.register(parser.add_subparsers())
    args = parser.parse_args(["gateway", "--shards", "2", "--http", "127.0.0.1:0", "--no-multicast-scouting",
                              "--listen", f"tcp/127.0.0.1:{free_port()}", "--basemap", str(path)])
    with Gateway(cmd_gateway.settings_from_args(args)) as gateway:
        gateway.start()
        with httpx.Client(base_url=gateway.url.rstrip("/"), timeout=10) as http:
            assert http.get("/v1/basemap.json").json() == {"url": "/v1/basemap/{z}/{x}/{y}", "minzoom": 14,
                                                            "maxzoom": 19, "attribution": "test orthophoto",
                                                            "local": True}
            x, y = (int(v) for v in GRID.tile_of(LAT, LON))
            tile = http.get(f"/v1/basemap/{GRID.z}/{x}/{y}")
            assert tile.status_code == 200 and tile.headers["content-type"] == "image/png"
    assert gateway.basemap is None  # its file closed


def test_a_gateway_just_started_lists_the_classes_of_a_shard_that_answers_slowly(lone_gateway):
    """The summaries' 0.5 s bound made a gateway just started list no class (and /v1/objects without cls answer
    nothing) while a shard took 1.2 s: before any answer, the class list waits for the whole query (review)."""
    import numpy as np

    from shared.tilecodec import TileMessage, encode_tile
    from tests.fusion_server.fake_agent import GRID, TILE_X, TILE_Y

    gateway, session = lone_gateway
    payload = encode_tile(TileMessage(uav="joint", cls="person", z=GRID.z, x=TILE_X, y=TILE_Y, n=GRID.n,
                                      t=time.time(), seq=1, values=np.full((GRID.n, GRID.n), 0.5, np.float32)))

    def slow(query: zenoh.Query) -> None:
        time.sleep(1.2)
        query.reply(KEYS.joint_tile("person", GRID.z, TILE_X, TILE_Y), payload)

    shard = session.declare_queryable(KEYS.joint_tiles_all(), slow)
    try:
        time.sleep(0.3)
        assert gateway.joint.classes() == {"person"}
    finally:
        shard.undeclare()


def test_a_region_message_stamped_ahead_within_the_skew_wins_nothing_over_a_copy_heard_after_it():
    """Review of 30 Nov 2026: a forged copy stamped 29 s ahead (inside the 30 s skew) was shown 16 of 16 times
    against an honest shard publishing at 4 Hz, and held the id's history back for 29 s. A message's time is now
    its t or its arrival, whichever is earlier."""
    merged = MergedTracks()
    honest = (16, 1, 1)
    forged = (16, 2, 1)
    merged.put(honest, JointTracksMessage(t=time.time(), tracks=_items(7, 1)))
    merged.put(forged, JointTracksMessage(t=time.time() + 29.0, tracks=(
        JointTrackItem(gid=7, cls="person", lat=10.0, lon=10.0, score=0.9, vel_en=(0.0, 0.0), members=(("x", 1),)),
    )))
    assert {r.gid: r.lat for r in merged.records()} == {7: 10.0}  # heard last, it is the newest for now
    time.sleep(0.01)
    merged.put(honest, JointTracksMessage(t=time.time(), tracks=_items(7, 1)))
    assert {r.gid: r.lat for r in merged.records()} == {7: 47.6}  # the honest copy heard after it wins
    (record,) = merged.records()
    assert all(t <= time.time() for t, _, _ in record.history)  # no row from the future

"""An agent receives the joint tiles and tracks of its window only: the fleet's others never cross its link."""

from __future__ import annotations

import time

import numpy as np
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from agent.joint_window import window_tiles
from agent.zenoh_config import ZenohOptions, agent_zenoh_config
from agent.zenoh_io import AgentLink
from shared.keys import track_region
from shared.messages import JointTrackItem, JointTracksMessage, encode_joint_tracks
from shared.tilecodec import encode_tile_sparse
from tests.agent.test_node_bandwidth import ByteCountingRelay
from tests.agent.test_node_zenoh import GRID, KEYS, FakeServer
from tests.netutil import free_port, wait_until

X0, Y0 = 137_700, 91_400


@given(gx0=st.integers(0, 2**26), gy0=st.integers(0, 2**26), size=st.integers(1, 2000), margin=st.integers(0, 2),
       n=st.sampled_from([8, 256]))
def test_window_tiles_cover_every_cell_of_the_window_and_the_margin_only(gx0, gy0, size, margin, n):
    tiles = window_tiles((gx0, gy0), size, n, margin)
    for gx, gy in [(gx0, gy0), (gx0 + size - 1, gy0), (gx0, gy0 + size - 1), (gx0 + size - 1, gy0 + size - 1)]:
        assert (gx // n, gy // n) in tiles
    xs = sorted({x for x, _ in tiles})
    ys = sorted({y for _, y in tiles})
    assert xs[0] == max(gx0 // n - margin, 0) and xs[-1] == (gx0 + size - 1) // n + margin
    assert ys[0] == max(gy0 // n - margin, 0) and ys[-1] == (gy0 + size - 1) // n + margin
    assert len(tiles) == len(xs) * len(ys)


def _joint(x: int, y: int, seq: int, cells: int) -> bytes:
    idx = np.arange(cells)
    return encode_tile_sparse("joint", "person", GRID.z, x, y, GRID.n, time.time(), seq, idx, np.full(cells, 200))


def test_only_the_window_tiles_reach_the_agent_and_the_others_stay_off_its_link():
    port = free_port()
    server = FakeServer(port, shared_memory=False)
    relay = ByteCountingRelay(port)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{relay.port}",), multicast_scouting=False,
                                           cfg=("transport/shared_memory/enabled:false",)))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    try:
        assert link.open(timeout_s=10.0)
        link.set_joint_window({(X0, Y0), (X0 + 1, Y0)})
        time.sleep(1.0)  # the subscriptions reach the router
        down_before = relay.down
        far = [(X0 + 10 + i, Y0 + 10) for i in range(20)]
        for seq in range(1, 4):
            for x, y in far:  # the rest of the fleet's map: 20 tiles of ~20 kB
                server.put(KEYS.joint_tile("person", GRID.z, x, y), _joint(x, y, seq, 10_000))
            server.put(KEYS.joint_tile("person", GRID.z, X0, Y0), _joint(X0, Y0, seq, 100))
        got = wait_until(lambda: link.drain_joint_tiles(), 10.0, "the window's joint tile")
        time.sleep(0.5)
        got += link.drain_joint_tiles()
        assert {(u.x, u.y) for u in got} == {(X0, Y0)}
        assert relay.down - down_before < 20_000  # 60 far tiles (1.2 MB) were not sent to it

        link.set_joint_window(None)  # every joint tile again
        time.sleep(1.0)
        x, y = far[0]
        server.put(KEYS.joint_tile("person", GRID.z, x, y), _joint(x, y, 9, 100))
        got = wait_until(lambda: link.drain_joint_tiles(), 10.0, "a joint tile outside the window")
        assert {(u.x, u.y) for u in got} == {(x, y)}
        assert link.stats()["counts"]["joint_window_changes"] == 2
    finally:
        link.close()
        relay.close()
        server.close()


def _tracks(gids: range, lat: float) -> bytes:
    return encode_joint_tracks(JointTracksMessage(t=time.time(), tracks=tuple(
        JointTrackItem(g, "person", lat, 9.27, 0.9, (0.0, 0.0), (("uav2", g),)) for g in gids)))


def test_only_the_track_regions_of_the_window_reach_the_agent():
    port = free_port()
    server = FakeServer(port, shared_memory=False)
    relay = ByteCountingRelay(port)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{relay.port}",), multicast_scouting=False,
                                           cfg=("transport/shared_memory/enabled:false",)))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    near = track_region(GRID.z, X0, Y0)
    far = track_region(GRID.z, X0 + 64, Y0)
    try:
        assert link.open(timeout_s=10.0)
        link.set_joint_window({(X0, Y0)})
        time.sleep(1.0)
        down_before = relay.down
        for _ in range(3):
            server.put(KEYS.joint_tracks(), _tracks(range(1, 2001), 47.0))  # the whole fleet's
            server.put(KEYS.region_tracks(*far), _tracks(range(100, 2000), 47.1))
            server.put(KEYS.region_tracks(*near), _tracks(range(1, 4), 47.67))
        wait_until(lambda: link.stats()["counts"].get("joint_tracks", 0) >= 3, 10.0, "the near region's tracks")
        time.sleep(0.5)
        msg, age = link.joint_tracks()
        assert [t.gid for t in msg.tracks] == [1, 2, 3] and age < 3.0
        assert relay.down - down_before < 20_000  # the global and the far region's (~1 MB) stayed away
    finally:
        link.close()
        relay.close()
        server.close()


def test_only_the_states_forwarded_to_the_window_regions_reach_the_agent():
    port = free_port()
    server = FakeServer(port, shared_memory=False)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    near = track_region(GRID.z, X0, Y0)
    far = track_region(GRID.z, X0 + 64, Y0)
    try:
        assert link.open(timeout_s=10.0)
        link.set_joint_window({(X0, Y0)})
        time.sleep(1.0)
        for _ in range(3):
            server.put(KEYS.region_state(*near, "uav2"), _state("uav2"))
            server.put(KEYS.region_state(*far, "uav3"), _state("uav3"))
            server.put(KEYS.uav_state("uav4"), _state("uav4"))  # not subscribed with a window
        got = wait_until(lambda: link.drain_footprints(), 10.0, "the near UAV's footprint")
        time.sleep(0.5)
        got += link.drain_footprints()
        assert {f.uav for f in got} == {"uav2"}
    finally:
        link.close()
        server.close()


def _state(uav: str) -> bytes:
    from shared.messages import CameraInfo, StateMessage, encode_state

    camera = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
    return encode_state(StateMessage(uav, time.time(), 47.67, 9.27, 40.0, 60.0, 90.0,
                                     ((47.67, 9.27), (47.6701, 9.27), (47.67, 9.2701)), camera))


def test_a_tile_entering_the_window_is_fetched_at_once_from_the_queryable():
    port = free_port()
    server = FakeServer(port, shared_memory=False)
    held = {(x, y): _joint(x, y, 1, 50) for x, y in [(X0, Y0), (X0 + 1, Y0), (X0 + 30, Y0)]}

    def on_query(query: zenoh.Query) -> None:  # the fusion server's late-join queryable, in short
        for (x, y), payload in held.items():
            key = KEYS.joint_tile("person", GRID.z, x, y)
            if query.key_expr.intersects(key):
                query.reply(key, payload)

    queryable = server.session.declare_queryable(KEYS.joint_all(), on_query)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    try:
        assert link.open(timeout_s=10.0)
        link.set_joint_window({(X0, Y0)})  # the first window: the start-up query has brought the map
        time.sleep(0.5)
        assert link.drain_joint_tiles() == []
        link.set_joint_window({(X0, Y0), (X0 + 1, Y0)})  # (X0 + 1, Y0) enters the window
        got = wait_until(lambda: link.drain_joint_tiles(), 10.0, "the tile that entered the window")
        time.sleep(0.3)
        got += link.drain_joint_tiles()
        assert {(u.x, u.y) for u in got} == {(X0 + 1, Y0)}
    finally:
        link.close()
        queryable.undeclare()
        server.close()

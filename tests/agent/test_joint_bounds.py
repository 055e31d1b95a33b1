"""The agent's joint side under hostile input (issue 19): forged joint tiles from the future do not
block the server's real ones, and the joint tiles an agent holds are capped (link and layer)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from agent.memory_map import JointLayer
from agent.zenoh_config import ZenohOptions, agent_zenoh_config
from agent.zenoh_io import AgentLink
from shared.tilecodec import MAX_SEQ, TileMessage, encode_tile
from tests.agent.test_node_zenoh import GRID, KEYS, FakeServer
from tests.netutil import free_port, wait_until

X, Y = 137_000, 91_000


def joint_tile(value: float, *, x: int = X, t: float | None = None, seq: int = 1) -> tuple[str, bytes]:
    values = np.full((GRID.n, GRID.n), value, np.float32)
    msg = TileMessage(uav="joint", cls="person", z=GRID.z, x=x, y=Y, n=GRID.n,
                      t=time.time() if t is None else t, seq=seq, values=values)
    return KEYS.joint_tile("person", GRID.z, x, Y), encode_tile(msg)


@pytest.fixture
def link_and_server():
    port = free_port()
    server = FakeServer(port)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID, max_joint_tiles=20)
    assert link.open(timeout_s=20.0)
    time.sleep(0.3)  # the subscriber reaches the router
    yield link, server
    link.close()
    server.close()


def held_value(link: AgentLink) -> float | None:
    updates = {(u.x, u.y): u for u in link.drain_joint_tiles()}
    return float(updates[(X, Y)].values[0, 0]) if (X, Y) in updates else None


@pytest.mark.parametrize(("t_ahead_s", "seq"), [(1e300, MAX_SEQ), (20.0, MAX_SEQ)])
def test_a_forged_joint_tile_does_not_block_the_servers_real_updates(link_and_server, t_ahead_s, seq):
    # probe: a joint tile with seq 2**64-1 and t 1e300 (65,536 cells at 1.0) replaced an agent's
    # joint tile and the server's real updates were rejected as stale for 3.5 s
    link, server = link_and_server
    server.put(*joint_tile(0.2, seq=100))
    assert wait_until(lambda: held_value(link)) == pytest.approx(0.2, abs=0.01)
    t = 1e300 if t_ahead_s == 1e300 else time.time() + t_ahead_s
    server.put(*joint_tile(1.0, t=t, seq=seq))
    if t_ahead_s == 1e300:  # beyond any clock skew: never taken
        wait_until(lambda: link.stats()["rejected"].get("t_in_future", 0) == 1)
    else:  # plausible: taken, but it holds the slot for at most the reorder window (1 s)
        assert wait_until(lambda: held_value(link)) == pytest.approx(1.0)
        time.sleep(1.1)
    server.put(*joint_tile(0.4, seq=101))
    assert wait_until(lambda: held_value(link)) == pytest.approx(0.4, abs=0.01)


def test_the_link_holds_at_most_max_joint_tiles(link_and_server):
    # probe: an agent given 2,000 joint tiles grew 339 -> 870 MB (no cap)
    link, server = link_and_server
    for i in range(60):
        server.put(*joint_tile(0.5, x=X + i, seq=i + 1))
    wait_until(lambda: link.stats()["counts"].get("joint_tiles", 0) == 60)
    stats = link.stats()
    assert stats["joint_tiles_held"] == 20 and stats["counts"]["joint_tiles_evicted"] == 40
    kept = sorted(u.x - X for u in link.drain_joint_tiles())
    assert kept == list(range(40, 60))  # the newest survive


def test_the_joint_layer_holds_at_most_max_tiles_newest_first():
    layer = JointLayer(GRID, ttl_s=3.0, max_tiles=5)
    values = np.zeros((GRID.n, GRID.n), np.float32)
    for i in range(12):
        layer.update("person", X + i, Y, values, t=100.0 + i)
    layer.update("person", X + 8, Y, values + 0.5, t=200.0)  # an update moves a tile to the newest end
    layer.update("person", X + 20, Y, values, t=201.0)
    assert len(layer) == 5
    assert layer.values_at("person", [(X + 8) * GRID.n], [Y * GRID.n], now=201.0)[0] == pytest.approx(0.5)
    assert layer.values_at("person", [(X + 7) * GRID.n], [Y * GRID.n], now=201.0)[0] == 0.0  # evicted


def test_an_agent_whose_clock_is_minutes_behind_takes_the_joint_map_once_the_lead_is_steady(link_and_server):
    # probe: a companion computer 2 minutes behind the server dropped every joint message (t_in_future)
    link, server = link_and_server
    seq = 1
    deadline = time.monotonic() + 10.0
    while held_value(link) is None and time.monotonic() < deadline:
        seq += 1
        server.put(*joint_tile(0.7, t=time.time() + 120.0, seq=seq))
        time.sleep(0.4)
    stats = link.stats()
    assert 4 <= stats["rejected"]["t_in_future"] <= 8  # rejected until five over 2 s confirmed the lead
    assert stats["joint_clock_lead_s"] == pytest.approx(120.0, abs=1.0)
    server.put(*joint_tile(0.9, t=time.time() + 121.0, seq=seq + 1))
    assert wait_until(lambda: held_value(link)) == pytest.approx(0.9, abs=0.01)
    server.put(*joint_tile(0.3, t=1e300, seq=seq + 2))  # an absurd stamp is still refused
    wait_until(lambda: link.stats()["rejected"]["t_in_future"] == stats["rejected"]["t_in_future"] + 1)
    assert held_value(link) is None

"""Hostile input from outside on loopback (issue 19's probes): each was reproduced with a plain
zenoh-python client against the real server and must now be dropped, counted and bounded."""

from __future__ import annotations

import sqlite3
import time

import httpx
import msgpack
import numpy as np
import pytest

from shared.messages import CameraInfo, StateMessage, encode_state
from shared.tilecodec import MAX_SEQ, TileMessage, encode_tile
from tests.fusion_server.fake_agent import GRID, KEYS, LAT, LON, TILE_X, TILE_Y, blob
from tests.netutil import wait_until

TILE = ("person", GRID.z, TILE_X, TILE_Y)


def spoof_tile(agent, uav: str, values: np.ndarray, *, t: float, seq: int, x: int = TILE_X, y: int = TILE_Y) -> None:
    """Put a well-formed tile under ``uav``'s key with any t and seq (what a hostile client can do)."""
    msg = TileMessage(uav=uav, cls="person", z=GRID.z, x=x, y=y, n=GRID.n, t=t, seq=seq, values=values)
    agent.put(KEYS.uav_tile(uav, "person", GRID.z, x, y), encode_tile(msg))


def joint_value(server, row: int, col: int) -> float:
    tile = server.joint.get(TILE)
    return -1.0 if tile is None else tile.values[row, col] / 255.0


@pytest.mark.parametrize(("t_ahead_s", "seq", "reason"), [
    (1e300, 5, "t_in_future"),  # t = 1e300
    (3600.0, 5, "t_in_future"),  # an hour ahead of the server clock
    (0.0, MAX_SEQ, "seq_in_future"),  # seq 2**64 - 1 with a plausible t
])
def test_a_tile_from_the_future_neither_erases_nor_blocks_the_real_data(server, agent_factory, t_ahead_s, seq,
                                                                         reason):
    real = agent_factory("uav1")
    real.tile(blob(40, 40, 0.8))
    wait_until(lambda: joint_value(server, 40, 40) > 0.7)
    attacker = agent_factory("mallory", alive=False)
    t = 1e300 if t_ahead_s == 1e300 else time.time() + t_ahead_s
    spoof_tile(attacker, "uav1", np.zeros((GRID.n, GRID.n), np.float32), t=t, seq=seq)
    wait_until(lambda: server.metrics.rejected_by_reason().get(reason, 0) == 1)
    assert joint_value(server, 40, 40) > 0.7  # not erased
    real.tile(blob(40, 40, 0.5))  # the genuine next tile is not "stale"
    wait_until(lambda: abs(joint_value(server, 40, 40) - 0.5) < 0.01)
    assert server.metrics.rejected_by_reason().get("stale", 0) == 0
    assert server.joint.get(TILE).t < time.time() + 1.0  # nothing from the future reaches the joint tile


def test_state_and_tracks_from_the_future_are_dropped(server, agent_factory):
    agent = agent_factory("uav1")
    camera = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
    state = StateMessage(uav="uav1", t=1e300, lat=LAT, lon=LON, height_m=40.0, pitch_deg=60.0, heading_deg=0.0,
                         footprint=(), camera=camera)
    agent.put(KEYS.uav_state("uav1"), encode_state(state))
    wait_until(lambda: server.metrics.rejected.get(("state", "t_in_future"), 0) == 1)


def test_a_footprint_beyond_the_map_is_dropped_without_an_internal_error(server, agent_factory):
    agent = agent_factory("uav1")
    agent.state(lat=89.0, lon=LON, footprint=((89.0, LON), (89.0001, LON), (89.0, LON + 0.0001)))
    wait_until(lambda: server.metrics.rejected.get(("state", "out_of_range"), 0) == 1)
    agent.state()  # a valid one still goes through
    wait_until(lambda: server.metrics.received.get("state", 0) == 1)
    assert "internal_error" not in server.metrics.rejected_by_reason()


@pytest.mark.parametrize("bbox", ["179.999,10,180,10.001", "179.999,-10.001,180,-10"])
def test_a_bbox_ending_at_lon_180_covers_its_cells(server, http, agent_factory, bbox):
    agent = agent_factory("uav1")
    agent.tile(blob(5, 5))
    wait_until(lambda: server.joint.get(TILE) is not None)
    body = http.get("/v1/map", params={"cls": "person", "bbox": bbox}).json()
    # 0.001 deg of longitude at z18 / 256 cells is ~186 cells, never a single wrapped cell
    assert 180 <= body["width"] <= 190, body["width"]
    assert body["bbox"][2] == pytest.approx(180.0) and body["bbox"][0] == pytest.approx(179.999, abs=1e-5)
    whole = http.get("/v1/map", params={"cls": "person", "bbox": "-180,10,180,10.001"})
    assert whole.status_code == 400 and "cells" in whole.json()["detail"]


def test_one_huge_tracks_message_neither_stops_joint_tracks_nor_saving(server, agent_factory):
    # probe: one 850 kB tracks message (10,000 tracks) made the joint-tracks publisher raise
    # "too_many" on every cycle: no joint tracks and no track saves while the fakes lived
    received: list[bytes] = []
    listener = agent_factory("listener", alive=False)
    sub = listener.session.declare_subscriber(KEYS.joint_tracks(), lambda s: received.append(s.payload.to_bytes()))
    evil = agent_factory("evil")
    m_lat = 1.0 / 111_320.0
    items = [(i, "person", LAT + 0.5 + (i // 100) * m_lat, LON + (i % 100) * m_lat) for i in range(10_000)]
    evil.tracks(items)  # ~850 kB: beyond the 256 KiB limit
    wait_until(lambda: server.metrics.rejected.get(("tracks", "too_large"), 0) == 1, timeout_s=10.0)
    evil.tracks(items[:2500])  # ~215 kB: within it, cut to its 1,000 best tracks
    wait_until(lambda: server.metrics.received.get("tracks", 0) == 1, timeout_s=10.0)
    real = agent_factory("uav1")
    real.tracks([(7, "person", LAT, LON)])

    def has_uav1() -> bool:
        return bool(received) and any(["uav1", 7] in t["members"] for t in msgpack.unpackb(received[-1])["tracks"])

    wait_until(has_uav1, timeout_s=10.0)
    assert server.tracker.dropped()["too_many_tracks"] == 1_500
    text = httpx.get(server.url + "metrics").text
    assert 'uavmm_fusion_tracks_dropped_total{reason="too_many_tracks"} 1500' in text
    store = server.store

    def saved() -> bool:
        with sqlite3.connect(store.path) as conn:
            return any("uav1" in row[0] for row in conn.execute("SELECT members FROM tracks"))

    wait_until(saved, timeout_s=10.0)
    del sub


def test_healthz_answers_while_the_tracker_is_busy(server, http):
    # probe: a long association held the tracker lock and /healthz with it
    with server.tracker._lock:  # what a long association does
        response = http.get("/healthz", timeout=5.0)
    assert response.status_code == 200 and response.json()["global_tracks"] == 0


def test_liveliness_tokens_without_data_cannot_lock_out_a_real_uav(server_factory, agent_factory, http_of):
    # probe: 260 fake liveliness tokens -> "too_many_uavs" for a real new UAV
    server = server_factory(max_uavs=8)
    faker = agent_factory("faker", alive=False)
    tokens = [faker.session.liveliness().declare_token(KEYS.uav_alive(f"ghost{i}")) for i in range(30)]
    wait_until(lambda: server.metrics.received.get("alive", 0) >= 30)
    real = agent_factory("uav1")
    real.tile(blob(10, 10))
    wait_until(lambda: server.joint.get(TILE) is not None)
    assert server.metrics.rejected_by_reason().get("too_many_uavs", 0) == 0
    # its tile and its liveliness token travel apart: wait for the token too
    wait_until(lambda: any(r["id"] == "uav1" and r["online"] for r in http_of(server).get("/v1/uavs").json()))
    rows = {row["id"]: row for row in http_of(server).get("/v1/uavs").json()}
    assert rows["uav1"]["online"] and rows["uav1"]["messages"] == {"tile": 1}
    assert len(rows) <= 8 * 4  # token-only entries are bounded too
    del tokens


def test_a_flooding_uav_is_rate_limited_and_the_others_still_fused(server_factory, agent_factory, http_of):
    server = server_factory(uav_max_msgs_per_s=50.0, uav_max_bytes_per_s=1e9)
    flood = agent_factory("flood")
    for i in range(500):
        flood.tile(blob(20, 20, 0.9), x=TILE_X + 1 + i % 10)
    honest = agent_factory("uav1")
    honest.tile(blob(40, 40, 0.6))
    wait_until(lambda: joint_value(server, 40, 40) > 0.5)
    wait_until(lambda: server.metrics.received.get("tile", 0) + sum(server.metrics.rejected_by_reason().values())
               >= 501)
    limited = server.metrics.rejected.get(("tile", "rate_limited"), 0)
    assert 300 <= limited <= 450  # a burst of 2 s (100) goes through, and what refills meanwhile
    rows = {row["id"]: row for row in http_of(server).get("/v1/uavs").json()}
    assert rows["flood"]["rejected"] == {"rate_limited": limited}
    assert "rejected" not in rows["uav1"] or rows["uav1"]["rejected"] == {}
    byte_server_metrics = server.metrics
    assert byte_server_metrics.rejected.get(("tile", "byte_rate_limited"), 0) == 0


def test_bytes_per_second_are_limited_per_uav(server_factory, agent_factory):
    server = server_factory(uav_max_msgs_per_s=1e6, uav_max_bytes_per_s=100_000.0)
    flood = agent_factory("flood")
    dense = np.full((GRID.n, GRID.n), 0.5, np.float32)  # a dense tile: ~64 KiB
    for i in range(40):
        flood.tile(dense, x=TILE_X + i)
    wait_until(lambda: server.metrics.received.get("tile", 0) + sum(server.metrics.rejected_by_reason().values())
               >= 40)
    assert server.metrics.rejected.get(("tile", "byte_rate_limited"), 0) >= 30  # 200 kB burst, 100 kB/s


def test_one_uav_id_used_by_two_sessions_is_reported(server, zenoh_port, http):
    from agent.zenoh_config import ZenohOptions, agent_zenoh_config
    from agent.zenoh_io import AgentLink

    conf = ZenohOptions(mode="client", connect=(f"tcp/127.0.0.1:{zenoh_port}",), multicast_scouting=False)
    links = [AgentLink(agent_zenoh_config(conf), KEYS, "uav1", GRID) for _ in range(2)]
    camera = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
    try:
        for link in links:
            assert link.open(timeout_s=20.0)
        state = StateMessage(uav="uav1", t=time.time(), lat=LAT, lon=LON, height_m=40.0, pitch_deg=60.0,
                             heading_deg=0.0, footprint=(), camera=camera)
        links[0].submit([("state", KEYS.uav_state("uav1"), encode_state(state))])
        row = wait_until(lambda: [r for r in http.get("/v1/uavs").json() if r["id"] == "uav1"
                                  and r["messages"].get("state") == 1])[0]
        assert row["sessions"] == [str(links[0].session.zid())] and not row["conflict"]
        links[1].submit([("state", KEYS.uav_state("uav1"), encode_state(state))])
        row = wait_until(lambda: [r for r in http.get("/v1/uavs").json() if r["id"] == "uav1" and r["conflict"]])[0]
        assert sorted(row["sessions"]) == sorted(str(link.session.zid()) for link in links)
        assert "uavmm_fusion_uav_conflicts 1" in http.get("/metrics").text
    finally:
        for link in links:
            link.close()


def test_a_misbehaving_uav_at_full_speed_is_counted_bounded_and_the_others_fused(server, agent_factory, http):
    # the 100,000-message figure is `uavmm bench hostile`; this is the same flood, shorter
    from benchmarks.bench_hostile import hostile_payloads

    honest = agent_factory("uav1")
    honest.tile(blob(60, 60, 0.7))
    wait_until(lambda: joint_value(server, 60, 60) > 0.6)
    mallory = agent_factory("mallory")
    payloads = hostile_payloads(np.random.default_rng(1))
    sent = 3000
    for i in range(sent):
        mallory.put(*payloads[i % len(payloads)])
    honest.tile(blob(60, 60, 0.3))

    def hostile_counted() -> int:
        return sum(server.metrics.rejected_by_reason().values()) + server.metrics.received.get("tracks", 0)

    wait_until(lambda: hostile_counted() >= sent, timeout_s=30.0)
    assert hostile_counted() == sent
    wait_until(lambda: abs(joint_value(server, 60, 60) - 0.3) < 0.01)
    reasons = server.metrics.rejected_by_reason()
    assert reasons["rate_limited"] > 0 and reasons["not_msgpack"] > 0 and "internal_error" not in reasons
    assert http.get("/healthz").json()["status"] == "ok"
    assert server.joint.uav_tile_counts() == {"uav1": 1}

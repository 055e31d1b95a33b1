"""A UAV whose clock runs ahead of the fusion server's, end to end over real Zenoh on loopback: its messages are
dropped until its steady lead is taken, then fused on the server's clock; forged stamps, absurd ones and other UAVs
move nothing, and a UAV back on time is fused at once."""

from __future__ import annotations

import time

import pytest

from fusion_server.server import FusionServer
from shared.messages import CameraInfo, StateMessage, TrackItem, TracksMessage, encode_state, encode_tracks
from shared.tilecodec import TileMessage, encode_tile
from tests.fusion_server.fake_agent import GRID, KEYS, LAT, LON, TILE_X, TILE_Y, FakeAgent, blob
from tests.netutil import wait_until

TILE = ("person", GRID.z, TILE_X, TILE_Y)
CAMERA = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
SKEW_S = 30.0
#: Between two messages of a UAV (each kind needs 5 over 2 s of them before its lead is taken).
PERIOD_S = 0.25


def send(agent: FakeAgent, lead_s: float, *, value: float = 0.8, row: int = 40, x: int = TILE_X,
         state: bool = False, tracks: bool = False) -> None:
    """One publish cycle of a UAV whose clock runs ``lead_s`` ahead: a tile (seq in nanoseconds of its clock, as a
    publisher stamping seq from its clock does), and its state and tracks when asked."""
    t = time.time() + lead_s
    agent.seq += 1
    agent.put(KEYS.uav_tile(agent.uav, "person", GRID.z, x, TILE_Y),
              encode_tile(TileMessage(uav=agent.uav, cls="person", z=GRID.z, x=x, y=TILE_Y, n=GRID.n, t=t,
                                      seq=int(t * 1e9) if t < 1e10 else agent.seq, values=blob(row, 40, value))))
    if state:
        footprint = ((LAT, LON), (LAT + 1e-4, LON), (LAT, LON + 1e-4))
        agent.put(KEYS.uav_state(agent.uav), encode_state(StateMessage(
            uav=agent.uav, t=t, lat=LAT, lon=LON, height_m=40.0, pitch_deg=60.0, heading_deg=90.0,
            footprint=footprint, camera=CAMERA)))
    if tracks:
        item = TrackItem(id=7, cls="person", lat=LAT, lon=LON, score=0.9, vel_en=(0.0, 0.0))
        agent.put(KEYS.uav_tracks(agent.uav), encode_tracks(TracksMessage(uav=agent.uav, t=t, tracks=(item,))))


def joint_value(server: FusionServer, row: int, col: int = 40, key=TILE) -> float:
    tile = server.joint.get(key)
    return -1.0 if tile is None else tile.values[row, col] / 255.0


def rows(http) -> dict[str, dict]:
    return {row["id"]: row for row in http.get("/v1/uavs").json()}


def rejected(server: FusionServer, reason: str) -> int:
    return server.metrics.rejected_by_reason().get(reason, 0)


@pytest.fixture
def server(server_factory) -> FusionServer:
    return server_factory(ttl_s=5.0)


def test_a_uav_two_minutes_ahead_is_fused_after_the_evidence_beside_one_on_time(server, http, agent_factory):
    fast, ontime = agent_factory("fast"), agent_factory("ontime")
    started = time.monotonic()
    fused_after = None
    while time.monotonic() - started < 8.0:
        send(fast, 120.0, state=True, tracks=True)
        send(ontime, 0.0, value=0.6, x=TILE_X + 1)
        if fused_after is None and joint_value(server, 40) > 0.7:
            fused_after = time.monotonic() - started
        if fused_after is not None and server.uavs.snapshot()[0].get("state") is not None and len(server.tracker):
            break
        time.sleep(PERIOD_S)
    # dropped as before until its lead was taken (5 over 2 s), then in the joint map beside the UAV on time
    assert fused_after is not None and 1.5 <= fused_after <= 6.0, fused_after
    assert rejected(server, "t_in_future") >= 3 * 4  # tiles, states and tracks: each kind's first ones
    assert abs(joint_value(server, 40, key=(TILE[0], TILE[1], TILE_X + 1, TILE_Y)) - 0.6) < 0.01
    # on the server's clock: the joint tile, the state and the tracks carry no time from the future
    assert server.joint.get(TILE).t <= time.time() + 1.0
    uavs = rows(http)
    assert uavs["fast"]["clock_lead_s"] == pytest.approx(120.0, abs=1.0)
    assert set(uavs["fast"]["clock_leads_s"]) == {"tile", "state", "tracks"}
    assert abs(uavs["fast"]["state"]["t"] - time.time()) < 5.0
    assert uavs["ontime"]["clock_lead_s"] == 0.0 and "clock_leads_s" not in uavs["ontime"]
    assert uavs["ontime"]["rejected"] == {}
    assert len(http.get("/v1/tracks").json()["features"]) == 1
    metrics = http.get("/metrics").text
    assert 'uavmm_fusion_uav_clock_lead_seconds{uav="fast"} 1' in metrics  # 119.9... or 120.0...
    assert 'uav="ontime"' not in metrics.split("uavmm_fusion_uav_clock_lead_seconds", 1)[1]


def test_forged_and_absurd_stamps_under_a_uavs_key_move_nothing(server, http, agent_factory):
    real = agent_factory("uav1")
    mallory = agent_factory("mallory", alive=False)
    send(real, 0.0)
    wait_until(lambda: joint_value(server, 40) > 0.7)
    forged = 0
    for i in range(16):  # over 4 s, among the real UAV's messages on time
        send(real, 0.0, value=0.8)
        if i % 4 == 0:
            send(mallory_as(mallory, "uav1"), 3600.0, value=0.1)  # one forged stamp an hour ahead
            forged += 1
        send(mallory_as(mallory, "uav1"), 1e300 - time.time(), value=0.1)  # t = 1e300, every time
        forged += 1
        time.sleep(PERIOD_S)
    for _ in range(20):  # a burst within a moment
        send(mallory_as(mallory, "uav1"), 600.0, value=0.1)
        forged += 1
    wait_until(lambda: rejected(server, "t_in_future") == forged, what="every forged message dropped")
    time.sleep(0.5)
    assert rejected(server, "t_in_future") == forged
    assert abs(joint_value(server, 40) - 0.8) < 0.01 and server.joint.get(TILE).t <= time.time() + 1.0
    assert rows(http)["uav1"]["clock_lead_s"] == 0.0
    assert "uavmm_fusion_uav_clock_lead_seconds{" not in http.get("/metrics").text


def mallory_as(agent: FakeAgent, uav: str) -> FakeAgent:
    """The attacker's session publishing under another UAV's id."""
    agent.uav = uav
    return agent


def test_two_uavs_with_different_leads_are_each_fused_on_the_servers_clock(server, http, agent_factory):
    minutes, hours = agent_factory("minutes"), agent_factory("hours")
    other = (TILE[0], TILE[1], TILE_X + 1, TILE_Y)

    def both_fused() -> bool:
        return joint_value(server, 40) > 0.7 and joint_value(server, 40, key=other) > 0.7

    deadline = time.monotonic() + 8.0
    while not both_fused() and time.monotonic() < deadline:
        send(minutes, 120.0)
        send(hours, 2 * 3600.0, x=TILE_X + 1)  # local time stamped as UTC two hours east of Greenwich
        time.sleep(PERIOD_S)
    assert both_fused()
    uavs = rows(http)
    assert uavs["minutes"]["clock_lead_s"] == pytest.approx(120.0, abs=1.0)
    assert uavs["hours"]["clock_lead_s"] == pytest.approx(7200.0, abs=1.0)
    assert server.joint.get(TILE).t <= time.time() + 1.0 and server.joint.get(other).t <= time.time() + 1.0
    # the hours UAV's lead lets none of the minutes UAV's messages two hours ahead in
    before = rejected(server, "t_in_future")
    send(minutes, 2 * 3600.0, value=0.3)
    wait_until(lambda: rejected(server, "t_in_future") == before + 1)
    assert joint_value(server, 40) > 0.7


def test_a_uav_back_on_the_right_clock_is_fused_at_once_and_its_lead_dropped(server, http, agent_factory):
    fast = agent_factory("fast")
    deadline = time.monotonic() + 8.0
    while joint_value(server, 40) < 0.7 and time.monotonic() < deadline:
        send(fast, 120.0)
        time.sleep(PERIOD_S)
    assert joint_value(server, 40) > 0.7 and rows(http)["fast"]["clock_lead_s"] == pytest.approx(120.0, abs=1.0)
    fast.close()  # restarted with NTP: a new session, its seq from its clock now 2 minutes lower
    fixed = agent_factory("fast")
    started = time.monotonic()
    send(fixed, 0.0, value=0.5)
    wait_until(lambda: abs(joint_value(server, 40) - 0.5) < 0.01, what="the first tile on time fused")
    first_fused_s = time.monotonic() - started
    assert first_fused_s < 2.0, first_fused_s  # not "stale" behind the old tiles, not waiting for evidence
    deadline = time.monotonic() + 6.0
    while rows(http)["fast"]["clock_lead_s"] != 0.0 and time.monotonic() < deadline:
        send(fixed, 0.0, value=0.5)
        time.sleep(PERIOD_S)
    uavs = rows(http)
    assert uavs["fast"]["clock_lead_s"] == 0.0 and "clock_leads_s" not in uavs["fast"]
    assert rejected(server, "stale") == 0
    assert abs(joint_value(server, 40) - 0.5) < 0.01

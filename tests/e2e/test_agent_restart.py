"""An agent restarts while the fusion server keeps running: the restarted agent's local track ids are new,
so its new object gets its own global id instead of taking over the one the previous run's object had.

Real parts: an in-process `FusionServer` (Zenoh router on a free loopback port) and two `AgentNode`
instances for the same UAV, one after the other, each through the real pipeline and tracker.
"""

from __future__ import annotations

import threading

import pytest

from agent.node import AgentNode, AgentSettings
from fusion_server.config import FusionSettings
from fusion_server.global_tracks import ground_distance_m
from fusion_server.server import FusionServer
from tests.agent.test_node_zenoh import BOX_A, BOX_B, RunningAgent, ScriptedSource, box_ground
from tests.netutil import free_port, wait_until
from transport.options import ZenohOptions

pytestmark = pytest.mark.e2e
FRAMES = 45  # 1.5 s at 30 fps, played in real time


def active_uav1_ids_near(server: FusionServer, lat: float, lon: float) -> set[int]:
    """uav1's local ids active in the global tracks within 1 m of (lat, lon)."""
    return {local_id for r in server.tracker.records() if ground_distance_m(r.lat, r.lon, lat, lon) < 1.0
            for uav, local_id in r.active if uav == "uav1"}


def run_agent_until_the_server_has_its_track(server: FusionServer, port: int, box: tuple) -> set[int]:
    """One agent run (uav1, one object at ``box``) held on its last frame until the server holds a global
    track there with one of this run's local ids active; returns those local ids."""
    release = threading.Event()
    source = ScriptedSource(FRAMES, lambda i: [(box, 0.9)], hold={FRAMES - 1: release})
    options = ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    node = AgentNode(AgentSettings(uav_id="uav1", zenoh=options, open_timeout_s=20.0, speed=1.0), source)
    with RunningAgent(node) as agent:
        ids = wait_until(lambda: active_uav1_ids_near(server, *box_ground(box)), 20.0, "uav1's track at the server")
        release.set()
        agent.join(20.0)
    return ids


def test_a_restarted_agent_does_not_take_over_the_global_id_of_its_previous_run():
    port = free_port()
    # gate 3 m: B (8.8 m east of A) is clearly a different object for the association
    settings = FusionSettings(zenoh=ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",),
                                                 multicast_scouting=False),
                              http_port=0, db_path=None, track_gate_m=3.0, track_hold_s=60.0)
    a, b = box_ground(BOX_A), box_ground(BOX_B)
    assert ground_distance_m(*a, *b) > 2 * settings.track_gate_m
    with FusionServer(settings) as server:
        server.start(http=False)
        first_ids = run_agent_until_the_server_has_its_track(server, port, BOX_A)
        (track_a,) = server.tracker.records()
        assert ground_distance_m(track_a.lat, track_a.lon, *a) < 1.0

        # the process restarts (a new node, a new tracker) and now sees another object, B
        second_ids = run_agent_until_the_server_has_its_track(server, port, BOX_B)
        assert first_ids and second_ids and not first_ids & second_ids
        records = {r.gid: r for r in server.tracker.records()}

    # A keeps its global id and its place, with only the first run's local tracks; B is a new global track
    assert set(records) == {track_a.gid, track_a.gid + 1}
    old, new = records[track_a.gid], records[track_a.gid + 1]
    assert ground_distance_m(old.lat, old.lon, *a) < 1.0, "the old global track was moved to the new object"
    assert {local_id for _, local_id in old.members} == first_ids
    assert ground_distance_m(new.lat, new.lon, *b) < 1.0
    assert {local_id for _, local_id in new.members} == second_ids

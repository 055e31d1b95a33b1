"""Replays that line up (AgentSettings.replay_sync_s): an agent replaying a recording in real time takes up the
source clock of another UAV that is ahead of it (started earlier), processing the frames it is behind on without
waiting; a UAV behind it, or too far ahead, or the setting off, changes nothing. Real Zenoh sessions on loopback,
the test plays the other UAV with state messages on the router."""

from __future__ import annotations

import time

import pytest

from agent.node import AgentNode, AgentSettings, state_message
from shared.geo import Pose
from shared.messages import encode_state
from tests.agent.test_node_zenoh import (
    CAMERA,
    KEYS,
    LAT,
    LON,
    FakeServer,
    RunningAgent,
    ScriptedSource,
    agent_settings,
)
from tests.netutil import free_port, wait_until

OTHER = Pose(lat=LAT, lon=LON + 0.0003, height_m=30.0, pitch_deg=90.0, heading_deg=0.0)


@pytest.fixture()
def server():
    port = free_port()
    server = FakeServer(port)
    server.port = port  # type: ignore[attr-defined]
    yield server
    server.close()


def _run_with_partner(server: FakeServer, lead_s: float, rate: float = 1.0,
                      **settings) -> tuple[AgentNode, list[tuple[float, float]]]:
    """Run an agent in real time, then say (as uav2, every 0.2 s for 2 s) that uav2's clock is lead_s ahead of the
    agent's last frame and runs at rate source seconds per wall second; returns the node and its (frame t, wall
    time) pairs."""
    seen: list[tuple[float, float]] = []
    port = server.port  # type: ignore[attr-defined]
    node = AgentNode(agent_settings(port, "uav1", speed=1.0, **settings), ScriptedSource(10**6, lambda i: []),
                     on_frame=lambda frame, result, tracks: seen.append((frame.t, time.monotonic())))
    with RunningAgent(node):
        wait_until(lambda: node.counts["frames"] > 10, 20.0)
        wait_until(lambda: node.link.stats()["counts"].get("sent_state", 0) > 0, 10.0)  # the route is up
        t_other = seen[-1][0] + lead_s
        start = time.monotonic()
        while time.monotonic() - start < 2.0:
            now = time.monotonic()
            state = state_message("uav2", t_other + rate * (now - start), OTHER, CAMERA, range_m=200.0)
            server.put(KEYS.uav_state("uav2"), encode_state(state))
            time.sleep(0.2)
        time.sleep(0.3)
    return node, seen


def _source_lead(seen: list[tuple[float, float]]) -> float:
    """How far the agent's source clock ran ahead of the wall clock over the run (s): 0 for a steady replay."""
    (t0, w0), (t1, w1) = seen[0], seen[-1]
    return (t1 - t0) - (w1 - w0)


def test_an_agent_behind_another_uav_catches_up_with_its_clock(server):
    node, seen = _run_with_partner(server, 5.0)
    assert node.counts["replay_sync_s"] == pytest.approx(5.0, abs=0.5)
    assert _source_lead(seen) == pytest.approx(5.0, abs=0.6)
    assert node.summary()["replay_sync_s"] == pytest.approx(node.counts["replay_sync_s"], abs=1e-3)


@pytest.mark.parametrize(("lead_s", "rate", "settings"),
                         [(-5.0, 1.0, {}), (0.2, 1.0, {}), (120.0, 1.0, {}), (5.0, 4.0, {}),
                          (5.0, 1.0, {"replay_sync_s": 0.0})])
def test_a_uav_behind_in_step_too_far_ahead_or_faster_or_the_setting_off_changes_nothing(server, lead_s, rate,
                                                                                        settings):
    # a replay played four times faster is not followed: it would drag this one along
    node, seen = _run_with_partner(server, lead_s, rate, **settings)
    assert node.counts["replay_sync_s"] == 0.0
    assert abs(_source_lead(seen)) < 0.5


def test_replay_sync_must_be_a_finite_non_negative_number():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="replay_sync_s"):
            AgentSettings(uav_id="uav1", replay_sync_s=bad)


def test_a_uav_whole_hours_apart_is_named_as_a_time_zone(server, caplog):
    """A DJI SRT's local dates (CEST) beside a UTC log: 2 h apart, no sync; one warning names the flag."""
    with caplog.at_level("WARNING", logger="agent.node"):
        node, _ = _run_with_partner(server, 7200.0 + 12.0)
    assert node.counts["replay_sync_s"] == 0.0
    warned = [r.getMessage() for r in caplog.records if "time zones" in r.getMessage()]
    assert len(warned) == 1 and "uav2's clock is +2.00 h" in warned[0] and "--telemetry-utc-offset-h" in warned[0]


@pytest.mark.parametrize(("lead_s", "rate"), [(30 * 86400.0 + 7200.0, 1.0), (7200.0, 4.0)])
def test_clocks_days_apart_or_running_faster_are_not_named_as_a_time_zone(server, caplog, lead_s, rate):
    """Another day's flight (a whole number of half hours apart by chance) or a replay at four times the speed
    (drifting through the window) is no time zone."""
    with caplog.at_level("WARNING", logger="agent.node"):
        _run_with_partner(server, lead_s, rate)
    assert "time zones" not in caplog.text

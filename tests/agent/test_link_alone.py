"""An agent whose Zenoh endpoint is dead says so (once, naming the endpoint) instead of flying silently
with `publishers: 0`, and says when it reaches the server again."""

from __future__ import annotations

import logging
import time

import pytest

import agent.zenoh_io
from agent.zenoh_config import ZenohOptions, agent_zenoh_config
from agent.zenoh_io import AgentLink
from tests.agent.test_node_zenoh import GRID, KEYS, FakeServer
from tests.netutil import free_port, wait_until


def _warnings(caplog, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and text in r.getMessage()]


def test_a_dead_endpoint_is_reported_and_so_is_the_recovery(monkeypatch, caplog):
    monkeypatch.setattr(agent.zenoh_io, "ALONE_WARN_S", 0.5)
    caplog.set_level(logging.INFO, logger="agent.zenoh_io")
    port = free_port()
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    assert link.open(timeout_s=10.0)  # a peer opens without anyone to talk to
    server = None
    try:
        wait_until(lambda: _warnings(caplog, "no zenoh router or peer reached"), 10.0)
        (warning,) = _warnings(caplog, "no zenoh router or peer reached")
        assert f"tcp/127.0.0.1:{port}" in warning and "uav1" in warning
        time.sleep(1.0)
        assert len(_warnings(caplog, "no zenoh router or peer reached")) == 1  # once per outage
        server = FakeServer(port)
        wait_until(lambda: _warnings(caplog, "connected again"), 15.0)
    finally:
        link.close()
        if server is not None:
            server.close()


def test_a_connected_agent_never_warns(monkeypatch, caplog):
    monkeypatch.setattr(agent.zenoh_io, "ALONE_WARN_S", 0.5)
    port = free_port()
    server = FakeServer(port)
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    try:
        assert link.open(timeout_s=10.0)
        time.sleep(1.5)
        assert not _warnings(caplog, "no zenoh router or peer reached")
        assert link.stats()["counts"].get("alone_checks", 0) == 0
    finally:
        link.close()
        server.close()
    assert not _warnings(caplog, "no zenoh router or peer was reached during the run")


def test_a_run_shorter_than_the_warning_that_reached_nobody_says_so_at_the_end(caplog):
    """`uavmm agent --duration 2 --connect tcp/127.0.0.1:WRONG` ran, printed "up" and exited 0 with no sign that
    nothing it published went anywhere (the outage warning waits ALONE_WARN_S)."""
    port = free_port()
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    assert link.open(timeout_s=10.0)
    link.close()
    (warning,) = _warnings(caplog, "no zenoh router or peer was reached during the run")
    assert f"tcp/127.0.0.1:{port}" in warning and "uav1" in warning


@pytest.mark.parametrize("endpoints", [None, ("tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447")])
def test_the_warning_names_what_it_dials(endpoints):
    conf = agent_zenoh_config(ZenohOptions(connect=endpoints, multicast_scouting=False))
    link = AgentLink(conf, KEYS, "uav1", GRID)
    assert link._connect_endpoints() == (", ".join(endpoints) if endpoints else "none (scouting only)")

"""Fixtures for the fusion server tests: a real server (Zenoh on loopback, HTTP on a free port) and
fake agents that publish real encoded messages from their own Zenoh sessions."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from fusion_server.config import FusionSettings, ZenohOptions
from fusion_server.server import FusionServer
from tests.fusion_server.fake_agent import FakeAgent
from tests.netutil import free_port


@pytest.fixture
def zenoh_port() -> int:
    return free_port()


def make_settings(port: int, db: Path | None, **overrides) -> FusionSettings:
    listen = overrides.pop("listen", f"tcp/127.0.0.1:{port}")
    options = ZenohOptions(mode="router", listen=(listen,), multicast_scouting=False,
                           cfg=overrides.pop("cfg", ()), config_file=overrides.pop("config_file", None))
    return FusionSettings(zenoh=options, http_port=0, db_path=db, **overrides)


@pytest.fixture
def server_factory(tmp_path: Path, zenoh_port: int):
    started: list[FusionServer] = []

    def start(**overrides) -> FusionServer:
        db = overrides.pop("db_path", tmp_path / "fusion.sqlite")
        server = FusionServer(make_settings(zenoh_port, db, **overrides))
        started.append(server)
        server.start()
        return server

    yield start
    for server in started:
        server.close()


@pytest.fixture
def server(server_factory) -> FusionServer:
    return server_factory(ttl_s=1.0)


@pytest.fixture
def http(server: FusionServer) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0) as client:
        yield client


@pytest.fixture
def agent_factory(zenoh_port: int):
    agents: list[FakeAgent] = []

    def make(uav: str, **kwargs) -> FakeAgent:
        agent = FakeAgent(uav, f"tcp/127.0.0.1:{zenoh_port}", **kwargs)
        agents.append(agent)
        return agent

    yield make
    for agent in agents:
        agent.close()


@pytest.fixture
def http_of():
    clients: list[httpx.Client] = []

    def make(server: FusionServer) -> httpx.Client:
        client = httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0)
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.close()

"""Fixtures of the agent tests on real Zenoh: a free loopback port and a router session standing in for the
fusion server (tests.agent.test_node_zenoh.FakeServer)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.netutil import free_port


@pytest.fixture
def server_port() -> int:
    return free_port()


@pytest.fixture
def server(server_port) -> Iterator:
    from tests.agent.test_node_zenoh import FakeServer

    fake = FakeServer(server_port)
    yield fake
    fake.close()

"""Helpers of the tests that use the network: free loopback ports, a UDP listener, polling until a condition holds.

One copy for every test package (tests/agent, tests/fusion_server, tests/e2e import them from here).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

__all__ = ["free_port", "free_udp_port", "udp_listener", "wait_until"]


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago (the OS picks it)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def free_udp_port() -> int:
    """A UDP port that was free on 127.0.0.1 a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def udp_listener(timeout_s: float) -> tuple[socket.socket, int]:
    """A UDP socket bound to a free port on 127.0.0.1 whose reads time out after timeout_s, and its port."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(timeout_s)
    return sock, int(sock.getsockname()[1])


def wait_until(predicate: Callable[[], Any], timeout_s: float = 10.0, what: str = "the condition",
               interval_s: float = 0.05) -> Any:
    """Poll predicate until it returns something truthy (returned); AssertionError naming `what` and the
    last value after timeout_s seconds."""
    deadline = time.monotonic() + timeout_s
    while True:
        last = predicate()
        if last:
            return last
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not within {timeout_s} s (last: {last!r})")
        time.sleep(interval_s)

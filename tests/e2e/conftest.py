"""Helpers of the end-to-end tests, which start real processes: free ports, the `uavmm` command line,
bounded waits, starting a process until its ready line, reading its stderr and stopping it.

Import them (`from tests.e2e.conftest import ...`); `port` is a fixture.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.netutil import free_port

REPO = Path(__file__).resolve().parents[2]
#: Environment of the processes: the repository first on the path (the checkout under test).
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture
def port() -> int:
    """A free TCP port on 127.0.0.1."""
    return free_port()


@pytest.fixture
def server(port: int):
    """A plain Zenoh router session on `port` playing the fusion server (records what agents publish)."""
    from tests.agent.test_node_zenoh import FakeServer

    fake = FakeServer(port)
    yield fake
    fake.close()


def uavmm(*args: str) -> list[str]:
    """The command line of `uavmm ARGS` with this interpreter (`python -m uavmm`)."""
    return [sys.executable, "-m", "uavmm", *args]


def start_until(cmd: list[str], ready: str, *, what: str, timeout_s: float = 60.0) -> tuple[subprocess.Popen, str]:
    """Start cmd in the repository and wait (bounded) for a stdout line containing `ready`.

    stdout is a pipe (read on by the test), stderr a temporary file (a pipe nobody reads would fill up
    and block the process's logging; `read_stderr`). Returns the process and its ready line; kills it
    and raises AssertionError with its stderr when the line does not come or it exits first.
    """
    stderr = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=stderr, text=True)
    proc.stderr_file = stderr  # type: ignore[attr-defined]
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    line = ""
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if ready in line or proc.poll() is not None:
            break
    if ready not in line:
        proc.kill()
        raise AssertionError(f"{what} did not start: {line!r} {read_stderr(proc)[-2000:]}")
    return proc, line


def read_stderr(proc: subprocess.Popen) -> str:
    """Everything a process started by `start_until` wrote to stderr so far."""
    stderr = proc.stderr_file  # type: ignore[attr-defined]
    stderr.seek(0)
    return stderr.read()


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout_s: float = 30.0) -> int:
    """Send sig and wait (bounded) for the exit code; kill and raise TimeoutExpired if it hangs."""
    proc.send_signal(sig)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


# ---- the two processes ------------------------------------------------------------------------

def agent_cmd(port: int, *args: str, uav: str = "uav1") -> list[str]:
    """`uavmm agent` connecting to 127.0.0.1:port (no multicast scouting), with more flags."""
    return uavmm("--log-level", "INFO", "agent", "--uav-id", uav, "--connect", f"tcp/127.0.0.1:{port}",
                 "--no-multicast-scouting", *args)


def start_agent(cmd: list[str], timeout_s: float = 60.0) -> subprocess.Popen:
    """Start an agent process and wait (bounded) for its ready line (" up: ")."""
    return start_until(cmd, " up: ", what="uavmm agent", timeout_s=timeout_s)[0]


def finish(proc: subprocess.Popen, timeout_s: float = 30.0) -> tuple[int, dict, str]:
    """Wait for an agent process to end; returns (exit code, parsed summary, stderr)."""
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    err = read_stderr(proc)
    lines = [line for line in out.splitlines() if line.startswith("uavmm agent: summary ")]
    assert lines, f"no summary line; stdout {out[-2000:]!r}; stderr {err[-2000:]!r}"
    return proc.returncode, json.loads(lines[-1].removeprefix("uavmm agent: summary ")), err


def start_fusion(zenoh_port: int, http_port: int, *args: str, timeout_s: float = 30.0) -> tuple[subprocess.Popen, str]:
    """Start `uavmm fusion` listening on 127.0.0.1 (Zenoh and HTTP ports) with more flags; wait (bounded)
    for its map line. Returns the process and the map URL."""
    cmd = uavmm("--log-level", "INFO", "fusion", "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--http",
                f"127.0.0.1:{http_port}", "--no-multicast-scouting", *args)
    proc, line = start_until(cmd, "map: http://", what="uavmm fusion", timeout_s=timeout_s)
    return proc, line.split("map: ", 1)[1].strip()

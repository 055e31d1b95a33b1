"""The router variant of the compose demo (deploy/docker-compose.router.yml) works: its fusion and agent
commands, run as processes on this machine against a Zenoh router, bring three UAVs, a joint map and
global tracks to the REST API. A Python Zenoh session in router mode stands in for the zenohd container
(PITFALLS.md: no zenohd binary here; the router logic is the same Zenoh core)."""

from __future__ import annotations

import json
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest
import zenoh

from tests.e2e.conftest import ENV, REPO, uavmm
from tests.netutil import free_port
from tests.test_deploy import load

pytestmark = pytest.mark.e2e


def localise(command: list[str], router: str, http: str, db: Path) -> list[str]:
    """The container command with the compose network's addresses replaced by this machine's."""
    out = []
    for arg in command:
        arg = arg.replace("tcp/router:7447", router).replace("0.0.0.0:8000", http)
        out.append(str(db) if arg == "/data/fusion.sqlite" else arg)
    return out


def health(url: str) -> dict:
    try:
        with urllib.request.urlopen(url + "healthz", timeout=3) as response:
            return json.loads(response.read())
    except OSError:
        return {}


def test_router_variant_commands_fuse_three_uavs_through_a_router(tmp_path):
    services = load("docker-compose.router.yml")["services"]
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    http = f"127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([router_endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    procs: list[subprocess.Popen] = []
    with zenoh.open(conf):
        try:
            for name in ("fusion", "uav1", "uav2", "uav3"):
                argv = localise(services[name]["command"], router_endpoint, http, tmp_path / "fusion.sqlite")
                with open(tmp_path / f"{name}.log", "wb") as log:
                    procs.append(subprocess.Popen(uavmm(*argv), cwd=REPO, env=ENV, stdout=log,
                                                  stderr=subprocess.STDOUT))
            deadline = time.monotonic() + 60
            state: dict = {}
            while time.monotonic() < deadline:
                state = health(f"http://{http}/")
                if state.get("uavs_online") == 3 and state["joint_tiles"] > 0 and state["global_tracks"] > 0:
                    break
                assert all(p.poll() is None for p in procs), [(tmp_path / f"{n}.log").read_text()[-2000:]
                                                              for n in ("fusion", "uav1", "uav2", "uav3")]
                time.sleep(0.5)
            assert state.get("uavs_online") == 3, state
            assert state["joint_tiles"] > 0 and state["global_tracks"] > 0, state
        finally:
            for proc in procs:
                proc.terminate()
            for proc in procs:
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
    assert all(p.returncode == 0 for p in procs), [p.returncode for p in procs]

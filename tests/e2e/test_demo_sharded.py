"""The sharded variant of the compose demo (deploy/docker-compose.sharded.yml) works: its shard, gateway and
agent commands, run as processes on this machine against a Zenoh router, fuse both meadows, one per
shard, behind one REST API; `kill shard1` shows it degraded and `start shard1` (same database) brings
it back, as the compose file's header says. A Python Zenoh session in router mode stands in for the
zenohd container (PITFALLS.md: no zenohd binary here; the router logic is the same Zenoh core)."""

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

#: one agent per meadow: uav1 over shard 0's, uav4 over shard 1's (tests/test_deploy.py checks the owners)
AGENTS = ("uav1", "uav4")


def localise(command: list[str], router: str, http: str, db: Path) -> list[str]:
    """A container command with the compose network's addresses and paths replaced by this machine's
    (every container has its own loopback; here the shards need their own HTTP ports)."""
    replace = {"tcp/router:7447": router, "0.0.0.0:8000": http, "127.0.0.1:8000": http,
               "/data/fusion.sqlite": str(db)}
    return [replace.get(arg, arg) for arg in command]


def get(url: str):
    try:
        with urllib.request.urlopen(url, timeout=3) as response:
            return json.loads(response.read())
    except (OSError, ValueError):
        return None


def start(name: str, command: list[str], tmp_path: Path) -> subprocess.Popen:
    with open(tmp_path / f"{name}.log", "ab") as log:
        return subprocess.Popen(uavmm(*command), cwd=REPO, env=ENV, stdout=log, stderr=subprocess.STDOUT)


def wait_for(predicate, what: str, procs: dict[str, subprocess.Popen], tmp_path: Path, timeout_s: float = 90.0):
    """Poll ``predicate`` (returns a truthy value when done) every 0.3 s; fail naming ``what`` and
    showing the logs if it does not come or a process exits."""
    deadline = time.monotonic() + timeout_s
    value = None
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        dead = [name for name, proc in procs.items() if proc.poll() is not None]
        assert not dead, {name: (tmp_path / f"{name}.log").read_text()[-2000:] for name in dead}
        time.sleep(0.3)
    raise AssertionError(f"{what}: not within {timeout_s} s (last: {value})")


def test_sharded_variant_fuses_a_meadow_per_shard_and_survives_a_shard_restart(tmp_path):
    services = load("docker-compose.sharded.yml")["services"]
    router = f"tcp/127.0.0.1:{free_port()}"
    http = {name: f"127.0.0.1:{free_port()}" for name in ("shard0", "shard1", "gateway")}
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([router]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    commands = {name: localise(services[name]["command"], router, http.get(name, ""),
                               tmp_path / f"{name}.sqlite") for name in ("shard0", "shard1", "gateway", *AGENTS)}
    gateway = f"http://{http['gateway']}"
    procs: dict[str, subprocess.Popen] = {}
    with zenoh.open(conf):
        try:
            for name, command in commands.items():
                procs[name] = start(name, command, tmp_path)

            def both_meadows():
                rows = get(f"{gateway}/v1/uavs") or []
                shards = {row["id"]: row.get("shard") for row in rows if row.get("online")}
                health = get(f"{gateway}/healthz") or {}
                fused = [get(f"http://{http[s]}/healthz") or {} for s in ("shard0", "shard1")]
                ok = (shards == {"uav1": 0, "uav4": 1} and health.get("status") == "ok"
                      and all(h.get("joint_tiles", 0) > 0 for h in fused))
                return (shards, health.get("status"), [h.get("joint_tiles") for h in fused]) if ok else None

            wait_for(both_meadows, "both agents online, each over its shard, both shards fusing", procs, tmp_path)

            procs.pop("shard1").kill()  # docker compose kill shard1

            def degraded():
                health = get(f"{gateway}/healthz") or {}
                rows = {row["id"]: row for row in get(f"{gateway}/v1/uavs") or []}
                ok = (health.get("down") == [1] and rows.get("uav4", {}).get("degraded") is True
                      and rows.get("uav1", {}).get("degraded") is False)
                return health if ok else None

            wait_for(degraded, "shard 1 down, uav4 degraded, uav1 not", procs, tmp_path, timeout_s=5.0)

            procs["shard1"] = start("shard1", commands["shard1"], tmp_path)  # docker compose start shard1

            def back():
                health = get(f"{gateway}/healthz") or {}
                shard1 = get(f"http://{http['shard1']}/healthz") or {}
                return health if health.get("status") == "ok" and shard1.get("joint_tiles", 0) > 0 else None

            wait_for(back, "shard 1 back on its database and fusing", procs, tmp_path)
        finally:
            for proc in procs.values():
                proc.terminate()
            for proc in procs.values():
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()

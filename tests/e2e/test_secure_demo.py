"""The secure set-up as a user runs it: `uavmm secure init`, then a `uavmm fusion` process and two `uavmm agent`
processes on the generated configs (mutual TLS, the fleet's ACL, a REST token): the UAVs fuse, the agents
receive joint tiles and tracks, the REST API answers 401 without the token and 200 with it; an agent
started with another UAV's credentials is refused at once."""

from __future__ import annotations

import signal
import subprocess

import httpx
import pytest

from tests.e2e.conftest import ENV, REPO, finish, start_agent, stop, uavmm
from tests.netutil import free_port, wait_until

pytestmark = pytest.mark.e2e


def start_secure_fusion(fleet, zenoh_port: int, http_port: int) -> tuple[subprocess.Popen, list[str]]:
    cmd = uavmm("fusion", "--config", str(fleet / "fusion" / "zenoh.json5"), "--listen", f"tls/127.0.0.1:{zenoh_port}",
                "--http", f"0.0.0.0:{http_port}", "--http-token-file", str(fleet / "fusion" / "http-tokens"), "--no-db")
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    lines = [proc.stdout.readline() for _ in range(2)]
    if not any("map: http://" in line for line in lines):
        proc.kill()
        raise AssertionError(f"uavmm fusion did not start: {lines!r}")
    return proc, lines


def test_secure_fleet_end_to_end(tmp_path):
    zenoh_port, http_port = free_port(), free_port()
    fleet = tmp_path / "fleet"
    init = subprocess.run(uavmm("secure", "init", str(fleet), "--uavs", "uav1,uav2", "--server-host", "localhost",
                                "--port", str(zenoh_port)),
                          cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    assert init.returncode == 0, init.stderr
    token = (fleet / "operators" / "operator" / "http-token").read_text().strip()
    fusion, lines = start_secure_fusion(fleet, zenoh_port, http_port)
    assert "REST API needs a bearer token (1 accepted" in lines[1] and token not in lines[1]
    agents = []
    try:
        # another UAV's credentials: refused before it flies, in one line
        wrong = subprocess.run(uavmm("agent", "--uav-id", "uav2", "--config",
                                     str(fleet / "uavs" / "uav1" / "zenoh.json5"), "--sim", "coop", "--uav-index", "1"),
                               cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
        assert wrong.returncode == 2 and "is for 'uav1', not --uav-id 'uav2'" in wrong.stderr
        for index in (0, 1):
            uav = f"uav{index + 1}"
            agents.append(start_agent(uavmm(
                "--log-level", "INFO", "agent", "--uav-id", uav, "--config", str(fleet / "uavs" / uav / "zenoh.json5"),
                "--sim", "coop", "--uav-index", str(index), "--frames", "900", "--loop")))
        base = f"http://127.0.0.1:{http_port}"
        with httpx.Client(base_url=base, timeout=10) as anonymous:
            assert anonymous.get("/v1/uavs").status_code == 401
            assert anonymous.get("/healthz").status_code == 200
        with httpx.Client(base_url=base, timeout=10, headers={"Authorization": f"Bearer {token}"}) as http:
            wait_until(lambda: {u["id"] for u in http.get("/v1/uavs").json() if u["online"] and u["state"]}
                     == {"uav1", "uav2"}, 30.0, "both UAVs online with their state")
            wait_until(lambda: any(set(t["uavs"]) == {"uav1", "uav2"} and t["max"] > 0
                                 for t in http.get("/v1/joint/tiles").json()), 30.0, "joint tiles of both UAVs")
            assert all(not u["rejected"] for u in http.get("/v1/uavs").json())
        for proc in agents:
            proc.send_signal(signal.SIGTERM)
            code, summary, err = finish(proc, 30.0)
            assert code == 0, err[-2000:]
            # the fusion identity's joint tiles and tracks reach each UAV through the ACL
            assert summary["joint_tiles_applied"] > 0 and summary["link"]["counts"]["joint_tracks"] > 0
    finally:
        for proc in agents:
            if proc.poll() is None:
                proc.kill()
        if fusion.poll() is None:
            assert stop(fusion) == 0


def test_an_api_bound_beyond_loopback_without_a_token_file_gets_a_generated_one():
    zenoh_port, http_port = free_port(), free_port()
    cmd = uavmm("fusion", "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--http", f"0.0.0.0:{http_port}", "--no-db",
                "--no-multicast-scouting")
    proc = subprocess.Popen(cmd, cwd=REPO, env={k: v for k, v in ENV.items() if k != "UAVMM_HTTP_TOKEN"},
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(2)]
        assert "generated for this run: " in lines[1], lines
        token = lines[1].split("generated for this run: ", 1)[1].split()[0]
        assert f"#token={token}" in lines[1]
        with httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=10) as http:
            assert http.get("/v1/uavs").status_code == 401
            assert http.get("/v1/uavs", headers={"Authorization": f"Bearer {token}"}).status_code == 200
    finally:
        assert stop(proc) == 0

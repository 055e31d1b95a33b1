"""Two `uavmm agent` processes (the coop scenario's UAVs) against a real `uavmm fusion` process: the server
sees both online with their state, fuses their tiles, associates their tracks; the agents receive joint
tiles and tracks they accept; after the fusion server restarts on the same port the agents' tiles flow
again."""

from __future__ import annotations

import signal
import time

import httpx
import pytest

from tests.e2e.conftest import agent_cmd, finish, read_stderr, start_agent, start_fusion, stop
from tests.netutil import free_port, wait_until

pytestmark = pytest.mark.e2e


def uavs(http: httpx.Client) -> dict[str, dict]:
    return {u["id"]: u for u in http.get("/v1/uavs").json()}


def test_two_agents_and_the_fusion_server(tmp_path):
    zenoh_port, http_port = free_port(), free_port()
    fusion, url = start_fusion(zenoh_port, http_port, "--no-db")
    agents = []
    try:
        for index in (0, 1):
            agents.append(start_agent(agent_cmd(zenoh_port, "--sim", "coop", "--uav-index", str(index),
                                                "--frames", "900", "--loop", uav=f"uav{index + 1}")))
        with httpx.Client(base_url=url, timeout=10) as http:
            both = wait_until(lambda: (u := uavs(http)) and all(
                u.get(f"uav{i}", {}).get("online") and u[f"uav{i}"].get("state") for i in (1, 2)) and u, 20.0,
                            "both UAVs online with their state")
            assert all(len(both[f"uav{i}"]["state"]["footprint"]) == 32 for i in (1, 2))
            # both UAVs look at the same scene: some joint tiles fuse the two of them
            wait_until(lambda: any(set(t["uavs"]) == {"uav1", "uav2"} and t["max"] > 0
                                 for t in http.get("/v1/joint/tiles").json()), 20.0, "joint tiles of both UAVs")
            # the people both see become global tracks with members from both UAVs
            wait_until(lambda: any({m[0] for m in f["properties"]["members"]} == {"uav1", "uav2"}
                                 for f in http.get("/v1/tracks").json()["features"]), 30.0,
                     "global tracks with members from both UAVs")

            # the fusion server goes away and comes back on the same port
            requeried = [read_stderr(proc).count("querying the joint map") for proc in agents]
            assert stop(fusion) == 0
            time.sleep(1.0)
            fusion, url = start_fusion(zenoh_port, http_port, "--no-db")
            wait_until(lambda: (u := uavs(http)) and all(
                u.get(f"uav{i}", {}).get("online") and u[f"uav{i}"].get("tiles", 0) > 0 for i in (1, 2)), 30.0,
                "both UAVs online with tiles at the restarted server")
            wait_until(lambda: http.get("/v1/joint/tiles").json(), 10.0, "joint tiles at the restarted server")
            # each agent noticed the new server and asked it for the joint map
            wait_until(lambda: all(read_stderr(proc).count("querying the joint map") > before
                                 for proc, before in zip(agents, requeried, strict=True)), 10.0,
                     "each agent querying the new server's joint map")
        summaries = []
        for proc in agents:
            proc.send_signal(signal.SIGTERM)
            code, summary, err = finish(proc, 30.0)
            assert code == 0, err[-2000:]
            summaries.append(summary)
        for summary in summaries:
            assert summary["joint_tiles_applied"] > 0 and summary["link"]["counts"]["joint_tracks"] > 0
            assert summary["link"]["counts"].get("reconnects", 0) >= 1, summary
            assert summary["link"]["rejected"].get("internal_error", 0) == 0
            # every joint message of the real server passes the agent's validation
            assert set(summary["link"]["rejected"]) <= {"stale"}
    finally:
        for proc in agents:
            if proc.poll() is None:
                proc.kill()
        if fusion.poll() is None:
            fusion.kill()

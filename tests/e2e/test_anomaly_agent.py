"""`uavmm agent --dataset DIR --anomaly METHOD` against a real `uavmm fusion`: the agent runs anomaly detection
on the rendered frames and publishes its ground layer as tiles of class `anomaly`, which the server fuses and
serves like any class (REST and the map page's class list)."""

from __future__ import annotations

import httpx
import pytest

from tests.e2e.conftest import agent_cmd, finish, start_agent, start_fusion
from tests.netutil import free_port, wait_until
from uavmm.cli import main

pytestmark = pytest.mark.e2e


def test_agent_publishes_the_anomaly_layer_to_the_fusion_server(tmp_path):
    data = tmp_path / "sea"
    assert main(["sim", "sea", "--out", str(data), "--frames", "60", "--image-size", "320x180", "--render",
                 "--max-texture-px", "1024", "--quiet"]) == 0
    zenoh_port, http_port = free_port(), free_port()
    fusion, url = start_fusion(zenoh_port, http_port, "--no-db")
    agent = None
    try:
        agent = start_agent(agent_cmd(zenoh_port, "--dataset", str(data), "--anomaly", "median", "--loop"))
        with httpx.Client(base_url=url, timeout=10) as http:
            wait_until(lambda: "anomaly" in http.get("/healthz").json().get("classes", []), 30.0,
                     "class anomaly at the fusion server")
            tiles = wait_until(lambda: [t for t in http.get("/v1/joint/tiles", params={"cls": "anomaly"}).json()
                                      if t["max"] > 0], 30.0, "non-empty joint anomaly tiles")
            t = tiles[0]
            png = http.get(f"/v1/tiles/anomaly/{t['z']}/{t['x']}/{t['y']}.png")
            assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
        agent.terminate()
        code, summary, err = finish(agent, 30.0)
        assert code == 0, err[-2000:]
        assert summary["anomaly_frames"] > 0
    finally:
        for proc in (agent, fusion):
            if proc is not None and proc.poll() is None:
                proc.kill()

"""`uavmm fusion` as a real process: prints the map URL, survives a kill with its SQLite database
(global tracks, their history and the joint map come back), stops cleanly on SIGTERM."""

from __future__ import annotations

import signal
import time

import httpx
import pytest

from tests.e2e.conftest import start_fusion, stop
from tests.fusion_server.fake_agent import LAT, LON, TILE_X, TILE_Y, FakeAgent, blob
from tests.netutil import free_port, wait_until

pytestmark = pytest.mark.e2e


def test_restart_keeps_global_tracks_history_and_joint_map(tmp_path):
    zenoh_port, http_port = free_port(), free_port()
    db = tmp_path / "fusion.sqlite"
    proc, url = start_fusion(zenoh_port, http_port, "--db", str(db), "--ttl-s", "3")
    assert url == f"http://127.0.0.1:{http_port}/"
    try:
        agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{zenoh_port}")
        with httpx.Client(base_url=url, timeout=10) as http:
            for i in range(12):  # 2.4 s of tracks at 5 Hz: history rows once a second
                agent.tracks([(7, "person", LAT + i * 1e-6, LON)])
                agent.tile(blob(40, 40, value=0.5 + 0.02 * i))
                time.sleep(0.2)
            before = http.get("/v1/tracks").json()["features"]
            assert len(before) == 1 and len(before[0]["properties"]["history"]) >= 2
            assert http.get("/v1/joint/tiles").json()
        agent.close()
        time.sleep(1.0)  # > the 0.5 s flush interval, < the 3 s TTL: the joint tile is still current
        proc.kill()  # no clean shutdown: what was flushed must be enough
        proc.wait(timeout=10)

        proc, url = start_fusion(zenoh_port, http_port, "--db", str(db), "--ttl-s", "3")
        with httpx.Client(base_url=url, timeout=10) as http:
            tiles = http.get("/v1/joint/tiles").json()
            assert [(t["x"], t["y"]) for t in tiles] == [(TILE_X, TILE_Y)]
            after = http.get("/v1/tracks").json()["features"]
            assert [f["properties"]["gid"] for f in after] == [before[0]["properties"]["gid"]]
            props = after[0]["properties"]
            assert props["status"] == "lost" and props["members"] == [["uav-a", 7]]
            assert props["history"][: len(before[0]["properties"]["history"])] == before[0]["properties"]["history"]
            # the UAV comes back with the same local id: same global id
            agent = FakeAgent("uav-a", f"tcp/127.0.0.1:{zenoh_port}")
            agent.tracks([(7, "person", LAT, LON)])
            wait_until(lambda: http.get("/v1/tracks").json()["features"][0]["properties"]["status"] == "tracked", 5.0,
                     "the returning UAV's track tracked again")
            assert http.get("/v1/tracks").json()["features"][0]["properties"]["gid"] == props["gid"]
            agent.close()
        assert stop(proc, signal.SIGTERM, 15.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()

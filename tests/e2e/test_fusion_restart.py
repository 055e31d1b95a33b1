"""`uavmm fusion` as a real process: prints the map URL, survives a kill with its SQLite database
(global tracks, their history, the joint map and the UAVs with their last state come back), stops
cleanly on SIGTERM."""

from __future__ import annotations

import signal
import sqlite3
import time
from contextlib import closing

import httpx
import pytest

from tests.e2e.conftest import read_stderr, start_fusion, stop
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


def _committed_tile_t(db) -> float | None:
    """The ``t`` of the joint tile committed to the database (read-only; None while there is none)."""
    try:
        with closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0)) as conn:
            row = conn.execute("SELECT t FROM joint_tiles").fetchone()
    except sqlite3.Error:
        return None
    return None if row is None else row[0]


def test_sigkill_restores_the_uavs_with_their_last_state(tmp_path):
    """Regression (issue 17): a UAV's row and its last state went to the database on the fusion thread's
    0.5 s persistence tick, a flush behind the joint tiles it had just sent, so a SIGKILL after the
    tile was committed restored the tile and no UAV ("0 UAVs restored" after the sharded e2e's kill -9).
    Whatever a SIGKILL leaves must hold the UAVs as they stood when the tiles they sent were saved."""
    zenoh_port, http_port = free_port(), free_port()
    db = tmp_path / "fusion.sqlite"
    proc, url = start_fusion(zenoh_port, http_port, "--db", str(db), "--ttl-s", "30", "--coverage", "tile")
    try:
        agent = FakeAgent("uav-k", f"tcp/127.0.0.1:{zenoh_port}")
        t0 = time.time()
        agent.state(LAT, LON)
        agent.tile(blob(40, 40), t=t0)
        wait_until(lambda: _committed_tile_t(db) == t0, 10.0, "the first joint tile in the database")
        agent.state(LAT + 2e-4, LON + 1e-4)  # the UAV moved: this state is its last one
        agent.tile(blob(40, 40, value=0.6), t=t0 + 1.0)
        wait_until(lambda: _committed_tile_t(db) == t0 + 1.0, 10.0, "the tile sent after the last state")
        proc.kill()  # right after the commit that holds the tile sent after the last state
        proc.wait(timeout=10)
        agent.close()

        proc, url = start_fusion(zenoh_port, http_port, "--db", str(db), "--ttl-s", "30", "--coverage", "tile")
        with httpx.Client(base_url=url, timeout=10) as http:
            rows = {row["id"]: row for row in http.get("/v1/uavs").json()}
        assert set(rows) == {"uav-k"}, read_stderr(proc)[-2000:]
        state = rows["uav-k"]["state"]
        assert state is not None and (state["lat"], state["lon"]) == (LAT + 2e-4, LON + 1e-4)
        assert rows["uav-k"]["online"] is False and rows["uav-k"]["last_seen"] >= t0
        assert stop(proc, signal.SIGTERM, 15.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()

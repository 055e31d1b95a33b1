"""The database loses nothing it was given: a restart restores the UAV list and keeps the joint map
until its time to live; writes that fail are retried, shown in /healthz and /metrics, and land once
the disk takes them again (a real `uavmm fusion` process whose file size limit the test lowers)."""

from __future__ import annotations

import os
import resource
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.fusion_server.fake_agent import LAT, LON, TILE_X, TILE_Y, FakeAgent, blob
from tests.netutil import free_port, wait_until

REPO = Path(__file__).resolve().parents[2]
TILE = ("person", 18, TILE_X, TILE_Y)


def test_a_restart_restores_the_uav_list_and_keeps_the_joint_map_until_its_ttl(server_factory, agent_factory,
                                                                                 http_of, tmp_path):
    # probe: the UAV list was not persisted; the restored joint map was deleted after 2 s
    db = tmp_path / "f.sqlite"
    first = server_factory(db_path=db, ttl_s=1.0)
    agent = agent_factory("uav1")
    agent.state()
    agent.tile(blob(30, 30))
    wait_until(lambda: first.joint.get(TILE) is not None and first.uavs.snapshot()[0]["state"] is not None)
    agent.close()
    time.sleep(0.3)
    first.close()
    second = server_factory(db_path=db, ttl_s=1.0, restore_keep_s=5.0)
    http = http_of(second)
    rows = http.get("/v1/uavs").json()
    assert [r["id"] for r in rows] == ["uav1"] and not rows[0]["online"]
    assert rows[0]["state"]["lat"] == pytest.approx(LAT) and rows[0]["last_seen"] > time.time() - 30
    time.sleep(2.5)  # longer than the TTL: the restored tile is still served
    assert [(t["x"], t["y"]) for t in http.get("/v1/joint/tiles").json()] == [(TILE_X, TILE_Y)]
    wait_until(lambda: http.get("/v1/joint/tiles").json() == [], timeout_s=10.0)  # 5 s after its last update
    second.close()
    with sqlite3.connect(db) as conn:
        assert conn.execute("SELECT COUNT(*) FROM joint_tiles").fetchone()[0] == 0
        assert conn.execute("SELECT id FROM uavs").fetchall() == [("uav1",)]


def start_fusion(zenoh_port: int, http_port: int, db: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "uavmm", "fusion", "--listen", f"tcp/127.0.0.1:{zenoh_port}",
           "--http", f"127.0.0.1:{http_port}", "--db", str(db), "--no-multicast-scouting"]
    proc = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    line = proc.stdout.readline()
    if "map: http://" not in line:
        proc.kill()
        raise AssertionError(f"uavmm fusion did not start: {line!r}")
    return proc


@pytest.mark.e2e
def test_failed_writes_are_retried_shown_and_nothing_is_lost(tmp_path):
    # probe: a failed batch was dropped, not retried; /healthz said ok and no metric counted it
    zenoh_port, http_port = free_port(), free_port()
    db = tmp_path / "f.sqlite"
    proc = start_fusion(zenoh_port, http_port, db)
    agent = FakeAgent("uav1", f"tcp/127.0.0.1:{zenoh_port}")
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=10) as http:
            agent.tracks([(1, "person", LAT, LON)])
            wait_until(lambda: http.get("/healthz").json()["db"]["flushes"] > 0, timeout_s=10.0)
            # the disk is full: every write beyond 4 KiB of any file fails (Python ignores SIGXFSZ)
            resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
            for i in range(2, 12):  # new tracks while the database cannot be written
                agent.tracks([(i, "person", LAT + i * 1e-3, LON)])
                time.sleep(0.1)
            health = wait_until(lambda: (h := http.get("/healthz").json())["status"] == "degraded" and h)
            assert health["db"]["status"] == "failing" and health["db"]["pending"] > 0
            assert "Error" in health["db"]["last_error"]  # e.g. "OperationalError: disk I/O error"
            metrics = http.get("/metrics").text
            errors = [line for line in metrics.splitlines() if line.startswith("uavmm_fusion_db_write_errors_total")]
            assert errors and int(errors[0].split()[-1]) > 0
            resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
            wait_until(lambda: http.get("/healthz").json()["status"] == "ok", timeout_s=30.0)
            assert http.get("/healthz").json()["db"]["pending"] == 0
    finally:
        agent.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    with sqlite3.connect(db) as conn:
        members = [row[0] for row in conn.execute("SELECT members FROM tracks")]
    assert all(any(f'["uav1", {i}]' in m for m in members) for i in range(1, 12))


def test_a_database_that_cannot_even_be_opened_still_drains_the_tracker_into_a_bounded_queue(tmp_path, monkeypatch):
    # probe (audit): when connecting failed (the -shm file could not be made) the writer never pulled its sources, so
    # the tracker's history rows and ended tracks piled up unbounded (180k, then 360k rows: 36, then 73 MB at 1, 2 h);
    # when connecting worked but writing failed, every queued record held its whole history tuple
    import fusion_server.persistence as persistence
    from fusion_server.global_tracks import GlobalTracker
    from shared.messages import TrackItem, TracksMessage

    monkeypatch.setattr(persistence, "MAX_HISTORY_BACKLOG", 500)
    monkeypatch.setattr(persistence, "MAX_QUEUED_TRACKS", 40)
    now = [0.0]
    tracker = GlobalTracker(clock=lambda: now[0], wall=lambda: 1.7e9 + now[0], hold_s=1.0)
    store = persistence.FusionStore(tmp_path / "fusion.sqlite")
    store.sources.append(lambda: store.save_tracks(*tracker.drain_changes(), tracker.next_gid))
    store.path = tmp_path / "gone" / "fusion.sqlite"  # the folder went away: connecting fails from now on
    for step in range(600):  # 10 min of one new 20 s track every 5 s, a message a second
        alive = range(step // 5 - 3, step // 5 + 1)
        tracker.update(TracksMessage(uav="uav1", t=1.7e9 + now[0], tracks=tuple(
            TrackItem(id=i, cls="person", lat=48.0 + i * 1e-3, lon=9.0, score=0.7, vel_en=(0.0, 0.0))
            for i in alive if i >= 0)))
        tracker.expire()
        now[0] += 1.0
        if step % 10 == 9:
            assert not store._attempt()
    assert not tracker._history_out and not tracker._ended_pending  # drained although nothing could be written
    assert len(store._history) <= 500 and store.history_dropped > 0
    assert all(not r.history for r in store._tracks.values())
    # beyond 40 queued tracks the ended ones keep no members, but stay queued: dropped, the ones the database holds
    # alive would have stayed alive there (and been restored as live)
    ended = [r for r in store._tracks.values() if r.ended is not None]
    assert len(store._tracks) > 40 and len(ended) > 40
    assert sum(bool(r.members) for r in ended) <= 40 // 10  # those that ended since the last compaction
    assert store.health()["status"] == "failing"
    store.path = tmp_path / "fusion.sqlite"  # back: what the queue holds is written
    assert store._attempt() and store.pending() == 0
    import sqlite3

    conn = sqlite3.connect(tmp_path / "fusion.sqlite")
    alive = {gid for (gid,) in conn.execute("SELECT gid FROM tracks WHERE ended IS NULL")}
    conn.close()
    assert alive == {r.gid for r in tracker.records()}  # every track that ended says so in the database


@pytest.mark.parametrize("where", ["under-a-file", "proc"])
def test_a_db_path_sqlite_cannot_open_is_one_line_naming_it(tmp_path, where):
    # the contract audit (1 Dec 2026): --db /proc/x.sqlite ended in a traceback (sqlite3.OperationalError), exit 1;
    # a --db whose parent is a file said only "[Errno 17] File exists: ..." without naming --db's file
    from fusion_server.persistence import DatabaseProblem, FusionStore

    if where == "under-a-file":
        (tmp_path / "camera.json").write_text("{}")
        path = tmp_path / "camera.json" / "x.sqlite"
    else:
        path = Path("/proc/uavmm-test.sqlite")
    with pytest.raises(DatabaseProblem, match=rf"database {path} cannot be opened: .*--no-db"):
        FusionStore(path)
    if where == "under-a-file":
        assert (tmp_path / "camera.json").read_text() == "{}"  # nothing already stored is touched

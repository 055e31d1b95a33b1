"""Issue 17's acceptance on loopback: a Zenoh router, three `uavmm fusion --shard K/3` processes, a
`uavmm gateway` and six UAVs spread so that every shard owns some. The gateway serves the whole map;
a shard killed with SIGKILL shows degraded (its UAVs in /v1/uavs, /healthz) within 5 s while the others
keep serving; restarted with its database it resumes with its tiles and tracks; a track walked across a
region border keeps its global id as the gateway shows it. A Python session in router mode stands in
for zenohd (PITFALLS.md)."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import threading
import time
from contextlib import closing

import httpx
import numpy as np
import pytest
import zenoh

from shared.sharding import ShardSpec
from tests.e2e.conftest import read_stderr, start_until, stop, uavmm
from tests.fusion_server.fake_agent import GRID, LAT, LON, TILE_X, TILE_Y, FakeAgent, blob
from tests.netutil import free_port, wait_until

pytestmark = pytest.mark.e2e

N = 3
ZOOM = 16  # regions of 4 x 4 grid tiles


def _tiles_per_shard(spec: ShardSpec, per_shard: int = 2) -> list[tuple[int, tuple[int, int]]]:
    """(shard, grid tile) pairs near LAT/LON, ``per_shard`` tiles in distinct regions for each shard."""
    found: dict[int, list[tuple[int, int]]] = {k: [] for k in range(spec.count)}
    for dx in range(0, 96, 4):
        for dy in range(0, 96, 4):
            x, y = TILE_X + dx, TILE_Y + dy
            owner = spec.owner(GRID.z, x, y)
            if len(found[owner]) < per_shard:
                found[owner].append((x, y))
    assert all(len(v) == per_shard for v in found.values()), found
    return [(k, tile) for k in sorted(found) for tile in found[k]]


def _center(x: int, y: int) -> tuple[float, float]:
    west, south, east, north = GRID.tile_bounds(x, y)
    return 0.5 * (south + north), 0.5 * (west + east)


def _corners(x: int, y: int) -> tuple[tuple[float, float], ...]:
    west, south, east, north = GRID.tile_bounds(x, y)
    return ((north, west), (north, east), (south, east), (south, west))


def _walk(spec: ShardSpec, steps: int = 30) -> tuple[list[tuple[float, float]], int, int]:
    """Points east from LAT/LON across the first border between two shards: (points, shard before, after)."""
    lons = LON + np.arange(0, 0.05, 2e-5)
    xs, ys = GRID.tile_of(np.full(lons.shape, LAT), lons)
    owners = [spec.owner(GRID.z, int(x), int(y)) for x, y in zip(xs, ys, strict=True)]
    for i in range(1, len(owners)):
        if owners[i - 1] != owners[i]:
            return [(LAT, float(lon)) for lon in lons[i - steps // 2: i + steps // 2]], owners[i - 1], owners[i]
    raise AssertionError("no border between shards east of LAT/LON")


class Fleet:
    """Six fake UAVs over their tiles, publishing tile, state and tracks every 0.2 s from a thread."""

    def __init__(self, router: str, placed: list[tuple[int, tuple[int, int]]]) -> None:
        self.placed = placed
        self.agents = [FakeAgent(f"uav-{i}", router) for i in range(len(placed))]
        self.tiles_off: set[int] = set()  # agents whose tiles are paused
        self.extra: dict[int, list[tuple[int, str, float, float]]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            for i, (agent, (_, (x, y))) in enumerate(zip(self.agents, self.placed, strict=True)):
                lat, lon = _center(x, y)
                if i not in self.tiles_off:
                    agent.tile(blob(100, 100), x=x, y=y)
                agent.state(lat, lon, footprint=_corners(x, y))
                agent.tracks([(1, "person", lat, lon), *self.extra.get(i, [])])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for agent in self.agents:
            agent.close()


def _launch(cmd: list[str], what: str, ready: str) -> tuple[subprocess.Popen, str]:
    return start_until(cmd, ready, what=what, timeout_s=60.0)


def _shard_cmd(k: int, router: str, db) -> list[str]:
    return uavmm("--log-level", "INFO", "fusion", "--shard", f"{k}/{N}", "--region-zoom", str(ZOOM), "--db", str(db),
                 "--mode", "peer", "--connect", router, "--listen", f"tcp/127.0.0.1:{free_port()}",
                 "--no-multicast-scouting", "--http", "127.0.0.1:0", "--ttl-s", "3")


def _saved_tracks(db) -> int:
    """Alive tracks committed to a shard's database (read-only; 0 while it has none)."""
    try:
        with closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0)) as conn:
            return conn.execute("SELECT COUNT(*) FROM tracks WHERE ended IS NULL").fetchone()[0]
    except sqlite3.Error:
        return 0


def _tracks(http: httpx.Client) -> dict[tuple[str, int], int]:
    """(uav, local id) -> global id of the gateway's tracks."""
    found = {}
    for feature in http.get("/v1/tracks", params={"history": "false"}).json()["features"]:
        for uav, local in feature["properties"]["members"]:
            found[(uav, local)] = feature["properties"]["gid"]
    return found


def test_three_shards_a_gateway_and_six_uavs(tmp_path):
    spec = ShardSpec(0, N, ZOOM)
    placed = _tiles_per_shard(spec)
    router = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([router]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    procs: dict[str, subprocess.Popen] = {}
    fleet: Fleet | None = None
    with zenoh.open(conf):
        try:
            # start the three shards and the gateway together, then wait for their ready lines
            for k in range(N):
                procs[f"shard{k}"] = _launch(_shard_cmd(k, router, tmp_path / f"shard{k}.sqlite"), f"shard {k}",
                                             "uavmm fusion:")[0]
            gateway, line = _launch(uavmm("--log-level", "INFO", "gateway", "--shards", str(N), "--region-zoom",
                                          str(ZOOM), "--mode", "client", "--connect", router,
                                          "--no-multicast-scouting", "--http", "127.0.0.1:0"),
                                    "gateway", "map: http://")
            procs["gateway"] = gateway
            url = line.split("map: ", 1)[1].strip()
            fleet = Fleet(router, placed)
            with httpx.Client(base_url=url, timeout=10) as http:
                everything = {tile for _, tile in placed}

                def served():
                    health = http.get("/healthz").json()
                    tiles = {(t["x"], t["y"]) for t in http.get("/v1/joint/tiles").json()}
                    return health["status"] == "ok" and tiles == everything and len(_tracks(http)) == 6 and health

                health = wait_until(served, 30.0, "the gateway serving every shard's tiles and tracks")
                assert {k: v["status"] for k, v in health["shards"].items()} == {"0": "up", "1": "up", "2": "up"}
                objects = http.get("/v1/objects", params={"cls": "person", "min_score": 0.3}).json()["features"]
                assert len(objects) == 6
                for _, (x, y) in placed:
                    west, south, east, north = GRID.tile_bounds(x, y)
                    window = http.get("/v1/map", params={"cls": "person", "bbox": f"{west},{south},{east},{north}",
                                                         "encoding": "sparse"}).json()
                    assert max(window["cells"]["value"]) > 0.5
                    assert http.get(f"/v1/tiles/person/18/{x}/{y}.png").status_code == 200
                gids = _tracks(http)
                for i, (k, _) in enumerate(placed):
                    assert (gids[(f"uav-{i}", 1)] - 1) % N == k  # shard K's global ids are K+1+iN
                rows = {r["id"]: r for r in http.get("/v1/uavs").json()}
                assert {r["shard"] for r in rows.values()} == {0, 1, 2}

                # kill -9 one shard: degraded within 5 s, the others keep serving
                victim = 1
                victims = {f"uav-{i}" for i, (k, _) in enumerate(placed) if k == victim}
                # what a SIGKILL keeps is what was committed: wait until its tracks are (<= ~1 s after a change)
                wait_until(lambda: _saved_tracks(tmp_path / f"shard{victim}.sqlite") == len(victims), 10.0,
                           "the shard's tracks in its database")
                procs[f"shard{victim}"].kill()
                procs[f"shard{victim}"].wait(timeout=10)
                fleet.tiles_off = {i for i, (k, _) in enumerate(placed) if k == victim}

                def degraded():
                    health = http.get("/healthz").json()
                    rows = http.get("/v1/uavs").json()
                    marked = {r["id"] for r in rows if r["degraded"]}
                    return health["status"] == "degraded" and marked == victims and health

                health = wait_until(degraded, 5.0, "the dead shard's UAVs degraded")
                assert health["down"] == [victim] and health["shards"][str(victim)]["status"] == "down"
                others = {tile for k, tile in placed if k != victim}
                time.sleep(0.5)  # past the gateway's cache
                assert {(t["x"], t["y"]) for t in http.get("/v1/joint/tiles").json()} == others
                survivors = {key: gid for key, gid in gids.items() if key[0] not in victims}
                wait_until(lambda: _tracks(http) == survivors, 5.0, "the other shards' tracks alone")

                # restart it with its database: its tiles (restored, its UAVs' tiles still paused) and tracks
                procs[f"shard{victim}"] = _launch(_shard_cmd(victim, router, tmp_path / f"shard{victim}.sqlite"),
                                                  f"shard {victim} again", "uavmm fusion:")[0]
                wait_until(lambda: http.get("/healthz").json()["status"] == "ok", 10.0, "healthz ok again")
                wait_until(lambda: {(t["x"], t["y"]) for t in http.get("/v1/joint/tiles").json()} == everything,
                           10.0, "the restarted shard's restored tiles")
                seen: list[dict] = []
                wait_until(lambda: seen.append(_tracks(http)) or seen[-1] == gids, 10.0,
                           f"every track with its global id again: {gids}")
                assert not any(r["degraded"] for r in http.get("/v1/uavs").json())
                fleet.tiles_off = set()

                # a track walked across a region border keeps its global id
                points, before, after = _walk(spec)
                walker = next(i for i, (k, _) in enumerate(placed) if k == before)
                fleet.extra[walker] = [(99, "person", *points[0])]
                gid = wait_until(lambda: _tracks(http).get((f"uav-{walker}", 99)), 10.0, "the walker's track")
                assert (gid - 1) % N == before
                for point in points:
                    fleet.extra[walker] = [(99, "person", *point)]
                    time.sleep(0.1)

                def walked():
                    features = http.get("/v1/tracks", params={"history": "false"}).json()["features"]
                    mine = [f for f in features if [f"uav-{walker}", 99] in f["properties"]["members"]]
                    if len(mine) != 1:
                        return None
                    lon = mine[0]["geometry"]["coordinates"][0]
                    x, y = GRID.tile_of(LAT, lon)
                    # the track is the other shard's now
                    return spec.owner(GRID.z, int(x), int(y)) == after and mine[0]["properties"]["gid"]

                assert wait_until(walked, 5.0, "the walked track in the next shard's region") == gid
                assert sum(f["properties"]["gid"] == gid for f in http.get("/v1/tracks").json()["features"]) == 1
        finally:
            if fleet is not None:
                fleet.close()
            for proc in procs.values():
                if proc.poll() is None:
                    stop(proc, timeout_s=20)
    for name, proc in procs.items():
        assert proc.returncode in (0, -9), (name, proc.returncode, read_stderr(proc)[-2000:])

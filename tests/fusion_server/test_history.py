"""`/v1/history`: the global tracks over a time window, from the SQLite history or the live tracker."""

from __future__ import annotations

import time

import pytest

from fusion_server.replay import MAX_HISTORY_ROWS, history_window
from tests.fusion_server.fake_agent import LAT, LON
from tests.netutil import wait_until


def _walk(agent, steps: int = 12, dt: float = 0.1) -> list[float]:
    """One person walking east, a tracks message every dt; returns the wall times of the messages."""
    times = []
    for k in range(steps):
        agent.tracks([(1, "person", LAT, LON + k * 1e-5)])
        times.append(time.time())
        time.sleep(dt)
    return times


@pytest.mark.parametrize("with_db", [True, False])
def test_history_window_positions_and_range(server_factory, agent_factory, tmp_path, with_db):
    server = server_factory(ttl_s=1.0, track_history_interval_s=0.05, persist_interval_s=0.1,
                            db_path=tmp_path / "f.sqlite" if with_db else None)
    import httpx

    http = httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0)
    agent = agent_factory("uav-a")
    _walk(agent)

    previous: list = [None]

    def settled():
        """Eight rows or more, and the same answer twice 0.3 s apart (the last rows may still be landing)."""
        body = http.get("/v1/history").json()
        rows = body["features"][0]["properties"]["history"] if body["features"] else []
        same = body == previous[0]
        previous[0] = body
        if len(rows) >= 8 and same:
            return body
        time.sleep(0.3)
        return None

    body = wait_until(settled, 15.0, "eight history rows, settled")
    assert body["type"] == "FeatureCollection" and len(body["features"]) == 1
    rows = body["features"][0]["properties"]["history"]
    first, last = body["time_range"]
    assert first == rows[0][0] and last >= rows[-1][0] and first < last
    # the map as it stood in the middle of the walk: the last row at or before `until`, west of the end
    mid = rows[len(rows) // 2][0]
    at_mid = http.get("/v1/history", params={"until": mid}).json()["features"][0]
    assert all(r[0] <= mid for r in at_mid["properties"]["history"])
    assert at_mid["geometry"]["coordinates"] == [at_mid["properties"]["history"][-1][2],
                                                 at_mid["properties"]["history"][-1][1]]
    assert at_mid["geometry"]["coordinates"][0] < body["features"][0]["geometry"]["coordinates"][0]
    # since: rows from then on; a window after the last row is empty with no time range
    later = http.get("/v1/history", params={"since": mid}).json()["features"][0]["properties"]["history"]
    assert later and all(r[0] >= mid for r in later)
    empty = http.get("/v1/history", params={"since": last + 100}).json()
    assert empty["features"] == [] and empty["time_range"] is None
    light = http.get("/v1/history", params={"rows": False}).json()
    assert "history" not in light["features"][0]["properties"] and light["time_range"] == body["time_range"]
    assert http.get("/v1/history", params={"cls": "boat"}).json()["features"] == []
    http.close()


@pytest.mark.parametrize(("params", "status", "message"), [
    ({"since": 10, "until": 5}, 400, "since (10.0) is after until (5.0)"),
    ({"until": "nan"}, 400, "until must be a finite time"),
    ({"since": "soon"}, 422, ""),
    ({"cls": "a/b"}, 400, "bad cls"),
])
def test_history_rejects_bad_parameters(http, params, status, message):
    response = http.get("/v1/history", params=params)
    assert response.status_code == status and message in response.text


def test_history_window_drops_tracks_outside_and_bounds_the_rows():
    def track(gid, times):
        return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [0, 0]},
                "properties": {"gid": gid, "cls": "person", "history": [[t, 1.0, float(t)] for t in times]}}

    window = history_window([track(1, [1, 2, 3]), track(2, [10, 11])], 2, 3)
    assert [f["properties"]["gid"] for f in window["features"]] == [1]
    assert window["features"][0]["geometry"]["coordinates"] == [3.0, 1.0] and window["time_range"] == [2, 3]
    big = history_window([track(1, range(MAX_HISTORY_ROWS + 10)), track(2, range(10))], None, None)
    rows = [len(f["properties"]["history"]) for f in big["features"]]
    assert sum(rows) <= MAX_HISTORY_ROWS and all(n >= 1 for n in rows)
    assert big["features"][0]["properties"]["history"][-1][0] == MAX_HISTORY_ROWS + 9  # newest rows kept


def test_the_slider_poll_reads_each_tracks_ends_from_the_database_and_answers_as_the_full_read(tmp_path):
    # probe (audit): /v1/history?rows=false (every open map page, every 10 s) read every history row of the database:
    # 1.7 s and 194 MB a poll after a day. It now reads each track's first and last row in the window by the index.
    import random

    from fusion_server.global_tracks import TrackRecord
    from fusion_server.persistence import FusionStore
    from fusion_server.replay import stored_tracks

    db = tmp_path / "fusion.sqlite"
    store = FusionStore(db)
    rng = random.Random(7)
    t0 = 1.7e9
    for gid in range(1, 41):
        start = t0 + rng.uniform(0, 600)
        times = sorted(start + rng.uniform(0, 300) for _ in range(rng.randint(1, 30)))
        history = [(gid, t, 48.0 + rng.uniform(0, 1e-3), 9.0 + rng.uniform(0, 1e-3)) for t in times]
        rec = TrackRecord(gid=gid, cls=rng.choice(["person", "boat"]), lat=48.0, lon=9.0, score=0.7, vel_en=(0.0, 0.0),
                          created=times[0], last_update=times[-1], members=(("uav1", gid),),
                          ended=times[-1] if gid % 3 else None, history=())
        store.save_tracks([rec], history, gid + 1)
    assert store._attempt()
    store.close()
    # a track with two rows at one time (the review's case): its last row is the one written last, in both reads
    tie = TrackRecord(gid=99, cls="person", lat=48.0, lon=9.0, score=0.7, vel_en=(0.0, 0.0), created=t0 + 20,
                      last_update=t0 + 20, members=(("uav1", 99),), ended=None, history=())
    store = FusionStore(db)
    store.save_tracks([tie], [(99, t0 + 10, 48.0, 9.0), (99, t0 + 20, 48.1, 9.1), (99, t0 + 20, 48.2, 9.2)], 100)
    assert store._attempt()
    store.close()
    windows = [(None, None), (t0 + 200, None), (None, t0 + 400), (t0 + 100, t0 + 500), (t0 + 450, t0 + 455),
               (t0 + 2000, None), (t0 + 20, t0 + 20), (None, t0 + 20)]
    for cls in (None, "boat"):
        for since, until in windows:
            full = history_window(stored_tracks(db, [], cls=cls, since=since), since, until)
            ends = history_window(stored_tracks(db, [], cls=cls, since=since, until=until, ends_only=True), since,
                                  until)
            for answer in (full, ends):
                for feature in answer["features"]:
                    del feature["properties"]["history"]
            assert ends == full
            assert full["time_range"] is None if since == t0 + 2000 else cls is not None or full["time_range"]
            tied = [f for f in full["features"] if f["properties"]["gid"] == 99]
            if tied and cls is None:
                assert tied[0]["geometry"]["coordinates"] == [9.2, 48.2]

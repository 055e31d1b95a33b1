"""/v1/history through the gateway of a sharded deployment: the window (``until``) and ``ends_only`` go to the
shards, which answer with those rows only, and the merged answer is the one the full read gave, for every window,
class and ``rows``, a track handed over between the shards included. Two real shards with databases on loopback,
the real gateway over HTTP, and a shard of the older version (ignoring the new query fields) beside a new one."""

from __future__ import annotations

import json
import random
import sqlite3
import time
from pathlib import Path
from typing import Any

import httpx
import msgpack
import pytest
import zenoh

from fusion_server.config import FusionSettings, ZenohOptions
from fusion_server.gateway import Gateway
from fusion_server.global_tracks import TrackRecord
from fusion_server.history_export import read_history
from fusion_server.persistence import FusionStore
from fusion_server.replay import history_window
from fusion_server.server import FusionServer
from fusion_server.shard_tracks import (
    TrackQuery,
    decode_reply,
    decode_request,
    encode_reply,
    encode_request,
    merge_tracks,
)
from shared.keys import KeySpace
from shared.messages import MessageError
from tests.netutil import free_port, wait_until

KEYS = KeySpace()
ZOOM = 16
T0 = 1.7e9
HANDED = 1000  # rows on both shards, a row shared at the handover
TIED = 1001  # rows on both shards, two rows at its last time (shard 0)
TIED_ONE = 1002  # one shard only, two rows at its last time
WINDOWS = [(None, None), (T0 + 200, None), (None, T0 + 450), (T0 + 395, T0 + 405), (T0 + 450, T0 + 1300),
           (T0 + 100, T0 + 399), (T0 + 1500, T0 + 1500), (T0 + 1200, T0 + 1200), (T0 + 9000, None)]
Rows = list[tuple[int, float, float, float]]


def _seed() -> tuple[list[list[TrackRecord]], list[Rows]]:
    """Each shard's ended tracks and history rows (gid, t, lat, lon) in the order written."""
    rng = random.Random(11)
    records: list[list[TrackRecord]] = [[], []]
    rows: list[Rows] = [[], []]

    def add(shard: int, gid: int, cls: str, history: Rows) -> None:
        times = [t for _, t, _, _ in history]
        records[shard].append(TrackRecord(
            gid=gid, cls=cls, lat=history[-1][2], lon=history[-1][3], score=0.5 + 0.01 * shard, vel_en=(0.0, 0.0),
            created=min(times), last_update=max(times), members=((f"uav{shard}", gid),), ended=max(times),
            history=()))
        rows[shard].extend(history)

    for shard in (0, 1):
        for i in range(25):
            gid = shard + 1 + 2 * i
            start = T0 + rng.uniform(0, 3000)
            times = sorted(start + rng.uniform(0, 600) for _ in range(rng.randint(1, 40)))
            if len(times) > 3 and i % 4 == 0:  # a tie inside and at an end
                times[1], times[-2] = times[0], times[-1]
            add(shard, gid, rng.choice(["person", "boat"]),
                [(gid, t, 48.0 + rng.uniform(0, 1e-3), 9.0 + rng.uniform(0, 1e-3)) for t in times])
    # handed over at T0 + 400 from shard 0 to shard 1: the row of that moment on both
    add(0, HANDED, "person", [(HANDED, T0 + t, 47.0, 9.0 + t * 1e-6) for t in range(100, 401, 20)])
    add(1, HANDED, "person", [(HANDED, T0 + t, 47.0, 9.0 + t * 1e-6) for t in range(400, 801, 20)])
    # handed over at T0 + 1200 from shard 1 to shard 0, a different position there on each; two rows at its end
    add(1, TIED, "boat", [(TIED, T0 + t, 47.5, 9.5 + t * 1e-6) for t in range(1000, 1201, 50)])
    add(0, TIED, "boat", [(TIED, T0 + 1200, 47.6, 9.6), (TIED, T0 + 1350, 47.7, 9.7), (TIED, T0 + 1500, 48.2, 9.2),
                          (TIED, T0 + 1500, 48.1, 9.1)])
    add(1, TIED_ONE, "person", [(TIED_ONE, T0 + 1400, 47.0, 9.0), (TIED_ONE, T0 + 1500, 48.2, 9.2),
                                (TIED_ONE, T0 + 1500, 48.1, 9.1)])
    return records, rows


def _write_databases(folder: Path) -> list[Path]:
    records, rows = _seed()
    paths = []
    for shard in (0, 1):
        path = folder / f"shard{shard}.sqlite"
        store = FusionStore(path)
        store.save_tracks(records[shard], rows[shard], 2000)
        assert store._attempt()
        store.close()
        paths.append(path)
    return paths


class Recorder:
    """A shard's track source that notes every query it is asked (the real FusionServer's, wrapped)."""

    def __init__(self, source) -> None:
        self.source = source
        self.asked: list[TrackQuery] = []

    def __call__(self, request: TrackQuery) -> list[dict[str, Any]]:
        self.asked.append(request)
        return self.source(request)


def _shard(index: int, port: int, db: Path) -> tuple[FusionServer, Recorder]:
    options = ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port if index == 0 else free_port()}",),
                           connect=() if index == 0 else (f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    server = FusionServer(FusionSettings(zenoh=options, http_port=0, db_path=db, ttl_s=1.0, shard_index=index,
                                         shard_count=2, region_zoom=ZOOM))
    assert server.node.track_source is not None
    recorder = Recorder(server.node.track_source)
    server.node.track_source = recorder
    server.start(http=False)
    return server, recorder


def _gateway(port: int) -> Gateway:
    options = ZenohOptions(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False)
    gateway = Gateway(FusionSettings(zenoh=options, http_port=0, db_path=None, shard_count=2, region_zoom=ZOOM))
    gateway.start()
    return gateway


def _all_gids(dbs: list[Path]) -> set[int]:
    return {f["properties"]["gid"] for db in dbs for f in read_history(db).tracks}


def _wait_for_both(gateway: Gateway, dbs: list[Path]) -> None:
    """Until both shards answer the gateway (a first query may go out before the links are up)."""
    want = _all_gids(dbs)
    wait_until(lambda: {t.gid for t in gateway.shard_tracks.stored() or ()} == want, 15.0, "both shards' tracks")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Two shards over their seeded databases and a gateway; yields (gateway, dbs, recorders)."""
    dbs = _write_databases(tmp_path_factory.mktemp("gateway_history"))
    port = free_port()
    started: list[FusionServer] = []
    gateway: Gateway | None = None
    try:
        recorders = []
        for index in (0, 1):
            server, recorder = _shard(index, port, dbs[index])
            started.append(server)
            recorders.append(recorder)
        gateway = _gateway(port)
        _wait_for_both(gateway, dbs)
        yield gateway, dbs, recorders
    finally:
        if gateway is not None:
            gateway.close()
        for server in started:
            server.close()


def _params(cls: str | None, since: float | None, until: float | None, rows: bool) -> dict[str, Any]:
    params: dict[str, Any] = {"rows": "true" if rows else "false"}
    for name, value in (("cls", cls), ("since", since), ("until", until)):
        if value is not None:
            params[name] = value
    return params


def _get(gateway: Gateway, params: dict[str, Any]) -> dict[str, Any]:
    answer = httpx.get(gateway.url.rstrip("/") + "/v1/history", params=params, timeout=15)
    assert answer.status_code == 200, answer.text
    return answer.json()


def full_read(dbs: list[Path], cls: str | None, since: float | None, until: float | None,
              rows: bool) -> dict[str, Any]:
    """/v1/history as the gateway answered before: every shard's every row since ``since`` (the database read),
    through the wire, merged by gid, then cut to the window."""
    tracks = [track for shard, db in enumerate(dbs)
              for track in decode_reply(encode_reply(shard, 2, "stored",
                                                     read_history(db, cls=cls, since=since).tracks))[3]]
    window = history_window([track.to_feature() for track in merge_tracks(tracks)], since, until)
    if not rows:
        for feature in window["features"]:
            del feature["properties"]["history"]
    return json.loads(json.dumps(window))


def test_the_gateways_history_asks_the_shards_for_the_window_and_answers_as_the_full_read(cluster):
    gateway, dbs, recorders = cluster
    for recorder in recorders:
        recorder.asked.clear()
    cache_s, gateway.shard_tracks.cache_s = gateway.shard_tracks.cache_s, -1.0  # every request asks the shards
    try:
        for cls in (None, "person", "boat"):
            for since, until in WINDOWS:
                for rows in (False, True):
                    found = _get(gateway, _params(cls, since, until, rows))
                    assert found == full_read(dbs, cls, since, until, rows), (cls, since, until, rows)
    finally:
        gateway.shard_tracks.cache_s = cache_s
    everything = _get(gateway, {"rows": "false"})
    ends = {f["properties"]["gid"]: f["geometry"]["coordinates"] for f in everything["features"]}
    # the last row of a handed-over track is the last over both shards; where rows tie, the full read's
    assert ends[HANDED] == [9.0 + 800e-6, 47.0] and ends[TIED] == [9.2, 48.2] and ends[TIED_ONE] == [9.1, 48.1]
    # every shard was asked for the window itself, and for ends only when the rows are left out
    for recorder in recorders:
        stored = {q for q in recorder.asked if q.source == "stored"}
        for cls in (None, "person", "boat"):
            for since, until in WINDOWS:
                for rows in (False, True):
                    assert TrackQuery("stored", cls=cls, since=since, until=until, ends_only=not rows) in stored


def _raw(session: zenoh.Session, request: TrackQuery) -> dict[int, tuple[int, list]]:
    """Each shard's reply to ``request``: shard -> (payload bytes, its tracks)."""
    found = {}
    for reply in session.get(KEYS.shard_tracks("*", 2), target=zenoh.QueryTarget.ALL,
                             consolidation=zenoh.ConsolidationMode.NONE, payload=encode_request(request), timeout=10.0):
        assert reply.ok is not None
        payload = reply.ok.payload.to_bytes()
        shard, _, _, tracks = decode_reply(payload)
        found[shard] = (len(payload), tracks)
    assert set(found) == {0, 1}
    return found


def test_a_poll_without_rows_carries_only_each_tracks_ends_from_every_shard(cluster):
    gateway, dbs, _ = cluster
    session = gateway.node.session
    full = _raw(session, TrackQuery("stored"))
    ends = _raw(session, TrackQuery("stored", ends_only=True))
    windowed = _raw(session, TrackQuery("stored", since=T0 + 100, until=T0 + 399))
    for shard in (0, 1):
        full_bytes, full_tracks = full[shard]
        ends_bytes, ends_tracks = ends[shard]
        assert [t.gid for t in ends_tracks] == [t.gid for t in full_tracks]  # every track, its properties
        assert sum(len(t.history) for t in full_tracks) > 5 * sum(len(t.history) for t in ends_tracks)
        assert ends_bytes < full_bytes / 2
        for whole, cut in zip(full_tracks, ends_tracks, strict=True):
            times = [row[0] for row in whole.history]
            assert [row for row in whole.history if row[0] in (min(times), max(times))] == list(cut.history)
        assert all(T0 + 100 <= row[0] <= T0 + 399 for t in windowed[shard][1] for row in t.history)
    # merged over both shards, the ends of a handed-over track are the ends of its whole history
    merged = {t.gid: t for t in gateway.shard_tracks.stored(ends_only=True)}
    assert [row[0] for row in merged[HANDED].history] == [T0 + 100, T0 + 400, T0 + 800]  # the shared row once
    assert merged[TIED].history[0] == (T0 + 1000, 47.5, 9.5 + 1000e-6)
    assert merged[TIED].history[-2:] == ((T0 + 1500, 48.1, 9.1), (T0 + 1500, 48.2, 9.2))


def test_rows_and_windows_are_cached_apart(cluster):
    gateway, dbs, _ = cluster
    tracks = gateway.shard_tracks
    cache_s = tracks.cache_s
    tracks.cache_s = 60.0
    try:
        since = T0 + 1.25  # a window asked nowhere else in this module
        asked = tracks.queries
        assert _get(gateway, _params(None, since, None, False)) == full_read(dbs, None, since, None, False)
        assert _get(gateway, _params(None, since, None, False)) == full_read(dbs, None, since, None, False)
        assert tracks.queries == asked + 1  # the same poll: from the cache
        assert _get(gateway, _params(None, since, None, True)) == full_read(dbs, None, since, None, True)
        assert _get(gateway, _params(None, since, T0 + 450, True)) == full_read(dbs, None, since, T0 + 450, True)
        assert tracks.queries == asked + 3  # rows and another until: asked again, never the ends' answer
    finally:
        tracks.cache_s = cache_s


class OlderShard:
    """Shard K of 2 as the version before this query field answered: a Zenoh queryable reading only the fields it
    knew (source, cls, since) and replying with every row since ``since`` from its database."""

    def __init__(self, session: zenoh.Session, index: int, db: Path) -> None:
        self.index = index
        self.db = db
        self.payloads: list[dict[str, Any]] = []
        self.key = KEYS.shard_tracks(index, 2)
        self.queryable = session.declare_queryable(self.key, self.on_query)

    def on_query(self, query: zenoh.Query) -> None:
        try:
            body = msgpack.unpackb(query.payload.to_bytes()) if query.payload is not None else {}
            self.payloads.append(body)
            if body.get("source") == "stored":
                features = read_history(self.db, cls=body.get("cls"), since=body.get("since")).tracks
                query.reply(self.key, encode_reply(self.index, 2, "stored", features))
        finally:
            query.drop()


def test_a_shard_of_the_older_version_ignores_the_window_and_the_answer_is_the_same(tmp_path):
    dbs = _write_databases(tmp_path)
    port = free_port()
    new, _ = _shard(0, port, dbs[0])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    gateway: Gateway | None = None
    try:
        with zenoh.open(conf) as session:
            old = OlderShard(session, 1, dbs[1])
            gateway = _gateway(port)
            _wait_for_both(gateway, dbs)
            for cls in (None, "boat"):
                for since, until in WINDOWS:
                    for rows in (False, True):
                        found = _get(gateway, _params(cls, since, until, rows))
                        assert found == full_read(dbs, cls, since, until, rows), (cls, since, until, rows)
            # the older shard was sent the new fields and answered without them
            assert any(body.get("ends_only") is True for body in old.payloads)
            assert any(body.get("until") == T0 + 450 for body in old.payloads)
            # and a gateway of the older version (no until, no ends_only) gets every row since `since` from a new shard
            older_query = msgpack.packb({"v": 1, "source": "stored", "ended": False, "since": T0 + 200})
            replies = list(session.get(KEYS.shard_tracks(0, 2), payload=older_query, timeout=10.0))
            assert len(replies) == 1 and replies[0].ok is not None
            _, _, _, tracks = decode_reply(replies[0].ok.payload.to_bytes())
            assert [t.to_feature() for t in tracks] == read_history(dbs[0], since=T0 + 200).tracks
    finally:
        if gateway is not None:
            gateway.close()
        new.close()


def test_the_query_carries_until_and_ends_only_only_when_set_and_checks_them():
    asked = TrackQuery("stored", cls="person", since=T0, until=T0 + 60, ends_only=True)
    assert decode_request(encode_request(asked)) == asked
    # a query without them is the older version's payload, byte for byte; one without them decodes to the defaults
    plain = TrackQuery("stored", cls="person", since=T0)
    assert msgpack.unpackb(encode_request(plain)) == {"v": 1, "source": "stored", "ended": False, "cls": "person",
                                                      "since": T0}
    older = decode_request(msgpack.packb({"v": 1, "source": "stored", "since": T0}))
    assert (older.until, older.ends_only) == (None, False)
    newer = decode_request(msgpack.packb({"v": 1, "source": "stored", "until": T0, "rows_max": 5}))
    assert newer == TrackQuery("stored", until=T0)  # a field it does not know is ignored
    for body, reason in (({"until": float("inf")}, "non_finite"), ({"until": "soon"}, "bad_type"),
                         ({"ends_only": 1}, "bad_type"), ({"since": T0 + 1, "until": T0}, "out_of_range")):
        with pytest.raises(MessageError) as info:
            decode_request(msgpack.packb({"v": 1, "source": "stored", **body}))
        assert info.value.reason == reason


def test_a_window_cut_of_the_full_read_is_the_databases_own_ends_read(tmp_path):
    # the shard's queryable cuts whatever its source read (window_rows); the database reads the ends by its index:
    # the two must agree, rows at a tied first or last time included
    from fusion_server.replay import window_rows

    dbs = _write_databases(tmp_path)
    started = time.monotonic()
    for db in dbs:
        for cls in (None, "person"):
            for since, until in WINDOWS:
                full = read_history(db, cls=cls, since=since).tracks
                for ends_only in (False, True):
                    read = read_history(db, cls=cls, since=since, until=until, ends_only=ends_only).tracks
                    assert window_rows(full, since, until, ends_only) == read, (db.name, cls, since, until, ends_only)
                    assert window_rows(read, since, until, ends_only) == read  # cutting again changes nothing
    tied = {f["properties"]["gid"]: f["properties"]["history"] for f in read_history(dbs[0], ends_only=True).tracks}
    assert tied[TIED] == [[T0 + 1200, 47.6, 9.6], [T0 + 1500, 48.2, 9.2], [T0 + 1500, 48.1, 9.1]]
    assert time.monotonic() - started < 30.0


def test_the_ends_read_keeps_a_tied_ends_rows_and_seeks_them_without_scanning_the_rows(tmp_path, monkeypatch):
    # a join SQLite may reorder: the ends read with ties ran over every history row (0.19 s, not 4 ms, at 324k rows)
    db = tmp_path / "many.sqlite"
    store = FusionStore(db)
    for gid in range(1, 201):
        rows = [(gid, T0 + gid + s, 48.0, 9.0) for s in range(200)] + [(gid, T0 + gid + 199, 48.5, 9.5)]
        store.save_tracks([TrackRecord(gid=gid, cls="person", lat=48.0, lon=9.0, score=0.5, vel_en=(0.0, 0.0),
                                       created=rows[0][1], last_update=rows[-1][1], members=(("uav1", gid),),
                                       ended=rows[-1][1], history=())], rows, 300)
    assert store._attempt()
    store.close()
    steps = [0]
    connect = sqlite3.connect

    def counted(*args: Any, **kwargs: Any) -> sqlite3.Connection:
        conn = connect(*args, **kwargs)
        conn.set_progress_handler(lambda: steps.__setitem__(0, steps[0] + 1), 100)  # every 100 VM steps
        return conn

    monkeypatch.setattr(sqlite3, "connect", counted)
    work = {}
    for ends_only in (False, True):
        steps[0] = 0
        found = read_history(db, ends_only=ends_only).tracks
        work[ends_only] = steps[0]
    assert work[True] * 10 < work[False], work  # 40,200 rows against 2 seeks of 200 tracks (27 x less work)
    assert [f["properties"]["history"] for f in found] == [
        [[T0 + gid, 48.0, 9.0], [T0 + gid + 199, 48.0, 9.0], [T0 + gid + 199, 48.5, 9.5]] for gid in range(1, 201)]


def test_the_trackers_features_are_built_only_when_no_database_answers(tmp_path):
    from fusion_server.replay import stored_tracks

    db = _write_databases(tmp_path)[0]
    built: list[int] = []
    live = [{"type": "Feature", "properties": {"gid": 7, "cls": "person", "history": []}}]

    def features() -> list[dict[str, Any]]:
        built.append(1)
        return live

    assert stored_tracks(db, features, cls=None, since=None, ends_only=True) == read_history(db, ends_only=True).tracks
    assert built == []  # the database answered: the tracker's features were never made
    assert stored_tracks(tmp_path / "none.sqlite", features, cls="person", since=None) == live and built == [1]
    assert stored_tracks(None, live, cls="boat", since=None) == []  # a list still does

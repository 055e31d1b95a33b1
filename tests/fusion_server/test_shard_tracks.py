"""fusion_server.shard_tracks: the tracks-with-history query between the shards and the gateway (codec,
merging a handed-over id's copies, the shard's queryable and the gateway's client over real Zenoh)."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import msgpack
import pytest
import zenoh

from fusion_server.global_tracks import TrackRecord
from fusion_server.shard_tracks import (
    ShardTrack,
    TrackQuery,
    TracksQueryable,
    decode_reply,
    decode_request,
    encode_reply,
    encode_request,
    merge_tracks,
)
from fusion_server.shard_tracks_client import ShardTracks
from shared.keys import KeySpace
from shared.messages import MESSAGE_ERROR_REASONS, MessageError
from tests.netutil import free_port, wait_until

KEYS = KeySpace()


def record(gid: int, *, active=(("a", 1),), ended=None, history=((10.0, 47.0, 9.0), (11.0, 47.001, 9.0)),
           created=10.0, last_update=11.0, members=(("a", 1),)) -> TrackRecord:
    return TrackRecord(gid=gid, cls="person", lat=47.001, lon=9.0, score=0.9, vel_en=(0.5, -0.25), created=created,
                       last_update=last_update, members=members, active=active, ended=ended, history=history)


def stored_feature(gid: int) -> dict[str, Any]:
    """A stored track as fusion_server.history_export.read_history lists it (no active_members)."""
    return {"type": "Feature", "id": gid, "geometry": {"type": "Point", "coordinates": [9.0, 47.0]},
            "properties": {"gid": gid, "cls": "person", "score": 0.8, "vel_en": [0.0, 0.0], "status": "tracked",
                           "created": 1.0, "last_update": 2.0, "ended": None, "members": [["a", 3]],
                           "history": [[1.0, 47.0, 9.0], [2.0, 47.0, 9.0]]}}


def test_a_reply_carries_the_features_as_the_shards_rest_api_lists_them():
    live = [record(1).to_geojson(), record(4, active=()).to_geojson(), record(7, active=(), ended=12.0).to_geojson()]
    shard, count, source, tracks = decode_reply(encode_reply(1, 3, "live", live))
    assert (shard, count, source) == (1, 3, "live")
    assert [t.to_feature() for t in tracks] == live  # the same GeoJSON, key for key
    assert [t.to_record().status for t in tracks] == ["tracked", "lost", "ended"]
    assert [t.to_record() for t in tracks] == [record(1), record(4, active=()), record(7, active=(), ended=12.0)]
    _, _, _, (stored,) = decode_reply(encode_reply(0, 3, "stored", [stored_feature(5)]))
    assert stored.to_feature() == stored_feature(5) and stored.active_members is None


def _reply(**track: Any) -> bytes:
    body = msgpack.unpackb(encode_reply(0, 2, "live", [record(1).to_geojson()]))
    body["tracks"][0].update(track)
    return msgpack.packb(body, use_bin_type=True)


@pytest.mark.parametrize(("payload", "reason"), [
    (msgpack.packb({"v": 2, "shard": 0, "shards": 1, "source": "live", "tracks": []}), "bad_version"),
    (msgpack.packb({"v": 1, "shard": 2, "shards": 2, "source": "live", "tracks": []}), "out_of_range"),
    (msgpack.packb({"v": 1, "shard": 0, "shards": 2, "source": "all", "tracks": []}), "out_of_range"),
    (msgpack.packb({"v": 1, "shard": 0, "shards": 2, "source": "live", "tracks": [1]}), "not_a_map"),
    (_reply(history=b"\x00" * 23), "bad_length"),
    (_reply(history=[[1.0, 47.0, 9.0]]), "bad_type"),
    (_reply(history=msgpack.unpackb(encode_reply(0, 1, "live", [record(
        1, history=((float("nan"), 47.0, 9.0),)).to_geojson()]))["tracks"][0]["history"]), "non_finite"),
    (_reply(status="gone"), "out_of_range"),
    (_reply(active_members=[["b", 2]]), "out_of_range"),
    (_reply(lat=91.0), "out_of_range"),
    (_reply(gid=True), "bad_type"),
    (b"\xc1", "not_msgpack"),
])
def test_malformed_replies_are_refused_with_a_reason(payload: bytes, reason: str):
    with pytest.raises(MessageError) as info:
        decode_reply(payload)
    assert info.value.reason == reason and reason in MESSAGE_ERROR_REASONS


def test_requests_round_trip_and_an_empty_query_asks_for_the_live_tracks():
    for request in (TrackQuery(), TrackQuery(ended=True), TrackQuery("stored", cls="person", since=12.5)):
        assert decode_request(encode_request(request)) == request
    assert decode_request(None) == TrackQuery() == decode_request(b"")
    with pytest.raises(MessageError):
        decode_request(msgpack.packb({"v": 1, "source": "everything"}))
    with pytest.raises(MessageError):
        decode_request(msgpack.packb({"v": 1, "cls": "a/b"}))


def _track(gid: int, **fields: Any) -> ShardTrack:
    _, _, _, (track,) = decode_reply(encode_reply(0, 1, "live", [record(gid, **fields).to_geojson()]))
    return track


def test_the_copies_of_a_handed_over_id_merge_into_one_track_with_the_whole_history():
    # the shard the object left: its held copy, ended when the other shard took the id on
    before = _track(5, active=(), ended=30.0, created=10.0, last_update=20.0, members=(("a", 1),),
                    history=((10.0, 47.0, 9.0), (15.0, 47.0, 9.001), (20.0, 47.0, 9.002)))
    after = _track(5, active=(("a", 1),), created=21.0, last_update=29.0, members=(("a", 1), ("b", 4)),
                   history=((20.0, 47.0, 9.002), (25.0, 47.0, 9.003), (29.0, 47.0, 9.004)))
    other = _track(8)
    merged = merge_tracks([after, other, before])
    assert [t.gid for t in merged] == [5, 8] and merged[1] == other
    track = merged[0]
    assert track.status == "tracked" and track.ended is None and track.active_members == (("a", 1),)
    assert (track.created, track.last_update) == (10.0, 29.0)
    assert track.members == (("a", 1), ("b", 4))
    assert [row[0] for row in track.history] == [10.0, 15.0, 20.0, 25.0, 29.0]  # the shared row once
    assert [row[0] for row in merge_tracks([before, after], history_len=2)[0].history] == [25.0, 29.0]


@pytest.fixture
def sessions():
    port = free_port()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    other = zenoh.Config()
    other.insert_json5("mode", '"peer"')
    other.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    other.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as shard_side, zenoh.open(other) as gateway_side:
        # connected before the first query (under load the link came up after it and the query went unanswered)
        wait_until(lambda: list(gateway_side.info.peers_zid()), 10.0, "the two sessions to connect")
        yield shard_side, gateway_side


def test_two_shards_answer_the_gateway_from_their_workers_and_bad_queries_get_errors(sessions):
    shard_side, gateway_side = sessions
    asked: list[TrackQuery] = []

    def source_of(shard: int):
        def source(request: TrackQuery) -> list[dict[str, Any]]:
            asked.append(request)
            if request.source == "stored":
                return [stored_feature(10 + shard)]
            return [record(shard + 1).to_geojson()] + ([record(9, active=(), ended=5.0).to_geojson()]
                                                        if request.ended else [])
        return source

    queryables = [TracksQueryable(source_of(k), KEYS.shard_tracks(k, 2), k, 2) for k in range(2)]
    declared = []
    for queryable in queryables:
        queryable.start()
        declared.append(shard_side.declare_queryable(queryable.key, queryable.on_query))
    try:
        # both queryables known on the gateway's side before the client asks (the declarations travel
        # after the link is up; under load the first query went out before them and nobody answered)
        wait_until(lambda: sum(r.ok is not None for r in gateway_side.get(
            KEYS.shard_tracks("*", 2), payload=encode_request(TrackQuery()), timeout=2.0)) == 2,
            20.0, "both shards' queryables to reach the gateway")
        client = ShardTracks(KEYS, 2, cache_s=60.0)
        assert client.live() is None  # no session yet: nobody asked
        client.session = gateway_side
        live = client.live()
        assert live is not None and [t.gid for t in live] == [1, 2]
        assert [t.gid for t in client.live(include_ended=True) or []] == [1, 2, 9]
        assert client.live() is live and client.queries == 2  # cached
        stored = client.stored(cls="person", since=1.0)
        assert stored is not None and [t.gid for t in stored] == [10, 11]
        assert TrackQuery("stored", cls="person", since=1.0) in asked
        # a malformed query is answered with an error, not a crash
        replies = list(gateway_side.get(KEYS.shard_tracks("*", 2), payload=b"\x01\x02", timeout=5.0))
        assert len(replies) == 2 and all(r.err is not None for r in replies)
        assert all(q.refused == 1 for q in queryables)
        other_count = ShardTracks(KEYS, 3, cache_s=0.0)  # a gateway of another N hears nobody
        other_count.session = gateway_side
        assert other_count.live() is None
    finally:
        for entity in declared:
            entity.undeclare()
        for queryable in queryables:
            queryable.close()


def test_queries_nobody_answers_leave_nothing_behind():
    """Review finding: one lock per distinct query was kept until the answer cache passed 64 entries, and a query no
    shard answers caches nothing: 50,000 /v1/history windows with every shard down held 50,000 locks (12 MB)."""
    tracks = ShardTracks(KeySpace(), 2)  # no session: as when every shard is down
    for i in range(2_000):
        assert tracks.stored(None, 1.7e9, 1.7e9 + i, True) is None
    assert tracks._asking == {} and tracks._cache == {}


@pytest.mark.parametrize(("source", "delays_s", "missing"), [
    ("live", (0.0, 1.2), (1,)),  # live: 0.5 s after the first answer
    ("stored", (0.0, 1.2), (1,)),  # stored: as long again as the first took, at least 0.5 s
    ("stored", (0.8, 1.4), ()),  # a database read as slow as the first one's is still waited for
])
def test_a_shard_answering_late_is_left_out_soon_after_the_first_answer_and_named(sessions, source, delays_s,
                                                                                   missing):
    """Before: the gateway waited the query's whole timeout (2 s live, 5 s stored) for a shard that did not answer,
    and said nothing of it; now it answers `late_answer_s` after the first answer, naming the shard."""
    import time

    shard_side, gateway_side = sessions

    def source_of(shard: int):
        def answer(request: TrackQuery) -> list[dict[str, Any]]:
            time.sleep(delays_s[shard])
            return [stored_feature(10 + shard)] if request.source == "stored" else [record(shard + 1).to_geojson()]
        return answer

    queryables = [TracksQueryable(source_of(k), KEYS.shard_tracks(k, 2), k, 2) for k in range(2)]
    declared = []
    for queryable in queryables:
        queryable.start()
        declared.append(shard_side.declare_queryable(queryable.key, queryable.on_query))
    try:
        wait_until(lambda: sum(r.ok is not None for r in gateway_side.get(
            KEYS.shard_tracks("*", 2), payload=encode_request(TrackQuery()), timeout=5.0)) == 2,
            20.0, "both shards' queryables to reach the gateway")
        client = ShardTracks(KEYS, 2, cache_s=0.0)
        client.session = gateway_side
        started = time.monotonic()
        found = client.live() if source == "live" else client.stored()
        took = time.monotonic() - started
        assert found is not None and found.missing == missing
        assert len(found) == 2 - len(missing)
        first = delays_s[0]
        bound = first + max(0.5, first if source == "stored" else 0.0)
        assert took < (bound if missing else delays_s[1]) + 0.4, took
    finally:
        for entity in declared:
            entity.undeclare()
        for queryable in queryables:
            queryable.close()


def test_close_ends_a_wait_for_silent_shards_at_once(sessions):
    import threading
    import time

    shard_side, gateway_side = sessions
    held: list[zenoh.Query] = []
    silent = shard_side.declare_queryable(KEYS.shard_tracks(0, 2), held.append)
    try:
        wait_until(lambda: gateway_side.get(KEYS.shard_tracks("*", 2), timeout=0.2) and held, 20.0, "the queryable")
        client = ShardTracks(KEYS, 2, cache_s=0.0)
        client.session = gateway_side
        threading.Timer(0.3, client.close).start()
        started = time.monotonic()
        assert client.stored() is None
        assert time.monotonic() - started < 0.8  # not the query's 5 s
        assert client.live() is None and client.queries == 1  # closed: nothing more asked
    finally:
        silent.undeclare()
        held.clear()


def test_a_copy_stamped_ahead_of_the_gateways_clock_is_left_out_and_counted(sessions):
    """Probe: a reply (a peer without the ACL answering as shard 1, or a shard whose clock runs an hour ahead)
    holding gid 1 with last_update an hour ahead was the merge's primary copy: the gateway served gid 1 at the
    forged place, hiding the honest shard's copy."""
    shard_side, gateway_side = sessions
    now = 1_700_000_000.0
    honest = record(1, created=now - 20.0, last_update=now - 1.0)
    forged = dataclasses.replace(honest, lat=10.0, last_update=now + 3600.0)
    # history rows stamped ahead on a copy updated on time: the merge keeps the newest rows, the honest ones pushed out
    pushed = record(3, created=now - 20.0, last_update=now - 1.0, history=((now - 20.0, 47.0, 9.0), (1e12, 10.0, 9.0)))
    answers = {0: [honest.to_geojson(), record(3, created=now - 20.0, last_update=now - 1.0).to_geojson()],
               1: [forged.to_geojson(), record(2, created=now, last_update=now + 2.0).to_geojson(),
                   pushed.to_geojson()]}
    queryables = [TracksQueryable(lambda request, k=k: answers[k], KEYS.shard_tracks(k, 2), k, 2) for k in range(2)]
    declared = []
    for queryable in queryables:
        queryable.start()
        declared.append(shard_side.declare_queryable(queryable.key, queryable.on_query))
    try:
        wait_until(lambda: sum(r.ok is not None for r in gateway_side.get(
            KEYS.shard_tracks("*", 2), payload=encode_request(TrackQuery()), timeout=2.0)) == 2,
            20.0, "both shards' queryables to reach the gateway")
        rejected: list[str] = []
        client = ShardTracks(KEYS, 2, cache_s=0.0, on_reject=rejected.append, max_ahead_s=5.0, wall=lambda: now)
        client.session = gateway_side
        live = client.live()
        assert live is not None and [t.gid for t in live] == [1, 2, 3]  # gid 2, 2 s ahead: within the skew
        assert live[0].lat == honest.lat and live[0].last_update == now - 1.0
        assert max(row[0] for row in live[2].history) < now  # the copy with rows stamped ahead left out
        assert rejected == ["t_in_future"] and not live.missing  # shard 1 answered: only its forged copies are out
        trusting = ShardTracks(KEYS, 2, cache_s=0.0)  # without the bound (as before): the forged copy wins
        trusting.session = gateway_side
        assert (trusting.live() or [])[0].lat == 10.0
    finally:
        for entity in declared:
            entity.undeclare()
        for queryable in queryables:
            queryable.close()

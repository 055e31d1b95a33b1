"""Global tracks with their history, from the fusion shards to the gateway, by Zenoh queries.

A region tracks message says where each global track is and which of its members still report it
(``JointTrackItem.active``), not since when it exists nor where it went. So each shard (``uavmm fusion
--shard K/N``) answers queries on ``{prefix}/fusion/tracks/{N}/{K}`` (``KeySpace.shard_tracks``) with
its global tracks as its own REST API would list them (:class:`TrackQuery`): ``live``, the tracks of
``/v1/tracks`` with their history (``ended``: also the recently ended ones), or ``stored``, the tracks
of ``/v1/history`` from its database (``cls``, ``since``; its rows cut to ``until``, and with ``ends_only``
to each track's ends: the map page's poll). The gateway (`fusion_server.shard_tracks_client.ShardTracks`) asks
every shard at once, checks each reply (a bad one is dropped and counted, never raised), merges the
copies of one global id (after a handover across a region border each shard holds part of its life:
the histories are joined) and reuses an answer ``cache_s`` seconds. A shard that does not answer (its
process frozen or cut off until its lease ends: its queryable is still declared) is waited for only a
while after the first answer (`late_answer_s`), not for the whole query, and the answer names it
(``ShardAnswer.missing``). A shard answers from a worker
thread (:class:`TracksQueryable`), never on a Zenoh thread: reading a long history must not hold up
the tiles.

Wire (msgpack): the query's payload, optional, ``{"v": 1, "source": "live"|"stored", "ended": bool,
"cls": str, "since": float, "until": float, "ends_only": bool}`` (``cls``, ``since`` and ``until`` only when
set, ``ends_only`` only when true: a shard of the older version ignores the keys it does not know and
answers with every row since ``since``, which the gateway cuts to the window all the same); a reply
``{"v": 1, "shard": K, "shards": N, "source", "tracks": [...]}`` with one map per track: the properties of
its ``/v1/tracks`` feature (``gid, cls, score, vel_en, status, created, last_update, ended, members``,
``active_members`` when the shard lists them), its position ``lat, lon`` and ``history`` as bytes: float64
little-endian rows (t, lat, lon).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import zenoh

from fusion_server.global_tracks import TrackRecord
from fusion_server.replay import window_rows
from shared.messages import (
    VERSION,
    MessageError,
    check_float,
    check_int,
    check_members,
    check_name,
    check_version,
    get_field,
    unpack_map,
)
from transport.guard import RateLimitedLog

__all__ = [
    "DEFAULT_CACHE_S",
    "MAX_HISTORY_ROWS",
    "ShardAnswer",
    "ShardTrack",
    "TrackQuery",
    "TracksQueryable",
    "decode_reply",
    "decode_request",
    "encode_reply",
    "encode_request",
    "merge_tracks",
]

log = logging.getLogger(__name__)

#: How long the gateway reuses the shards' answer, seconds (region messages come twice a second).
DEFAULT_CACHE_S = 0.5
#: Longest wait for the shards' replies, seconds: live tracks, and stored history (a database read).
LIVE_TIMEOUT_S = 2.0
STORED_TIMEOUT_S = 5.0
#: After the first shard's answer, the others are waited for this much longer, seconds (/healthz's bound): a shard
#: that does not answer then held every /v1/history for the whole 5 s query (and a gateway's SIGTERM with it).
LATE_ANSWER_S = 0.5
#: Most history rows one track of a reply may carry.
MAX_HISTORY_ROWS = 100_000
#: Most tracks one reply may carry, and its largest size in bytes.
MAX_TRACKS = 200_000
MAX_REPLY_BYTES = 512 * 1024 * 1024
#: Queries a shard holds for its worker; beyond, it answers "busy" at once.
MAX_PENDING = 8
SOURCES = ("live", "stored")
STATUSES = ("tracked", "lost", "ended")
_ROW = np.dtype("<f8")


def late_answer_s(source: str, first_s: float) -> float:
    """How long after the first shard's answer (``first_s`` seconds into the query) the others are still waited
    for: `LATE_ANSWER_S` for live tracks (each shard answers from memory), and for stored history (a database read,
    longer the more history a shard holds) as long again as the first took, at least `LATE_ANSWER_S`; the query's
    own timeout bounds both."""
    return LATE_ANSWER_S if source == "live" else max(LATE_ANSWER_S, first_s)


class ShardAnswer(list):
    """What the shards answered: a list (of `ShardTrack`, or of their features) and ``missing``, the shards (K,
    sorted) that did not answer in time (the answer holds none of their tracks)."""

    def __init__(self, items: Iterable[Any] = (), missing: Iterable[int] = ()) -> None:
        super().__init__(items)
        self.missing: tuple[int, ...] = tuple(sorted(missing))


@dataclass(frozen=True, slots=True)
class TrackQuery:
    """What the gateway asks a shard for: ``source`` "live" (``/v1/tracks``; ``ended``: with the recently
    ended tracks) or "stored" (``/v1/history``: the database's tracks of class ``cls`` (None: all) updated
    at or after ``since`` (None: any time), with their rows from then on up to ``until`` (None: the newest);
    ``ends_only``: only each track's rows at its first and last time in that window, for
    ``/v1/history?rows=false``). Epoch seconds; ``since`` after ``until`` is refused."""

    source: str = "live"
    ended: bool = False
    cls: str | None = None
    since: float | None = None
    until: float | None = None
    ends_only: bool = False

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise MessageError("out_of_range", f"source must be one of {', '.join(SOURCES)}, got {self.source!r:.40}",
                               "source")
        if not isinstance(self.ended, bool):
            raise MessageError("bad_type", f"ended must be a bool, got {type(self.ended).__name__}", "ended")
        if self.cls is not None:
            check_name(self.cls, "cls")
        if self.since is not None:
            object.__setattr__(self, "since", check_float(self.since, "since"))
        if self.until is not None:
            object.__setattr__(self, "until", check_float(self.until, "until"))
            if self.since is not None and self.since > self.until:
                raise MessageError("out_of_range", f"since ({self.since}) is after until ({self.until})", "until")
        if not isinstance(self.ends_only, bool):
            raise MessageError("bad_type", f"ends_only must be a bool, got {type(self.ends_only).__name__}",
                               "ends_only")


def encode_request(request: TrackQuery) -> bytes:
    """The query payload of ``request``."""
    body: dict[str, Any] = {"v": VERSION, "source": request.source, "ended": request.ended}
    if request.cls is not None:
        body["cls"] = request.cls
    if request.since is not None:
        body["since"] = request.since
    if request.until is not None:
        body["until"] = request.until
    if request.ends_only:
        body["ends_only"] = True
    return msgpack.packb(body, use_bin_type=True)


def decode_request(payload: bytes | None) -> TrackQuery:
    """The TrackQuery of a query payload (None or empty: the live tracks); MessageError when malformed. A key
    it does not know is ignored (a newer gateway's); one that is missing takes its default."""
    if not payload:
        return TrackQuery()
    record = unpack_map(payload, 64 * 1024)
    check_version(get_field(record, "v"))
    return TrackQuery(source=record.get("source", "live"), ended=record.get("ended", False),
                      cls=record.get("cls"), since=record.get("since"), until=record.get("until"),
                      ends_only=record.get("ends_only", False))


@dataclass(frozen=True, slots=True)
class ShardTrack:
    """One global track as a shard lists it (the properties of its GeoJSON feature, ``TrackRecord.to_geojson``
    or a stored track of ``/v1/history``). active_members: None when the shard does not list them (its
    stored tracks). history: (t, lat, lon) rows, oldest first."""

    gid: int
    cls: str
    lat: float
    lon: float
    score: float
    vel_en: tuple[float, float]
    status: str
    created: float
    last_update: float
    ended: float | None
    members: tuple[tuple[str, int], ...]
    active_members: tuple[tuple[str, int], ...] | None
    history: tuple[tuple[float, float, float], ...]

    def to_feature(self) -> dict[str, Any]:
        """The GeoJSON feature the shard's own REST API gives for it (``active_members`` only if listed)."""
        props: dict[str, Any] = {
            "gid": self.gid, "cls": self.cls, "score": self.score, "vel_en": list(self.vel_en),
            "status": self.status, "created": self.created, "last_update": self.last_update, "ended": self.ended,
            "members": [list(m) for m in self.members],
        }
        if self.active_members is not None:
            props["active_members"] = [list(m) for m in self.active_members]
        props["history"] = [list(row) for row in self.history]
        return {"type": "Feature", "id": self.gid, "geometry": {"type": "Point", "coordinates": [self.lon, self.lat]},
                "properties": props}

    def to_record(self) -> TrackRecord:
        """As a TrackRecord (status from ``active_members`` and ``ended``, as the shard's tracker has it)."""
        active = self.active_members if self.active_members is not None else (
            self.members if self.status == "tracked" else ())
        return TrackRecord(gid=self.gid, cls=self.cls, lat=self.lat, lon=self.lon, score=self.score,
                           vel_en=self.vel_en, created=self.created, last_update=self.last_update,
                           members=self.members, active=active, ended=self.ended, history=self.history)


def _history(value: object, field: str) -> tuple[tuple[float, float, float], ...]:
    if not isinstance(value, bytes):
        raise MessageError("bad_type", f"{field} must be bytes, got {type(value).__name__}", field)
    if len(value) % (3 * _ROW.itemsize):
        raise MessageError("bad_length", f"{field} has {len(value)} bytes, not rows of 3 float64", field)
    rows = np.frombuffer(value, dtype=_ROW).reshape(-1, 3)
    if len(rows) > MAX_HISTORY_ROWS:
        raise MessageError("too_many", f"{field} has {len(rows)} rows, limit {MAX_HISTORY_ROWS}", field)
    if not np.isfinite(rows).all():
        raise MessageError("non_finite", f"{field} holds a non-finite number", field)
    if (np.abs(rows[:, 1]) > 90.0).any() or (np.abs(rows[:, 2]) > 180.0).any():
        raise MessageError("out_of_range", f"{field} holds a position outside lat -90..90, lon -180..180", field)
    return tuple(tuple(row) for row in rows.tolist())  # type: ignore[misc]


def _track(raw: Mapping[Any, Any], path: str) -> ShardTrack:
    status = get_field(raw, "status", path)
    if status not in STATUSES:
        raise MessageError("out_of_range", f"{path}status must be one of {', '.join(STATUSES)}, got {status!r:.40}",
                           f"{path}status")
    vel = get_field(raw, "vel_en", path)
    if not isinstance(vel, list) or len(vel) != 2:
        raise MessageError("bad_length", f"{path}vel_en must be [east, north]", f"{path}vel_en")
    ended = get_field(raw, "ended", path)
    members = check_members(get_field(raw, "members", path), f"{path}members")
    active = raw.get("active_members")
    if active is not None:
        active = check_members(active, f"{path}active_members")
        if not set(active) <= set(members):
            raise MessageError("out_of_range", f"{path}active_members must be members", f"{path}active_members")
    return ShardTrack(
        gid=check_int(get_field(raw, "gid", path), f"{path}gid", 0, 2**63 - 1),
        cls=check_name(get_field(raw, "cls", path), f"{path}cls"),
        lat=check_float(get_field(raw, "lat", path), f"{path}lat", -90.0, 90.0),
        lon=check_float(get_field(raw, "lon", path), f"{path}lon", -180.0, 180.0),
        score=check_float(get_field(raw, "score", path), f"{path}score"),
        vel_en=(check_float(vel[0], f"{path}vel_en[0]"), check_float(vel[1], f"{path}vel_en[1]")),
        status=status,
        created=check_float(get_field(raw, "created", path), f"{path}created"),
        last_update=check_float(get_field(raw, "last_update", path), f"{path}last_update"),
        ended=None if ended is None else check_float(ended, f"{path}ended"),
        members=members, active_members=active,
        history=_history(get_field(raw, "history", path), f"{path}history"),
    )


def _wire(feature: Mapping[str, Any]) -> dict[str, Any]:
    """The msgpack map of a reply's track from its REST API feature (``TrackRecord.to_geojson`` or a
    stored track of ``/v1/history``)."""
    props = feature["properties"]
    lon, lat = feature["geometry"]["coordinates"]
    body = {key: props[key] for key in ("gid", "cls", "score", "vel_en", "status", "created", "last_update", "ended",
                                        "members")}
    body["lat"], body["lon"] = lat, lon
    if props.get("active_members") is not None:
        body["active_members"] = props["active_members"]
    body["history"] = np.asarray(props.get("history", ()), dtype=_ROW).reshape(-1, 3).tobytes()
    return body


def encode_reply(shard: int, count: int, source: str, features: Iterable[Mapping[str, Any]]) -> bytes:
    """A shard's reply: its track features of ``source`` ("live" or "stored"), as its REST API lists them."""
    return msgpack.packb({"v": VERSION, "shard": shard, "shards": count, "source": source,
                          "tracks": [_wire(feature) for feature in features]}, use_bin_type=True)


def decode_reply(payload: bytes, *, max_bytes: int = MAX_REPLY_BYTES) -> tuple[int, int, str, list[ShardTrack]]:
    """(shard, shards, source, tracks) of a reply; MessageError (``.reason``) when anything is malformed."""
    record = unpack_map(payload, max_bytes)
    check_version(get_field(record, "v"))
    count = check_int(get_field(record, "shards"), "shards", 1, 1 << 16)
    shard = check_int(get_field(record, "shard"), "shard", 0, count - 1)
    source = get_field(record, "source")
    if source not in SOURCES:
        raise MessageError("out_of_range", f"source must be one of {', '.join(SOURCES)}, got {source!r:.40}",
                           "source")
    raw_tracks = get_field(record, "tracks")
    if not isinstance(raw_tracks, list):
        raise MessageError("bad_type", "tracks must be a list", "tracks")
    if len(raw_tracks) > MAX_TRACKS:
        raise MessageError("too_many", f"tracks: {len(raw_tracks)}, limit {MAX_TRACKS}", "tracks")
    tracks = []
    for i, raw in enumerate(raw_tracks):
        if not isinstance(raw, Mapping):
            raise MessageError("not_a_map", f"tracks[{i}] must be a map", f"tracks[{i}]")
        tracks.append(_track(raw, f"tracks[{i}]."))
    return shard, count, source, tracks


def merge_tracks(tracks: Iterable[ShardTrack], history_len: int | None = None) -> list[ShardTrack]:
    """One track per global id, by gid. Copies of one id (a handover: the shard it left holds the past,
    possibly ended, the one it entered carries it on) become one: the alive, reported, most recently
    updated copy for where it is and its status; the earliest ``created``, the latest ``last_update``,
    the members of every copy and their histories joined in time (the newest ``history_len`` rows).

    Copies cut to their ends (``TrackQuery.ends_only``) join into the ends of the whole: each copy carries
    every row at its first and last time, so the joined rows' first and last are those of all copies' rows
    joined (the same row where the last time ties, as joining the full histories picks it)."""
    by_gid: dict[int, list[ShardTrack]] = {}
    for track in tracks:
        by_gid.setdefault(track.gid, []).append(track)
    merged = []
    for gid in sorted(by_gid):
        copies = by_gid[gid]
        if len(copies) == 1:
            merged.append(copies[0])
            continue
        primary = max(copies, key=lambda c: (c.ended is None, c.status == "tracked", c.last_update))
        members: dict[tuple[str, int], None] = {}
        for copy in sorted(copies, key=lambda c: c.last_update):
            members.update(dict.fromkeys(copy.members))
        rows = sorted({row for copy in copies for row in copy.history})
        if history_len is not None:
            rows = rows[-history_len:]
        merged.append(dataclasses.replace(
            primary, created=min(c.created for c in copies), last_update=max(c.last_update for c in copies),
            members=tuple(members), history=tuple(rows)))
    return merged


class TracksQueryable:
    """A shard's answer to ``fusion/tracks`` queries: ``on_query`` (a Zenoh callback) queues the query,
    a worker thread asks ``source(TrackQuery)`` for the track features and replies on ``key``. A stored
    answer carries only the rows of the query's window (``since``, ``until``, ``ends_only``;
    `fusion_server.replay.window_rows`), whatever ``source`` read.

    shard, count: this shard's K and N. max_pending: queries waiting for the worker; beyond, the query
    is answered with an error ("busy") at once. Malformed queries get an error reply too.
    """

    def __init__(self, source: Callable[[TrackQuery], list[dict[str, Any]]], key: str, shard: int, count: int, *,
                 max_pending: int = MAX_PENDING) -> None:
        self.source = source
        self.key = key
        self.shard = shard
        self.count = count
        self.answered = 0
        self.refused = 0
        self._pending: queue.Queue[tuple[zenoh.Query, TrackQuery] | None] = queue.Queue(max_pending)
        self._thread: threading.Thread | None = None
        self._closed = False
        self._log = RateLimitedLog(log)

    def start(self) -> None:
        """Start the worker thread."""
        self._closed = False
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="uavmm-shard-tracks", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the worker (queries still waiting are answered with an error)."""
        self._closed = True
        if self._thread is None:
            return
        while True:
            try:
                item = self._pending.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                self._refuse(item[0], "shutting down")
        self._pending.put(None)
        self._thread.join(timeout=10.0)
        self._thread = None

    def on_query(self, query: zenoh.Query) -> None:
        """Zenoh thread: check the query and queue it for the worker; never raises."""
        try:
            payload = query.payload
            try:
                request = decode_request(payload.to_bytes() if payload is not None else None)
            except MessageError as exc:
                self._refuse(query, f"bad query: {exc}")
                return
            if self._closed:
                self._refuse(query, "shutting down")
                return
            try:
                self._pending.put_nowait((query, request))
            except queue.Full:
                self._refuse(query, "busy")
        except Exception:
            log.exception("internal error taking a shard tracks query")

    def _refuse(self, query: zenoh.Query, why: str) -> None:
        self.refused += 1
        self._log.warning(why.split(":")[0], "shard tracks query refused: %s", why)
        try:
            query.reply_err(why.encode())
        except zenoh.ZError:
            pass
        query.drop()

    def _run(self) -> None:
        while True:
            item = self._pending.get()
            if item is None:
                return
            query, request = item
            try:
                features = self.source(request)
                if request.source == "stored":  # only the window's rows go on the wire
                    features = window_rows(features, request.since, request.until, request.ends_only)
                query.reply(self.key, encode_reply(self.shard, self.count, request.source, features))
                self.answered += 1
            except Exception as exc:
                log.exception("answering a shard tracks query failed")
                try:
                    query.reply_err(f"failed: {exc}"[:200].encode())
                except zenoh.ZError:
                    pass
            finally:
                query.drop()

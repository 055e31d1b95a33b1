"""The gateway's side of the shards' tracks queries (`fusion_server.shard_tracks` has the wire, the merge and the
shards' queryable): every shard asked at once, each reply checked, the copies of an id merged, answers reused."""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable

import zenoh

from fusion_server.shard_tracks import (
    DEFAULT_CACHE_S,
    LIVE_TIMEOUT_S,
    STORED_TIMEOUT_S,
    ShardAnswer,
    ShardTrack,
    TrackQuery,
    decode_reply,
    encode_request,
    late_answer_s,
    merge_tracks,
)
from shared.keys import KeySpace
from shared.messages import MessageError
from transport.guard import RateLimitedLog

__all__ = ["ShardTracks"]

log = logging.getLogger(__name__)


class ShardTracks:
    """The gateway's view of the shards' tracks with history, asked for over ``session`` (None until the
    gateway opens).

    keys: the key space; count: how many shards (N). history_len: most rows a merged live track keeps
    (the tracker's). cache_s: how long an answer is reused. on_reject(reason): called for every reply
    dropped, and once (``t_in_future``) for a reply whose tracks were cut: a track with any time more than
    ``max_ahead_s`` after ``wall()`` (the gateway's --max-clock-skew-s) is left out (`_not_ahead`: the copy of
    an id updated last wins the merge, so one stamped ahead, forged or from a shard whose clock runs ahead,
    would hide the others; None: never). Thread-safe: HTTP threads call it concurrently; one query
    per kind runs at a time and the others wait for its answer. Answers are `ShardAnswer` (``missing``: the
    shards that did not answer in time). A query no shard answered before its timeout is not asked again for
    ``cache_s`` (None at once: the shards are silent, not refusing). ``close()`` ends the waits at once (a
    gateway's SIGTERM).
    """

    def __init__(self, keys: KeySpace, count: int, *, history_len: int = 600, cache_s: float = DEFAULT_CACHE_S,
                 on_reject: Callable[[str], None] | None = None, clock=time.monotonic,
                 max_ahead_s: float | None = None, wall: Callable[[], float] = time.time) -> None:
        self.keys = keys
        self.max_ahead_s = max_ahead_s
        self._wall = wall
        self.count = count
        self.history_len = history_len
        self.cache_s = float(cache_s)
        self.session: zenoh.Session | None = None
        self.queries = 0
        self._on_reject = on_reject
        self._clock = clock
        self._lock = threading.Lock()
        self._asking: dict[TrackQuery, list] = {}  # query -> [its lock, threads using it]
        # keyed by the whole query (source, ended, cls, since, until, ends_only): a rows=false answer is never
        # served for rows=true, nor one window's for another
        self._cache: dict[TrackQuery, tuple[float, ShardAnswer]] = {}
        self._silent_at = -float("inf")  # when a query last ran to its timeout without any answer
        self._closed = threading.Event()
        self._log = RateLimitedLog(log)

    def close(self) -> None:
        """End every wait for the shards now (their answers so far are returned) and ask nothing more."""
        self._closed.set()

    def live(self, include_ended: bool = False) -> ShardAnswer | None:
        """Every shard's live tracks (and recently ended ones), merged by gid; None when no shard answered."""
        return self._answer(TrackQuery(source="live", ended=include_ended), self.history_len)

    def stored(self, cls: str | None = None, since: float | None = None, until: float | None = None,
               ends_only: bool = False) -> ShardAnswer | None:
        """Every shard's stored tracks (class ``cls``, updated since ``since``) with their history rows up to
        ``until`` (``ends_only``: the rows at each track's first and last time in the window), merged by gid;
        None when no shard answered. A shard of the older version answers with every row since ``since``:
        cut the window afterwards (`fusion_server.replay.history_window`)."""
        return self._answer(TrackQuery(source="stored", cls=cls, since=since, until=until, ends_only=ends_only),
                            None)

    def _forget_old_answers(self) -> None:
        """Drop the answers too old to be served again (lock held): kept until 64 distinct windows came, 60 stored
        histories of 2 x 200 tracks of 600 rows held ~1 GB that nothing would read again."""
        now = self._clock()
        for request in [r for r, (asked, _) in self._cache.items() if now - asked > self.cache_s]:
            del self._cache[request]

    def _answer(self, request: TrackQuery, history_len: int | None) -> ShardAnswer | None:
        with self._lock:
            self._forget_old_answers()
            cached = self._cache.get(request)
            if cached is not None and self._clock() - cached[0] <= self.cache_s:
                return cached[1]
            # one asker per distinct query at a time; the entry lives while threads wait on it (a query nobody
            # answers caches nothing, and clients choose since / until: entries kept after use grew without bound)
            entry = self._asking.setdefault(request, [threading.Lock(), 0])
            entry[1] += 1
        try:
            with entry[0]:
                with self._lock:
                    cached = self._cache.get(request)
                    if cached is not None and self._clock() - cached[0] <= self.cache_s:
                        return cached[1]  # another thread asked while this one waited
                asked = self._clock()
                if asked - self._silent_at <= self.cache_s:
                    return None  # a query just waited its whole timeout for nobody
                replies = self._ask(request)
                if replies is None:  # nobody answered (no session, every shard down or too old to answer): ask again
                    return None
                found = ShardAnswer(merge_tracks(replies, history_len), getattr(replies, "missing", ()))
                with self._lock:
                    self._forget_old_answers()
                    if len(self._cache) > 64:  # many distinct history windows at once: forget them
                        self._cache.clear()
                    self._cache[request] = (asked, found)
                return found
        finally:
            with self._lock:
                entry[1] -= 1
                if not entry[1]:
                    self._asking.pop(request, None)

    def _ask(self, request: TrackQuery) -> ShardAnswer | None:
        """Every shard's tracks for ``request``, with the shards that did not answer in time (``missing``); None
        when none did. Waits until every shard has answered, the query ends, `late_answer_s` after the first
        answer, or ``close()``."""
        session = self.session
        if session is None or session.is_closed() or self._closed.is_set():
            return None
        self.queries += 1
        timeout = LIVE_TIMEOUT_S if request.source == "live" else STORED_TIMEOUT_S
        replies: queue.SimpleQueue[zenoh.Reply | None] = queue.SimpleQueue()
        started = time.monotonic()  # not self._clock: these are real waits
        try:
            session.get(self.keys.shard_tracks("*", self.count), zenoh.handlers.Callback(replies.put,
                                                                                          lambda: replies.put(None)),
                        target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                        payload=encode_request(request), timeout=timeout)
        except zenoh.ZError as exc:
            self._reject("query_failed", str(exc))
            return None
        tracks: list[ShardTrack] = []
        answered: set[int] = set()
        deadline = started + timeout
        first_s = 0.0
        timed_out = False
        while len(answered) < self.count and not self._closed.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                timed_out = True
                break
            try:
                reply = replies.get(timeout=min(left, 0.1))  # 0.1: close() is seen within it
            except queue.Empty:
                continue
            if reply is None:  # the query ended: every queryable replied, or Zenoh's timeout
                timed_out = time.monotonic() - started >= timeout - 0.05
                break
            if reply.ok is None:
                self._reject("reply_error", "a shard answered with an error")
                continue
            sample = reply.ok
            key = str(sample.key_expr)
            try:
                index, count = self.keys.parse_shard_tracks(key)
                shard, shards, source, found = decode_reply(sample.payload.to_bytes())
                if (shard, shards, source) != (index, count, request.source) or count != self.count:
                    raise MessageError("out_of_range", f"reply of shard {shard}/{shards} ({source}) on key {key:.120} "
                                                       f"to a {request.source} query of {self.count} shards")
            except MessageError as exc:
                self._reject(exc.reason, str(exc))
                continue
            except ValueError as exc:
                self._reject("bad_key", str(exc))
                continue
            if shard in answered:
                continue  # the same shard twice (two routes): one answer is enough
            if not answered:
                first_s = time.monotonic() - started
                deadline = min(deadline, started + first_s + late_answer_s(request.source, first_s))
            answered.add(shard)
            tracks.extend(self._not_ahead(found, shard))
        if not answered:
            if timed_out:  # silent, not refusing: the next query within cache_s would wait as long for nothing
                self._silent_at = self._clock()
            return None
        missing = set(range(self.count)) - answered
        if missing:
            self._log.warning("late", "gateway: shard(s) %s did not answer a %s tracks query within %.1f s of the "
                              "first answer; answered without them", sorted(missing), request.source,
                              late_answer_s(request.source, first_s))
        return ShardAnswer(tracks, missing)

    def _not_ahead(self, found: list[ShardTrack], shard: int) -> list[ShardTrack]:
        """The tracks of one reply whose every time (created, last_update, ended, history rows) is at most max_ahead_s
        ahead of the wall clock (the others rejected: an honest shard's history never runs past its own last_update;
        the merge keeps the newest rows, so rows stamped ahead would push the honest ones out)."""
        if self.max_ahead_s is None:
            return found
        now = self._wall()
        # each track's newest time: created, updated, ended, its history's rows (a forged copy's need not be sorted)
        latest = [max(t.created, t.last_update, -math.inf if t.ended is None else t.ended,
                      max((row[0] for row in t.history), default=-math.inf)) for t in found]
        kept = [t for t, newest in zip(found, latest, strict=True) if newest <= now + self.max_ahead_s]
        if len(kept) < len(found):
            ahead = max(latest) - now
            self._reject("t_in_future", f"shard {shard} answered {len(found) - len(kept)} track(s) updated up to "
                                        f"{ahead:.1f} s ahead of this clock, more than --max-clock-skew-s "
                                        f"{self.max_ahead_s:g} (forged, or the shard's clock runs ahead): left out")
        return kept

    def _reject(self, reason: str, detail: str) -> None:
        if self._on_reject is not None:
            self._on_reject(reason)
        self._log.warning(reason, "gateway: dropped a shard tracks reply: %s: %.200s", reason, detail)

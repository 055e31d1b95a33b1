"""The joint map of a sharded deployment as the gateway reads it: joint tiles asked of the shards by Zenoh queries.

Each shard answers ``{prefix}/joint/tiles/...`` queries for the tiles of its regions (its queryable,
``fusion_server.zenoh_node``). :class:`RemoteJoint` offers the read side of
:class:`fusion_server.joint_map.JointMap` that the REST API uses (``tiles``, ``tiles_in_range``,
``classes``, ``stats``, ``uav_tile_counts``): a small range (a PNG tile at the grid's zoom, a
``/v1/map`` window) asks for its tiles by key; anything larger, and the class list, ask for every tile
once and keep the answer ``cache_s`` seconds (0.4 by default), so a page loading twenty PNG tiles at once
costs one query. Replies are validated like every message (key, version, grid): a bad one is dropped
and counted, never raised.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable

import zenoh

from fusion_server.joint_map import JointTile, TileKey
from shared.keys import JOINT_UAV, KeySpace
from shared.messages import MessageError
from shared.tilecodec import decode_tile_sparse
from shared.tiles import TileGrid
from transport.guard import RateLimitedLog

__all__ = ["DEFAULT_CACHE_S", "SMALL_RANGE_TILES", "RemoteJoint"]

log = logging.getLogger(__name__)

#: How long an answer of the shards is served again, seconds (the shards publish at most 5 Hz per tile).
DEFAULT_CACHE_S = 0.4
#: Ranges of at most this many tiles are asked for tile by tile; larger ones by one query of the class.
SMALL_RANGE_TILES = 16
#: The class list and /healthz's tile count reuse a whole-map answer up to this old, seconds.
SUMMARY_MAX_AGE_S = 2.0
#: Longest wait for the shards' replies, seconds (a query ends earlier, once every shard has answered).
QUERY_TIMEOUT_S = 2.0
#: Longest a summary (the class list, /healthz's tile count) waits for the shards, seconds: a shard that does not
#: answer (cut off until its lease ends, or a peer's queryable that never replies) must not hold up /healthz
#: for the query's 2 s; the summary then gives the last answer and the query goes on in the background.
SUMMARY_WAIT_S = 0.5
#: Most classes remembered (as JointMap).
_MAX_CLASSES = 1024


class RemoteJoint:
    """Joint tiles of all shards, asked for on demand over ``session`` (None until the gateway opens).

    keys: the key space; grid: the shared grid (replies of another z or n are rejected).
    on_reject(reason): called for every reply dropped (the gateway counts them by reason).
    cache_s: how long an answer is reused. Thread-safe: HTTP threads call it concurrently; one query
    of the whole map runs at a time and the others wait for its answer.
    """

    def __init__(self, keys: KeySpace, grid: TileGrid, *, cache_s: float = DEFAULT_CACHE_S,
                 on_reject: Callable[[str], None] | None = None, clock=time.monotonic) -> None:
        self.keys = keys
        self.grid = grid
        self.cache_s = float(cache_s)
        self.session: zenoh.Session | None = None
        self.queries = 0
        self._on_reject = on_reject
        self._clock = clock
        self._lock = threading.Lock()
        self._all_lock = threading.Lock()  # one query of everything at a time
        self._all: tuple[float, dict[TileKey, JointTile]] | None = None
        self._all_done = -float("inf")  # when the query of _all ended
        self._by_key: dict[TileKey, tuple[float, JointTile | None]] = {}
        self._classes: set[str] = set()
        # the background query of the whole map for the summaries: (monotonic start, done, its thread)
        self._refresh: tuple[float, threading.Event, threading.Thread] | None = None
        self._closed = threading.Event()
        self._log = RateLimitedLog(log)

    def close(self) -> None:
        """End every wait for the shards now (the tiles come so far are used) and ask nothing more: a gateway's
        SIGTERM no longer waits out a silent shard's 2 s."""
        self._closed.set()

    # ---- the read side the REST API uses (JointMap's) ---------------------------------------------
    def tiles(self, cls: str | None = None) -> list[JointTile]:
        """The current joint tiles of every shard (of one class, or all)."""
        tiles = self._everything().values()
        return list(tiles) if cls is None else [t for t in tiles if t.cls == cls]

    def tiles_in_range(self, cls: str, x0: int, x1: int, y0: int, y1: int) -> list[JointTile]:
        """Joint tiles of ``cls`` at the grid's zoom with x0 <= x <= x1 and y0 <= y <= y1; x wraps around the world
        as in `JointMap.tiles_in_range` (x0 = -1 is the last column, x1 = 2**z the first)."""
        z, side = self.grid.z, self.grid.tiles_per_side
        width = min(x1 - x0 + 1, side)
        whole = self._fresh_all()
        if whole is None and width * (y1 - y0 + 1) <= SMALL_RANGE_TILES:
            keys = [(cls, z, (x0 + dx) % side, y) for y in range(y0, y1 + 1) for dx in range(width)]
            return [tile for tile in self._by_keys(keys) if tile is not None]
        tiles = whole if whole is not None else self._everything()
        return [t for t in tiles.values() if t.cls == cls and (t.x - x0) % side < width and y0 <= t.y <= y1]

    def get(self, key: TileKey) -> JointTile | None:
        """The current joint tile at key (cls, z, x, y), or None."""
        return self._by_keys([key])[0]

    def classes(self) -> set[str]:
        """Classes of the joint tiles seen since start (at most 1024; a new class shows within 2 s while the
        shards answer). Waits at most SUMMARY_WAIT_S for them once the shards have answered at least once; before
        that, for the whole query (a gateway just started would answer /v1/objects with nothing)."""
        with self._lock:
            answered = self._all is not None
        self._summary(SUMMARY_WAIT_S if answered else QUERY_TIMEOUT_S + 0.5)
        with self._lock:
            return set(self._classes)

    def uav_tile_counts(self) -> None:
        """None: the shards' UAV tiles stay on the shards (/v1/uavs rows of a gateway have no ``tiles``)."""
        return None

    def stats(self) -> dict[str, int]:
        """JointMap.stats() of the gateway: the joint tiles of all shards; it holds no UAV tiles,
        pending fusions, coverage masks or footprints (those are the shards', on their /healthz)."""
        return {"joint_tiles": len(self._summary()), "uav_tiles": 0, "pending": 0,
                "coverage_masks": 0, "footprints": 0}

    def join(self, timeout_s: float = QUERY_TIMEOUT_S + 1.0) -> None:
        """Wait for a background query of the summaries to end (after the session closed: at once)."""
        with self._lock:
            refresh = self._refresh
        if refresh is not None:
            refresh[2].join(timeout_s)

    # ---- queries ----------------------------------------------------------------------------------
    def _fresh_all(self, max_age_s: float | None = None) -> dict[TileKey, JointTile] | None:
        with self._lock:
            found = self._all
        max_age_s = self.cache_s if max_age_s is None else max_age_s
        if found is not None and self._clock() - found[0] <= max_age_s:
            return found[1]
        return None

    def _summary(self, wait_s: float = SUMMARY_WAIT_S) -> dict[TileKey, JointTile]:
        """The whole map for the summaries: an answer at most SUMMARY_MAX_AGE_S old, else a new one asked for in the
        background and waited for until ``wait_s`` after that query started; the last answer (or none) when the
        shards are slower than that."""
        found = self._fresh_all(SUMMARY_MAX_AGE_S)
        if found is not None:
            return found
        with self._lock:
            if self._all is not None and self._clock() - self._all_done <= SUMMARY_WAIT_S:
                # an answer that just ended (asked up to QUERY_TIMEOUT_S ago): the tile count after the class list
                # of one /healthz takes it, not a new query and another wait
                return self._all[1]
            if self._refresh is None or self._refresh[1].is_set():
                done = threading.Event()
                thread = threading.Thread(target=self._run_refresh, args=(done,), name="uavmm-gateway-joint",
                                          daemon=True)
                self._refresh = (self._clock(), done, thread)
                thread.start()
            started, done, _ = self._refresh
        done.wait(max(0.0, started + wait_s - self._clock()))
        with self._lock:
            last = self._all
        return last[1] if last is not None else {}

    def _run_refresh(self, done: threading.Event) -> None:
        try:
            self._everything(SUMMARY_MAX_AGE_S)
        except Exception:  # a thread of its own: log, never die silently
            log.exception("gateway: asking the shards for the whole joint map failed")
        finally:
            done.set()

    def _everything(self, max_age_s: float | None = None) -> dict[TileKey, JointTile]:
        """Every joint tile of every shard: one query ``joint/tiles/**``, reused up to ``max_age_s``
        (default cache_s) seconds from when it was asked, and by every thread that waited for it."""
        found = self._fresh_all(max_age_s)
        if found is not None:
            return found
        waiting = self._clock()
        with self._all_lock:
            found = self._fresh_all(max_age_s)
            with self._lock:
                if found is None and self._all is not None and self._all_done >= waiting:
                    # another thread's query ended while this one waited: its answer is as new as this one's
                    # would be (a query slow to end, 2 s for a shard that does not answer, was asked again)
                    found = self._all[1]
            if found is not None:
                return found
            asked = self._clock()
            tiles: dict[TileKey, JointTile] = {}
            for tile in self._ask([self.keys.joint_tiles_all()]):
                old = tiles.get(tile.key)
                if old is None or (tile.t, tile.seq) > (old.t, old.seq):
                    tiles[tile.key] = tile
            with self._lock:
                self._all = (asked, tiles)
                self._all_done = self._clock()
            return tiles

    def _by_keys(self, keys: list[TileKey]) -> list[JointTile | None]:
        """The tiles at ``keys`` (None where no shard has one), each asked for unless cached."""
        now = self._clock()
        with self._lock:
            cached = {key: self._by_key.get(key) for key in keys}
        missing = [key for key, entry in cached.items() if entry is None or now - entry[0] > self.cache_s]
        if missing:
            found: dict[TileKey, JointTile] = {}
            for tile in self._ask([self.keys.joint_tile(*key) for key in missing]):
                old = found.get(tile.key)
                if old is None or (tile.t, tile.seq) > (old.t, old.seq):
                    found[tile.key] = tile
            with self._lock:
                if len(self._by_key) > 4096:
                    self._by_key.clear()
                for key in missing:
                    entry = (now, found.get(key))
                    self._by_key[key] = entry
                    cached[key] = entry
        return [entry[1] if entry is not None else None for entry in (cached[key] for key in keys)]

    def _ask(self, selectors: Iterable[str]) -> list[JointTile]:
        """Send every selector's query at once, then gather the valid replies of all shards."""
        session = self.session
        if session is None or session.is_closed() or self._closed.is_set():
            return []
        replies: queue.SimpleQueue[zenoh.Reply | None] = queue.SimpleQueue()  # None: one query ended
        asked = 0
        for selector in selectors:
            self.queries += 1
            try:
                session.get(selector, zenoh.handlers.Callback(replies.put, lambda: replies.put(None)),
                            target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                            timeout=QUERY_TIMEOUT_S)
                asked += 1
            except zenoh.ZError as exc:
                self._reject("query_failed", f"{selector}: {exc}")
        tiles = []
        deadline = time.monotonic() + QUERY_TIMEOUT_S + 0.5  # Zenoh ends each query by its timeout: a bound only
        while asked and not self._closed.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                reply = replies.get(timeout=min(left, 0.1))  # 0.1: close() is seen within it
            except queue.Empty:
                continue
            if reply is None:
                asked -= 1
                continue
            tile = self._tile_of(reply)
            if tile is not None:
                tiles.append(tile)
        return tiles

    def _tile_of(self, reply: zenoh.Reply) -> JointTile | None:
        """A reply as a JointTile, or None (counted) when it is an error or not a valid joint tile."""
        if reply.ok is None:
            self._reject("reply_error", "a shard answered with an error")
            return None
        sample = reply.ok
        key = str(sample.key_expr)
        try:
            parsed = self.keys.parse(key)
            if parsed.kind != "joint_tile":
                raise MessageError("unexpected_key", f"not a joint tile key: {key:.120}")
            message = decode_tile_sparse(sample.payload.to_bytes())
            if message.uav != JOINT_UAV or (message.cls, message.z, message.x, message.y) != (
                    parsed.cls, parsed.z, parsed.x, parsed.y):
                raise MessageError("tile_mismatch", f"tile {message.uav}/{message.cls}/{message.z}/{message.x}/"
                                                    f"{message.y} on key {key:.120}")
            if message.z != self.grid.z or message.n != self.grid.n:
                raise MessageError("wrong_grid", f"tile z={message.z} n={message.n}, grid z={self.grid.z} "
                                                 f"n={self.grid.n}")
        except MessageError as exc:
            self._reject(exc.reason, str(exc))
            return None
        except ValueError as exc:
            self._reject("bad_key", str(exc))
            return None
        with self._lock:
            if len(self._classes) < _MAX_CLASSES:
                self._classes.add(message.cls)
        return JointTile(message.cls, message.z, message.x, message.y, None, message.t, message.seq,
                         sample.payload.to_bytes(), (), time.time(), cells=(message.n, message.idx, message.val))

    def _reject(self, reason: str, detail: str) -> None:
        if self._on_reject is not None:
            self._on_reject(reason)
        self._log.warning(reason, "gateway: dropped a joint tile reply: %s: %.200s", reason, detail)

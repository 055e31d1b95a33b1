"""The joint map: the UAVs' latest tiles and their fusion into joint tiles, with no I/O.

Per (uav, cls, tile) the latest tile and its receive time are kept; a UAV covers a tile while that
tile is younger than the time to live. Inside a tile, with ``coverage="footprint"`` (the default), a
UAV covers the cells its camera footprints (from its state messages, :meth:`JointMap.put_footprint`)
held within the time to live: a UAV that does not see a cell (behind it, beside it) does not pull
the mean down there. A UAV that sent no footprint within the time to live covers its whole tiles, as
does every UAV with ``coverage="tile"``; a cell no footprint holds falls back to every UAV covering
the tile (see :mod:`fusion_server.rules`). :meth:`JointMap.step` fuses the tiles that changed (at
most ``max_hz`` times a second per tile), expires old ones and returns the joint tile messages to
publish, including one empty tile for a joint tile nobody covers any more. Thread-safe: one
internal lock (:meth:`JointMap.put_many` takes it once for a batch of tiles).

Tiles are held sparse (sorted non-zero cell indices and their bytes, as on the wire) and fused over
the union of their non-zero cells only: every rule maps all-zero inputs to zero, so the cells
outside the union stay zero. A tile one UAV covers is published from its cells as they came.
"""

from __future__ import annotations

import heapq
import math
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass

import msgpack
import numpy as np
from numpy.typing import NDArray

from fusion_server.rules import FusionRule
from shared.keys import JOINT_UAV
from shared.messages import VERSION
from shared.tiles import TileGrid, fill_cell_polygons

__all__ = ["COVERAGE_MODES", "JointMap", "JointTile", "JointUpdate", "TileKey", "encode_joint_tile"]

#: (cls, z, x, y) of a tile.
TileKey = tuple[str, int, int, int]
_MAX_CLASSES = 1024
#: Coverage models: "footprint" (cells inside the UAV's recent camera footprints) or "tile" (whole tiles).
COVERAGE_MODES = ("footprint", "tile")
#: Footprints kept per UAV (5 Hz state messages over a 2 s time to live are 10).
_MAX_FOOTPRINTS = 64
#: Publications a tile may make in a burst above its max_hz average (absorbs jitter of the agents).
_BURST = 2.0


class JointTile:
    """One fused tile as published.

    values: (n, n) uint8, read-only (value = byte / 255); built on first access when the tile was
    made from its non-zero cells (``cells=(n, idx, val)`` with ``values=None``, as the joint map
    does: most tiles are published and never read densely). t: newest ``t`` (seconds since the
    epoch) of the UAV tiles fused into it. seq: the server's publish counter. payload: the encoded
    tile message (``uav = "joint"``). uavs: the UAVs covering it when it was fused (empty for a tile
    restored from the database). updated: wall time of the fusion, seconds since the epoch.
    Equality is identity.
    """

    __slots__ = ("_cells", "_values", "cls", "payload", "seq", "t", "updated", "uavs", "x", "y", "z")

    def __init__(self, cls: str, z: int, x: int, y: int, values: NDArray[np.uint8] | None, t: float, seq: int,
                 payload: bytes, uavs: tuple[str, ...], updated: float, *,
                 cells: tuple[int, NDArray[np.uint16], NDArray[np.uint8]] | None = None) -> None:
        if values is None and cells is None:
            raise ValueError("a JointTile needs values or cells")
        self.cls, self.z, self.x, self.y = cls, z, x, y
        self._values = values
        self._cells = cells
        self.t, self.seq, self.payload, self.uavs, self.updated = t, seq, payload, uavs, updated

    @property
    def values(self) -> NDArray[np.uint8]:
        """(n, n) uint8, read-only."""
        values = self._values
        if values is None:
            assert self._cells is not None
            values = self._values = _dense(*self._cells)
            values.flags.writeable = False
        return values

    @property
    def key(self) -> TileKey:
        """(cls, z, x, y)."""
        return (self.cls, self.z, self.x, self.y)


@dataclass(frozen=True, slots=True, eq=False)
class JointUpdate:
    """A joint tile message to publish.

    tile: the new joint tile, or None when the tile was dropped (``payload`` is then an empty tile
    telling subscribers to clear it). pending_since: monotonic time of the oldest change not yet
    published (a receive or an expiry), so ``publish time - pending_since`` is the fusion latency.
    """

    key: TileKey
    payload: bytes
    tile: JointTile | None
    pending_since: float


@dataclass(slots=True)
class _UavTile:
    idx: NDArray[np.uint16]  # sorted row-major indices of the non-zero cells
    val: NDArray[np.uint8]  # their bytes, non-zero
    t: float
    seq: int
    received: float  # monotonic


@dataclass(slots=True)
class _Footprint:
    cells: NDArray[np.float64]  # (M, 2) global cell coordinates (gx, gy), continuous
    lo: NDArray[np.float64]  # (2,) min gx, gy
    hi: NDArray[np.float64]  # (2,) max gx, gy
    received: float  # monotonic


def encode_joint_tile(key: TileKey, n: int, values: NDArray[np.uint8], t: float, seq: int) -> bytes:
    """Tile message bytes (``uav = "joint"``) of (n, n) uint8 ``values``, sparse or dense."""
    flat = values.reshape(-1)
    idx = np.flatnonzero(flat != 0)  # on a bool array: ~10x faster than flatnonzero on uint8
    return _encode_sparse(key, n, idx.astype(np.uint16), flat[idx], t, seq)


def _encode_sparse(key: TileKey, n: int, idx: NDArray[np.uint16], val: NDArray[np.uint8], t: float,
                   seq: int) -> bytes:
    """The joint tile message of sorted distinct ``idx`` < n*n and their non-zero ``val`` (the wire
    form of shared.tilecodec, dense when that is smaller), without re-validating the fields."""
    cls, z, x, y = key
    if 3 * idx.size < n * n:
        wire = {"idx": idx.astype("<u2", copy=False).tobytes(), "val": val.tobytes()}
    else:
        dense = np.zeros(n * n, dtype=np.uint8)
        dense[idx] = val
        wire = {"val": dense.tobytes()}
    return msgpack.packb({"v": VERSION, "uav": JOINT_UAV, "cls": cls, "z": z, "x": x, "y": y, "n": n,
                          "t": float(t), "seq": seq, **wire}, use_bin_type=True)


def _dense(n: int, idx: NDArray[np.uint16], val: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(n, n) uint8 tile of the sparse cells."""
    flat = np.zeros(n * n, dtype=np.uint8)
    flat[idx] = val
    return flat.reshape(n, n)


class JointMap:
    """Latest per-UAV tiles and the fused joint tiles of one grid.

    grid: the only grid accepted (tiles of other z or n are the caller's to reject). rule: a
    :mod:`fusion_server.rules` function. ttl_s: how long a tile counts as covering after it was
    received. max_hz: most joint publications per tile and second. max_uav_tiles: bound on the
    stored UAV tiles (memory: n*n bytes each), max_tiles_per_uav the share one UAV may hold (so one
    UAV, real or forged, cannot take the whole store); max_hz is an average (token bucket, burst of 2), so
    a tile updated at exactly max_hz is never delayed by jitter. coverage: "footprint" (a UAV covers
    the cells of its footprints received within ttl_s; whole tiles while it sent none) or "tile" (the
    whole tile). refresh_s: a tile whose fused values did not change is published again when its last
    publication is this old (agents drop joint tiles after their TTL, 3 s by default, and a map at a
    steady state or clipped at 1 does not change). clock: monotonic seconds; wall: epoch seconds.
    """

    def __init__(
        self,
        grid: TileGrid,
        rule: FusionRule,
        ttl_s: float,
        max_hz: float,
        *,
        max_uav_tiles: int = 20_000,
        max_tiles_per_uav: int = 1024,
        coverage: str = "footprint",
        refresh_s: float = 1.0,
        clock=time.monotonic,
        wall=time.time,
    ) -> None:
        self.grid = grid
        self.rule = rule
        self.ttl_s = float(ttl_s)
        self.max_hz = float(max_hz)
        self.max_uav_tiles = int(max_uav_tiles)
        self.max_tiles_per_uav = int(max_tiles_per_uav)
        if coverage not in COVERAGE_MODES:
            raise ValueError(f"coverage must be one of {', '.join(COVERAGE_MODES)}, got {coverage!r}")
        self.coverage = coverage
        if not refresh_s > 0:
            raise ValueError(f"refresh_s must be > 0, got {refresh_s!r}")
        self.refresh_s = float(refresh_s)
        self._published: dict[TileKey, float] = {}  # monotonic time of each tile's last publication
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        self._covers: dict[TileKey, dict[str, _UavTile]] = {}
        self._n_uav_tiles = 0
        self._joint: dict[TileKey, JointTile] = {}
        self._joint_cells: dict[TileKey, tuple[bytes, bytes]] = {}  # idx, val bytes of each joint tile
        self._dirty: dict[TileKey, float] = {}  # tiles to fuse -> monotonic time of their oldest change
        self._fresh: list[TileKey] = []  # dirty tiles step() has not looked at yet
        self._held: list[tuple[float, TileKey]] = []  # heap of dirty tiles waiting for a token: (when, key)
        # token bucket per tile: (tokens, time of the last refill); rate max_hz, burst _BURST, so the
        # average rate is capped while a put arriving a little early (jitter) is not held back
        self._buckets: dict[TileKey, tuple[float, float]] = {}
        # (expiry, key, uav or None for a restored tile, received); validated when popped
        self._expiries: list[tuple[float, TileKey, str | None, float]] = []
        # increasing across restarts: a restarted server's seq continues above the old one's
        self._seq = time.time_ns() // 1000
        self._wake = threading.Condition(self._lock)
        self._poked = False
        self._classes: set[str] = set()  # every class seen since start (bounded)
        self._uav_keys: dict[str, set[TileKey]] = {}  # tiles each UAV covers now
        self._footprints: dict[str, list[_Footprint]] = {}  # oldest first
        self._masks: dict[tuple[str, int, int], tuple[int, NDArray[np.bool_] | None]] = {}
        self._fp_versions: dict[str, int] = {}  # per UAV: bumped when its footprints change
        self._fp_version_last = 0  # versions come from one counter, so a UAV dropped and back reuses none
        self._next_prune = -math.inf  # monotonic time of the next sweep of old footprints

    # ---- input ---------------------------------------------------------------------------------
    def put(self, uav: str, key: TileKey, values: NDArray[np.uint8], t: float, seq: int,
            now: float | None = None) -> str | None:
        """Store a UAV's tile; return None when accepted, else the reason it was not.

        values: (n, n) uint8 of the grid's n. Reasons: "stale" (not newer than the stored tile: seq
        and t both not greater), "too_many_tiles" (the store is full, or this UAV already holds
        max_tiles_per_uav tiles). Wakes a thread blocked in :meth:`wait`.
        """
        flat = np.asarray(values).reshape(-1)
        idx = np.flatnonzero(flat != 0)
        return self.put_many([(uav, key, idx.astype(np.uint16), flat[idx].astype(np.uint8), t, seq)], now)[0]

    def put_many(self, tiles: Iterable[tuple[str, TileKey, NDArray[np.uint16], NDArray[np.uint8], float, int]],
                 now: float | None = None) -> list[str | None]:
        """Store a batch of UAV tiles ``(uav, key, idx, val, t, seq)`` under one lock; per tile None
        when accepted, else the reason (as :meth:`put`).

        idx: sorted distinct row-major cell indices < n*n (uint16), val: their non-zero bytes (a
        :class:`shared.tilecodec.SparseTile`'s fields; not copied). Wakes a thread blocked in
        :meth:`wait` once.
        """
        now = self._clock() if now is None else now
        with self._lock:
            reasons = [self._put_locked(uav, key, idx, val, t, seq, now) for uav, key, idx, val, t, seq in tiles]
            self._poked = True
            self._wake.notify_all()
        return reasons

    def _put_locked(self, uav: str, key: TileKey, idx: NDArray[np.uint16], val: NDArray[np.uint8], t: float,
                    seq: int, now: float) -> str | None:
        per_uav = self._covers.get(key)
        old = per_uav.get(uav) if per_uav is not None else None
        if old is not None and seq <= old.seq and t <= old.t:
            return "stale"
        if old is None and (self._n_uav_tiles >= self.max_uav_tiles
                            or len(self._uav_keys.get(uav, ())) >= self.max_tiles_per_uav):
            return "too_many_tiles"
        if per_uav is None:
            per_uav = self._covers[key] = {}
        if old is None:
            self._n_uav_tiles += 1
            self._uav_keys.setdefault(uav, set()).add(key)
        per_uav[uav] = _UavTile(idx, val, float(t), int(seq), now)
        if len(self._classes) < _MAX_CLASSES:
            self._classes.add(key[0])
        heapq.heappush(self._expiries, (now + self.ttl_s, key, uav, now))
        self._mark(key, now)
        return None

    def put_footprint(self, uav: str, footprint_latlon, now: float | None = None) -> bool:
        """Record a UAV's camera footprint (from its state message) received now.

        footprint_latlon: (M, 2) ``[lat, lon]`` degrees, the ground polygon (M >= 3; fewer points,
        non-finite ones or latitudes beyond the map are ignored: returns False). For ``ttl_s`` after
        it was received the UAV covers the cells inside it (see the module docstring); the tiles the
        UAV covers are fused again.
        """
        if self.coverage != "footprint":
            return False
        try:
            cells = self.grid.polygon_cells(footprint_latlon)
        except ValueError:  # beyond the map's latitude limit (the validator drops such states)
            return False
        if cells is None:
            return False
        now = self._clock() if now is None else now
        with self._lock:
            prints = self._footprints.setdefault(uav, [])
            prints.append(_Footprint(cells, cells.min(axis=0), cells.max(axis=0), now))
            if len(prints) > _MAX_FOOTPRINTS:
                del prints[0]
            self._bump_footprints(uav)
            for key in self._uav_keys.get(uav, ()):
                self._mark(key, now)
            self._poked = True
            self._wake.notify_all()
        return True

    def _coverage_mask(self, uav: str, key: TileKey, now: float) -> NDArray[np.bool_] | None:
        """(n, n) bool cells of tile ``key`` inside ``uav``'s fresh footprints; None: the whole tile."""
        prints = self._footprints.get(uav)
        if not prints:
            return None
        cutoff = now - self.ttl_s
        if prints[0].received < cutoff:
            prints[:] = [fp for fp in prints if fp.received >= cutoff]
            self._bump_footprints(uav)
            if not prints:
                del self._footprints[uav]
                self._fp_versions.pop(uav, None)
                return None
        _, _, x, y = key
        version = self._fp_versions.get(uav, 0)
        cached = self._masks.get((uav, x, y))
        if cached is not None and cached[0] == version:
            return cached[1]
        n = self.grid.n
        x0, y0 = x * n, y * n
        mask = fill_cell_polygons((fp.cells for fp in prints if not (fp.hi[0] < x0 or fp.lo[0] > x0 + n
                                                                     or fp.hi[1] < y0 or fp.lo[1] > y0 + n)),
                                  x0, y0, n, n)
        if len(self._masks) > self.max_uav_tiles:  # masks are freed with their tiles: a safety net only
            self._masks.clear()
        self._masks[(uav, x, y)] = (version, mask)
        return mask

    def _bump_footprints(self, uav: str) -> None:
        """Invalidate the cached coverage masks of ``uav`` (its footprints changed)."""
        self._fp_version_last += 1
        self._fp_versions[uav] = self._fp_version_last

    def restore(self, tiles: Iterable[JointTile], keep_s: float, now: float | None = None) -> int:
        """Serve joint tiles loaded from the database until ``keep_s`` after their last update.

        ``tile.updated`` is wall time; tiles already older than keep_s are skipped. They are replaced
        as soon as a UAV covers them, and dropped (empty tile published) when their time is up
        unless one does. Returns the number restored.
        """
        now = self._clock() if now is None else now
        wall = self._wall()
        count = 0
        with self._lock:
            for tile in tiles:
                left = keep_s - max(wall - tile.updated, 0.0)
                if tile.key in self._joint or left <= 0:
                    continue
                self._joint[tile.key] = tile
                flat = tile.values.reshape(-1)
                idx = np.flatnonzero(flat != 0)
                self._joint_cells[tile.key] = (idx.astype("<u2").tobytes(), flat[idx].tobytes())
                self._classes.add(tile.cls)
                self._seq = max(self._seq, tile.seq + 1)
                heapq.heappush(self._expiries, (now + left, tile.key, None, now))
                count += 1
        return count

    # ---- fusion --------------------------------------------------------------------------------
    def wait(self, timeout_s: float) -> None:
        """Block until :meth:`put` (or :meth:`poke`) is called or ``timeout_s`` passes.

        For the publishing thread: a put since the last wait returns at once.
        """
        with self._lock:
            if not self._poked and timeout_s > 0:
                self._wake.wait(timeout_s)
            self._poked = False

    def poke(self) -> None:
        """Wake a thread blocked in :meth:`wait` (e.g. to shut down)."""
        with self._lock:
            self._poked = True
            self._wake.notify_all()

    def step(self, now: float | None = None) -> tuple[list[JointUpdate], float | None]:
        """Expire old tiles, fuse the changed tiles that may be published now.

        Returns the updates to publish (joint tiles whose values changed, empty tiles for dropped
        ones) and the monotonic time of the next thing to do (None: nothing pending).
        """
        now = self._clock() if now is None else now
        updates: list[JointUpdate] = []
        with self._lock:
            self._expire(now)
            # only the tiles changed since the last step and those whose token is due are looked at
            candidates = self._fresh
            self._fresh = []
            held = self._held
            while held and held[0][0] <= now:
                candidates.append(heapq.heappop(held)[1])
            for key in candidates:
                tokens = self._tokens(key, now)
                if tokens < 1.0 - 1e-9:
                    heapq.heappush(held, (now + (1.0 - tokens) / self.max_hz, key))
                    continue
                pending_since = self._dirty.pop(key)
                update = self._fuse(key, pending_since, now)
                if update is not None:
                    updates.append(update)
                    if update.tile is not None:
                        self._buckets[key] = (tokens - 1.0, now)
            next_due = held[0][0] if held else math.inf
            if self._expiries:
                next_due = min(next_due, self._expiries[0][0])
        return updates, (None if next_due == math.inf else next_due)

    def _mark(self, key: TileKey, since: float) -> None:
        """Tile ``key`` changed at ``since``: fuse it at the next step its token bucket allows."""
        if key not in self._dirty:
            self._dirty[key] = since
            self._fresh.append(key)

    def _tokens(self, key: TileKey, now: float) -> float:
        bucket = self._buckets.get(key)
        if bucket is None:
            return _BURST
        tokens, stamp = bucket
        return min(_BURST, tokens + (now - stamp) * self.max_hz)

    def _prune_footprints(self, now: float) -> None:
        """Forget footprints older than the TTL, also of UAVs that send no tiles (twice a TTL at most)."""
        if now < self._next_prune:
            return
        self._next_prune = now + min(self.ttl_s, 0.5)
        cutoff = now - self.ttl_s
        for uav in list(self._footprints):
            prints = self._footprints[uav]
            if prints[0].received >= cutoff:
                continue
            prints[:] = [fp for fp in prints if fp.received >= cutoff]
            self._bump_footprints(uav)
            if not prints:
                del self._footprints[uav]
                self._fp_versions.pop(uav, None)

    def _expire(self, now: float) -> None:
        self._prune_footprints(now)
        heap = self._expiries
        while heap and heap[0][0] <= now:
            expiry, key, uav, received = heapq.heappop(heap)
            if uav is None:  # a restored tile's grace time is over: recompute from real coverage
                self._mark(key, expiry)
                continue
            per_uav = self._covers.get(key)
            entry = per_uav.get(uav) if per_uav is not None else None
            if per_uav is None or entry is None or entry.received != received:
                continue  # replaced by a newer tile: its own heap entry decides
            del per_uav[uav]
            self._n_uav_tiles -= 1
            # another class of this UAV in the same tile recomputes it on demand
            self._masks.pop((uav, key[2], key[3]), None)
            keys = self._uav_keys.get(uav)
            if keys is not None:
                keys.discard(key)
                if not keys:
                    del self._uav_keys[uav]
            if not per_uav:
                del self._covers[key]
            self._mark(key, expiry)

    def _fuse(self, key: TileKey, pending_since: float, now: float) -> JointUpdate | None:
        per_uav = self._covers.get(key)
        previous = self._joint.get(key)
        n = self.grid.n
        if not per_uav:
            if previous is None:
                return None
            del self._joint[key]
            self._joint_cells.pop(key, None)
            self._buckets.pop(key, None)
            self._published.pop(key, None)
            self._seq += 1
            empty = np.zeros(0, dtype=np.uint16)
            payload = _encode_sparse(key, n, empty, empty.astype(np.uint8), self._wall(), self._seq)
            return JointUpdate(key, payload, None, pending_since)
        if len(per_uav) == 1:
            (entry,) = per_uav.values()
            idx, val = entry.idx, entry.val  # every rule maps one layer to itself (also with its mask)
            t = entry.t
        else:
            idx, val = self._fuse_layers(key, per_uav, now)
            t = max(e.t for e in per_uav.values())
        cells = (idx.astype("<u2", copy=False).tobytes(), val.tobytes())
        if (previous is not None and self._joint_cells.get(key) == cells
                and now - self._published.get(key, -math.inf) < self.refresh_s):
            return None  # unchanged and recently published (agents drop joint tiles after their TTL)
        self._published[key] = now
        self._seq += 1
        payload = _encode_sparse(key, n, idx, val, t, self._seq)
        cls, z, x, y = key
        tile = JointTile(cls, z, x, y, None, t, self._seq, payload, tuple(sorted(per_uav)), self._wall(),
                         cells=(n, idx, val))
        self._joint[key] = tile
        self._joint_cells[key] = cells
        return JointUpdate(key, payload, tile, pending_since)

    def _fuse_layers(self, key: TileKey, per_uav: dict[str, _UavTile],
                     now: float) -> tuple[NDArray[np.uint16], NDArray[np.uint8]]:
        """The rule over k >= 2 layers on the union of their non-zero cells: (idx, non-zero val)."""
        entries = list(per_uav.values())
        union = np.unique(np.concatenate([e.idx for e in entries]))
        stack = np.zeros((len(entries), union.size), dtype=np.uint8)
        for row, entry in zip(stack, entries, strict=True):
            row[np.searchsorted(union, entry.idx)] = entry.val
        covered = None
        if self.coverage == "footprint":
            masks = [self._coverage_mask(uav, key, now) for uav in per_uav]
            if any(m is not None for m in masks):
                covered = np.stack([np.ones(union.size, dtype=bool) if m is None else m.reshape(-1)[union]
                                    for m in masks])
        fused = self.rule(stack, covered)
        keep = fused != 0
        return union[keep], fused[keep]

    # ---- reading -------------------------------------------------------------------------------
    def get(self, key: TileKey) -> JointTile | None:
        """The current joint tile at key, or None."""
        with self._lock:
            return self._joint.get(key)

    def tiles(self, cls: str | None = None) -> list[JointTile]:
        """Snapshot of the current joint tiles (of one class, or all)."""
        with self._lock:
            if cls is None:
                return list(self._joint.values())
            return [tile for tile in self._joint.values() if tile.cls == cls]

    def tiles_in_range(self, cls: str, x0: int, x1: int, y0: int, y1: int) -> list[JointTile]:
        """Joint tiles of ``cls`` at the grid's zoom with x0 <= x <= x1 and y0 <= y <= y1.

        x wraps around the world (the antimeridian): x0 = -1 is the last column, x1 = 2**z the first, so a range
        with a tile of margin past either end holds the tiles across the line.
        """
        z, side = self.grid.z, self.grid.tiles_per_side
        width = min(x1 - x0 + 1, side)
        if width * (y1 - y0 + 1) <= 64:
            with self._lock:
                found = (self._joint.get((cls, z, (x0 + dx) % side, y)) for y in range(y0, y1 + 1)
                         for dx in range(width))
                return [tile for tile in found if tile is not None]
        with self._lock:
            return [t for t in self._joint.values() if t.cls == cls and (t.x - x0) % side < width and y0 <= t.y <= y1]

    def classes(self) -> set[str]:
        """Classes seen since start (in UAV tiles or restored joint tiles), at most 1024."""
        with self._lock:
            return set(self._classes)

    def uav_tile_counts(self) -> dict[str, int]:
        """Number of tiles each UAV currently covers (fresh tiles only)."""
        counts: dict[str, int] = {}
        with self._lock:
            for per_uav in self._covers.values():
                for uav in per_uav:
                    counts[uav] = counts.get(uav, 0) + 1
        return counts

    def stats(self) -> dict[str, int]:
        """Sizes: joint tiles, stored UAV tiles, tiles waiting to be fused, cached coverage masks,
        footprints held."""
        with self._lock:
            return {"joint_tiles": len(self._joint), "uav_tiles": self._n_uav_tiles, "pending": len(self._dirty),
                    "coverage_masks": len(self._masks),
                    "footprints": sum(len(prints) for prints in self._footprints.values())}

"""Which memory-map tiles go out in a publish cycle: changed or due for a refresh, within a byte budget,
encoded as sparse tile messages with per-tile sequence numbers (no network here).
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.memory_map import MemoryMap
from shared.tilecodec import encode_tile_sparse, quantise
from shared.tiles import TileGrid

__all__ = ["TileChangeTracker"]

#: Tiles whose cells take at most this many bytes go out even when the byte budget is spent.
_ALWAYS_SEND_BYTES = 256


@dataclass(slots=True)
class _SentTile:
    digest: bytes
    seq: int
    sent: float  # monotonic


class TileChangeTracker:
    """Decides which memory-map tiles to publish and encodes them with per-tile sequence numbers.

    A tile is due when its quantised content differs from what was last sent for it, or when it was
    last sent ``refresh_s`` ago or more (the server only counts a UAV as covering a tile while its
    latest message is fresher than the server's TTL). With a byte budget (``budget_bytes_per_s``, a
    token bucket holding at most one second of budget), due tiles go out stalest first until the
    budget is spent; the others stay due and rise in priority, so on a slow link every tile is still
    refreshed, just less often. Tiles with (nearly) no evidence are never held back: they cost ~60
    bytes and keep "I cover this and see nothing" fresh at the server. Tiles that leave the window
    are forgotten, so they are sent at once when the window comes back. Sequence numbers start at
    the wall clock in microseconds and grow by one per message of a tile, so they keep increasing
    across restarts.

    uav: this UAV's id; classes: the class names to publish (tiles of classes never seen go out empty:
    "I cover this tile and see nothing"); min_value: cells below it are sent as 0.
    """

    def __init__(self, uav: str, classes: list[str], grid: TileGrid, *, refresh_s: float = 1.0,
                 min_value: float = 0.0, budget_bytes_per_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if budget_bytes_per_s is not None and not (math.isfinite(budget_bytes_per_s) and budget_bytes_per_s > 0):
            raise ValueError(f"budget_bytes_per_s must be > 0 or None, got {budget_bytes_per_s!r}")
        self.uav = uav
        self.classes = list(classes)
        self.grid = grid
        self.refresh_s = refresh_s
        self.min_value = min_value
        self.budget_bytes_per_s = budget_bytes_per_s
        self.clock = clock
        self._sent: dict[tuple[str, int, int], _SentTile] = {}
        self._seq_base = time.time_ns() // 1000
        self._tokens = 0.0 if budget_bytes_per_s is None else float(budget_bytes_per_s)
        self._t_tokens: float | None = None
        self.n_changed = 0
        self.n_refreshed = 0
        self.n_skipped = 0
        self.n_deferred = 0

    def _refill(self, now: float) -> None:
        if self.budget_bytes_per_s is None:
            return
        if self._t_tokens is not None:
            burst = self.budget_bytes_per_s  # at most one second of budget saved up
            self._tokens = min(self._tokens + (now - self._t_tokens) * self.budget_bytes_per_s, burst)
        self._t_tokens = now

    def messages(self, memory: MemoryMap, t: float) -> list[tuple[str, int, int, bytes]]:
        """Tiles to publish now as ``(cls, x, y, payload)`` for a map at time t (seconds).

        Every class in ``classes`` plus any class the map holds is considered.
        """
        now = self.clock()
        self._refill(now)
        due = []  # (priority, tile id, digest, changed, idx, val)
        seen: set[tuple[str, int, int]] = set()
        for cls in dict.fromkeys([*self.classes, *memory.classes]):
            for x, y, values in memory.tiles(cls):
                tile_id = (cls, x, y)
                seen.add(tile_id)
                if self.min_value > 0:
                    values = np.where(values >= self.min_value, values, np.float32(0.0))
                flat = quantise(values).reshape(-1)
                idx = np.flatnonzero(flat != 0)
                val = flat[idx]
                digest = hashlib.blake2b(idx.astype("<u2").tobytes() + val.tobytes(), digest_size=16).digest()
                old = self._sent.get(tile_id)
                if old is not None and old.digest == digest and now - old.sent < self.refresh_s:
                    self.n_skipped += 1
                    continue
                age = math.inf if old is None else now - old.sent
                due.append((age, tile_id, digest, old is None or old.digest != digest, idx, val))
        for tile_id in [k for k in self._sent if k not in seen]:
            # keep the sequence going if the tile comes back: forget only what decides "due"
            self._seq_base = max(self._seq_base, self._sent[tile_id].seq + 1)
            del self._sent[tile_id]
        due.sort(key=lambda item: -item[0])  # stalest (and never sent) first
        out = []
        n = self.grid.n
        for _, tile_id, digest, changed, idx, val in due:
            # an empty or nearly empty tile costs ~60 bytes: never hold coverage back for that
            size = min(3 * idx.size, n * n)
            if self.budget_bytes_per_s is not None and self._tokens <= 0 and size > _ALWAYS_SEND_BYTES:
                self.n_deferred += 1
                continue
            cls, x, y = tile_id
            old = self._sent.get(tile_id)
            seq = self._seq_base if old is None else old.seq + 1
            payload = encode_tile_sparse(self.uav, cls, self.grid.z, x, y, n, t, seq, idx, val)
            self._tokens -= len(payload)  # may go below 0: repaid before the next tile goes out
            self._sent[tile_id] = _SentTile(digest, seq, now)
            if changed:
                self.n_changed += 1
            else:
                self.n_refreshed += 1
            out.append((cls, x, y, payload))
        return out

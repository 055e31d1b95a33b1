"""Where the agent puts its tiles: DESIGN.md's plain key, or the fusion shard's bucket key while shards are up.

Fusion shards (``uavmm fusion --shard K/N``, :mod:`shared.sharding`) announce themselves with liveliness
tokens that carry their region zoom. While any is present, each tile goes on
``{prefix}/uav/{uav}/shard/{region_zoom}/{bucket}/tiles/{cls}/{z}/{x}/{y}``, which only the shard that
owns the bucket subscribes to: Zenoh delivers the tile to that shard alone. Without shards (a single
fusion server) tiles go on DESIGN.md's ``{prefix}/uav/{uav}/tiles/{cls}/{z}/{x}/{y}``.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable

import zenoh

from shared.keys import KeySpace
from shared.sharding import tile_bucket

__all__ = ["ShardRouting"]

log = logging.getLogger(__name__)


class ShardRouting:
    """The shards' tokens as an agent sees them, and the tile keys they imply.

    keys, uav, z: the key space, this UAV's id and the grid zoom. on_bad_key(key, problem): called for
    a token key that does not parse. warn(name, fmt, *args): rate-limited warning.
    """

    def __init__(self, keys: KeySpace, uav: str, z: int, on_bad_key: Callable[[str, object], None],
                 warn: Callable[..., object]) -> None:
        self.keys = keys
        self.uav = uav
        self.z = z
        self._on_bad_key = on_bad_key
        self._warn = warn
        self._lock = threading.Lock()
        self._tokens: dict[str, int] = {}  # shard liveliness key -> its region zoom
        #: region zoom of the shards while any is up, else None (plain keys)
        self.zoom: int | None = None

    def declare(self, session: zenoh.Session, wrap: Callable[[Callable[[zenoh.Sample], None]], Callable]) -> object:
        """Watch the shards' tokens (with history); returns the subscriber (keep a reference)."""
        return session.liveliness().declare_subscriber(self.keys.shard_alive("*", "*"), wrap(self.on_token),
                                                       history=True)

    def tile_key(self, cls: str, x: int, y: int) -> str:
        """Key of this UAV's tile (cls, x, y) as things stand."""
        zoom = self.zoom
        if zoom is None:
            return self.keys.uav_tile(self.uav, cls, self.z, x, y)
        return self.keys.uav_bucket_tile(self.uav, zoom, tile_bucket(zoom, self.z, x, y), cls, self.z, x, y)

    def on_token(self, sample: zenoh.Sample) -> None:
        """A fusion shard came or went."""
        key = str(sample.key_expr)
        try:
            _, _, zoom = self.keys.parse_shard_token(key)
        except ValueError as exc:
            self._on_bad_key(key, exc)
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens[key] = zoom
            else:
                self._tokens.pop(key, None)
            zooms = Counter(self._tokens.values())
            before = self.zoom
            self.zoom = zooms.most_common(1)[0][0] if zooms else None
        if len(zooms) > 1:
            self._warn("shard_zoom", "agent %s: fusion shards disagree on the region zoom (%s): using %s", self.uav,
                       dict(zooms), self.zoom)
        if self.zoom != before:
            log.info("agent %s: %s", self.uav, "tiles on the plain keys (no fusion shard)" if self.zoom is None
                     else f"tiles routed to the fusion shards (regions of zoom {self.zoom})")

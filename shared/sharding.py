"""Which fusion shard owns which part of the tile space: regions of the slippy grid, hashed to shards.

Several fusion processes (shards, ``uavmm fusion --shard K/N``) split the map by **region**: the
slippy tile of zoom ``region_zoom`` (default 14: 16 x 16 grid tiles of zoom 18, 2.4 km x cos(lat)
across) that holds a grid tile. A region belongs to shard ``hash(region) mod N``: a mixing hash, so a
fleet packed into a few square kilometres still spreads over all shards, and every process (shard,
gateway, test) computes the same owner from the key alone. Region zoom is at most the zoom of the
track regions (``shared.keys.track_region``), so every track region and state region lies inside
one shard region and has one owner.

Routing by Zenoh: a region hashes to one of ``BUCKETS`` (64) buckets and bucket ``b`` belongs to
shard ``b mod N``. An agent that sees shard liveliness tokens (``KeySpace.shard_alive``, which carry
the region zoom) publishes each tile on ``{prefix}/uav/{uav}/shard/{region_zoom}/{bucket}/tiles/...``
(``KeySpace.uav_bucket_tile``), and each shard subscribes to its own buckets only
(``KeySpace.uav_bucket_tiles``): Zenoh delivers a tile to the one shard that fuses it, on whichever
machine it runs. Tiles on DESIGN.md's plain key still reach every shard, which drops the others' by key.

Shards are numbered from 0; ``ShardSpec.single()`` (0 of 1) is the unsharded server.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from shared.keys import TRACK_REGION_ZOOM_DROP

__all__ = ["BUCKETS", "DEFAULT_REGION_ZOOM", "ShardSpec", "parse_shard", "region_bucket", "region_owner", "tile_bucket"]

#: Zoom of the shard regions: 16 x 16 tiles of the default zoom-18 grid.
DEFAULT_REGION_ZOOM = 14

#: Buckets the regions hash to; bucket b belongs to shard b mod N (so at most 64 shards).
BUCKETS = 64

_MASK = 0xFFFFFFFFFFFFFFFF


def _mix(value: int) -> int:
    """splitmix64's finaliser: every input bit moves every output bit."""
    value = (value ^ (value >> 30)) * 0xBF58476D1CE4E5B9 & _MASK
    value = (value ^ (value >> 27)) * 0x94D049BB133111EB & _MASK
    return value ^ (value >> 31)


def region_bucket(region_z: int, rx: int, ry: int) -> int:
    """The bucket (0..BUCKETS-1) of region tile (region_z, rx, ry)."""
    return _mix(_mix((region_z << 58) ^ (rx << 29) ^ ry) + 0x9E3779B97F4A7C15 & _MASK) % BUCKETS


def tile_bucket(region_zoom: int, z: int, x: int, y: int) -> int:
    """The bucket of grid tile (z, x, y) when regions have zoom ``region_zoom`` (what an agent needs)."""
    drop = max(z - region_zoom, 0)
    return region_bucket(min(z, region_zoom), x >> drop, y >> drop)


def region_owner(region_z: int, rx: int, ry: int, count: int) -> int:
    """The shard (0..count-1) that owns region tile (region_z, rx, ry): its bucket modulo count."""
    return 0 if count == 1 else region_bucket(region_z, rx, ry) % count


@dataclass(frozen=True, slots=True)
class ShardSpec:
    """Shard ``index`` of ``count`` over regions of zoom ``region_zoom``; raises ValueError when invalid."""

    index: int = 0
    count: int = 1
    region_zoom: int = DEFAULT_REGION_ZOOM

    def __post_init__(self) -> None:
        for name in ("index", "count", "region_zoom"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"shard {name} must be an int, got {value!r}")
        if not 1 <= self.count <= BUCKETS:
            raise ValueError(f"shard count must be in 1..{BUCKETS}, got {self.count}")
        if not 0 <= self.index < self.count:
            raise ValueError(f"shard index must be in 0..{self.count - 1} for {self.count} shards, got {self.index}")
        if not 0 <= self.region_zoom <= 30:
            raise ValueError(f"region zoom must be in 0..30, got {self.region_zoom}")

    @classmethod
    def single(cls) -> ShardSpec:
        """The unsharded server: one shard owns everything."""
        return cls(0, 1)

    @property
    def sharded(self) -> bool:
        """Whether other shards share the map (count > 1)."""
        return self.count > 1

    def check_grid(self, grid_z: int) -> None:
        """ValueError unless the regions hold whole track regions of a zoom-``grid_z`` grid."""
        limit = max(grid_z - TRACK_REGION_ZOOM_DROP, 0)
        if self.region_zoom > limit:
            raise ValueError(f"region zoom {self.region_zoom} is finer than the track regions of a zoom-{grid_z} "
                             f"grid (zoom {limit}): use --region-zoom {limit} or less")

    def region(self, z: int, x: int, y: int) -> tuple[int, int, int]:
        """The region tile (region_zoom, rx, ry) holding tile (z, x, y) (z >= region_zoom; else the tile)."""
        drop = z - self.region_zoom
        if drop <= 0:
            return z, x, y
        return self.region_zoom, x >> drop, y >> drop

    def owner(self, z: int, x: int, y: int) -> int:
        """The shard that owns tile (z, x, y) (any zoom >= region_zoom)."""
        return 0 if self.count == 1 else self.bucket(z, x, y) % self.count

    def bucket(self, z: int, x: int, y: int) -> int:
        """The bucket of tile (z, x, y)'s region (the chunk of its shard-routed key)."""
        return tile_bucket(self.region_zoom, z, x, y)

    def buckets(self) -> list[int]:
        """The buckets this shard owns (its Zenoh subscriptions)."""
        return list(range(self.index, BUCKETS, self.count))

    def owns(self, z: int, x: int, y: int) -> bool:
        """Whether this shard owns tile (z, x, y)."""
        return self.count == 1 or self.owner(z, x, y) == self.index

    def label(self) -> str:
        """``K/N`` as the command line writes it."""
        return f"{self.index}/{self.count}"


def parse_shard(text: str, region_zoom: int = DEFAULT_REGION_ZOOM) -> ShardSpec:
    """``"K/N"`` (shard K of N, from 0) as a ShardSpec; ValueError naming the problem otherwise."""
    match = re.fullmatch(r"\s*(\d{1,4})\s*/\s*(\d{1,4})\s*", text)
    if match is None:
        raise ValueError(f"shard {text!r} is not K/N (shard K of N, counting from 0, e.g. 0/2)")
    return ShardSpec(int(match.group(1)), int(match.group(2)), region_zoom)

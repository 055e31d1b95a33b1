"""Settings of the fusion server process, validated once at start-up, and its Zenoh configuration.

`FusionSettings` holds every tunable of `uavmm fusion`. The Zenoh options (`ZenohOptions`,
`zenoh_config`) live in `transport.options` and are re-exported here.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from fusion_server.basemap import open_basemap
from fusion_server.cot import parse_cot_url
from fusion_server.http_auth import HttpToken, is_loopback_host
from fusion_server.joint_map import COVERAGE_MODES
from fusion_server.rules import FUSION_RULES
from shared.keys import DEFAULT_PREFIX, KeySpace
from shared.sharding import DEFAULT_REGION_ZOOM, ShardSpec
from shared.tiles import TileGrid
from transport.options import ZENOH_MODES, ZenohOptions, zenoh_config  # re-exported

__all__ = [
    "ZENOH_MODES",
    "FusionSettings",
    "ZenohOptions",
    "default_db_path",
    "zenoh_config",
]


def default_db_path() -> Path:
    """Default SQLite file: ``$XDG_DATA_HOME/uavmm/fusion.sqlite`` (``~/.local/share/uavmm/...``)."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "uavmm" / "fusion.sqlite"


def _positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class FusionSettings:
    """Everything `uavmm fusion` can be told; invalid values raise ValueError naming the field.

    Times in seconds, rates in Hz, distances in metres. ``db_path`` None disables persistence.
    ``http_port`` 0 picks a free port (the chosen one is reported by the server).
    """

    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    http_host: str = "127.0.0.1"
    http_port: int = 8000
    db_path: Path | None = field(default_factory=default_db_path)
    prefix: str = DEFAULT_PREFIX
    ttl_s: float = 2.0
    fusion_rule: str = "mean"
    coverage: str = "footprint"
    grid_z: int = 18
    grid_n: int = 256
    joint_max_hz: float = 5.0
    tracks_max_hz: float = 5.0
    track_gate_m: float = 10.0
    track_hold_s: float = 10.0
    track_reassociate_m: float = 6.0  # GlobalTracker's reassociate_m (0: off)
    track_history_len: int = 600
    track_history_interval_s: float = 1.0
    max_uavs: int = 256
    max_uav_tiles: int = 20_000
    max_tiles_per_uav: int = 1024
    restore_grace_s: float | None = None  # legacy name of restore_keep_s (wins when set)
    restore_keep_s: float = 300.0
    uav_keep_s: float = 3600.0
    db_recover: bool = False
    #: most cells of one /v1/map window (--map-max-cells): 2**23 holds 1 km x 1 km at z 18, n 256 up to
    #: ~54 deg latitude (0.4 m cells at 48 deg N: 2,503 x 2,503); a dense answer is ~4 bytes a cell
    map_max_cells: int = 2**23
    persist_interval_s: float = 0.5
    max_clock_skew_s: float = 30.0
    uav_max_msgs_per_s: float = 500.0
    uav_max_bytes_per_s: float = 4 * 1024 * 1024
    #: a UAV message that waited longer than this for the fusion thread is dropped unread ("overloaded"),
    #: so a server that fell behind catches up on fresh data and holds a few seconds of backlog, not a minute
    inbox_max_age_s: float = 5.0
    #: REST bearer tokens; required when ``http_host`` is not loopback, unless ``insecure_public``
    http_tokens: tuple[HttpToken, ...] = ()
    insecure_public: bool = False
    #: origins allowed to read the REST API from a browser page of theirs (CORS); none by default
    cors_origins: tuple[str, ...] = ()
    #: Cursor-on-Target events of UAVs and global tracks to udp://HOST:PORT or tcp://HOST:PORT (None: off)
    cot_url: str | None = None
    cot_interval_s: float = 1.0
    #: with cot_url: also the fused objects (joint-map peaks at or above this value) no global track explains
    #: (None: none)
    cot_objects_min_score: float | None = 0.5
    #: map under the live page: an http(s) XYZ template with {z}/{x}/{y} or an MBTiles file (None: none)
    basemap: str | None = None
    basemap_attribution: str | None = None
    #: this process is shard ``shard_index`` of ``shard_count`` over regions of zoom ``region_zoom``
    #: (shared.sharding; 0 of 1: the whole map)
    shard_index: int = 0
    shard_count: int = 1
    region_zoom: int = DEFAULT_REGION_ZOOM

    def __post_init__(self) -> None:
        if self.fusion_rule not in FUSION_RULES:
            raise ValueError(f"fusion_rule must be one of {', '.join(FUSION_RULES)}, got {self.fusion_rule!r}")
        if self.coverage not in COVERAGE_MODES:
            raise ValueError(f"coverage must be one of {', '.join(COVERAGE_MODES)}, got {self.coverage!r}")
        KeySpace(self.prefix)  # raises ValueError naming the bad chunk
        TileGrid(self.grid_z, self.grid_n)
        ShardSpec(self.shard_index, self.shard_count, self.region_zoom).check_grid(self.grid_z)
        if not isinstance(self.http_port, int) or not 0 <= self.http_port <= 65535:
            raise ValueError(f"http_port must be in 0..65535, got {self.http_port!r}")
        if not all(isinstance(t, HttpToken) for t in self.http_tokens):
            raise ValueError("http_tokens must be HttpToken values")
        if self.cot_url is not None:
            parse_cot_url(self.cot_url)
        if self.cot_objects_min_score is not None and not 0.0 < self.cot_objects_min_score <= 1.0:
            raise ValueError(f"cot_objects_min_score must be in (0, 1], got {self.cot_objects_min_score!r}")
        if self.basemap is not None:
            basemap = open_basemap(self.basemap, self.basemap_attribution)  # raises ValueError naming the problem
            if basemap.mbtiles is not None:
                basemap.mbtiles.close()
        for origin in self.cors_origins:
            if origin != "*" and not re.fullmatch(r"https?://[^/\s]+", origin):
                raise ValueError(f"cors_origins: {origin!r} is not an origin like https://maps.example.org "
                                 "(scheme and host[:port], no path) or *")
        if not self.http_tokens and not self.insecure_public and not is_loopback_host(self.http_host):
            raise ValueError(f"the REST API on {self.http_host} is reachable beyond this machine: give it a "
                             "token (--http-token-file FILE or UAVMM_HTTP_TOKEN) or accept an open API "
                             "with --insecure-public")
        for name in ("ttl_s", "joint_max_hz", "tracks_max_hz", "track_gate_m", "track_hold_s",
                     "track_history_interval_s", "persist_interval_s", "max_clock_skew_s",
                     "uav_max_msgs_per_s", "uav_max_bytes_per_s", "restore_keep_s", "uav_keep_s", "cot_interval_s",
                     "inbox_max_age_s"):
            _positive(name, getattr(self, name))
        if self.restore_grace_s is not None:
            _positive("restore_grace_s", self.restore_grace_s)
        reassociate = self.track_reassociate_m
        if not (isinstance(reassociate, (int, float)) and math.isfinite(reassociate) and reassociate >= 0):
            raise ValueError(f"track_reassociate_m must be a finite number >= 0 (0: off), got {reassociate!r}")
        for name in ("track_history_len", "max_uavs", "max_uav_tiles", "max_tiles_per_uav", "map_max_cells"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")

    @property
    def grid(self) -> TileGrid:
        """The shared tile grid the server accepts (tiles of another z or n are rejected)."""
        return TileGrid(self.grid_z, self.grid_n)

    @property
    def shard(self) -> ShardSpec:
        """The part of the map this process owns (ShardSpec.single() unless --shard)."""
        return ShardSpec(self.shard_index, self.shard_count, self.region_zoom)

    @property
    def keys(self) -> KeySpace:
        """The key space under ``prefix``."""
        return KeySpace(self.prefix)

"""The gateway process of a sharded deployment: the whole map's REST API and page, served from the shards.

``uavmm gateway --shards N`` fuses nothing: joint tiles are asked of the shards by Zenoh queries
(:mod:`fusion_server.remote_joint`), global tracks merged from their region messages
(:mod:`fusion_server.merged_tracks`) with their history asked of the shards by Zenoh queries
(:mod:`fusion_server.shard_tracks`), UAVs and shard liveliness heard on Zenoh
(:mod:`fusion_server.gateway_node`). :class:`Gateway` offers these through the same view as a fusion
server (``fusion_server.api.FusionView``), so ``create_app`` serves the same routes and page. While a
shard is down, /healthz says ``degraded`` and names it, and the UAVs over its regions are ``degraded``
in /v1/uavs; the rest keeps working. A shard that holds its token but does not answer (frozen, or cut off until
its lease ends) costs /v1/history and /v1/tracks at most a short wait after the first answer
(``fusion_server.shard_tracks.late_answer_s``), and /v1/history names it in ``missing_shards``.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from fusion_server.api import create_app
from fusion_server.basemap import open_basemap
from fusion_server.config import FusionSettings, zenoh_config
from fusion_server.gateway_node import GatewayNode, ShardWatch
from fusion_server.merged_tracks import DEFAULT_STALE_S, MergedTracks
from fusion_server.metrics import FusionMetrics
from fusion_server.remote_joint import DEFAULT_CACHE_S, RemoteJoint
from fusion_server.server import HttpThread
from fusion_server.shard_tracks import ShardAnswer
from fusion_server.shard_tracks_client import ShardTracks
from fusion_server.uav_clocks import UavClocks
from fusion_server.uav_registry import UavRegistry
from fusion_server.validation import MessageValidator
from shared.messages import MAX_TRACKS
from shared.sharding import ShardSpec
from shared.tiles import TileGrid

__all__ = ["Gateway", "ShardedUavs", "run_gateway"]

log = logging.getLogger(__name__)


class ShardedUavs(UavRegistry):
    """The UAV registry of a gateway: every /v1/uavs row also says which shard owns the region under the
    UAV (``shard``, from its last state's position; None without a state) and whether that shard is down
    (``degraded``)."""

    def __init__(self, spec: ShardSpec, grid: TileGrid, shards: ShardWatch, max_uavs: int = 256,
                 clocks: UavClocks | None = None) -> None:
        super().__init__(max_uavs=max_uavs, clocks=clocks)
        self.spec = spec
        self.grid = grid
        self.shards = shards

    def owner(self, lat: float, lon: float) -> int:
        """The shard that owns the region holding (lat, lon)."""
        x, y = self.grid.tile_of(lat, lon)
        return self.spec.owner(self.grid.z, int(x), int(y))

    def snapshot(self, tile_counts: dict[str, int] | None = None) -> list[dict[str, Any]]:
        """UavRegistry.snapshot() rows plus ``shard`` (int or None) and ``degraded`` (bool)."""
        rows = super().snapshot(tile_counts)
        down = self.shards.down()
        for row in rows:
            state = row["state"]
            shard = self.owner(state["lat"], state["lon"]) if state is not None else None
            row["shard"] = shard
            row["degraded"] = shard is not None and shard in down
        return rows


class Gateway:
    """A gateway over ``settings.shard_count`` shards (its ``settings.shard_index`` is unused).

    settings: FusionSettings of the REST side (http, tokens, CORS, basemap, prefix, grid, region zoom, Zenoh);
    its database is never used (each shard keeps its own). cache_s: how long the shards' joint tiles
    are reused; stale_s: a region's tracks drop out this long after its last message.
    """

    def __init__(self, settings: FusionSettings, *, cache_s: float = DEFAULT_CACHE_S,
                 stale_s: float = DEFAULT_STALE_S) -> None:
        if settings.shard_count < 1:
            raise ValueError(f"shards must be >= 1, got {settings.shard_count}")
        self.settings = settings
        self.started = time.monotonic()
        self.spec = ShardSpec(0, settings.shard_count, settings.region_zoom)
        keys = settings.keys
        grid = settings.grid
        self.metrics = FusionMetrics()
        # the fusion server's page draws the same basemap (an MBTiles file is served by the gateway itself)
        self.basemap = open_basemap(settings.basemap, settings.basemap_attribution) if settings.basemap else None
        self.shards = ShardWatch(settings.shard_count, settings.region_zoom)
        self.joint = RemoteJoint(keys, grid, cache_s=cache_s,
                                 on_reject=lambda reason: self.metrics.reject("joint_tile", reason))
        # each shard lists at most MAX_TRACKS tracks over its regions; twice that leaves room for handovers
        self.tracker = MergedTracks(stale_s=stale_s, history_len=settings.track_history_len,
                                    history_interval_s=settings.track_history_interval_s,
                                    max_tracks=2 * MAX_TRACKS * settings.shard_count)
        # the tracks' history, times and ended ones, asked of the shards (their region messages carry
        # where each track is and its status only)
        self.shard_tracks = ShardTracks(keys, settings.shard_count, history_len=settings.track_history_len,
                                        on_reject=lambda reason: self.metrics.reject("shard_tracks", reason),
                                        max_ahead_s=settings.max_clock_skew_s)
        self.tracker.details = self.shard_tracks.live
        #: how far each UAV's clock runs ahead, taken on evidence as a shard does (its states moved back by it)
        self.clocks = UavClocks(settings.max_clock_skew_s)
        self.uavs = ShardedUavs(self.spec, grid, self.shards, max_uavs=settings.max_uavs, clocks=self.clocks)
        validator = MessageValidator(keys, grid, max_clock_skew_s=settings.max_clock_skew_s, clocks=self.clocks)
        self.node = GatewayNode(zenoh_config(settings.zenoh), keys, validator, self.tracker, self.uavs,
                                self.shards, self.metrics, tracks_max_hz=settings.tracks_max_hz,
                                uav_keep_s=settings.uav_keep_s)
        #: REST requests refused for a missing or wrong bearer token, by reason
        self.http_denied: dict[str, int] = {}
        self.app = create_app(self)
        self.http: HttpThread | None = None

    def start(self, *, http: bool = True) -> None:
        """Open Zenoh (and ask the shards for their tracks), then serve the REST API if ``http``."""
        self.node.start()
        self.joint.session = self.node.session
        self.shard_tracks.session = self.node.session
        if http:
            self.http = HttpThread(self.app, self.settings.http_host, self.settings.http_port)
            self.http.start()

    def close(self) -> None:
        """Stop HTTP and close Zenoh (idempotent). A request waiting for the shards' tracks gets what has come so far
        at once: HTTP stops only once its requests end (a silent shard held SIGTERM for the 5 s query, and for a
        tile query's 2 s)."""
        self.shard_tracks.close()
        self.joint.close()
        if self.http is not None:
            self.http.stop()
            self.http = None
        self.joint.session = None
        self.shard_tracks.session = None
        self.node.close()
        self.joint.join()  # a summary's query in the background ends with the session
        if self.basemap is not None and self.basemap.mbtiles is not None:
            self.basemap.mbtiles.close()
            self.basemap = None

    def __enter__(self) -> Gateway:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def url(self) -> str | None:
        """Base URL of the REST API and map page, or None when HTTP is off."""
        return None if self.http is None else self.http.url

    # ---- FusionView ---------------------------------------------------------------------------------
    def classes(self) -> set[str]:
        """Classes of the shards' joint tiles (seen since start)."""
        return self.joint.classes()

    def history_tracks(self, cls: str | None = None, since: float | None = None, until: float | None = None,
                       ends_only: bool = False) -> ShardAnswer:
        """/v1/history's tracks: every shard's stored tracks (class ``cls``, updated since ``since``) with their
        history rows up to ``until`` (``ends_only``: the rows at each track's first and last time, what
        ``rows=false`` needs), merged by global id; the gateway's own merged tracks when no shard answers.
        The window is asked of the shards (a shard of the older version answers with every row since ``since``)
        and `history_window` cuts it again, so the answer is the same either way. ``missing``: the shards that did
        not answer in time (`ShardTracks`; all of them when none did), /v1/history's ``missing_shards``."""
        found = self.shard_tracks.stored(cls, since, until, ends_only)
        if found is None:
            return ShardAnswer([record.to_geojson() for record in self.tracker.records(include_ended=True)
                                if cls is None or record.cls == cls], range(self.spec.count))
        return ShardAnswer([track.to_feature() for track in found], found.missing)

    def db_health(self) -> dict[str, Any]:
        """``{"status": "off"}``: a gateway keeps nothing; each shard reports its own database."""
        return {"status": "off"}

    def zenoh_open(self) -> bool:
        """Whether the Zenoh session is open."""
        session = self.node.session
        return session is not None and not session.is_closed()

    def count_http_denied(self, reason: str) -> None:
        """Count a REST request refused for ``reason`` (``no_token`` or ``bad_token``)."""
        self.http_denied[reason] = self.http_denied.get(reason, 0) + 1

    def cluster_health(self) -> dict[str, Any]:
        """/healthz fields of a gateway: ``shards`` ({"K": {status, since, changes, regions, tracks}}),
        ``degraded`` (a shard is down), ``down`` (their indices), the shard count and region zoom."""
        regions: dict[str, int] = {}
        for region in self.tracker.regions():
            owner = str(self.spec.owner(*region))
            regions[owner] = regions.get(owner, 0) + 1
        status = {k: {**info, "regions": regions.get(k, 0)} for k, info in self.shards.status().items()}
        down = sorted(self.shards.down())
        body: dict[str, Any] = {"gateway": True, "shard_count": self.spec.count, "region_zoom": self.spec.region_zoom,
                                "shards": status, "degraded": bool(down), "down": down}
        if self.shards.foreign:
            body["foreign_shards"] = dict(self.shards.foreign)
        return body

    def prometheus(self) -> str:
        """Prometheus text: the gateway's message and drop counters, shards up, tracks, UAVs."""
        down = self.shards.down()
        gauges = {
            "uavmm_gateway_shards": ("Shards the gateway expects (--shards).", self.spec.count),
            "uavmm_gateway_shards_down": ("Shards without a liveliness token.", len(down)),
            "uavmm_gateway_joint_queries_total": ("Zenoh queries sent to the shards for joint tiles.",
                                                  self.joint.queries),
            "uavmm_gateway_track_queries_total": ("Zenoh queries sent to the shards for their tracks' history.",
                                                  self.shard_tracks.queries),
            "uavmm_fusion_uavs_online": ("UAVs whose liveliness token is present.", len(self.uavs.online())),
            "uavmm_fusion_global_tracks": ("Global tracks merged from the shards.", len(self.tracker)),
            "uavmm_gateway_regions_evicted_total": ("Fresh track regions forgotten beyond the gateway's bound of "
                                                    "tracks (2 x 10,000 per shard).", self.tracker.regions_evicted),
        }
        reasons = {"uavmm_fusion_http_denied_total": (
            "REST requests refused without a valid bearer token, by reason.", dict(self.http_denied))}
        return self.metrics.prometheus(gauges, reasons)


def run_gateway(settings: FusionSettings, stop: threading.Event) -> None:
    """Run a gateway until ``stop`` is set."""
    with Gateway(settings) as gateway:
        gateway.start()
        while not stop.wait(0.5):
            pass

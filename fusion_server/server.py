"""The fusion server process: its components wired together, the Zenoh node and the HTTP thread.

``with FusionServer(settings) as server: server.start()`` restores the database, opens Zenoh and
serves the REST API on ``server.url``; leaving the block shuts everything down and flushes the
database. :func:`run` does that until a stop event is set (the CLI sets it on SIGINT/SIGTERM).
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import uvicorn

from fusion_server.api import create_app
from fusion_server.basemap import open_basemap
from fusion_server.config import FusionSettings, zenoh_config
from fusion_server.cot import MAX_OBJECTS, CotSender, parse_cot_url
from fusion_server.db_check import check_database, move_aside
from fusion_server.global_tracks import GlobalTracker
from fusion_server.joint_map import JointMap
from fusion_server.metrics import FusionMetrics
from fusion_server.peaks import Peak, find_peaks
from fusion_server.persistence import FusionStore
from fusion_server.rate_limit import UavRateLimiter
from fusion_server.replay import stored_tracks
from fusion_server.rules import get_fusion_rule
from fusion_server.shard_tracks import TrackQuery
from fusion_server.uav_clocks import UavClocks
from fusion_server.uav_registry import UavRegistry
from fusion_server.validation import MessageValidator
from fusion_server.zenoh_node import FusionNode

__all__ = ["FusionServer", "HttpThread", "run"]

log = logging.getLogger(__name__)


class HttpThread:
    """uvicorn serving an ASGI app from a background thread; port 0 picks a free port."""

    def __init__(self, app, host: str, port: int) -> None:
        config = uvicorn.Config(app, host=host, port=port, log_level="warning", lifespan="off", access_log=False)
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="uavmm-fusion-http", daemon=True)
        self.host = host
        self.port = port

    def start(self, timeout_s: float = 10.0) -> None:
        """Start serving; raises OSError if the server did not come up within timeout_s."""
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise OSError(f"HTTP server could not listen on {self.host}:{self.port}")
            time.sleep(0.01)
        sockets = [s for server in self._server.servers for s in server.sockets]
        if sockets:
            self.port = sockets[0].getsockname()[1]

    def stop(self) -> None:
        """Stop serving and wait for the thread."""
        self._server.should_exit = True
        self._thread.join(timeout=10.0)

    @property
    def url(self) -> str:
        """Base URL of the REST API and map page (a wildcard bind shows as 127.0.0.1)."""
        host = self.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else f"[{host}]" if ":" in host else host
        return f"http://{shown}:{self.port}/"


class FusionServer:
    """All components of one fusion server, built from validated settings."""

    def __init__(self, settings: FusionSettings) -> None:
        self.settings = settings
        self.started = time.monotonic()
        keys = settings.keys
        grid = settings.grid
        self.metrics = FusionMetrics()
        self.joint = JointMap(grid, get_fusion_rule(settings.fusion_rule), settings.ttl_s, settings.joint_max_hz,
                              max_uav_tiles=settings.max_uav_tiles, max_tiles_per_uav=settings.max_tiles_per_uav,
                              coverage=settings.coverage)
        shard = settings.shard
        self.tracker = GlobalTracker(
            gate_m=settings.track_gate_m, hold_s=settings.track_hold_s, member_ttl_s=settings.ttl_s,
            reassociate_m=settings.track_reassociate_m,
            history_len=settings.track_history_len, history_interval_s=settings.track_history_interval_s,
            next_gid=shard.index + 1, gid_step=shard.count,  # shards hand out disjoint ids
            keep_changes=settings.db_path is not None,  # only a database drains them
        )
        #: how far each UAV's clock runs ahead of this one's, adopted on evidence (the validator moves its messages)
        self.clocks = UavClocks(settings.max_clock_skew_s)
        self.uavs = UavRegistry(max_uavs=settings.max_uavs, clocks=self.clocks)
        #: (what was wrong, where the bad file went) when --db-recover moved a database aside
        self.db_recovered: tuple[str, Path] | None = None
        self.store: FusionStore | None = None
        if settings.db_path is not None:
            if settings.db_recover:
                problem = check_database(settings.db_path)
                if problem is not None:
                    moved = move_aside(settings.db_path)
                    self.db_recovered = (problem, moved)
                    log.warning("database %s %s: moved it to %s and started a new one", settings.db_path,
                                problem, moved)
            self.store = FusionStore(settings.db_path, flush_interval_s=settings.persist_interval_s,
                                     history_len=settings.track_history_len)
        validator = MessageValidator(keys, grid, max_clock_skew_s=settings.max_clock_skew_s, clocks=self.clocks)
        self.node = FusionNode(
            zenoh_config(settings.zenoh), keys, validator, self.joint, self.tracker,
            self.uavs, self.metrics, self.store,
            UavRateLimiter(settings.uav_max_msgs_per_s, settings.uav_max_bytes_per_s, max_uavs=4 * settings.max_uavs),
            tracks_max_hz=settings.tracks_max_hz,
            uav_keep_s=settings.uav_keep_s, inbox_max_age_s=settings.inbox_max_age_s, shard=shard,
        )
        if self.node.handover is not None:
            self.tracker.adopt = self.node.handover.adopt
            self.node.track_source = self._track_features_for
        #: REST requests refused for a missing or wrong bearer token, by reason
        self.http_denied: dict[str, int] = {}
        self.basemap = open_basemap(settings.basemap, settings.basemap_attribution) if settings.basemap else None
        self.app = create_app(self)
        self.http: HttpThread | None = None
        self.cot: CotSender | None = None
        if settings.cot_url is not None:
            self.cot = CotSender(parse_cot_url(settings.cot_url), lambda: self.tracker.records(include_ended=True),
                                 self.uavs.snapshot,
                                 interval_s=settings.cot_interval_s,
                                 objects=None if settings.cot_objects_min_score is None else self._object_peaks)

    def start(self, *, http: bool = True) -> None:
        """Restore the database, open Zenoh, start publishing and (if ``http``) the REST API."""
        if self.store is not None:
            restored = self.store.load()
            keep_s = self.settings.restore_grace_s or self.settings.restore_keep_s
            n_tracks = self.tracker.restore(restored.tracks)
            kept = self.joint.restore(restored.joint_tiles, keep_s)
            for tile in restored.joint_tiles:  # older than their time to live: not served, not kept
                if self.joint.get(tile.key) is not tile:
                    self.store.save_joint(tile.key, None)
            n_uavs = self.uavs.restore(list(restored.uavs), self.settings.uav_keep_s)
            log.info("restored %d global tracks, %d joint tiles and %d UAVs from %s", n_tracks, kept, n_uavs,
                     self.store.path)
            self.store.start()
        self.node.start()
        if self.cot is not None:
            self.cot.start()
        if http:
            self.http = HttpThread(self.app, self.settings.http_host, self.settings.http_port)
            self.http.start()

    def close(self) -> None:
        """Stop HTTP, close Zenoh, flush and close the database (idempotent)."""
        if self.http is not None:
            self.http.stop()
            self.http = None
        if self.cot is not None:
            self.cot.close()
        if self.basemap is not None and self.basemap.mbtiles is not None:
            self.basemap.mbtiles.close()
            self.basemap = None
        self.node.close()
        if self.store is not None:
            self.store.close()
            self.store = None

    def __enter__(self) -> FusionServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- read side for the API -----------------------------------------------------------------
    @property
    def url(self) -> str | None:
        """Base URL of the REST API and map page, or None when HTTP is off."""
        return None if self.http is None else self.http.url

    def zenoh_open(self) -> bool:
        """Whether the Zenoh session is open."""
        session = self.node.session
        return session is not None and not session.is_closed()

    def classes(self) -> set[str]:
        """Classes present in the joint map or the UAVs' tiles."""
        return self.joint.classes()

    def _track_features(self) -> list[dict[str, Any]]:
        return [record.to_geojson() for record in self.tracker.records(include_ended=True)]

    def history_tracks(self, cls: str | None = None, since: float | None = None, until: float | None = None,
                       ends_only: bool = False) -> list[dict[str, Any]]:
        """Track features with their history rows for ``/v1/history``: from the database when there is one
        (class ``cls``, updated since ``since``, rows up to ``until``; ``ends_only``: each track's first and last
        row), else the tracker's own (fusion_server.replay)."""
        return stored_tracks(self.settings.db_path, self._track_features, cls=cls, since=since, until=until,
                             ends_only=ends_only)

    def _track_features_for(self, request: TrackQuery) -> list[dict[str, Any]]:
        """What a shard answers a ``fusion/tracks`` query with (fusion_server.shard_tracks): the features its
        ``/v1/tracks`` (``live``) or ``/v1/history`` (``stored``) would list."""
        if request.source == "stored":
            return self.history_tracks(request.cls, request.since, request.until, request.ends_only)
        return [record.to_geojson() for record in self.tracker.records(include_ended=request.ended)]

    def _object_peaks(self) -> list[Peak]:
        """The fused objects of every class at or above ``cot_objects_min_score``, strongest first (for CoT)."""
        min_score = self.settings.cot_objects_min_score or 0.5
        peaks = [peak for cls in sorted(self.classes())
                 for peak in find_peaks(self.joint.tiles(cls), self.joint.grid, min_score, limit=MAX_OBJECTS)]
        return sorted(peaks, key=lambda p: -p.score)

    def count_http_denied(self, reason: str) -> None:
        """Count a REST request refused for ``reason`` (``no_token`` or ``bad_token``)."""
        self.http_denied[reason] = self.http_denied.get(reason, 0) + 1

    def prometheus(self) -> str:
        """Prometheus text of all metrics, with the gauges of the joint map, UAVs and tracks."""
        stats = self.joint.stats()
        inbox = self.node.inbox_health()
        gauges: dict[str, tuple[str, float]] = {
            "uavmm_fusion_inbox_samples": ("UAV messages waiting for the fusion thread.", inbox["samples"]),
            "uavmm_fusion_inbox_oldest_seconds": ("How long the oldest waiting UAV message has waited (beyond "
                                                  "inbox_max_age_s it is dropped unread as overloaded).",
                                                  inbox["oldest_s"]),
            "uavmm_fusion_uavs_online": ("UAVs whose liveliness token is present.", len(self.uavs.online())),
            "uavmm_fusion_joint_tiles": ("Joint tiles currently published.", stats["joint_tiles"]),
            "uavmm_fusion_uav_tiles": ("Fresh UAV tiles held for fusion.", stats["uav_tiles"]),
            "uavmm_fusion_global_tracks": ("Global tracks (tracked or held).", len(self.tracker)),
            "uavmm_fusion_tracks_reassociated_total": (
                "Local tracks moved to the global track other UAVs report their object under (re-association).",
                self.tracker.stats()["reassociated"]),
            "uavmm_fusion_uav_conflicts": ("UAV ids heard from more than one Zenoh session at once.",
                                           len(self.uavs.conflicts())),
            "uavmm_fusion_liveliness_tokens_evicted": ("Liveliness tokens of ids without data forgotten "
                                                       "(registry full).", self.uavs.tokens_evicted),
        }
        reasons = {"uavmm_fusion_tracks_dropped_total": (
            "Local tracks cut from messages, new tracks refused a global id, held tracks ended early "
            "(bounds of the global tracker), by reason.", self.tracker.dropped()),
            "uavmm_fusion_http_denied_total": (
                "REST requests refused without a valid bearer token, by reason.", dict(self.http_denied))}
        if self.node.handover is not None:
            gauges["uavmm_fusion_shard_skipped_tiles_total"] = (
                "Tile messages of other shards' regions dropped by key (--shard).", self.node.skipped)
            reasons["uavmm_fusion_handovers_total"] = (
                "Global ids taken over from another shard (in) and held copies ended because another shard "
                "carries them on (out).", dict(self.tracker.handovers))
        if self.cot is not None:
            gauges["uavmm_fusion_cot_events_total"] = ("Cursor-on-Target events sent (--cot-url).", self.cot.sent)
            gauges["uavmm_fusion_cot_failures_total"] = ("Cursor-on-Target rounds that failed to send.",
                                                         self.cot.failed)
        if self.store is not None:
            db = self.store.health()
            gauges.update({
                "uavmm_fusion_db_failing": ("1 while writes to the database fail (they are retried).",
                                            1.0 if db["status"] == "failing" else 0.0),
                "uavmm_fusion_db_pending": ("Changes queued for the database, not yet committed.", db["pending"]),
                "uavmm_fusion_db_write_errors_total": ("Failed database flushes (each is retried).",
                                                       db["write_errors"]),
                "uavmm_fusion_db_flushes_total": ("Committed database flushes.", db["flushes"]),
                "uavmm_fusion_db_history_dropped_total": ("History rows dropped from the backlog while the "
                                                          "database could not be written.", db["history_dropped"]),
            })
        leads = {uav: max(kinds.values()) for uav, kinds in self.clocks.leads().items()}
        labelled = {"uavmm_fusion_uav_clock_lead_seconds": (
            "How far a UAV's clock runs ahead of the server's, adopted on evidence (its messages are moved back by "
            "it); UAVs without a lead are not listed.", "uav", leads)}
        return self.metrics.prometheus(gauges, reasons, labelled)

    def cluster_health(self) -> dict[str, Any]:
        """Extra /healthz fields: ``inbox`` (UAV messages waiting for the fusion thread and how long the
        oldest has waited); of a shard also ``shard`` (K/N), what crossed its borders and the
        ``fusion/tracks`` queries it answered and refused."""
        inbox = self.node.inbox_health()
        handover = self.node.handover
        if handover is None:
            return {"inbox": inbox}
        body = {"inbox": inbox, "shard": self.settings.shard.label(), "region_zoom": self.settings.region_zoom,
                "skipped_tiles": self.node.skipped, "handovers": dict(self.tracker.handovers),
                "foreign_region_messages": handover.received}
        queryable = self.node.tracks_queryable
        if queryable is not None:  # the gateway's questions for the tracks' history (fusion/tracks)
            body["track_queries"] = {"answered": queryable.answered, "refused": queryable.refused}
        return body

    def db_health(self) -> dict[str, Any]:
        """The database's health for /healthz: FusionStore.health(), or ``{"status": "off"}``."""
        store = self.store
        return store.health() if store is not None else {"status": "off"}


def run(settings: FusionSettings, stop: threading.Event,
        on_ready: Callable[[FusionServer], None] | None = None) -> None:
    """Run a fusion server until ``stop`` is set, then shut it down cleanly."""
    with FusionServer(settings) as server:
        server.start()
        if on_ready is not None:
            on_ready(server)
        # the objects of start-up (modules, the restored state) are never garbage: keep the cyclic
        # collector from scanning them again in every full collection (a 50 ms pause at 200 UAVs)
        gc.freeze()
        while not stop.wait(0.5):
            pass
        log.info("shutting down")

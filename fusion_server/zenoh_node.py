"""The fusion server's Zenoh side: subscriptions, liveliness, the joint queryable and the publisher thread.

Callbacks validate every sample and feed the joint map, the global tracker and the UAV registry;
they count and log (rate-limited) what they drop and never raise. One thread fuses and publishes
joint tiles and joint tracks (``CongestionControl.BLOCK``) and hands changes to persistence.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import zenoh

from fusion_server.joint_map import JointMap, TileKey
from fusion_server.validation import MessageValidator, Rejected
from shared.messages import MAX_TRACKS, StateMessage, TracksMessage, encode_joint_tracks
from shared.tilecodec import TileMessage
from transport.guard import RateLimitedLog, guarded
from transport.publishers import PublisherCache

if TYPE_CHECKING:
    from fusion_server.global_tracks import GlobalTracker
    from fusion_server.metrics import FusionMetrics
    from fusion_server.persistence import FusionStore
    from fusion_server.rate_limit import UavRateLimiter
    from fusion_server.uav_registry import UavRegistry
    from shared.keys import KeySpace

__all__ = ["FusionNode"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

#: Housekeeping period of the publisher thread (track expiry, joint tracks, persistence), seconds.
_TICK_S = 0.05


def _session_of(sample: zenoh.Sample) -> str | None:
    """The sending agent's Zenoh session id from the sample's attachment (docs/protocol.md), if any."""
    attachment = sample.attachment
    if attachment is None:
        return None
    raw = attachment.to_bytes()
    if 1 <= len(raw) <= 32 and all(c in b"0123456789abcdef" for c in raw):
        return raw.decode("ascii")
    return "invalid"


class FusionNode:
    """One Zenoh session of the fusion server.

    conf: the Zenoh config. keys: the key space. tracks_max_hz: most joint tracks messages a second.
    max_tracks_bytes: largest joint tracks message (fewer tracks are sent beyond it, tracked ones
    first). store: persistence, or None. limiter: per-UAV rate limits checked before decoding, or
    None. uav_keep_s: offline UAVs not seen for this long are forgotten. The components are shared
    with the REST API.
    """

    def __init__(
        self,
        conf: zenoh.Config,
        keys: KeySpace,
        validator: MessageValidator,
        joint: JointMap,
        tracker: GlobalTracker,
        uavs: UavRegistry,
        metrics: FusionMetrics,
        store: FusionStore | None = None,
        limiter: UavRateLimiter | None = None,
        *,
        tracks_max_hz: float = 5.0,
        persist_interval_s: float = 0.5,
        max_tracks_bytes: int = 1024 * 1024,
        uav_keep_s: float = 3600.0,
    ) -> None:
        self.conf = conf
        self.keys = keys
        self.validator = validator
        self.joint = joint
        self.tracker = tracker
        self.uavs = uavs
        self.metrics = metrics
        self.store = store
        self.limiter = limiter
        self.tracks_min_interval_s = 1.0 / tracks_max_hz
        self.persist_interval_s = persist_interval_s
        self.max_tracks_bytes = max_tracks_bytes
        self.uav_keep_s = uav_keep_s
        self.session: zenoh.Session | None = None
        self._declared: list = []
        self._publishers: PublisherCache | None = None
        self._tracks_publisher: zenoh.Publisher | None = None
        self._tracks_payload = encode_joint_tracks(tracker.joint_message())
        self._tracks_key = keys.joint_tracks()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reject_log = RateLimitedLog(log)
        self._step_log = RateLimitedLog(log)

    # ---- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Open the session, declare the subscribers and the queryable, start the publisher thread.

        Raises zenoh.ZError when the session cannot be opened (e.g. the listen port is taken).
        """
        self.session = zenoh.open(self.conf)
        session = self.session
        # BLOCK: a joint tile must arrive (the default DROP loses some under load)
        self._publishers = PublisherCache(session)
        self._tracks_publisher = self._publishers.get(self._tracks_key)
        # keep references: declared entities are undeclared when garbage-collected
        self._declared = [
            session.declare_subscriber(self.keys.uav_all(), self._on_sample),
            session.liveliness().declare_subscriber(self.keys.uav_alive("*"), self._on_alive, history=True),
            session.declare_queryable(self.keys.joint_all(), guarded(self._on_query, log, "a query")),
        ]
        self._thread = threading.Thread(target=self._run, name="uavmm-fusion-publisher", daemon=True)
        self._thread.start()
        log.info("fusion node %s up, subscribed to %s", session.zid(), self.keys.uav_all())

    def close(self) -> None:
        """Stop the publisher thread and close the session (idempotent)."""
        self._stop.set()
        self.joint.poke()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        if self.session is not None:
            for entity in self._declared:
                try:
                    entity.undeclare()
                except zenoh.ZError:
                    pass
            self._declared = []
            if self._publishers is not None:
                self._publishers.clear()
            self.session.close()
            self.session = None

    # ---- callbacks (Zenoh threads; never raise) ------------------------------------------------
    def _reject(self, kind: str, reason: str, key: str, detail: object, uav: str | None = None) -> None:
        self.metrics.reject(kind, reason)
        if uav is not None:
            self.uavs.rejected(uav, reason)
        self._reject_log.warning(reason, "dropped %s message on %.120s: %s: %.200s", kind, key, reason, detail)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = "?"
        uav: str | None = None
        try:
            key = str(sample.key_expr)
            if sample.kind != zenoh.SampleKind.PUT:
                kind = "unknown"
                try:
                    kind = self.validator.parse_key(key)[1]
                except Rejected:
                    pass
                self._reject(kind, "unexpected_delete", key, "DELETE sample")
                return
            parsed, kind = self.validator.parse_key(key)
            uav = parsed.uav
            nbytes = len(sample.payload)
            limited = self.limiter.check(uav, nbytes) if self.limiter is not None else None
            if limited is not None:  # before decoding: a flood costs a lookup per message
                self._reject(kind, limited, key, f"{nbytes} bytes", uav)
                return
            received = self.validator.validate(key, sample.payload, parsed=parsed)
            message = received.message
            if not self.uavs.message(uav, received.kind, received.nbytes,
                                     message if isinstance(message, StateMessage) else None,
                                     session=_session_of(sample)):
                self._reject(received.kind, "too_many_uavs", key, "UAV registry full")
                return
            if isinstance(message, TileMessage):
                values = np.rint(message.values * np.float32(255.0)).astype(np.uint8)
                tile_key: TileKey = (message.cls, message.z, message.x, message.y)
                reason = self.joint.put(message.uav, tile_key, values, message.t, message.seq)
                if reason is not None:
                    self._reject("tile", reason, key, f"seq {message.seq}", uav)
                    return
            elif isinstance(message, StateMessage):
                self.joint.put_footprint(message.uav, message.footprint)
            elif isinstance(message, TracksMessage):
                self.tracker.update(message)
                self.joint.poke()
            self.metrics.message(received.kind, received.nbytes)
        except Rejected as exc:
            self._reject(exc.kind, exc.reason, key, exc, uav)
        except Exception:  # a bug must not take the subscriber down: count it, log it
            self.metrics.reject("unknown", "internal_error")
            log.exception("internal error handling a sample on %.120s", key)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        key = "?"
        try:
            key = str(sample.key_expr)
            try:
                parsed = self.keys.parse(key)
            except ValueError as exc:
                self._reject("alive", "bad_key", key, exc)
                return
            if parsed.kind != "uav_alive":
                self._reject("alive", "unexpected_key", key, "not an alive key")
                return
            online = sample.kind == zenoh.SampleKind.PUT
            if not self.uavs.alive(parsed.uav, online):
                self._reject("alive", "too_many_uavs", key, "UAV registry full")
                return
            self.metrics.message("alive", 0)
            log.info("UAV %s %s", parsed.uav, "online" if online else "offline")
            if not online and self.tracker.uav_lost(parsed.uav):
                self.joint.poke()
        except Exception:
            self.metrics.reject("alive", "internal_error")
            log.exception("internal error handling liveliness on %.120s", key)

    def _on_query(self, query: zenoh.Query) -> None:
        selector = query.key_expr
        for tile in self.joint.tiles():
            tile_key = self.keys.joint_tile(tile.cls, tile.z, tile.x, tile.y)
            if selector.intersects(tile_key):
                query.reply(tile_key, tile.payload)
        if selector.intersects(self._tracks_key):
            query.reply(self._tracks_key, self._tracks_payload)
        self.metrics.query()

    # ---- publisher thread ----------------------------------------------------------------------
    def _publish_tiles(self) -> float | None:
        updates, next_due = self.joint.step()
        assert self._publishers is not None
        for update in updates:
            cls, z, x, y = update.key
            key = self.keys.joint_tile(cls, z, x, y)
            self._publishers.put(key, update.payload)
            dropped = update.tile is None
            if dropped:
                self._publishers.drop(key)
            self.metrics.published(time.monotonic() - update.pending_since, dropped=dropped)
            if self.store is not None:
                self.store.save_joint(update.key, update.tile)
        return next_due

    def _publish_tracks(self) -> None:
        # bounded: at most MAX_TRACKS tracks (the schema's limit) and max_tracks_bytes, tracked ones
        # first, so a flood of tracks shortens the message instead of stopping it
        limit = MAX_TRACKS
        while True:
            message = self.tracker.joint_message(limit)
            payload = encode_joint_tracks(message)
            if len(payload) <= self.max_tracks_bytes or limit <= 1:
                break
            limit = len(message.tracks) // 2
        left_out = len(self.tracker) - len(message.tracks)
        if left_out > 0:
            self.metrics.tracks_left_out(left_out)
        self._tracks_payload = payload
        assert self._tracks_publisher is not None
        self._tracks_publisher.put(payload)
        self.metrics.tracks_sent()

    def _step(self, name: str, action: Callable[[], _T]) -> _T | None:
        """Run one step of the publisher thread; a failure is logged (rate-limited) and counted, and
        never keeps the other steps (joint tiles, tracks, persistence) from running."""
        try:
            return action()
        except Exception as exc:
            if self._stop.is_set():
                return None
            self.metrics.reject("publisher", f"{name}_failed")
            self._step_log.warning(name, "publisher step %s failed: %s", name, exc)
            log.debug("publisher step %s failed", name, exc_info=True)
            return None

    def _persist_tracks(self) -> None:
        assert self.store is not None
        records, history = self.tracker.drain_changes()
        self.store.save_tracks(records, history, self.tracker.next_gid)
        uavs, forgotten = self.uavs.drain_changes()
        self.store.save_uavs(uavs, forgotten)

    def _run(self) -> None:
        tracks_version = -1
        last_tracks = -float("inf")
        next_housekeeping = 0.0
        next_forget = 0.0
        next_persist = time.monotonic() + self.persist_interval_s
        while not self._stop.is_set():
            next_due = self._step("joint_tiles", self._publish_tiles)
            now = time.monotonic()
            if now >= next_housekeeping:
                self._step("expire", self.tracker.expire)
                next_housekeeping = now + _TICK_S
            if now >= next_forget:
                self._step("forget_uavs", lambda: self.uavs.forget_offline(self.uav_keep_s))
                next_forget = now + 5.0
            if self.tracker.version != tracks_version and now - last_tracks >= self.tracks_min_interval_s:
                tracks_version = self.tracker.version
                last_tracks = now
                self._step("joint_tracks", self._publish_tracks)
            if self.store is not None and now >= next_persist:
                self._step("persist", self._persist_tracks)
                next_persist = now + self.persist_interval_s
            timeout = _TICK_S if next_due is None else min(_TICK_S, next_due - time.monotonic())
            self.joint.wait(max(timeout, 0.0))
        if self.store is not None:
            self._step("persist", self._persist_tracks)

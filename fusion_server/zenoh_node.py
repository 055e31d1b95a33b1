"""The fusion server's Zenoh side: subscriptions, liveliness, the joint queryable and the fusion thread.

The data subscriber's callback only enqueues the sample with its arrival time (a bounded inbox: beyond
it samples are dropped and counted as "overloaded", and so are samples that waited in it longer than
``inbox_max_age_s``: every UAV message is a snapshot its UAV sends again within a second or so, and an
old backlog only pins memory and delays the fresh ones). One thread drains the inbox in batches, validates every
sample and feeds the joint map (one lock per batch), the global tracker and the UAV registry,
counting and logging (rate-limited) what it drops; between batches it fuses and publishes joint
tiles and joint tracks (``CongestionControl.BLOCK``) and hands the joint tiles to persistence, whose
writer thread batches them into SQLite with the tracks' and UAVs' changes it collects itself at each
flush. Callbacks never raise.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import zenoh

from fusion_server.handover import Handover
from fusion_server.joint_map import JointMap, TileKey
from fusion_server.shard_tracks import TrackQuery, TracksQueryable
from fusion_server.uav_intake import UavIntake
from fusion_server.validation import MessageValidator, Received, Rejected
from shared.keys import track_region
from shared.messages import (
    JointTrackItem,
    JointTracksMessage,
    StateMessage,
    TracksMessage,
    encode_joint_tracks,
    encode_joint_tracks_within,
)
from shared.sharding import ShardSpec
from shared.tilecodec import SparseTile
from transport.guard import RateLimitedLog, guarded
from transport.publishers import PublisherCache
from transport.session import close_session

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from fusion_server.global_tracks import GlobalTracker
    from fusion_server.metrics import FusionMetrics
    from fusion_server.persistence import FusionStore
    from fusion_server.rate_limit import UavRateLimiter
    from fusion_server.uav_registry import UavRegistry
    from shared.keys import KeySpace

__all__ = ["FusionNode"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

#: Housekeeping period of the fusion thread (track expiry, joint tracks, persistence), seconds.
_TICK_S = 0.05
#: Samples handled between two publishing steps of the fusion thread.
_BATCH = 256
#: A region's joint tracks are published again after this long even when unchanged (agents drop joint
#: tracks older than their joint TTL, 3 s by default), seconds.
_REGION_REFRESH_S = 1.0
#: Region tracks messages a second (at most, per region): 2 Hz keeps a UAV's share of the fleet's
#: tracks within its downlink budget; the global joint tracks go at --tracks-max-hz.
REGION_TRACKS_HZ = 2.0
#: Most regions a state message is forwarded to (a footprint over more: its UAV's region only).
_MAX_STATE_REGIONS = 16


def _session_of(raw: bytes) -> str:
    """The session id an attachment names (docs/protocol.md): lowercase hex, 1-32 chars, else "invalid"."""
    if 1 <= len(raw) <= 32 and all(c in b"0123456789abcdef" for c in raw):
        return raw.decode("ascii")
    return "invalid"


class FusionNode:
    """One Zenoh session of the fusion server.

    conf: the Zenoh config. keys: the key space. tracks_max_hz: most joint tracks messages a second.
    max_tracks_bytes: largest joint tracks message (fewer tracks are sent beyond it, tracked ones
    first). store: persistence, or None. limiter: per-UAV rate limits checked before decoding, or
    None. uav_keep_s: offline UAVs not seen for this long are forgotten. inbox_max: samples waiting
    for the fusion thread (beyond: dropped, counted as "overloaded"; 65,536 are ~7 s of 200 UAVs of
    `uavmm bench fusion`, ~36 s of 50 UAVs sending states, tracks and moving footprints, and up to
    ~20 kB of memory each). inbox_max_age_s: a sample that waited longer than this is dropped unread
    when the fusion thread reaches it (counted as "overloaded"): it catches up on fresh data at once.
    The components are shared with the REST API.
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
        max_tracks_bytes: int = 1024 * 1024,
        uav_keep_s: float = 3600.0,
        inbox_max: int = 65_536,
        inbox_max_age_s: float = 5.0,
        shard: ShardSpec | None = None,
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
        self.max_tracks_bytes = max_tracks_bytes
        self.uav_keep_s = uav_keep_s
        self.shard = shard if shard is not None else ShardSpec.single()
        self.handover = Handover(self.shard, keys, tracker, joint.grid) if self.shard.sharded else None
        #: tile samples of other shards' regions dropped by key, before decoding
        self.skipped = 0
        self.session: zenoh.Session | None = None
        self._declared: list = []
        self._publishers: PublisherCache | None = None
        self._tracks_publisher: zenoh.Publisher | None = None
        self._tracks_payload = encode_joint_tracks(tracker.joint_message())
        self._tracks_key = keys.joint_tracks()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._intake = UavIntake(keys, uavs, metrics, log)
        self._step_log = RateLimitedLog(log)
        self.inbox_max = int(inbox_max)
        self.inbox_max_age_s = float(inbox_max_age_s)
        self._inbox: deque[tuple[float, zenoh.Sample]] = deque()  # (monotonic arrival, sample), oldest first
        self._wakeup = threading.Event()
        self._sessions: dict[bytes, str] = {}  # attachment bytes -> session id (bounded cache)
        # region -> (its tracks, payload, monotonic time) as last published on region/tracks/{z}/{x}/{y}
        self._region_payloads: dict[tuple[int, int, int], tuple[tuple[JointTrackItem, ...], bytes, float]] = {}
        #: a shard's track features for ``fusion/tracks`` queries (the server sets it: what its REST API
        #: lists for /v1/tracks and /v1/history); None: no such queryable
        self.track_source: Callable[[TrackQuery], list[dict[str, Any]]] | None = None
        #: the queryable answering them (while started)
        self.tracks_queryable: TracksQueryable | None = None
        if store is not None:
            # pulled by the store's writer at each flush, so a commit never holds tiles without the
            # UAVs and tracks of that moment (a SIGKILL between two ticks of this thread lost them)
            store.sources.append(self._persist_tracks)

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
            *[session.declare_subscriber(selector, self._on_sample) for selector in self._data_selectors()],
            session.liveliness().declare_subscriber(self.keys.uav_alive("*"), self._on_alive, history=True),
            session.declare_queryable(self.keys.joint_all(), guarded(self._on_query, log, "a query")),
            session.declare_queryable(self.keys.region_all(), guarded(self._on_query, log, "a region query")),
        ]
        if self.handover is not None:
            shard = self.shard
            self._declared += [
                session.liveliness().declare_token(self.keys.shard_alive(shard.index, shard.count, shard.region_zoom)),
                session.declare_subscriber(self.keys.region_tracks_all(),
                                           guarded(self.handover.on_region_tracks, log, "foreign region tracks")),
            ]
            if self.track_source is not None:  # the gateway asks here for the tracks' history
                key = self.keys.shard_tracks(shard.index, shard.count)
                self.tracks_queryable = TracksQueryable(self.track_source, key, shard.index, shard.count)
                self.tracks_queryable.start()
                self._declared.append(session.declare_queryable(key, self.tracks_queryable.on_query))
        self._thread = threading.Thread(target=self._run, name="uavmm-fusion", daemon=True)
        self._thread.start()
        log.info("fusion node %s up, subscribed to %s", session.zid(),
                 self.keys.uav_all() if not self.shard.sharded else
                 f"shard {self.shard.label()}: states, tracks, plain tile keys and buckets {self.shard.buckets()}")

    def _data_selectors(self) -> list[str]:
        """What the agents publish that this process takes: everything (``uav/**``), or for a shard the
        states, tracks, the plain tile keys (dropped by key unless its own) and its own buckets of
        shard-routed tile keys (shared.sharding)."""
        keys, shard = self.keys, self.shard
        if not shard.sharded:
            return [keys.uav_all()]
        return [keys.uav_state("*"), keys.uav_tracks("*"), keys.uav_tiles_all(),
                *[keys.uav_bucket_tiles(shard.region_zoom, b) for b in shard.buckets()]]

    def close(self) -> None:
        """Stop the fusion thread and close the session (idempotent)."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        if self.tracks_queryable is not None:
            self.tracks_queryable.close()
            self.tracks_queryable = None
        if self.session is not None:
            close_session(self.session, self._declared, self._publishers)
            self.session = None

    # ---- callbacks (Zenoh threads; never raise) ------------------------------------------------
    def _wake(self) -> None:
        """Wake the fusion thread (a sample, a tracks change, shutdown)."""
        if not self._wakeup.is_set():
            self._wakeup.set()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: enqueue only (the fusion thread validates and fuses)."""
        try:
            if self.handover is not None and not self._mine(str(sample.key_expr)):
                self.skipped += 1
                return
            if len(self._inbox) >= self.inbox_max:
                self.metrics.reject("unknown", "overloaded")
                self._intake.warnings.warning(
                    "overloaded", "fusion inbox full (%d samples): dropped a sample on %.120s", self.inbox_max,
                    str(sample.key_expr))
                return
            self._inbox.append((time.monotonic(), sample))
            self._wake()
        except Exception:
            self.metrics.reject("unknown", "internal_error")
            log.exception("internal error enqueueing a sample")

    def _mine(self, key: str) -> bool:
        """Whether a sample on ``key`` is this shard's: tiles of its regions and every other message
        (states and tracks are split later, by position). Cheap: no decoding."""
        parts = key.rsplit("/", 5)
        if len(parts) != 6 or parts[1] != "tiles":
            return True
        try:
            return self.shard.owns(int(parts[3]), int(parts[4]), int(parts[5]))
        except ValueError:
            return True  # the validator rejects it with its reason

    def _session_of(self, sample: zenoh.Sample) -> str | None:
        """The sending agent's Zenoh session id from the sample's attachment (docs/protocol.md), if any."""
        attachment = sample.attachment
        if attachment is None:
            return None
        raw = attachment.to_bytes()
        session = self._sessions.get(raw)
        if session is None:
            session = _session_of(raw)
            if len(self._sessions) >= 4096:
                self._sessions.clear()
            self._sessions[raw] = session
        return session

    def _ingest(self, batch: list[zenoh.Sample]) -> None:
        """Validate a batch of samples; states and tracks are applied in order, tiles go to the joint
        map together at the end (one lock)."""
        tiles: list[tuple[str, TileKey, NDArray[np.uint16], NDArray[np.uint8], float, int]] = []
        accepted: list[tuple[Received, str, int]] = []  # with the tile's seq
        for sample in batch:
            received, key = self._admit(sample)
            if received is None:
                continue
            message = received.message
            try:
                if isinstance(message, SparseTile):
                    tiles.append((message.uav, (message.cls, message.z, message.x, message.y), message.idx,
                                  message.val, message.t, message.seq))
                    accepted.append((received, key, message.seq))
                    continue
                if isinstance(message, StateMessage):
                    self.joint.put_footprint(message.uav, message.footprint)
                    self._forward_state(message, sample.payload.to_bytes())
                elif isinstance(message, TracksMessage):
                    if self.handover is not None:
                        message = self.handover.own_tracks(message)
                    self.tracker.update(message)
                self.metrics.message(received.kind, received.nbytes)
            except Exception:  # a bug must not take the fusion thread down: count it, log it
                self.metrics.reject("unknown", "internal_error")
                log.exception("internal error handling a sample on %.120s", key)
        if not tiles:
            return
        reasons = self.joint.put_many(tiles)
        count = nbytes = 0
        for reason, (received, key, seq) in zip(reasons, accepted, strict=True):
            if reason is None:
                count += 1
                nbytes += received.nbytes
            else:
                self._intake.reject("tile", reason, key, f"seq {seq}", received.key.uav)
        if count:
            self.metrics.message("tile", nbytes, count)

    def _forward_state(self, message: StateMessage, payload: bytes) -> None:
        """Put a UAV's state message, as it came, on ``region/states/{z}/{x}/{y}/{uav}`` for each region
        its footprint and position touch (at most _MAX_STATE_REGIONS; beyond, its position's only), so
        an agent receives the states of the UAVs near it only (agent.joint_window)."""
        if self.session is None:
            return
        grid = self.joint.grid
        points = np.array([*message.footprint, (message.lat, message.lon)], dtype=np.float64)
        xs, ys = grid.tile_of(points[:, 0], points[:, 1])
        z, rx0, ry0 = track_region(grid.z, int(xs.min()), int(ys.min()))
        _, rx1, ry1 = track_region(grid.z, int(xs.max()), int(ys.max()))
        if (rx1 - rx0 + 1) * (ry1 - ry0 + 1) > _MAX_STATE_REGIONS:
            z, rx0, ry0 = track_region(grid.z, int(xs[-1]), int(ys[-1]))
            rx1, ry1 = rx0, ry0
        for ry in range(ry0, ry1 + 1):
            for rx in range(rx0, rx1 + 1):
                if not self.shard.owns(z, rx, ry):
                    continue  # the region's shard forwards it
                self.session.put(self.keys.region_state(z, rx, ry, message.uav), payload,
                                 congestion_control=zenoh.CongestionControl.BLOCK)

    def _admit(self, sample: zenoh.Sample) -> tuple[Received | None, str]:
        """Key, rate limit, decoding, registry of one sample: (the valid message, key) or (None, key)."""
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
                self._intake.reject(kind, "unexpected_delete", key, "DELETE sample")
                return None, key
            parsed, kind = self.validator.parse_key(key)
            uav = parsed.uav
            nbytes = len(sample.payload)
            limited = self.limiter.check(uav, nbytes) if self.limiter is not None else None
            if limited is not None:  # before decoding: a flood costs a lookup per message
                self._intake.reject(kind, limited, key, f"{nbytes} bytes", uav)
                return None, key
            received = self.validator.validate(key, sample.payload, parsed=parsed, sparse=True)
            message = received.message
            if not self.uavs.message(uav, received.kind, received.nbytes,
                                     message if isinstance(message, StateMessage) else None,
                                     session=self._session_of(sample)):
                self._intake.reject(received.kind, "too_many_uavs", key, "UAV registry full")
                return None, key
            return received, key
        except Rejected as exc:
            self._intake.reject(exc.kind, exc.reason, key, exc, uav)
        except Exception:  # a bug must not take the fusion thread down: count it, log it
            self.metrics.reject("unknown", "internal_error")
            log.exception("internal error handling a sample on %.120s", key)
        return None, key

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self._intake.on_alive(sample, self._uav_alive)

    def _uav_alive(self, uav: str, online: bool) -> None:
        """A UAV's token came or went (accepted): logged; an offline UAV's track members are marked lost."""
        log.info("UAV %s %s", uav, "online" if online else "offline")
        if not online and self.tracker.uav_lost(uav):
            self._wake()

    def _on_query(self, query: zenoh.Query) -> None:
        selector = query.key_expr
        for tile in self.joint.tiles():
            tile_key = self.keys.joint_tile(tile.cls, tile.z, tile.x, tile.y)
            if selector.intersects(tile_key):
                query.reply(tile_key, tile.payload)
        if not self.shard.sharded and selector.intersects(self._tracks_key):
            query.reply(self._tracks_key, self._tracks_payload)
        for region, (_, payload, _) in list(self._region_payloads.items()):
            region_key = self.keys.region_tracks(*region)
            if selector.intersects(region_key):
                query.reply(region_key, payload)
        self.metrics.query()

    # ---- publisher thread ----------------------------------------------------------------------
    def _publish_tiles(self) -> float | None:
        assert self._publishers is not None
        updates, next_due = self.joint.step()
        for update in updates:
            cls, z, x, y = update.key
            key = self.keys.joint_tile(cls, z, x, y)
            self._publishers.put(key, update.payload)
            dropped = update.tile is None
            if dropped:
                self._publishers.drop(key)
            self.metrics.published(time.monotonic() - update.pending_since, dropped=dropped)
        if self.store is not None and updates:
            self.store.save_joints([(update.key, update.tile) for update in updates])
        return next_due

    def _publish_tracks(self) -> None:
        # bounded: at most MAX_TRACKS tracks (the schema's limit) and max_tracks_bytes, tracked ones
        # first, so a flood of tracks shortens the message instead of stopping it
        message, payload = encode_joint_tracks_within(self.tracker.joint_message, self.max_tracks_bytes)
        left_out = len(self.tracker) - len(message.tracks)
        if left_out > 0:
            self.metrics.tracks_left_out(left_out)
        self._tracks_payload = payload
        assert self._tracks_publisher is not None
        self._tracks_publisher.put(payload)
        self.metrics.tracks_sent()

    def _publish_track_regions(self) -> None:
        """The global tracks again per region tile (``region/tracks/{z}/{x}/{y}``, shared.keys.track_region),
        so a UAV receives those near it only: a region whose tracks changed, or whose last message is
        1 s old; one empty message for a region that has none any more. Run REGION_TRACKS_HZ times a
        second."""
        assert self._publishers is not None
        message = self.tracker.joint_message()
        grid = self.joint.grid
        by_region: dict[tuple[int, int, int], list[JointTrackItem]] = {}
        if message.tracks:
            lat = np.array([item.lat for item in message.tracks])
            lon = np.array([item.lon for item in message.tracks])
            xs, ys = grid.tile_of(lat, lon)
            for item, x, y in zip(message.tracks, xs.tolist(), ys.tolist(), strict=True):
                region = track_region(grid.z, x, y)
                if self.shard.owns(*region):  # a held track drifted across a border: not ours to publish
                    by_region.setdefault(region, []).append(item)
        now = time.monotonic()
        for region in [r for r in self._region_payloads if r not in by_region]:
            by_region[region] = []
        for region, found in by_region.items():
            items = tuple(found)
            last = self._region_payloads.get(region)
            if last is not None and last[0] == items and now - last[2] < _REGION_REFRESH_S:
                continue  # the same tracks, published less than a second ago
            payload = encode_joint_tracks(JointTracksMessage(t=message.t, tracks=items))
            while len(payload) > self.max_tracks_bytes and len(items) > 1:
                items = items[: len(items) // 2]
                payload = encode_joint_tracks(JointTracksMessage(t=message.t, tracks=items))
            key = self.keys.region_tracks(*region)
            self._publishers.put(key, payload)
            if items:
                self._region_payloads[region] = (tuple(found), payload, now)
            else:
                self._region_payloads.pop(region, None)
                self._publishers.drop(key)

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
        """Queue the tracks' and UAVs' changes since the last call (the store's writer thread calls it)."""
        assert self.store is not None
        records, history = self.tracker.drain_changes()
        self.store.save_tracks(records, history, self.tracker.next_gid)
        uavs, forgotten = self.uavs.drain_changes()
        self.store.save_uavs(uavs, forgotten)

    def inbox_health(self) -> dict[str, Any]:
        """``{"samples": waiting, "oldest_s": how long the oldest has waited (0.0: none)}`` (no lock: reads)."""
        inbox = self._inbox
        try:
            oldest = time.monotonic() - inbox[0][0] if inbox else 0.0
        except IndexError:  # the fusion thread took it meanwhile
            oldest = 0.0
        return {"samples": len(inbox), "oldest_s": round(max(oldest, 0.0), 3)}

    def _drain(self) -> list[zenoh.Sample]:
        """Up to _BATCH samples from the inbox, oldest first; those that waited longer than
        ``inbox_max_age_s`` are dropped unread and counted as "overloaded"."""
        inbox = self._inbox
        batch: list[zenoh.Sample] = []
        stale = 0
        cutoff = time.monotonic() - self.inbox_max_age_s
        while inbox and len(batch) < _BATCH:
            arrived, sample = inbox.popleft()
            if arrived < cutoff:
                stale += 1
                continue
            batch.append(sample)
        if stale:
            self.metrics.reject("unknown", "overloaded", stale)
            self._intake.warnings.warning(
                "overloaded_age", "fusion thread behind: dropped %d samples that waited more than %.1f s", stale,
                self.inbox_max_age_s)
        return batch

    def _run(self) -> None:
        tracks_version = -1
        last_tracks = -float("inf")
        next_housekeeping = 0.0
        next_forget = 0.0
        next_regions = 0.0
        while not self._stop.is_set():
            batch = self._drain()
            if batch:
                self._step("ingest", functools.partial(self._ingest, batch))
            next_due = self._step("joint_tiles", self._publish_tiles)
            now = time.monotonic()
            if now >= next_housekeeping:
                self._step("expire", self.tracker.expire)
                next_housekeeping = now + _TICK_S
            if now >= next_forget:
                self._step("forget_uavs", lambda: self.uavs.forget_offline(self.uav_keep_s))
                next_forget = now + 5.0
            if (not self.shard.sharded and self.tracker.version != tracks_version
                    and now - last_tracks >= self.tracks_min_interval_s):
                tracks_version = self.tracker.version
                last_tracks = now
                self._step("joint_tracks", self._publish_tracks)
            if now >= next_regions:
                self._step("track_regions", self._publish_track_regions)
                next_regions = now + 1.0 / REGION_TRACKS_HZ
            self._wakeup.clear()
            if self._inbox:
                continue
            timeout = _TICK_S if next_due is None else min(_TICK_S, next_due - time.monotonic())
            if timeout > 0:
                self._wakeup.wait(timeout)

"""The gateway's Zenoh side: shard liveliness, the shards' region tracks, the UAVs' states, and ``joint/tracks``.

A gateway (``uavmm gateway``) fuses nothing: it listens to what the shards and agents already publish.
It watches the shards' liveliness tokens (``{prefix}/fusion/shards/{N}/{K}``, history on: a shard that
dies loses its token as soon as its session ends), merges the shards' ``region/tracks/**`` into the
global tracks (asking for them once at start, for a late join) and publishes those on
``{prefix}/joint/tracks`` (at most ``tracks_max_hz``, and once a second while unchanged) and answers
queries of that key: the DESIGN.md contract key, which shards leave to the gateway. UAVs come from
their ``uav/*/state`` messages and ``uav/*/alive`` tokens. Callbacks never raise: a malformed message
is dropped, counted and logged (rate-limited); so is a region message whose ``t`` is more than the clock skew
ahead of the gateway's clock (``t_in_future``: the newest message wins a global id, so such a message, forged
or from a shard whose clock runs ahead, kept the honest shard's copy of every id it listed out of the view).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from fusion_server.merged_tracks import MergedTracks
from fusion_server.metrics import FusionMetrics
from fusion_server.uav_intake import UavIntake
from fusion_server.uav_registry import UavRegistry
from fusion_server.validation import MessageValidator, Rejected
from shared.keys import KeySpace
from shared.messages import (
    MessageError,
    StateMessage,
    decode_joint_tracks,
    encode_joint_tracks,
    encode_joint_tracks_within,
)
from transport.guard import guarded
from transport.publishers import PublisherCache
from transport.session import close_session

__all__ = ["GatewayNode", "ShardWatch"]

log = logging.getLogger(__name__)

#: Period of the publisher thread, seconds.
_TICK_S = 0.05
#: joint/tracks is published again after this long even when unchanged, seconds.
_TRACKS_REFRESH_S = 1.0
#: Largest joint/tracks message, bytes (a fusion server's bound: fewer tracks beyond it, counted as left out).
MAX_TRACKS_BYTES = 1024 * 1024
#: Tokens of other deployments' shards listed in ShardWatch.foreign (and /healthz).
_MAX_FOREIGN = 64


class ShardWatch:
    """Which of the ``count`` shards hold their liveliness token. Thread-safe.

    A shard never seen is down (since None). Tokens of another shard count or, when ``region_zoom`` is
    given, another region zoom (a shard started with a different N or --region-zoom) are listed in
    ``foreign`` ("K/N", or "K/N zoom Z" for another zoom: True while the token is up) and logged, not counted:
    they say the deployment is misconfigured. ``foreign`` keeps the latest _MAX_FOREIGN of them (gone ones
    forgotten first), so tokens the network declares cost bounded memory and /healthz stays small.
    """

    def __init__(self, count: int, region_zoom: int | None = None, wall: Callable[[], float] = time.time) -> None:
        self.count = count
        self.region_zoom = region_zoom
        self._wall = wall
        self._lock = threading.Lock()
        self._up: dict[int, bool] = {}
        self._since: dict[int, float] = {}
        self._changes: dict[int, int] = {}
        self.foreign: dict[str, bool] = {}
        #: foreign tokens forgotten beyond _MAX_FOREIGN
        self.foreign_forgotten = 0

    def is_foreign(self, count: int, zoom: int | None = None) -> bool:
        """Whether a token of shard count ``count`` and region zoom ``zoom`` (None: not known) is another
        deployment's."""
        return count != self.count or (zoom is not None and self.region_zoom is not None and zoom != self.region_zoom)

    def token(self, index: int, count: int, alive: bool, zoom: int | None = None) -> None:
        """A shard token (of region zoom ``zoom``, None: not known) appeared (alive) or disappeared."""
        with self._lock:
            if self.is_foreign(count, zoom):
                label = f"{index}/{count}" if count != self.count else f"{index}/{count} zoom {zoom}"
                foreign = self.foreign
                foreign.pop(label, None)
                foreign[label] = alive  # the newest last
                if len(foreign) > _MAX_FOREIGN:
                    gone = next((name for name, up in foreign.items() if not up), None)
                    del foreign[gone if gone is not None else next(iter(foreign))]
                    self.foreign_forgotten += 1
                return
            if self._up.get(index) == alive:
                return
            self._up[index] = alive
            self._since[index] = self._wall()
            self._changes[index] = self._changes.get(index, 0) + 1

    def down(self) -> set[int]:
        """Shards (0..count-1) without a token."""
        with self._lock:
            return {k for k in range(self.count) if not self._up.get(k, False)}

    def status(self) -> dict[str, dict[str, object]]:
        """``{"K": {"status": "up"|"down", "since": epoch s of the last change or None, "changes": n}}``."""
        with self._lock:
            return {str(k): {"status": "up" if self._up.get(k, False) else "down", "since": self._since.get(k),
                             "changes": self._changes.get(k, 0)} for k in range(self.count)}


class GatewayNode:
    """One Zenoh session of the gateway, feeding ``tracks``, ``uavs`` and ``shards``.

    conf: the Zenoh config; keys: the key space; validator: checks the UAVs' state messages (its
    ``max_clock_skew_s`` also bounds how far a shard's region message may be ahead of this clock).
    tracks_max_hz: most ``joint/tracks`` messages a second; max_tracks_bytes: their largest size (fewer
    tracks beyond it, tracked ones first, counted as ``tracks_left_out``). session: the open session (None before
    start and after close), shared with the gateway's RemoteJoint.
    """

    def __init__(self, conf: zenoh.Config, keys: KeySpace, validator: MessageValidator, tracks: MergedTracks,
                 uavs: UavRegistry, shards: ShardWatch, metrics: FusionMetrics, *,
                 tracks_max_hz: float = 5.0, uav_keep_s: float = 3600.0,
                 max_tracks_bytes: int = MAX_TRACKS_BYTES) -> None:
        self.conf = conf
        self.keys = keys
        self.validator = validator
        self.tracks = tracks
        self.uavs = uavs
        self.shards = shards
        self.metrics = metrics
        self.tracks_min_interval_s = 1.0 / tracks_max_hz
        self.uav_keep_s = uav_keep_s
        self.max_tracks_bytes = max_tracks_bytes
        self.session: zenoh.Session | None = None
        self._declared: list = []
        self._publishers: PublisherCache | None = None
        self._tracks_key = keys.joint_tracks()
        self._tracks_payload = encode_joint_tracks(tracks.joint_message())
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._intake = UavIntake(keys, uavs, metrics, log, prefix="gateway: ")
        self._log = self._intake.warnings

    # ---- lifecycle ----------------------------------------------------------------------------------
    def start(self, late_join_timeout_s: float = 2.0) -> None:
        """Open the session, declare subscribers and the joint/tracks queryable, ask the shards for their
        region tracks (late join) and start the publisher thread. Raises zenoh.ZError when the session
        cannot be opened."""
        self.session = session = zenoh.open(self.conf)
        self._publishers = PublisherCache(session)
        self._publishers.get(self._tracks_key)
        liveliness = session.liveliness()
        self._declared = [
            liveliness.declare_subscriber(self.keys.shard_alive("*", "*"), self._on_shard, history=True),
            liveliness.declare_subscriber(self.keys.uav_alive("*"), self._intake.on_alive, history=True),
            session.declare_subscriber(self.keys.uav_state("*"), self._on_state),
            session.declare_subscriber(self.keys.region_tracks_all(), self._on_region_tracks),
            session.declare_queryable(self._tracks_key, guarded(self._on_query, log, "a joint/tracks query")),
        ]
        replies = session.get(self.keys.region_tracks_all(), target=zenoh.QueryTarget.ALL,
                              consolidation=zenoh.ConsolidationMode.NONE, timeout=late_join_timeout_s)
        for reply in replies:
            if reply.ok is not None:
                self._on_region_tracks(reply.ok)
        self._thread = threading.Thread(target=self._run, name="uavmm-gateway", daemon=True)
        self._thread.start()
        log.info("gateway node %s up: %d shards", session.zid(), self.shards.count)

    def close(self) -> None:
        """Stop the publisher thread and close the session (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        if self.session is not None:
            close_session(self.session, self._declared, self._publishers)
            self.session = None

    # ---- callbacks (Zenoh threads; never raise) -----------------------------------------------------
    def _on_shard(self, sample: zenoh.Sample) -> None:
        key = "?"
        try:
            key = str(sample.key_expr)
            try:
                index, count, zoom = self.keys.parse_shard_token(key)
            except ValueError as exc:
                self._intake.reject("shard_alive", "bad_key", key, exc)
                return
            alive = sample.kind == zenoh.SampleKind.PUT
            self.shards.token(index, count, alive, zoom)
            if self.shards.is_foreign(count, zoom):
                self._log.warning("foreign_shard", "gateway of %d shards, regions of zoom %s: shard %d/%d of region "
                                  "zoom %d %s (started with another --shard N or --region-zoom?)", self.shards.count,
                                  self.shards.region_zoom, index, count, zoom, "up" if alive else "down")
                return
            log.info("shard %d/%d %s", index, count, "up" if alive else "down")
        except Exception:
            self.metrics.reject("shard_alive", "internal_error")
            log.exception("internal error handling shard liveliness on %.120s", key)

    def _on_state(self, sample: zenoh.Sample) -> None:
        key = "?"
        uav: str | None = None
        try:
            key = str(sample.key_expr)
            if sample.kind != zenoh.SampleKind.PUT:
                self._intake.reject("state", "unexpected_delete", key, "DELETE sample")
                return
            parsed, _ = self.validator.parse_key(key)
            uav = parsed.uav
            received = self.validator.validate(key, sample.payload, parsed=parsed)
            message = received.message
            assert isinstance(message, StateMessage)
            if not self.uavs.message(uav, "state", received.nbytes, message):
                self._intake.reject("state", "too_many_uavs", key, "UAV registry full")
                return
            self.metrics.message("state", received.nbytes)
        except Rejected as exc:
            self._intake.reject(exc.kind, exc.reason, key, exc, uav)
        except Exception:
            self.metrics.reject("state", "internal_error")
            log.exception("internal error handling a state on %.120s", key)

    def _on_region_tracks(self, sample: zenoh.Sample) -> None:
        key = "?"
        try:
            key = str(sample.key_expr)
            try:
                parsed = self.keys.parse(key)
            except ValueError as exc:
                self._intake.reject("region_tracks", "bad_key", key, exc)
                return
            if parsed.kind != "region_tracks" or sample.kind != zenoh.SampleKind.PUT:
                self._intake.reject("region_tracks", "unexpected_key", key, "not a region tracks message")
                return
            try:
                message = decode_joint_tracks(sample.payload.to_bytes())
            except MessageError as exc:
                self._intake.reject("region_tracks", exc.reason, key, exc)
                return
            # the newest message wins each id it lists: one stamped in the future would hold the honest shard's
            # copies out of the view for as long as it is fresh (3 s; for good when sent again). A shard whose
            # clock is ahead by at most the skew keeps working (its copies win handovers, as before)
            ahead_s = message.t - time.time()
            if ahead_s > self.validator.max_clock_skew_s:
                self._intake.reject("region_tracks", "t_in_future", key,
                                    f"t is {ahead_s:.4g} s ahead of the gateway's clock, more than "
                                    f"--max-clock-skew-s {self.validator.max_clock_skew_s:g} (forged, or the "
                                    "shard's clock runs ahead: set it)")
                return
            assert parsed.z is not None and parsed.x is not None and parsed.y is not None
            self.tracks.put((parsed.z, parsed.x, parsed.y), message)
            self.metrics.message("region_tracks", len(sample.payload))
        except Exception:
            self.metrics.reject("region_tracks", "internal_error")
            log.exception("internal error handling region tracks on %.120s", key)

    def _on_query(self, query: zenoh.Query) -> None:
        if query.key_expr.intersects(self._tracks_key):
            query.reply(self._tracks_key, self._tracks_payload)
        self.metrics.query()

    # ---- publisher thread ---------------------------------------------------------------------------
    def _publish_tracks(self) -> None:
        assert self._publishers is not None
        # bounded as a fusion server bounds it (MAX_TRACKS tracks, MAX_TRACKS_BYTES, tracked ones first): the
        # whole map's tracks of many shards made messages agents refuse
        message, payload = encode_joint_tracks_within(self.tracks.joint_message, self.max_tracks_bytes)
        left_out = len(self.tracks) - len(message.tracks)
        if left_out > 0:
            self.metrics.tracks_left_out(left_out)
        self._tracks_payload = payload
        self._publishers.put(self._tracks_key, payload)
        self.metrics.tracks_sent()

    def _run(self) -> None:
        version = -1
        last = -float("inf")
        next_forget = 0.0
        while not self._stop.wait(_TICK_S):
            now = time.monotonic()
            try:
                self.tracks.refresh()
                changed = self.tracks.version != version
                if (changed and now - last >= self.tracks_min_interval_s) or now - last >= _TRACKS_REFRESH_S:
                    version = self.tracks.version
                    last = now
                    self._publish_tracks()
                if now >= next_forget:
                    self.uavs.forget_offline(self.uav_keep_s)
                    next_forget = now + 5.0
            except Exception as exc:
                if self._stop.is_set():
                    return
                self.metrics.reject("publisher", "joint_tracks_failed")
                self._log.warning("publish", "gateway: publishing joint tracks failed: %s", exc)

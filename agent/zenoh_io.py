"""The agent's Zenoh side: liveliness, publishers on a background thread, joint tiles/tracks in, late-join query.

The detection loop never waits for the network: it hands encoded messages to :meth:`AgentLink.submit`
(latest message per key wins while the network is slow) and a publisher thread puts them with
``CongestionControl.BLOCK``. Subscriber callbacks validate every joint message, count and log what they
drop, and never raise; the loop takes the decoded joint tiles with :meth:`AgentLink.drain_joint_tiles`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import msgpack
import numpy as np
import zenoh
from numpy.typing import NDArray

from agent.joint_clock import MAX_CLOCK_SKEW_S, JointClock
from agent.joint_window import JointWindowSubscriptions
from agent.partner_clocks import PartnerClocks
from agent.shard_routing import ShardRouting
from shared.keys import JOINT_UAV, KeySpace, track_region
from shared.messages import (
    DEFAULT_MAX_STATE_BYTES,
    VERSION,
    JointTracksMessage,
    MessageError,
    TracksMessage,
    decode_joint_tracks,
    decode_state,
)
from shared.tilecodec import DEFAULT_MAX_TILE_BYTES, decode_tile
from shared.tiles import TileGrid
from transport.guard import RateLimitedLog, guarded
from transport.publishers import PublisherCache
from transport.session import config_value, open_session, remote_ids

__all__ = ["AgentLink", "FootprintUpdate", "JointTileUpdate", "encode_tracks_with_gid"]

log = logging.getLogger(__name__)

_M = TypeVar("_M")  # a decoded message

#: Track regions held (agent.joint_window; a window touches 1-4), and how long one counts, seconds.
_MAX_REGIONS = 64
MAX_REGION_AGE_S = 3.0
#: Largest joint tracks payload accepted, bytes.
MAX_JOINT_TRACKS_BYTES = 8 * 1024 * 1024
#: How often the publisher thread looks for new routers/peers (to query the joint map again), seconds.
_CONNECTIVITY_CHECK_S = 0.5
#: Warn when the session has reached no router or peer for this long (a dead or mistyped --connect).
ALONE_WARN_S = 5.0
#: A joint tile not newer (by seq and t) than the held one is stale only within this long of the held
#: one's arrival (a late query reply); later it replaces it, so one forged tile with a huge seq
#: cannot block the server's real ones.
_REORDER_WINDOW_S = 1.0


def encode_tracks_with_gid(msg: TracksMessage, gids: dict[int, int]) -> bytes:
    """msgpack bytes of a local tracks message whose items may carry an optional ``gid``.

    ``gid`` (the global id the agent adopted for that local track, see docs/agent.md) is a compatible
    extension of the DESIGN.md tracks message: decoders ignore unknown keys. msg is validated by its
    own constructor; gids maps local track id -> global id (ints in 0..2**63-1), absent ids get no gid.
    """
    tracks = []
    for item in msg.tracks:
        record = item.to_dict()
        gid = gids.get(item.id)
        if gid is not None:
            record["gid"] = int(gid)
        tracks.append(record)
    return msgpack.packb({"v": VERSION, "uav": msg.uav, "t": float(msg.t), "tracks": tracks}, use_bin_type=True)


@dataclass(frozen=True, slots=True, eq=False)
class JointTileUpdate:
    """A joint tile received from the fusion server.

    cls, x, y: the tile (of the agent's grid zoom). values: (n, n) float32 in [0, 1].
    age_s: wall seconds since it was received (at the time it was drained).
    """

    cls: str
    x: int
    y: int
    values: NDArray[np.float32]
    age_s: float


@dataclass(frozen=True, slots=True, eq=False)
class FootprintUpdate:
    """Another UAV's camera footprint, from its latest state message.

    footprint: ((lat, lon), ...) ground polygon, >= 3 vertices. age_s: wall seconds since it was
    received (at the time it was drained).
    """

    uav: str
    footprint: tuple[tuple[float, float], ...]
    age_s: float


class AgentLink:
    """One agent's Zenoh session.

    Parameters
    ----------
    conf : zenoh.Config
        From `agent.zenoh_config.agent_zenoh_config`.
    keys : KeySpace
    uav : str
        This UAV's id (a valid key chunk).
    grid : TileGrid
        Joint tiles of another zoom or cell count are rejected ("wrong_grid").
    max_publishers : int
        Declared tile publishers kept (least recently used ones are undeclared beyond it).
    max_tile_bytes : int
        Largest joint tile payload accepted.
    max_joint_tiles : int
        Joint tiles held (256 KiB each); beyond it the least recently updated one is forgotten
        (counted as "joint_tiles_evicted").

    Use: ``open()``, ``query_joint()``, then per publish cycle ``submit(...)``; per frame
    ``drain_joint_tiles()`` and ``joint_tracks()``; ``close()`` at the end. ``stats()`` gives the counters.
    """

    def __init__(self, conf: zenoh.Config, keys: KeySpace, uav: str, grid: TileGrid, *,
                 max_publishers: int = 1024, max_tile_bytes: int = DEFAULT_MAX_TILE_BYTES,
                 max_joint_tiles: int = 1024) -> None:
        self.conf = conf
        self.keys = keys
        self.uav = uav
        self.grid = grid
        self.max_publishers = max_publishers
        self.max_tile_bytes = max_tile_bytes
        self.max_joint_tiles = max_joint_tiles
        self.session: zenoh.Session | None = None
        self._session_tag = b""
        self._declared: list[Any] = []
        self._window: JointWindowSubscriptions | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._publishers: PublisherCache | None = None
        self._lock = threading.Lock()
        self._outbox: dict[str, tuple[str, bytes]] = {}
        self._wake = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # joint tiles: (cls, x, y) -> (values, monotonic receive time, seq, t), least recently updated first
        self._joint_tiles: OrderedDict[tuple[str, int, int], tuple[NDArray[np.float32], float, int, float]] = \
            OrderedDict()
        self._joint_pending: set[tuple[str, int, int]] = set()
        self._joint_tracks: tuple[JointTracksMessage, float] | None = None
        self._region_tracks: OrderedDict[tuple[Any, Any, Any], tuple[JointTracksMessage, float]] = OrderedDict()
        # other UAVs' latest footprints: uav -> (footprint, monotonic receive time), and the new ones
        self._footprints: dict[str, tuple[tuple[tuple[float, float], ...], float]] = {}
        self._footprints_pending: set[str] = set()
        self.partner_clocks = PartnerClocks()  # the other UAVs' source clocks (AgentSettings.replay_sync_s)
        self.joint_clock = JointClock(MAX_CLOCK_SKEW_S)  # how far the joint messages' clock leads this one
        self._counts: Counter[str] = Counter()
        self._bytes: Counter[str] = Counter()
        self._rejects: Counter[str] = Counter()
        self._warn = RateLimitedLog(log).warning
        self._on_reply_guarded = self._guarded(self._on_reply, "a query reply")  # built once, used per reply
        self._routing = ShardRouting(keys, uav, grid.z, lambda key, exc: self._reject("bad_key", key, exc), self._warn)
        self._known_remotes: set[str] = set()
        self._alone_since: float | None = None  # monotonic time since when no router/peer is connected
        self._alone_warned = False
        self._ever_connected = False

    # ---- lifecycle -----------------------------------------------------------------------------
    def open(self, stop: threading.Event | None = None, *, timeout_s: float | None = None) -> bool:
        """Open the session (retrying a client until its router answers), declare the liveliness
        token and the subscribers, start the publisher thread. Returns False when ``stop`` was set or
        ``timeout_s`` passed before the session opened."""
        session = open_session(self.conf, stop, timeout_s=timeout_s)
        if session is None:
            return False
        self.session = session
        # every put carries this session's id, so the server can tell two sessions using one UAV id
        self._session_tag = str(session.zid()).encode("ascii")
        self._token = session.liveliness().declare_token(self.keys.uav_alive(self.uav))
        # keep references: declared entities are undeclared when garbage-collected
        self._publishers = PublisherCache(session, self.max_publishers)
        on_sample = self._guarded(self._on_sample, "a sample")
        # every joint tile and the global tracks until set_joint_window() narrows them to the window
        self._window = JointWindowSubscriptions(session, self.keys, self.grid.z, on_sample)
        # (it also brings the other UAVs' states: their footprints say where the joint mean holds
        # their evidence, JointLayer.others_cover)
        self._declared = [self._routing.declare(session, lambda callback: self._guarded(callback, "a shard token"))]
        self._known_remotes = self._remotes()
        self._alone_since = None if self._known_remotes else time.monotonic()
        self._ever_connected = bool(self._known_remotes)
        self._thread = threading.Thread(target=self._run, name=f"uavmm-agent-{self.uav}-publisher", daemon=True)
        self._thread.start()
        log.info("agent %s: zenoh session %s open (%d router/peer connections)", self.uav, session.zid(),
                 len(self._known_remotes))
        return True

    def close(self) -> None:
        """Send what is queued, stop the publisher thread and close the session (idempotent); the
        liveliness token goes with the session."""
        self._stop.set()
        with self._lock:
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        if self.session is not None and not self._ever_connected and not self._alone_warned:
            try:  # a run shorter than ALONE_WARN_S that never reached anyone: say so once, at the end
                reached = bool(self._remotes())
            except zenoh.ZError:
                reached = False
            if not reached:
                log.warning("agent %s: no zenoh router or peer was reached during the run (connect: %s): what it "
                            "published reached nobody; is the fusion server up and --connect right?", self.uav,
                            self._connect_endpoints())
        if self.session is not None:
            if self._publishers is not None:
                self._publishers.clear()
            self._declared = []
            if self._window is not None:
                self._window.clear()
                self._window = None
            self._token = None
            try:
                self.session.close()
            except zenoh.ZError as exc:
                log.warning("closing the zenoh session: %s", exc)
            self.session = None

    def __enter__(self) -> AgentLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- late join -----------------------------------------------------------------------------
    def query_joint(self, timeout_s: float = 2.0) -> int:
        """Ask the fusion server's queryable for the current joint tiles and tracks and wait for them.

        Replies go through the same validation as published samples. Returns the number of replies
        (0 when no fusion server answers; the call returns as soon as all queryables replied).
        """
        if self.session is None:
            raise RuntimeError("AgentLink.query_joint before open()")
        self._count("queries")
        replies = self.session.get(self.keys.joint_all(), timeout=timeout_s)
        n = 0
        for reply in replies:
            n += 1
            self._on_reply_guarded(reply)
        log.info("agent %s: joint query answered with %d replies", self.uav, n)
        return n

    def _query_async(self) -> None:
        """Ask for the current joint map again (a new connection): the window's tiles and track
        regions when a window is set (agent.joint_window), else everything."""
        assert self.session is not None
        window = self._window
        if window is not None and window.tiles is not None:
            self._query_selectors(window.selectors())
            return
        self._query_selectors([self.keys.joint_all()])

    def _query_selectors(self, selectors: list[str]) -> None:
        assert self.session is not None
        for selector in selectors:
            self._count("queries")
            self.session.get(selector, self._on_reply_guarded, timeout=5.0)

    def _remotes(self) -> set[str]:
        return set() if self.session is None else remote_ids(self.session)

    # ---- outgoing ------------------------------------------------------------------------------
    def submit(self, messages: list[tuple[str, str, bytes]]) -> None:
        """Queue messages ``(kind, key, payload)`` for the publisher thread; never blocks on the network.

        A message replaces one still queued under the same key (counted as "coalesced"): when the
        link is slower than the publish rate the newest state of each tile is what gets through.
        """
        with self._lock:
            for kind, key, payload in messages:
                if key in self._outbox:
                    self._counts["coalesced"] += 1
                self._outbox[key] = (kind, payload)
            self._wake.notify_all()

    def set_joint_window(self, tiles: set[tuple[int, int]] | None,
                         track_tiles: set[tuple[int, int]] | None = None) -> None:
        """Receive the joint tiles of these (x, y) only and the joint tracks of the regions of
        ``track_tiles`` (default: of ``tiles``); None: every joint tile and track. See agent.joint_window."""
        if self._window is None:
            raise RuntimeError("AgentLink.set_joint_window before open()")
        regions = None if tiles is None else {track_region(self.grid.z, x, y)
                                               for x, y in (tiles if track_tiles is None else track_tiles)}
        if tiles != self._window.tiles or regions != self._window.regions:
            before = set(self._window.selectors()) if self._window.tiles is not None else None
            self._window.set(tiles, track_tiles)
            self._count("joint_window_changes")
            if tiles is not None and before is not None:
                # tiles and regions new to the window: their current joint data now, not at the next
                # publication (the first window: the start-up query brought everything already)
                self._query_selectors([s for s in self._window.selectors() if s not in before])

    def tile_key(self, cls: str, x: int, y: int) -> str:
        """Key of one of this UAV's tiles on the agent's grid: DESIGN.md's, or the shard-routed one while
        fusion shards announce themselves."""
        return self._routing.tile_key(cls, x, y)

    def state_key(self) -> str:
        """Key of this UAV's state."""
        return self.keys.uav_state(self.uav)

    def tracks_key(self) -> str:
        """Key of this UAV's tracks."""
        return self.keys.uav_tracks(self.uav)

    def _run(self) -> None:
        next_check = time.monotonic() + _CONNECTIVITY_CHECK_S
        while True:
            with self._lock:
                if not self._outbox and not self._stop.is_set():
                    self._wake.wait(_CONNECTIVITY_CHECK_S)
                batch, self._outbox = self._outbox, {}
            self._send(batch)
            if self._stop.is_set():
                return  # what was queued before close() has been sent
            now = time.monotonic()
            if now >= next_check:
                next_check = now + _CONNECTIVITY_CHECK_S
                self._check_connectivity()

    def _send(self, batch: dict[str, tuple[str, bytes]]) -> None:
        for key, (kind, payload) in batch.items():
            try:
                assert self._publishers is not None
                self._publishers.put(key, payload, attachment=self._session_tag)
                self._count(f"sent_{kind}", len(payload))
            except zenoh.ZError as exc:
                self._count("publish_errors")
                self._warn("publish", "agent %s: publishing on %s failed: %s", self.uav, key, exc)

    def _check_connectivity(self) -> None:
        """Query the joint map again when a router/peer appears (e.g. the fusion server came back)."""
        try:
            remotes = self._remotes()
            new = remotes - self._known_remotes
            if new:
                log.info("agent %s: new zenoh connection(s) %s: querying the joint map", self.uav, sorted(new))
                self._count("reconnects")
                self._query_async()
            self._known_remotes = remotes
            self._check_alone(bool(remotes))
        except zenoh.ZError as exc:
            self._warn("connectivity", "agent %s: connectivity check failed: %s", self.uav, exc)

    def _check_alone(self, connected: bool) -> None:
        """Warn once per outage when nothing this agent publishes has reached anyone for ALONE_WARN_S."""
        now = time.monotonic()
        if connected:
            self._ever_connected = True
            if self._alone_warned:
                log.warning("agent %s: zenoh connected again: publishing reaches the fusion server", self.uav)
            self._alone_since, self._alone_warned = None, False
            return
        if self._alone_since is None:
            self._alone_since = now
        alone_s = now - self._alone_since
        if alone_s >= ALONE_WARN_S:
            self._count("alone_checks")
            if not self._alone_warned:
                self._alone_warned = True
                self._warn("alone", "agent %s: no zenoh router or peer reached for %.0f s (connect: %s): what it "
                           "publishes reaches nobody; is the fusion server up and --connect right?", self.uav,
                           alone_s, self._connect_endpoints())

    def _connect_endpoints(self) -> str:
        endpoints = config_value(self.conf, "connect/endpoints")
        return ", ".join(endpoints) if isinstance(endpoints, list) and endpoints else "none (scouting only)"

    # ---- incoming (Zenoh threads: never raise) -------------------------------------------------
    def _count(self, name: str, nbytes: int | None = None) -> None:
        with self._lock:
            self._counts[name] += 1
            if nbytes is not None:
                self._bytes[name] += nbytes

    def _reject(self, reason: str, key: str, detail: object) -> None:
        with self._lock:
            self._rejects[reason] += 1
        self._warn(reason, "agent %s: dropped message on %.120s: %s: %.200s", self.uav, key, reason, detail)

    def _guarded(self, callback: Callable[[Any], None], what: str) -> Callable[[Any], None]:
        """callback for a Zenoh thread: an exception is logged and counted as "internal_error"."""
        return guarded(callback, log, f"{what} (agent {self.uav})", self._internal_error)

    def _internal_error(self) -> None:
        with self._lock:
            self._rejects["internal_error"] += 1

    def _on_reply(self, reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is None:
            self._reject("query_error", self.keys.joint_all(), reply.err)
            return
        self._on_sample(sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if sample.kind != zenoh.SampleKind.PUT:
            self._reject("unexpected_delete", key, "DELETE sample")
            return
        try:
            parsed = self.keys.parse(key)
        except ValueError as exc:
            self._reject("bad_key", key, exc)
            return
        if parsed.kind == "joint_tile":
            self._on_joint_tile(key, parsed, sample.payload)
        elif parsed.kind == "joint_tracks":
            self._on_joint_tracks(key, sample.payload)
        elif parsed.kind == "region_tracks":
            self._on_joint_tracks(key, sample.payload, (parsed.z, parsed.x, parsed.y))
        elif parsed.kind == "region_state":  # a state the fusion server forwarded to a region
            if parsed.uav != self.uav:
                self._on_state(key, parsed.uav, sample.payload)
        elif parsed.kind == "uav_state":
            if parsed.uav != self.uav:
                self._on_state(key, parsed.uav, sample.payload)
        else:
            self._reject("unexpected_key", key, "not a joint key")

    def _decode(self, key: str, payload: zenoh.ZBytes, decode: Callable[..., _M], max_bytes: int) -> _M | None:
        """``decode(payload, max_bytes=...)``, or None after rejecting it: "too_large" before reading
        it, else the decoder's reason."""
        if len(payload) > max_bytes:
            self._reject("too_large", key, f"{len(payload)} bytes")
            return None
        try:
            return decode(payload.to_bytes(), max_bytes=max_bytes)
        except MessageError as exc:
            self._reject(exc.reason, key, exc)
            return None

    def _in_future(self, key: str, t: float, kind: str) -> bool:
        """Whether a joint message's t is ahead of this clock (and the lead agent.joint_clock adopted for `kind`'s
        evidence) by more than MAX_CLOCK_SKEW_S (rejected)."""
        if not self.joint_clock.accepts(t, kind):
            self._reject("t_in_future", key, f"t {t!r:.30} is ahead of this clock")
            return True
        return False

    def _on_joint_tile(self, key: str, parsed, payload: zenoh.ZBytes) -> None:
        msg = self._decode(key, payload, decode_tile, self.max_tile_bytes)
        if msg is None:
            return
        if msg.uav != JOINT_UAV:
            self._reject("uav_mismatch", key, f"uav {msg.uav!r} on a joint key")
            return
        if (msg.cls, msg.z, msg.x, msg.y) != (parsed.cls, parsed.z, parsed.x, parsed.y):
            self._reject("tile_mismatch", key, f"tile {msg.cls}/{msg.z}/{msg.x}/{msg.y}")
            return
        if msg.z != self.grid.z or msg.n != self.grid.n:
            self._reject("wrong_grid", key, f"z={msg.z} n={msg.n}, agent grid z={self.grid.z} n={self.grid.n}")
            return
        if self._in_future(key, msg.t, "tiles"):
            return
        tile_id = (msg.cls, msg.x, msg.y)
        now = time.monotonic()
        with self._lock:
            old = self._joint_tiles.get(tile_id)
            # a query reply may arrive after a newer published sample: keep the newer one
            if (old is not None and msg.seq <= old[2] and msg.t <= old[3]
                    and now - old[1] < _REORDER_WINDOW_S):
                self._rejects["stale"] += 1
                return
            self._joint_tiles[tile_id] = (msg.values, now, msg.seq, msg.t)
            self._joint_tiles.move_to_end(tile_id)
            while len(self._joint_tiles) > self.max_joint_tiles:
                evicted, _ = self._joint_tiles.popitem(last=False)
                self._joint_pending.discard(evicted)
                self._counts["joint_tiles_evicted"] += 1
            self._joint_pending.add(tile_id)
            self._counts["joint_tiles"] += 1
            self._bytes["joint_tiles"] += len(payload)

    def _on_joint_tracks(self, key: str, payload: zenoh.ZBytes, region: tuple[Any, Any, Any] | None = None) -> None:
        msg = self._decode(key, payload, decode_joint_tracks, MAX_JOINT_TRACKS_BYTES)
        if msg is None:
            return
        if msg.uav != JOINT_UAV:
            self._reject("uav_mismatch", key, f"uav {msg.uav!r} on the joint tracks key")
            return
        if self._in_future(key, msg.t, "tracks"):
            return
        with self._lock:
            if region is None:
                self._joint_tracks = (msg, time.monotonic())
            else:  # the tracks of one region (agent.joint_window); at most _MAX_REGIONS held
                self._region_tracks.pop(region, None)
                self._region_tracks[region] = (msg, time.monotonic())
                while len(self._region_tracks) > _MAX_REGIONS:
                    self._region_tracks.popitem(last=False)
            self._counts["joint_tracks"] += 1
            self._bytes["joint_tracks"] += len(payload)

    def _on_state(self, key: str, uav: str, payload: zenoh.ZBytes) -> None:
        msg = self._decode(key, payload, decode_state, DEFAULT_MAX_STATE_BYTES)
        if msg is None:
            return
        if msg.uav != uav:
            self._reject("uav_mismatch", key, f"uav {msg.uav!r} on the state key of {uav!r}")
            return
        self.partner_clocks.observe(uav, msg.t)
        with self._lock:
            self._counts["states"] += 1
            self._bytes["states"] += len(payload)
            if len(msg.footprint) >= 3:
                self._footprints[uav] = (msg.footprint, time.monotonic())
                self._footprints_pending.add(uav)

    # ---- reading the joint side ----------------------------------------------------------------
    def drain_joint_tiles(self, max_age_s: float | None = None) -> list[JointTileUpdate]:
        """Joint tiles received since the last call (latest per tile), with their age in seconds.

        Tiles older than ``max_age_s`` are forgotten here (and not returned).
        """
        now = time.monotonic()
        with self._lock:
            if max_age_s is not None:
                for tile_id in [k for k, v in self._joint_tiles.items() if now - v[1] > max_age_s]:
                    del self._joint_tiles[tile_id]
                    self._joint_pending.discard(tile_id)
            out = []
            for cls, x, y in self._joint_pending:
                values, received, _, _ = self._joint_tiles[(cls, x, y)]
                out.append(JointTileUpdate(cls, x, y, values, now - received))
            self._joint_pending.clear()
        return out

    def drain_footprints(self, max_age_s: float | None = None) -> list[FootprintUpdate]:
        """Other UAVs' footprints received since the last call (the latest per UAV), with their age.

        Footprints older than ``max_age_s`` are forgotten here (and not returned).
        """
        now = time.monotonic()
        with self._lock:
            out = []
            for uav in self._footprints_pending:
                footprint, received = self._footprints[uav]
                if max_age_s is None or now - received <= max_age_s:
                    out.append(FootprintUpdate(uav, footprint, now - received))
            self._footprints_pending.clear()
            if max_age_s is not None:
                for uav in [u for u, v in self._footprints.items() if now - v[1] > max_age_s]:
                    del self._footprints[uav]
        return out

    def joint_tracks(self) -> tuple[JointTracksMessage, float] | None:
        """The latest global tracks and their age in seconds, or None before any arrived.

        With track regions (agent.joint_window): the tracks of every region heard from within
        MAX_REGION_AGE_S, merged, aged as the newest of them, unless the global message is newer.
        """
        now = time.monotonic()
        with self._lock:
            fresh = [(msg, received) for msg, received in self._region_tracks.values()
                     if now - received <= MAX_REGION_AGE_S]
            latest = self._joint_tracks
        if fresh:
            newest = max(received for _, received in fresh)
            if latest is None or newest >= latest[1]:
                # a track that moved between regions: the newer region's message wins
                by_gid = {item.gid: item for msg, _ in sorted(fresh, key=lambda entry: entry[1]) for item in msg.tracks}
                merged = JointTracksMessage(t=max(msg.t for msg, _ in fresh),
                                            tracks=tuple(by_gid[gid] for gid in sorted(by_gid)))
                return merged, now - newest
        if latest is None:
            return None
        return latest[0], now - latest[1]

    def stats(self) -> dict[str, Any]:
        """Counters: messages and bytes sent per kind, joint messages received, rejects by reason,
        publishers declared, joint tiles held, the joint messages' clock lead adopted (agent.joint_clock)."""
        with self._lock:
            return {"counts": dict(self._counts), "bytes": dict(self._bytes), "rejected": dict(self._rejects),
                    "publishers": 0 if self._publishers is None else len(self._publishers),
                    "joint_tiles_held": len(self._joint_tiles),
                    "joint_clock_lead_s": round(self.joint_clock.lead_s, 3)}

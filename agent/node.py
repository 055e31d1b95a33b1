"""The live agent: frames from a source -> detection pipeline (local + joint memory map) -> GPS tracker,
published over Zenoh at a fixed rate (tiles that changed, state, tracks) while joint tiles flow back.

`AgentNode(settings, source).run(stop)` runs until the source ends, ``duration_s`` passes or ``stop``
is set. The pure parts (tile change detection, message building, global id adoption) are separate
classes so they are testable without a network.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agent.frame_result import FrameResult
from agent.memory_map import JointLayer, MemoryMap
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.sources import FrameSource, SourceFrame
from agent.tracking import GpsTracker, TrackerConfig, TrackOutput
from agent.tracking.appearance import with_image_descriptors
from agent.zenoh_config import ZenohOptions, agent_zenoh_config
from agent.zenoh_io import AgentLink, encode_tracks_with_gid
from shared.geo import Camera, Pose, footprint_latlon, latlon_to_local
from shared.keys import DEFAULT_PREFIX, KeySpace, validate_uav_id
from shared.messages import (
    CameraInfo,
    JointTracksMessage,
    StateMessage,
    TrackItem,
    TracksMessage,
    encode_state,
)
from shared.tilecodec import encode_tile_sparse, quantise
from shared.tiles import TileGrid

__all__ = [
    "AgentNode",
    "AgentSettings",
    "GlobalIdAdopter",
    "TileChangeTracker",
    "run_first_track_id",
    "state_message",
    "tracks_message",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------

def _positive(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"AgentSettings.{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class AgentSettings:
    """Everything `uavmm agent` can be told besides the source and the pipeline; validated at creation.

    Attributes
    ----------
    uav_id : str
        This UAV's id: ASCII letters, digits, ``_ . -`` (``shared.keys.uav_id_problem``), not ``joint``.
    zenoh : ZenohOptions
        Mode, endpoints, config file (see `agent.zenoh_config`).
    prefix : str
        Key prefix (default ``uavmm/v1``).
    publish_hz : float
        Publish cycles per wall second (tiles that changed, state, tracks).
    refresh_s : float
        An unchanged tile is sent again after this many wall seconds, so the server (TTL 2 s by
        default) keeps counting this UAV as covering it; keep it below the server's TTL.
    tile_min_value : float
        Cells below this value are sent as 0 (the Gaussian tails: boosting by less than 0.05 changes
        little, and they are ~half the bytes). 0 sends every cell that quantises to a non-zero byte.
    tile_budget_bytes_per_s : float or None
        Most tile payload bytes a second (token bucket, stalest tiles first); None = no limit. State
        and tracks (~10 kB/s) come on top. See docs/agent.md for the measured rates.
    joint_ttl_s : float
        A joint tile not refreshed for this many wall seconds stops boosting.
    speed : float
        Playback speed against the source's clock (1 = real time); 0 = as fast as possible.
    duration_s : float or None
        Stop after this many wall seconds.
    loop : bool
        Start the source again when it ends (times keep increasing).
    gid_gate_m : float
        A new local track adopts the id of a global track of its class within this distance.
    gid_window_s : float
        How long after its birth a local track may still adopt a global id by position (the server's
        membership list is used at any time).
    query_timeout_s : float
        Bound of the start-up query for the current joint map (late join).
    footprint_points : int
        Vertices of the footprint polygon in state messages (a multiple of 4, at most 256).
    grid_z, grid_n : int
        The shared tile grid (must match the fusion server's).
    tracks_out : Path or None
        Write the reported tracks (with adopted global ids) as GeoJSON here at the end.
    open_timeout_s : float or None
        Give up when the Zenoh session cannot be opened within this time (None: keep trying).
    """

    uav_id: str
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    prefix: str = DEFAULT_PREFIX
    publish_hz: float = 5.0
    refresh_s: float = 1.0
    tile_min_value: float = 0.05
    tile_budget_bytes_per_s: float | None = 70_000.0
    joint_ttl_s: float = 3.0
    speed: float = 1.0
    duration_s: float | None = None
    loop: bool = False
    gid_gate_m: float = 10.0
    gid_window_s: float = 2.0
    query_timeout_s: float = 2.0
    footprint_points: int = 32
    grid_z: int = 18
    grid_n: int = 256
    tracks_out: Path | None = None
    open_timeout_s: float | None = None

    def __post_init__(self) -> None:
        validate_uav_id(self.uav_id, "uav_id")
        KeySpace(self.prefix)
        TileGrid(self.grid_z, self.grid_n)
        for name in ("publish_hz", "refresh_s", "joint_ttl_s", "gid_gate_m", "gid_window_s", "query_timeout_s"):
            _positive(name, getattr(self, name))
        if not (isinstance(self.speed, int | float) and math.isfinite(self.speed) and self.speed >= 0):
            raise ValueError(f"AgentSettings.speed must be >= 0 (0 = as fast as possible), got {self.speed!r}")
        if not (isinstance(self.tile_min_value, int | float) and 0 <= self.tile_min_value < 1):
            raise ValueError(f"AgentSettings.tile_min_value must be in [0, 1), got {self.tile_min_value!r}")
        if self.duration_s is not None:
            _positive("duration_s", self.duration_s)
        if self.tile_budget_bytes_per_s is not None:
            _positive("tile_budget_bytes_per_s", self.tile_budget_bytes_per_s)
        if self.open_timeout_s is not None:
            _positive("open_timeout_s", self.open_timeout_s)
        if (isinstance(self.footprint_points, bool) or not isinstance(self.footprint_points, int)
                or not 4 <= self.footprint_points <= 256 or self.footprint_points % 4):
            raise ValueError(f"AgentSettings.footprint_points must be a multiple of 4 in 4..256, "
                             f"got {self.footprint_points!r}")

    @property
    def grid(self) -> TileGrid:
        """The shared tile grid."""
        return TileGrid(self.grid_z, self.grid_n)

    @property
    def keys(self) -> KeySpace:
        """The key space under ``prefix``."""
        return KeySpace(self.prefix)


# ---------------------------------------------------------------------------------------------
# Tiles: what to send this cycle
# ---------------------------------------------------------------------------------------------

#: How long (wall seconds) another UAV covers the cells of a footprint it sent: the fusion server's
#: default --ttl-s, after which the server stops counting it in a cell's mean.
COVER_TTL_S = 2.0

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


# ---------------------------------------------------------------------------------------------
# State and tracks messages
# ---------------------------------------------------------------------------------------------

def state_message(uav: str, t: float, pose: Pose, camera: Camera, *, range_m: float,
                  footprint_points: int = 32) -> StateMessage:
    """The state message of a UAV at time t (seconds) with its camera pose.

    The footprint is the image border cast on the ground up to ``range_m`` (the pipeline's
    georeferencing range), ``footprint_points`` vertices ``(lat, lon)``; heading is sent in [0, 360).
    """
    polygon = footprint_latlon(camera, pose, max_range_m=range_m, samples_per_edge=footprint_points // 4)
    return StateMessage(
        uav=uav, t=t, lat=pose.lat, lon=pose.lon, height_m=pose.height_m, pitch_deg=pose.pitch_deg,
        heading_deg=pose.heading_deg % 360.0,
        footprint=tuple((float(a), float(b)) for a, b in polygon),
        camera=CameraInfo(width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy,
                          cx=camera.cx, cy=camera.cy),
    )


def publishable_tracks(tracks: list[TrackOutput]) -> list[TrackOutput]:
    """The tracks an agent reports: confirmed (also while coasting) with a finite ground position."""
    return [tr for tr in tracks if tr.confirmed and math.isfinite(tr.lat) and math.isfinite(tr.lon)]


def tracks_message(uav: str, t: float, tracks: list[TrackOutput], class_names: dict[int, str]) -> TracksMessage:
    """A tracks message of the publishable tracks; scores (boosted, may exceed 1) are clipped to [0, 1]."""
    items = tuple(
        TrackItem(id=tr.id, cls=class_names.get(tr.cls, str(tr.cls)), lat=tr.lat, lon=tr.lon,
                  score=min(max(tr.score, 0.0), 1.0), vel_en=(tr.vel_en[0], tr.vel_en[1]))
        for tr in publishable_tracks(tracks)
    )
    return TracksMessage(uav=uav, t=t, tracks=items)


#: Local track ids of a live run stay below this, so they are exact in JSON numbers (doubles) on the
#: map page and in REST clients as well as in msgpack/SQLite int64.
_TRACK_ID_SPAN = 2**53


def run_first_track_id(wall_ns: int | None = None) -> int:
    """The first local track id of an agent run: microseconds since the UNIX epoch (mod 2**53).

    The fusion server keys local tracks by ``(uav, local id)``; a restarted agent whose ids began at 1
    again would have its new objects taken for the previous run's. A run starting a second later
    begins 10**6 ids higher, more tracks than any run makes, so runs never share ids (given a clock
    that does not jump back, e.g. GPS/NTP time). wall_ns: ``time.time_ns()`` (tests pass a value).
    """
    wall_ns = time.time_ns() if wall_ns is None else wall_ns
    return (wall_ns // 1000) % _TRACK_ID_SPAN


# ---------------------------------------------------------------------------------------------
# Global id adoption
# ---------------------------------------------------------------------------------------------

@dataclass(slots=True)
class _LocalTrack:
    born: float  # wall seconds (monotonic) the local track was first reported
    last: float
    gid: int | None = None
    via: str = ""  # "position" or "server"


class GlobalIdAdopter:
    """Which global track (fusion server id) each local track of this UAV is.

    Two rules, checked every update:

    * membership: a global track listing ``(uav, local id)`` among its members gives its gid (the
      server's association wins over everything else);
    * position: a local track reported for less than ``window_s`` with no gid yet takes the gid of the
      nearest global track of its class within ``gate_m`` metres that is not already another of this
      UAV's current tracks: the object another UAV has been tracking keeps its id when this UAV
      starts seeing it.

    uav: this UAV's id; horizon_s: a local track unseen this long is forgotten.
    """

    def __init__(self, uav: str, *, gate_m: float = 10.0, window_s: float = 2.0, horizon_s: float = 300.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.uav = uav
        self.gate_m = gate_m
        self.window_s = window_s
        self.horizon_s = horizon_s
        self.clock = clock
        self._tracks: dict[int, _LocalTrack] = {}
        self.n_adopted_by_position = 0

    def gid_of(self, local_id: int) -> int | None:
        """The adopted global id of a local track, or None."""
        entry = self._tracks.get(local_id)
        return None if entry is None else entry.gid

    def gids(self) -> dict[int, int]:
        """local id -> global id for every local track that has one."""
        return {lid: e.gid for lid, e in self._tracks.items() if e.gid is not None}

    def update(self, tracks: list[tuple[int, str, float, float]], joint: JointTracksMessage | None) -> dict[int, int]:
        """Take this UAV's reported tracks ``(local id, class name, lat, lon)`` and the latest global
        tracks (None when none are known or they are stale); returns :meth:`gids`."""
        now = self.clock()
        for lid, *_ in tracks:
            entry = self._tracks.get(lid)
            if entry is None:
                self._tracks[lid] = _LocalTrack(born=now, last=now)
            else:
                entry.last = now
        if joint is not None and joint.tracks:
            self._by_membership(joint)
            self._by_position(tracks, joint, now)
        for lid in [k for k, e in self._tracks.items() if now - e.last > self.horizon_s]:
            del self._tracks[lid]
        return self.gids()

    def _by_membership(self, joint: JointTracksMessage) -> None:
        for g in joint.tracks:
            for uav, lid in g.members:
                if uav == self.uav and lid in self._tracks:
                    entry = self._tracks[lid]
                    if entry.gid != g.gid:
                        log.debug("local track %d is global %d (server membership)", lid, g.gid)
                    entry.gid, entry.via = g.gid, "server"

    def _by_position(self, tracks: list[tuple[int, str, float, float]], joint: JointTracksMessage, now: float) -> None:
        current = {lid for lid, *_ in tracks}
        taken = {self._tracks[lid].gid for lid in current if self._tracks[lid].gid is not None}
        # a global track holding another of our current local tracks is that object, not this one
        taken |= {g.gid for g in joint.tracks if any(u == self.uav and lid in current for u, lid in g.members)}
        want = [(lid, cls, lat, lon) for lid, cls, lat, lon in tracks
                if self._tracks[lid].gid is None and now - self._tracks[lid].born <= self.window_s]
        if not want:
            return
        for cls in sorted({w[1] for w in want}):
            mine = [w for w in want if w[1] == cls]
            theirs = [g for g in joint.tracks if g.cls == cls and g.gid not in taken]
            if not theirs:
                continue
            lat0, lon0 = mine[0][2], mine[0][3]
            e1, n1 = latlon_to_local(np.array([w[2] for w in mine]), np.array([w[3] for w in mine]), lat0, lon0)
            e2, n2 = latlon_to_local(np.array([g.lat for g in theirs]), np.array([g.lon for g in theirs]), lat0, lon0)
            dist = np.hypot(e1[:, None] - e2[None, :], n1[:, None] - n2[None, :])  # (mine, theirs) metres
            # greedy by distance: closest pairs first, each global and local track used once
            for flat in np.argsort(dist, axis=None):
                i, j = divmod(int(flat), len(theirs))
                if dist[i, j] > self.gate_m:
                    break
                lid, gid = mine[i][0], theirs[j].gid
                if self._tracks[lid].gid is not None or gid in taken:
                    continue
                self._tracks[lid].gid, self._tracks[lid].via = gid, "position"
                taken.add(gid)
                self.n_adopted_by_position += 1
                log.info("local track %d adopts global id %d (%.1f m away)", lid, gid, dist[i, j])


# ---------------------------------------------------------------------------------------------
# The agent
# ---------------------------------------------------------------------------------------------

class AgentNode:
    """One agent: a source, the pipeline with a joint layer, the tracker and the Zenoh link.

    Parameters
    ----------
    settings : AgentSettings
    source : FrameSource
    pipeline_config : PipelineConfig, optional
    size_filter : SizeFilter, optional
    tracker_config : TrackerConfig, optional
    on_frame : callable, optional
        Called after each frame with (frame, pipeline result, tracks): for tests and tools.
    on_ready : callable, optional
        Called with the node once Zenoh is open and the start-up joint query answered.
    """

    def __init__(self, settings: AgentSettings, source: FrameSource, pipeline_config: PipelineConfig | None = None,
                 size_filter: SizeFilter | None = None, tracker_config: TrackerConfig | None = None, *,
                 on_frame: Callable[[SourceFrame, FrameResult, list[TrackOutput]], None] | None = None,
                 on_ready: Callable[[AgentNode], None] | None = None) -> None:
        self.settings = settings
        self.source = source
        grid = settings.grid
        self.joint = JointLayer(grid, ttl_s=settings.joint_ttl_s)
        self.pipeline = DetectionPipeline(source.camera, source.class_names, pipeline_config,
                                          size_filter=size_filter, joint=self.joint, grid=grid)
        # ids unique per run: the server would otherwise take a restarted agent's new tracks for old ones
        self.tracker = GpsTracker(tracker_config, source.class_names, evidence_at=self._evidence_at,
                                  first_id=run_first_track_id())
        self.link = AgentLink(agent_zenoh_config(settings.zenoh), settings.keys, settings.uav_id, grid)
        self.tiles = TileChangeTracker(settings.uav_id, list(dict.fromkeys(source.class_names.values())), grid,
                                       refresh_s=settings.refresh_s, min_value=settings.tile_min_value,
                                       budget_bytes_per_s=settings.tile_budget_bytes_per_s)
        self.adopter = GlobalIdAdopter(settings.uav_id, gate_m=settings.gid_gate_m, window_s=settings.gid_window_s)
        self.on_frame = on_frame
        self.on_ready = on_ready
        self.counts: dict[str, Any] = {"frames": 0, "frames_without_pose": 0, "frame_errors": 0, "detections": 0,
                                       "publish_cycles": 0, "joint_tiles_applied": 0, "footprints_applied": 0,
                                       "joint_query_replies": 0, "joint_detections": 0, "behind_s_max": 0.0}
        self._rows: list[tuple[int, float, TrackOutput]] = []
        self._last_pose: tuple[float, Pose, Camera] | None = None
        self._t_frame: float | None = None
        self._tracks: list[TrackOutput] = []
        self._clock0: tuple[float, float] | None = None  # (frame t, monotonic) of the first frame
        self._started = 0.0

    # ---- evidence for the tracker's re-identification ------------------------------------------
    def _evidence_at(self, class_id: int, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        gx, gy = self.pipeline.grid.latlon_to_cell(lat, lon)
        return self.pipeline.memory.values_at(self.pipeline.class_names[class_id], gx, gy)

    # ---- clocks --------------------------------------------------------------------------------
    def _clock_rate(self, t: float) -> float:
        """Frame-clock seconds per wall second, measured since the first frame (speed until 1 s passed)."""
        if self._clock0 is not None:
            wall = time.monotonic() - self._clock0[1]
            if wall >= 1.0:
                return max((t - self._clock0[0]) / wall, 1e-3)
        return self.settings.speed if self.settings.speed > 0 else 1.0

    def _frames(self) -> Iterator[SourceFrame]:
        offset = 0.0
        while True:
            first = last = None
            for frame in self.source.frames():
                if offset:
                    frame = dataclasses.replace(frame, t=frame.t + offset,
                                                pose_t=None if frame.pose_t is None else frame.pose_t + offset)
                first = frame.t if first is None else first
                last = frame.t
                yield frame
            if not self.settings.loop or first is None or last is None:
                return
            log.info("source %s ended: starting it again", self.source.name)
            offset += (last - first) + 1.0 / 30.0

    # ---- run -----------------------------------------------------------------------------------
    def run(self, stop: threading.Event | None = None) -> dict[str, Any]:
        """Open Zenoh, fetch the current joint map, process frames until the end, publish; close.

        Returns the counters (frames, detections, publish cycles, link statistics, bytes per second).
        """
        stop = stop or threading.Event()
        s = self.settings
        self._started = time.monotonic()
        if not self.link.open(stop, timeout_s=s.open_timeout_s):
            log.warning("agent %s: no zenoh session; stopping", s.uav_id)
            return self.summary()
        try:
            self.counts["joint_query_replies"] = self.link.query_joint(s.query_timeout_s)
            if self.on_ready is not None:
                self.on_ready(self)
            self._loop(stop)
        finally:
            self.link.close()
            self.source.close()
        if s.tracks_out is not None:
            n = self.write_tracks(s.tracks_out)
            log.info("wrote %d tracks to %s", n, s.tracks_out)
        return self.summary()

    def _loop(self, stop: threading.Event) -> None:
        s = self.settings
        deadline = None if s.duration_s is None else self._started + s.duration_s
        period = 1.0 / s.publish_hz
        next_publish = time.monotonic()
        warned_behind = -math.inf
        for frame in self._frames():
            now = time.monotonic()
            if stop.is_set() or (deadline is not None and now >= deadline):
                break
            if self._clock0 is None:
                self._clock0 = (frame.t, now)
            elif s.speed > 0:
                due = self._clock0[1] + (frame.t - self._clock0[0]) / s.speed
                wait = due - now
                if deadline is not None:
                    wait = min(wait, deadline - now)
                if wait > 0 and stop.wait(wait):
                    break
                if deadline is not None and time.monotonic() >= deadline:
                    break
                behind = -wait
                self.counts["behind_s_max"] = max(self.counts["behind_s_max"], behind)
                if behind > 1.0 and now - warned_behind > 10.0:
                    warned_behind = now
                    log.warning("agent %s: %.1f s behind the source's clock at speed %g (processing too slow)",
                                s.uav_id, behind, s.speed)
            try:
                self.step(frame)
            except Exception:  # one bad frame must not take a flying agent down: count, log, go on
                self.counts["frame_errors"] += 1
                if self.counts["frame_errors"] in (1, 10) or self.counts["frame_errors"] % 1000 == 0:
                    log.exception("agent %s: frame %d failed (%d so far)", s.uav_id, frame.index,
                                  self.counts["frame_errors"])
            now = time.monotonic()
            if now >= next_publish:
                self.publish()
                next_publish = max(next_publish + period, now)
        self.publish()  # the final state of the map and tracks

    def step(self, frame: SourceFrame) -> tuple[FrameResult, list[TrackOutput]]:
        """Process one frame: apply the joint tiles received meanwhile, run the pipeline and the tracker."""
        rate = self._clock_rate(frame.t)
        self._apply_joint(frame.t, rate)
        if self.pipeline.camera != frame.camera:
            self.pipeline.camera = frame.camera
        result = self.pipeline.process(frame.boxes_xyxy, frame.scores, frame.class_ids, frame.pose, frame.t,
                                       frame.embeddings)
        if frame.image is not None:  # appearance of the kept boxes for re-ID (docs/agent.md)
            result = with_image_descriptors(result, frame.image)
        tracks = self.tracker.update(result, frame.pose, frame.t, frame.camera, pose_t=frame.pose_t)
        self._tracks = tracks
        self._t_frame = frame.t
        if frame.pose is not None:
            self._last_pose = (frame.t, frame.pose, frame.camera)
        self.counts["frames"] += 1
        self.counts["frames_without_pose"] += frame.pose is None
        self.counts["detections"] += len(result)
        if result.from_joint is not None:  # detections the other UAVs' evidence added or promoted
            self.counts["joint_detections"] += int(result.from_joint.sum())
        if self.settings.tracks_out is not None:
            self._rows.extend((frame.index, frame.t, tr) for tr in tracks if tr.confirmed and tr.matched)
        if self.on_frame is not None:
            self.on_frame(frame, result, tracks)
        return result, tracks

    def _apply_joint(self, t: float, rate: float) -> None:
        """Move the joint tiles received since the last frame into the joint layer.

        Freshness is a wall-clock matter (the server refreshes tiles in wall time) while the layer
        works on the frame clock: a tile received ``age`` wall seconds ago is stamped
        ``t - age * rate`` and the layer's TTL is ``joint_ttl_s * rate`` frame seconds.
        """
        ttl = self.settings.joint_ttl_s
        self.joint.ttl_s = ttl * rate
        for update in self.link.drain_joint_tiles(max_age_s=ttl):
            if update.values.shape != (self.joint.grid.n, self.joint.grid.n):
                continue  # the link rejects other grids already
            self.joint.update(update.cls, update.x, update.y, update.values, t - update.age_s * rate)
            self.counts["joint_tiles_applied"] += 1
        self.joint.prune(t)
        # the others' footprints say which cells their evidence is in the joint mean for
        self.joint.cover_ttl_s = COVER_TTL_S * rate
        for fp in self.link.drain_footprints(max_age_s=COVER_TTL_S):
            if self.joint.put_footprint(fp.uav, fp.footprint, t - fp.age_s * rate):
                self.counts["footprints_applied"] += 1

    # ---- publishing ----------------------------------------------------------------------------
    def _joint_tracks(self) -> JointTracksMessage | None:
        latest = self.link.joint_tracks()
        if latest is None or latest[1] > self.settings.joint_ttl_s:
            return None
        return latest[0]

    def publish(self) -> None:
        """Build this cycle's messages (changed/refresh tiles, state, tracks) and hand them to the link."""
        if self._t_frame is None:
            return
        s = self.settings
        t = self._t_frame
        messages: list[tuple[str, str, bytes]] = []
        for cls, x, y, payload in self.tiles.messages(self.pipeline.memory, t):
            messages.append(("tile", self.link.tile_key(cls, x, y), payload))
        if self._last_pose is not None:
            t_pose, pose, camera = self._last_pose
            state = state_message(s.uav_id, t_pose, pose, camera, range_m=self.pipeline.config.range_limit_m,
                                  footprint_points=s.footprint_points)
            messages.append(("state", self.link.state_key(), encode_state(state)))
        names = self.pipeline.class_names
        msg = tracks_message(s.uav_id, t, self._tracks, names)
        gids = self.adopter.update([(i.id, i.cls, i.lat, i.lon) for i in msg.tracks], self._joint_tracks())
        messages.append(("tracks", self.link.tracks_key(), encode_tracks_with_gid(msg, gids)))
        self.link.submit(messages)
        self.counts["publish_cycles"] += 1

    # ---- outputs -------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Counters of the run so far, the link's statistics and the bytes per second sent."""
        elapsed = max(time.monotonic() - self._started, 1e-9)
        link = self.link.stats()
        sent = sum(v for k, v in link["bytes"].items() if k.startswith("sent_"))
        return {
            **self.counts,
            "behind_s_max": round(self.counts["behind_s_max"], 3),
            "elapsed_s": round(elapsed, 3),
            "tiles_changed": self.tiles.n_changed,
            "tiles_refreshed": self.tiles.n_refreshed,
            "tiles_unchanged_skipped": self.tiles.n_skipped,
            "tiles_deferred_by_budget": self.tiles.n_deferred,
            "gids_adopted_by_position": self.adopter.n_adopted_by_position,
            "sent_bytes_per_s": round(sent / elapsed, 1),
            "link": link,
        }

    def write_tracks(self, path: str | Path) -> int:
        """Write the reported tracks as GeoJSON (see `agent.tracking_io.geojson_tracks`) with ``uav`` and
        ``gid`` (the adopted global id, null without one) in each feature's properties."""
        from agent.tracking_io import TrackRow, geojson_tracks

        rows = [TrackRow(index, index, t, tr) for index, t, tr in self._rows]
        collection = geojson_tracks({0: rows}, self.pipeline.class_names)
        for feature in collection["features"]:
            props = feature["properties"]
            props["uav"] = self.settings.uav_id
            props["gid"] = self.adopter.gid_of(props["id"])
        Path(path).write_text(json.dumps(collection))
        return len(collection["features"])

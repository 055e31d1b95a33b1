"""The live agent: frames from a source -> detection pipeline (local + joint memory map) -> GPS tracker,
published over Zenoh at a fixed rate (tiles that changed, state, tracks) while joint tiles flow back.

`AgentNode(settings, source).run(stop)` runs until the source ends, ``duration_s`` passes or ``stop``
is set. The pure parts are testable without a network: message building here, the choice of tiles to
send in `agent.tile_updates`, global id adoption in `agent.global_ids`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agent.boost import StreamedResults, results_to_coco
from agent.dataset import count_reasons
from agent.frame_result import FrameResult
from agent.global_ids import GlobalIdAdopter
from agent.joint_window import window_tiles
from agent.memory_map import JointLayer
from agent.node_messages import publishable_tracks, state_message, tracks_message
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from agent.sources import FrameSource, SourceFrame
from agent.stage_report import StageSummary
from agent.tile_updates import TileChangeTracker
from agent.track_lending import TrackLending
from agent.track_rows import FirstPass, TrackRowLog
from agent.tracking import GpsTracker, TrackerConfig, TrackOutput
from agent.tracking.appearance import with_image_descriptors
from agent.zenoh_config import ZenohOptions, agent_zenoh_config
from agent.zenoh_io import AgentLink, encode_tracks_with_gid
from shared.geo import Camera, Pose
from shared.keys import DEFAULT_PREFIX, KeySpace, validate_uav_id
from shared.messages import (
    JointTracksMessage,
    encode_state,
)
from shared.tiles import TileGrid

__all__ = [
    "AgentNode",
    "AgentSettings",
    "publishable_tracks",
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


def _non_negative(name: str, value: object, zero: str) -> None:
    """zero: what 0 means for the setting."""
    if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
        raise ValueError(f"AgentSettings.{name} must be >= 0 (0 = {zero}), got {value!r}")


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
    joint_window : bool
        Receive the joint tiles of the memory map's window (and one tile around it) only, not the
        whole fleet's (agent.joint_window); False subscribes to every joint tile.
    speed : float
        Playback speed against the source's clock (1 = real time); 0 = as fast as possible.
    replay_sync_s : float
        Recordings replayed together line up on their own clocks: when another UAV's state messages show its
        source clock ahead of this agent's by more than REPLAY_SYNC_MIN_LEAD_S and at most this many seconds
        (it started earlier), running at this agent's speed (REPLAY_SYNC_RATE_TOL), this agent takes up its
        clock, processing the frames it is behind on without waiting, so both UAVs' evidence of one moment meets
        in the joint map (0: off). Started 2 s apart without it, the weaker UAV of `coop-glare` lost most of its
        joint map's gain (docs/agent.md).
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
    detections_out : Path or None
        Write the final detections of every frame (boosted, NMS'd, with the joint map's) as a COCO result
        list here at the end: image ids of a dataset source, frame indices otherwise.
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
    joint_window: bool = True
    speed: float = 1.0
    replay_sync_s: float = 30.0
    duration_s: float | None = None
    loop: bool = False
    gid_gate_m: float = 10.0
    gid_window_s: float = 2.0
    query_timeout_s: float = 2.0
    footprint_points: int = 32
    grid_z: int = 18
    grid_n: int = 256
    tracks_out: Path | None = None
    detections_out: Path | None = None
    open_timeout_s: float | None = None

    def __post_init__(self) -> None:
        validate_uav_id(self.uav_id, "uav_id")
        KeySpace(self.prefix)
        TileGrid(self.grid_z, self.grid_n)
        for name in ("publish_hz", "refresh_s", "joint_ttl_s", "gid_gate_m", "gid_window_s", "query_timeout_s"):
            _positive(name, getattr(self, name))
        _non_negative("replay_sync_s", self.replay_sync_s, "off")
        _non_negative("speed", self.speed, "as fast as possible")
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
# The agent
# ---------------------------------------------------------------------------------------------

#: How long (wall seconds) another UAV covers the cells of a footprint it sent: the fusion server's
#: default --ttl-s, after which the server stops counting it in a cell's mean.
COVER_TTL_S = 2.0
#: Replay sync (AgentSettings.replay_sync_s): another UAV's source clock counts when its state message is at most
#: this old (wall seconds), and is taken up when it leads this agent's by more than REPLAY_SYNC_MIN_LEAD_S (two
#: publish cycles and a frame: a UAV in step reads up to ~0.4 s behind or ahead from its last state).
REPLAY_SYNC_MAX_AGE_S = 2.0
REPLAY_SYNC_MIN_LEAD_S = 0.5
#: ... and only a clock whose rate (over the last second or more of its states) is within this share of this
#: agent's speed.
REPLAY_SYNC_RATE_TOL = 0.2
#: Another UAV's source clock this close (s) to a whole number of TIME_ZONE_STEP_S from this agent's is taken for
#: a time zone (said once; time zones differ by half hours at the least, bar three quarter-hour ones).
TIME_ZONE_STEP_S = 1800.0
TIME_ZONE_TOL_S = 60.0
TIME_ZONE_MAX_S = 26 * 3600.0


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
    anomaly : agent.anomaly.AnomalyDetector, optional
        Also run anomaly detection on the frames' pixels and publish its ground layer as tiles of class
        ``anomaly`` (docs/anomaly.md); frames without pixels are skipped.
    """

    def __init__(self, settings: AgentSettings, source: FrameSource, pipeline_config: PipelineConfig | None = None,
                 size_filter: SizeFilter | None = None, tracker_config: TrackerConfig | None = None, *,
                 on_frame: Callable[[SourceFrame, FrameResult, list[TrackOutput]], None] | None = None,
                 on_ready: Callable[[AgentNode], None] | None = None, anomaly: Any | None = None) -> None:
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
        self.anomaly = anomaly
        self.anomaly_tiles = None if anomaly is None else TileChangeTracker(
            settings.uav_id, ["anomaly"], grid, refresh_s=settings.refresh_s, min_value=settings.tile_min_value,
            budget_bytes_per_s=settings.tile_budget_bytes_per_s)
        self.adopter = GlobalIdAdopter(settings.uav_id, gate_m=settings.gid_gate_m, window_s=settings.gid_window_s)
        self.lending = TrackLending(settings.uav_id, self.pipeline.config.track_lending)
        self.on_frame = on_frame
        self.on_ready = on_ready
        prepare = getattr(source, "prepare", None)
        if prepare is not None:  # a recording: read as `uavmm track` reads it (agent.dataset_source.DatasetSource)
            prepare(self.pipeline.config, self.pipeline)
        self.counts: dict[str, Any] = {"frames": 0, "frames_without_pose": 0, "frame_errors": 0, "detections": 0,
                                       "publish_cycles": 0, "joint_tiles_applied": 0, "footprints_applied": 0,
                                       "joint_query_replies": 0, "joint_detections": 0, "behind_s_max": 0.0,
                                       "replay_sync_s": 0.0, "frames_not_written": 0}
        self._written = FirstPass()  # the image ids the output files hold (--loop: the first pass)
        self._rows = TrackRowLog()  # for settings.tracks_out, as columns (104 B a row; 538 B as objects)
        self._detections = None if settings.detections_out is None else StreamedResults(settings.detections_out)
        self._last_pose: tuple[float, Pose, Camera] | None = None
        self._t_frame: float | None = None
        self._tracks: list[TrackOutput] = []
        self._clock0: tuple[float, float] | None = None  # (frame t, monotonic) of the first frame
        self._zone_warned: set[str] = set()  # UAVs whose clock was named as another time zone
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

    def _sync_replay(self, now: float) -> None:
        """Take up the source clock of another UAV that is ahead of this agent's (AgentSettings.replay_sync_s)."""
        assert self._clock0 is not None
        s = self.settings
        t0, w0 = self._clock0
        mine = t0 + (now - w0) * s.speed
        # only clocks that run at this agent's speed: a replay played faster would drag it along (the link keeps
        # no clock of this UAV's own states)
        clocks = self.link.partner_clocks.read(REPLAY_SYNC_MAX_AGE_S)
        self._say_time_zones(clocks, mine)
        lead = max((t + age * s.speed - mine for _, t, age, rate in clocks
                    if rate is not None and abs(rate - s.speed) <= REPLAY_SYNC_RATE_TOL * s.speed), default=0.0)
        if REPLAY_SYNC_MIN_LEAD_S < lead <= s.replay_sync_s:
            self._clock0 = (t0, w0 - lead / s.speed)
            self.counts["replay_sync_s"] += lead
            log.info("agent %s: another UAV's clock is %.2f s ahead: catching up", s.uav_id, lead)

    def _say_time_zones(self, clocks: list[tuple[str, float, float, float | None]], mine: float) -> None:
        """Warn once per UAV whose source clock is a whole number of half hours from this agent's (+-1 min, at most
        26 h, running at this agent's speed): two time zones, most likely a DJI SRT's local dates beside a UTC log,
        which no replay sync bridges (other days, simulated clocks from 0 and faster replays are not named)."""
        speed = self.settings.speed
        for uav, t, age, rate in clocks:
            apart = t + age * speed - mine
            zones = round(apart / TIME_ZONE_STEP_S)
            if (uav not in self._zone_warned and zones and abs(apart) <= TIME_ZONE_MAX_S
                    and abs(apart - zones * TIME_ZONE_STEP_S) <= TIME_ZONE_TOL_S
                    and rate is not None and abs(rate - speed) <= REPLAY_SYNC_RATE_TOL * speed):
                self._zone_warned.add(uav)
                log.warning("agent %s: %s's clock is %+.2f h from this agent's: two time zones? A DJI SRT's dates are "
                            "the drone's local time (--telemetry-utc-offset-h puts them on UTC); replays this far "
                            "apart are not lined up", self.settings.uav_id, uav, apart / 3600.0)

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
        if self._read_recording(stop):
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
        else:  # stopped (SIGTERM, --duration) while reading the recording: the outputs are written, empty
            self.source.close()
        if s.tracks_out is not None:
            n = self.write_tracks(s.tracks_out)
            log.info("wrote %d tracks to %s", n, s.tracks_out)
        if self._detections is not None:
            self._detections.close()
            log.info("wrote %d detections to %s", self._detections.count, s.detections_out)
        return self.summary()

    def _read_recording(self, stop: threading.Event) -> bool:
        """Let a recording's source run its telemetry stages before the agent connects (DatasetSource.read_recording),
        in a thread of its own so that `stop` and --duration hold meanwhile; False when they ended the run."""
        read = getattr(self.source, "read_recording", None)
        if read is None:
            return True
        failed: list[BaseException] = []

        def work() -> None:
            try:
                read()
            except BaseException as exc:  # raised again below, in the caller's thread
                failed.append(exc)

        worker = threading.Thread(target=work, name="uavmm-agent-recording", daemon=True)
        worker.start()
        deadline = None if self.settings.duration_s is None else self._started + self.settings.duration_s
        while worker.is_alive():
            if stop.wait(0.1) or (deadline is not None and time.monotonic() >= deadline):
                log.info("agent %s: stopped while reading the recording", self.settings.uav_id)
                return False
        if failed:
            raise failed[0]
        return True

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
                if s.replay_sync_s > 0:
                    self._sync_replay(now)
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
        tracks = self.tracker.update(result, frame.pose, frame.t, frame.camera, pose_t=frame.pose_t,
                                     pose_retimed=frame.pose_retimed, terrain=self.pipeline.terrain_for(frame.pose))
        if self.lending.weight and (self._detections is not None or self.on_frame is not None):  # the output only
            result = self.lending.apply(result, tracks, self._joint_tracks(), frame.t)
        if self.anomaly is not None and frame.image is not None:
            self.anomaly.process(frame.image, frame.pose, frame.t, frame.camera)
            self.counts["anomaly_frames"] = self.counts.get("anomaly_frames", 0) + 1
        self._tracks = tracks
        self._t_frame = frame.t
        if frame.pose is not None:
            self._last_pose = (frame.t, frame.pose, frame.camera)
        self.counts["frames"] += 1
        self.counts["frames_without_pose"] += frame.pose is None
        self.counts["detections"] += len(result)
        if result.from_joint is not None:  # detections the other UAVs' evidence added or promoted
            self.counts["joint_detections"] += int(result.from_joint.sum())
        written = (self._detections is not None or self.settings.tracks_out is not None) and self._written.take(
            frame.index if frame.image_id is None else frame.image_id)
        self.counts["frames_not_written"] = self._written.skipped
        if self._detections is not None and written:
            self._detections.extend(results_to_coco(frame.index if frame.image_id is None else frame.image_id, result))
        if self.settings.tracks_out is not None and written:
            self._rows.extend(frame.index if frame.frame_index is None else frame.frame_index, frame.t,
                              self.tracker.report(tracks))  # as `uavmm track` reports them
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
        memory = self.pipeline.memory
        if s.joint_window and memory.size_cells > 0:
            # joint tiles of the window and one tile around it; tracks of the regions the window touches
            origin, size, n, side = memory.origin, memory.size_cells, memory.grid.n, memory.grid.tiles_per_side
            self.link.set_joint_window(window_tiles(origin, size, n, tiles_per_side=side),
                                       window_tiles(origin, size, n, margin=0, tiles_per_side=side))
        for cls, x, y, payload in self.tiles.messages(memory, t):
            messages.append(("tile", self.link.tile_key(cls, x, y), payload))
        if self.anomaly_tiles is not None and self.anomaly is not None:
            for cls, x, y, payload in self.anomaly_tiles.messages(self.anomaly.map, t):
                messages.append(("tile", self.link.tile_key(cls, x, y), payload))
        if self._last_pose is not None:
            t_pose, pose, camera = self._last_pose
            state = state_message(s.uav_id, t_pose, pose, camera, range_m=self.pipeline.config.range_limit_m,
                                  footprint_points=s.footprint_points, terrain=self.pipeline.terrain_for(pose))
            messages.append(("state", self.link.state_key(), encode_state(state)))
        names = self.pipeline.class_names
        msg = tracks_message(s.uav_id, t, self._tracks, names)
        self.lending.reported(msg)
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
        problems = getattr(self.source, "problems", None)  # a dataset's PoseProblems (other sources: a count)
        return {
            **self.counts,
            "behind_s_max": round(self.counts["behind_s_max"], 3),
            "replay_sync_s": round(self.counts["replay_sync_s"], 3),
            "elapsed_s": round(elapsed, 3),
            "tiles_changed": self.tiles.n_changed,
            "tiles_refreshed": self.tiles.n_refreshed,
            "tiles_unchanged_skipped": self.tiles.n_skipped,
            "tiles_deferred_by_budget": self.tiles.n_deferred,
            "gids_adopted_by_position": self.adopter.n_adopted_by_position,
            "detections_lent": self.lending.lent_detections,
            "sent_bytes_per_s": round(sent / elapsed, 1),
            "link": link,
            "stages": self.stage_summary().as_dict(),
            # why frames had no pose, by reason (a dataset's meta), as `uavmm track`'s summary gives it
            "frames_without_pose_by_reason": count_reasons(problems) if isinstance(problems, list) else {},
        }

    def stage_summary(self) -> StageSummary:
        """What the adaptive stages did so far: the source's telemetry stages (a recording's), the pipeline's and
        the tracker's (`agent.stage_report`; the summary says whether each acted)."""
        stages = StageSummary()
        reports = getattr(self.source, "stage_reports", None)
        for report in [*(reports() if reports is not None else []), *self.pipeline.stage_reports(),
                       *self.tracker.stage_reports()]:
            stages.add(report)
        return stages

    def write_tracks(self, path: str | Path) -> int:
        """Write the reported tracks as GeoJSON (see `agent.tracking_io.geojson_tracks`) with ``uav`` and
        ``gid`` (the adopted global id, null without one) in each feature's properties."""
        video_id = getattr(self.source, "video_id", 0)  # a dataset's video, as `uavmm track` numbers it

        def add(props: dict[str, Any]) -> None:
            props["video_id"] = video_id
            props["uav"] = self.settings.uav_id
            props["gid"] = self.adopter.gid_of(props["id"])

        return self._rows.write_geojson(path, self.pipeline.class_names, add)

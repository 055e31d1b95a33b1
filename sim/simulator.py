"""Step-wise simulation: per time step and per UAV, the true pose, noisy meta, ground truth and candidates.

`Simulation(scenario, seed, frames, noise_scale).frames()` yields one `FrameSample` per frame of each video;
the dataset writer (`sim.dataset`) and the live agent both consume it. Deterministic per seed: every
world, flight, telemetry stream and detector has its own generator seeded from (seed, group, role, video).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.geo import Camera, Pose, local_to_latlon
from shared.terrain import Terrain
from sim.detector_emulator import (
    KIND_CLUTTER,
    KIND_OBJECT,
    KIND_OCCLUDED,
    Candidates,
    DetectorEmulator,
    EmulatorParams,
    object_appearance,
)
from sim.flight import Flight
from sim.groundtruth import project_objects, terrain_hidden
from sim.noise import TelemetryNoise, TelemetryStream, format_frame_time
from sim.scenarios import GAP_BETWEEN_FLIGHTS_S, START_UNIX_S, Scenario, get_scenario
from sim.terrain import SimTerrain
from sim.world import CATEGORY_IDS, World

logger = logging.getLogger(__name__)

#: COCO categories, the same ids in every scenario.
CATEGORIES: list[dict[str, Any]] = [{"id": i, "name": n, "supercategory": n} for n, i in CATEGORY_IDS.items()]

# roles of the generators derived from the seed
_ROLE_WORLD, _ROLE_FLIGHT, _ROLE_TELEMETRY, _ROLE_DETECTOR, _ROLE_APPEARANCE, _ROLE_TERRAIN, _ROLE_WEAK = range(7)
#: Least height of the camera above the terrain below it (metres): flights lower than this are refused.
MIN_CLEARANCE_M = 3.0


@dataclass(frozen=True, slots=True)
class VideoInfo:
    """One video (one flight of one UAV): 1-based `id`, `name`, `uav` id, `group` (videos of a group fly
    at the same time over one world), flight `kind` and `t0` (UNIX seconds of frame 0)."""

    id: int
    name: str
    uav: str
    group: int
    kind: str
    t0: float


@dataclass(frozen=True, slots=True)
class ObjectTruth:
    """Ground truth of one object in one frame.

    Attributes
    ----------
    track_id : int
        Unique over the whole simulation; the same object seen by several UAVs keeps its id.
    cls : str
    category_id : int
    lat, lon : float
        True ground position (degrees).
    bbox_xywh : tuple of 4 float or None
        The true box clipped to the image, pixels, when `in_view` (also when occluded); else None.
    in_view : bool
        In the image (>= 50 % of the box inside, >= 4 px) and below the horizon.
    occluded : bool
        The line of sight to the object's centre passes through a tree.
    visible : bool
        in_view and not occluded: the object is annotated.
    """

    track_id: int
    cls: str
    category_id: int
    lat: float
    lon: float
    bbox_xywh: tuple[float, float, float, float] | None
    in_view: bool
    occluded: bool
    visible: bool


@dataclass(frozen=True, slots=True)
class FrameSample:
    """Everything the simulator knows about one frame of one UAV.

    Attributes
    ----------
    image_id : int
        1-based, increasing in the order frames are yielded.
    video_id : int
    uav : str
    frame_index : int
        0-based within the video.
    t : float
        UNIX seconds of the frame (UTC, whatever the frame clock writes).
    date_time : str
        The frame clock: `t` as ISO 8601 UTC with milliseconds, or with the noise's
        `frame_clock_utc_offset_s` as naive local time with microseconds (`sim.noise.format_frame_time`).
    true_pose : shared.geo.Pose
    meta : dict or None
        SeaDronesSee meta from the NOISY telemetry (see `sim.noise.TelemetryStream.meta`); None = dropout.
    objects : tuple of ObjectTruth
        Every object of the world (use `visible` for the annotated ones).
    candidates : Candidates
        Pre-NMS detector output.
    blurred : bool
        Whether the detector saw a motion-blurred frame.
    """

    image_id: int
    video_id: int
    uav: str
    frame_index: int
    t: float
    date_time: str
    true_pose: Pose
    meta: dict[str, Any] | None
    objects: tuple[ObjectTruth, ...]
    candidates: Candidates
    blurred: bool


def _rng(*keys: int) -> np.random.Generator:
    return np.random.default_rng([int(k) for k in keys])


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


class Simulation:
    """A deterministic simulation of one scenario.

    Parameters
    ----------
    scenario : Scenario or str
        A scenario or its registry name.
    seed : int
        Non-negative seed; the same seed gives the same frames.
    frames : int, optional
        Frames per video (default: the scenario's `default_frames`).
    noise_scale : float
        Multiplies every telemetry bias, jitter and the time offset (`TelemetryNoise.scaled`); the world,
        flights and detector do not depend on it.

    Attributes
    ----------
    scenario : Scenario
    camera : shared.geo.Camera
    videos : list of VideoInfo
    categories : list of dict
        COCO categories ``[{id: 1, name: "person"}, {id: 2, name: "swimmer"}]``.
    noise : TelemetryNoise
        The scaled noise in use (a UAV with a `UavSetting` of its own: `noise_for`).
    terrain : sim.terrain.SimTerrain or None
        The scenario's terrain for this seed (one for every group: they fly over one place), None = flat.
        The true poses' heights count from the take-off at the world's origin (its elevation on the DEM).
    """

    def __init__(self, scenario: Scenario | str, seed: int = 0, frames: int | None = None,
                 noise_scale: float = 1.0) -> None:
        self.scenario = get_scenario(scenario) if not isinstance(scenario, Scenario) else scenario
        self.seed = _check_seed(seed)
        if frames is None:
            frames = self.scenario.default_frames
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
            raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
        self.frames_per_video = int(frames)
        if isinstance(noise_scale, bool) or not isinstance(noise_scale, (int, float)) \
                or not math.isfinite(noise_scale) or noise_scale < 0:
            raise ValueError(f"noise_scale must be a finite number >= 0, got {noise_scale!r}")
        self.noise_scale = float(noise_scale)
        self.noise: TelemetryNoise = self.scenario.noise.scaled(self.noise_scale)
        self.camera: Camera = self.scenario.camera
        self.categories = [dict(c) for c in CATEGORIES]
        sc = self.scenario
        if sc.simultaneous:
            self._groups = [list(range(len(sc.flights)))]
        else:
            self._groups = [[i] for i in range(len(sc.flights))]
        duration_s = self.frames_per_video / sc.fps
        self.videos: list[VideoInfo] = []
        for g, members in enumerate(self._groups):
            t0 = START_UNIX_S + g * (duration_s + GAP_BETWEEN_FLIGHTS_S)
            for i in members:
                spec = sc.flights[i]
                self.videos.append(VideoInfo(id=i + 1, name=f"{sc.name}_{i + 1:02d}_{spec.kind}_{spec.uav}",
                                             uav=spec.uav, group=g, kind=spec.kind, t0=t0))
        self._objects_per_world = sc.world.n_objects + len(sc.world.fixed_objects)
        self._facts: dict[str, Any] | None = None
        self.terrain: SimTerrain | None = (None if sc.terrain is None else
                                           sc.terrain.build(_rng(self.seed, _ROLE_TERRAIN), sc.world.origin_lat,
                                                            sc.world.origin_lon))
        #: per video id, the take-off's height above the origin's on the terrain (0 over flat ground, or when
        #: every UAV takes off at the origin); the video's true and reported heights count from its take-off
        self.takeoff_up_m: dict[int, float] = dict.fromkeys((v.id for v in self.videos), 0.0)
        if self.terrain is not None and sc.takeoff == "start":
            for v in self.videos:
                start = self._flight(v).state(0.0)
                self.takeoff_up_m[v.id] = float(self.terrain.up_world_m(start.east_m, start.north_m))

    def noise_for(self, uav: str) -> TelemetryNoise:
        """The scaled telemetry noise of `uav` (`Scenario.noise_for` times the noise scale)."""
        return self.scenario.noise_for(uav).scaled(self.noise_scale)

    def frames_of(self, video: VideoInfo) -> int:
        """Frames of one video: every frame_step-th of the scenario's clock (`Scenario.frame_step_for`)."""
        step = self.scenario.frame_step_for(video.uav)
        return (self.frames_per_video + step - 1) // step

    @property
    def n_frames_total(self) -> int:
        """Frames over all videos."""
        return sum(self.frames_of(v) for v in self.videos)

    # ------------------------------------------------------------------ building blocks

    def _world(self, g: int) -> World:
        return World(self.scenario.world, _rng(self.seed, g, _ROLE_WORLD),
                     first_track_id=1 + g * self._objects_per_world)

    def _flight(self, video: VideoInfo) -> Flight:
        spec = self.scenario.flights[video.id - 1]
        return spec.build(_rng(self.seed, video.group, _ROLE_FLIGHT, video.id),
                          self.frames_per_video / self.scenario.fps)

    def _weak(self, params: EmulatorParams, n_obj: int, n_clu: int, g: int, video_id: int) -> np.ndarray | None:
        """Which objects the video's detector sees weakly: a share params.weak_fraction of them (at least one when
        the share is > 0), drawn from a generator of their own; None when the share is 0."""
        if params.weak_fraction <= 0.0 or n_obj == 0:
            return None
        rng = _rng(self.seed, g, _ROLE_WEAK, video_id)
        k = max(1, round(params.weak_fraction * n_obj))
        weak = np.zeros(n_obj + n_clu, dtype=bool)
        weak[rng.choice(n_obj, size=min(k, n_obj), replace=False)] = True
        return weak

    def flights(self) -> dict[int, Flight]:
        """The true trajectory of every video, by video id (flight time 0 = frame 0)."""
        return {v.id: self._flight(v) for v in self.videos}

    # ------------------------------------------------------------------ iteration

    def frames(self) -> Iterator[FrameSample]:
        """Yield every frame: group by group, time step by time step, UAV by UAV.

        Each call restarts the simulation from the seed. After a complete pass, `facts()` describes it.
        """
        sc, cam = self.scenario, self.camera
        wp = sc.world
        image_id = 0
        facts: dict[str, Any] = {"videos": [], "occlusion": [], "trees": [], "clutter": []}
        for g, members in enumerate(self._groups):
            world = self._world(g)
            videos = [self.videos[i] for i in members]
            flights = {v.id: self._flight(v) for v in videos}
            streams = {v.id: TelemetryStream(self.noise_for(v.uav), flights[v.id],
                                             _rng(self.seed, g, _ROLE_TELEMETRY, v.id), wp.origin_lat, wp.origin_lon,
                                             v.t0) for v in videos}
            n_obj, n_clu = world.n, len(world.clutter_east_m)
            # Appearance: one vector per object of the world (all UAVs see the same people), noise per UAV;
            # generators of their own, so boxes and scores do not depend on it.
            looks = (object_appearance(n_obj + n_clu, sc.emulator, _rng(self.seed, g, _ROLE_APPEARANCE))
                     if sc.emulator.appearance_dim > 0 else None)
            params = {v.id: sc.emulator_for(v.uav) for v in videos}
            emulators = {v.id: DetectorEmulator(params[v.id], cam,
                                                _rng(self.seed, g, _ROLE_DETECTOR, v.id), n_obj + n_clu, world.box_m,
                                                world.category_id, appearance=looks,
                                                appearance_rng=_rng(self.seed, g, _ROLE_APPEARANCE, v.id),
                                                weak=self._weak(params[v.id], n_obj, n_clu, g, v.id))
                         for v in videos}
            steps = {v.id: sc.frame_step_for(v.uav) for v in videos}
            keys_all = np.arange(n_obj + n_clu)
            kinds_clutter = np.full(n_clu, KIND_CLUTTER)
            occ_counts = {v.id: np.zeros((n_obj, 3), dtype=np.int64) for v in videos}  # in_view, occluded, visible
            facts["trees"].extend({"group": g, "east_m": t.east_m, "north_m": t.north_m, "radius_m": t.radius_m,
                                   "height_m": t.height_m} for t in world.trees)
            relief = self.terrain
            # each UAV's heights count from its own take-off: the terrain it projects with says where that is
            grounds = {v.id: None if relief is None else
                       Terrain(relief.grid, relief.takeoff_elevation_m + self.takeoff_up_m[v.id]) for v in videos}
            tree_ground = None if relief is None else relief.up_world_m([t.east_m for t in world.trees],
                                                                        [t.north_m for t in world.trees])
            clat, clon = world.clutter_latlon()
            facts["clutter"].extend({"group": g, "lat": float(a), "lon": float(b)}
                                    for a, b in zip(clat, clon, strict=True))
            blurred_counts = dict.fromkeys(flights, 0)
            missing_counts = dict.fromkeys(flights, 0)
            dt = 1.0 / sc.fps
            for f in range(self.frames_per_video):
                if f:
                    world.step(dt)
                t_rel = f * dt
                lat, lon = world.latlon()
                all_lat = np.concatenate([lat, clat])
                all_lon = np.concatenate([lon, clon])
                all_yaw = np.concatenate([world.yaw_deg, world.clutter_yaw_deg])
                all_e = np.concatenate([world.east_m, world.clutter_east_m])
                all_n = np.concatenate([world.north_m, world.clutter_north_m])
                for v in videos:
                    if f % steps[v.id]:
                        continue  # this UAV films at a lower rate
                    st = flights[v.id].state(t_rel)
                    plat, plon = local_to_latlon(st.east_m, st.north_m, wp.origin_lat, wp.origin_lon)
                    meta, _ = streams[v.id].meta(t_rel)
                    pose = Pose(float(plat), float(plon), st.height_m, st.pitch_deg, st.heading_deg,
                                streams[v.id].camera_roll_deg())
                    ground = grounds[v.id]
                    proj = project_objects(all_lat, all_lon, all_yaw, world.box_m, cam, pose, terrain=ground)
                    if relief is None or ground is None:
                        occluded = world.occluded(st.east_m, st.north_m, st.height_m, all_e, all_n,
                                                  world.box_m[2] / 2.0)
                    else:
                        up_m = st.height_m + self.takeoff_up_m[v.id]  # above the origin's take-off
                        clearance = up_m - float(relief.up_world_m(st.east_m, st.north_m))
                        if not clearance >= MIN_CLEARANCE_M:
                            raise ValueError(f"scenario {sc.name!r} seed {self.seed}: {v.name} flies "
                                             f"{clearance:.1f} m above the terrain at {t_rel:.2f} s (at least "
                                             f"{MIN_CLEARANCE_M:g} m): lower the terrain's relief_m")
                        occluded = world.occluded(st.east_m, st.north_m, up_m, all_e, all_n,
                                                  world.box_m[2] / 2.0, ground_m=relief.up_world_m(all_e, all_n),
                                                  tree_ground_m=tree_ground)
                        occluded |= terrain_hidden(all_lat, all_lon, world.box_m[2] / 2.0, pose, ground)
                    in_view = proj.in_view
                    obj_view, obj_occ = in_view[:n_obj], occluded[:n_obj]
                    visible = obj_view & ~obj_occ
                    kinds = np.concatenate([np.where(obj_occ, KIND_OCCLUDED, KIND_OBJECT), kinds_clutter])
                    target = in_view & ~(occluded & (kinds == KIND_CLUTTER))
                    cats = np.full(n_obj + n_clu, world.category_id)
                    emu = emulators[v.id]
                    blurred = emu.is_blurred(st.heading_rate_deg_s)
                    cands = emu.detect(proj.clipped_xyxy[target], keys_all[target], kinds[target], cats[target],
                                       pose, t_rel, blurred)
                    cb = proj.clipped_xyxy
                    objects = tuple(
                        ObjectTruth(
                            track_id=int(world.track_ids[j]), cls=world.cls, category_id=world.category_id,
                            lat=float(lat[j]), lon=float(lon[j]),
                            bbox_xywh=(float(cb[j, 0]), float(cb[j, 1]), float(cb[j, 2] - cb[j, 0]),
                                       float(cb[j, 3] - cb[j, 1])) if obj_view[j] else None,
                            in_view=bool(obj_view[j]), occluded=bool(obj_occ[j]), visible=bool(visible[j]),
                        )
                        for j in range(n_obj)
                    )
                    cnt = occ_counts[v.id]
                    cnt[:, 0] += obj_view
                    cnt[:, 1] += obj_view & obj_occ
                    cnt[:, 2] += visible
                    blurred_counts[v.id] += blurred
                    missing_counts[v.id] += meta is None
                    image_id += 1
                    t_unix = v.t0 + t_rel
                    # only the written frame clock is local time; t and the true poses stay UTC
                    frame_clock = format_frame_time(t_unix, streams[v.id].noise.frame_clock_utc_offset_s)
                    yield FrameSample(image_id=image_id, video_id=v.id, uav=v.uav, frame_index=f // steps[v.id],
                                      t=t_unix, date_time=frame_clock, true_pose=pose, meta=meta, objects=objects,
                                      candidates=cands, blurred=blurred)
            for v in videos:
                weak = emulators[v.id].weak
                facts["videos"].append({
                    "video_id": v.id, "name": v.name, "uav": v.uav, "kind": v.kind, "group": g,
                    "telemetry_bias": streams[v.id].bias, "telemetry_phase_s": streams[v.id].phase_s,
                    "blurred_frames": int(blurred_counts[v.id]), "frames_without_meta": int(missing_counts[v.id]),
                    **({} if weak is None else {"weak_track_ids": [int(k) for k in world.track_ids[weak[:n_obj]]]}),
                    **({"takeoff_elevation_m": round(relief.takeoff_elevation_m + self.takeoff_up_m[v.id], 4)}
                       if relief is not None and sc.takeoff != "origin" else {}),
                })
            facts["occlusion"].extend(_occlusion_facts(videos, occ_counts, world.track_ids))
        if self.terrain is not None:
            facts["terrain"] = self.terrain.facts()
        self._facts = facts
        logger.debug("simulation %s seed %d: %d frames", sc.name, self.seed, image_id)

    def facts(self) -> dict[str, Any]:
        """Facts gathered during the last complete `frames()` pass.

        Keys: ``videos`` (realised telemetry biases, blurred and meta-less frame counts per video; over a terrain
        with the scenario's takeoff "start", each video's ``takeoff_elevation_m`` on the DEM),
        ``occlusion`` (objects that one UAV of a group sees only behind a tree while another sees them),
        ``trees``, ``clutter`` (and ``terrain``, `SimTerrain.facts`, over a terrain). Raises RuntimeError before
        a complete pass.
        """
        if self._facts is None:
            raise RuntimeError("Simulation.facts() needs a complete pass over frames() first")
        return self._facts


def _occlusion_facts(videos: list[VideoInfo], counts: dict[int, np.ndarray], track_ids: np.ndarray) -> list[dict]:
    """Objects occluded in one UAV's view (in view behind a tree, never visible) yet visible to another UAV."""
    out = []
    for v in videos:
        for w in videos:
            if v.id == w.id:
                continue
            cv, cw = counts[v.id], counts[w.id]
            hit = (cv[:, 1] > 0) & (cv[:, 2] == 0) & (cw[:, 2] > 0)
            for j in np.flatnonzero(hit):
                out.append({"track_id": int(track_ids[j]), "occluded_for": v.uav, "occluded_video_id": v.id,
                            "visible_for": w.uav, "visible_video_id": w.id,
                            "frames_occluded_in_view": int(cv[j, 1]), "frames_visible_other": int(cw[j, 2])})
    return out

"""Scenario registry: named, frozen bundles of world, flights, telemetry noise and detector emulator settings.

`SCENARIOS` maps a name to a `Scenario`; `get_scenario(name)` looks one up and lists the valid names
when the name is unknown. Scenarios: ``sea`` (swimmers, SeaDronesSee-like), ``sea-hard`` (the same at the
anomaly paper's per-frame difficulty: higher, rougher, hazier), ``grass`` (people walking,
POG-like), ``coop`` (two UAVs over one scene, a tree line hides several people from the far one), ``reid``
(objects leave and re-enter the view), ``trio`` (three UAVs over one meadow for `uavmm demo`), ``hills`` (the
meadow on hills, with its DEM), ``coop-slope`` (two UAVs on opposite sides of a slope, each launched from its
own side, with the DEM).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from shared.geo import CAMERA_PRESETS, Camera
from sim.detector_emulator import EmulatorParams
from sim.flight import ClimbSpec, FlightSpec, HoverSweepsSpec, LawnmowerSpec, LineSpec, OrbitSpec
from sim.noise import TelemetryNoise
from sim.sea_state import SeaState
from sim.terrain import TerrainSpec
from sim.world import Tree, WorldParams

#: UNIX time of the first frame of every scenario: 2023-06-01T10:00:00Z.
START_UNIX_S = 1685613600.0
#: Pause between consecutive flights of one scenario (seconds).
GAP_BETWEEN_FLIGHTS_S = 60.0
#: Where a scenario's UAVs take off (their heights count from there): all at the world's origin, or each on the
#: ground under its flight's first position (only a terrain makes the two differ).
TAKEOFF_SITES = ("origin", "start")
#: Longest image side the simulated camera may have (`uavmm sim --image-size`) and the renderer draws: 8K (a frame of
#: 7680x4320 takes ~2.8 GB to draw; one of 100000x100000 asked 224 GiB and ended in a MemoryError traceback).
MAX_IMAGE_SIDE_PX = 8192
#: Most frames per video `uavmm sim --frames` (also with --render) and `uavmm eval --frames` take: 20 minutes at the
#: scenarios' 30 fps, a battery's flight and twice the longest default (trio's 18000). A dataset is held in memory
#: until written, ~80 kB an image: `sea`'s three videos at the cap peak at ~8.5 GB; 10**9 ran for days.
MAX_FRAMES_PER_VIDEO = 36_000


def check_frames_per_video(frames: int | None, flag: str) -> None:
    """ValueError naming `flag` unless `frames` is None (the scenario's default) or in 1..`MAX_FRAMES_PER_VIDEO`:
    the one check of `uavmm sim --frames` and `uavmm eval --frames`, made before any work."""
    if frames is not None and not 1 <= frames <= MAX_FRAMES_PER_VIDEO:
        raise ValueError(f"{flag} must be in 1..{MAX_FRAMES_PER_VIDEO} (frames per video), got {frames}")


@dataclass(frozen=True, slots=True)
class UavSetting:
    """What differs for one UAV of a scenario (the cooperative domains' per-UAV conditions, `sim.coop_domains`).

    uav: the flight's UAV id. noise: `TelemetryNoise` fields replaced on the scenario's noise for this UAV (its
    own GPS, heading and height bias levels, its telemetry lag; before the run's noise scale). emulator:
    `EmulatorParams` fields replaced on the scenario's emulator for this UAV's detector (more or less confident,
    a share of the objects seen weakly as through glare: ``weak_fraction``, ``weak_logit_drop``). frame_step:
    this UAV keeps every frame_step-th frame of the scenario's clock (15 fps at 30 with 2).
    """

    uav: str
    noise: dict[str, Any] = field(default_factory=dict)
    emulator: dict[str, Any] = field(default_factory=dict)
    frame_step: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.uav, str) or not self.uav:
            raise ValueError(f"UavSetting: uav must be a non-empty string, got {self.uav!r}")
        if isinstance(self.frame_step, bool) or not isinstance(self.frame_step, int) or self.frame_step < 1:
            raise ValueError(f"UavSetting {self.uav!r}: frame_step must be an integer >= 1, got {self.frame_step!r}")
        for name, cls in (("noise", TelemetryNoise), ("emulator", EmulatorParams)):
            unknown = sorted(set(getattr(self, name)) - {f.name for f in dataclasses.fields(cls)})
            if unknown:
                raise ValueError(f"UavSetting {self.uav!r}: unknown {name} field(s) {', '.join(unknown)}")
        dataclasses.replace(TelemetryNoise(), **self.noise)  # the values are checked by the classes themselves
        dataclasses.replace(EmulatorParams(), **self.emulator)


@dataclass(frozen=True, slots=True)
class Scenario:
    """A named simulation setting.

    Attributes
    ----------
    name, description : str
    world : WorldParams
        The scene (one world per flight, or one shared world when `simultaneous`).
    flights : tuple of flight specs
        One video per flight; each spec names its UAV id.
    simultaneous : bool
        True: all flights fly at the same time over one world with one clock (cooperative UAVs).
        False: flights are separate videos one after another, each over its own world.
    noise : TelemetryNoise
        Telemetry noise at scale 1.
    emulator : EmulatorParams
        Detector emulator knobs.
    default_frames : int
        Frames per video when none are requested.
    fps : float
        Frame rate (30).
    camera_preset : str
        A `shared.geo.CAMERA_PRESETS` name; the image is `image_size` (3840 x 2160).
    sea_state : SeaState or None
        How rough and murky the renderer draws the sea (`sim.sea_state`); None = the calm sea (and
        nothing written to truth.json, so existing datasets stay byte-identical).
    terrain : TerrainSpec or None
        The ground's relief (`sim.terrain`: hills, a slope, a step), drawn per seed; the dataset gets dem.npz.
        None = flat ground (nothing written to truth.json).
    uav_settings : tuple of UavSetting
        Per-UAV telemetry, detector and frame rate (`noise_for`, `emulator_for`, `frame_step_for`); () = every
        UAV as the scenario (nothing written to truth.json).
    takeoff : str
        Where the UAVs take off, one of `TAKEOFF_SITES`: "origin" (all at the scene's centre, the default) or
        "start" (each under its flight's first position, as operators launching from their own side of a
        slope); over a terrain each video's heights count from its take-off's elevation (truth.json's
        videos[i].takeoff_elevation_m).
    """

    name: str
    description: str
    world: WorldParams
    flights: tuple[FlightSpec, ...]
    simultaneous: bool = False
    noise: TelemetryNoise = field(default_factory=TelemetryNoise)
    emulator: EmulatorParams = field(default_factory=EmulatorParams)
    default_frames: int = 600
    fps: float = 30.0
    camera_preset: str = "dji-mavic2-pro"
    image_size: tuple[int, int] = (3840, 2160)
    sea_state: SeaState | None = None
    terrain: TerrainSpec | None = None
    uav_settings: tuple[UavSetting, ...] = ()
    takeoff: str = "origin"

    def __post_init__(self) -> None:
        if self.takeoff not in TAKEOFF_SITES:
            raise ValueError(f"Scenario {self.name!r}: takeoff={self.takeoff!r} is not one of "
                             f"{', '.join(TAKEOFF_SITES)}")
        if not self.flights:
            raise ValueError(f"Scenario {self.name!r} has no flights")
        if self.camera_preset not in CAMERA_PRESETS:
            raise ValueError(f"Scenario {self.name!r}: unknown camera preset {self.camera_preset!r}")
        if self.default_frames < 1 or self.fps <= 0:
            raise ValueError(f"Scenario {self.name!r}: default_frames must be >= 1 and fps > 0")
        uavs = [f.uav for f in self.flights]
        if self.simultaneous and len(set(uavs)) != len(uavs):
            raise ValueError(f"Scenario {self.name!r}: simultaneous flights need distinct UAV ids, got {uavs}")
        named = [u.uav for u in self.uav_settings]
        if len(set(named)) != len(named) or not set(named) <= set(uavs):
            raise ValueError(f"Scenario {self.name!r}: uav_settings name UAVs {named}; each at most once and "
                             f"one of the flights' {sorted(set(uavs))}")

    def _setting(self, uav: str) -> UavSetting | None:
        return next((u for u in self.uav_settings if u.uav == uav), None)

    def noise_for(self, uav: str) -> TelemetryNoise:
        """The telemetry noise of `uav` at scale 1 (the scenario's, with its UavSetting's fields)."""
        setting = self._setting(uav)
        return self.noise if setting is None else dataclasses.replace(self.noise, **setting.noise)

    def emulator_for(self, uav: str) -> EmulatorParams:
        """The detector emulator of `uav` (the scenario's, with its UavSetting's fields)."""
        setting = self._setting(uav)
        return self.emulator if setting is None else dataclasses.replace(self.emulator, **setting.emulator)

    def frame_step_for(self, uav: str) -> int:
        """`uav` keeps every frame_step-th frame of the scenario's clock (1 unless its UavSetting says)."""
        setting = self._setting(uav)
        return 1 if setting is None else setting.frame_step

    @property
    def n_videos(self) -> int:
        """Number of videos (= flights)."""
        return len(self.flights)

    @property
    def camera(self) -> Camera:
        """The scenario's camera (`shared.geo.Camera.from_preset`)."""
        return Camera.from_preset(self.camera_preset, *self.image_size)


_SEA = Scenario(
    name="sea",
    description="Swimmers drifting in a current on Lake Constance (SeaDronesSee-like): orbit, hover with "
                "heading sweeps and lawnmower flights at 20-80 m, pitch 20-90 deg; 1 % of frames lack meta.",
    world=WorldParams(origin_lat=47.6, origin_lon=9.3, cls="swimmer", n_objects=14, spawn_radius_m=35.0,
                      n_clutter=3, clutter_radius_m=35.0),
    flights=(
        OrbitSpec(radius_m=(45.0, 70.0), height_m=(30.0, 60.0)),
        HoverSweepsSpec(height_m=(20.0, 45.0), pitch_deg=(25.0, 45.0)),
        LawnmowerSpec(height_m=(40.0, 80.0), pitch_deg=(70.0, 90.0)),
    ),
    noise=TelemetryNoise(missing_meta_rate=0.01),
    # Small swimmers, but glare and wave crests give many confident false positives (SeaDronesSee: AP50 ~68).
    emulator=EmulatorParams(logit_at_32px=2.8, fp_confusing_frac=0.5),
)

# Sea-hard: the paper's difficulty (OpenWater: a per-frame autoencoder finds ~71 % of the objects at a 5 %
# broadcasting rate), where `sea` is far easier (~99-100 %). The same swimmers, buoys and boats, seen higher
# up and on a rougher, hazier sea: flights at 50-100 m (swimmers ~4-10 px at 1280x720), a strong breeze's
# whitecaps (~2 % of the sea, Beaufort 6) and the foam they leave, more glitter, sea haze (0.8-3 km), a soft
# lens (1.5 mrad) and swimmers lower in the water. Its knobs were chosen on the per-frame figures of seeds 0
# and 1 alone (docs/anomaly.md, "Paper-difficulty sea (sea-hard)").
SEA_HARD_STATE = SeaState(whitecap_rate=10.0, sparkle_rate=4.0, glint_gain=1.6, visibility_scale=0.2,
                          swimmer_wash=0.6, foam_rate=0.05, blur_mrad=1.5)
_SEA_HARD = Scenario(
    name="sea-hard",
    description="The sea scenario at the paper's per-frame anomaly difficulty: higher flights (50-100 m), a "
                "rough sea (10x the whitecaps, residual foam, more glitter), sea haze, a soft lens and swimmers "
                "lower in the water.",
    world=_SEA.world,
    flights=(
        OrbitSpec(radius_m=(55.0, 80.0), height_m=(55.0, 85.0)),
        HoverSweepsSpec(height_m=(50.0, 75.0), pitch_deg=(40.0, 60.0)),
        LawnmowerSpec(height_m=(75.0, 100.0), pitch_deg=(70.0, 90.0)),
    ),
    noise=_SEA.noise,
    emulator=_SEA.emulator,
    sea_state=SEA_HARD_STATE,
)

_GRASS = Scenario(
    name="grass",
    description="People walking on a meadow near Tuebingen with trees (POG-like): orbit, hover with heading "
                "sweeps, lawnmower and climb/descend flights at 12-90 m, pitch 20-90 deg.",
    world=WorldParams(origin_lat=48.53, origin_lon=9.06, cls="person", n_objects=14, spawn_radius_m=35.0,
                      boundary_radius_m=45.0, n_trees=6, n_clutter=3, clutter_radius_m=35.0),
    flights=(
        OrbitSpec(radius_m=(40.0, 70.0), height_m=(25.0, 60.0)),
        HoverSweepsSpec(height_m=(20.0, 50.0), pitch_deg=(25.0, 45.0)),
        LawnmowerSpec(height_m=(40.0, 70.0), pitch_deg=(70.0, 90.0)),
        ClimbSpec(),
    ),
    emulator=EmulatorParams(logit_at_32px=1.7, fp_confusing_frac=0.12),
)

# Coop: the paper's 2AVs setting (two UAVs over one meadow at the same time, one view far, oblique and
# blocked by trees). A tree line of four trees (crowns 2.4 m, 8 m tall, 4.5 m apart) runs east-west 12 m
# south of the scene centre. uav1 hovers ~80 m south of the centre at 25-30 m looking north at a grazing
# 18-22 deg (people ~30 px), so the line hides a band ~14 m wide and ~25 m deep behind it: three people
# who stand still in the shade behind the trees (track 1 at the front) are hidden from uav1 for the whole
# flight, and walkers are hidden whenever they cross the band. The foliage is dense: a hidden person still
# gives a weak detector signal (logit lowered by 5, the paper's occluded person scored 4.3 AP50 with a
# single-view tracker), mostly below the detector's output threshold. uav2 flies east-west ~40 m north
# of the centre at 25-30 m, pitch 35-42 deg, and sees the people behind the line in front of the trees
# (people south of the line are hidden from it instead).
_COOP_TREE_LINE = tuple(Tree(east, -12.0, 2.4, 8.0) for east in (-6.75, -2.25, 2.25, 6.75))
_COOP = Scenario(
    name="coop",
    description="Two UAVs over one meadow at the same time (the paper's 2AVs): uav1 far (~80 m) and oblique "
                "(18-22 deg) looking north across a tree line that hides three resting people (track 1 first) "
                "and passing walkers from it for long stretches; uav2 closer (~40 m) from the north sees them.",
    world=WorldParams(origin_lat=48.5312, origin_lon=9.0585, cls="person", n_objects=10, spawn_radius_m=25.0,
                      boundary_radius_m=30.0, n_trees=1, n_clutter=2, clutter_radius_m=25.0,
                      fixed_trees=_COOP_TREE_LINE,
                      fixed_objects=((1.0, -4.0, True), (-5.0, -6.0, True), (6.0, -7.0, True))),
    flights=(
        HoverSweepsSpec(uav="uav1", bearing_deg=(180.0, 180.0), distance_m=(75.0, 85.0), height_m=(25.0, 30.0),
                        pitch_deg=(18.0, 22.0), sweep_deg=(8.0, 15.0), sweep_rate_deg_s=(10.0, 20.0),
                        dwell_s=(3.0, 6.0)),
        LineSpec(uav="uav2", bearing_deg=(0.0, 0.0), distance_m=(35.0, 45.0), height_m=(25.0, 30.0),
                 pitch_deg=(35.0, 42.0)),
    ),
    simultaneous=True,
    default_frames=900,
    emulator=EmulatorParams(logit_at_32px=1.7, fp_confusing_frac=0.12, occluded_logit_drop=5.0),
)

_REID = Scenario(
    name="reid",
    description="People walking out of view and back while a hovering UAV makes fast heading sweeps "
                "(long-term re-identification); 1 % of frames lack meta.",
    world=WorldParams(origin_lat=48.5295, origin_lon=9.0620, cls="person", n_objects=10, spawn_radius_m=30.0,
                      boundary_radius_m=55.0, n_trees=3, n_clutter=2, clutter_radius_m=30.0,
                      sharp_turn_rate_hz=0.08),
    flights=(
        HoverSweepsSpec(height_m=(20.0, 35.0), pitch_deg=(25.0, 40.0), sweep_deg=(70.0, 110.0),
                        sweep_rate_deg_s=(70.0, 110.0), dwell_s=(2.5, 5.0)),
        HoverSweepsSpec(height_m=(25.0, 45.0), pitch_deg=(30.0, 45.0), sweep_deg=(60.0, 100.0),
                        sweep_rate_deg_s=(60.0, 100.0), dwell_s=(3.0, 6.0)),
    ),
    noise=TelemetryNoise(missing_meta_rate=0.01),
    default_frames=900,
    emulator=EmulatorParams(logit_at_32px=1.7, fp_confusing_frac=0.12),
)

# Trio: the `uavmm demo` scene. Three UAVs fly at the same time over one meadow with people walking: uav1
# orbits the scene, uav2 hovers south-east of it with gentle heading sweeps, uav3 flies back and forth along a
# north-south line just west of the centre, looking down steeply. Every flight stays over the scene however
# long it lasts (a lawnmower would drift away lane by lane), and the footprints overlap around the centre,
# so the joint map fuses two or three views there. Ten minutes by default; `uavmm demo` plays it with
# --loop so it runs until stopped.
_TRIO = Scenario(
    name="trio",
    description="Three UAVs over one meadow at the same time (orbit, hover with sweeps, steep line) with "
                "people walking: the scene of `uavmm demo`.",
    world=WorldParams(origin_lat=48.5335, origin_lon=9.0555, cls="person", n_objects=12, spawn_radius_m=30.0,
                      boundary_radius_m=38.0, n_trees=3, n_clutter=2, clutter_radius_m=30.0),
    flights=(
        OrbitSpec(uav="uav1", radius_m=(50.0, 55.0), height_m=(35.0, 40.0), speed_mps=(3.0, 3.5),
                  pitch_offset_deg=(-2.0, 2.0)),
        HoverSweepsSpec(uav="uav2", bearing_deg=(130.0, 140.0), distance_m=(45.0, 50.0), height_m=(30.0, 35.0),
                        pitch_deg=(32.0, 38.0), sweep_deg=(15.0, 25.0), sweep_rate_deg_s=(10.0, 15.0),
                        dwell_s=(4.0, 8.0)),
        LineSpec(uav="uav3", bearing_deg=(265.0, 275.0), distance_m=(15.0, 20.0), half_length_m=(30.0, 35.0),
                 height_m=(45.0, 50.0), pitch_deg=(70.0, 78.0), speed_mps=(2.5, 3.5)),
    ),
    simultaneous=True,
    default_frames=18_000,
    emulator=EmulatorParams(logit_at_32px=1.7, fp_confusing_frac=0.12),
)

# Hills: the grass meadow on hills and hollows up to ~12 m (sim.terrain), for trying `--dem`: the dataset gets
# dem.npz, and truth.json's terrain.takeoff_elevation_m is the --takeoff-elevation-m of its flights.
_HILLS = Scenario(
    name="hills",
    description="People walking on a hilly meadow (hills and hollows up to ~12 m, the DEM written as dem.npz): "
                "orbit and an oblique line flight at 25-60 m, pitch 30-45 deg; heights above the take-off.",
    world=_GRASS.world,
    flights=(
        OrbitSpec(radius_m=(40.0, 70.0), height_m=(25.0, 60.0)),
        LineSpec(bearing_deg=(0.0, 360.0), distance_m=(40.0, 55.0), height_m=(25.0, 40.0), pitch_deg=(30.0, 45.0)),
    ),
    emulator=_GRASS.emulator,
    terrain=TerrainSpec("hills", relief_m=12.0),
)

# Coop-slope: two UAVs on opposite sides of a meadow slope (rising 10 m per 100 m to the north), each launched
# from its own side: uav1 hovers ~55 m south at the foot (its take-off ~5.5 m below the scene's centre) looking
# up the slope at 30-35 deg with gentle heading sweeps; uav2 flies east-west ~55 m north near the top (take-off
# ~5.5 m above the centre) looking down it at 36-42 deg. Ten people stand still on the slope across both views
# (heights -2.5 .. +2 m about the centre), three more walk. Over flat earth each UAV projects them onto the plane
# of its own take-off: uav1 from below puts them metres up the slope, uav2 from above a few metres up the slope
# too but by other amounts, so the joint map splits each person; with the DEM (dem.npz, truth.json's per-video
# take-off elevations) both put them where they stand (`uavmm eval --tasks coop --scenarios coop-slope`).
_COOP_SLOPE_PEOPLE = ((-12.0, -18.0, True), (-3.0, -14.0, True), (9.0, -11.0, True), (-9.0, -4.0, True),
                      (3.0, -2.0, True), (13.0, 3.0, True), (-14.0, 8.0, True), (-2.0, 11.0, True),
                      (8.0, 15.0, True), (1.0, 20.0, True))
_COOP_SLOPE = Scenario(
    name="coop-slope",
    description="Two UAVs on opposite sides of a meadow slope (10 m per 100 m, the DEM written as dem.npz), each "
                "launched from its own side: uav1 ~55 m below hovering at 35-42 m looking up at 30-35 deg, uav2 "
                "~55 m above flying east-west at 35-42 m looking down at 36-42 deg; ten people standing on the "
                "slope, three walking. Heights above each UAV's own take-off.",
    world=WorldParams(origin_lat=48.5348, origin_lon=9.0610, cls="person", n_objects=3, spawn_radius_m=18.0,
                      boundary_radius_m=22.0, n_trees=0, n_clutter=2, clutter_radius_m=22.0,
                      fixed_objects=_COOP_SLOPE_PEOPLE),
    flights=(
        HoverSweepsSpec(uav="uav1", bearing_deg=(180.0, 180.0), distance_m=(52.0, 58.0), height_m=(35.0, 42.0),
                        pitch_deg=(30.0, 35.0), sweep_deg=(5.0, 12.0), sweep_rate_deg_s=(8.0, 15.0),
                        dwell_s=(3.0, 6.0)),
        LineSpec(uav="uav2", bearing_deg=(0.0, 0.0), distance_m=(52.0, 58.0), half_length_m=(10.0, 20.0),
                 height_m=(35.0, 42.0), pitch_deg=(36.0, 42.0), speed_mps=(1.5, 2.5)),
    ),
    simultaneous=True,
    default_frames=900,
    emulator=_GRASS.emulator,
    terrain=TerrainSpec("slope", relief_m=10.0, aspect_deg=0.0),
    takeoff="start",
)

#: All scenarios by name.
SCENARIOS: dict[str, Scenario] = {s.name: s for s in (_SEA, _SEA_HARD, _GRASS, _COOP, _REID, _TRIO, _HILLS,
                                                      _COOP_SLOPE)}


def get_scenario(name: str) -> Scenario:
    """The scenario called `name`; ValueError listing the valid names if there is none."""
    try:
        return SCENARIOS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown scenario {name!r}; valid scenarios: {', '.join(sorted(SCENARIOS))}") from None

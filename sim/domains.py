"""Evaluation domains: scenarios shifted the way real data differs from our simulator, split into the
domains parameters are tuned on and held-out ones nobody tunes to.

A `Domain` takes a base scenario (`sim.scenarios`) and changes what a new user's data changes: the
telemetry's defects (white per-frame jitter, GPS rounded to 4-6 decimals, altitude steps, constant or
drifting time offsets), the frame rate (24/30/60 fps), the clip length, the detector's regime (over- or
under-confident scores, more or less persistent clutter at fixed ground spots, more part boxes) and the
camera (the base 4K Mavic 2 Pro, a 1080p wide camera, a 4K 70 mm tele). Each domain flies gentle flights
(orbit, lawnmower, line), heading sweeps (hover with fast sweeps) or view jumps (a hover whose heading jumps
60 deg away and back every ~3 s, so objects leave the view and return: long-term re-ID), so tracking can be
judged per kind. Real detectors' outputs carry no appearance descriptor: `descriptors=False` drops the
emulator's `embedding` field (the same boxes and scores). `DOMAINS` lists them; `TUNING_DOMAINS` and
`HELDOUT_DOMAINS` are the split: every default and design choice of the memory map, the telemetry correction
and the tracker is chosen on the tuning domains (and the base scenarios); the held-out ones are only reported.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypedDict, TypeVar

from sim.detector_emulator import EmulatorParams
from sim.flight import HoverSweepsSpec, LawnmowerSpec, LineSpec, OrbitSpec
from sim.noise import TelemetryNoise
from sim.scenarios import Scenario, get_scenario
from sim.terrain import TerrainSpec
from sim.world import WorldParams

T = TypeVar("T")
SPLITS = ("tune", "heldout")
MOTIONS = ("gentle", "sweeps", "jumps")
#: Cameras of the domains: name -> (shared.geo preset, width, height).
CAMERAS: dict[str, tuple[str, int, int]] = {
    "4k": ("dji-mavic2-pro", 3840, 2160),
    "1080p-wide": ("dji-m30-wide", 1920, 1080),
    "4k-tele": ("dji-mavic3pro-tele", 3840, 2160),
}


@dataclass(frozen=True, slots=True)
class Domain:
    """One evaluation domain (see the module docstring).

    Attributes
    ----------
    name, description : str
    split : str
        "tune" or "heldout".
    motion : str
        "gentle", "sweeps" (heading sweeps) or "jumps" (60 deg view jumps away and back, re-ID): which
        tracking bars apply.
    base : str
        Base scenario (its world, class and emulator defaults).
    flights : tuple of flight specs
    fps : float
    clip_s : float
        Clip length in seconds (frames = round(clip_s * fps)); `--full` evaluates 5x longer clips.
    camera : str
        A key of CAMERAS.
    noise : dict
        TelemetryNoise fields replaced on the base scenario's noise.
    emulator : dict
        EmulatorParams fields replaced on the base scenario's emulator.
    world : dict
        WorldParams fields replaced on the base scenario's world.
    final_score : float or None
        The detector's final output instead of its pre-NMS candidates (what most users have: per-class NMS at
        IoU 0.5, scores >= final_score; `final_output`); None: the candidates.
    terrain : TerrainSpec or None
        The ground's relief (`sim.terrain`); the dataset gets dem.npz and the evaluation runs our variants with
        and without it (flat earth vs --dem) and on the same flights over flat ground (`flat_twin`).
    descriptors : bool
        The candidates carry the emulator's appearance descriptors (`embedding` in pre_nms.json); False: none,
        as a real detector's output (EmulatorParams.appearance_dim 0; boxes and scores are the same).
    """

    name: str
    description: str
    split: str
    motion: str
    base: str
    flights: tuple[Any, ...]
    fps: float = 30.0
    clip_s: float = 8.0
    camera: str = "4k"
    noise: dict[str, Any] = field(default_factory=dict)
    emulator: dict[str, Any] = field(default_factory=dict)
    world: dict[str, Any] = field(default_factory=dict)
    final_score: float | None = None
    terrain: TerrainSpec | None = None
    descriptors: bool = True

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"Domain {self.name!r}: split must be one of {SPLITS}, got {self.split!r}")
        if self.motion not in MOTIONS:
            raise ValueError(f"Domain {self.name!r}: motion must be one of {MOTIONS}, got {self.motion!r}")
        if self.camera not in CAMERAS:
            raise ValueError(f"Domain {self.name!r}: unknown camera {self.camera!r}; valid: {', '.join(CAMERAS)}")
        if not (math.isfinite(self.fps) and self.fps > 0 and math.isfinite(self.clip_s) and self.clip_s > 0):
            raise ValueError(f"Domain {self.name!r}: fps and clip_s must be > 0")
        if self.final_score is not None and not (0.0 <= self.final_score < 1.0):
            raise ValueError(f"Domain {self.name!r}: final_score must be in [0, 1), got {self.final_score!r}")
        self.scenario()  # every field name and value is checked by the dataclasses it builds

    def frames(self, full: bool = False) -> int:
        """Frames per video: the clip length at the domain's frame rate (5x with full)."""
        return max(1, round(self.clip_s * (5.0 if full else 1.0) * self.fps))

    def scenario(self) -> Scenario:
        """The domain as a Scenario (name = the domain's name)."""
        base = get_scenario(self.base)
        preset, width, height = CAMERAS[self.camera]
        noise: TelemetryNoise = dataclasses.replace(base.noise, **self.noise)
        emulator: EmulatorParams = dataclasses.replace(base.emulator, **self.emulator)
        if not self.descriptors:
            emulator = dataclasses.replace(emulator, appearance_dim=0)
        world: WorldParams = dataclasses.replace(base.world, **self.world)
        return dataclasses.replace(base, name=self.name, description=self.description, world=world,
                                   flights=self.flights, simultaneous=False, noise=noise, emulator=emulator,
                                   default_frames=self.frames(), fps=self.fps, camera_preset=preset,
                                   image_size=(width, height), terrain=self.terrain)

    def flat_twin(self) -> Domain:
        """The same domain over flat ground: the same worlds, flights, telemetry and detector per seed (the
        terrain draws from a generator of its own), named <name>-flat."""
        return dataclasses.replace(self, name=f"{self.name}-flat", description=f"{self.description} (flat twin)",
                                   terrain=None)

    def changes(self) -> dict[str, Any]:
        """What differs from the base scenario (noise, emulator and world fields; the final output)."""
        extra: dict[str, Any] = {} if self.final_score is None else {
            "final_output": f"NMS 0.5, scores >= {self.final_score:g}"}
        if self.terrain is not None:
            extra["terrain"] = f"{self.terrain.kind} {self.terrain.relief_m:g} m"
        if not self.descriptors:
            extra["descriptors"] = "none"
        return {**self.noise, **self.emulator, **self.world, **extra}

    @property
    def tag(self) -> str:
        """Short hash of the definition: dataset caches keyed by it regenerate when a domain changes."""
        text = repr(self)
        for later in ("final_score", "terrain"):  # fields that came later: domains without them keep their tags
            if getattr(self, later) is None:
                text = text.replace(f", {later}=None", "")
        if self.descriptors:
            text = text.replace(", descriptors=True", "")
        text = text.replace(", min_pitch_deg=17.0)", ")")  # HoverSweepsSpec's later fields at their defaults
        text = text.replace(", min_turn_s=0.2)", ")")
        text = text.replace(", aspect_deg=None", "")  # TerrainSpec's later field: the terrain domains keep theirs
        return hashlib.sha1(text.encode()).hexdigest()[:8]

    def summary(self) -> str:
        """One line: split, motion, fps, clip, camera and what differs from the base scenario."""
        changes = ", ".join(f"{k}={v}" for k, v in self.changes().items())
        return (f"{self.split:7s} {self.motion:6s} {self.base:5s} {self.fps:g} fps {self.clip_s:g} s "
                f"{self.camera}: {changes}")


# Telemetry profiles (replacements of TelemetryNoise fields).
#: A DJI log at the frame rate whose gimbal angles and GPS jitter frame to frame (white), 6 decimals.
_JITTER: dict[str, Any] = {"white_gps_m": 0.5, "white_heading_deg": 0.6, "white_pitch_deg": 0.4,
                           "gps_decimals": 6, "camera_roll_deg": 0.3}
#: 5-decimal GPS (1.1 m steps), 0.5 m altitude steps.
_GPS5: dict[str, Any] = {"gps_decimals": 5, "altitude_step_m": 0.5}
#: An old DJI SRT: 4-decimal GPS (11 m steps north, 7 m east at 48 N), whole-metre altitude, the video
#: 0.3 s ahead of its subtitle track.
_OLD_SRT: dict[str, Any] = {"gps_decimals": 4, "altitude_step_m": 1.0, "time_offset_s": 0.3}
#: Clocks drifting apart: 0.1 s offset at the start, growing 0.02 s per second.
_DRIFT: dict[str, Any] = {"time_offset_s": 0.1, "time_offset_drift": 0.02}
#: SeaDronesSee Object Detection v2's clocks: a 10 Hz flight log in its own column names, stamped in UTC at
#: whole seconds, beside frames stamped in local time two hours ahead (CEST).
_SDS_CLOCKS: dict[str, Any] = {"meta_layout": "flight_log", "stamp_resolution_s": 1.0,
                               "frame_clock_utc_offset_s": 7200.0}
#: The telemetry both clock domains share (values and timing), so the twins differ in their clocks alone.
_SDS_TELEMETRY: dict[str, Any] = {"telemetry_hz": 10.0, "time_offset_s": 0.05}

# Detector regimes (replacements of EmulatorParams fields).
_OVERCONFIDENT: dict[str, Any] = {"score_logit_scale": 1.6, "score_logit_shift": 0.8}
_UNDERCONFIDENT: dict[str, Any] = {"score_logit_scale": 0.6, "score_logit_shift": -0.4}
_MORE_CLUTTER_EMU: dict[str, Any] = {"clutter_detect_prob": 0.85, "clutter_logit_drop": 1.5}
_MORE_PARTS: dict[str, Any] = {"duplicate_box_rate": 0.25, "duplicate_score_range": (0.2, 0.7)}

_GENTLE_SEA = (OrbitSpec(radius_m=(45.0, 70.0), height_m=(30.0, 60.0)),
               LawnmowerSpec(height_m=(40.0, 80.0), pitch_deg=(70.0, 90.0)))
_GENTLE_GRASS = (OrbitSpec(radius_m=(40.0, 70.0), height_m=(25.0, 60.0)),
                 LineSpec(bearing_deg=(0.0, 360.0), distance_m=(40.0, 55.0), height_m=(25.0, 40.0),
                          pitch_deg=(30.0, 45.0)))
_SWEEPS = (HoverSweepsSpec(height_m=(20.0, 40.0), pitch_deg=(25.0, 40.0), sweep_deg=(50.0, 100.0),
                           sweep_rate_deg_s=(60.0, 100.0), dwell_s=(1.5, 3.0)),
           HoverSweepsSpec(height_m=(25.0, 45.0), pitch_deg=(30.0, 45.0), sweep_deg=(30.0, 80.0),
                           sweep_rate_deg_s=(40.0, 90.0), dwell_s=(2.0, 4.0)))
#: Gentle flights whose camera turns like a pilot panning (5-15 deg/s): a hover panning 20-45 deg to the
#: sides at a peak rate of 5-15 deg/s, and a tight orbit (4.9-11.5 deg/s), so the telemetry's timing matters.
_PANNING_SEA = (HoverSweepsSpec(distance_m=(40.0, 60.0), height_m=(25.0, 45.0), pitch_deg=(30.0, 45.0),
                                sweep_deg=(20.0, 45.0), sweep_rate_deg_s=(5.0, 15.0), dwell_s=(1.0, 2.5)),
                OrbitSpec(radius_m=(25.0, 35.0), height_m=(25.0, 45.0), speed_mps=(3.0, 5.0)))
_TELE_SWEEPS = (HoverSweepsSpec(distance_m=(60.0, 80.0), height_m=(30.0, 50.0), pitch_deg=(25.0, 35.0),
                                sweep_deg=(20.0, 50.0), sweep_rate_deg_s=(30.0, 60.0), dwell_s=(1.5, 3.0)),
                HoverSweepsSpec(distance_m=(50.0, 70.0), height_m=(30.0, 45.0), pitch_deg=(30.0, 40.0),
                                sweep_deg=(30.0, 60.0), sweep_rate_deg_s=(40.0, 80.0), dwell_s=(2.0, 3.0)))
#: View jumps (long-term re-ID): a hover whose heading jumps 60 deg to one side at 200-400 deg/s (0.25-0.45 s),
#: dwells ~3 s, jumps back, dwells, jumps to the other side, ...: what the view showed leaves it and returns
#: every ~3-7 s. Low and steep-ish, and higher and steeper.
_JUMPS_LOW = HoverSweepsSpec(distance_m=(40.0, 55.0), height_m=(20.0, 35.0), pitch_deg=(25.0, 40.0),
                             sweep_deg=(60.0, 60.0), sweep_rate_deg_s=(250.0, 400.0), dwell_s=(2.5, 3.5))
_JUMPS_HIGH = HoverSweepsSpec(distance_m=(45.0, 60.0), height_m=(30.0, 50.0), pitch_deg=(30.0, 45.0),
                              sweep_deg=(60.0, 60.0), sweep_rate_deg_s=(200.0, 350.0), dwell_s=(2.5, 3.5))
_JUMPS = (_JUMPS_LOW, _JUMPS_HIGH)
#: Instant jumps: the heading changes by 60 deg between two frames (a turn of at most 0.04 s), every 3 s.
_INSTANT: dict[str, Any] = {"sweep_rate_deg_s": (4000.0, 5000.0), "min_turn_s": 0.03, "dwell_s": (3.0, 3.0)}
_JUMPS_INSTANT = (dataclasses.replace(_JUMPS_LOW, **_INSTANT), dataclasses.replace(_JUMPS_HIGH, **_INSTANT))
#: Wider and slower: 90 deg jumps, 4-5 s dwells (objects away for 4-5 s), and narrower and quicker: 45 deg, 2 s.
_JUMPS_90 = (dataclasses.replace(_JUMPS_HIGH, sweep_deg=(90.0, 90.0), dwell_s=(4.0, 5.0), min_turn_s=0.1),)
_JUMPS_45 = (dataclasses.replace(_JUMPS_LOW, sweep_deg=(45.0, 45.0), dwell_s=(1.8, 2.2), min_turn_s=0.1),)
#: Larger telemetry biases per flight than the base scenarios' (GPS 1.5 m, heading 2 deg, pitch 0.5 deg).
_BIASED: dict[str, Any] = {"gps_bias_m": 3.0, "heading_bias_deg": 4.0, "pitch_bias_deg": 1.0}

_DOMAIN_LIST = (
    # ---------------------------------------------------------------- tuning domains
    Domain("sea-jitter", "sea, gentle flights, per-frame telemetry jitter at 30 fps", "tune", "gentle", "sea",
           _GENTLE_SEA, noise={**_JITTER, "telemetry_hz": 30.0}),
    Domain("grass-gps5-24", "grass, gentle flights at 24 fps, 5-decimal GPS, under-confident detector with "
           "more part boxes", "tune", "gentle", "grass", _GENTLE_GRASS, fps=24.0, clip_s=10.0,
           noise={**_GPS5, "time_offset_s": 0.1}, emulator={**_UNDERCONFIDENT, **_MORE_PARTS}),
    Domain("grass-sweeps-wide", "grass, heading sweeps with a 1080p wide camera, jitter and drifting clocks, "
           "over-confident detector, more clutter", "tune", "sweeps", "grass", _SWEEPS, camera="1080p-wide",
           noise={**_JITTER, **_DRIFT, "telemetry_hz": 30.0}, emulator={**_OVERCONFIDENT, **_MORE_CLUTTER_EMU},
           world={"n_clutter": 6}),
    Domain("sea-sweeps-60", "sea, heading sweeps at 60 fps, 5-decimal GPS, 0.2 s offset, less clutter",
           "tune", "sweeps", "sea", _SWEEPS, fps=60.0, clip_s=6.0, noise={**_GPS5, "time_offset_s": 0.2},
           world={"n_clutter": 1}),
    # Added in the third round (issue 15): the defects the first tuning set lacked, each in a combination
    # no held-out domain has (tele camera on a gentle flight; 4-decimal GPS).
    Domain("sea-tele-gps4", "sea, gentle flights with a 4K tele camera, 4-decimal GPS (7-11 m steps), 1 m "
           "altitude steps", "tune", "gentle", "sea", _GENTLE_SEA, camera="4k-tele",
           noise={"gps_decimals": 4, "altitude_step_m": 1.0}),
    Domain("grass-gps4-parts", "grass, gentle flights, 4-decimal GPS, 0.2 s offset, more part boxes and more "
           "clutter", "tune", "gentle", "grass", _GENTLE_GRASS,
           noise={"gps_decimals": 4, "time_offset_s": 0.2}, emulator={**_MORE_PARTS, **_MORE_CLUTTER_EMU},
           world={"n_clutter": 5}),
    # Added in the fourth round (issue 15): tele camera on heading sweeps, in a combination no held-out
    # domain has (grass, per-frame jitter, default detector).
    Domain("grass-sweeps-tele", "grass, heading sweeps with a 4K tele camera, per-frame jitter at 30 fps",
           "tune", "sweeps", "grass", _TELE_SWEEPS, camera="4k-tele", noise={**_JITTER, "telemetry_hz": 30.0}),
    # Added in the sixth round (issue 15): tele camera on gentle flights over persistent clutter, in a
    # combination no held-out domain has (24 fps, drifting clocks, jitter in the gimbal angles only, 6-decimal
    # GPS, the default detector).
    Domain("grass-tele-drift", "grass, gentle flights with a 4K tele camera at 24 fps, drifting clocks, gimbal "
           "jitter, more persistent clutter at fixed ground spots", "tune", "gentle", "grass", _GENTLE_GRASS,
           camera="4k-tele", fps=24.0, noise={**_DRIFT, "white_heading_deg": 0.4, "white_pitch_deg": 0.3,
                                              "telemetry_hz": 24.0},
           emulator=_MORE_CLUTTER_EMU, world={"n_clutter": 8}),
    # Added with the re-ID round (view jumps): objects leave the view for ~3 s during a 60 deg heading jump and
    # return; most without appearance descriptors, as real detectors' outputs come.
    Domain("grass-jumps", "people walking, a hover whose heading jumps 60 deg between two frames every 3 s (away "
           "and back), no appearance descriptors", "tune", "jumps", "reid", _JUMPS_INSTANT, clip_s=24.0,
           descriptors=False),
    Domain("sea-jumps-24", "swimmers, 60 deg view jumps every ~3 s at 24 fps, 5-decimal GPS, 3 deg heading bias, no "
           "appearance descriptors", "tune", "jumps", "sea", _JUMPS, fps=24.0, clip_s=24.0,
           noise={**_GPS5, "heading_bias_deg": 3.0}, descriptors=False),
    Domain("grass-jumps-biased", "people walking, 60 deg view jumps, larger telemetry biases (GPS 3 m, heading 4 deg, "
           "pitch 1 deg), 0.1 s offset, no appearance descriptors", "tune", "jumps", "grass", _JUMPS, clip_s=24.0,
           noise={**_BIASED, "time_offset_s": 0.1}, descriptors=False),
    Domain("grass-jumps-90-dense", "16 people walking, 90 deg view jumps every 4-5 s (away for 4-5 s), 0.2 s offset, "
           "no appearance descriptors", "tune", "jumps", "reid", _JUMPS_90, clip_s=30.0,
           noise={"time_offset_s": 0.2}, world={"n_objects": 16}, descriptors=False),
    Domain("grass-jumps-desc-wide", "people walking, 60 deg view jumps at 25 fps with a 1080p wide camera, per-frame "
           "jitter, with appearance descriptors", "tune", "jumps", "reid", (_JUMPS_LOW,), fps=25.0, clip_s=24.0,
           camera="1080p-wide", noise={**_JITTER, "telemetry_hz": 25.0}),
    # Added with the view-cut round: the telemetry is a flight log at 1 Hz with whole-second stamps, so a jump
    # between two frames shows in the interpolated poses as a second-long turn (agent.view_cuts).
    Domain("grass-jumps-1hz", "people walking, a heading that jumps 60 deg between two frames every 3 s, logged at "
           "1 Hz with whole-second stamps, no appearance descriptors", "tune", "jumps", "reid", _JUMPS_INSTANT,
           clip_s=24.0, noise={"telemetry_hz": 1.0, "stamp_resolution_s": 1.0}, descriptors=False),
    # ---------------------------------------------------------------- held-out domains
    Domain("grass-tele-clutter", "grass, gentle flights with a 4K tele camera, per-frame jitter, 5-decimal "
           "GPS, over-confident detector, persistent clutter at fixed ground spots, 1 % frames without meta",
           "heldout", "gentle", "grass", _GENTLE_GRASS, camera="4k-tele",
           noise={**_JITTER, **_GPS5, "telemetry_hz": 30.0, "missing_meta_rate": 0.01},
           emulator={**_OVERCONFIDENT, **_MORE_CLUTTER_EMU}, world={"n_clutter": 8}),
    Domain("sea-oldsrt-60", "sea, gentle flights at 60 fps, old SRT telemetry (4-decimal GPS, 1 m altitude, "
           "0.3 s offset), under-confident detector, more part boxes", "heldout", "gentle", "sea", _GENTLE_SEA,
           fps=60.0, clip_s=6.0, noise=_OLD_SRT, emulator={**_UNDERCONFIDENT, **_MORE_PARTS}),
    Domain("grass-wide-jitter", "grass, gentle flights with a 1080p wide camera at 30 fps, per-frame jitter, "
           "drifting clocks, less clutter", "heldout", "gentle", "grass", _GENTLE_GRASS, camera="1080p-wide",
           noise={**_JITTER, **_DRIFT, "telemetry_hz": 30.0}, world={"n_clutter": 1}),
    Domain("grass-sweeps-24", "grass, heading sweeps and jumps at 24 fps, per-frame jitter, 5-decimal GPS, "
           "over-confident detector", "heldout", "sweeps", "grass", _SWEEPS, fps=24.0, clip_s=10.0,
           noise={**_JITTER, **_GPS5, "telemetry_hz": 24.0}, emulator=_OVERCONFIDENT),
    Domain("sea-sweeps-tele", "sea, heading sweeps with a 4K tele camera, 0.3 s offset, under-confident "
           "detector, more clutter", "heldout", "sweeps", "sea", _TELE_SWEEPS, camera="4k-tele",
           noise={"time_offset_s": 0.3, "white_heading_deg": 0.3}, emulator={**_UNDERCONFIDENT, **_MORE_CLUTTER_EMU},
           world={"n_clutter": 6}),
    # Added with the simulator's SeaDronesSee-style clocks: the clocks of real SeaDronesSee v2 files, and a twin
    # with agreeing clocks that simulates the same world, flights, detections and telemetry values per seed.
    Domain("sea-sds-clocks", "sea, gentle flights panning at 5-15 deg/s, SeaDronesSee v2 clocks: flight-log "
           "meta stamped in UTC at whole seconds (10 Hz, sample and hold), frames in local time (UTC+2)",
           "heldout", "gentle", "sea", _PANNING_SEA, noise={**_SDS_TELEMETRY, **_SDS_CLOCKS}),
    Domain("sea-sds-clocks-agree", "reference twin of sea-sds-clocks with agreeing clocks (SeaDronesSee meta "
           "stamped in UTC with milliseconds, frames in UTC): the same world, flights, detections and telemetry "
           "values per seed, for comparisons only", "heldout", "gentle", "sea", _PANNING_SEA,
           noise=dict(_SDS_TELEMETRY)),
    # Added with issue 31: a detector's final output (post-NMS, scores >= 0.25) every 0.5 s, as SeaDronesSee's
    # results are (every 15th video frame): boosting can only re-rank it. Held out: nothing was chosen on them.
    Domain("sea-final-2fps", "sea, gentle flights, the detector's final output (NMS, scores >= 0.25) at 2 fps",
           "heldout", "gentle", "sea", _GENTLE_SEA, fps=2.0, clip_s=40.0, final_score=0.25),
    Domain("grass-final-2fps", "grass, gentle flights, the detector's final output (NMS, scores >= 0.25) at 2 fps, "
           "over-confident detector", "heldout", "gentle", "grass", _GENTLE_GRASS, fps=2.0, clip_s=40.0,
           emulator=_OVERCONFIDENT, final_score=0.25),
    Domain("sea-sds-final", "sea, panning flights, SeaDronesSee v2 clocks and the detector's final output (NMS, "
           "scores >= 0.25) at 2 fps: the layout of the real SeaDronesSee files", "heldout", "gentle", "sea",
           _PANNING_SEA, fps=2.0, clip_s=40.0, noise={**_SDS_TELEMETRY, **_SDS_CLOCKS}, final_score=0.25),
    # Added with the terrain (issue 33): the grass world on hills, a slope and a river bank, heights above the
    # take-off at the scene's centre; evaluated over flat earth and with the DEM, and against the same flights over
    # flat ground (Domain.flat_twin). Held out: nothing was chosen on them.
    Domain("grass-hills", "grass, gentle flights over hills and hollows (12 m from the lowest to the highest, "
           "slopes to ~15 deg), per-frame jitter", "heldout", "gentle", "grass", _GENTLE_GRASS,
           noise={**_JITTER, "telemetry_hz": 30.0},
           terrain=TerrainSpec("hills", relief_m=12.0)),
    Domain("grass-slope", "grass, gentle flights over a 10 % slope, oblique line flights and orbits", "heldout",
           "gentle", "grass", _GENTLE_GRASS, terrain=TerrainSpec("slope", relief_m=10.0)),
    Domain("grass-step", "grass, heading sweeps over a 5 m river bank (a step 3 m wide) near the centre",
           "heldout", "sweeps", "grass", _SWEEPS, terrain=TerrainSpec("step", relief_m=5.0)),
    # Added with the re-ID round (view jumps). Held out: nothing was chosen on them.
    Domain("grass-jumps-jitter", "people walking, instant 60 deg view jumps every 3 s at 24 fps, higher and steeper "
           "hovers, per-frame jitter, 5-decimal GPS, no appearance descriptors", "heldout", "jumps", "grass",
           (_JUMPS_INSTANT[1],), fps=24.0, clip_s=30.0, noise={**_JITTER, **_GPS5, "telemetry_hz": 24.0},
           descriptors=False),
    Domain("sea-jumps-biased", "swimmers, 60 deg view jumps at 25 fps, larger telemetry biases, over-confident "
           "detector, no appearance descriptors", "heldout", "jumps", "sea", _JUMPS, fps=25.0, clip_s=24.0,
           noise=_BIASED, emulator=_OVERCONFIDENT, descriptors=False),
    Domain("grass-jumps-45-lag", "people walking, 45 deg view jumps every 2 s, 0.25 s offset, 10 Hz telemetry, no "
           "appearance descriptors", "heldout", "jumps", "reid", _JUMPS_45, clip_s=24.0,
           noise={"time_offset_s": 0.25, "telemetry_hz": 10.0}, descriptors=False),
    Domain("sea-jumps-log", "swimmers, 60 deg view jumps (0.25-0.45 s turns) at 25 fps, the telemetry a 1 Hz flight "
           "log in UTC with whole-second stamps and the frames in local time, 5-decimal GPS, no appearance "
           "descriptors", "heldout", "jumps", "sea", _JUMPS, fps=25.0, clip_s=24.0,
           noise={**_SDS_CLOCKS, **_GPS5, "telemetry_hz": 1.0}, descriptors=False),
    Domain("sea-jumps-desc", "swimmers, 60 deg view jumps at 30 fps, 0.15 s offset, 3 deg heading bias, with "
           "appearance descriptors", "heldout", "jumps", "sea", _JUMPS, clip_s=24.0,
           noise={"time_offset_s": 0.15, "heading_bias_deg": 3.0}),
    # Added 30 Nov 2026 with agent.telemetry_holds (a coordinate held between its updates). Held out: nothing was
    # chosen on it.
    Domain("sea-gps-held", "sea, gentle flights at 30 fps, a telemetry record per frame with gimbal jitter whose "
           "6-decimal GPS updates once a second and repeats in between", "heldout", "gentle", "sea", _GENTLE_SEA,
           noise={**_JITTER, "telemetry_hz": 30.0, "gps_hz": 1.0}),
)

class _Sweeps(TypedDict):
    """The sweep fields of a HoverSweepsSpec."""

    sweep_deg: tuple[float, float]
    sweep_rate_deg_s: tuple[float, float]
    dwell_s: tuple[float, float]
    min_pitch_deg: float


#: Far, low views (30 Nov 2026): every object beyond the pipeline's 150 m range, a 4K tele camera on a hover with slow
#: sweeps below the simulator's usual 17 deg pitch floor. Where the tracker's own far ground points were chosen
#: (docs/tracking.md, "Far views"); a group of their own (`--domains far`), apart from the grid above, whose
#: figures and bars they would shift (the memory map boosts nothing beyond its range).
_FAR_SWEEPS: _Sweeps = {"sweep_deg": (5.0, 12.0), "sweep_rate_deg_s": (3.0, 8.0), "dwell_s": (2.0, 4.0),
                        "min_pitch_deg": 3.0}
_FAR_LIST = (
    Domain("sea-far-tele", "swimmers 190-260 m away, 20-35 m up at 5-9 deg, 4K tele, per-frame jitter", "tune",
           "gentle", "sea", (HoverSweepsSpec(distance_m=(190.0, 260.0), height_m=(20.0, 35.0), pitch_deg=(5.0, 9.0),
                                             **_FAR_SWEEPS),), camera="4k-tele", noise=_JITTER),
    Domain("sea-farther-tele", "swimmers 380-520 m away, 20-35 m up at 3-5 deg, 4K tele, per-frame jitter", "tune",
           "gentle", "sea", (HoverSweepsSpec(distance_m=(380.0, 520.0), height_m=(20.0, 35.0), pitch_deg=(3.0, 5.0),
                                             **_FAR_SWEEPS),), camera="4k-tele", noise=_JITTER),
    Domain("grass-far-tele", "people 220-320 m away, 25-45 m up at 5-9 deg, 4K tele at 24 fps, drifting clocks",
           "heldout", "gentle", "grass", (HoverSweepsSpec(distance_m=(220.0, 320.0), height_m=(25.0, 45.0),
                                                          pitch_deg=(5.0, 9.0), **_FAR_SWEEPS),),
           camera="4k-tele", fps=24.0, noise={**_DRIFT, "telemetry_hz": 24.0}),
    # added 30 Nov 2026 with the loose far points (TrackerConfig.far_loose_gate), held out from their choice
    Domain("grass-farther-tele", "people 400-600 m away, 30-50 m up at 3-6 deg, 4K tele at 24 fps, drifting clocks",
           "heldout", "gentle", "grass", (HoverSweepsSpec(distance_m=(400.0, 600.0), height_m=(30.0, 50.0),
                                                          pitch_deg=(3.0, 6.0), **_FAR_SWEEPS),),
           camera="4k-tele", fps=24.0, noise={**_DRIFT, "telemetry_hz": 24.0}),
    # added 30 Nov 2026 with far points followed in the image within the reach (TrackerConfig.far_image_sigma_m),
    # held out from their choice: people who walk behind trees and come back, at 30 fps with per-frame jitter
    Domain("grass-trees-far-tele", "people among 18 trees 250-400 m away, 30-50 m up at 4-8 deg, 4K tele at 30 fps, "
           "per-frame jitter, 12 s clips", "heldout", "gentle", "grass",
           (HoverSweepsSpec(distance_m=(250.0, 400.0), height_m=(30.0, 50.0), pitch_deg=(4.0, 8.0), **_FAR_SWEEPS),),
           clip_s=12.0, camera="4k-tele", noise={**_JITTER, "telemetry_hz": 30.0},
           world={"n_trees": 18, "tree_radius_m": (2.5, 5.0), "tree_height_m": (8.0, 18.0)}),
)

#: All domains by name.
DOMAINS: dict[str, Domain] = {d.name: d for d in (*_DOMAIN_LIST, *_FAR_LIST)}
TUNING_DOMAINS: tuple[str, ...] = tuple(d.name for d in _DOMAIN_LIST if d.split == "tune")
HELDOUT_DOMAINS: tuple[str, ...] = tuple(d.name for d in _DOMAIN_LIST if d.split == "heldout")
FAR_DOMAINS: tuple[str, ...] = tuple(d.name for d in _FAR_LIST)


def get_domain(name: str) -> Domain:
    """The domain called `name`; ValueError listing the valid names if there is none."""
    try:
        return DOMAINS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown domain {name!r}; valid domains: {', '.join(DOMAINS)} "
                         "(or the groups all, tune, heldout)") from None


def resolve_named(names: list[str], groups: dict[str, tuple[str, ...]], get: Callable[[str], T]) -> list[T]:
    """What `get` returns for each of `names`, a group's members in its place, in order, without repeats."""
    out: list[T] = []
    for name in names:
        for n in groups.get(name, (name,)):
            d = get(n)
            if d not in out:
                out.append(d)
    return out


def resolve_domains(names: list[str]) -> list[Domain]:
    """Domains named in `names` (the groups "all" (tune and held out), "tune", "heldout" and "far" expand), in order,
    without repeats."""
    return resolve_named(names, {"all": TUNING_DOMAINS + HELDOUT_DOMAINS, "tune": TUNING_DOMAINS,
                                 "heldout": HELDOUT_DOMAINS, "far": FAR_DOMAINS}, get_domain)


def domain_table() -> str:
    """Markdown table of the domains (the `uavmm eval --list-domains` output and docs/simulator.md)."""
    lines = ["| domain | split | flights | base | fps | clip | camera | changes |", "|---|---|---|---|---|---|---|---|"]
    for d in (*_DOMAIN_LIST, *_FAR_LIST):
        changes = ", ".join(f"{k}={v}" for k, v in d.changes().items())
        split = f"{d.split} (far)" if d in _FAR_LIST else d.split
        lines.append(f"| {d.name} | {split} | {d.motion} | {d.base} | {d.fps:g} | {d.clip_s:g} s | {d.camera} | "
                     f"{changes} |")
    return "\n".join(lines)

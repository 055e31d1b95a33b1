"""Cooperative evaluation domains: two or three UAVs over one scene, shifted the ways real teams of drones differ.

Issue 15's domains (`sim.domains`) vary one UAV's data; these vary what makes a joint map hard: each UAV's own
telemetry biases (GPS 1-2 m, heading 0.5-1.5 deg, height), its altitude and pitch, who sees what (a tree line
that hides people from one UAV, a share of the people one UAV sees only weakly as through glare or foliage, one
UAV far more confident than the other), frame rates and telemetry lags that differ between the UAVs. Each
`CoopDomain` builds a simultaneous `Scenario` with per-UAV `UavSetting`s; `weaker` names the UAV the scene
hides things from (the one the joint map is for). Parameters are chosen on the "tune" domains; the "heldout"
ones are only reported (`uavmm eval --tasks coop --domains heldout`, `sim.coop_domain_eval`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

from sim.domains import SPLITS, resolve_named
from sim.flight import HoverSweepsSpec, LineSpec, OrbitSpec
from sim.scenarios import Scenario, UavSetting, get_scenario


@dataclass(frozen=True, slots=True)
class CoopDomain:
    """One cooperative domain (see the module docstring).

    base: a scenario of `sim.scenarios` whose world, class, noise and emulator the domain starts from.
    flights: one spec per UAV (distinct `uav` ids). uavs: per-UAV settings (`sim.scenarios.UavSetting`).
    weaker: the UAV the scene hides objects from or shows them weakly (acceptance: the joint map's gain is
    asked of it). world / emulator / noise: fields replaced on the base scenario for every UAV.
    """

    name: str
    description: str
    split: str
    base: str
    flights: tuple[Any, ...]
    uavs: tuple[UavSetting, ...]
    weaker: str
    fps: float = 30.0
    clip_s: float = 12.0
    world: dict[str, Any] = field(default_factory=dict)
    emulator: dict[str, Any] = field(default_factory=dict)
    noise: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"coop domain {self.name!r}: split must be one of {SPLITS}, got {self.split!r}")
        if not (math.isfinite(self.fps) and self.fps > 0 and math.isfinite(self.clip_s) and self.clip_s > 0):
            raise ValueError(f"coop domain {self.name!r}: fps and clip_s must be > 0")
        uavs = [f.uav for f in self.flights]
        if len(uavs) < 2:
            raise ValueError(f"coop domain {self.name!r}: needs two or more UAVs, got {uavs}")
        if self.weaker not in uavs:
            raise ValueError(f"coop domain {self.name!r}: weaker={self.weaker!r} is none of the UAVs {uavs}")
        self.scenario()  # every field name and value is checked by the dataclasses it builds

    def frames(self) -> int:
        """Frames of the scenario's clock (a UAV with frame_step k keeps every k-th)."""
        return max(1, round(self.clip_s * self.fps))

    def scenario(self) -> Scenario:
        """The domain as a simultaneous Scenario named after it."""
        base = get_scenario(self.base)
        return dataclasses.replace(
            base, name=self.name, description=self.description, flights=self.flights, simultaneous=True,
            world=dataclasses.replace(base.world, **self.world), noise=dataclasses.replace(base.noise, **self.noise),
            emulator=dataclasses.replace(base.emulator, **self.emulator), default_frames=self.frames(),
            fps=self.fps, uav_settings=self.uavs, terrain=None)

    @property
    def tag(self) -> str:
        """Short hash of the definition: dataset caches keyed by it regenerate when a domain changes."""
        return hashlib.sha1(repr(self).encode()).hexdigest()[:8]

    def summary(self) -> str:
        """One line per UAV: its flight and what differs for it."""
        parts = []
        for f in self.flights:
            setting = next((u for u in self.uavs if u.uav == f.uav), None)
            changes = {} if setting is None else {**setting.noise, **setting.emulator}
            if setting is not None and setting.frame_step > 1:
                changes["fps"] = round(self.fps / setting.frame_step, 2)
            text = ", ".join(f"{k}={v}" for k, v in changes.items())
            parts.append(f"{f.uav}{' (weaker)' if f.uav == self.weaker else ''}: {f.kind}"
                         f"{'; ' + text if text else ''}")
        return "; ".join(parts)


# The coop scenario's world: four trees in a line 12 m south of the centre, three people resting behind it.
_TREE_WORLD: dict[str, Any] = {}
# An open meadow (no tree line): what one UAV misses, it misses through glare, shade or its detector.
_OPEN_MEADOW: dict[str, Any] = {"fixed_trees": (), "n_trees": 2, "n_objects": 12,
                                "fixed_objects": ((-8.0, -6.0, True), (4.0, 3.0, True), (10.0, -2.0, True))}


def _bias(gps_m: float, heading_deg: float, height_m: float = 1.0, **more: Any) -> dict[str, Any]:
    return {"gps_bias_m": gps_m, "heading_bias_deg": heading_deg, "height_bias_m": height_m, **more}


_DOMAIN_LIST: tuple[CoopDomain, ...] = (
    # ------------------------------------------------------------------ tuning
    CoopDomain(
        name="coop-trees", split="tune", base="coop",
        description="The coop scenario on a 12 s clip: uav1 far and oblique behind the tree line, uav2 from the "
                    "north; each UAV with its own GPS and heading bias.",
        flights=get_scenario("coop").flights,
        uavs=(UavSetting("uav1", noise=_bias(1.5, 1.0)), UavSetting("uav2", noise=_bias(1.0, 0.5))),
        weaker="uav1", world=_TREE_WORLD),
    CoopDomain(
        name="coop-glare", split="tune", base="coop",
        description="An open meadow; uav1 (south, 25-30 m, 28-34 deg) sees half of the people weakly (glare, "
                    "shade); uav2 ~25 m east of it, higher and steeper, sees them well.",
        flights=(HoverSweepsSpec(uav="uav1", bearing_deg=(180.0, 180.0), distance_m=(50.0, 55.0),
                                 height_m=(25.0, 30.0), pitch_deg=(28.0, 34.0), sweep_deg=(8.0, 15.0),
                                 sweep_rate_deg_s=(8.0, 15.0), dwell_s=(3.0, 6.0)),
                 HoverSweepsSpec(uav="uav2", bearing_deg=(152.0, 155.0), distance_m=(55.0, 60.0),
                                 height_m=(40.0, 45.0), pitch_deg=(45.0, 50.0), sweep_deg=(8.0, 15.0),
                                 sweep_rate_deg_s=(8.0, 15.0), dwell_s=(3.0, 6.0))),
        uavs=(UavSetting("uav1", noise=_bias(2.0, 1.5), emulator={"weak_fraction": 0.5, "weak_logit_drop": 3.0}),
              UavSetting("uav2", noise=_bias(1.0, 0.5))),
        weaker="uav1", world=_OPEN_MEADOW),
    CoopDomain(
        name="coop-sea-rates", split="tune", base="sea",
        description="Swimmers; uav1 orbits with an under-confident detector at 30 fps, uav2 hovers over-confident "
                    "at 15 fps with telemetry 0.2 s late.",
        flights=(OrbitSpec(uav="uav1", radius_m=(45.0, 55.0), height_m=(30.0, 40.0)),
                 HoverSweepsSpec(uav="uav2", bearing_deg=(60.0, 80.0), distance_m=(40.0, 50.0),
                                 height_m=(30.0, 40.0), pitch_deg=(40.0, 50.0), sweep_deg=(10.0, 20.0),
                                 sweep_rate_deg_s=(10.0, 20.0), dwell_s=(3.0, 6.0))),
        uavs=(UavSetting("uav1", noise=_bias(1.5, 1.0), emulator={"score_logit_scale": 0.7, "score_logit_shift": -0.6,
                                                                   "weak_fraction": 0.3}),
              UavSetting("uav2", noise=_bias(1.0, 0.5, time_offset_s=0.2),
                         emulator={"score_logit_scale": 1.4, "score_logit_shift": 0.6}, frame_step=2)),
        weaker="uav1", world={"spawn_radius_m": 25.0}),
    CoopDomain(
        name="coop-trio-meadow", split="tune", base="coop",
        description="Three UAVs over an open meadow: uav1 (south-west, 25-30 m, 28-34 deg) sees 40 % of the people "
                    "weakly, uav2 hovers east, higher and steeper, uav3 flies a line to the north-west; three "
                    "different GPS, heading and height biases.",
        flights=(HoverSweepsSpec(uav="uav1", bearing_deg=(200.0, 210.0), distance_m=(45.0, 50.0),
                                 height_m=(25.0, 30.0), pitch_deg=(28.0, 34.0), sweep_deg=(8.0, 15.0),
                                 sweep_rate_deg_s=(8.0, 15.0), dwell_s=(3.0, 6.0)),
                 HoverSweepsSpec(uav="uav2", bearing_deg=(95.0, 105.0), distance_m=(50.0, 55.0),
                                 height_m=(40.0, 45.0), pitch_deg=(45.0, 50.0), sweep_deg=(8.0, 15.0),
                                 sweep_rate_deg_s=(8.0, 15.0), dwell_s=(3.0, 6.0)),
                 LineSpec(uav="uav3", bearing_deg=(320.0, 330.0), distance_m=(50.0, 55.0), half_length_m=(5.0, 10.0),
                          height_m=(35.0, 40.0), pitch_deg=(38.0, 44.0), speed_mps=(1.0, 2.0))),
        uavs=(UavSetting("uav1", noise=_bias(1.5, 1.0), emulator={"weak_fraction": 0.4, "weak_logit_drop": 3.0}),
              UavSetting("uav2", noise=_bias(2.0, 0.5, 0.5)), UavSetting("uav3", noise=_bias(1.0, 1.5, 1.5))),
        weaker="uav1", world=_OPEN_MEADOW),
    # ------------------------------------------------------------------ held out
    CoopDomain(
        name="coop-glare-east", split="heldout", base="coop",
        description="An open meadow; uav1 (south, 25-30 m, 25-30 deg) sees half of the people weakly, uav2 25 m "
                    "east of it, higher (42-48 m) and steeper (52-58 deg), sees the two thirds in its footprint "
                    "well; GPS, heading and height biases differ.",
        flights=(HoverSweepsSpec(uav="uav1", bearing_deg=(180.0, 180.0), distance_m=(48.0, 52.0),
                                 height_m=(25.0, 30.0), pitch_deg=(25.0, 30.0), sweep_deg=(5.0, 10.0),
                                 sweep_rate_deg_s=(5.0, 10.0), dwell_s=(3.0, 6.0)),
                 LineSpec(uav="uav2", bearing_deg=(150.0, 156.0), distance_m=(52.0, 58.0), half_length_m=(5.0, 10.0),
                          height_m=(42.0, 48.0), pitch_deg=(52.0, 58.0), speed_mps=(1.0, 2.0))),
        uavs=(UavSetting("uav1", noise=_bias(1.5, 1.0, 1.5), emulator={"weak_fraction": 0.5, "weak_logit_drop": 3.5}),
              UavSetting("uav2", noise=_bias(2.0, 1.5, 0.5))),
        weaker="uav1", world=_OPEN_MEADOW),
    CoopDomain(
        name="coop-trees-clock", split="heldout", base="coop",
        description="The tree line; uav2's telemetry 0.3 s late and its video at 10 fps; both headings 1.5 deg "
                    "off.",
        flights=get_scenario("coop").flights,
        uavs=(UavSetting("uav1", noise=_bias(1.0, 1.5)),
              UavSetting("uav2", noise=_bias(1.5, 1.5, time_offset_s=0.3), frame_step=3)),
        weaker="uav1", world=_TREE_WORLD),
    CoopDomain(
        name="coop-sea-glare", split="heldout", base="sea",
        description="Swimmers; uav1 hovers low and oblique with sun glint hiding 40 % of them (logit -4), uav2 "
                    "orbits higher.",
        flights=(HoverSweepsSpec(uav="uav1", bearing_deg=(200.0, 220.0), distance_m=(45.0, 50.0),
                                 height_m=(22.0, 28.0), pitch_deg=(25.0, 32.0), sweep_deg=(8.0, 15.0),
                                 sweep_rate_deg_s=(8.0, 15.0), dwell_s=(3.0, 6.0)),
                 OrbitSpec(uav="uav2", radius_m=(40.0, 50.0), height_m=(40.0, 50.0))),
        uavs=(UavSetting("uav1", noise=_bias(2.0, 0.5), emulator={"weak_fraction": 0.4, "weak_logit_drop": 4.0}),
              UavSetting("uav2", noise=_bias(1.0, 1.0, 2.0))),
        weaker="uav1", world={"spawn_radius_m": 25.0}),
    CoopDomain(
        name="coop-high-low", split="heldout", base="coop",
        description="An open meadow; uav1 low (18-22 m) and grazing (18-22 deg) with an under-confident detector "
                    "and a third of the people weak, uav2 high (60-70 m) looking almost straight down, "
                    "over-confident; uav2 at 15 fps.",
        flights=(HoverSweepsSpec(uav="uav1", bearing_deg=(250.0, 270.0), distance_m=(50.0, 55.0),
                                 height_m=(18.0, 22.0), pitch_deg=(18.0, 22.0), sweep_deg=(5.0, 10.0),
                                 sweep_rate_deg_s=(5.0, 10.0), dwell_s=(3.0, 6.0)),
                 LineSpec(uav="uav2", bearing_deg=(90.0, 90.0), distance_m=(8.0, 12.0), half_length_m=(10.0, 15.0),
                          height_m=(60.0, 70.0), pitch_deg=(75.0, 85.0), speed_mps=(1.5, 2.5))),
        uavs=(UavSetting("uav1", noise=_bias(1.0, 0.5, 2.0),
                         emulator={"score_logit_scale": 0.7, "score_logit_shift": -0.5, "weak_fraction": 0.33}),
              UavSetting("uav2", noise=_bias(1.5, 1.0), emulator={"score_logit_scale": 1.5, "score_logit_shift": 0.5},
                         frame_step=2)),
        weaker="uav1", world=_OPEN_MEADOW),
    CoopDomain(
        name="coop-trio-glare", split="heldout", base="coop",
        description="Three UAVs over the tree line: uav1 behind it from the south with half of the people weak, "
                    "uav2 from the north, uav3 orbiting high; three different GPS and heading biases.",
        flights=(*get_scenario("coop").flights,
                 OrbitSpec(uav="uav3", radius_m=(45.0, 50.0), height_m=(45.0, 50.0))),
        uavs=(UavSetting("uav1", noise=_bias(1.5, 1.0), emulator={"weak_fraction": 0.5}),
              UavSetting("uav2", noise=_bias(2.0, 0.5)), UavSetting("uav3", noise=_bias(1.0, 1.5, 2.0))),
        weaker="uav1", world=_TREE_WORLD),
)

COOP_DOMAINS: dict[str, CoopDomain] = {d.name: d for d in _DOMAIN_LIST}
TUNING_COOP_DOMAINS = tuple(d.name for d in _DOMAIN_LIST if d.split == "tune")
HELDOUT_COOP_DOMAINS = tuple(d.name for d in _DOMAIN_LIST if d.split == "heldout")


def get_coop_domain(name: str) -> CoopDomain:
    """The coop domain called `name`; ValueError listing the valid names if there is none."""
    try:
        return COOP_DOMAINS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown coop domain {name!r}; valid: {', '.join(COOP_DOMAINS)} "
                         "(or the groups all, tune, heldout)") from None


def resolve_coop_domains(names: list[str]) -> list[CoopDomain]:
    """Coop domains named in `names` (the groups "all", "tune", "heldout" expand), in order, without repeats."""
    return resolve_named(names, {"all": tuple(COOP_DOMAINS), "tune": TUNING_COOP_DOMAINS,
                                 "heldout": HELDOUT_COOP_DOMAINS}, get_coop_domain)


def coop_domain_table() -> str:
    """Markdown table of the coop domains (`uavmm eval --tasks coop --list-domains`, docs/fusion.md)."""
    lines = ["| coop domain | split | base | fps | clip | per UAV |", "|---|---|---|---|---|---|"]
    for d in _DOMAIN_LIST:
        lines.append(f"| {d.name} | {d.split} | {d.base} | {d.fps:g} | {d.clip_s:g} s | {d.summary()} |")
    return "\n".join(lines)

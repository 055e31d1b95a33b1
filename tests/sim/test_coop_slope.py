"""The `coop-slope` scenario: two UAVs on opposite sides of a slope, each launched from its own side, over the
DEM the dataset carries; and the simulator's take-off per UAV (`Scenario.takeoff`) and fixed slope aspect."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from agent.boxes import box_anchor_points
from shared.geo import Camera, Pose, latlon_to_local, pixel_to_latlon
from sim.dataset import TERRAIN_DEM_FILE, write_dataset
from sim.scenarios import get_scenario
from sim.simulator import Simulation
from sim.terrain import TerrainSpec
from sim.terrain_eval import terrain_of


def test_the_uavs_look_at_the_slope_from_opposite_sides_and_see_the_same_people():
    sim = Simulation("coop-slope", seed=0, frames=30)
    assert sim.terrain is not None and sim.scenario.simultaneous
    ground = sim.terrain
    assert float(ground.up_world_m(0.0, 30.0)) > float(ground.up_world_m(0.0, -30.0)) + 5.0  # rises to the north
    start = {v.uav: sim.flights()[v.id].state(0.0) for v in sim.videos}
    below, above = start["uav1"], start["uav2"]
    assert below.north_m < -40.0 and (below.heading_deg + 30.0) % 360.0 < 60.0  # south, looking up (north)
    assert above.north_m > 40.0 and abs(above.heading_deg - 180.0) < 30.0  # north, looking down (south)
    takeoff = {v.uav: sim.takeoff_up_m[v.id] for v in sim.videos}
    assert takeoff["uav1"] < -4.0 and takeoff["uav2"] > 4.0  # each launched from its own side
    seen: dict[str, set[int]] = {"uav1": set(), "uav2": set()}
    for fs in sim.frames():
        seen[fs.uav] |= {o.track_id for o in fs.objects if o.visible}
    assert len(seen["uav1"] & seen["uav2"]) >= 10  # the standing people, from both sides


def test_each_uav_counts_its_heights_from_its_own_takeoff(tmp_path):
    """truth.json gives each video's take-off elevation; with it and the true pose the DEM puts every annotated
    person where it stands, while the scene's (centre's) take-off misplaces them by metres."""
    write_dataset("coop-slope", tmp_path, seed=1, frames=6, progress=False)
    truth = json.loads((tmp_path / "truth.json").read_text())
    coco = json.loads((tmp_path / "images.json").read_text())
    assert (tmp_path / TERRAIN_DEM_FILE).exists() and truth["scenario"]["takeoff"] == "start"
    cam = Camera.from_file(tmp_path / "camera.json")
    poses = {p["image_id"]: p for p in truth["poses"]}
    video_of = {im["id"]: im["video_id"] for im in coco["images"]}
    for video in truth["videos"]:
        own = terrain_of(tmp_path, video["id"])
        assert own.takeoff_elevation_m == pytest.approx(video["takeoff_elevation_m"])
        first = next(p for p in truth["poses"] if p["video_id"] == video["id"])
        assert float(own.height_at(first["lat"], first["lon"])) == pytest.approx(video["takeoff_elevation_m"],
                                                                                 abs=0.05)
        scene = terrain_of(tmp_path)  # the centre's take-off, as if it had launched there
        assert abs(scene.takeoff_elevation_m - own.takeoff_elevation_m) > 4.0
        errors: dict[str, list[float]] = {"own": [], "scene": []}
        for a in coco["annotations"]:
            if video_of[a["image_id"]] != video["id"]:
                continue
            p = poses[a["image_id"]]
            pose = Pose(p["lat"], p["lon"], p["height_m"], p["pitch_deg"], p["heading_deg"])
            x, y, w, h = a["bbox"]
            uv = box_anchor_points(np.array([[x, y, x + w, y + h]]), "bottom", pose.pitch_deg)
            for name, terrain in (("own", own), ("scene", scene)):
                lat, lon, ok = pixel_to_latlon(uv, cam, pose, terrain=terrain)
                e, n = latlon_to_local(lat, lon, a["lat"], a["lon"])
                errors[name].append(float(np.hypot(e, n)[0]) if ok[0] else math.inf)
        assert len(errors["own"]) > 20
        assert np.median(errors["own"]) < 0.5
        assert np.median(errors["scene"]) > 3.0


def test_takeoff_is_checked_and_the_default_keeps_every_uav_at_the_origin():
    with pytest.raises(ValueError, match="takeoff"):
        dataclasses.replace(get_scenario("coop"), takeoff="runway")
    sim = Simulation("hills", seed=0, frames=2)
    assert set(sim.takeoff_up_m.values()) == {0.0}
    for _ in sim.frames():
        pass
    assert all("takeoff_elevation_m" not in v for v in sim.facts()["videos"])


def test_a_slope_rises_towards_its_fixed_aspect():
    rng_seed = [0, 5]
    east = TerrainSpec("slope", relief_m=10.0, extent_m=200.0, aspect_deg=90.0).build(
        np.random.default_rng(rng_seed), 48.5, 9.0)
    assert float(east.up_world_m(30.0, 0.0)) == pytest.approx(3.0, abs=1e-6)
    assert float(east.up_world_m(0.0, 30.0)) == pytest.approx(0.0, abs=1e-6)
    drawn = TerrainSpec("slope", relief_m=10.0, extent_m=200.0).build(np.random.default_rng(rng_seed), 48.5, 9.0)
    again = TerrainSpec("slope", relief_m=10.0, extent_m=200.0).build(np.random.default_rng(rng_seed), 48.5, 9.0)
    np.testing.assert_array_equal(drawn.grid.heights_m, again.grid.heights_m)  # without it: drawn per seed
    with pytest.raises(ValueError, match="aspect_deg"):
        TerrainSpec("slope", aspect_deg=math.nan)

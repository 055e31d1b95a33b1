"""The simulator's terrain (sim.terrain): objects stand on it, the dataset carries its DEM, and the world,
flights, telemetry and detector are those of the same scenario over flat ground."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from agent.dem import read_dem
from shared.geo import Pose, latlon_to_local, local_to_latlon, pixel_to_latlon
from shared.terrain import ElevationGrid, Terrain
from sim.dataset import DATASET_FILES, TERRAIN_DEM_FILE, write_dataset
from sim.domains import DOMAINS, HELDOUT_DOMAINS, get_domain
from sim.groundtruth import terrain_hidden
from sim.scenarios import get_scenario
from sim.simulator import Simulation
from sim.terrain import TERRAIN_KINDS, TerrainSpec


def hilly(kind: str = "hills", **kw):
    return dataclasses.replace(get_scenario("grass"), terrain=TerrainSpec(kind, **kw))


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"kind": "dunes"}, "kind"), ({"relief_m": -1.0}, "relief_m"), ({"cell_m": 0.0}, "cell_m"),
    ({"extent_m": 1e6}, "4,000 cells"), ({"hill_sigma_m": (5.0, 2.0)}, "hill_sigma_m"),
])
def test_terrain_spec_refuses_bad_values_naming_them(kwargs, field):
    with pytest.raises(ValueError, match=field):
        TerrainSpec(**{"kind": "hills", **kwargs})


@pytest.mark.parametrize("kind", TERRAIN_KINDS)
def test_each_kind_is_seeded_has_relief_and_takes_off_at_the_origin(kind):
    spec = TerrainSpec(kind, relief_m=6.0, extent_m=300.0)
    a = spec.build(np.random.default_rng([3, 5]), 48.53, 9.06)
    b = spec.build(np.random.default_rng([3, 5]), 48.53, 9.06)
    c = spec.build(np.random.default_rng([4, 5]), 48.53, 9.06)
    np.testing.assert_array_equal(a.grid.heights_m, b.grid.heights_m)
    assert not np.array_equal(a.grid.heights_m, c.grid.heights_m)
    assert a.up_world_m(0.0, 0.0) == pytest.approx(0.0, abs=1e-9)
    assert a.takeoff_elevation_m == pytest.approx(float(a.grid.height_at(48.53, 9.06)))
    ups = a.up_world_m(*np.meshgrid(np.linspace(-60, 60, 25), np.linspace(-60, 60, 25)))
    assert np.ptp(ups) > 2.0  # the scene is not flat
    lat, lon = local_to_latlon(37.0, -12.0, 48.53, 9.06)  # world-local metres and lat/lon agree
    assert a.up_world_m(37.0, -12.0) == pytest.approx(float(a.grid.height_at(lat, lon)) - a.takeoff_elevation_m)


def test_objects_stand_on_the_terrain_and_the_rest_is_the_flat_scenario():
    """The annotations' boxes see the objects where the DEM puts their ground; the meta, true positions and
    poses are those of the same scenario over flat ground (the terrain draws from a generator of its own)."""
    scenario = hilly("slope", relief_m=15.0)
    sim = Simulation(scenario, seed=2, frames=12)
    flat = Simulation(get_scenario("grass"), seed=2, frames=12)
    assert sim.terrain is not None and flat.terrain is None
    terrain = sim.terrain.terrain
    checked = 0
    for fs, ff in zip(sim.frames(), flat.frames(), strict=True):
        assert fs.meta == ff.meta and fs.true_pose == ff.true_pose
        assert [(o.lat, o.lon) for o in fs.objects] == [(o.lat, o.lon) for o in ff.objects]
        for o in fs.objects:
            if not o.visible:
                continue
            x, y, w, h = o.bbox_xywh
            inside = 0 < x and x + w < sim.camera.width and 0 < y and y + h < sim.camera.height
            if inside and fs.true_pose.pitch_deg < 60:
                # the bottom centre of an upright person's box is about where the feet are (half the depth)
                lat, lon, valid = pixel_to_latlon(np.array([[x + w / 2, y + h]]), sim.camera, fs.true_pose,
                                                  terrain=terrain)
                assert valid[0]
                de, dn = latlon_to_local(lat[0], lon[0], o.lat, o.lon)
                assert np.hypot(de, dn) < 1.0
                checked += 1
    assert checked > 20


def test_a_ridge_between_camera_and_object_hides_it():
    east = np.arange(-100, 101, dtype=float)
    heights = 100.0 + 20.0 * np.exp(-((east - 30.0) ** 2) / 20.0)  # a 20 m ridge 30 m east, running north-south
    grid = ElevationGrid.from_local(np.repeat(heights[None, :], 201, axis=0), 48.0, 9.0, west_m=-100, north_m=100,
                                    cell_m=1.0)
    terrain = Terrain(grid, 100.0)
    pose = Pose(lat=48.0, lon=9.0, height_m=15.0, pitch_deg=20.0, heading_deg=90.0)
    lat, lon = local_to_latlon(np.array([60.0, 15.0]), np.array([0.0, 0.0]), 48.0, 9.0)
    assert terrain_hidden(lat, lon, 0.85, pose, terrain).tolist() == [True, False]  # behind it, in front of it


def test_a_terrain_dataset_writes_its_dem_and_a_flat_one_does_not(tmp_path):
    write_dataset(hilly("step", relief_m=4.0), tmp_path / "d", seed=1, frames=3, progress=False)
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == sorted([*DATASET_FILES, TERRAIN_DEM_FILE])
    truth = json.loads((tmp_path / "d" / "truth.json").read_text())
    assert truth["terrain"]["kind"] == "step" and truth["scenario"]["terrain"]["relief_m"] == 4.0
    grid = read_dem(tmp_path / "d" / TERRAIN_DEM_FILE)
    first = truth["poses"][0]
    assert np.isfinite(grid.height_at(first["lat"], first["lon"]))
    assert truth["terrain"]["min_elevation_m"] < truth["terrain"]["takeoff_elevation_m"] + 4.0
    from sim.render import SimulatedDataset

    with pytest.raises(ValueError, match="flat ground only"):  # the renderer would draw the people elsewhere
        SimulatedDataset(tmp_path / "d")
    write_dataset("grass", tmp_path / "d", seed=1, frames=3, progress=False)  # a flat one in the same place
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == sorted(DATASET_FILES)
    assert "terrain" not in json.loads((tmp_path / "d" / "truth.json").read_text())


def test_terrain_domains_are_held_out_with_flat_twins_and_old_tags_stay():
    names = [n for n, d in DOMAINS.items() if d.terrain is not None]
    assert {"grass-hills", "grass-slope", "grass-step"} <= set(names) <= set(HELDOUT_DOMAINS)
    hills = get_domain("grass-hills")
    twin = hills.flat_twin()
    assert twin.terrain is None and twin.flights == hills.flights and twin.name == "grass-hills-flat"
    assert twin.tag != hills.tag and hills.scenario().terrain == hills.terrain
    assert "terrain" in hills.changes() and "terrain" not in DOMAINS["sea-jitter"].changes()
    assert DOMAINS["sea-jitter"].tag == "fbcdf83b"  # domains without a terrain keep their cached datasets


def test_a_flight_below_the_terrain_is_refused():
    scenario = hilly("slope", relief_m=60.0)  # 60 m per 100 m: the orbits run into the hillside
    with pytest.raises(ValueError, match="above the terrain"):
        for _ in Simulation(scenario, seed=0, frames=30).frames():
            pass


def test_domain_eval_runs_flat_earth_dem_and_the_flat_twin_on_a_terrain_domain(tmp_path):
    from sim.domain_eval import run_domain_eval

    tiny = [dataclasses.replace(get_domain("grass-step"), clip_s=1.5)]
    report = run_domain_eval(tiny, [0], noise_scales=(1.0,), out_dir=tmp_path)
    det = {r["variant"] for r in report["detection_rows"]}
    assert {"memory map", "memory map + DEM", "baseline + DEM", "flat twin: memory map"} <= det
    trk = {r["variant"]: r for r in report["tracking_rows"]}
    assert {"GPS tracker + memory map", "GPS tracker + memory map + DEM", "flat twin: GPS tracker + memory map"} \
        <= set(trk)
    # the 5 m bank under the people: flat earth puts them metres off, the DEM as close as over flat ground
    flat, dem = trk["GPS tracker + memory map"], trk["GPS tracker + memory map + DEM"]
    assert dem["pos_err_m"] < flat["pos_err_m"]
    (s,) = report["terrain"]
    assert s["domain"] == "grass-step" and s["pos_err_m_dem"] == pytest.approx(dem["pos_err_m"])
    criteria = [a["criterion"] for a in report["acceptance"]]
    assert "grass-step: pos err with DEM - flat-ground twin, m" in criteria
    md = (tmp_path / "report.md").read_text()
    assert "## Terrain: flat earth vs --dem" in md and "| grass-step |" in md
    assert "grass-step-flat" not in {s["domain"] for s in report["detection"]}  # the twin is no domain of its own

"""`--dem` on `uavmm fit-size-filter` and `uavmm tune`, on a short simulated `hills` dataset (dem.npz beside it,
truth.json's take-off elevation as --takeoff-elevation-m)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import agent.tune
from agent.boost import load_params
from agent.dem import load_terrain, write_npz
from agent.size_filter import SizeFilter
from agent.size_filter_fit import fit_from_dataset
from shared.terrain import ElevationGrid
from sim.dataset import write_dataset
from uavmm.cli import main


@pytest.fixture(scope="module")
def hills(tmp_path_factory: pytest.TempPathFactory):
    """Two 20-frame videos of people walking over hills and hollows (12 m relief); returns the folder and the
    take-off's elevation on the DEM."""
    d = tmp_path_factory.mktemp("hills")
    write_dataset("hills", d, seed=0, frames=20, progress=False)
    takeoff_m = json.loads((d / "truth.json").read_text())["terrain"]["takeoff_elevation_m"]
    return d, float(takeoff_m)


def _frames(d):
    return ["--frames", str(d / "images.json"), "--camera", str(d / "camera.json")]


def _median_log_size_m(report) -> float:
    return float(np.log(report["person"]["median_size_m"]))


def test_fit_size_filter_with_the_dem_measures_sizes_at_the_range_to_the_terrain(hills, capsys):
    """Over flat ground a box's feet-ray meets the take-off's plane; on the DEM it meets the terrain. Where people
    stand h_t below the plane (a hollow) the true range is longer by the factor (h - h_t) / h along the same ray
    (h: the camera's height above the plane), so flat earth makes them smaller by it. The fitted sizes move by
    the median of that factor, in its direction."""
    d, takeoff_m = hills
    terrain = load_terrain(d / "dem.npz", takeoff_m)
    flat_sf, flat_report = fit_from_dataset(d / "images.json", d / "camera.json")
    dem_sf, dem_report = fit_from_dataset(d / "images.json", d / "camera.json", terrain=terrain)
    coco = json.loads((d / "images.json").read_text())
    poses = {p["image_id"]: p for p in json.loads((d / "truth.json").read_text())["poses"]}
    anns = coco["annotations"]
    up_m = terrain.height_at(np.array([a["lat"] for a in anns]), np.array([a["lon"] for a in anns])) - takeoff_m
    height_m = np.array([poses[a["image_id"]]["height_m"] for a in anns])
    expected = float(np.median(np.log1p(-up_m / height_m)))
    shift = _median_log_size_m(dem_report) - _median_log_size_m(flat_report)
    assert abs(expected) > 0.01  # these people stand mostly in hollows: the geometry predicts a shift
    assert np.sign(shift) == np.sign(expected)
    assert 0.5 * abs(expected) < abs(shift) < 2.0 * abs(expected)
    assert dem_report["person"]["samples"] == flat_report["person"]["samples"]

    # the command: the same flags as boost/track, the same fit as the API
    assert main(["fit-size-filter", *_frames(d), "--out", str(d / "flat_sf.json")]) == 0
    assert main(["fit-size-filter", *_frames(d), "--out", str(d / "dem_sf.json"), "--dem", str(d / "dem.npz"),
                 "--takeoff-elevation-m", str(takeoff_m)]) == 0
    capsys.readouterr()
    for name, fitted in (("dem_sf.json", dem_sf), ("flat_sf.json", flat_sf)):
        written = SizeFilter.load(d / name)  # the fit's bands, and the built-in priors of the classes it did not fit
        assert {k: v for k, v in written.bands.items() if k in fitted.bands} == fitted.bands
        assert all(band == SizeFilter.builtin().bands[k] for k, band in written.bands.items() if k not in fitted.bands)


def test_a_dem_level_with_the_takeoff_fits_what_flat_ground_fits(hills, tmp_path):
    d, takeoff_m = hills
    grid = load_terrain(d / "dem.npz").grid
    level = ElevationGrid(np.full(grid.shape, takeoff_m), lat0_deg=grid.lat0_deg, lon0_deg=grid.lon0_deg,
                          lat_step_deg=grid.lat_step_deg, lon_step_deg=grid.lon_step_deg)
    write_npz(tmp_path / "level.npz", level)
    flat_sf, _ = fit_from_dataset(d / "images.json", d / "camera.json")
    level_sf, _ = fit_from_dataset(d / "images.json", d / "camera.json", terrain=load_terrain(tmp_path / "level.npz"))
    a, b = flat_sf.bands["person"], level_sf.bands["person"]
    np.testing.assert_allclose(b.mean_log_m, a.mean_log_m, atol=1e-6)
    np.testing.assert_allclose(b.std_log, a.std_log, atol=1e-6)


def _record_runs(monkeypatch):
    """Wrap tune's pipeline runs and size-filter fit: the terrain each one was given, in call order."""
    runs: list = []
    fits: list = []
    fit_images: list = []
    real_run, real_fit = agent.tune.run_pipeline, agent.tune.fit_from_dataset

    def run_pipeline(dataset, candidates, camera, config, *args, **kwargs):
        runs.append((config.terrain, kwargs.get("video_ids")))
        return real_run(dataset, candidates, camera, config, *args, **kwargs)

    def fit(*args, **kwargs):
        fits.append(kwargs.get("terrain"))
        fit_images.append(kwargs.get("image_ids"))
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(agent.tune, "run_pipeline", run_pipeline)
    monkeypatch.setattr(agent.tune, "fit_from_dataset", fit)
    # one setting, two values: the runs stay few, the search and the held-out check still run
    monkeypatch.setattr(agent.tune, "SEARCH_SPACE", (("boost_weight", (1.0, 2.0)),))
    return runs, fits, fit_images


def _tune(d, out, *extra):
    return main(["tune", *_frames(d), "--candidates", str(d / "pre_nms.json"), "--out", str(d / out), "--quiet",
                 *extra])


def test_tune_runs_every_pipeline_and_the_size_filter_fit_on_the_dem(hills, monkeypatch, capsys):
    d, takeoff_m = hills
    runs, fits, fit_images = _record_runs(monkeypatch)
    assert _tune(d, "params_dem.json", "--dem", str(d / "dem.npz"), "--takeoff-elevation-m", str(takeoff_m)) == 0
    out = capsys.readouterr().out
    assert "held-out videos [2]" in out
    # one fit on every video, one on the held-out check's tuning video alone (its ground truth only), both on the DEM
    assert len(fits) == 2 and fits[0] is not None and fits[0].takeoff_elevation_m == pytest.approx(takeoff_m)
    assert fits[1] is fits[0]
    video_1 = {im["id"] for im in json.loads((d / "images.json").read_text())["images"] if im["video_id"] == 1}
    assert fit_images == [None, video_1]
    assert runs and all(terrain is fits[0] for terrain, _ in runs)
    assert {tuple(v) for _, v in runs} == {(1, 2), (1,), (2,)}  # all videos, then the held-out check's halves
    params = json.loads((d / "params_dem.json").read_text())
    assert "terrain" not in params["pipeline"]  # PARAMS.json keeps the settings, not the DEM
    assert load_params(d / "params_dem.json")[0].terrain is None
    dem_fit = params["tuned_on"]["size_filter"]["fit"]["person"]["median_size_m"]

    runs.clear()
    fits.clear()
    assert _tune(d, "params_flat.json") == 0
    assert fits == [None, None] and runs and all(terrain is None for terrain, _ in runs)
    flat_fit = json.loads((d / "params_flat.json").read_text())["tuned_on"]["size_filter"]["fit"]["person"]
    assert flat_fit["median_size_m"] != dem_fit


@pytest.mark.parametrize("command", ["tune", "fit-size-filter"])
def test_dem_flags_refuse_bad_input_in_one_line(hills, capsys, command):
    d, _ = hills
    argv = [command, *_frames(d), "--out", str(d / "never.json")]
    if command == "tune":
        argv += ["--candidates", str(d / "pre_nms.json")]
    assert main([*argv, "--dem", str(d / "nope.tif")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"uavmm {command}: error: DEM file" in err and "nope.tif does not exist" in err
    assert main([*argv, "--takeoff-elevation-m", "300"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--takeoff-elevation-m needs --dem" in err
    (d / "bad.npz").write_bytes(b"not a zip")
    assert main([*argv, "--dem", str(d / "bad.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.npz" in err
    assert not (d / "never.json").exists()

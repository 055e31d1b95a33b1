"""Cooperative evaluation: two UAVs exchange tiles and footprints fused by the server's JointMap."""

from __future__ import annotations

import dataclasses
import json

import pytest

from agent.params_file import make_params
from agent.pipeline import DetectionPipeline
from agent.size_filter import SizeFilter
from shared.geo import Camera, Pose
from sim.coop_eval import CoopFusion, run_coop_eval, slope_acceptance
from uavmm.cli import main

LAT, LON = 48.0, 9.0


@pytest.mark.parametrize(("coverage", "expected"), [("footprint", 0.8), ("tile", 0.4)])
def test_coop_fusion_a_uav_not_seeing_a_cell_does_not_dilute_it(coverage, expected):
    cam = Camera(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    pipes = {uav: DetectionPipeline(cam, {1: "person"}) for uav in ("a", "b")}
    gx, gy = pipes["a"].grid.latlon_to_cell(LAT, LON)
    for pipe in pipes.values():
        pipe.memory.advance(0.0, LAT, LON)
    pipes["a"].memory.add("person", [gx], [gy], [0.8])
    # b hovers right above the cell looking north at 30 deg: the cell is in its memory window (its tiles
    # cover it, with zeros) but not in its camera footprint, which starts ~20 m ahead
    poses = {"a": (Pose(LAT - 3e-4, LON, 30.0, 45.0, 0.0), cam), "b": (Pose(LAT, LON, 30.0, 30.0, 0.0), cam)}
    fusion = CoopFusion(["a", "b"], ["person"], pipes, coverage=coverage)
    joint = {(cls, x, y): values for cls, x, y, values in fusion.publish(0.0, poses)}
    n = pipes["a"].grid.n
    values = joint[("person", int(gx) // n, int(gy) // n)]
    assert fusion.joint.get(("person", 18, int(gx) // n, int(gy) // n)).uavs == ("a", "b")
    assert float(values[int(gy) % n, int(gx) % n]) == pytest.approx(expected, abs=1 / 255)


def test_coop_eval_reports_every_uav_and_finds_hidden_people(tmp_path):
    report = run_coop_eval([0], frames=120, out_dir=tmp_path)
    by = {(s["uav"], s["variant"]): s for s in report["summary"]}
    assert {u for u, _ in by} == {"uav1", "uav2"}
    hidden = by[("uav1", "joint map boosting")]["hidden_detected"]
    assert hidden > by[("uav1", "baseline")]["hidden_detected"]
    # the joint map brings uav2's evidence to the people the tree line hides from uav1
    assert hidden > by[("uav1", "own memory map")]["hidden_detected"] + 3.0
    # and joint detections report more of them than boosting alone
    assert by[("uav1", "joint map + joint detections")]["hidden_detected"] > hidden + 2.0
    for metric in ("AP50", "AP50_hidden_ignored", "AP50_hidden_as_fp"):
        assert by[("uav1", "joint map boosting")][metric] > by[("uav1", "baseline")][metric]
    assert (tmp_path / "report.md").read_text().count("| coop | x1 | uav1 |") == 4
    # the tracker on each variant's detections: TrackEval's HOTA and the tracks' ground error
    for uav in ("uav1", "uav2"):
        assert 20.0 < by[(uav, "own memory map")]["HOTA"] <= 100.0
        assert 0.0 <= by[(uav, "own memory map")]["pos_err_m"] < 5.0
    # the joint map's peaks against the people resting behind the tree line (uav2 sees them)
    peak_rows = {p["uav"]: p for p in report["peak_summary"]}
    assert set(peak_rows) == {"both", "uav1", "uav2"}
    peaks = peak_rows["both"]
    assert peaks["variant"] == "joint map + joint detections" and peaks["standing_objects"] >= 3
    assert 0.0 <= peaks["peak_err_m"] <= peaks["peak_err_p90_m"] < 5.0 and peaks["objects_with_peak"] > 50.0
    assert "## Joint-map peaks against the truth" in (tmp_path / "report.md").read_text()
    assert not report["acceptance"]  # the bars are those of a terrain: flat coop has no DEM rows
    # the fusion server's global tracks: the objects both UAVs track get one id on both more often than not
    cross = {c["variant"]: c for c in report["cross_summary"]}
    assert set(cross) == {v for _, v in by}
    for c in cross.values():
        assert c["shared_objects"] >= 3 and c["same_id"] > 50.0 and c["same_id_first_look"] > 0.0
        assert c["IDF1"] > c["IDF1_separate"] + 10.0 and c["IDs"] <= c["IDs_separate"]
        assert c["IDF1_first_look"] > c["IDF1_separate"]
    assert "## One object, one id across UAVs" in (tmp_path / "report.md").read_text()


def test_the_slope_bars_compare_the_dem_with_flat_earth_per_uav():
    summary = [{"scenario": "coop-slope", "noise_scale": 0.0, "uav": "uav1", "variant": v, "AP50": ap, "HOTA": hota}
               for v, ap, hota in (("own memory map", 80.0, 60.0), ("own memory map + DEM", 79.5, 61.0),
                                   ("joint map + joint detections", 82.0, 62.0),
                                   ("joint map + joint detections + DEM", 83.0, 61.5))]
    peaks = [{"scenario": "coop-slope", "noise_scale": 0.0, "variant": "joint map + joint detections" + s,
              "uav": uav, "peak_err_m": m} for s, uav, m in (("", "uav1", 3.5), (" + DEM", "uav1", 0.3),
                                                           (" + DEM", "uav2", 1.4), (" + DEM", "both", 0.9))]
    bars = {a["criterion"]: a for a in slope_acceptance(summary, peaks)}
    assert bars["coop-slope x0 uav1: joint-map peak error with DEM, median m"]["ok"]
    assert not bars["coop-slope x0 uav2: joint-map peak error with DEM, median m"]["ok"]
    own = bars["coop-slope x0 uav1 own memory map: AP50 with DEM - flat"]
    assert own["value"] == pytest.approx(-0.5) and not own["ok"]
    assert bars["coop-slope x0 uav1 own memory map: HOTA with DEM - flat"]["ok"]
    assert bars["coop-slope x0 uav1 joint map + joint detections: AP50 with DEM - flat"]["ok"]
    assert not bars["coop-slope x0 uav1 joint map + joint detections: HOTA with DEM - flat"]["ok"]
    assert len(bars) == 6  # the 'both' row is reported, the bars are each UAV's


def test_the_cli_passes_a_tune_files_size_filter_and_names_the_settings(tmp_path):
    # `uavmm eval --tasks coop --config PARAMS.json`: the fitted size filter a `uavmm tune` file carries reaches
    # the runs (it was dropped until 28 Nov 2026) and the report says so; a plain config records none
    fitted = dataclasses.replace(SizeFilter.builtin(), k=2.0)
    params = tmp_path / "params.json"
    params.write_text(json.dumps(make_params({"fragment_iou": 0.0}, fitted, {"by": "test"})))
    plain = tmp_path / "plain.json"
    plain.write_text('{"fragment_iou": 0.0}')
    reports = {}
    for name, path in (("params", params), ("plain", plain)):
        out = tmp_path / name
        assert main(["eval", "--tasks", "coop", "--seeds", "0", "--frames", "30", "--config", str(path),
                     "--out", str(out)]) == 0
        reports[name] = (json.loads((out / "coop" / "report.json").read_text()),
                         (out / "coop" / "report.md").read_text())
    report, text = reports["params"]
    assert report["size_filter"] == fitted.to_dict() and report["config_overrides"] == {"fragment_iou": 0.0}
    assert "Settings: fragment_iou = 0.0, a fitted size filter (--config), the rest the defaults." in text
    report, text = reports["plain"]
    assert report["size_filter"] is None and "Settings: fragment_iou = 0.0 (--config)" in text
    # the filter changes what the single-frame detector keeps (k 2 against the priors' 3)
    base = {s["uav"]: s["AP50"] for s in reports["params"][0]["summary"] if s["variant"] == "baseline"}
    assert base != {s["uav"]: s["AP50"] for s in reports["plain"][0]["summary"] if s["variant"] == "baseline"}

"""Cooperative evaluation: two UAVs exchange tiles and footprints fused by the server's JointMap."""

from __future__ import annotations

import pytest

from agent.pipeline import DetectionPipeline
from shared.geo import Camera, Pose
from sim.coop_eval import CoopFusion, run_coop_eval

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
    report = run_coop_eval([0], frames=90, out_dir=tmp_path)
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
    assert (tmp_path / "report.md").read_text().count("| uav1 |") == 4

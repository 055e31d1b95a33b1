"""Cooperative evaluation: two UAVs exchange byte-quantised tiles fused by the server's mean rule."""

from __future__ import annotations

import numpy as np
import pytest

from agent.pipeline import DetectionPipeline
from shared.geo import Camera
from sim.coop_eval import _fuse, run_coop_eval


def test_fuse_is_the_mean_of_the_uavs_covering_a_tile():
    cam = Camera(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    a, b = (DetectionPipeline(cam, {1: "person"}) for _ in range(2))
    for pipe, value in ((a, 0.8), (b, 0.2)):
        pipe.memory.advance(0.0, 48.0, 9.0)
        gx, gy = pipe.grid.latlon_to_cell(48.0, 9.0)
        pipe.memory.add("person", [gx], [gy], [value])
    joint = _fuse({"a": a, "b": b}, "mean")
    peak = max(float(v.max()) for v in joint.values())
    assert peak == pytest.approx(0.5, abs=1 / 255)
    assert all(v.dtype == np.float32 and v.max() <= 1.0 for v in joint.values())


def test_coop_eval_reports_every_uav_and_finds_hidden_people(tmp_path):
    report = run_coop_eval([0], frames=90, out_dir=tmp_path)
    by = {(s["uav"], s["variant"]): s for s in report["summary"]}
    assert {u for u, _ in by} == {"uav1", "uav2"}
    hidden = by[("uav1", "memory map + joint map")]["hidden_detected"]
    assert hidden > by[("uav1", "baseline")]["hidden_detected"]
    assert by[("uav1", "memory map + joint map")]["AP50"] > by[("uav1", "baseline")]["AP50"]
    assert (tmp_path / "report.md").read_text().count("| uav1 |") == 3

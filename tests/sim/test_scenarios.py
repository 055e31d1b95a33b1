"""Scenario registry; coop has two overlapping views and a one-sided occlusion; reid objects leave and return."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shared.geo import footprint_local, latlon_to_local
from sim.scenarios import SCENARIOS, get_scenario
from sim.simulator import Simulation


def test_registry_has_the_required_scenarios_with_a_4k_camera() -> None:
    assert {"sea", "grass", "coop", "reid"} <= set(SCENARIOS)
    for name, sc in SCENARIOS.items():
        assert sc.name == name and sc.description
        assert sc.fps == 30.0
        cam = sc.camera
        assert (cam.width, cam.height) == (3840, 2160)
        assert sc.n_videos == len(sc.flights) >= 1
    assert SCENARIOS["sea"].world.cls == "swimmer" and SCENARIOS["grass"].world.cls == "person"
    assert abs(SCENARIOS["sea"].world.origin_lat - 47.6) < 0.2 and abs(SCENARIOS["sea"].world.origin_lon - 9.3) < 0.2
    assert SCENARIOS["grass"].world.n_trees > 0
    assert SCENARIOS["sea"].n_videos >= 3


def test_unknown_scenario_lists_the_valid_names() -> None:
    with pytest.raises(ValueError, match="unknown scenario 'moon'.*coop.*grass.*reid.*sea"):
        get_scenario("moon")
    with pytest.raises(ValueError, match="unknown scenario"):
        get_scenario(["sea"])  # type: ignore[arg-type]


def test_coop_two_uavs_share_a_clock_and_have_overlapping_footprints() -> None:
    sim = Simulation("coop", seed=0, frames=90)
    assert [v.uav for v in sim.videos] == ["uav1", "uav2"]
    assert len({v.group for v in sim.videos}) == 1
    by_step: dict[int, dict[str, object]] = {}
    for fs in sim.frames():
        by_step.setdefault(fs.frame_index, {})[fs.uav] = fs
    overlaps = []
    for step in (0, 45, 89):
        a, b = by_step[step]["uav1"], by_step[step]["uav2"]
        assert a.t == b.t and a.date_time == b.date_time
        fa = footprint_local(sim.camera, a.true_pose, max_range_m=300.0)
        e, n = latlon_to_local(b.true_pose.lat, b.true_pose.lon, a.true_pose.lat, a.true_pose.lon)
        fb = footprint_local(sim.camera, b.true_pose, max_range_m=300.0) + np.array([float(e), float(n)])
        area, _ = cv2.intersectConvexConvex(fa.astype(np.float32), fb.astype(np.float32))
        overlaps.append(area)
        # the two UAVs look at the scene from opposite sides
        dh = abs((a.true_pose.heading_deg - b.true_pose.heading_deg + 180.0) % 360.0 - 180.0)
        assert dh > 120.0
    assert min(overlaps) > 500.0  # square metres seen by both


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coop_one_object_is_occluded_for_one_uav_only(seed: int) -> None:
    sim = Simulation("coop", seed=seed, frames=60)
    hidden: dict[str, list[bool]] = {"uav1": [], "uav2": []}
    for fs in sim.frames():
        o = next(o for o in fs.objects if o.track_id == 1)
        hidden[fs.uav].append(o.in_view and o.occluded)
        if fs.uav == "uav2":
            assert o.visible
    assert all(hidden["uav1"]) and not any(hidden["uav2"])
    facts = sim.facts()["occlusion"]
    assert {"track_id": 1, "occluded_for": "uav1", "visible_for": "uav2"}.items() <= facts[0].items()
    assert any(f["track_id"] == 1 and f["occluded_for"] == "uav1" for f in facts)


def test_coop_occluded_uav_still_gets_weak_candidates_at_the_hidden_object() -> None:
    sim = Simulation("coop", seed=0, frames=90)
    hits = 0
    for fs in sim.frames():
        if fs.uav != "uav1":
            continue
        o = next(o for o in fs.objects if o.track_id == 1)
        x, y, w, h = o.bbox_xywh
        b = fs.candidates.boxes_xywh
        cu, cv = b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2
        near = (np.abs(cu - (x + w / 2)) < w / 2) & (np.abs(cv - (y + h / 2)) < h / 2)
        hits += bool(near.any())
        if near.any():
            assert np.median(fs.candidates.scores[near]) < 0.5
    assert hits > 45  # most frames


@pytest.mark.parametrize("seed", [0, 1])
def test_reid_objects_leave_the_view_and_come_back(seed: int) -> None:
    sim = Simulation("reid", seed=seed, frames=600)
    visible: dict[tuple[int, int], list[bool]] = {}
    for fs in sim.frames():
        for o in fs.objects:
            visible.setdefault((fs.video_id, o.track_id), []).append(o.visible)
    returns = 0
    for seq in visible.values():
        idx = np.flatnonzero(seq)
        returns += int((np.diff(idx) > 30).any()) if len(idx) > 1 else 0  # back after > 1 s away
    assert returns >= 3

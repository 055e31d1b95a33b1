"""Simulation: deterministic per seed, different across seeds, invariants hold for any seed, inputs checked."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import Camera, Pose
from sim.simulator import CATEGORIES, FrameSample, Simulation

SEADRONESSEE_FIELDS = {"gps_latitude", "gps_latitude_ref", "gps_longitude", "gps_longitude_ref", "altitude",
                       "gimbal_pitch", "compass_heading", "gimbal_heading", "speed", "xspeed", "yspeed", "zspeed",
                       "date_time"}


def _digest(frames: list[FrameSample]) -> list[tuple]:
    return [(f.image_id, f.video_id, f.frame_index, f.t, f.true_pose, f.meta,
             tuple((o.track_id, o.lat, o.lon, o.bbox_xywh, o.visible) for o in f.objects),
             f.candidates.boxes_xywh.tobytes(), f.candidates.scores.tobytes(), f.candidates.category_ids.tobytes())
            for f in frames]


@pytest.mark.parametrize("scenario", ["sea", "coop"])
def test_same_seed_gives_identical_frames_and_other_seeds_differ(scenario: str) -> None:
    a = _digest(list(Simulation(scenario, seed=11, frames=20).frames()))
    b = _digest(list(Simulation(scenario, seed=11, frames=20).frames()))
    c = _digest(list(Simulation(scenario, seed=12, frames=20).frames()))
    assert a == b
    assert a != c


def test_frames_restarts_from_the_seed_on_each_call() -> None:
    sim = Simulation("grass", seed=1, frames=10)
    assert _digest(list(sim.frames())) == _digest(list(sim.frames()))


def test_noise_scale_changes_only_the_meta() -> None:
    a = list(Simulation("grass", seed=2, frames=15).frames())
    b = list(Simulation("grass", seed=2, frames=15, noise_scale=2.0).frames())
    for x, y in zip(a, b, strict=True):
        assert x.true_pose == y.true_pose
        np.testing.assert_array_equal(x.candidates.scores, y.candidates.scores)
        assert x.objects == y.objects
    assert any(x.meta != y.meta for x, y in zip(a, b, strict=True))


def test_frame_order_times_and_ids() -> None:
    sim = Simulation("sea", seed=0, frames=12)
    frames = list(sim.frames())
    assert len(frames) == sim.n_frames_total == 36
    assert [f.image_id for f in frames] == list(range(1, 37))
    for v in sim.videos:
        fs = [f for f in frames if f.video_id == v.id]
        assert [f.frame_index for f in fs] == list(range(12))
        np.testing.assert_allclose(np.diff([f.t for f in fs]), 1.0 / 30.0, atol=1e-6)  # UNIX-time float ulp
        assert fs[0].t == v.t0
    starts = [v.t0 for v in sim.videos]
    assert starts == sorted(starts) and starts[0] == 1685613600.0
    assert frames[0].date_time == "2023-06-01T10:00:00.000Z"
    assert sim.categories == CATEGORIES == [{"id": 1, "name": "person", "supercategory": "person"},
                                             {"id": 2, "name": "swimmer", "supercategory": "swimmer"}]
    assert isinstance(sim.camera, Camera)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scenario=st.sampled_from(["sea", "grass", "coop", "reid"]))
def test_invariants_hold_for_any_seed(seed: int, scenario: str) -> None:
    sim = Simulation(scenario, seed=seed, frames=8)
    cam = sim.camera
    track_ids = set()
    for fs in sim.frames():
        assert isinstance(fs.true_pose, Pose)
        assert 10.0 <= fs.true_pose.height_m <= 100.0 and 17.0 <= fs.true_pose.pitch_deg <= 90.0
        if fs.meta is not None:
            assert set(fs.meta) == SEADRONESSEE_FIELDS
            assert 0.0 <= fs.meta["gimbal_pitch"] <= 90.0 and fs.meta["altitude"] > 0.0
        c = fs.candidates
        n = len(c)
        assert c.boxes_xywh.shape == (n, 4) and c.scores.shape == (n,) and c.category_ids.shape == (n,)
        assert np.isfinite(c.boxes_xywh).all()
        assert (c.boxes_xywh[:, 2:] >= 1.0).all()
        assert (c.boxes_xywh[:, 0] + c.boxes_xywh[:, 2] <= cam.width + 1e-9).all()
        assert (c.boxes_xywh[:, 1] + c.boxes_xywh[:, 3] <= cam.height + 1e-9).all()
        assert ((c.scores >= sim.scenario.emulator.score_threshold) & (c.scores < 1.0)).all()
        for o in fs.objects:
            track_ids.add(o.track_id)
            assert o.visible == (o.in_view and not o.occluded)
            assert (o.bbox_xywh is not None) == o.in_view
    assert min(track_ids) == 1


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"scenario": "nope"}, "unknown scenario 'nope'; valid scenarios: coop, coop-slope, grass, hills, reid, sea"),
    ({"scenario": "sea", "seed": -1}, "seed must be a non-negative integer"),
    ({"scenario": "sea", "seed": 1.5}, "seed must be a non-negative integer"),
    ({"scenario": "sea", "seed": True}, "seed must be a non-negative integer"),
    ({"scenario": "sea", "frames": 0}, "frames must be an integer >= 1"),
    ({"scenario": "sea", "frames": 2.0}, "frames must be an integer >= 1"),
    ({"scenario": "sea", "noise_scale": -0.5}, "noise_scale"),
    ({"scenario": "sea", "noise_scale": float("nan")}, "noise_scale"),
])
def test_bad_arguments_raise_clear_errors(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Simulation(**kwargs)


def test_facts_need_a_complete_pass() -> None:
    sim = Simulation("sea", seed=0, frames=3)
    with pytest.raises(RuntimeError, match="complete pass"):
        sim.facts()
    for _ in sim.frames():
        pass
    facts = sim.facts()
    assert len(facts["videos"]) == 3 and len(facts["clutter"]) == 3 * 3

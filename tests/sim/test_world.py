"""World motion (walkers, swimmers) and tree occlusion geometry."""

from __future__ import annotations

import numpy as np
import pytest

from sim.world import Tree, World, WorldParams


def _walk(params: WorldParams, seconds: float, seed: int = 0) -> tuple[World, np.ndarray]:
    world = World(params, np.random.default_rng(seed))
    dt = 1.0 / 30.0
    track = [np.column_stack([world.east_m, world.north_m])]
    for _ in range(int(seconds * 30)):
        world.step(dt)
        track.append(np.column_stack([world.east_m, world.north_m]))
    return world, np.array(track)  # (T, N, 2)


def test_walkers_walk_at_1_2_to_1_5_mps_and_sometimes_pause() -> None:
    params = WorldParams(origin_lat=48.5, origin_lon=9.0, cls="person", n_objects=30, pause_rate_hz=0.05)
    _, track = _walk(params, 60.0)
    speed = np.linalg.norm(np.diff(track, axis=0), axis=2) * 30.0  # (T-1, N) m/s
    moving = speed[speed > 0.01]
    assert moving.min() >= 1.2 - 1e-9 and moving.max() <= 1.5 + 1e-9
    paused_fraction = np.mean(speed < 0.01)
    assert 0.02 < paused_fraction < 0.5


def test_walkers_stay_near_the_boundary() -> None:
    params = WorldParams(origin_lat=48.5, origin_lon=9.0, n_objects=20, spawn_radius_m=20.0, boundary_radius_m=25.0)
    _, track = _walk(params, 120.0)
    assert np.linalg.norm(track, axis=2).max() < 25.0 + 10.0


def test_swimmers_drift_with_a_common_current() -> None:
    params = WorldParams(origin_lat=47.6, origin_lon=9.3, cls="swimmer", n_objects=20)
    world, track = _walk(params, 60.0, seed=4)
    drift = (track[-1] - track[0]) / 60.0  # (N, 2) mean velocity
    current = world.current_en_mps
    assert 0.1 <= np.linalg.norm(current) <= 0.4
    np.testing.assert_allclose(drift.mean(axis=0), current, atol=0.05)
    assert np.std(drift, axis=0).max() < 0.1  # small own motion


def test_fixed_stationary_objects_do_not_move() -> None:
    params = WorldParams(origin_lat=48.5, origin_lon=9.0, n_objects=3, fixed_objects=((1.0, 2.0, True),))
    world, track = _walk(params, 10.0)
    assert world.track_ids.tolist() == [1, 2, 3, 4]
    np.testing.assert_allclose(track[:, 0], [[1.0, 2.0]] * len(track))
    assert np.ptp(track[:, 1:], axis=0).max() > 1.0


def test_a_tree_between_camera_and_object_occludes_it_and_one_behind_does_not() -> None:
    params = WorldParams(origin_lat=48.5, origin_lon=9.0, n_objects=0, n_clutter=0,
                         fixed_trees=(Tree(0.0, -3.5, 2.0, 9.0),))
    world = World(params, np.random.default_rng(0))
    east, north = np.array([0.0, 0.0, 10.0]), np.array([0.0, -8.0, 0.0])
    # camera south of the scene at 30 m: the tree hides the object at the origin but not the one in front
    # of the tree (north = -8) nor one 10 m east
    occ = world.occluded(0.0, -45.0, 30.0, east, north, 0.85)
    assert occ.tolist() == [True, False, False]
    # from the north the tree is behind the object
    assert not world.occluded(0.0, 45.0, 30.0, east[:1], north[:1], 0.85)[0]
    # straight above: the line of sight misses a tree 3.5 m away
    assert not world.occluded(0.0, 0.0, 40.0, east[:1], north[:1], 0.85)[0]
    # a low tree under a steep line of sight does not hide the object
    low = World(WorldParams(origin_lat=48.5, origin_lon=9.0, n_objects=0, n_clutter=0,
                            fixed_trees=(Tree(0.0, -3.5, 2.0, 1.0),)), np.random.default_rng(0))
    assert not low.occluded(0.0, -45.0, 30.0, east[:1], north[:1], 0.85)[0]


def test_bad_world_params_are_rejected() -> None:
    with pytest.raises(ValueError, match="cls"):
        WorldParams(origin_lat=48.5, origin_lon=9.0, cls="car")
    with pytest.raises(ValueError, match="lat/lon"):
        WorldParams(origin_lat=95.0, origin_lon=9.0)

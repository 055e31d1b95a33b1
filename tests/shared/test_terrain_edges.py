"""Second ground points past an edge of the terrain (shared.terrain.edge_alternatives): a bank's lip seen from
above, level ground, and bad input."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import local_to_pixel
from shared.terrain import Terrain, edge_alternatives, pixel_to_terrain
from tests.shared.test_terrain import CAM, HALF_M, local_grid, pose_at

AXIS = np.arange(-HALF_M, HALF_M + 1, dtype=float)
EAST, NORTH = np.meshgrid(AXIS, AXIS[::-1])
#: Looking north from 30 m over the upper level: a bank falls 5 m between 40 and 41 m north, away from the camera.
BANK = Terrain(local_grid(np.where(NORTH <= 40.0, 50.0, 45.0)), 50.0)
POSE = pose_at(0.0, 0.0, height_m=30.0, pitch_deg=35.0, heading_deg=0.0)


def _lip_pixel_v() -> float:
    uv, ok = local_to_pixel(np.array([0.0]), np.array([40.0]), CAM, POSE, terrain=BANK)
    assert ok[0]
    return float(uv[0, 1])


def _alternatives(uv: np.ndarray, probe_px: float, terrain: Terrain = BANK):
    e, n, _, valid = pixel_to_terrain(uv, CAM, POSE, terrain)
    assert valid.all()
    ae, an = edge_alternatives(uv, probe_px, CAM, POSE, terrain, e, n)
    return e, n, ae, an


def test_a_box_at_a_banks_lip_has_its_point_on_the_other_level_as_alternative():
    v = _lip_pixel_v()
    # just below the lip in the image: the upper level near the lip, the alternative on the lower level past it,
    # where the probe above lands
    uv = np.array([[CAM.cx, v + 4.0], [CAM.cx + 200.0, v + 4.0]])
    e, n, ae, an = _alternatives(uv, 10.0)
    assert (n < 40.0).all() and (n > 38.0).all()
    assert (an > 45.0).all()
    pe, pn, pup, _ = pixel_to_terrain(uv - np.array([0.0, 10.0]), CAM, POSE, BANK)
    np.testing.assert_allclose(np.column_stack([ae, an]), np.column_stack([pe, pn]), atol=1e-9)
    np.testing.assert_allclose(pup, -5.0, atol=1e-9)
    # just above it: the lower level, with the upper level at the lip as alternative
    e, n, ae, an = _alternatives(np.array([[CAM.cx, v - 4.0]]), 10.0)
    assert n[0] > 45.0 and 38.0 < an[0] <= 40.0
    # far from the lip (more than the probe) and a probe of 0: none
    far = np.array([[CAM.cx, v + 300.0], [CAM.cx, v - 300.0], [CAM.cx, v + 12.0]])
    assert np.isnan(_alternatives(far, 10.0)[2]).all()
    assert np.isnan(_alternatives(np.array([[CAM.cx, v + 4.0]]), 0.0)[2]).all()


def test_per_box_probes_and_points_without_ground_give_none_for_those():
    v = _lip_pixel_v()
    uv = np.array([[CAM.cx, v + 4.0], [CAM.cx, v + 4.0], [CAM.cx, v + 4.0]])
    e, n, _, _ = pixel_to_terrain(uv, CAM, POSE, BANK)
    e[2] = np.nan
    ae, an = edge_alternatives(uv, np.array([10.0, 2.0, 10.0]), CAM, POSE, BANK, e, n)
    assert np.isfinite(ae[0]) and np.isnan(ae[1:]).all() and np.isnan(an[1:]).all()
    # the probe above passes over everything within the range limit: no alternative either
    ae, an = edge_alternatives(uv[:1], 10.0, CAM, POSE, BANK, e[:1], n[:1], max_range_m=44.0)
    assert np.isnan(ae).all()
    assert edge_alternatives(np.zeros((0, 2)), 5.0, CAM, POSE, BANK, np.zeros(0), np.zeros(0))[0].shape == (0,)


@settings(max_examples=80, deadline=None)
@given(level=st.floats(20.0, 80.0), height=st.floats(10.0, 80.0), pitch=st.floats(30.0, 90.0),
       heading=st.floats(0.0, 360.0), u=st.floats(0.0, CAM.width), v_frac=st.floats(0.5, 1.0),
       probe=st.floats(1.0, 60.0), tilt=st.floats(-0.3, 0.3))
def test_level_and_plane_ground_have_no_edges(level, height, pitch, heading, u, v_frac, probe, tilt):
    # a plane (no edge anywhere; up to 17 deg of slope) at 30-90 deg pitch, pixels in the lower half of the frame (at
    # least the pitch down), probes up to 60 px (0.3 x a 200 px person): the probes' jumps differ by far less than
    # the ratio of 3, also without the 2 m floor (min_jump_m 0: the ratio alone decides)
    terrain = Terrain(local_grid(level + tilt * NORTH), level)
    pose = pose_at(0.0, 0.0, height_m=height, pitch_deg=pitch, heading_deg=heading)
    uv = np.array([[u, v_frac * CAM.height]])
    e, n, _, valid = pixel_to_terrain(uv, CAM, pose, terrain, max_range_m=120.0)
    ae, an = edge_alternatives(uv, probe, CAM, pose, terrain, e, n, max_range_m=120.0, min_jump_m=0.0)
    assert np.isnan(ae).all() and np.isnan(an).all()

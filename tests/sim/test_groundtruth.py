"""Ground-truth boxes agree with shared.geo: the true ground point projected with the true pose is in the box."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon
from sim.groundtruth import MIN_SIZE_PX, project_objects
from sim.simulator import Simulation
from sim.world import CLASS_BOX_M

CAM = Camera.from_preset("dji-mavic2-pro")


@pytest.mark.parametrize("scenario", ["sea", "grass", "coop", "reid"])
def test_true_ground_point_projects_inside_its_box(scenario: str) -> None:
    sim = Simulation(scenario, seed=3, frames=40)
    checked = 0
    for fs in sim.frames():
        for o in fs.objects:
            if not o.visible:
                assert o.in_view or o.bbox_xywh is None
                continue
            uv, ok = latlon_to_pixel([o.lat], [o.lon], sim.camera, fs.true_pose)
            assert ok[0]
            u, v = uv[0]
            x, y, w, h = o.bbox_xywh
            assert w >= MIN_SIZE_PX and h >= MIN_SIZE_PX
            assert 0.0 <= x and x + w <= sim.camera.width + 1e-9 and 0.0 <= y and y + h <= sim.camera.height + 1e-9
            if 0.0 <= u <= sim.camera.width and 0.0 <= v <= sim.camera.height:
                assert x - 1e-6 <= u <= x + w + 1e-6 and y - 1e-6 <= v <= y + h + 1e-6
                checked += 1
    assert checked > 50


def test_nadir_swimmer_box_has_pinhole_size() -> None:
    """Straight down from h metres, a 0.5 x 0.5 x 0.3 m swimmer spans f * 0.5 / (h - 0.3) px at its top."""
    pose = Pose(lat=47.6, lon=9.3, height_m=40.0, pitch_deg=90.0, heading_deg=0.0)
    proj = project_objects(np.array([47.6]), np.array([9.3]), np.array([0.0]), CLASS_BOX_M["swimmer"], CAM, pose)
    x0, y0, x1, y1 = proj.boxes_xyxy[0]
    expected = CAM.fx * 0.5 / (40.0 - 0.3)
    assert x1 - x0 == pytest.approx(expected, rel=1e-6)
    assert y1 - y0 == pytest.approx(expected, rel=1e-6)
    assert (x0 + x1) / 2 == pytest.approx(CAM.cx) and (y0 + y1) / 2 == pytest.approx(CAM.cy)


def test_standing_person_is_taller_than_wide_at_low_pitch() -> None:
    pose = Pose(lat=48.53, lon=9.06, height_m=20.0, pitch_deg=25.0, heading_deg=0.0)
    lat, lon = local_to_latlon(0.0, 20.0 / math.tan(math.radians(25.0)), 48.53, 9.06)
    proj = project_objects(np.atleast_1d(lat), np.atleast_1d(lon), np.array([90.0]), CLASS_BOX_M["person"], CAM, pose)
    x0, y0, x1, y1 = proj.boxes_xyxy[0]
    assert proj.in_view[0]
    assert (y1 - y0) > 2.0 * (x1 - x0)


def test_objects_behind_the_camera_or_beyond_the_horizon_are_not_in_view() -> None:
    pose = Pose(lat=48.53, lon=9.06, height_m=30.0, pitch_deg=20.0, heading_deg=0.0)
    lat, lon = local_to_latlon(np.array([0.0, 0.0]), np.array([-30.0, 40000.0]), 48.53, 9.06)
    proj = project_objects(lat, lon, np.zeros(2), CLASS_BOX_M["person"], CAM, pose)
    assert not proj.in_view.any()
    assert np.isnan(proj.boxes_xyxy).all()


@settings(max_examples=60, deadline=None)
@given(
    height=st.floats(10.0, 100.0), pitch=st.floats(17.0, 90.0), heading=st.floats(0.0, 359.9),
    east=st.floats(-150.0, 150.0), north=st.floats(-150.0, 150.0), yaw=st.floats(0.0, 360.0),
    cls=st.sampled_from(["person", "swimmer"]),
)
def test_box_contains_projected_ground_point_for_any_pose(height, pitch, heading, east, north, yaw, cls) -> None:
    pose = Pose(lat=48.0, lon=9.0, height_m=height, pitch_deg=pitch, heading_deg=heading)
    lat, lon = local_to_latlon(east, north, 48.0, 9.0)
    proj = project_objects(np.atleast_1d(lat), np.atleast_1d(lon), np.array([yaw]), CLASS_BOX_M[cls], CAM, pose)
    if not proj.valid[0]:
        return
    uv, ok = latlon_to_pixel(np.atleast_1d(lat), np.atleast_1d(lon), CAM, pose)
    x0, y0, x1, y1 = proj.boxes_xyxy[0]
    assert ok[0]
    assert x0 - 1e-6 <= uv[0, 0] <= x1 + 1e-6 and y0 - 1e-6 <= uv[0, 1] <= y1 + 1e-6
    if proj.in_view[0]:
        c = proj.clipped_xyxy[0]
        assert c[2] - c[0] >= MIN_SIZE_PX and c[3] - c[1] >= MIN_SIZE_PX
        assert (c[2] - c[0]) * (c[3] - c[1]) >= 0.5 * (x1 - x0) * (y1 - y0) - 1e-6

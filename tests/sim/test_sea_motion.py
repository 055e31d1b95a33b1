"""The moving sea (sim.render.sea_motion.WaveDrift): the texture travels, the glint twinkles, per seed and time."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim.dataset import write_dataset
from sim.render import RenderOptions, SimulatedDataset, WorldRenderer
from sim.render.effects import glint_map
from sim.render.geometry import first_ground_row
from sim.render.sea_motion import WaveDrift
from sim.scenarios import get_scenario

QUIET = RenderOptions(max_texture_px=1024, sensor_noise_std=0.0, sea_events=False, scenery=False)


@pytest.fixture(scope="module")
def sea(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sea-motion") / "data"
    write_dataset(dataclasses.replace(get_scenario("sea"), image_size=(320, 180)), out, seed=0, frames=6,
                  progress=False)
    return out


def _glint_frame(ds: SimulatedDataset, options: RenderOptions):
    """A renderer and a frame (no objects) whose view holds the sun's glint patch."""
    for video in ds.videos:
        renderer = WorldRenderer(ds, ds.worlds[video.group], options)
        frame = next(ds.frames(video))
        glint = glint_map(renderer.camera, frame.pose, renderer.atmosphere,
                          first_ground_row(renderer.camera, frame.pose))
        if glint is not None and (glint[1][2] - glint[1][0]) * (glint[1][3] - glint[1][1]) > 2000:
            return renderer, dataclasses.replace(frame, objects=(), blurred=False), glint[1]
    raise AssertionError("no frame of the fixture sees the glint")


def _brightest(image: np.ndarray, rect: tuple[int, int, int, int], share: float = 0.01) -> np.ndarray:
    x0, y0, x1, y1 = rect
    grey = image[y0:y1, x0:x1].astype(np.float32).sum(axis=2)
    return grey >= np.quantile(grey, 1.0 - share)


def test_the_sea_moves_and_its_glint_twinkles_while_a_frozen_sea_stays(sea):
    ds = SimulatedDataset(sea)
    for waves in (True, False):
        renderer, frame, rect = _glint_frame(ds, dataclasses.replace(QUIET, sea_waves=waves))
        now = renderer.render(frame)
        later = renderer.render(dataclasses.replace(frame, t=frame.t + 0.5))  # same pose, half a second on
        first = first_ground_row(renderer.camera, frame.pose)
        change = np.abs(now[first:].astype(int) - later[first:].astype(int)).mean()
        a, b = _brightest(now, rect), _brightest(later, rect)
        overlap = (a & b).sum() / max((a | b).sum(), 1)
        if waves:
            assert change > 2.0  # the waves travelled ~0.9 m
            assert overlap < 0.3  # other glint facets are lit now
        else:
            assert change == 0.0 and overlap == 1.0


def test_the_moving_sea_is_the_same_for_every_renderer_of_a_seed(sea):
    ds = SimulatedDataset(sea)
    first_renderer, frame, _ = _glint_frame(ds, QUIET)
    second_renderer, _, _ = _glint_frame(ds, QUIET)
    later = dataclasses.replace(frame, t=frame.t + 1.3)
    assert np.array_equal(first_renderer.render(later), second_renderer.render(later))
    assert first_renderer.describe()["waves"] == second_renderer.describe()["waves"]


@given(st.floats(0.0, 360.0), st.floats(0.0, 60.0), st.floats(0.0, 5.0))
def test_the_drift_is_the_phase_speed_times_the_time_towards_the_wind(wind, t, dt):
    drift = WaveDrift(wind)
    (e0, n0), (e1, n1) = drift.offset_en(t, drift.long_mps), drift.offset_en(t + dt, drift.long_mps)
    if (t + dt) < drift.period_s:  # no wrap in between
        assert math.isclose(math.hypot(e1 - e0, n1 - n0), drift.long_mps * dt, abs_tol=1e-6)
        if dt > 0.1:
            assert math.isclose(math.degrees(math.atan2(e1 - e0, n1 - n0)) % 360.0, wind % 360.0, abs_tol=1e-3) \
                or math.isclose(abs(math.degrees(math.atan2(e1 - e0, n1 - n0)) % 360.0 - wind % 360.0), 360.0,
                                abs_tol=1e-3)


@given(st.floats(0.0, 360.0), st.lists(st.floats(-30.0, 200.0), min_size=1, max_size=8))
def test_the_grown_texture_covers_the_ground_at_every_time(wind, times):
    drift = WaveDrift(wind)
    extent = (-50.0, -40.0, 60.0, 70.0)
    g0, gn0, g1, gn1 = drift.grow(extent, np.array(times))
    for t in times:
        for speed in (drift.long_mps, drift.short_mps):
            de, dn = drift.offset_en(t, speed)  # world p shows texel p - offset
            assert g0 - 1e-6 <= extent[0] - de and extent[2] - de <= g1 + 1e-6
            assert gn0 - 1e-6 <= extent[1] - dn and extent[3] - dn <= gn1 + 1e-6


# ---------------------------------------------------------------------------------------------- ground truth

def test_the_unannotated_boxes_hold_the_drawn_buoys_and_boats(sea):
    ds = SimulatedDataset(sea)
    options = dataclasses.replace(QUIET, scenery=True, sea_waves=False)
    kinds, boxes_seen = set(), 0
    for video in ds.videos:
        drawn = WorldRenderer(ds, ds.worlds[video.group], options)
        bare = WorldRenderer(ds, ds.worlds[video.group], options)
        bare.static, bare.scenery = [], []  # the same world without its unannotated objects
        for frame in list(ds.frames(video))[::3]:
            frame = dataclasses.replace(frame, objects=(), blurred=False)
            boxes = drawn.unannotated_boxes(frame)
            if not boxes:
                continue
            diff = np.abs(drawn.render(frame).astype(int) - bare.render(frame).astype(int)).sum(axis=2)
            for kind, (x, y, w, h) in boxes:
                kinds.add(kind)
                assert 0 <= x and 0 <= y and x + w <= 320 + 1e-6 and y + h <= 180 + 1e-6 and w >= 1 and h >= 1
                box = diff[int(y):int(math.ceil(y + h)), int(x):int(math.ceil(x + w))]
                assert box.max() > 30, (kind, x, y, w, h)  # the object is drawn inside its box
                boxes_seen += 1
    assert boxes_seen >= 3 and kinds <= {"buoy", "boat"} and "buoy" in kinds

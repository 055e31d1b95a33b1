"""Transient sea clutter (sim.render.sea_motion): whitecaps and sparkles that come and go, fixed per seed."""

from __future__ import annotations

import numpy as np

from shared.geo import Camera, Pose
from sim.render.sea_motion import BUCKET_S, WHITECAPS, SeaEvents
from sim.render.sprites import _WATER, _washed

EXTENT = (-100.0, -100.0, 100.0, 100.0)


def test_events_are_the_same_for_a_seed_and_differ_for_another():
    a = SeaEvents(1, 0, 107, EXTENT).active(0, 3.0)
    b = SeaEvents(1, 0, 107, EXTENT).active(0, 3.0)
    c = SeaEvents(2, 0, 107, EXTENT).active(0, 3.0)
    assert len(a) > 0
    np.testing.assert_array_equal(a, b)
    assert len(a) != len(c) or not np.array_equal(a, c)


def test_whitecaps_live_less_than_a_second_and_are_replaced_by_others():
    ev = SeaEvents(0, 0, 107, EXTENT)
    now = ev.active(0, 10.0)
    later = ev.active(0, 10.0 + WHITECAPS.life_s[1] + BUCKET_S)
    assert len(now) and len(later)
    # nothing alive now is still alive a lifetime later: the clutter moves, it does not stay put
    assert not set(map(tuple, now[:, :2].round(6))) & set(map(tuple, later[:, :2].round(6)))
    assert np.all((now[:, 5] >= 0) & (now[:, 5] <= WHITECAPS.opacity[1]))
    area = (EXTENT[2] - EXTENT[0]) * (EXTENT[3] - EXTENT[1])
    expected = WHITECAPS.rate_per_m2_s * area * np.mean(WHITECAPS.life_s)
    assert 0.5 * expected < len(now) < 1.5 * expected


def test_whitecaps_are_drawn_in_a_nadir_view_and_only_below_the_first_row():
    cam = Camera(width=320, height=240, fx=200.0, fy=200.0, cx=160.0, cy=120.0)
    pose = Pose(lat=48.0, lon=9.0, height_m=30.0, pitch_deg=90.0, heading_deg=0.0)
    ev = SeaEvents(0, 0, 107, EXTENT, kinds=(WHITECAPS,))
    image = np.full((240, 320, 3), 60, np.uint8)
    drawn = sum(ev.draw(image, cam, pose, (0.0, 0.0), t, 120, None) for t in (1.0, 2.0, 3.0, 4.0))
    assert drawn > 0
    assert (image[120:] > 100).any()
    assert (image[:120] == 60).all()


def test_water_washes_a_swimmers_colour_towards_the_sea():
    cap = (0, 120, 255)
    half = _washed(cap, 0.5)
    assert _washed(cap, 0.0) == cap and _washed(cap, 1.0) == tuple(round(c) for c in _WATER)
    assert max(half) - min(half) < max(cap) - min(cap)

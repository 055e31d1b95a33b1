"""Flights: true poses stay in the paper's envelope; sweeps are fast; orbits look at the centre."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.flight import ClimbSpec, HoverSweepsSpec, KeyframeFlight, LawnmowerSpec, LineSpec, OrbitSpec
from sim.scenarios import SCENARIOS

SPECS = [HoverSweepsSpec(), OrbitSpec(), LawnmowerSpec(), ClimbSpec(), LineSpec()]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spec_index=st.integers(0, len(SPECS) - 1))
def test_every_flight_stays_within_10_100_m_and_17_90_deg(seed: int, spec_index: int) -> None:
    flight = SPECS[spec_index].build(np.random.default_rng(seed), 40.0)
    for t in np.arange(0.0, 40.0, 0.25):
        s = flight.state(float(t))
        assert 10.0 <= s.height_m <= 100.0
        assert 17.0 <= s.pitch_deg <= 90.0
        assert 0.0 <= s.heading_deg < 360.0


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_flights_cover_their_default_duration(name: str) -> None:
    sc = SCENARIOS[name]
    duration = sc.default_frames / sc.fps
    for spec in sc.flights:
        flight = spec.build(np.random.default_rng(0), duration)
        assert flight.duration_s >= duration


def test_hover_sweeps_turn_fast_and_come_back() -> None:
    flight = HoverSweepsSpec(sweep_rate_deg_s=(80.0, 80.0)).build(np.random.default_rng(1), 30.0)
    states = [flight.state(t) for t in np.arange(0.0, 30.0, 1.0 / 30.0)]
    rates = np.abs([s.heading_rate_deg_s for s in states])
    assert rates.max() == pytest.approx(80.0, rel=0.05)
    base = states[0].heading_deg
    back = [abs((s.heading_deg - base + 180.0) % 360.0 - 180.0) < 1e-6 for s in states[1:]]
    assert any(back)  # the sweep returns to the base heading
    positions = {(round(s.east_m, 6), round(s.north_m, 6)) for s in states}
    assert len(positions) == 1  # hovering


def test_orbit_camera_looks_at_the_centre_and_moves_at_the_speed() -> None:
    flight = OrbitSpec(speed_mps=(4.0, 4.0)).build(np.random.default_rng(3), 60.0)
    for t in (0.0, 7.3, 21.0):
        s = flight.state(t)
        bearing_to_centre = math.degrees(math.atan2(-s.east_m, -s.north_m)) % 360.0
        assert (s.heading_deg - bearing_to_centre + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-6)
        assert math.hypot(s.vel_east_mps, s.vel_north_mps) == pytest.approx(4.0, rel=1e-3)
        assert abs((s.aircraft_heading_deg - s.heading_deg) % 360.0 - 180.0) == pytest.approx(90.0, abs=1e-6)


def test_lawnmower_flies_lanes_with_the_camera_along_the_track() -> None:
    flight = LawnmowerSpec().build(np.random.default_rng(5), 60.0)
    for t in np.arange(0.5, 60.0, 0.5):
        s = flight.state(float(t))
        speed = math.hypot(s.vel_east_mps, s.vel_north_mps)
        if speed > 1.0 and abs(s.heading_rate_deg_s) < 1e-6:
            track = math.degrees(math.atan2(s.vel_east_mps, s.vel_north_mps)) % 360.0
            assert (track - s.heading_deg + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1.0)


def test_keyframe_flight_validates_its_input() -> None:
    with pytest.raises(ValueError, match="increasing"):
        KeyframeFlight([0.0, 0.0], [0, 0], [0, 0], [20, 20], [45, 45], [0, 0])
    with pytest.raises(ValueError, match="length"):
        KeyframeFlight([0.0, 1.0], [0], [0, 0], [20, 20], [45, 45], [0, 0])
    with pytest.raises(ValueError, match="height_m"):
        HoverSweepsSpec(height_m=(5.0, 20.0))
    with pytest.raises(ValueError, match="pitch_deg"):
        LineSpec(pitch_deg=(10.0, 20.0))

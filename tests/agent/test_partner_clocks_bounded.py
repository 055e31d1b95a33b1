"""PartnerClocks forgets the UAVs it has not heard for a minute (a day of UAVs coming and going kept them all),
and reads the clocks of the others as before."""

from __future__ import annotations

import pytest

from agent.partner_clocks import PartnerClocks

PARTNER_KEEP_S = 60.0  # agent.partner_clocks.PARTNER_KEEP_S


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_uavs_not_heard_for_a_minute_are_forgotten_on_observe():
    clock = Clock()
    clocks = PartnerClocks(clock=clock)
    for i in range(288):  # a new UAV id every 5 minutes for a day, each heard for 10 s
        for second in range(10):
            clocks.observe(f"visitor{i}", 1000.0 + second)
            clock.now += 1.0
        clock.now += 290.0
    assert list(clocks._history) == ["visitor287"]  # before: all 288 kept
    clock.now += 10.0
    clocks.observe("resident", 5.0)
    assert list(clocks._history) == ["resident"]


def test_read_forgets_too_and_reports_the_others_as_before():
    clock = Clock()
    clocks = PartnerClocks(clock=clock)
    clocks.observe("gone", 100.0)
    for step in range(6):  # a partner at 2 Hz, its clock running at the wall's rate
        clock.now = 1.0 + 0.5 * step
        clocks.observe("partner", 500.0 + 0.5 * step)
    clock.now = 4.0
    (uav, t, age, rate), = clocks.read(2.0)
    assert (uav, t, age) == ("partner", 502.5, pytest.approx(0.5)) and rate == pytest.approx(1.0)
    assert set(clocks._history) == {"gone", "partner"}  # heard 4 s ago: kept, only too old for this read
    clock.now = PARTNER_KEEP_S + 1.0
    assert clocks.read(2.0) == [] and set(clocks._history) == {"partner"}
    clock.now = PARTNER_KEEP_S + 4.0
    assert clocks.read(2.0) == [] and clocks._history == {}

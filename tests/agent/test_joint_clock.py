"""agent.joint_clock: a machine whose clock is behind the joint messages' takes their lead once it is steady,
and nothing else moves it."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.joint_clock import CONFIRM_MESSAGES, CONFIRM_S, MAX_CLOCK_SKEW_S, MAX_LEAD_S, JointClock
from tests.fakeclock import Clocks


def clock_and_time(wall: float = 1.7e9) -> tuple[JointClock, Clocks]:
    clocks = Clocks(wall)
    return JointClock(MAX_CLOCK_SKEW_S, wall=lambda: clocks.wall, monotonic=lambda: clocks.mono), clocks


@given(lead=st.floats(MAX_CLOCK_SKEW_S + 1, 2e9), jitter=st.floats(0.0, 2.0))
def test_a_steady_lead_is_taken_after_the_confirmation_and_kept(lead, jitter):
    clock, clocks = clock_and_time()
    verdicts = []
    for i in range(CONFIRM_MESSAGES + 3):  # one message every 0.5 s, the server's lead plus latency jitter
        verdicts.append(clock.accepts(clocks.wall + lead + (jitter if i % 2 else 0.0)))
        clocks.step(0.5)
    first = verdicts.index(True)
    # CONFIRM_MESSAGES over CONFIRM_S: the fifth message at 2.0 s
    assert first == max(CONFIRM_MESSAGES, int(CONFIRM_S / 0.5) + 1) - 1
    assert all(verdicts[first:])
    assert clock.lead_s == pytest.approx(lead, abs=1e-6 * lead)  # the smallest lead seen
    # later messages up to the skew beyond the lead still pass, ones further ahead do not
    assert clock.accepts(clocks.wall + lead + MAX_CLOCK_SKEW_S - 1)
    assert not clock.accepts(clocks.wall + lead + MAX_CLOCK_SKEW_S + 5)


def test_a_burst_within_a_moment_does_not_move_the_clock():
    clock, clocks = clock_and_time()
    for _ in range(50):  # fifty forged messages within 1 s
        assert not clock.accepts(clocks.wall + 3600.0)
        clocks.step(0.02)
    assert clock.lead_s == 0.0


def test_scattered_messages_ahead_do_not_add_up_beyond_the_evidence_window():
    clock, clocks = clock_and_time()
    for _ in range(20):  # one forged message every 11 s: never five within the window
        assert not clock.accepts(clocks.wall + 600.0)
        clocks.step(11.0)
    assert clock.lead_s == 0.0


@pytest.mark.parametrize("t", [1e300, math.inf, math.nan])
def test_absurd_stamps_stay_rejected_however_many(t):
    clock, clocks = clock_and_time()
    verdicts = []
    for _ in range(40):
        verdicts.append(clock.accepts(t))
        clocks.step(0.5)
    assert not any(verdicts)
    assert clock.lead_s == 0.0


def test_a_clock_behind_by_decades_is_within_reach_but_not_beyond_a_century():
    clock, clocks = clock_and_time(wall=0.0)  # a companion computer that booted at 1970
    for _ in range(CONFIRM_MESSAGES):
        clock.accepts(1.7e9 + clocks.wall)
        clocks.step(0.5)
    assert clock.lead_s == pytest.approx(1.7e9)
    assert MAX_LEAD_S < 1e10


def test_messages_within_the_skew_pass_and_are_no_evidence():
    clock, clocks = clock_and_time()
    for _ in range(20):
        assert clock.accepts(clocks.wall + MAX_CLOCK_SKEW_S - 0.5)
        assert clock.accepts(clocks.wall - 86_400.0)  # from the past (a replayed source clock): fine
        clocks.step(0.5)
    assert clock.lead_s == 0.0


def test_stamps_far_ahead_among_messages_on_time_never_move_the_clock():
    # probe (review): five stamps 31 years ahead spread over 2 s among the server's own messages on time set the lead,
    # and from then on the t_in_future check was off for good
    clock, clocks = clock_and_time()
    for i in range(30):
        assert clock.accepts(clocks.wall - 0.05, "tracks")  # the server's own, on time
        if i % 3 == 0:
            assert not clock.accepts(clocks.wall + 1e9, "tracks")  # forged, interleaved
        clocks.step(0.2)
    assert clock.lead_s == 0.0


def test_tiles_on_a_replayed_past_clock_do_not_hold_back_the_servers_lead():
    # a UAV replaying a 2020 dataset stamps its tiles in the past; the server's tracks run 2 minutes ahead of this clock
    clock, clocks = clock_and_time()
    adopted = []
    for _ in range(15):
        assert clock.accepts(1.6e9, "tiles")
        adopted.append(clock.accepts(clocks.wall + 120.0, "tracks"))
        clocks.step(0.5)
    assert adopted.index(True) == 4 and all(adopted[4:]) and clock.lead_s == pytest.approx(120.0)

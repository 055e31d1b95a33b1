"""agent.joint_clock on shared.clock_lead: the message that confirms a lead is judged against the lead taken."""

from __future__ import annotations

import pytest

from agent.joint_clock import CONFIRM_MESSAGES, MAX_CLOCK_SKEW_S, JointClock


def test_the_message_confirming_a_lead_but_far_beyond_it_stays_rejected():
    # four messages 120 s ahead over 2 s, then a fifth 1e9 s ahead: the lead taken is the run's smallest (120 s),
    # and the fifth, beyond it by far more than the skew, was let in with it
    wall, mono = [1.7e9], [100.0]
    clock = JointClock(MAX_CLOCK_SKEW_S, wall=lambda: wall[0], monotonic=lambda: mono[0])
    for _ in range(CONFIRM_MESSAGES - 1):
        assert not clock.accepts(wall[0] + 120.0, "tiles")
        wall[0] += 0.6
        mono[0] += 0.6
    assert not clock.accepts(wall[0] + 1e9, "tiles")
    assert clock.lead_s == pytest.approx(120.0)
    assert clock.accepts(wall[0] + 121.0, "tiles")

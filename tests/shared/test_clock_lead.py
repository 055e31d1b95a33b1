"""shared.clock_lead: a lead is confirmed only by a steady run of messages, and its memory stays bounded."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from shared.clock_lead import CONFIRM_MESSAGES, CONFIRM_S, EVIDENCE_S, MAX_LEAD_S, LeadEvidence, plausible_lead


@given(leads=st.lists(st.floats(31.0, MAX_LEAD_S), min_size=CONFIRM_MESSAGES, max_size=20),
       spacing_s=st.floats(0.06, 1.0))
def test_a_run_is_confirmed_at_its_smallest_lead_once_it_spans_the_confirmation(leads, spacing_s):
    evidence = LeadEvidence()
    for i, lead in enumerate(leads):
        confirmed = evidence.add(100.0 + i * spacing_s, lead)
        if confirmed is not None:
            assert i + 1 >= CONFIRM_MESSAGES and i * spacing_s >= CONFIRM_S
            assert confirmed == min(leads[:i + 1])
            assert len(evidence) == 0  # taken: the run starts over
            return
    assert len(leads) < CONFIRM_MESSAGES or (len(leads) - 1) * spacing_s < CONFIRM_S


def test_a_flood_within_a_moment_is_never_enough_and_its_memory_stays_small():
    evidence = LeadEvidence()
    for i in range(100_000):  # 100,000 messages within one second
        assert evidence.add(i * 1e-5, 600.0) is None
    assert len(evidence) == 100_000
    assert len(evidence._groups) <= 21  # noqa: SLF001 - the bound is the point: groups of 50 ms


def test_messages_older_than_the_window_leave_the_run():
    evidence = LeadEvidence()
    for i in range(4):
        assert evidence.add(i * 3.0, 120.0) is None  # 0, 3, 6, 9 s
    assert evidence.add(EVIDENCE_S + 0.5, 120.0) is None  # the one at 0 s has left: four within the window
    assert len(evidence) == 4
    assert evidence.add(EVIDENCE_S + 1.0, 119.0) == 119.0


@pytest.mark.parametrize(("lead", "plausible"), [(0.0, True), (-1e12, True), (MAX_LEAD_S, True),
                                                 (MAX_LEAD_S * 1.01, False), (1e300, False), (math.inf, False),
                                                 (math.nan, False)])
def test_only_a_finite_lead_within_a_century_may_be_a_clocks(lead, plausible):
    assert plausible_lead(lead) is plausible

"""The gimbal's readings at a flight log's position times (shared.telemetry.gimbal_track): interpolated, heading on
the short arc, never carried further than the bound."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry.gimbal_track import MIN_HOLD_S, bounded_interp, camera_angles, describe_spans, hold_limit_s


def test_the_hold_is_a_few_of_the_gimbals_own_intervals_and_at_least_a_second():
    assert hold_limit_s(np.arange(0.0, 10.0, 0.1)) == MIN_HOLD_S
    assert hold_limit_s(np.arange(0.0, 10.0, 1.0)) == pytest.approx(3.0)
    assert hold_limit_s([5.0]) == MIN_HOLD_S


@settings(max_examples=200, deadline=None)
@given(times=st.lists(st.floats(0.0, 100.0), min_size=1, max_size=30, unique=True),
       queries=st.lists(st.floats(-20.0, 120.0), min_size=1, max_size=30), hold=st.floats(0.1, 5.0))
def test_a_value_is_never_carried_beyond_the_hold_and_stays_between_its_neighbours(times, queries, hold):
    t_src = np.sort(np.array(times))
    values = np.sin(t_src) * 10.0
    got = bounded_interp(queries, t_src, values, hold)
    distance = np.min(np.abs(np.asarray(queries)[:, None] - t_src[None, :]), axis=1)
    assert np.all(np.isnan(got[distance > 2 * hold]))  # a bracket spans at most 2 * hold
    assert np.all(np.isfinite(got[distance <= hold]))
    finite = np.isfinite(got)
    assert np.all((got[finite] >= values.min() - 1e-9) & (got[finite] <= values.max() + 1e-9))


@settings(max_examples=200, deadline=None)
@given(yaw0=st.floats(0.0, 360.0, exclude_max=True), turn=st.floats(-170.0, 170.0), frac=st.floats(0.0, 1.0))
def test_heading_goes_the_short_way_round_between_two_readings(yaw0, turn, frac):
    heading = camera_angles([frac], [0.0, 1.0], [-45.0, -45.0], [0.0, 0.0], [yaw0, (yaw0 + turn) % 360.0],
                            [True, True], [], [])[2][0]
    assert np.cos(np.radians(heading - (yaw0 + frac * turn))) == pytest.approx(1.0, abs=1e-9)


def test_past_the_hold_there_is_no_pitch_and_the_heading_is_the_vehicles_yaw():
    pitch, roll, heading, stale = camera_angles([0.5, 2.0, 10.0], [0.0, 1.0], [-30.0, -40.0], [1.0, 1.0],
                                                [100.0, 110.0], [True, True], [0.0, 10.0], [200.0, 210.0], 1.0)
    assert list(stale) == [False, False, True]
    assert pitch[:2] == pytest.approx([-35.0, -40.0]) and np.isnan(pitch[2])
    assert heading == pytest.approx([105.0, 110.0, 210.0]) and roll == pytest.approx([1.0, 1.0, 0.0])


def test_runs_are_named_with_their_count_and_times():
    assert describe_spans([0.0, 1.0, 2.0, 3.0, 4.0], [True, False, True, True, False], 0.0) == \
        "1 from 0.0 s to 0.0 s, 2 from 2.0 s to 3.0 s"

"""The autopilot's boot clock (shared.telemetry.mavlink_clock): SYSTEM_TIME offsets and their jumps, reboots found
in a log's boot times, the vehicle's yaw interpolated on the circle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry.mavlink_clock import (
    CLOCK_JUMP_S,
    REBOOT_S,
    UnixClock,
    boot_segments,
    interpolate_yaw_deg,
    yaw_between_deg,
)


@settings(max_examples=200, deadline=None)
@given(y0=st.floats(0, 360, exclude_max=True), step=st.floats(-179, 179), frac=st.floats(0, 1),
       t0=st.floats(0, 1e5), span=st.floats(0.01, 10))
def test_yaw_is_interpolated_on_the_shorter_arc(y0, step, frac, t0, span):
    got = interpolate_yaw_deg([t0 + span, t0], [(y0 + step) % 360, y0], [t0 + frac * span])[0]
    assert 0 <= got < 360
    assert math.cos(math.radians(got - (y0 + frac * step))) == pytest.approx(1.0, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(y0=st.floats(0, 360, exclude_max=True), step=st.floats(-179, 179), frac=st.floats(0, 1))
def test_one_yaw_between_two_samples_is_the_arrays_one(y0, step, frac):
    one = yaw_between_deg(10.0, y0, 11.0, (y0 + step) % 360, 10.0 + frac)
    assert 0 <= one < 360
    many = interpolate_yaw_deg([10.0, 11.0], [y0, (y0 + step) % 360], [10.0 + frac])[0]
    assert math.cos(math.radians(one - many)) == pytest.approx(1.0, abs=1e-12)


def test_yaw_is_nan_where_no_sample_brackets_the_time_and_exact_at_a_sample():
    got = interpolate_yaw_deg([1.0, 2.0], [350.0, 10.0], [0.5, 1.0, 1.5, 2.0, 2.5])
    assert np.isnan(got[[0, 4]]).all()
    assert got[1:4] == pytest.approx([350.0, 0.0, 10.0])
    assert np.isnan(interpolate_yaw_deg([], [], [1.0])).all()


@settings(max_examples=100, deadline=None)
@given(offset=st.floats(1e9, 2e9), steps=st.lists(st.floats(-3600, 3600).filter(lambda s: abs(s) > CLOCK_JUMP_S),
                                                  max_size=3),
       jitter=st.lists(st.floats(-0.01, 0.01), min_size=12, max_size=12))
def test_the_unix_clock_is_the_one_after_its_last_jump(offset, steps, jitter):
    clock = UnixClock()
    boot, now = 100.0, offset
    for step in [0.0, *steps]:
        now += step
        for j in jitter[:4]:
            clock.add(boot, now + j)
            boot += 1.0
    assert clock.offset_s == pytest.approx(now + jitter[0], abs=1e-6)
    assert [s for _, s in clock.jumps] == pytest.approx(steps, abs=0.03)


@settings(max_examples=100, deadline=None)
@given(first_s=st.floats(REBOOT_S + 0.1, 3600), again_s=st.floats(0, 3600), gap_s=st.floats(0, 600))
def test_a_boot_time_going_back_while_the_log_goes_on_is_a_new_boot(first_s, again_s, gap_s):
    """Boot 1 runs to `first_s`; boot 2 restarts at `again_s` (anything more than REBOOT_S behind) after `gap_s`."""
    if again_s >= first_s - REBOOT_S:
        again_s = first_s - REBOOT_S - 0.1
    boots = np.r_[np.linspace(0, first_s, 20), np.nan, again_s + np.arange(5.0)]
    stamps = np.r_[1e9 + np.linspace(0, first_s, 20), 1e9 + first_s, 1e9 + first_s + gap_s + np.arange(5.0)]
    assert boot_segments(stamps, boots).tolist() == [0] * 21 + [1] * 5


@settings(max_examples=100, deadline=None)
@given(late_s=st.floats(REBOOT_S + 0.1, 60), burst=st.integers(1, 40), rate=st.sampled_from([5.0, 10.0, 50.0]))
def test_a_burst_repeated_late_while_the_stream_goes_on_is_no_reboot(late_s, burst, rate):
    """A link buffer flushed: `burst` messages of boot time 10 s.. received `late_s` later, between the stream's own
    messages (it was taken for a reboot: a warning and duplicate records)."""
    boots = np.arange(0.0, 120.0, 1.0 / rate)
    stamps = 1e9 + boots
    repeat = boots[(boots >= 10.0) & (boots < 10.0 + late_s)][:burst]  # what the stream had sent by then
    at = np.searchsorted(stamps, stamps[0] + 10.0 + late_s)
    boots = np.r_[boots[:at], repeat, boots[at:]]
    stamps = np.r_[stamps[:at], stamps[at - 1] + 1e-4 * np.arange(1, len(repeat) + 1), stamps[at:]]
    assert boot_segments(stamps, boots).tolist() == [0] * len(boots)


def test_late_repeats_and_small_disorder_are_no_reboot():
    boots = np.array([10.0, 11.0, 12.0, 10.5, 13.0, 2.0, 14.0])
    stamps = np.array([1.0, 2.0, 3.0, 3.1, 4.0, 1.5, 5.0])  # 2.0: a repeat logged with its old receive time
    assert boot_segments(stamps, boots).tolist() == [0] * 7

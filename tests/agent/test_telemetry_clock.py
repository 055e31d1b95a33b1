"""Telemetry on the frame clock (agent.telemetry_clock): time zones removed, samples recognised, poses at frame
time, and a stand-down where the stamps do not follow the frames."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.telemetry_clock import TelemetryClockSettings, TelemetryTrack, reconcile_clock


def _values(n: int, heading0: float = 10.0, rate: float = 5.0) -> np.ndarray:
    """(n, 5): a UAV turning at `rate` degrees per sample."""
    k = np.arange(n, dtype=float)
    return np.column_stack([47.6 + 1e-6 * k, 9.3 + 1e-6 * k, np.full(n, 30.0), heading0 + rate * k,
                            np.full(n, 40.0)])


def _seadronessee_video(frames: int = 40, zone_s: float = 7200.0, step_s: float = 0.5, phase_s: float = 0.647):
    """Frames every 0.5 s in local time; a 1 Hz log stamped in UTC at whole seconds, each sample carried by
    the frames nearest its second (as the real file does)."""
    frame_t = 1_598_357_960.0 + phase_s + step_s * np.arange(frames)
    stamp = np.round(frame_t) - zone_s
    samples = stamp - stamp[0]
    values = _values(int(samples.max()) + 1)[samples.astype(int)]
    return frame_t, stamp, values


def test_the_real_files_clocks_are_reconciled():
    frame_t, stamp, values = _seadronessee_video()
    track, report = reconcile_clock(frame_t, stamp, values, np.ones(len(frame_t), bool))
    assert report.zone_offset_s == 7200.0 and report.whole_seconds and report.stamps_used
    assert report.samples == 20 and report.held_frames == 20  # each sample on two frames
    assert abs(report.residual_s) < 0.5  # whole-second rounding left for the clock-offset estimate
    assert np.allclose(track.t, np.unique(stamp) + 7200.0)
    # a frame between two samples gets the heading between them, not the one it carries
    mid = track.at(frame_t[2])[0]
    assert 10.0 + 5.0 * 0.5 < mid[3] < 10.0 + 5.0 * 1.5
    assert "zone offset +2 h removed" in report.describe()


def test_clocks_that_agree_are_left_alone_and_samples_keep_their_stamps():
    t = 1000.0 + np.arange(30) / 30.0
    stamp = np.floor((t - 0.05) * 10.0) / 10.0  # 10 Hz telemetry held on 30 fps frames, 50 ms late
    values = _values(400)[np.round((stamp - 1000.0) * 10).astype(int) + 1]
    track, report = reconcile_clock(t, stamp, values, np.ones(30, bool))
    assert report.zone_offset_s == 0.0 and report.stamps_used and not report.whole_seconds
    assert np.allclose(track.t, np.unique(stamp))


def test_several_samples_under_one_whole_second_stamp_are_spread_over_the_second():
    # a 10 Hz log stamped at whole seconds: ten different values share one stamp
    t = 5000.0 + np.arange(40) / 10.0
    stamp = np.floor(t)
    values = _values(40)
    track, report = reconcile_clock(t, stamp, values, np.zeros(40, bool))
    assert report.whole_seconds and report.samples == 40
    assert np.allclose(track.t, t)  # spread evenly: k / 10 s into each second


def test_a_difference_that_is_not_a_time_zone_stands_the_stamps_down():
    frame_t, stamp, values = _seadronessee_video(zone_s=7200.0 - 400.0)  # 1 h 53 min 20 s: no zone
    track, report = reconcile_clock(frame_t, stamp, values, np.ones(len(frame_t), bool))
    assert not report.stamps_used and report.zone_offset_s == 0.0 and "quarter hours" in report.reason
    first = np.searchsorted(np.r_[True, np.any(values[1:] != values[:-1], axis=1)].cumsum() - 1, np.arange(20))
    assert np.allclose(track.t, frame_t[first])  # where the values first appear in the frames
    spread = stamp + np.where(np.arange(len(stamp)) > 20, 3600.0, 0.0)  # a log that jumps by an hour midway
    _, report = reconcile_clock(frame_t, spread, values, np.ones(len(frame_t), bool))
    assert not report.stamps_used and "spread" in report.reason


def test_frames_without_their_own_clock_share_the_stamps_clock():
    frame_t, stamp, values = _seadronessee_video()
    track, report = reconcile_clock(stamp, stamp, values, np.zeros(len(stamp), bool))
    assert report.zone_offset_s == 0.0 and report.stamps_used
    assert np.allclose(track.t, np.unique(stamp))


def test_track_interpolation_turns_the_short_way_and_holds_its_ends():
    track = TelemetryTrack(np.array([0.0, 1.0]), np.array([[0, 0, 10, 350, 30], [0, 0, 20, 10, 50]], float))
    assert track.at(0.5)[0, 3] == pytest.approx(0.0)  # 350 -> 10 through north
    assert track.at(-3.0)[0, 2] == 10.0 and track.at(9.0)[0, 2] == 20.0
    assert track.at(0.25)[0, 4] == pytest.approx(35.0)
    with pytest.raises(ValueError, match="increase"):
        TelemetryTrack(np.array([1.0, 1.0]), np.zeros((2, 5)))
    with pytest.raises(ValueError, match="no samples"):
        TelemetryTrack(np.zeros(0), np.zeros((0, 5))).at(0.0)


def test_bad_inputs_and_settings_are_named():
    with pytest.raises(ValueError, match="same length"):
        reconcile_clock(np.zeros(3), np.zeros(2), np.zeros((3, 5)), np.ones(3, bool))
    with pytest.raises(ValueError, match="zone_tolerance_s"):
        TelemetryClockSettings(zone_tolerance_s=500.0)
    with pytest.raises(ValueError, match="max_spread_s"):
        TelemetryClockSettings(max_spread_s=0.0)
    track, report = reconcile_clock(np.zeros(0), np.zeros(0), np.zeros((0, 5)), np.zeros(0, bool))
    assert len(track) == 0 and report.frames == 0


@settings(max_examples=60, deadline=None)
@given(zone_q=st.integers(-56, 56), lag=st.floats(-60.0, 60.0), n=st.integers(4, 60),
       hold=st.integers(1, 4))
def test_property_any_whole_quarter_hour_zone_is_found(zone_q, lag, n, hold):
    zone = 900.0 * zone_q
    frame_t = 1.6e9 + np.arange(n * hold) * 0.25
    stamp = np.repeat(1.6e9 + np.arange(n) * 0.25 * hold, hold) - zone - lag  # sample and hold, `lag` late
    values = np.repeat(_values(n), hold, axis=0)
    track, report = reconcile_clock(frame_t, stamp, values, np.ones(len(frame_t), bool))
    assert report.stamps_used and report.zone_offset_s == zone
    assert report.samples == n and report.frames == n * hold
    assert report.residual_s == pytest.approx(float(np.median(frame_t - stamp)) - zone, abs=1e-6)
    assert abs(report.residual_s - lag) <= 0.25 * hold  # what is left is the lag and the hold
    assert np.all(np.diff(track.t) > 0)


@settings(max_examples=60, deadline=None)
@given(d=st.floats(0.001, 0.05), speed=st.floats(0.008, 0.02), east=st.booleans(), frac=st.floats(0.0, 1.0))
def test_property_longitude_is_interpolated_the_short_way_across_the_antimeridian(d, speed, east, frac):
    # a UAV d degrees short of the antimeridian flying across it at `speed` degrees a sample, east or west
    n = 8  # 7 steps of >= 0.008 deg carry it across
    sign = 1.0 if east else -1.0
    lon0 = sign * (180.0 - d)
    lons = (lon0 + sign * speed * np.arange(n) + 180.0) % 360.0 - 180.0
    assert np.any(np.abs(np.diff(lons)) > 180.0)  # the samples do jump from +-180 to -+180
    values = np.column_stack([np.full(n, -17.0), lons, np.full(n, 40.0), np.zeros(n), np.full(n, 60.0)])
    track = TelemetryTrack(np.arange(n, dtype=float), values)
    t = frac * (n - 1)
    lon = float(track.at(t)[0, 1])
    assert -180.0 <= lon < 180.0
    want = lon0 + sign * speed * t
    assert abs((lon - want + 180.0) % 360.0 - 180.0) < 1e-9  # on the arc the UAV flew, never the long way round
    np.testing.assert_allclose((track.at(np.arange(n))[:, 1] - lons + 180.0) % 360.0 - 180.0, 0.0, atol=1e-9)

"""The tracker benchmark's track-lending row: every track lent, timed against the tracker of the same run."""

import math

from benchmarks.bench_tracker import _lending_ms


def test_lending_every_track_is_timed_per_frame():
    ms = _lending_ms(100)  # 20 frames a call: the quickest set-up
    assert math.isfinite(ms) and ms > 0

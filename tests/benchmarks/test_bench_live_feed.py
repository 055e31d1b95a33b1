"""The live-feed benchmark runs on a real feed over loopback and receives the whole flight it sends."""

from __future__ import annotations

import pytest

pytest.importorskip("pymavlink")


def test_the_live_feed_benchmark_measures_both_cases_on_the_whole_flight():
    from benchmarks.bench_live_feed import run

    rows = run(quick=True)
    assert [r["unit"] for r in rows] == ["ms/frame", "ms/frame"]
    assert "(3000 of 3000, 5 min at 10 Hz)" in rows[0]["case"]  # no datagram lost: the baseline is the flight's
    assert rows[1]["baseline_name"] == "every record" and rows[1]["ratio"] > 0

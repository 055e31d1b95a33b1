"""The global tracker's benchmark runs and reports re-association's cost beside the tracker without it."""

import math

from benchmarks.bench_global_tracks import run


def test_the_quick_run_reports_the_cost_ratio_and_the_pairing():
    rows = run(quick=True)
    assert len(rows) == 4
    cost = rows[1]
    assert cost["baseline_name"] == "without" and math.isfinite(cost["ratio"]) and cost["ratio"] > 0
    assert all(math.isfinite(r["value"]) and r["value"] > 0 for r in rows[:2])
    # the quick field is sparse: every person is on one global id on both UAVs of its pair, with or without
    assert rows[2]["value"] == rows[3]["value"] == 100.0

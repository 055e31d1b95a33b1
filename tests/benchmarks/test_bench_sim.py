"""`uavmm bench sim` times each scenario after a warm-up against serialising and writing the same files, measured in
the same run (it compared with the video's duration, a constant, and its first scenario paid the first-call costs)."""

from __future__ import annotations

import json
from pathlib import Path

import sim.dataset
from benchmarks import bench_sim


def test_each_scenario_is_warmed_up_and_compared_with_writing_its_own_json(monkeypatch):
    calls: list[tuple[str, int]] = []

    def write_dataset(name, out_dir, *, seed, frames, progress):
        calls.append((name, frames))
        Path(out_dir).mkdir(parents=True)
        (Path(out_dir) / "truth.json").write_text(json.dumps({"frames": list(range(frames))}))

    monkeypatch.setattr(sim.dataset, "write_dataset", write_dataset)
    rows = bench_sim.run(quick=True)
    assert calls == [(name, frames) for name in bench_sim.SCENARIOS for frames in (5, 100)]
    timed = [r for r in rows if r["unit"] == "s" and "baseline_name" in r]
    assert len(timed) == len(bench_sim.SCENARIOS)
    for row in timed:
        scenario = row["case"].split(":")[0]
        alone = next(r for r in rows if r["case"] == f"{scenario}: its JSON serialised + written alone")
        assert row["baseline_name"] == "its JSON serialised + written"
        assert row["ratio"] == row["value"] / alone["value"]

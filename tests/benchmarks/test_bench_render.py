"""`uavmm bench --quick render` draws the first flight of each scenario: every flight's ground set-up, done twice
per image size, made the smoke run take three minutes."""

from __future__ import annotations

import pytest

import sim.dataset
import sim.render
from benchmarks import bench_render
from sim.scenarios import get_scenario


@pytest.mark.parametrize("quick", [True, False])
def test_quick_draws_one_flight_per_scenario_and_the_full_run_every_flight(monkeypatch, quick):
    flights: list[tuple[str, int]] = []

    def write_dataset(scenario, out_dir, *, seed, frames, progress):
        flights.append((scenario.name, scenario.n_videos))

    monkeypatch.setattr(sim.dataset, "write_dataset", write_dataset)
    monkeypatch.setattr(bench_render, "_draw_and_warp_s", lambda data: ([0.02], [0.01], 1.0, 30.0, 1))
    monkeypatch.setattr(sim.render, "render_dataset", lambda data, **kw: {"frames_per_s": 20.0})
    rows = bench_render.run(quick=quick)
    expected = {name: 1 if quick else get_scenario(name).n_videos for name in ("sea", "grass")}
    assert flights == [(name, n) for name, n in expected.items() for _ in bench_render.SIZES]
    assert rows[0]["case"].startswith(f"sea 1920x1080, {expected['sea']} flight")

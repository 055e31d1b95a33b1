"""Benchmark timing: cases compared in one row are sampled in turns, so load that changes during a run falls on the
subject and its baseline alike."""

from __future__ import annotations

import pytest

from benchmarks import timing


class _LoadedClock:
    """perf_counter of a machine whose load grows with time: a call of `cost` seconds takes cost * (1 + now)."""

    def __init__(self) -> None:
        self.now = 0.0
        self.calls: list[str] = []

    def perf_counter(self) -> float:
        return self.now

    def work(self, name: str, cost_s: float):
        def fn() -> None:
            self.calls.append(name)
            self.now += cost_s * (1.0 + self.now)
        return fn


def test_interleaved_samples_warm_up_each_case_then_take_turns(monkeypatch):
    clock = _LoadedClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock.perf_counter)
    samples = timing.interleaved_samples_s({"a": clock.work("a", 0.1), "b": clock.work("b", 0.1)}, repeat=3,
                                           min_time_s=0.0)
    assert clock.calls == ["a", "a", "b", "b", "a", "b", "a", "b", "a", "b"]  # warm-up + calibration, then rounds
    assert [len(v) for v in samples.values()] == [3, 3]


def test_the_paired_ratio_holds_while_the_load_grows(monkeypatch):
    clock = _LoadedClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock.perf_counter)
    samples = timing.interleaved_samples_s({"baseline": clock.work("baseline", 0.01),
                                            "subject": clock.work("subject", 0.02)}, repeat=7, min_time_s=0.0)
    assert timing.paired_ratio(samples["subject"], samples["baseline"]) == pytest.approx(2.0, rel=0.05)
    # measured one after the other, as the benchmarks did, the later case also pays the load that came meanwhile
    clock = _LoadedClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock.perf_counter)
    baseline = timing.median_time_s(clock.work("baseline", 0.01), repeat=7, min_time_s=0.0)
    subject = timing.median_time_s(clock.work("subject", 0.02), repeat=7, min_time_s=0.0)
    assert subject / baseline > 2.2


def test_median_time_batches_calls_up_to_the_minimum_sample_time(monkeypatch):
    clock = _LoadedClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock.perf_counter)
    fn = clock.work("f", 0.0)

    def fixed() -> None:  # 10 ms a call whatever the load
        fn()
        clock.now += 0.01

    assert timing.median_time_s(fixed, repeat=3, min_time_s=0.05) == pytest.approx(0.01)
    assert len(clock.calls) == 1 + (1 + 2 + 4 + 8) + 3 * 8  # warm-up, calibration up to 8 calls, 3 samples of 8

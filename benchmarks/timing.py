"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np


def _loops_for(fn: Callable[[], Any], min_time_s: float) -> int:
    """Calls of fn per sample so that a sample lasts at least min_time_s (doubling from 1; fn runs meanwhile)."""
    loops = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(loops):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time_s or loops >= 1 << 20:
            return loops
        loops *= 2


def median_time_s(fn: Callable[[], Any], *, repeat: int = 7, min_time_s: float = 0.05) -> float:
    """Median wall time of fn() in seconds over `repeat` samples, each at least min_time_s long."""
    return float(np.median(interleaved_samples_s({"fn": fn}, repeat=repeat, min_time_s=min_time_s)["fn"]))


def interleaved_samples_s(fns: Mapping[str, Callable[[], Any]], *, repeat: int = 7,
                          min_time_s: float = 0.05) -> dict[str, list[float]]:
    """Seconds per call of each fn, `repeat` samples each, taken in turns: round k samples every fn once, so a
    change of the machine's load between two samples falls on all of them alike (compare them with
    `paired_ratio`). Each fn is called once first (warm-up: imports, caches, compiled kernels), then in batches
    of at least min_time_s (min_time_s 0: one call a sample; fn runs 2 + repeat times in all).

    Returns name -> list of `repeat` seconds per call, in the order of fns.
    """
    loops = {}
    for name, fn in fns.items():
        fn()  # warm-up: imports, caches, JIT-like first-call costs
        loops[name] = _loops_for(fn, min_time_s)
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            for _ in range(loops[name]):
                fn()
            samples[name].append((time.perf_counter() - t0) / loops[name])
    return samples


def paired_ratio(subject: Sequence[float], baseline: Sequence[float]) -> float:
    """Median of the per-round ratios subject[k] / baseline[k] of two `interleaved_samples_s` lists."""
    return float(np.median(np.asarray(subject, dtype=float) / np.asarray(baseline, dtype=float)))

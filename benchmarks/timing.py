"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np


def median_time_s(fn: Callable[[], Any], *, repeat: int = 7, min_time_s: float = 0.05) -> float:
    """Median wall time of fn() in seconds over `repeat` samples, each at least min_time_s long."""
    fn()  # warm-up: imports, caches, JIT-like first-call costs
    loops = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(loops):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time_s or loops >= 1 << 20:
            break
        loops *= 2
    samples = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(loops):
            fn()
        samples.append((time.perf_counter() - t0) / loops)
    return float(np.median(samples))

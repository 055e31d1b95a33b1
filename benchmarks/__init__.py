"""Performance benchmarks, run by `uavmm bench`.

Each module has DESCRIPTION and run(quick) -> list of rows; a row reports a measured figure and
the baseline measured in the same run, so results are ratios that hold across machines.
"""

from __future__ import annotations

import importlib
import json
import platform
from pathlib import Path
from types import ModuleType
from typing import Any

# name -> module in this package; loaded on use so `uavmm bench --list` stays fast.
BENCHMARK_MODULES: dict[str, str] = {
    "geo": "benchmarks.bench_geo",
    "terrain": "benchmarks.bench_terrain",
    "memory_map": "benchmarks.bench_memory_map",
    "sim": "benchmarks.bench_sim",
    "fusion": "benchmarks.bench_fusion",
    "tracker": "benchmarks.bench_tracker",
    "hostile": "benchmarks.bench_hostile",
    "render": "benchmarks.bench_render",
    "anomaly": "benchmarks.bench_anomaly",
    "view_cuts": "benchmarks.bench_view_cuts",
    "live_feed": "benchmarks.bench_live_feed",
}


def load_benchmark(name: str) -> ModuleType:
    """The benchmark module registered under name; ValueError listing the valid names."""
    if name not in BENCHMARK_MODULES:
        raise ValueError(f"unknown benchmark {name!r}; valid: {', '.join(BENCHMARK_MODULES)}")
    return importlib.import_module(BENCHMARK_MODULES[name])


def run_benchmarks(names: list[str] | None = None, *, quick: bool = False,
                   json_path: Path | None = None) -> list[dict[str, Any]]:
    """Run the named benchmarks (all when None) and return their rows."""
    names = list(BENCHMARK_MODULES) if not names else names
    modules = {name: load_benchmark(name) for name in names}
    rows: list[dict[str, Any]] = []
    for name, module in modules.items():
        for row in module.run(quick=quick):
            rows.append({"benchmark": name, **row})
    if json_path is not None:
        meta = {"python": platform.python_version(), "machine": platform.machine(), "quick": quick}
        Path(json_path).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """Rows as an aligned text table: benchmark, case, value, unit, baseline, ratio."""
    header = ("benchmark", "case", "value", "unit", "baseline", "ratio")
    lines = [header]
    for r in rows:
        lines.append((
            r["benchmark"], r["case"], f"{r['value']:.4g}", r["unit"],
            r.get("baseline_name", "-"), "-" if r.get("ratio") is None else f"{r['ratio']:.3g}",
        ))
    widths = [max(len(str(line[i])) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(line, widths, strict=True)) for line in lines)

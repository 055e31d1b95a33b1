"""Performance benchmarks, run by `uavmm bench`.

Each module has DESCRIPTION and run(quick) -> list of rows; a row reports a measured figure and
the baseline measured in the same run, so results are ratios that hold across machines.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import math
import os
import platform
import stat
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from shared.files import PendingFile, write_chunks_atomic

# name -> module in this package; loaded on use so `uavmm bench --list` stays fast.
BENCHMARK_MODULES: dict[str, str] = {
    "geo": "benchmarks.bench_geo",
    "terrain": "benchmarks.bench_terrain",
    "memory_map": "benchmarks.bench_memory_map",
    "sim": "benchmarks.bench_sim",
    "fusion": "benchmarks.bench_fusion",
    "tracker": "benchmarks.bench_tracker",
    "global_tracks": "benchmarks.bench_global_tracks",
    "hostile": "benchmarks.bench_hostile",
    "render": "benchmarks.bench_render",
    "anomaly": "benchmarks.bench_anomaly",
    "view_cuts": "benchmarks.bench_view_cuts",
    "live_feed": "benchmarks.bench_live_feed",
    "detect": "benchmarks.bench_detect",
}


def load_benchmark(name: str) -> ModuleType:
    """The benchmark module registered under name; ValueError listing the valid names."""
    if name not in BENCHMARK_MODULES:
        raise ValueError(f"unknown benchmark {name!r}; valid: {', '.join(BENCHMARK_MODULES)}")
    return importlib.import_module(BENCHMARK_MODULES[name])


#: --json paths that name this process's standard output: written through sys.stdout, so that what the command
#: prints after stays in order and a file stdout is redirected to is appended to, not replaced
_STDOUT_PATHS = frozenset({"/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"})


def results_target(json_path: Path) -> tuple[Path, bool]:
    """Where the results go: (path, direct). An existing path that is not a regular file (a character device, a
    pipe, or a link to one: ``--json /dev/stdout``) is written directly, as it is (direct True); a link to a file
    is replaced at its target, whole (the link stays); anything else is written whole at its own path."""
    path = Path(json_path)
    try:
        mode = path.stat().st_mode
    except OSError:
        return path, False
    if not stat.S_ISREG(mode):
        return path, True
    return Path(os.path.realpath(path)), False


def check_results_path(json_path: Path) -> None:
    """ValueError in one line when the results cannot be written to json_path: a folder, a folder that does not
    exist, or one this process cannot create a file in (a temporary is created beside it and removed). Checked
    before the benchmarks run, so minutes of work do not end in an error about the file."""
    path = Path(json_path)
    if str(path) in _STDOUT_PATHS:
        return
    if path.is_dir():
        raise ValueError(f"{path} is a directory: give the results file's path")
    path, direct = results_target(path)
    if direct:  # a device or a pipe (/dev/stdout): written as it is, nothing to probe (a FIFO would block)
        return
    if not path.parent.is_dir():
        raise ValueError(f"output directory {path.parent} does not exist (for {path})")
    try:
        PendingFile(path).discard()
    except OSError as exc:
        raise ValueError(f"cannot write the results file {path}: {exc.strerror or exc}") from None


def machine_meta() -> dict[str, Any]:
    """Where the figures were measured: CPU model and count, load, OS, Python and the numeric libraries' versions."""
    meta: dict[str, Any] = {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu_model": _cpu_model(),
        "machine": platform.machine(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    for module, distribution in (("cv2", "opencv-python-headless"), ("numba", "numba"), ("scipy", "scipy"),
                                 ("onnxruntime", "onnxruntime"), ("zenoh", "eclipse-zenoh")):
        meta[module] = _version(module, distribution)
    return meta


def _version(module: str, distribution: str) -> str | None:
    """The module's __version__, else its installed distribution's; None when neither is there."""
    try:
        return str(importlib.import_module(module).__version__)
    except (ImportError, AttributeError):
        pass
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def _cpu_model() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _plain(value: Any) -> Any:
    """value with numpy scalars as Python numbers and non-finite floats as None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def run_benchmarks(names: list[str] | None = None, *, quick: bool = False, json_path: Path | None = None,
                   progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Run the named benchmarks (all when None) and return their rows.

    Unknown names and an unusable json_path raise ValueError before any benchmark runs. json_path: the rows and
    `machine_meta` with the start and end times (UTC) and load averages, written whole (`write_chunks_atomic`).
    progress: called with one line before and after each benchmark (the CLI prints them to stderr).
    """
    names = list(BENCHMARK_MODULES) if not names else list(dict.fromkeys(names))
    modules = {name: load_benchmark(name) for name in names}
    if json_path is not None:
        check_results_path(json_path)
    started, load_before = _utc_now(), _load_average()
    rows: list[dict[str, Any]] = []
    for name, module in modules.items():
        if progress is not None:
            progress(f"bench {name}{' --quick' if quick else ''}: running")
        t0 = time.perf_counter()
        produced = module.run(quick=quick)
        if progress is not None:
            progress(f"bench {name}: {len(produced)} rows in {time.perf_counter() - t0:.0f} s")
        rows.extend({"benchmark": name, **row} for row in produced)
    if json_path is not None:
        meta = {**machine_meta(), "quick": quick, "benchmarks": names, "started_utc": started,
                "finished_utc": _utc_now(), "load_average_before": load_before, "load_average_after": _load_average()}
        text = json.dumps(_plain({"meta": meta, "rows": rows}), indent=2, allow_nan=False) + "\n"
        target, direct = results_target(Path(json_path))
        if str(json_path) in _STDOUT_PATHS:
            sys.stdout.write(text)
            sys.stdout.flush()
        elif direct:
            with open(target, "w") as handle:
                handle.write(text)
        else:
            write_chunks_atomic(target, [text])
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

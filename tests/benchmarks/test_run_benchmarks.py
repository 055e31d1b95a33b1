"""`uavmm bench`: bad input is refused in one line before any benchmark runs, and --json is written whole, as strict
JSON, saying on which machine and when the figures were measured."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

import benchmarks.bench_geo
from benchmarks import run_benchmarks
from uavmm.cli import main


@pytest.fixture
def geo_runs(monkeypatch):
    """bench geo replaced by a stub that records its runs and returns a numpy scalar and a NaN ratio."""
    runs: list[bool] = []

    def run(quick: bool = False):
        runs.append(quick)
        return [{"case": "stub", "value": np.float32(1.5), "unit": "ms", "baseline_name": "nothing",
                 "ratio": float("nan"), "count": np.int64(3)}]

    monkeypatch.setattr(benchmarks.bench_geo, "run", run)
    return runs


def _error_lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if not line.startswith("bench ")]


def test_a_json_path_naming_a_folder_is_refused_before_any_benchmark_runs(tmp_path, geo_runs, capsys):
    assert main(["bench", "geo", "--quick", "--json", str(tmp_path)]) == 2
    assert _error_lines(capsys) == [f"uavmm bench: error: {tmp_path} is a directory: give the results file's path"]
    assert geo_runs == []


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc, a folder no file can be created in")
def test_a_json_path_that_cannot_be_written_is_refused_before_any_benchmark_runs(geo_runs, capsys):
    assert main(["bench", "geo", "--quick", "--json", "/proc/self/bench.json"]) == 2
    (line,) = _error_lines(capsys)
    assert line.startswith("uavmm bench: error: cannot write the results file /proc/self/bench.json: ")
    assert geo_runs == []


def test_an_unknown_name_is_refused_before_any_benchmark_runs(geo_runs, capsys):
    assert main(["bench", "geo", "nope", "--quick"]) == 2
    (line,) = _error_lines(capsys)
    assert line.startswith("uavmm bench: error: unknown benchmark 'nope'; valid: geo, ")
    assert geo_runs == []


def test_list_with_names_lists_those_and_refuses_an_unknown_one(capsys):
    assert main(["bench", "--list", "geo"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith("geo ") and "cv2.perspectiveTransform" in line
    assert main(["bench", "--list", "nope"]) == 2
    assert "unknown benchmark 'nope'" in capsys.readouterr().err


def test_the_json_says_on_which_machine_and_when_and_is_strict_json(tmp_path, geo_runs, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "geo", "geo", "--quick", "--json", str(out)]) == 0
    assert geo_runs == [True]  # a name given twice runs once
    assert "bench geo --quick: running" in capsys.readouterr().err  # progress on stderr, results on stdout
    report = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    meta = report["meta"]
    assert meta["cpu_count"] == os.cpu_count() and meta["numpy"] == np.__version__ and meta["python"]
    assert meta["quick"] is True and meta["benchmarks"] == ["geo"]
    assert meta["started_utc"] <= meta["finished_utc"] and meta["started_utc"].endswith("+00:00")
    assert report["rows"] == [{"benchmark": "geo", "case": "stub", "value": 1.5, "unit": "ms",
                               "baseline_name": "nothing", "ratio": None, "count": 3}]


def test_the_json_is_put_in_place_whole_not_written_through_the_old_file(tmp_path, monkeypatch):
    monkeypatch.setattr(benchmarks.bench_geo, "run", lambda quick: [{"case": "stub", "value": 1.0, "unit": "ms"}])
    out, other_name = tmp_path / "bench.json", tmp_path / "previous.json"
    out.write_text("previous results")
    os.link(out, other_name)  # written in place, the other name of the old file would change as well
    run_benchmarks(["geo"], quick=True, json_path=out)
    assert other_name.read_text() == "previous results"
    assert json.loads(out.read_text())["rows"][0]["case"] == "stub"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bench.json", "previous.json"]  # no temporary left


def test_non_finite_figures_become_null():
    from benchmarks import _plain

    assert _plain({"a": [np.float64("inf"), 1.0], "b": (np.int32(2), -math.inf)}) == {"a": [None, 1.0],
                                                                                       "b": [2, None]}


def test_a_pipe_or_a_link_to_one_is_written_directly_and_a_link_to_a_file_stays_a_link(tmp_path, geo_runs):
    """--json /dev/stdout worked before the results were written whole: a device or a pipe is written as it is (the
    review found a link to one replaced by a regular file and the JSON never reaching the pipe)."""
    import threading

    fifo = tmp_path / "results.fifo"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    link = tmp_path / "stdout-link"
    link.symlink_to(fifo)
    run_benchmarks(["geo"], quick=True, json_path=link)
    reader.join(10)
    assert link.is_symlink() and json.loads(got[0])["rows"][0]["case"] == "stub"
    target = tmp_path / "kept.json"
    target.write_text("{}")
    file_link = tmp_path / "results.json"
    file_link.symlink_to(target)
    run_benchmarks(["geo"], quick=True, json_path=file_link)
    assert file_link.is_symlink() and json.loads(target.read_text())["rows"][0]["case"] == "stub"


def test_json_to_dev_stdout_goes_through_stdout_in_order_with_the_table(tmp_path):
    """With stdout sent to a file (`> log` or `>> log`), --json /dev/stdout replaced that file whole and the table
    printed after it went into the replaced one (the second review): it is written through stdout instead."""
    import subprocess
    import sys

    log = tmp_path / "log.txt"
    log.write_text("earlier\n")
    code = ("import sys, benchmarks.bench_geo as g; from uavmm.cli import main\n"
            "g.run = lambda quick=False: [{'case': 'stub', 'value': 1.0, 'unit': 'ms'}]\n"
            "sys.exit(main(['bench', 'geo', '--quick', '--json', '/dev/stdout']))")
    with open(log, "a") as out:
        proc = subprocess.run([sys.executable, "-c", code], stdout=out, stderr=subprocess.PIPE, text=True,
                              cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert proc.returncode == 0, proc.stderr
    text = log.read_text()
    assert text.startswith("earlier\n{") and text.index('"rows"') < text.index("benchmark  case")

"""`uavmm eval`'s files as a killed or interrupted run leaves them: the domain dataset cache (`ensure_domain_dataset`)
is never reused half-built, and report.json / report.md are replaced whole or not at all."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import sim.domain_eval as domain_eval
import sim.evaluate as evaluate
import sim.real_eval as real_eval
from sim.dataset import write_dataset
from sim.domain_eval import COMPLETE_MARKER, ensure_domain_dataset
from sim.domains import get_domain

REPO = Path(__file__).resolve().parents[2]
#: a final-output domain (pre_nms.json is rewritten after the simulation) on a 5 s clip: 10 frames per video
TINY_FINAL = "dataclasses.replace(get_domain('sea-sds-final'), clip_s=5.0)"


def _tiny_final():
    return dataclasses.replace(get_domain("sea-sds-final"), clip_s=5.0)


def _min_score(data: Path) -> float:
    return min(e["score"] for e in json.loads((data / "pre_nms.json").read_text()))


def test_a_domain_dataset_killed_while_built_is_built_again_not_reused(tmp_path: Path) -> None:
    # a real SIGKILL after the simulation wrote the dataset and before final_output thresholded its candidates:
    # until 30 Nov 2026 images.json marked the entry complete and the next run scored the unfiltered candidates
    code = (
        "import dataclasses, os, signal, sys\n"
        "from pathlib import Path\n"
        "import sim.domain_eval as de\n"
        "from sim.domains import get_domain\n"
        "de.final_output = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)\n"
        f"de.ensure_domain_dataset({TINY_FINAL}, 0, 1.0, False, Path(sys.argv[1]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=REPO, capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL
    data = ensure_domain_dataset(_tiny_final(), 0, 1.0, False, tmp_path)
    assert _min_score(data) >= 0.25 and (data / COMPLETE_MARKER).is_file()
    assert [p.name for p in tmp_path.iterdir()] == [data.name]  # the killed run's partial folder removed


def test_a_cache_entry_without_the_completion_mark_is_built_again(tmp_path: Path) -> None:
    # what an older version (or a kill between its renames) left: the simulation's files, candidates unfiltered
    domain = _tiny_final()
    entry = ensure_domain_dataset(domain, 0, 1.0, False, tmp_path)
    (entry / COMPLETE_MARKER).unlink()
    write_dataset(domain.scenario(), entry, seed=0, frames=domain.frames(False), noise_scale=1.0, progress=False)
    assert _min_score(entry) < 0.25
    assert ensure_domain_dataset(domain, 0, 1.0, False, tmp_path) == entry
    assert _min_score(entry) >= 0.25 and (entry / COMPLETE_MARKER).is_file()


def test_a_failed_build_leaves_no_entry_and_the_next_run_builds_it(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    def interrupted(*args: object, **kwargs: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(domain_eval, "final_output", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ensure_domain_dataset(_tiny_final(), 0, 1.0, False, tmp_path)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    assert _min_score(ensure_domain_dataset(_tiny_final(), 0, 1.0, False, tmp_path)) >= 0.25


@pytest.fixture(scope="module")
def real_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("real") / "data"
    write_dataset("reid", out, seed=3, frames=10, progress=False)
    return out


@pytest.mark.parametrize("which", ["scenarios", "domains", "real"])
def test_an_interrupted_report_leaves_the_previous_pair_as_it_was(which: str, tmp_path: Path, real_data: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "report.json").write_text('{"previous": true}')
    (tmp_path / "report.md").write_text("previous\n")

    def interrupted(report: object) -> str:  # Ctrl-C while report.md is made: report.json was already rewritten
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        if which == "scenarios":
            monkeypatch.setattr(evaluate, "markdown_report", interrupted)
            evaluate.run_eval([], [0], out_dir=tmp_path)
        elif which == "domains":
            monkeypatch.setattr(domain_eval, "markdown_domain_report", interrupted)
            domain_eval.run_domain_eval([], [0], out_dir=tmp_path)
        else:
            monkeypatch.setattr(real_eval, "markdown_real_report", interrupted)
            real_eval.run_real_eval(real_data / "images.json", real_data / "pre_nms.json", real_data / "camera.json",
                                    out_dir=tmp_path)
    assert (tmp_path / "report.json").read_text() == '{"previous": true}'
    assert (tmp_path / "report.md").read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_reports_are_written_through_a_temporary_renamed_over_them(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # a truncating write in place leaves half a report to a SIGKILL; a rename never does
    renamed: list[str] = []
    real_replace = Path.replace

    def spy(self: Path, target: str | os.PathLike[str]) -> Path:
        renamed.append(Path(target).name)
        return real_replace(self, target)

    monkeypatch.setattr(Path, "replace", spy)
    domain_eval.run_domain_eval([], [0], out_dir=tmp_path)
    assert renamed == ["report.json", "report.md"]


def test_an_earlier_evals_folder_is_taken_again_by_every_task_and_its_cache_reused(tmp_path: Path,
                                                                                   real_data: Path) -> None:
    """`uavmm eval --out` refuses a folder of other files, never an earlier eval's: re-runs of detection and tracking
    (their cache under data/ and tracking/data/ reused), --real beside them (real/), and hidden files, all as real
    processes."""
    out = tmp_path / "eval"

    def run(*argv: str) -> None:
        proc = subprocess.run([sys.executable, "-m", "uavmm.cli", "eval", *argv, "--out", str(out)], cwd=REPO,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr

    short = ("--scenarios", "sea", "--seeds", "0", "--noise-scales", "1", "--frames", "3")
    run(*short, "--tasks", "detection,tracking")
    cached = sorted(p.name for p in (out / "data").iterdir())
    (out / ".DS_Store").write_text("")
    stamp = (out / "data" / cached[0] / "images.json").stat().st_mtime_ns
    run(*short, "--tasks", "detection,tracking")
    run("--real", str(real_data))
    run(*short)
    assert sorted(p.name for p in out.iterdir()) == [".DS_Store", "data", "real", "report.json", "report.md",
                                                      "tracking"]
    assert sorted(p.name for p in (out / "data").iterdir()) == cached
    assert (out / "data" / cached[0] / "images.json").stat().st_mtime_ns == stamp  # reused, not simulated again

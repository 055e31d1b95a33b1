"""`uavmm eval`'s bad input: one line naming the flag and exit 2, before any simulation or scoring starts."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import sim.domain_eval
import sim.evaluate
import sim.real_eval
from sim.dataset import write_dataset
from uavmm.cli import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any evaluation reached is a failure: the input must have been refused before it."""

    def work(*args: object, **kwargs: object) -> None:
        raise AssertionError("the evaluation started")

    for module, name in ((sim.evaluate, "run_eval"), (sim.domain_eval, "run_domain_eval"),
                         (sim.real_eval, "run_real_eval")):
        monkeypatch.setattr(module, name, work)


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(["eval", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


@pytest.mark.parametrize("noise", ["1,-1", "1,nan", "inf"])
@pytest.mark.parametrize("where", [[], ["--domains", "sea-jitter"]])
def test_a_bad_noise_scale_anywhere_in_the_list_is_refused_before_the_work(
        noise: str, where: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # until 30 Nov 2026 the first noise scale's whole run came first, then write_dataset's error on `noise_scale`
    err = _refused([*where, "--seeds", "0", "--noise-scales", noise, "--out", str(tmp_path)], capsys)
    assert "--noise-scales" in err and ">= 0" in err


@pytest.mark.parametrize("where", [[], ["--domains", "sea-jitter"], ["--tasks", "coop", "--domains", "coop-trees"]])
def test_an_out_that_is_a_file_is_refused_naming_out(where: list[str], tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "afile").write_text("x")
    err = _refused([*where, "--seeds", "0", "--out", str(tmp_path / "afile")], capsys)
    assert f"--out {tmp_path / 'afile'}" in err and "not a folder" in err  # was "[Errno 17] File exists: ..."


def test_eval_real_with_an_out_that_is_a_file_is_refused_before_scoring(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    write_dataset("reid", data, seed=3, frames=3, progress=False)
    (tmp_path / "afile").write_text("x")
    # until 30 Nov 2026: the whole evaluation, then "[Errno 20] Not a directory: 'afile/real'"
    err = _refused(["--real", str(data), "--out", str(tmp_path / "afile")], capsys)
    assert "--out" in err and "not a folder" in err


@pytest.mark.parametrize("tasks", [["--tasks", "tracking"], []])
def test_domain_tracking_without_noise_one_is_refused_not_an_empty_report(
        tasks: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # until 30 Nov 2026: exit 0 and a report without a row, written over the previous one
    err = _refused(["--domains", "sea-jitter", *tasks, "--seeds", "0", "--noise-scales", "2",
                    "--out", str(tmp_path)], capsys)
    assert "tracking runs at noise x1" in err


@pytest.mark.parametrize("flag", [["--frames", "30"], ["--scenarios", "sea"], ["--ablations"]])
def test_scenario_flags_with_domains_are_refused_not_ignored(flag: list[str], tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    err = _refused(["--domains", "sea-jitter", *flag, "--seeds", "0", "--out", str(tmp_path)], capsys)
    assert flag[0] in err and "--domains" in err


def test_full_without_domains_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert "--full goes with --domains" in _refused(["--full", "--seeds", "0", "--out", str(tmp_path)], capsys)


def _eval_process(*argv: str) -> subprocess.CompletedProcess[str]:
    """`uavmm eval` as a real process (a short scenario run unless argv says otherwise)."""
    return subprocess.run([sys.executable, "-m", "uavmm.cli", "eval", "--scenarios", "sea", "--seeds", "0",
                           "--noise-scales", "1", *argv], cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("frames", ["36001", "1000000000"])
def test_frames_over_the_cap_are_refused_in_one_line_before_any_work(frames: str, tmp_path: Path) -> None:
    # until 30 Nov 2026 no upper bound: --frames 1000000000 simulated for days (the cache folder made first)
    run = _eval_process("--frames", frames, "--out", str(tmp_path / "e"))
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line == f"uavmm eval: error: --frames must be in 1..36000 (frames per video), got {frames}"
    assert not (tmp_path / "e").exists()


def test_an_out_folder_of_the_users_files_is_refused_and_left_as_it_was(tmp_path: Path) -> None:
    # until 30 Nov 2026 report.json, report.md and data/ were written among the user's files, exit 0
    out = tmp_path / "mine"
    (out / "photos").mkdir(parents=True)
    (out / "photos" / "a.jpg").write_bytes(b"precious")
    (out / "notes.txt").write_text("precious")
    run = _eval_process("--frames", "3", "--out", str(out))
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line == (f"uavmm eval: error: output directory {out} holds files that are not an earlier uavmm eval's "
                    "(notes.txt, photos): give a new or empty folder, or an earlier eval's")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["notes.txt", "photos", "photos/a.jpg"]


@pytest.mark.parametrize(("files", "listed"), [
    (["notes.txt"], "notes.txt"),
    (["report.md"], "report.md"),  # not beside report.json, which an eval writes first: someone's report
    (["report.json", "data/table.csv"], "data/table.csv"),  # a cache holds a folder per dataset
    (["tracking/report.json", "tracking/notes.txt"], "tracking/notes.txt"),
    ([f"n{i}.txt" for i in range(6)], "n0.txt, n1.txt, n2.txt, n3.txt and 2 more"),
])
@pytest.mark.parametrize("where", [[], ["--domains", "sea-jitter"], ["--tasks", "coop", "--domains", "coop-trees"]])
def test_every_eval_refuses_an_out_folder_of_other_files(files: list[str], listed: str, where: list[str],
                                                         tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mine"
    for name in files:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("precious")
    err = _refused([*where, "--seeds", "0", "--out", str(out)], capsys)
    assert f"output directory {out} holds files that are not an earlier uavmm eval's ({listed})" in err
    assert all((out / name).read_text() == "precious" for name in files)


def test_eval_real_refuses_an_out_folder_of_other_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data"
    write_dataset("reid", data, seed=3, frames=3, progress=False)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    err = _refused(["--real", str(data), "--out", str(out)], capsys)
    assert "holds files that are not an earlier uavmm eval's (notes.txt)" in err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize("extra", [["--frames", "30"], ["--seeds", "0"], ["--scenarios", "sea"], ["--ablations"],
                                   ["--tasks", "tracking"], ["--noise-scales", "2"], ["--domains", "tune"],
                                   ["--full"], ["--frames", "999999999", "--ablations"]])
def test_the_simulated_evaluations_flags_are_refused_beside_a_real_file(
        extra: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # until 30 Nov 2026 they did nothing beside --real, silently: `--real F --frames 999999999` exited 0
    err = _refused(["--real", str(tmp_path), *extra, "--out", str(tmp_path / "out")], capsys)
    assert "not used with --real" in err and all(flag in err for flag in extra if flag.startswith("--"))

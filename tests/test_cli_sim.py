"""`uavmm sim` as a new user meets it: bad input refused in one line with exit 2 before any work, an --out folder
that holds someone else's files or a rendered dataset left as it was, a full disk named in one line."""

from __future__ import annotations

import json
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from sim.dataset import DATASET_FILES, write_dataset
from uavmm.cli import main

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--frames", "2", "--image-size", "64x36", "--quiet"]


def _one_line_error(capsys: pytest.CaptureFixture, argv: list[str], message: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err, err
    return err


def test_an_image_size_over_the_renderers_limit_is_refused_before_simulating(tmp_path, capsys):
    """Probe: --image-size 100000x100000 wrote the dataset, and --render then died in a 224 GiB MemoryError
    traceback (exit 1)."""
    out = tmp_path / "big"
    err = _one_line_error(capsys, ["sim", "grass", "--out", str(out), "--image-size", "100000x100000", "--render",
                                   "--frames", "1"], "--image-size is at most 8192 a side")
    assert err.startswith("uavmm sim: error: --image-size")  # once "sim: " twice
    assert not out.exists()


@pytest.mark.parametrize("frames", ["36001", "1000000000"])
def test_frames_over_the_cap_are_refused_in_one_line_before_any_work(tmp_path, frames):
    """Probe: `uavmm sim sea --frames 1000000000 --render` had no upper bound: it simulated (for days, the dataset
    held in memory) before writing or drawing anything. The cap is `uavmm eval --frames`'s too (one check)."""
    out = tmp_path / "long"
    run = subprocess.run([sys.executable, "-m", "uavmm.cli", "sim", "sea", "--out", str(out), "--frames", frames,
                          "--render", "--video", "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line == f"uavmm sim: error: --frames must be in 1..36000 (frames per video), got {frames}"
    assert not out.exists()


def test_frames_at_the_cap_pass_the_check(tmp_path, capsys):
    """36000 is taken: the run goes on to the next check (here --out, a file, refused before any work)."""
    (tmp_path / "afile").write_text("x")
    _one_line_error(capsys, ["sim", "sea", "--out", str(tmp_path / "afile"), "--frames", "36000"], "is a file")


def test_rendering_flags_without_render_are_refused(tmp_path, capsys):
    """Probe: `uavmm sim grass --out o --jpeg-quality 500 --sensor-noise -4` ignored both flags, exit 0."""
    out = tmp_path / "o"
    _one_line_error(capsys, ["sim", "grass", "--out", str(out), "--jpeg-quality", "500", "--sensor-noise", "-4",
                             *SMALL], "--jpeg-quality --sensor-noise: rendering flags, they go with --render")
    assert not out.exists()


def test_render_of_a_terrain_scenario_is_refused_before_simulating(tmp_path, capsys):
    """Probe: `uavmm sim hills --render` wrote the dataset, then failed with exit 2 (the renderer draws flat
    ground only)."""
    out = tmp_path / "h"
    _one_line_error(capsys, ["sim", "hills", "--out", str(out), "--render", *SMALL],
                    "scenario hills has a terrain and the renderer draws flat ground only")
    assert not out.exists()


def test_an_out_folder_holding_other_files_is_refused_and_left_as_it_was(tmp_path, capsys):
    """Probe: the dataset was written among the user's files (notes.txt), exit 0."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    _one_line_error(capsys, ["sim", "grass", "--out", str(out), *SMALL],
                    f"output directory {out} holds files that are not a uavmm sim dataset (notes.txt)")
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize("beside", [[], ["notes.txt"]])
def test_an_out_folder_holding_someone_elses_images_json_is_refused_and_left_as_it_was(tmp_path, capsys, beside):
    """The contract audit (1 Dec 2026): a folder with the user's own dataset as images.json (the real dev file) was
    taken for an earlier sim dataset by the name alone and replaced, exit 0, no warning."""
    out = tmp_path / "mine"
    out.mkdir()
    own = json.dumps({"info": {"description": "SeaDronesSee v2"}, "images": [], "annotations": [], "categories": []})
    (out / "images.json").write_text(own)
    for name in beside:
        (out / name).write_text("precious")
    _one_line_error(capsys, ["sim", "grass", "--out", str(out), *SMALL],
                    f"output directory {out} holds an images.json that is not a uavmm sim dataset's")
    assert (out / "images.json").read_text() == own
    assert sorted(p.name for p in out.iterdir()) == sorted(["images.json", *beside])


def test_an_out_folder_holding_a_rendered_dataset_is_replaced_without_its_marks_and_says_so(tmp_path, caplog):
    """`uavmm sim grass --out D` over a rendered sea dataset left render.json (the mark of a complete render) beside
    the grass dataset. The dataset is replaced as before (the docs' commands re-run into their folder: the second
    review's finding against refusing it), the marks go and the frames left are named in a warning."""
    out = tmp_path / "sea"
    write_dataset("sea", out, frames=2, progress=False)
    video = json.loads((out / "images.json").read_text())["videos"][0]["name"]
    (out / video).mkdir()
    (out / f"{video}.mp4").write_bytes(b"frames")
    (out / "render.json").write_text("{}")
    (out / "results.json").write_text("[]")  # boost's output beside its dataset (the README's commands)
    (out / ".DS_Store").write_text("")
    assert main(["sim", "grass", "--out", str(out), *SMALL]) == 0
    assert json.loads((out / "truth.json").read_text())["scenario"]["name"] == "grass"
    assert not (out / "render.json").exists() and (out / "results.json").read_text() == "[]"
    assert any("earlier render's frames" in r.getMessage() and video in r.getMessage() for r in caplog.records)


def test_a_folder_holding_only_hidden_files_is_taken(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / ".gitkeep").write_text("")
    assert main(["sim", "grass", "--out", str(out), *SMALL]) == 0
    assert (out / ".gitkeep").exists() and (out / "images.json").exists()


def test_an_earlier_dataset_without_frames_is_replaced_and_a_file_is_refused(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["sim", "sea", "--out", str(out), *SMALL]) == 0
    assert main(["sim", "grass", "--out", str(out), *SMALL]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(DATASET_FILES)
    assert json.loads((out / "truth.json").read_text())["scenario"]["name"] == "grass"
    capsys.readouterr()
    _one_line_error(capsys, ["sim", "grass", "--out", str(out / "images.json"), *SMALL],
                    "images.json is a file: give a folder")


def test_a_full_disk_names_the_file_and_keeps_the_earlier_dataset(tmp_path):
    """Probe: a disk that filled up said only "[Errno 27] File too large"."""
    out = tmp_path / "d"
    write_dataset("grass", out, frames=2, progress=False)
    before = {name: (out / name).read_bytes() for name in DATASET_FILES}

    def full_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    run = subprocess.run([sys.executable, "-m", "uavmm.cli", "sim", "grass", "--out", str(out), "--frames", "30",
                          "--image-size", "640x360", "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=120,
                         preexec_fn=full_disk)
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line.startswith(f"uavmm sim: error: cannot write {out / 'images.json'}: "), line
    assert {name: (out / name).read_bytes() for name in DATASET_FILES} == before
    assert sorted(p.name for p in out.iterdir()) == sorted(DATASET_FILES)  # no temporary folder left


def test_a_temporary_folder_a_killed_run_left_does_not_block_the_next(tmp_path):
    out = tmp_path / "ds"
    assert main(["sim", "sea", "--out", str(out), *SMALL]) == 0
    (out / ".sim-tmp-left").mkdir()  # what a SIGKILL during the write leaves
    assert main(["sim", "grass", "--out", str(out), *SMALL]) == 0
    assert json.loads((out / "truth.json").read_text())["scenario"]["name"] == "grass"

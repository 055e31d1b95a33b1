"""`uavmm anomaly-train` (sim.anomaly_train): bad input refused in one line before any rendering, the model written
whole, loadable by the agent's autoencoder, the same for a seed. Tests that train need PyTorch (the train extra)
and skip without it; the refusals do not."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

import sim.anomaly_train as anomaly_train
from agent.anomaly.autoencoder import DEFAULT_MODEL, OnnxAutoencoder
from uavmm.cli import main


@pytest.fixture
def no_rendering(monkeypatch):
    """Fail the test if a run gets as far as rendering its scenes."""

    def render(*args, **kwargs):
        raise AssertionError("the training scenes were rendered before the input was refused")

    monkeypatch.setattr(anomaly_train, "render_training_scenes", render)


def _refused(capsys, *argv: str | Path) -> str:
    """Run the command, expect exit code 2 and one line on stderr; return the line."""
    assert main(["anomaly-train", *map(str, argv)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize(("flags", "expected"), [
    (["--steps", "0"], "--steps must be >= 1, got 0"),
    (["--steps", "-3"], "--steps must be >= 1, got -3"),
    (["--frames", "0"], "--frames must be >= 1, got 0"),
    (["--seeds", "-1"], "--seeds needs one or more integers >= 0"),
    (["--seeds", ","], "--seeds needs one or more integers >= 0"),
    (["--seeds", "1,x"], "--seeds: expected comma-separated integers"),
])
def test_bad_values_are_refused_naming_the_flag(tmp_path, capsys, no_rendering, flags, expected):
    line = _refused(capsys, "--out", tmp_path / "m.onnx", "--work-dir", tmp_path / "w", *flags)
    assert expected in line
    assert not (tmp_path / "w").exists()


def test_an_out_in_a_missing_folder_is_refused_not_created(tmp_path, capsys, no_rendering):
    out = tmp_path / "missing" / "sub" / "m.onnx"
    line = _refused(capsys, "--out", out, "--work-dir", tmp_path / "w")
    assert "does not exist" in line and str(out.parent) in line
    assert not (tmp_path / "missing").exists() and not (tmp_path / "w").exists()


def test_an_out_naming_a_folder_is_refused_before_the_work(tmp_path, capsys, no_rendering):
    line = _refused(capsys, "--out", tmp_path, "--work-dir", tmp_path / "w")
    assert "is a directory" in line
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("spelling", ["absolute", "relative", "symlink", "hardlink"])
def test_the_shipped_model_is_never_the_out(tmp_path, capsys, monkeypatch, no_rendering, spelling):
    before = DEFAULT_MODEL.read_bytes()
    if spelling == "absolute":
        out = DEFAULT_MODEL
    elif spelling == "relative":  # docs/anomaly.md's old command, from the checkout
        monkeypatch.chdir(DEFAULT_MODEL.parent.parent.parent)
        out = Path("agent/anomaly/../anomaly") / DEFAULT_MODEL.name
    elif spelling == "symlink":
        out = tmp_path / "link.onnx"
        out.symlink_to(DEFAULT_MODEL)
    else:
        out = tmp_path / "hard.onnx"
        try:
            os.link(DEFAULT_MODEL, out)
        except OSError as exc:  # another file system
            pytest.skip(f"no hard link to the package here: {exc}")
    line = _refused(capsys, "--out", out, "--work-dir", tmp_path / "w")
    assert "the model shipped in the package" in line
    assert DEFAULT_MODEL.read_bytes() == before


def test_a_work_dir_holding_other_files_is_refused(tmp_path, capsys, no_rendering):
    work = tmp_path / "mine"
    work.mkdir()
    (work / "notes.txt").write_text("hello")
    (work / "sea_1280x720_s100_f120").mkdir()  # an earlier run's scene does not count
    line = _refused(capsys, "--out", tmp_path / "m.onnx", "--work-dir", work)
    assert "holds other files (notes.txt)" in line
    assert sorted(p.name for p in work.iterdir()) == ["notes.txt", "sea_1280x720_s100_f120"]


def test_a_work_dir_that_is_a_file_is_refused(tmp_path, capsys, no_rendering):
    (tmp_path / "afile").write_text("x")
    assert "is not a directory" in _refused(capsys, "--out", tmp_path / "m.onnx", "--work-dir", tmp_path / "afile")


def test_new_empty_and_earlier_work_dirs_are_accepted(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "earlier" / "sea_640x360_s7_f2").mkdir(parents=True)
    (tmp_path / "earlier" / ".DS_Store").write_text("")  # a file browser's: not a reason to refuse (review)
    for work in ("new", "empty", "earlier"):
        anomaly_train.check_paths(tmp_path / "m.onnx", tmp_path / work)
    (tmp_path / "m.onnx").write_bytes(b"old")  # an existing --out is replaced: no error
    anomaly_train.check_paths(tmp_path / "m.onnx", tmp_path / "new")


def test_without_torch_one_line_names_the_train_extra(tmp_path, capsys, monkeypatch, no_rendering):
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch: ImportError
    line = _refused(capsys, "--out", tmp_path / "m.onnx", "--work-dir", tmp_path / "w")
    assert "PyTorch is missing (the train extra): pip install -e '.[train]'" in line
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize(("option", "value"), [("steps", 0), ("frames", -1), ("batch", 0), ("lr", 0.0),
                                               ("seeds", []), ("seeds", [3, -1])])
def test_the_library_refuses_bad_values_before_any_work(tmp_path, no_rendering, option, value):
    with pytest.raises(ValueError, match=option):
        anomaly_train.train_autoencoder(tmp_path / "m.onnx", work_dir=tmp_path / "w", **{option: value})


# ------------------------------------------------------------------------------------------ with PyTorch


@pytest.fixture
def synthetic_frames(monkeypatch):
    """Three small textured frames instead of rendered scenes (training itself is what is tested here)."""
    pytest.importorskip("torch", reason="needs PyTorch (the train extra; CI has none)")
    rng = np.random.default_rng(5)
    images = rng.integers(60, 120, (3, 136, 200, 3), dtype=np.uint8)
    masks = np.ones((3, 136, 200), np.uint8)
    monkeypatch.setattr(anomaly_train, "render_training_scenes", lambda *args, **kwargs: [])
    monkeypatch.setattr(anomaly_train, "load_frames", lambda dirs, work_width: (images, masks))


def _train(out: Path, tmp_path: Path, **kwargs) -> dict:
    return anomaly_train.train_autoencoder(out, work_dir=tmp_path / "w", steps=3, batch=2, **kwargs)


def test_the_trained_model_loads_with_the_shipped_models_inputs_and_outputs(tmp_path, synthetic_frames):
    import onnxruntime as ort

    out = tmp_path / "m.onnx"
    _train(out, tmp_path)

    def io(path: Path) -> tuple[list, list]:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        return ([(i.name, i.shape, i.type) for i in session.get_inputs()],
                [(o.name, o.shape, o.type) for o in session.get_outputs()])

    assert io(out) == io(DEFAULT_MODEL)
    heat = OnnxAutoencoder(out).heatmap(np.full((360, 640, 3), 90, np.uint8))
    assert heat.shape == (360, 640) and heat.dtype == np.float32


def test_training_is_the_same_for_a_seed(tmp_path, synthetic_frames):
    _train(tmp_path / "a.onnx", tmp_path, seed=3)
    _train(tmp_path / "b.onnx", tmp_path, seed=3)
    assert (tmp_path / "a.onnx").read_bytes() == (tmp_path / "b.onnx").read_bytes()


def test_a_failed_write_leaves_the_model_that_was_there(tmp_path, monkeypatch, synthetic_frames):
    out = tmp_path / "m.onnx"
    out.write_bytes(DEFAULT_MODEL.read_bytes())

    def fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError, match="No space left"):
        _train(out, tmp_path)
    assert out.read_bytes() == DEFAULT_MODEL.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]


def test_training_steps_show_progress_on_stderr_a_line_per_10_percent(capsys):
    from uavmm.cmd_anomaly import _StepProgress

    progress = _StepProgress()
    for done in range(1, 1501):
        progress(done, 1500)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 11 and lines[0] == "anomaly-train: step 1/1500"
    assert lines[-1].startswith("anomaly-train: step 1500/1500, 0 s left")

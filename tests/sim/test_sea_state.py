"""The rough sea of `sea-hard` (sim.sea_state): calm by default, written to truth.json only when rough, and drawn
smaller, murkier and more cluttered than `sea`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from sim.dataset import write_dataset
from sim.render import RenderOptions, SimulatedDataset, WorldRenderer
from sim.scenarios import get_scenario
from sim.sea_state import CALM, SeaState

SIZE = (640, 360)
FRAMES = 6
OPTIONS = RenderOptions(max_texture_px=1024, scenery=False)


def _write(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    out = tmp_path_factory.mktemp(name) / "data"
    write_dataset(dataclasses.replace(get_scenario(name), image_size=SIZE), out, seed=0, frames=FRAMES,
                  progress=False)
    return out


@pytest.fixture(scope="module")
def sea(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write(tmp_path_factory, "sea")


@pytest.fixture(scope="module")
def hard(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write(tmp_path_factory, "sea-hard")


def test_the_default_sea_state_is_calm_and_round_trips():
    assert SeaState().calm and SeaState.from_dict(None) is CALM and SeaState.from_dict({}) is CALM
    rough = get_scenario("sea-hard").sea_state
    assert rough is not None and not rough.calm
    assert SeaState.from_dict(rough.to_dict()) == rough


@pytest.mark.parametrize("field, value", [("whitecap_rate", -1.0), ("visibility_scale", 0.0),
                                          ("swimmer_wash", 1.5), ("blur_mrad", float("nan"))])
def test_a_bad_sea_state_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SeaState(**{field: value})


def test_an_unknown_sea_state_field_is_refused():
    with pytest.raises(ValueError, match="unknown sea state field"):
        SeaState.from_dict({"waves": 2.0})


def test_only_a_rough_sea_is_written_to_truth_json(sea, hard):
    # the calm `sea` keeps the truth.json it always had (no key), so its datasets and renders stay identical
    assert "sea_state" not in json.loads((sea / "truth.json").read_text())["scenario"]
    assert SimulatedDataset(sea).sea_state is CALM
    assert SimulatedDataset(hard).sea_state == get_scenario("sea-hard").sea_state


def _median_box_px(directory: Path) -> float:
    coco = json.loads((directory / "images.json").read_text())
    return float(np.median([max(a["bbox"][2], a["bbox"][3]) for a in coco["annotations"]]))


def test_sea_hard_shows_the_swimmers_smaller(tmp_path):
    # at the scenarios' 4K, where few swimmers fall under the simulator's 4-pixel annotation limit
    sizes = {}
    for name in ("sea", "sea-hard"):
        write_dataset(name, tmp_path / name, seed=0, frames=30, progress=False)
        sizes[name] = _median_box_px(tmp_path / name)
    assert sizes["sea-hard"] < 0.85 * sizes["sea"]  # seed 0: 23.8 vs 30.3 px


def _first_frames(directory: Path) -> list[np.ndarray]:
    ds = SimulatedDataset(directory)
    frames = []
    for group, world in ds.worlds.items():
        renderer = WorldRenderer(ds, world, OPTIONS)
        video = next(v for v in ds.videos if v.group == group)
        frames.append(renderer.render(list(ds.frames(video))[-1]))
    return frames


def _local_contrast(image: np.ndarray) -> float:
    """Mean absolute difference of the grey image to its 9x9 median: how much small clutter a frame holds."""
    import cv2

    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return float(np.abs(grey.astype(np.float32) - cv2.medianBlur(grey, 9).astype(np.float32)).mean())


def test_sea_hard_renders_more_clutter_than_sea(sea, hard):
    calm, rough = _first_frames(sea), _first_frames(hard)
    assert all(f.shape == (SIZE[1], SIZE[0], 3) for f in calm + rough)
    # whitecaps and foam: more bright specks on the water (mean over the three flights)
    def bright(frames: list[np.ndarray]) -> float:
        return float(np.mean([(f.max(axis=2) > 200).mean() for f in frames]))

    assert bright(rough) > 2 * bright(calm)
    assert np.mean([_local_contrast(f) for f in rough]) > np.mean([_local_contrast(f) for f in calm])


def test_eval_cli_accepts_sea_hard(tmp_path, monkeypatch, capsys):
    import sim.anomaly_eval as anomaly_eval
    from uavmm.cli import main

    monkeypatch.setattr(anomaly_eval, "EVAL_IMAGE_SIZE", (320, 180))  # small frames: the path, not the figures
    monkeypatch.setattr(anomaly_eval, "EVAL_METHODS", ("median",))
    seen = {}
    run = anomaly_eval.run_anomaly_eval

    def one_method(scenarios, seeds, **kw):
        seen["scenarios"] = list(scenarios)
        return run(scenarios, seeds, **{**kw, "methods": ("median",)})

    monkeypatch.setattr(anomaly_eval, "run_anomaly_eval", one_method)
    assert main(["eval", "--tasks", "anomaly", "--scenarios", "sea-hard", "--seeds", "0", "--frames", "3",
                 "--out", str(tmp_path)]) == 0
    assert seen["scenarios"] == ["sea-hard"]
    report = json.loads((tmp_path / "anomaly" / "report.json").read_text())
    assert "sea-hard" in report["results"] and "median" in report["results"]["sea-hard"]
    assert "## sea-hard" in capsys.readouterr().out

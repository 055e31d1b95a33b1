"""Shared fixtures: small simulated datasets written once per test session."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim.dataset import write_dataset

SMALL_FRAMES = 150  # per video: sea 450 images, grass 600, a few seconds each


def _write(tmp_path_factory: pytest.TempPathFactory, scenario: str, seed: int) -> Path:
    out = tmp_path_factory.mktemp(f"{scenario}-{seed}") / "data"
    write_dataset(scenario, out, seed=seed, frames=SMALL_FRAMES, progress=False)
    return out


@pytest.fixture(scope="session")
def sea_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write(tmp_path_factory, "sea", 0)


@pytest.fixture(scope="session")
def grass_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write(tmp_path_factory, "grass", 0)


def load(path: Path, name: str):
    return json.loads((path / name).read_text())

"""Simulator speed: generating a 300-frame scenario (quick: 100) against only writing the dataset it makes.

Baseline in the same run: serialising the same dataset's JSON content (json.dumps of what it wrote, parsed) and
writing it, the floor of any generator of these files. Each scenario is generated once, a few frames, before it is
timed, so the first one does not also pay the process's first-call costs. Also given: the speed as a multiple of
real time (the videos' duration at the scenario's fps).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

DESCRIPTION = "uavmm sim: seconds to write a 300-frame dataset per scenario vs serialising + writing its JSON alone"

SCENARIOS = ("sea", "grass", "coop", "reid")


def _serialise_and_write_s(dataset: Path, out: Path) -> float:
    """Seconds to json.dumps the content of dataset's JSON files (parsed beforehand) and write it into out."""
    contents = {f.name: json.loads(f.read_text()) for f in sorted(dataset.glob("*.json"))}
    out.mkdir()
    t0 = time.perf_counter()
    for name, content in contents.items():
        (out / name).write_text(json.dumps(content))
    return time.perf_counter() - t0


def run(quick: bool = False) -> list[dict[str, Any]]:
    from sim.dataset import write_dataset
    from sim.scenarios import get_scenario

    rows: list[dict[str, Any]] = []
    frames = 100 if quick else 300
    for name in SCENARIOS:
        scenario = get_scenario(name)
        video_s = frames / scenario.fps * scenario.n_videos
        with tempfile.TemporaryDirectory() as tmp:
            write_dataset(name, Path(tmp) / "warm-up", seed=0, frames=5, progress=False)
            t0 = time.perf_counter()
            write_dataset(name, Path(tmp) / "d", seed=0, frames=frames, progress=False)
            dt = time.perf_counter() - t0
            io_s = _serialise_and_write_s(Path(tmp) / "d", Path(tmp) / "copy")
        rows.append({"case": f"{name}: {frames} frames x {scenario.n_videos} videos", "value": dt, "unit": "s",
                     "baseline_name": "its JSON serialised + written", "ratio": dt / io_s})
        rows.append({"case": f"{name}: its JSON serialised + written alone", "value": io_s, "unit": "s"})
        rows.append({"case": f"{name}: speed, {video_s:.1f} s of video at {scenario.fps:g} fps", "value": video_s / dt,
                     "unit": "x real time"})
    return rows

"""Simulator speed: generating a 300-frame scenario, as a multiple of real time (30 fps video).

Baseline in the same run: writing the same dataset's JSON files alone (the I/O floor).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

DESCRIPTION = "uavmm sim: seconds to write a 300-frame dataset per scenario vs its video duration"


def run(quick: bool = False) -> list[dict[str, Any]]:
    from sim.dataset import write_dataset
    from sim.scenarios import get_scenario

    rows: list[dict[str, Any]] = []
    frames = 100 if quick else 300
    for name in ("sea", "grass", "coop", "reid"):
        scenario = get_scenario(name)
        video_s = frames / scenario.fps * scenario.n_videos
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_dataset(name, Path(tmp) / "d", seed=0, frames=frames, progress=False)
            dt = time.perf_counter() - t0
            files = list((Path(tmp) / "d").glob("*.json"))
            blobs = [f.read_bytes() for f in files]
            t1 = time.perf_counter()
            for f, b in zip(files, blobs, strict=True):
                (Path(tmp) / (f.name + ".copy")).write_bytes(b)
            io_s = time.perf_counter() - t1
        rows.append({"case": f"{name}: {frames} frames x {scenario.n_videos} videos", "value": dt, "unit": "s",
                     "baseline_name": "video duration", "ratio": dt / video_s})
        rows.append({"case": f"{name}: JSON write alone", "value": io_s, "unit": "s"})
    return rows

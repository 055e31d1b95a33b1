"""The 1 Hz view-jump domain end to end (agent.view_cuts on simulated flight-log telemetry): `uavmm boost`'s summary
says the view-cut stage acted, and the poses it hands the pipeline sit closer to the true headings than the
interpolated ones. Real simulator, real files, no mocks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from agent.boost import boost_dataset
from agent.dataset import Candidates, Dataset, VideoTelemetry
from agent.file_frames import prepared_frames
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera
from sim.dataset import write_dataset
from sim.domains import DOMAINS


def _heading_errors(data: Path, config: PipelineConfig) -> tuple[np.ndarray, list[VideoTelemetry]]:
    ds = Dataset.load(data / "images.json")
    cands = Candidates.load(data / "pre_nms.json", ds)
    cam = Camera.from_file(data / "camera.json")
    truth = {p["image_id"]: p["heading_deg"] for p in json.loads((data / "truth.json").read_text())["poses"]}
    errors, infos = [], []
    for vid in ds.videos:
        info = VideoTelemetry()
        for frame, _ in prepared_frames(ds, cam, vid, cands, config, report=info):
            if frame.pose is not None:
                errors.append((frame.pose.heading_deg - truth[frame.image.id] + 180.0) % 360.0 - 180.0)
        infos.append(info)
    e = np.asarray(errors)
    return np.abs(e - np.median(e)), infos  # the constant heading bias taken out


def test_jumps_logged_at_one_hertz_are_cut_where_the_view_jumps(tmp_path: Path) -> None:
    domain = dataclasses.replace(DOMAINS["grass-jumps-1hz"], clip_s=7.0)  # two jumps (every 3 s)
    data = tmp_path / "d"
    write_dataset(domain.scenario(), data, seed=0, frames=domain.frames(), progress=False)
    cut, infos = _heading_errors(data, PipelineConfig())
    smeared, _ = _heading_errors(data, dataclasses.replace(PipelineConfig(), view_cuts=False))
    assert all(info.view_cuts is not None and info.view_cuts[1] >= 1 for info in infos)
    assert (smeared > 20.0).sum() >= 30  # a second-long smear of each 60 deg jump
    assert (cut > 20.0).sum() <= (smeared > 20.0).sum() // 3
    _, stats = boost_dataset(data / "images.json", data / "pre_nms.json", data / "camera.json", PipelineConfig())
    assert stats["stages"]["view cuts"]["acted"] >= 1
    _, stats = boost_dataset(data / "images.json", data / "pre_nms.json", data / "camera.json",
                             dataclasses.replace(PipelineConfig(), view_cuts=False))
    assert "view cuts" not in stats["stages"]

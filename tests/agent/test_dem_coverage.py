"""A DEM that does not lie under the flight (agent.dem.DemCoverage): said, and counted in the stage report. Before,
`uavmm boost --dem` with another place's DEM gave the detector's boxes unboosted and unfiltered without a word."""

from __future__ import annotations

import logging

import numpy as np

from agent.dem import DemCoverage
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose
from shared.terrain import ElevationGrid, Terrain

CAMERA = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)


def _terrain(lat0: float) -> Terrain:
    grid = ElevationGrid(np.full((5, 5), 100.0), lat0_deg=lat0, lon0_deg=9.0, lat_step_deg=-0.001, lon_step_deg=0.001)
    return Terrain(grid, takeoff_elevation_m=100.0)


def _run(terrain: Terrain, frames: int = 12) -> DetectionPipeline:
    pipe = DetectionPipeline(CAMERA, {0: "person"}, PipelineConfig(terrain=terrain))
    boxes = np.array([[300, 200, 320, 240]], np.float32)
    for i in range(frames):
        pipe.process(boxes, np.array([0.8], np.float32), np.zeros(1, np.int64),
                     Pose(lat=47.002, lon=9.002, height_m=40.0, pitch_deg=60.0, heading_deg=0.0), 100.0 + 0.1 * i)
    return pipe


def test_a_dem_of_another_place_is_said_and_reported(caplog):
    with caplog.at_level(logging.WARNING, logger="agent.dem"):
        pipe = _run(_terrain(48.0))  # the DEM 100 km north of the flight
    said = [r.getMessage() for r in caplog.records if "off the DEM in each of the first" in r.getMessage()]
    assert len(said) == 1 and "is it this flight's DEM?" in said[0]
    (report,) = [r for r in pipe.stage_reports() if r.stage == "terrain"]
    assert not report.acted and report.why == "UAV over the DEM in 0 of 12 frames (another place's DEM?)"


def test_a_dem_under_the_flight_is_not_warned_about(caplog):
    with caplog.at_level(logging.WARNING, logger="agent.dem"):
        pipe = _run(_terrain(47.004))
    assert not [r for r in caplog.records if "off the DEM in each" in r.getMessage()]
    (report,) = [r for r in pipe.stage_reports() if r.stage == "terrain"]
    assert report.acted and report.why == "UAV over the DEM in 12 of 12 frames"


def test_flat_ground_has_no_terrain_report():
    pipe = DetectionPipeline(CAMERA, {0: "person"}, PipelineConfig())
    assert not [r for r in pipe.stage_reports() if r.stage == "terrain"]
    assert DemCoverage().report().acted is False

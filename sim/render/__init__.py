"""Rendering of simulated datasets: pixels for the frames `uavmm sim` describes (docs/simulator.md, Rendering).

Modules name the steps: `scene` (what to draw, from the dataset files), `geometry` (projections with the true
pose), `texture` (procedural ground), `sprites` (objects), `effects` (sky, haze, glint, blur, exposure),
`renderer` (one frame), `telemetry_files` (SRT/CSV beside a video) and `output` (files, `render_dataset`).
"""

from sim.render.output import render_dataset
from sim.render.renderer import RenderOptions, WorldRenderer, exposure_for
from sim.render.scene import SimulatedDataset

__all__ = ["RenderOptions", "SimulatedDataset", "WorldRenderer", "exposure_for", "render_dataset"]

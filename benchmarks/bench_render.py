"""Rendering speed: frames/s drawing simulated flights at 1080p and 4K, against real time and one warpPerspective.

Per scenario (sea, grass; every flight of it) and image size, measured in the same run:
- drawing a frame (`sim.render.WorldRenderer.render`): frames/s, and the ratio to real time at the scenario's
  30 fps (>= 1: faster than real time);
- the same per frame in ms beside one plain `cv2.warpPerspective` of the ground texture into the whole frame
  with that frame's pose (the floor the renderer's ground is built on): the ratio says what everything else
  costs on top;
- `render_dataset` writing JPEG images and MP4 video after the worlds are set up (encoding on a second
  thread): frames/s against real time; and the set-up (ground textures) per world in seconds.

--quick: 20 frames of the first flight of each scenario (each world's ground set-up, done twice, was 2/3 of the
3 minutes that every flight took).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

DESCRIPTION = "uavmm render: frames/s at 1080p and 4K vs real time (30 fps) and vs one plain warpPerspective"

SIZES = ((1920, 1080), (3840, 2160))


def _draw_and_warp_s(data: Path) -> tuple[list[float], list[float], float, float, int]:
    """Per frame: drawing seconds and plain-warp seconds (alternating, so load hits both); set-up s; fps; worlds."""
    from sim.render import SimulatedDataset, WorldRenderer, exposure_for
    from sim.render.geometry import texture_to_image_homography, uav_world_en

    ds = SimulatedDataset(data)
    draw, warp = [], []
    setup_s = 0.0
    for group in sorted(ds.worlds):
        t0 = time.perf_counter()
        renderer = WorldRenderer(ds, ds.worlds[group])
        setup_s += time.perf_counter() - t0
        tex = renderer.ground.levels[0]
        for video in renderer.videos:
            drift = exposure_for(ds, video)
            frames = list(ds.frames(video))
            renderer.render(frames[0], drift)  # warm-up
            for frame in frames:
                t0 = time.perf_counter()
                renderer.render(frame, drift)
                draw.append(time.perf_counter() - t0)
                uav = uav_world_en(frame.pose, renderer.world.origin_lat, renderer.world.origin_lon)
                m = texture_to_image_homography(renderer.camera, frame.pose, uav, renderer.ground.texel_to_world(0))
                t0 = time.perf_counter()
                cv2.warpPerspective(tex, m, (renderer.camera.width, renderer.camera.height), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REFLECT_101)
                warp.append(time.perf_counter() - t0)
    return draw, warp, setup_s, ds.fps, len(ds.worlds)


def run(quick: bool = False) -> list[dict[str, Any]]:
    from sim.dataset import write_dataset
    from sim.render import render_dataset
    from sim.scenarios import get_scenario

    frames = 20 if quick else 90
    rows: list[dict[str, Any]] = []
    for name in ("sea", "grass"):
        scenario = get_scenario(name)
        if quick:
            scenario = dataclasses.replace(scenario, flights=scenario.flights[:1])
        for width, height in SIZES:
            flights = f"{scenario.n_videos} flight{'' if scenario.n_videos == 1 else 's'}"
            label = f"{name} {width}x{height}, {flights} x {frames} frames"
            with tempfile.TemporaryDirectory() as tmp:
                data = Path(tmp) / "d"
                write_dataset(dataclasses.replace(scenario, image_size=(width, height)), data, seed=0, frames=frames,
                              progress=False)
                draw, warp, setup_s, fps, worlds = _draw_and_warp_s(data)
                draw_s, warp_s = float(np.median(draw)), float(np.median(warp))
                rows.append({"case": f"{label}: draw", "value": 1.0 / draw_s, "unit": "frames/s",
                             "baseline_name": f"real time ({fps:g} fps)", "ratio": 1.0 / draw_s / fps})
                rows.append({"case": f"{label}: draw, ms per frame", "value": draw_s * 1e3, "unit": "ms",
                             "baseline_name": "one warpPerspective of the ground", "ratio": draw_s / warp_s})
                summary = render_dataset(data, images=True, video=True, progress=False)
                rows.append({"case": f"{label}: draw + JPEG + MP4 after set-up", "value": summary["frames_per_s"],
                             "unit": "frames/s", "baseline_name": f"real time ({fps:g} fps)",
                             "ratio": summary["frames_per_s"] / fps})
                rows.append({"case": f"{label}: set-up (ground) per world", "value": setup_s / worlds, "unit": "s"})
    return rows

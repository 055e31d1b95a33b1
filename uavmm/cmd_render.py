"""`uavmm render DIR`: draw the frames of a simulated dataset (image files, MP4 + SRT/CSV telemetry).

Registered through `uavmm.cli.COMMAND_MODULES`; `uavmm sim --render` shares its flags (`uavmm.render_args`).
The work is in `sim.render.render_dataset` (docs/simulator.md, Rendering).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from uavmm.render_args import add_render_options, print_render_summary, render_kwargs


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `render` subcommand to the `uavmm` parser."""
    p = sub.add_parser(
        "render", help="draw the frames of a simulated dataset (images, MP4 + SRT/CSV telemetry)",
        description="Render a dataset directory written by `uavmm sim`: a procedural ground (sea with waves and "
                    "sun glint, or meadow with soil and roads) warped with each frame's TRUE pose, sky, haze, the "
                    "annotated objects as textured sprites of their size with shadows, trees, clutter, motion "
                    "blur on blurred frames, exposure and colour drift. Writes the image files named in "
                    "images.json and, with --video, an MP4 per video with its telemetry (the dataset's noisy "
                    "meta) as DJI-style SRT and CSV, and render.json. See docs/simulator.md.",
    )
    p.add_argument("directory", type=Path, help="dataset directory (images.json, camera.json, truth.json)")
    add_render_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Handler of `uavmm render`: validate, render, print a summary; returns the exit code."""
    from sim.render import render_dataset

    kwargs = render_kwargs(args)
    summary = render_dataset(args.directory, progress=not args.quiet, **kwargs)
    print_render_summary(summary)
    return 0

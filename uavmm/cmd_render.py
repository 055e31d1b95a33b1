"""`uavmm render DIR`: draw the frames of a simulated dataset (image files, MP4 + SRT/CSV telemetry).

Registered through `uavmm.cli.COMMAND_MODULES`; `uavmm sim --render` shares the options defined here. The work
is in `sim.render.render_dataset` (docs/simulator.md, Rendering).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from uavmm.cli import CliError


def add_render_options(p: argparse.ArgumentParser) -> None:
    """The flags `uavmm render` and `uavmm sim --render` share."""
    g = p.add_argument_group("rendering (docs/simulator.md, Rendering)")
    g.add_argument("--video", action="store_true",
                   help="also write <video name>.mp4 with its telemetry <video name>.srt (DJI style) and .csv "
                        "per video, for uavmm agent --video")
    g.add_argument("--no-images", action="store_true", help="do not write the image files (needs --video)")
    g.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality of the image files, 1..100 (90)")
    g.add_argument("--max-texture-px", type=int, default=4096,
                   help="longest side of the near ground texture in texels (4096)")
    g.add_argument("--no-scenery", action="store_true",
                   help="no boats or cars (unannotated objects the renderer adds; listed in render.json)")
    g.add_argument("--sensor-noise", type=float, default=2.0, help="sensor noise std, grey levels (2; 0 = none)")


def render_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of `sim.render.render_dataset` from the parsed flags; CliError for bad combinations."""
    from sim.render import RenderOptions

    if args.no_images and not args.video:
        raise CliError("--no-images writes nothing without --video")
    if not 1 <= args.jpeg_quality <= 100:
        raise CliError(f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    try:
        options = RenderOptions(max_texture_px=args.max_texture_px, scenery=not args.no_scenery,
                                sensor_noise_std=args.sensor_noise)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return {"images": not args.no_images, "video": args.video, "options": options, "jpeg_quality": args.jpeg_quality}


def print_render_summary(summary: dict[str, Any]) -> None:
    """The CLI's result lines: counts, speed, then each video and telemetry file."""
    print(f"rendered {summary['directory']}: {summary['frames']} frames ({summary['width']}x{summary['height']}), "
          f"{summary['images']} images, {len(summary['videos'])} videos in {summary['seconds']} s: ground of "
          f"{summary['worlds']} world(s) {summary['setup_s']} s, then {summary['frames_per_s']} frames/s "
          f"(drawing alone {summary['draw_frames_per_s']} frames/s)")
    for path in summary["videos"] + summary["telemetry"]:
        print(f"  {path}")


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

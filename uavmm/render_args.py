"""The rendering flags `uavmm render` and `uavmm sim --render` share, and the summary both print.

Kept apart from both commands so that `uavmm.cli` (which defines `sim`) and `uavmm.cmd_render` need not
import each other.
"""

from __future__ import annotations

import argparse
from typing import Any


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
    g.add_argument("--frozen-sea", action="store_true",
                   help="keep the sea's waves and glint fixed in the world (the renderer before 25 Nov 2026; "
                        "for comparisons)")


def render_flags_given(args: argparse.Namespace) -> list[str]:
    """The rendering flags of `add_render_options` but --video given with values other than their defaults (`uavmm
    sim` refuses them without --render or --video: nothing is drawn)."""
    probe = argparse.ArgumentParser(add_help=False)
    add_render_options(probe)
    return [action.option_strings[0] for action in probe._actions
            if action.dest != "video" and getattr(args, action.dest, action.default) != action.default]


def render_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of `sim.render.render_dataset` from the parsed flags; ValueError (one line, exit 2 from
    `uavmm.cli.main`) for bad values and combinations."""
    from sim.render import RenderOptions

    if args.no_images and not args.video:
        raise ValueError("--no-images writes nothing without --video")
    if not 1 <= args.jpeg_quality <= 100:
        raise ValueError(f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    options = RenderOptions(max_texture_px=args.max_texture_px, scenery=not args.no_scenery,
                            sensor_noise_std=args.sensor_noise, sea_waves=not args.frozen_sea)
    return {"images": not args.no_images, "video": args.video, "options": options, "jpeg_quality": args.jpeg_quality}


def print_render_summary(summary: dict[str, Any]) -> None:
    """The CLI's result lines: counts, speed, then each video and telemetry file."""
    print(f"rendered {summary['directory']}: {summary['frames']} frames ({summary['width']}x{summary['height']}), "
          f"{summary['images']} images, {len(summary['videos'])} videos in {summary['seconds']} s: ground of "
          f"{summary['worlds']} world(s) {summary['setup_s']} s, then {summary['frames_per_s']} frames/s "
          f"(drawing alone {summary['draw_frames_per_s']} frames/s)")
    for path in summary["videos"] + summary["telemetry"]:
        print(f"  {path}")

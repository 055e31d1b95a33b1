"""`uavmm export --db FUSION.sqlite --out FILE.gpkg|.kml|.kmz|.geojson`: the fusion server's history for GIS tools."""

from __future__ import annotations

import argparse
import math
import sys
from datetime import datetime, timezone
from pathlib import Path

from uavmm.cli import CliError

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand."""
    p = sub.add_parser(
        "export", help="the fusion server's stored tracks as GeoPackage (QGIS), KML/KMZ (Google Earth, ATAK) or "
                       "GeoJSON",
        description="Read a fusion server's SQLite database (read-only; the server may keep running) and write "
                    "its global tracks: a GeoPackage with the layers tracks, track_lines and track_points, a KML "
                    "document (zipped: .kmz), or a GeoJSON FeatureCollection, chosen by the --out extension.",
    )
    p.add_argument("--db", type=Path, required=True, help="the fusion server's database (uavmm fusion --db)")
    p.add_argument("--out", type=Path, required=True, help="output file: .gpkg, .kml, .kmz or .geojson")
    p.add_argument("--cls", default=None, help="only this class")
    p.add_argument("--since", type=float, default=None, metavar="EPOCH_S",
                   help="only tracks updated since this time (seconds since the epoch), and history from then on")
    p.set_defaults(handler=_run_export)


def _run_export(args: argparse.Namespace) -> int:
    from fusion_server.history_export import EXPORT_FORMATS, export_history, stored_classes

    if args.since is not None and not math.isfinite(args.since):
        raise CliError(f"--since must be a finite time in seconds since the epoch, got {args.since}")
    counts = export_history(args.db, args.out, cls=args.cls, since=args.since)
    kind = EXPORT_FORMATS[args.out.suffix.lower()]
    sys.stdout.write(f"wrote {args.out} ({kind}): " + ", ".join(f"{k}={v}" for k, v in counts.items()) + "\n")
    if not counts["tracks"]:
        sys.stderr.write(_nothing_matched(args, *stored_classes(args.db)) + "\n")
    return 0


def _nothing_matched(args: argparse.Namespace, classes: dict[str, int], latest: float | None) -> str:
    """The warning for an export without tracks: what the database holds, so a typo in --cls or --since in
    milliseconds shows."""
    if not classes:
        return "uavmm export: warning: the database has no tracks yet"
    filters = "".join(f" --{name} {value}" for name, value in (("cls", args.cls), ("since", args.since))
                      if value is not None)
    held = ", ".join(f"{name} ({n})" for name, n in classes.items())
    try:
        when = f" ({datetime.fromtimestamp(latest, timezone.utc):%Y-%m-%dT%H:%M:%SZ})" if latest is not None else ""
    except (OverflowError, ValueError, OSError):  # not a time a datetime holds
        when = ""
    return (f"uavmm export: warning: no tracks match{filters}; the database has tracks of class {held}, "
            f"the last one updated at {latest} s since the epoch{when}")

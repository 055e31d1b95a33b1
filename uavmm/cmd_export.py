"""`uavmm export --db FUSION.sqlite --out FILE.gpkg|.kml|.kmz|.geojson`: the fusion server's history for GIS tools."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

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
    from fusion_server.history_export import EXPORT_FORMATS, export_history

    counts = export_history(args.db, args.out, cls=args.cls, since=args.since)
    kind = EXPORT_FORMATS[args.out.suffix.lower()]
    sys.stdout.write(f"wrote {args.out} ({kind}): " + ", ".join(f"{k}={v}" for k, v in counts.items()) + "\n")
    return 0

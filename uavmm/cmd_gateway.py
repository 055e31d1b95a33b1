"""`uavmm gateway`: serve the REST API and map page of a sharded deployment (`uavmm fusion --shard K/N`).

Parses the flags into FusionSettings (the REST and Zenoh side; the gateway keeps no database), runs the
gateway until SIGINT/SIGTERM and prints the map URL.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from uavmm._signals import stop_on_signals
from uavmm._zenoh_args import add_zenoh_arguments, zenoh_options_from_args
from uavmm.cmd_fusion import _rest_access_line, add_map_max_cells_argument, http_address, http_tokens_from_args

__all__ = ["register", "settings_from_args"]

log = logging.getLogger("uavmm.gateway")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``gateway`` subcommand."""
    p = sub.add_parser(
        "gateway", help="serve the whole map of sharded fusion servers (REST API, map page, joint/tracks)",
        description="Serve the REST API and map page of N fusion shards (`uavmm fusion --shard K/N`) as one "
                    "map: joint tiles asked of the shards over Zenoh, global tracks merged from their regions "
                    "and published on joint/tracks, UAVs from their state messages. A shard that is down "
                    "shows as degraded (/healthz, /v1/uavs); the rest keeps working.",
    )
    add_zenoh_arguments(p)
    p.add_argument("--shards", type=int, required=True, metavar="N",
                   help="how many shards there are (the N of their --shard K/N)")
    p.add_argument("--region-zoom", type=int, default=None, metavar="Z",
                   help="zoom of the shard regions (default 14); the shards' --region-zoom")
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT",
                   help="REST API address (default 127.0.0.1:8000; port 0 picks a free one)")
    p.add_argument("--http-token-file", type=Path, default=None, metavar="FILE",
                   help="REST bearer tokens, one per line (TOKEN or NAME:TOKEN). Default: $UAVMM_HTTP_TOKEN; "
                        "with neither, an --http beyond loopback gets a generated token, printed at start-up")
    p.add_argument("--insecure-public", action="store_true",
                   help="serve the REST API beyond loopback without a token (only behind your own proxy)")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="let pages from ORIGIN read the REST API in a browser (repeatable; none by default)")
    p.add_argument("--basemap", default=None, metavar="URL|FILE.mbtiles",
                   help="map under the live page: an XYZ tile URL with {z}/{x}/{y} (fetched by the browser) or "
                        "an MBTiles file served by this gateway (offline)")
    p.add_argument("--basemap-attribution", default=None, metavar="TEXT",
                   help="attribution shown with the basemap (default: the MBTiles file's)")
    p.add_argument("--prefix", default="uavmm/v1", help="key prefix (default uavmm/v1)")
    p.add_argument("--tracks-max-hz", type=float, default=5.0,
                   help="most joint/tracks messages a second (5; one a second while nothing changes)")
    p.add_argument("--max-clock-skew-s", type=float, default=30.0,
                   help="drop UAV states and shard region messages whose t is this far ahead of the gateway's "
                        "clock (30; the shards' value)")
    p.add_argument("--grid-z", type=int, default=18, help="zoom of the shared tile grid (18)")
    p.add_argument("--grid-n", type=int, default=256, help="cells per tile edge of the shared grid (256)")
    add_map_max_cells_argument(p)
    p.set_defaults(handler=_run_gateway, no_http=False)


def settings_from_args(args: argparse.Namespace):
    """FusionSettings of the gateway from parsed flags; ValueError naming the bad flag."""
    from fusion_server.config import FusionSettings
    from shared.sharding import DEFAULT_REGION_ZOOM, ShardSpec

    zoom = DEFAULT_REGION_ZOOM if args.region_zoom is None else args.region_zoom
    try:
        ShardSpec(0, args.shards, zoom)
    except ValueError as exc:
        raise ValueError(f"--shards/--region-zoom: {exc}") from None
    if args.shards < 2:
        raise ValueError(f"--shards must be at least 2, got {args.shards} (one fusion server serves its own map)")
    host, port = http_address(args.http)
    tokens, _ = http_tokens_from_args(args, host)
    return FusionSettings(
        zenoh=zenoh_options_from_args(args), http_host=host, http_port=port, db_path=None, prefix=args.prefix,
        grid_z=args.grid_z, grid_n=args.grid_n, shard_index=0, shard_count=args.shards, region_zoom=zoom,
        http_tokens=tokens, insecure_public=args.insecure_public, cors_origins=tuple(args.cors_origin),
        map_max_cells=args.map_max_cells, tracks_max_hz=args.tracks_max_hz, max_clock_skew_s=args.max_clock_skew_s,
        basemap=args.basemap, basemap_attribution=args.basemap_attribution,
    )


def _run_gateway(args: argparse.Namespace) -> int:
    import zenoh

    from fusion_server.gateway import Gateway
    from transport.certificates import check_certificates
    from transport.options import zenoh_config

    settings = settings_from_args(args)
    check_certificates(zenoh_config(settings.zenoh), log)
    stop = stop_on_signals(log)
    try:
        with Gateway(settings) as gateway:
            gateway.start()
            assert gateway.url is not None
            connect = ", ".join(settings.zenoh.connect or ("from config",))
            sys.stdout.write(f"uavmm gateway: {settings.shard_count} shards (regions of zoom {settings.region_zoom}); "
                             f"zenoh {settings.zenoh.mode or 'peer'} to {connect}; map: {gateway.url}\n")
            sys.stdout.write(_rest_access_line(settings, gateway.url, args).replace("uavmm fusion", "uavmm gateway")
                             + "\n")
            sys.stdout.flush()
            while not stop.wait(0.5):
                pass
    except zenoh.ZError as exc:
        sys.stderr.write(f"uavmm gateway: error: zenoh: {exc}\n")
        return 2
    return 0

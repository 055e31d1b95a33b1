"""`uavmm fusion`: run the fusion server (Zenoh side, joint map, global tracks, REST API, SQLite).

Parses the flags into a FusionSettings, runs the server until SIGINT/SIGTERM and prints the map URL.
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import sys
from pathlib import Path

from uavmm._signals import stop_on_signals
from uavmm._zenoh_args import add_zenoh_arguments, zenoh_options_from_args

__all__ = ["DEFAULT_LISTEN", "DEFAULT_MAP_MAX_CELLS", "add_map_max_cells_argument", "add_zenoh_arguments",
           "register", "settings_from_args", "shard_from_args"]

log = logging.getLogger("uavmm.fusion")

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
DEFAULT_MODE = "router"


def _config_file_sets(path: Path | None) -> tuple[str | None, bool]:
    """The ``mode`` the Zenoh config file itself sets (None if it does not), and whether it sets
    ``listen/endpoints``: as the help of ``--mode`` and ``--listen`` says, only then are DEFAULT_MODE and
    DEFAULT_LISTEN left out. Zenoh's own defaults (listen/endpoints is a per-mode table that is never
    empty) do not count: the file's keys are read. ValueError naming a file Zenoh or the parser cannot read."""
    if path is None:
        return None, False
    from transport.options import ZenohOptions, config_file_value, zenoh_config

    zenoh_config(ZenohOptions(config_file=path))  # the server's own errors for a file Zenoh refuses
    mode = config_file_value(path, "mode")
    return (str(mode) if mode is not None else None), config_file_value(path, "listen/endpoints") is not None


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fusion`` subcommand."""
    p = sub.add_parser(
        "fusion", help="run the fusion server (joint map, global tracks, REST API)",
        description="Subscribe to the agents over Zenoh, fuse their tiles into the joint map (mean over the "
                    "UAVs covering a cell), associate their tracks into global tracks, publish both, keep "
                    "them in SQLite and serve the read-only REST API and map page.",
    )
    add_zenoh_arguments(p, default_mode=DEFAULT_MODE, default_listen=DEFAULT_LISTEN)
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT",
                   help="REST API address (default 127.0.0.1:8000; port 0 picks a free one)")
    p.add_argument("--no-http", action="store_true", help="do not serve the REST API")
    p.add_argument("--http-token-file", type=Path, default=None, metavar="FILE",
                   help="REST bearer tokens, one per line (TOKEN or NAME:TOKEN; `uavmm secure init` writes "
                        "fusion/http-tokens). Default: $UAVMM_HTTP_TOKEN; with neither, an --http beyond "
                        "loopback gets a generated token, printed once at start-up")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="let pages from ORIGIN (e.g. https://maps.example.org) read the REST API in a browser "
                        "(repeatable; none by default)")
    p.add_argument("--cot-url", default=None, metavar="URL",
                   help="send Cursor-on-Target events of the UAVs, global tracks and untracked fused objects to "
                        "TAK: udp://HOST:PORT (unicast or multicast, e.g. udp://239.2.3.1:6969) or tcp://HOST:PORT "
                        "(a TAK server)")
    p.add_argument("--cot-objects-min-score", type=float, default=0.5, metavar="S",
                   help="--cot-url: also send the fused objects (joint-map peaks >= S, as /v1/objects) that no "
                        "global track explains (0.5)")
    p.add_argument("--no-cot-objects", action="store_true", help="--cot-url: UAVs and global tracks only")
    p.add_argument("--basemap", default=None, metavar="URL|FILE.mbtiles",
                   help="map under the live page: an XYZ tile URL with {z}/{x}/{y} (fetched by the browser) or "
                        "an MBTiles file served by this server (offline)")
    p.add_argument("--basemap-attribution", default=None, metavar="TEXT",
                   help="attribution shown with the basemap (default: the MBTiles file's)")
    p.add_argument("--insecure-public", action="store_true",
                   help="serve the REST API beyond loopback without a token (only behind your own "
                        "authenticating proxy, or a container port published on loopback)")
    p.add_argument("--db", type=Path, default=None,
                   help="SQLite file (default $XDG_DATA_HOME/uavmm/fusion.sqlite, i.e. ~/.local/share/...)")
    p.add_argument("--no-db", action="store_true", help="keep nothing on disk")
    p.add_argument("--db-recover", action="store_true",
                   help="if the database fails its start-up check, move it aside (NAME.bad-TIME) and start a new one")
    p.add_argument("--restore-keep-s", type=float, default=300.0,
                   help="after a restart, serve the saved joint map until this long after its last update (300)")
    p.add_argument("--prefix", default="uavmm/v1", help="key prefix (default uavmm/v1)")
    p.add_argument("--ttl-s", type=float, default=2.0, help="a UAV covers a tile this long after its message (2)")
    p.add_argument("--fusion-rule", default="mean", help="mean (default, the paper's), max or noisy-or")
    p.add_argument("--coverage", choices=("footprint", "tile"), default="footprint",
                   help="which cells a UAV covers: those in its camera footprints of the last --ttl-s "
                        "(default) or its whole tiles")
    p.add_argument("--joint-max-hz", type=float, default=5.0, help="most joint publications per tile a second (5)")
    p.add_argument("--tracks-max-hz", type=float, default=5.0, help="most joint tracks messages a second (5)")
    p.add_argument("--track-gate-m", type=float, default=10.0, help="association gate on the ground, m (10)")
    p.add_argument("--track-hold-s", type=float, default=10.0, help="keep a track nobody reports this long (10)")
    p.add_argument("--track-reassociate-m", type=float, default=6.0,
                   help="move a UAV's track to the global track other UAVs report its object under when, for "
                        "seconds, that one lies within this many metres and clearly nearer than its own (6; 0: off)")
    p.add_argument("--max-clock-skew-s", type=float, default=30.0,
                   help="drop messages whose t is this far ahead of the server clock (30)")
    p.add_argument("--uav-max-msgs-per-s", type=float, default=500.0,
                   help="per-UAV message rate limit, messages/s (500; bursts of 2 s)")
    p.add_argument("--uav-max-bytes-per-s", type=float, default=4 * 1024 * 1024,
                   help="per-UAV payload rate limit, bytes/s (4 MiB; bursts of 2 s)")
    p.add_argument("--inbox-max-age-s", type=float, default=5.0,
                   help="a UAV message that waited longer than this for the fusion thread (the server fell "
                        "behind) is dropped unread as 'overloaded': it catches up on fresh data (5)")
    p.add_argument("--grid-z", type=int, default=18, help="zoom of the shared tile grid (18)")
    p.add_argument("--grid-n", type=int, default=256, help="cells per tile edge of the shared grid (256)")
    add_map_max_cells_argument(p)
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="run as shard K of N (from 0): fuse and track only the regions hashed to K; a "
                        "`uavmm gateway` serves the whole map (docs/deploy.md, 'Sharding')")
    p.add_argument("--region-zoom", type=int, default=None, metavar="Z",
                   help="zoom of the shard regions (14: 16 x 16 grid tiles, 2.4 km x cos(lat)); all shards "
                        "and the gateway must agree")
    p.set_defaults(handler=_run_fusion)


#: FusionSettings.map_max_cells (kept here too: the CLI does not import the server to build its parser)
DEFAULT_MAP_MAX_CELLS = 2**23


def add_map_max_cells_argument(p: argparse.ArgumentParser) -> None:
    """``--map-max-cells N``: the largest /v1/map window (fusion server and gateway)."""
    p.add_argument("--map-max-cells", type=int, default=DEFAULT_MAP_MAX_CELLS, metavar="N",
                   help="most cells of one /v1/map window; larger bboxes get a 400 (default 8388608 = 2^23: "
                        "1 km x 1 km at the default grid up to ~54 deg latitude; a dense answer is ~4 bytes a cell)")


def shard_from_args(args: argparse.Namespace):
    """The ShardSpec of --shard / --region-zoom (single() without --shard); ValueError naming the flag."""
    from shared.sharding import DEFAULT_REGION_ZOOM, ShardSpec, parse_shard

    zoom = DEFAULT_REGION_ZOOM if args.region_zoom is None else args.region_zoom
    if args.shard is None:
        if args.region_zoom is not None:
            raise ValueError("--region-zoom needs --shard K/N")
        return ShardSpec.single()
    try:
        return parse_shard(args.shard, zoom)
    except ValueError as exc:
        raise ValueError(f"--shard: {exc}") from None


def http_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` of --http (an IPv6 host in brackets) as (host, port); ValueError naming --http."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ValueError(f"--http must be HOST:PORT, got {text!r}")
    if not 0 <= int(port) <= 65535:
        raise ValueError(f"--http: the port must be in 0..65535, got {port}")
    return host.strip("[]"), int(port)


def http_tokens_from_args(args: argparse.Namespace, host: str) -> tuple[tuple, bool]:
    """The REST tokens the flags ask for, and whether one was generated here.

    ``--http-token-file``, else ``$UAVMM_HTTP_TOKEN``, else (a bind beyond loopback without
    ``--insecure-public``) a new random token. ValueError for an unreadable file or a too short token.
    """
    from fusion_server.http_auth import HttpToken, is_loopback_host, read_token_file

    if args.http_token_file is not None:
        return read_token_file(args.http_token_file), False
    env = os.environ.get("UAVMM_HTTP_TOKEN", "").strip()
    if env:
        try:
            return (HttpToken("UAVMM_HTTP_TOKEN", env),), False
        except ValueError as exc:
            raise ValueError(f"UAVMM_HTTP_TOKEN: {exc}") from None
    if args.no_http or args.insecure_public or is_loopback_host(host):
        return (), False
    return (HttpToken("generated", secrets.token_urlsafe(32)),), True


def settings_from_args(args: argparse.Namespace):
    """FusionSettings from parsed flags; ValueError on bad values."""
    from fusion_server.config import FusionSettings, default_db_path

    file_mode, file_listens = _config_file_sets(args.config)
    mode = args.mode or file_mode or DEFAULT_MODE
    default_listen = None
    if args.listen is None and mode != "client" and not file_listens:
        default_listen = [DEFAULT_LISTEN]
    zenoh_options = zenoh_options_from_args(args, default_listen=default_listen,
                                            default_mode=None if file_mode is not None else DEFAULT_MODE)
    host, port = http_address(args.http)
    tokens, _ = http_tokens_from_args(args, host)
    shard = shard_from_args(args)
    return FusionSettings(
        shard_index=shard.index, shard_count=shard.count, region_zoom=shard.region_zoom,
        zenoh=zenoh_options, http_host=host, http_port=port,
        db_path=None if args.no_db else (args.db or default_db_path()),
        prefix=args.prefix, ttl_s=args.ttl_s, fusion_rule=args.fusion_rule, coverage=args.coverage, grid_z=args.grid_z,
        grid_n=args.grid_n, joint_max_hz=args.joint_max_hz, tracks_max_hz=args.tracks_max_hz,
        track_gate_m=args.track_gate_m, track_hold_s=args.track_hold_s, track_reassociate_m=args.track_reassociate_m,
        max_clock_skew_s=args.max_clock_skew_s,
        uav_max_msgs_per_s=args.uav_max_msgs_per_s, uav_max_bytes_per_s=args.uav_max_bytes_per_s,
        inbox_max_age_s=args.inbox_max_age_s, db_recover=args.db_recover, restore_keep_s=args.restore_keep_s,
        http_tokens=tokens, insecure_public=args.insecure_public, cors_origins=tuple(args.cors_origin),
        cot_url=args.cot_url, cot_objects_min_score=None if args.no_cot_objects else args.cot_objects_min_score,
        basemap=args.basemap, basemap_attribution=args.basemap_attribution, map_max_cells=args.map_max_cells,
    )


def _rest_access_line(settings, url: str, args: argparse.Namespace) -> str:
    """One start-up line saying who may read the REST API."""
    from fusion_server.http_auth import is_loopback_host

    tokens = settings.http_tokens
    if not tokens:
        if is_loopback_host(settings.http_host):
            return "uavmm fusion: REST API open to this machine only (loopback)"
        return (f"uavmm fusion: WARNING: REST API on {settings.http_host} open to anyone who reaches it "
                "(--insecure-public)")
    if len(tokens) == 1 and tokens[0].name == "generated":
        return (f"uavmm fusion: REST API needs a bearer token; generated for this run: {tokens[0].token} "
                f"(page: {url}#token={tokens[0].token}; give --http-token-file to keep one)")
    source = args.http_token_file or "UAVMM_HTTP_TOKEN"
    return (f"uavmm fusion: REST API needs a bearer token ({len(tokens)} accepted, from {source}); "
            f"page: {url}#token=TOKEN")


def _run_fusion(args: argparse.Namespace) -> int:
    import zenoh

    from fusion_server.server import FusionServer
    from transport.certificates import check_certificates
    from transport.options import zenoh_config

    settings = settings_from_args(args)
    check_certificates(zenoh_config(settings.zenoh), log)
    stop = stop_on_signals(log)
    try:
        with FusionServer(settings) as server:
            if server.db_recovered is not None:
                problem, moved = server.db_recovered
                sys.stderr.write(f"uavmm fusion: database {settings.db_path} {problem}: moved it to {moved} "
                                 "and started a new database\n")
            server.start(http=not args.no_http)
            mode = settings.zenoh.mode or _config_file_sets(settings.zenoh.config_file)[0] or "peer"
            listen = "on " + ", ".join(settings.zenoh.listen or ("from config",))
            if mode == "client":
                listen = "to " + ", ".join(settings.zenoh.connect or ("from config",))
            where = f"map: {server.url}" if server.url else "REST API off"
            db = settings.db_path or "off"
            part = f"shard {settings.shard.label()} (regions of zoom {settings.region_zoom}); " \
                if settings.shard.sharded else ""
            sys.stdout.write(f"uavmm fusion: {part}zenoh {mode} {listen}; db {db}; {where}\n")
            if server.url:
                sys.stdout.write(_rest_access_line(settings, server.url, args) + "\n")
            sys.stdout.flush()
            while not stop.wait(0.5):
                pass
    except zenoh.ZError as exc:
        sys.stderr.write(f"uavmm fusion: error: zenoh: {exc}\n")
        return 2
    return 0

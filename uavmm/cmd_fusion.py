"""`uavmm fusion`: run the fusion server (Zenoh side, joint map, global tracks, REST API, SQLite).

Parses the flags into a FusionSettings, runs the server until SIGINT/SIGTERM and prints the map URL.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

log = logging.getLogger("uavmm.fusion")

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str | None = None,
                        default_listen: str | None = None) -> None:
    """The Zenoh options every uavmm process takes (as zenoh-python's examples/common/common.py)."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", "-m", choices=["peer", "router", "client"], default=default_mode,
                       help=f"Zenoh session mode (default: {default_mode or 'from --config, else peer'})")
    group.add_argument("--connect", "-e", metavar="ENDPOINT", action="append",
                       help="endpoint to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)")
    group.add_argument("--listen", "-l", metavar="ENDPOINT", action="append",
                       help=f"endpoint to listen on (repeatable; default {default_listen or 'Zenoh default'} "
                            "unless --config sets listen/endpoints)")
    group.add_argument("--config", "-c", metavar="FILE", type=Path,
                       help="Zenoh JSON5 config file (usrpwd, TLS, ACL ... pass through)")
    group.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    group.add_argument("--cfg", metavar="KEY:VALUE", action="append", default=[],
                       help="extra Zenoh config entry, VALUE in JSON5, e.g. 'transport/link/tx/lease:2000'")


def _config_sets_listen(path: Path | None) -> bool:
    if path is None:
        return False
    import zenoh

    try:
        return zenoh.Config.from_file(str(path)).get_json("listen/endpoints") not in ("null", "[]", "{}")
    except zenoh.ZError as exc:
        raise ValueError(f"cannot read zenoh config {path}: {exc}") from None


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fusion`` subcommand."""
    p = sub.add_parser(
        "fusion", help="run the fusion server (joint map, global tracks, REST API)",
        description="Subscribe to the agents over Zenoh, fuse their tiles into the joint map (mean over the "
                    "UAVs covering a cell), associate their tracks into global tracks, publish both, keep "
                    "them in SQLite and serve the read-only REST API and map page.",
    )
    add_zenoh_arguments(p, default_mode="router", default_listen=DEFAULT_LISTEN)
    p.add_argument("--http", default="127.0.0.1:8000", metavar="HOST:PORT",
                   help="REST API address (default 127.0.0.1:8000; port 0 picks a free one)")
    p.add_argument("--no-http", action="store_true", help="do not serve the REST API")
    p.add_argument("--db", type=Path, default=None,
                   help="SQLite file (default $XDG_DATA_HOME/uavmm/fusion.sqlite, i.e. ~/.local/share/...)")
    p.add_argument("--no-db", action="store_true", help="keep nothing on disk")
    p.add_argument("--prefix", default="uavmm/v1", help="key prefix (default uavmm/v1)")
    p.add_argument("--ttl-s", type=float, default=2.0, help="a UAV covers a tile this long after its message (2)")
    p.add_argument("--fusion-rule", default="mean", help="mean (default, the paper's), max or noisy-or")
    p.add_argument("--joint-max-hz", type=float, default=5.0, help="most joint publications per tile a second (5)")
    p.add_argument("--tracks-max-hz", type=float, default=5.0, help="most joint tracks messages a second (5)")
    p.add_argument("--track-gate-m", type=float, default=10.0, help="association gate on the ground, m (10)")
    p.add_argument("--track-hold-s", type=float, default=10.0, help="keep a track nobody reports this long (10)")
    p.add_argument("--grid-z", type=int, default=18, help="zoom of the shared tile grid (18)")
    p.add_argument("--grid-n", type=int, default=256, help="cells per tile edge of the shared grid (256)")
    p.set_defaults(handler=_run_fusion)


def _http_address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ValueError(f"--http must be HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


def settings_from_args(args: argparse.Namespace):
    """FusionSettings from parsed flags; ValueError on bad values."""
    from fusion_server.config import FusionSettings, ZenohOptions, default_db_path

    listen = args.listen
    if listen is None and not _config_sets_listen(args.config):
        listen = [DEFAULT_LISTEN]
    zenoh_options = ZenohOptions(
        mode=args.mode,
        connect=tuple(args.connect) if args.connect else None,
        listen=tuple(listen) if listen else None,
        config_file=args.config,
        multicast_scouting=False if args.no_multicast_scouting else None,
        cfg=tuple(args.cfg),
    )
    host, port = _http_address(args.http)
    return FusionSettings(
        zenoh=zenoh_options, http_host=host, http_port=port,
        db_path=None if args.no_db else (args.db or default_db_path()),
        prefix=args.prefix, ttl_s=args.ttl_s, fusion_rule=args.fusion_rule, grid_z=args.grid_z,
        grid_n=args.grid_n, joint_max_hz=args.joint_max_hz, tracks_max_hz=args.tracks_max_hz,
        track_gate_m=args.track_gate_m, track_hold_s=args.track_hold_s,
    )


def _run_fusion(args: argparse.Namespace) -> int:
    import zenoh

    from fusion_server.server import FusionServer

    settings = settings_from_args(args)
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        with FusionServer(settings) as server:
            server.start(http=not args.no_http)
            listen = ", ".join(settings.zenoh.listen or ("from config",))
            where = f"map: {server.url}" if server.url else "REST API off"
            db = settings.db_path or "off"
            sys.stdout.write(f"uavmm fusion: zenoh {settings.zenoh.mode or 'peer'} on {listen}; db {db}; {where}\n")
            sys.stdout.flush()
            while not stop.wait(0.5):
                pass
    except zenoh.ZError as exc:
        sys.stderr.write(f"uavmm fusion: error: zenoh: {exc}\n")
        return 2
    return 0

"""The Zenoh flags every uavmm subcommand takes, and their parsed form (`transport.options.ZenohOptions`).

Argument parsing stays in the CLI package; the value object and the ``zenoh.Config`` it builds are in transport/.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from transport.options import ZENOH_MODES, ZenohOptions

__all__ = ["add_zenoh_arguments", "zenoh_options_from_args"]


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str | None = None,
                        default_listen: str | None = None) -> None:
    """The Zenoh options every uavmm process takes (as zenoh-python's examples/common/common.py).

    default_mode, default_listen: only shown in the help; the caller applies them unless the --config
    file sets ``mode`` / ``listen/endpoints`` itself (see `zenoh_options_from_args`). Without them the
    config file's values, else Zenoh's defaults, apply.
    """
    group = parser.add_argument_group("zenoh")
    shown = f"{default_mode} unless --config sets mode" if default_mode else "from --config, else peer"
    group.add_argument("--mode", "-m", choices=list(ZENOH_MODES), default=None,
                       help=f"Zenoh session mode (default: {shown})")
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


def zenoh_options_from_args(args: argparse.Namespace, *, default_listen: Sequence[str] | None = None,
                            default_mode: str | None = None) -> ZenohOptions:
    """ZenohOptions from the flags `add_zenoh_arguments` added; ValueError on bad values.

    default_listen: endpoints used when no ``--listen`` was given (None: the config file's / Zenoh's).
    default_mode: the mode used when no ``--mode`` was given (None: the config file's / Zenoh's peer).
    """
    listen = args.listen if args.listen is not None else default_listen
    return ZenohOptions(
        mode=args.mode if args.mode is not None else default_mode,
        connect=tuple(args.connect) if args.connect else None,
        listen=tuple(listen) if listen else None,
        config_file=args.config,
        multicast_scouting=False if args.no_multicast_scouting else None,
        cfg=tuple(args.cfg),
    )

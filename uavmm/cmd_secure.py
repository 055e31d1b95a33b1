"""`uavmm secure init DIR --uavs ID,...`: a CA, identities, Zenoh configs with per-UAV ACLs and REST tokens.

Parses the flags into a `FleetPlan` (defaults from the folder's manifest when it already holds a fleet),
writes the folder with `fusion_server.provision` and prints what goes where.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["plan_from_args", "register"]


def _ids(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    return tuple(part.strip() for part in text.split(",") if part.strip())


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``secure`` subcommand (with its ``init`` action)."""
    p = sub.add_parser(
        "secure", help="make a fleet's credentials: CA, certificates, Zenoh configs with ACLs, REST tokens",
        description="Security set-up of a fleet (docs/deploy.md, 'Secure set-up').",
    )
    actions = p.add_subparsers(dest="secure_action", metavar="ACTION")
    init = actions.add_parser(
        "init", help="write (or extend) a fleet folder",
        description="Write a folder per identity: fusion/ (the ground station), uavs/ID/ (each drone), "
                    "operators/NAME/ (read-only users and their REST tokens), router/ (a zenohd router, "
                    "optional). Each UAV may put only on uavmm/v1/uav/<its id>/**, only the fusion server "
                    "on uavmm/v1/joint/**, everyone else is denied. Run again on the same folder to add "
                    "identities (existing keys are kept).",
    )
    init.add_argument("dir", type=Path, metavar="DIR", help="the fleet folder (new, or made by this command)")
    init.add_argument("--uavs", required=True, metavar="ID,...", help="UAV ids, comma-separated (their --uav-id)")
    init.add_argument("--operators", default=None, metavar="NAME,...",
                      help="read-only identities with a REST token each (default: operator)")
    init.add_argument("--server-host", action="append", default=None, metavar="NAME",
                      help="name or address the agents dial, repeatable or comma-separated; the first one goes "
                           "into their configs, all into the server certificate (default: localhost, 127.0.0.1)")
    init.add_argument("--port", type=int, default=None, help="Zenoh TLS port of the server (7447)")
    init.add_argument("--auth", choices=("mtls", "usrpwd"), default=None,
                      help="mtls (default): a client certificate per identity; usrpwd: TLS plus a password each")
    init.add_argument("--prefix", default=None, help="key prefix (default uavmm/v1)")
    init.add_argument("--mount-path", default=None, metavar="PATH",
                      help="write file paths for each folder mounted at PATH (e.g. /etc/uavmm in containers); "
                           "default: the folders' own absolute paths")
    init.add_argument("--days", type=int, default=825,
                      help="validity of new certificates in days (825; at most 3650 and what the folder's CA has left)")
    p.set_defaults(handler=_run_secure, secure_parser=p)


def plan_from_args(args: argparse.Namespace):
    """FleetPlan from the flags; the folder's manifest supplies the settings not given. ValueError on bad values."""
    from fusion_server.provision import MANIFEST, FleetPlan

    known: dict = {}
    manifest = args.dir / MANIFEST
    if manifest.is_file():
        try:
            known = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"cannot read {manifest}: {exc}") from None
    hosts = None
    if args.server_host:
        hosts = tuple(h for item in args.server_host for h in _ids(item) or ())
    given = {
        "server_hosts": hosts, "port": args.port, "auth": args.auth, "prefix": args.prefix,
        "mount_path": args.mount_path, "operators": _ids(args.operators),
    }
    values = {}
    for name, value in given.items():
        if value is not None:
            values[name] = value
        elif name in known:
            values[name] = tuple(known[name]) if isinstance(known[name], list) else known[name]
    if known and args.operators is None:
        values["operators"] = ()  # keep the folder's operators (merged in provision), add none
    uavs = _ids(args.uavs) or ()
    return FleetPlan(uavs=uavs, days=args.days, **values)


def _run_secure(args: argparse.Namespace) -> int:
    from fusion_server.provision import provision

    if args.secure_action != "init":
        args.secure_parser.print_help(sys.stderr)
        return 2
    plan = plan_from_args(args)
    result = provision(args.dir, plan)
    added = ", ".join(result.added) or "none (all existed)"
    sys.stdout.write(f"uavmm secure: wrote {result.root} ({plan.auth}); new identities: {added}\n")
    sys.stdout.write(f"  ground station: {result.root / 'fusion'}/  -> uavmm fusion --config zenoh.json5 "
                     "--http-token-file http-tokens\n")
    for uav in plan.uavs:
        sys.stdout.write(f"  {uav}: {result.folders[uav]}/  -> uavmm agent --uav-id {uav} --config zenoh.json5 ...\n")
    if result.without_token:
        sys.stdout.write(f"  no REST token (its line was deleted from http-tokens): {', '.join(result.without_token)}; "
                         "name them with --operators to issue new ones\n")
    for line in _expiring(result.root):
        sys.stdout.write(f"  {line}\n")
    sys.stdout.write(f"  keep {result.root / 'ca' / 'ca.key'} offline; see {result.root / 'README.md'}\n")
    return 0


def _expiring(root: Path) -> list[str]:
    """A line for each certificate of the fleet folder that has run out or runs out within
    `transport.certificates.EXPIRY_WARNING_DAYS` days (kept certificates are not renewed by a re-run)."""
    import datetime as dt

    from shared.pki import certificate_validities
    from transport.certificates import EXPIRY_WARNING_DAYS

    now = dt.datetime.now(dt.timezone.utc)
    lines = []
    for path in [root / "ca" / "ca.pem", *sorted(root.rglob("cert.pem"))]:
        try:
            validities = certificate_validities(path.read_bytes())
        except (OSError, ValueError):
            continue
        end = min(v.not_after for v in validities)
        if end - now > dt.timedelta(days=EXPIRY_WARNING_DAYS):
            continue
        when = end.strftime("%Y-%m-%d")
        if path.parent == root / "ca":
            lines.append(f"the fleet's CA {'expired' if end < now else 'expires'} on {when}: no certificate it "
                         "signed works after that; make a new fleet folder")
        else:
            lines.append(f"{path.parent.name}'s certificate {'expired' if end < now else 'expires'} on {when}: "
                         f"delete {path} and its key.pem and re-run to renew it")
    return lines

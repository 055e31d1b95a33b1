"""Zenoh configuration of the agent: the shared options of every uavmm process plus the agent's defaults.

The options themselves (``--mode/--connect/--listen/--config/--cfg``) are every process's
(`transport.options.ZenohOptions`, re-exported here), so all read them the same way; this module adds
what an agent on a drone needs: start without the ground station, keep retrying, reconnect.
"""

from __future__ import annotations

import json
import logging

import zenoh

from transport.options import ZENOH_MODES, ZenohOptions, zenoh_config
from transport.session import config_value, open_session  # open_session re-exported

__all__ = ["AGENT_DEFAULT_MODE", "ZENOH_MODES", "ZenohOptions", "agent_zenoh_config", "open_session"]

log = logging.getLogger(__name__)

#: A peer opens without a reachable router and keeps retrying its connect endpoints in the
#: background (measured: tiles flow ~0.5 s after the server comes back); a client cannot open at
#: all without its router, so `open_session` retries it.
AGENT_DEFAULT_MODE = "peer"

#: Defaults applied before the user's ``--cfg`` entries (which therefore override them): never exit
#: because the ground station is not up yet; retry every 0.5 s up to every 2 s; no gossip, so agents
#: in peer mode do not open links to each other over the radio (a star around the fusion server).
_AGENT_DEFAULTS = (
    ("connect/exit_on_failure", "false"),
    ("scouting/gossip/enabled", "false"),
    ("connect/retry", json.dumps({"period_init_ms": 500, "period_max_ms": 2000, "period_increase_factor": 2})),
)


def agent_zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config`` for an agent: the shared options with the agent's reconnection defaults.

    options: the parsed Zenoh options; mode None becomes ``AGENT_DEFAULT_MODE`` unless a config file
    sets one. ``--cfg`` entries are applied last and override the defaults. Raises ValueError for an
    unreadable config file or a bad ``--cfg`` value.
    """
    mode = options.mode
    if mode is None and options.config_file is None:
        mode = AGENT_DEFAULT_MODE
    cfg = tuple(f"{key}:{value}" for key, value in _AGENT_DEFAULTS) + tuple(options.cfg)
    return zenoh_config(ZenohOptions(mode=mode, connect=options.connect, listen=options.listen,
                                     config_file=options.config_file,
                                     multicast_scouting=options.multicast_scouting, cfg=cfg))


def identity_problem(conf: zenoh.Config, uav_id: str) -> str | None:
    """Why the identity in ``conf`` cannot publish as ``uav_id``, or None.

    The fleet's access control (`uavmm secure init`) lets an identity put only on its own UAV's keys:
    a usrpwd user or a mutual-TLS certificate common name other than ``uav_id`` would have every
    message dropped by the server without a word. The certificate is read with the optional
    `cryptography` package; without it the certificate is not checked.
    """
    user = config_value(conf, "transport/auth/usrpwd/user")
    if isinstance(user, str) and user != uav_id:
        return (f"the Zenoh config authenticates as user {user!r}, not --uav-id {uav_id!r}: the server's "
                "access control would drop every message (use that UAV's own config)")
    path = config_value(conf, "transport/link/tls/connect_certificate")
    if not isinstance(path, str) or config_value(conf, "transport/link/tls/enable_mtls") is not True:
        return None
    try:
        from shared.pki import certificate_common_name
    except ImportError:  # a drone without the server's packages: the server's ACL still holds
        log.debug("cryptography is not installed: the certificate's identity is not checked")
        return None
    try:
        with open(path, "rb") as handle:
            name = certificate_common_name(handle.read())
    except (OSError, ValueError) as exc:
        return f"cannot read the certificate {path} named in the Zenoh config: {exc}"
    if name != uav_id:
        return (f"the certificate {path} is for {name!r}, not --uav-id {uav_id!r}: the server's access "
                "control would drop every message (use that UAV's own config)")
    return None

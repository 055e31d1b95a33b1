"""Zenoh configuration of the agent: the shared options of every uavmm process plus the agent's defaults.

The options themselves (``--mode/--connect/--listen/--config/--cfg``) are every process's
(`shared.zenoh_options.ZenohOptions`, re-exported here), so all read them the same way; this module adds
what an agent on a drone needs: start without the ground station, keep retrying, reconnect.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import zenoh

from shared.zenoh_options import ZENOH_MODES, ZenohOptions, zenoh_config

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


def open_session(conf: zenoh.Config, stop: threading.Event | None = None, *, retry_s: float = 2.0,
                 timeout_s: float | None = None) -> zenoh.Session | None:
    """Open a Zenoh session, retrying while it fails (a client whose router is not up yet).

    Returns the session, or None when ``stop`` was set or ``timeout_s`` passed first. Errors other
    than a failed open (e.g. a malformed config) are raised by ``zenoh.open`` on the first try the
    same way, so a config mistake shows up as repeated warnings: use ``timeout_s`` in tests.
    """
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    attempt = 0
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            attempt += 1
            if attempt == 1 or attempt % 30 == 0:
                log.warning("cannot open the Zenoh session (attempt %d, retrying every %.1f s): %s",
                            attempt, retry_s, exc)
        if deadline is not None and time.monotonic() + retry_s > deadline:
            return None
        if stop is not None:
            if stop.wait(retry_s):
                return None
        else:
            time.sleep(retry_s)

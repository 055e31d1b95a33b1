"""Opening a Zenoh session the way every uavmm process does, and reading its config and connections.

`open_session` retries while the open fails (a client whose router is not up yet, a drone started
before the ground station) until it opens, a stop event is set or a timeout passes. `config_value`
reads one entry of a ``zenoh.Config`` as plain JSON; `remote_ids` lists the routers and peers a session
is connected to (an empty set means nothing it publishes reaches anyone).
"""

from __future__ import annotations

import json
import logging
import threading
import time

import zenoh

from transport.publishers import PublisherCache

__all__ = ["close_session", "config_value", "open_session", "remote_ids"]

log = logging.getLogger(__name__)


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


def config_value(conf: zenoh.Config, key: str) -> object:
    """The config entry ``key`` (a path such as ``connect/endpoints``) as JSON data; None when unset."""
    try:
        return json.loads(conf.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


def remote_ids(session: zenoh.Session) -> set[str]:
    """Ids of the routers and peers the session is connected to right now."""
    info = session.info
    return {str(z) for z in info.routers_zid()} | {str(z) for z in info.peers_zid()}


def close_session(session: zenoh.Session, declared: list, publishers: PublisherCache | None = None) -> None:
    """Undeclare ``declared`` (subscribers, queryables, tokens; errors ignored), drop the cached
    publishers and close ``session``."""
    for entity in declared:
        try:
            entity.undeclare()
        except zenoh.ZError:
            pass
    declared.clear()
    if publishers is not None:
        publishers.clear()
    session.close()

"""Declared Zenoh publishers, one per key, reused across puts and bounded in number.

Declaring a publisher per put costs a round of declarations on every link; keeping every key's publisher
forever grows without bound when the keys move (a UAV flying over new tiles). `PublisherCache` keeps
the most recently used ``max_publishers`` and undeclares the rest. Every publisher uses
``CongestionControl.BLOCK``: the default DROP loses messages silently under load (PITFALLS.md), and
Zenoh takes the congestion control only at declaration (``Publisher.put`` has no such argument).
"""

from __future__ import annotations

import logging
from collections import OrderedDict

import zenoh

__all__ = ["PublisherCache"]

log = logging.getLogger(__name__)


class PublisherCache:
    """Publishers of one session by key, least recently used undeclared beyond ``max_publishers``.

    Not thread-safe: use it from one thread (the process's publisher thread).
    """

    def __init__(self, session: zenoh.Session, max_publishers: int | None = None) -> None:
        if max_publishers is not None and max_publishers < 1:
            raise ValueError(f"max_publishers must be >= 1 or None, got {max_publishers!r}")
        self.session = session
        self.max_publishers = max_publishers
        self._publishers: OrderedDict[str, zenoh.Publisher] = OrderedDict()

    def __len__(self) -> int:
        return len(self._publishers)

    def __contains__(self, key: object) -> bool:
        return key in self._publishers

    def get(self, key: str) -> zenoh.Publisher:
        """The publisher of ``key``, declared (with BLOCK) on first use."""
        publisher = self._publishers.get(key)
        if publisher is not None:
            self._publishers.move_to_end(key)
            return publisher
        publisher = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._publishers[key] = publisher
        if self.max_publishers is not None:
            while len(self._publishers) > self.max_publishers:
                _, old = self._publishers.popitem(last=False)
                _undeclare(old)
        return publisher

    def put(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Put ``payload`` on ``key`` through its publisher; zenoh.ZError when the put fails."""
        if attachment is None:
            self.get(key).put(payload)
        else:
            self.get(key).put(payload, attachment=attachment)

    def drop(self, key: str) -> None:
        """Undeclare the publisher of ``key`` (a key that will not be used again); no-op if unknown."""
        publisher = self._publishers.pop(key, None)
        if publisher is not None:
            _undeclare(publisher)

    def clear(self) -> None:
        """Forget every publisher (they go with the session when it closes)."""
        self._publishers.clear()


def _undeclare(publisher: zenoh.Publisher) -> None:
    try:
        publisher.undeclare()
    except zenoh.ZError as exc:  # the session is closing; nothing to recover
        log.debug("undeclaring a publisher: %s", exc)

"""What the fusion node and the gateway do alike with what UAVs send: drop a message, follow a liveliness token.

A dropped message is counted (per kind and reason, and on its UAV when known) and logged at most once per
reason every 10 s (`transport.guard.RateLimitedLog`); a UAV's ``uav/{uav}/alive`` token appearing or going
is parsed, refused when the registry is full, and recorded. Both run on Zenoh threads and never raise.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

from transport.guard import RateLimitedLog

if TYPE_CHECKING:
    from fusion_server.metrics import FusionMetrics
    from fusion_server.uav_registry import UavRegistry
    from shared.keys import KeySpace

__all__ = ["UavIntake"]


class UavIntake:
    """Rejections and liveliness of one node's UAVs.

    logger: the node's logger (the lines keep its name). prefix: put before "dropped ..." in the log
    ("gateway: " for the gateway). ``warnings`` is the rate-limited log the rejections use; the node
    may log its own rate-limited warnings there under other reasons.
    """

    def __init__(self, keys: KeySpace, uavs: UavRegistry, metrics: FusionMetrics, logger: logging.Logger,
                 prefix: str = "") -> None:
        self.keys = keys
        self.uavs = uavs
        self.metrics = metrics
        self.logger = logger
        self.warnings = RateLimitedLog(logger)
        self._dropped = prefix + "dropped %s message on %.120s: %s: %.200s"

    def reject(self, kind: str, reason: str, key: str, detail: object, uav: str | None = None) -> None:
        """Count a dropped message of ``kind`` for ``reason`` (on ``uav`` too when known) and log it."""
        self.metrics.reject(kind, reason)
        if uav is not None:
            self.uavs.rejected(uav, reason)
        self.warnings.warning(reason, self._dropped, kind, key, reason, detail)

    def on_alive(self, sample: zenoh.Sample, then: Callable[[str, bool], object] | None = None) -> None:
        """A UAV liveliness sample: recorded in the registry, then ``then(uav, online)`` when accepted.

        A bad key ("bad_key"), another key ("unexpected_key") or a full registry ("too_many_uavs") is
        rejected; an exception (in ``then`` too) is logged and counted as "internal_error".
        """
        key = "?"
        try:
            key = str(sample.key_expr)
            try:
                parsed = self.keys.parse(key)
            except ValueError as exc:
                self.reject("alive", "bad_key", key, exc)
                return
            if parsed.kind != "uav_alive":
                self.reject("alive", "unexpected_key", key, "not an alive key")
                return
            online = sample.kind == zenoh.SampleKind.PUT
            if not self.uavs.alive(parsed.uav, online):
                self.reject("alive", "too_many_uavs", key, "UAV registry full")
                return
            self.metrics.message("alive", 0)
            if then is not None:
                then(parsed.uav, online)
        except Exception:
            self.metrics.reject("alive", "internal_error")
            self.logger.exception("internal error handling liveliness on %.120s", key)

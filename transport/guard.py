"""Guards for code that runs on Zenoh's threads: rate-limited warnings and callbacks that never raise.

A subscriber or queryable callback that raises is lost to the process (Zenoh logs it and goes on, the
message is gone without a count), and one bad peer can flood the log. `RateLimitedLog` keeps at most one
warning per reason per interval, with the number suppressed in between; `guarded` wraps a callback so an
unexpected exception is logged with its traceback and counted, and the callback keeps serving.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TypeVar

__all__ = ["RateLimitedLog", "guarded"]

_T = TypeVar("_T")


class RateLimitedLog:
    """Logs a warning per reason at most once every ``interval_s`` seconds, with the count suppressed.

    Thread-safe. ``warning(reason, message, *args)`` formats like `logging` (``message % args``).
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()

    def warning(self, reason: str, message: str, *args: object) -> bool:
        """Log ``message % args`` under ``reason`` unless one was logged less than interval_s ago.

        Returns True when it was logged, False when it was suppressed (and counted for the next one).
        """
        now = time.monotonic()
        with self._lock:
            last = self._last.get(reason)
            if last is not None and now - last < self.interval_s:
                self._suppressed[reason] = self._suppressed.get(reason, 0) + 1
                return False
            self._last[reason] = now
            suppressed = self._suppressed.pop(reason, 0)
        suffix = f" ({suppressed} more like it suppressed)" if suppressed else ""
        self.logger.warning(message + suffix, *args)
        return True

    def suppressed(self, reason: str) -> int:
        """Warnings under ``reason`` suppressed since the last one logged."""
        with self._lock:
            return self._suppressed.get(reason, 0)


def guarded(callback: Callable[[_T], object], logger: logging.Logger, what: str,
            on_error: Callable[[], object] | None = None) -> Callable[[_T], None]:
    """``callback`` wrapped for a Zenoh thread: an exception is logged (with traceback) and never raised.

    what: names the callback in the log line ("a sample", "a query", ...). on_error: called after an
    exception (e.g. to count it as ``internal_error``); an exception in on_error is logged too.
    """

    def run(item: _T) -> None:
        try:
            callback(item)
        except Exception:  # a bug must not take the subscriber down: log it, count it
            logger.exception("internal error handling %s", what)
            if on_error is not None:
                try:
                    on_error()
                except Exception:
                    logger.exception("internal error counting an internal error")

    run.__name__ = getattr(callback, "__name__", "guarded")
    run.__doc__ = callback.__doc__
    return run

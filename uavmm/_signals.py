"""Stopping a long-running command on a signal: one event that SIGINT/SIGTERM (and more if asked) set."""

from __future__ import annotations

import logging
import signal
import threading

__all__ = ["stop_on_signals"]


def stop_on_signals(log: logging.Logger, signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> threading.Event:
    """An event set (and logged on ``log``) when one of ``signums`` arrives; installs the handlers."""
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    for signum in signums:
        signal.signal(signum, on_signal)
    return stop

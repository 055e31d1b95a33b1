"""Signals: a long-running command stops on an event that SIGINT/SIGTERM (and more if asked) set; any other command
unwinds on SIGTERM as on Ctrl-C (`terminate_as_interrupt`)."""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator

__all__ = ["SERVER_COMMANDS", "Terminated", "stop_on_signals", "terminate_as_interrupt"]

#: The commands that run until stopped: SIGINT / SIGTERM stop them cleanly, exit 0 (their own handlers, and before
#: those are in place `uavmm.cli.main`).
SERVER_COMMANDS = frozenset({"fusion", "agent", "gateway", "demo"})


def stop_on_signals(log: logging.Logger, signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> threading.Event:
    """An event set (and logged on ``log``) when one of ``signums`` arrives; installs the handlers."""
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    for signum in signums:
        signal.signal(signum, on_signal)
    return stop


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill`, `timeout`, a service manager) during a command: it unwinds as Ctrl-C does, so what a command
    removes or finishes on an interrupt (hidden temporaries, a partial results file it keeps) happens on SIGTERM too;
    exit 143. The servers (`fusion`, `agent`, `gateway`, `demo`) put their own handlers in place (a clean stop)."""


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within it SIGTERM raises `Terminated` in the main thread (off the main thread, where Python cannot install a
    handler, or where SIGTERM is ignored, nothing changes); the handler before is put back after."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) == signal.SIG_IGN:
        yield  # a parent that set SIGTERM to be ignored (nohup-like, `trap '' TERM`) keeps it so, as Python does SIGINT
        return

    def on_term(_signum: int, _frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)

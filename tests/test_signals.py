"""SIGTERM during a batch command (uavmm._signals.terminate_as_interrupt, around every handler in uavmm.cli.main): it
unwinds as Ctrl-C does, unless the parent set it to be ignored or the command runs off the main thread."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from uavmm._signals import Terminated, terminate_as_interrupt


def test_sigterm_raises_terminated_inside_and_the_old_handler_comes_back():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), terminate_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5.0)  # the handler raises at once (a sleep ends on a signal)
        raise AssertionError("SIGTERM did not unwind")
    assert signal.getsignal(signal.SIGTERM) == before
    assert issubclass(Terminated, KeyboardInterrupt)  # every command's Ctrl-C clean-up runs for it


def test_a_sigterm_the_parent_ignores_stays_ignored():
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with terminate_as_interrupt():
            assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGTERM)  # ignored: nothing happens
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_off_the_main_thread_nothing_changes():
    before = signal.getsignal(signal.SIGTERM)
    seen: list[object] = []

    def run() -> None:
        with terminate_as_interrupt():
            seen.append(signal.getsignal(signal.SIGTERM))

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == [before]

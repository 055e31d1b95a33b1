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


def _blocked_on_fifo(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/wchan") as f:
            return f.read().strip() == "wait_for_partner"  # open() of a FIFO that nobody writes
    except OSError:
        return False


@pytest.mark.parametrize("command, code", [("fusion", 0), ("boost", 143)])
def test_sigterm_before_a_servers_own_handler_stops_it_as_after_it(tmp_path, command, code):
    # a FIFO that nobody writes, given as an input file, holds the command where it reads it: for `uavmm fusion`
    # before its own SIGTERM handler is in place (its REST token file), for `uavmm boost` its frames
    import subprocess
    import sys
    from pathlib import Path

    fifo = tmp_path / "input.json"
    os.mkfifo(fifo)
    argv = {"fusion": ["fusion", "--http-token-file", str(fifo), "--listen", "tcp/127.0.0.1:0",
                       "--http", "127.0.0.1:0"],
            "boost": ["boost", "--frames", str(fifo), "--candidates", str(fifo), "--camera", "dji-mavic2-pro",
                      "--out", str(tmp_path / "out.json")]}[command]
    proc = subprocess.Popen([sys.executable, "-m", "uavmm", *argv], cwd=Path(__file__).resolve().parents[1],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not _blocked_on_fifo(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is None and not _blocked_on_fifo(proc.pid):
            pytest.skip("cannot see the process wait on the FIFO (/proc/PID/wchan)")
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == code, err
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

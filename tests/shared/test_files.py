"""shared.files: a file is written whole through a new temporary of its own (never a file or link already at the
temporary's name, never another writer's), on disk before the rename, and no temporary is left behind."""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys

import pytest
from hypothesis import given
from hypothesis import strategies as st

import shared.files
from shared.files import (
    PendingFile,
    new_temporary,
    stale_temporaries,
    temporary_pids,
    write_atomic,
    write_chunks_atomic,
)


def _planted_links(folder, name, target):
    """Links at every temporary name a writer of ``name`` used or uses first (old and new)."""
    names = (f"{name}.tmp", f".{name}.tmp", f".{name}.{os.getpid()}.tmp")
    for planted in names:
        (folder / planted).symlink_to(target)
    return names


def test_a_link_planted_at_the_temporary_name_is_not_written_through(tmp_path):
    """write_atomic without a mode opened ``.NAME.PID.tmp`` with a plain open(): a link planted there took the
    file's content and the rename made the output that link."""
    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    names = _planted_links(tmp_path, "out.json", outside)
    write_chunks_atomic(tmp_path / "out.json", ["{", "}"])
    assert outside.read_text() == "precious\n"
    assert not (tmp_path / "out.json").is_symlink() and (tmp_path / "out.json").read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out.json", "outside.txt", *names])


def test_the_new_file_gets_the_default_permissions_or_the_mode_whatever_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        write_chunks_atomic(tmp_path / "plain.txt", ["x"])
        write_atomic(tmp_path / "key.pem", lambda f: f.write(b"k"), mode=0o600)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "plain.txt").stat().st_mode) == 0o640  # 0o666 less the umask, as open() gives
    assert stat.S_IMODE((tmp_path / "key.pem").stat().st_mode) == 0o600


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    out = tmp_path / "out.txt"
    out.write_text("old")

    def chunks():
        yield "new"
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_chunks_atomic(out, chunks())
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_the_file_is_on_disk_before_the_rename(tmp_path, monkeypatch):
    order: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(shared.files.os, "fsync", lambda fd: (order.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (order.append("rename"), real_replace(a, b))[1])
    write_chunks_atomic(tmp_path / "out.txt", ["x"])
    assert order == ["fsync", "rename"]


def test_two_writers_of_one_path_never_share_a_temporary(tmp_path):
    """Two writers (threads of one process, or runs) had one fixed temporary: the second truncated the first's, and
    the first's rename put the second's half-written file in place."""
    out = tmp_path / "out.txt"
    first, second = PendingFile(out), PendingFile(out)
    assert first.tmp != second.tmp and first.tmp.parent == second.tmp.parent == tmp_path
    first.write("first")
    second.write("second")
    first.commit()
    assert out.read_text() == "first"
    second.commit()
    assert out.read_text() == "second" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_committed_file_does_not_remove_a_temporary_that_took_its_name_since(tmp_path):
    out = tmp_path / "out.txt"
    pending = PendingFile(out)
    pending.write("x")
    pending.commit()
    pending.tmp.write_text("another writer's")  # the name is free after the rename: another writer may take it
    pending.discard()
    pending.commit()
    assert pending.tmp.read_text() == "another writer's" and out.read_text() == "x"


def test_a_write_the_disk_refuses_at_close_leaves_no_temporary(tmp_path):
    """discard() closed the temporary before removing it: a close whose flush failed (a full disk) raised there, and
    the temporary stayed (the export's full-disk test caught it)."""
    out = tmp_path / "out.txt"
    pending = PendingFile(out)
    pending.write("x")
    real = pending.file

    class FullDisk:
        closed = False

        def close(self):
            real.close()
            raise OSError(28, "No space left on device")

    pending.file = FullDisk()  # type: ignore[assignment]
    pending.discard()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("code", [errno.EINVAL, errno.ENOTSUP, errno.ENOSYS])
def test_a_file_system_that_cannot_sync_still_gets_the_file(tmp_path, monkeypatch, code):
    """Some FUSE and network mounts answer fsync with EINVAL / ENOTSUP: the writers did not sync before this stop and
    wrote there; losing every output (a flight's detections spool) for it would be worse (the review's finding)."""
    def cannot(fd):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "fsync", cannot)
    write_chunks_atomic(tmp_path / "out.txt", ["kept"])
    assert (tmp_path / "out.txt").read_text() == "kept"


def test_a_sync_that_fails_for_real_keeps_the_old_file(tmp_path, monkeypatch):
    (tmp_path / "out.txt").write_text("old")

    def broken(fd):
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(os, "fsync", broken)
    with pytest.raises(OSError):
        write_chunks_atomic(tmp_path / "out.txt", ["new"])
    assert (tmp_path / "out.txt").read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


_NAMES = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="/\x00"), min_size=1, max_size=40)
_HEX = st.text("0123456789abcdef", min_size=8, max_size=8)


@given(name=_NAMES, pid=st.integers(1, 2**22), token=st.none() | _HEX, suffix=st.sampled_from([".tmp", ".tmp.mp4"]))
def test_every_name_new_temporary_makes_is_read_back_with_its_pid(name, pid, token, suffix):
    entry = f".{name}.{pid}" + (f".{token}" if token else "") + suffix
    assert pid in temporary_pids(entry, {name}, suffix)
    assert temporary_pids(entry, {name + "x"}, suffix) == []  # another file's name: not ours
    assert temporary_pids(entry, {name}, ".tmp.png") == []  # another suffix


@given(entry=st.text(".0123456789abcdefmp4tx", max_size=30), names=st.sets(st.text(".0123456789abcx", max_size=8),
                                                                             max_size=3))
def test_a_pid_is_read_only_from_a_name_new_temporary_could_have_made(entry, names):
    """Whatever the text, each pid read rebuilds it exactly as `.NAME.PID.tmp` or `.NAME.PID.TOKEN.tmp` (TOKEN 8 hex
    digits) for a NAME of ``names`` (never a name that merely contains one, never a signed or zero-padded number)."""
    hexes = ["", *("." + "".join(t) for t in [entry[i:i + 8] for i in range(len(entry))] if len(t) == 8
                   and set(t) <= set("0123456789abcdef"))]
    for pid in temporary_pids(entry, names):
        assert any(entry == f".{name}.{pid}{token}.tmp" for name in names for token in hexes), (entry, pid)


def test_a_killed_writers_temporaries_are_stale_and_no_one_elses(tmp_path):
    """A writer killed with SIGKILL (a real process) leaves its temporaries; those of the asked names and suffix are
    found, and only they: another file's, a live process's, a link or a directory at such a name are not."""
    made = subprocess.run([sys.executable, "-c", (
        "import os, signal, sys; from pathlib import Path; from shared.files import new_temporary\n"
        "folder = Path(sys.argv[1])\n"
        "for name, suffix in (('out.mp4', '.tmp'), ('out.mp4', '.tmp'), ('out.mp4', '.tmp.mp4'), ('other', '.tmp')):\n"
        "    print(new_temporary(folder / name, suffix=suffix)[0].name, flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)"), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert made.returncode == -signal.SIGKILL, made.stderr
    dead = made.stdout.split()  # .out.mp4.PID.tmp, .out.mp4.PID.TOKEN.tmp, .out.mp4.PID.tmp.mp4, .other.PID.tmp
    assert len(dead) == 4 and all((tmp_path / name).is_file() for name in dead)
    live = new_temporary(tmp_path / "out.mp4")[0]  # this process's
    (tmp_path / ".out.mp4.1.tmp").mkdir()  # a directory at such a name
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (tmp_path / f".out.mp4.{dead[0].split('.')[3]}.{'0' * 8}.tmp").symlink_to(victim)  # a link at such a name
    assert sorted(p.name for p in stale_temporaries(tmp_path, {"out.mp4"})) == sorted(dead[:2])
    assert [p.name for p in stale_temporaries(tmp_path, {"out.mp4"}, suffix=".tmp.mp4")] == [dead[2]]
    assert live.exists() and stale_temporaries(tmp_path / "missing", {"out.mp4"}) == []

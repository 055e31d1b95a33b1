"""shared.files: a file is written whole through a new temporary of its own (never a file or link already at the
temporary's name, never another writer's), on disk before the rename, and no temporary is left behind."""

from __future__ import annotations

import errno
import os
import stat

import pytest

import shared.files
from shared.files import PendingFile, write_atomic, write_chunks_atomic


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

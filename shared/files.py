"""Files written whole or not at all, and a GeoJSON FeatureCollection given feature by feature.

Used by the agent's track files (`agent.track_rows`, `uavmm detect`), the results and CSV files of boost, track,
tune and anomaly, the fusion server's export (`fusion_server.history_export`) and the fleet's credentials
(`fusion_server.provision`, 0600): a reader never sees half a file, and a failed write (a full disk) leaves what was
there and no temporary file. A writer killed outright (SIGKILL, a power cut) cannot remove its own: `stale_temporaries`
finds them for the next run to remove.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

__all__ = ["PendingFile", "collection_chunks", "listed_names", "new_temporary", "process_gone", "same_file",
           "stale_temporaries", "sync_to_disk", "temporary_pids", "write_atomic", "write_chunks_atomic"]

#: bytes of the random token of a temporary's name when its first name is taken (two hex digits a byte)
_TOKEN_BYTES = 4


def listed_names(names: Sequence[str], shown: int = 4) -> str:
    """The first ``shown`` names, comma-separated, and how many more there are (for one-line messages)."""
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def new_temporary(path: Path, mode: int = 0o666, *, suffix: str = ".tmp") -> tuple[Path, int]:
    """Create a new hidden file beside ``path`` for writing: ``.NAME.PID`` + suffix, or ``.NAME.PID.TOKEN`` +
    suffix (TOKEN: 8 random lowercase hex digits) while that name is taken (another writer's temporary in this
    process, a leftover, a planted link). O_EXCL: a file or a link already at the name is never written through,
    and two writers never share one; the permissions are ``mode`` less the umask, as ``open()`` gives. suffix:
    ``.tmp.mp4`` for a writer that picks its format from the extension (OpenCV's VideoWriter). Returns (name,
    descriptor)."""
    name = f".{path.name}.{os.getpid()}"
    for attempt in range(100):
        tmp = path.with_name(f"{name}{suffix}" if attempt == 0 else f"{name}.{secrets.token_hex(_TOKEN_BYTES)}{suffix}")
        try:
            return tmp, os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), mode)
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path}")


def temporary_pids(entry: str, names: Collection[str], suffix: str = ".tmp") -> list[int]:
    """The process ids a `new_temporary` name ``entry`` may carry (``.NAME.PID`` + suffix, or ``.NAME.PID.TOKEN``
    + suffix with TOKEN 8 lowercase hex digits) for a NAME in ``names``: [] for any other name. Both readings are given
    when a name allows two (``.a.1.12345678.tmp`` is ``a``'s of process 1 and ``a.1``'s of process 12345678)."""
    if not (entry.startswith(".") and entry.endswith(suffix)) or len(entry) <= len(suffix) + 1:
        return []
    parts = entry[1:len(entry) - len(suffix)].split(".")
    pids = []
    for tail in (1, 2):  # .NAME.PID, then .NAME.PID.TOKEN
        if len(parts) <= tail:
            break
        pid, token = parts[-tail], parts[-1]
        if tail == 2 and not (len(token) == 2 * _TOKEN_BYTES and all(c in "0123456789abcdef" for c in token)):
            continue
        # getpid's decimal form only: no sign, no leading zero, no other script's digits
        decimal = len(pid) <= 10 and pid.isascii() and pid.isdigit() and pid == str(int(pid))
        if decimal and ".".join(parts[:-tail]) in names:
            pids.append(int(pid))
    return [pid for pid in pids if 0 < pid < 2**31]


def process_gone(pid: int) -> bool:
    """Whether no process ``pid`` runs on this machine (signal 0 asks without sending one); False when unsure: this
    process, another user's (EPERM), or Windows, where os.kill would end the process."""
    if pid == os.getpid() or os.name == "nt":
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def stale_temporaries(folder: Path, names: Collection[str], suffix: str = ".tmp") -> list[Path]:
    """The temporaries `new_temporary` made in ``folder`` for the files ``names`` whose process is gone (killed by
    SIGKILL or a power cut before it could remove them; nobody else ever will). Only regular files (not links) named
    exactly as `temporary_pids` reads them; a live process's stay (a PID given to a new process since keeps its
    temporary: left, never wrongly removed). [] when ``folder`` cannot be listed. The caller removes them."""
    try:
        with os.scandir(folder) as entries:
            found = [(entry.name, temporary_pids(entry.name, names, suffix)) for entry in entries
                     if entry.name.startswith(".") and entry.is_file(follow_symlinks=False)]
    except OSError:
        return []
    return [Path(folder) / name for name, pids in found if pids and all(process_gone(pid) for pid in pids)]


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one existing file, however spelled (``./x``, ``../dir/x``) or linked (a symbolic or a
    hard link); False when either does not exist."""
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


#: fsync errors that mean "this file system cannot sync" (some FUSE and network mounts), not "the data is lost"
_CANNOT_SYNC = frozenset(getattr(errno, name) for name in ("EINVAL", "ENOTSUP", "EOPNOTSUPP", "ENOSYS")
                         if hasattr(errno, name))


def sync_to_disk(fd: int) -> None:
    """fsync, tolerating a file system that cannot sync (the rename goes ahead: the file is as safe as that file
    system makes any); other errors (EIO, ENOSPC) raise."""
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in _CANNOT_SYNC:
            raise


class PendingFile:
    """A file written beside its final ``path`` under a new hidden name (`new_temporary`) and put in place whole by
    `commit` (flushed, on disk, then renamed over ``path``), or dropped by `discard`; the file stays open between, for
    writers that stream (`agent.boost.StreamedResults`).

    mode: permission bits of the new file (0o600 for a private key), whatever the umask, set before a byte is
    written. None: ``open``'s default (0o666 less the umask).
    """

    def __init__(self, path: str | Path, *, mode: int | None = None) -> None:
        self.path = Path(path)
        self.tmp, fd = new_temporary(self.path, 0o666 if mode is None else mode)
        try:
            if mode is not None:  # the umask may have taken bits away
                os.chmod(fd if os.chmod in os.supports_fd else self.tmp, mode)
            self.file: IO[bytes] = os.fdopen(fd, "wb")
        except BaseException:
            os.close(fd)
            self.tmp.unlink(missing_ok=True)
            raise
        self.done = False

    def write(self, data: str | bytes) -> None:
        """Append text (written as UTF-8) or bytes."""
        self.file.write(data if isinstance(data, bytes) else data.encode("utf-8"))

    def commit(self) -> None:
        """Put the file on disk and rename it over ``path`` (idempotent; the temporary is gone either way)."""
        if self.done:
            return
        try:
            self.file.flush()
            sync_to_disk(self.file.fileno())  # on disk before the rename makes it the file
            self.file.close()
            self.tmp.replace(self.path)
            self.done = True  # the name is free again: another writer's temporary may take it from here
        finally:
            self.discard()

    def discard(self) -> None:
        """Close and remove the temporary without touching ``path`` (idempotent; after `commit`, nothing to do)."""
        if not self.file.closed:
            try:
                self.file.close()
            except OSError:  # what it cannot flush (a full disk) is dropped anyway; the descriptor is closed
                pass
        if not self.done:
            self.tmp.unlink(missing_ok=True)
            self.done = True


def write_atomic(path: Path, write: Callable[[IO[bytes]], None], *, mode: int | None = None) -> None:
    """Call ``write`` on a new hidden temporary file beside ``path`` (`PendingFile`: ``.NAME.PID.tmp``, never one
    already there nor through a link planted at that name), put it on disk, then rename it over ``path``; the
    temporary is removed whatever happens.

    mode: permission bits of the new file (0o600 for a private key), whatever the umask. None: ``open``'s default
    (0o666 less the umask).
    """
    pending = PendingFile(path, mode=mode)
    try:
        write(pending.file)
        pending.commit()
    finally:
        pending.discard()


def write_chunks_atomic(path: Path, chunks: Iterable[str | bytes]) -> None:
    """`write_atomic` of text given piece by piece (str, written as UTF-8, or bytes)."""

    def write(file: IO[bytes]) -> None:
        for chunk in chunks:
            file.write(chunk if isinstance(chunk, bytes) else chunk.encode("utf-8"))

    write_atomic(path, write)


def collection_chunks(features: Iterable[dict[str, Any]]) -> Iterator[str]:
    """``json.dumps`` of a FeatureCollection of the features, piece by piece (the same text)."""
    yield '{"type": "FeatureCollection", "features": ['
    for i, feature in enumerate(features):
        yield (", " if i else "") + json.dumps(feature)
    yield "]}"

"""Files written whole or not at all, and a GeoJSON FeatureCollection given feature by feature.

Used by the agent's track files (`agent.track_rows`, `uavmm detect`), the fusion server's export
(`fusion_server.history_export`) and the fleet's credentials (`fusion_server.provision`, 0600): a reader never
sees half a file, and a failed write (a full disk) leaves what was there and no temporary file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["collection_chunks", "write_atomic", "write_chunks_atomic"]


def write_atomic(path: Path, write: Callable[[IO[bytes]], None], *, mode: int | None = None) -> None:
    """Call ``write`` on a hidden temporary file beside ``path`` (``.NAME.PID.tmp``), put it on disk, then rename it
    over ``path``; the temporary is removed whatever happens.

    mode: permission bits of the new file (0o600 for a private key), whatever the umask, set before ``write``
    puts a byte in; the temporary is then always a new file (one left at its name, or a link planted there, is
    replaced, never written through). None: ``open``'s default (0o666 less the umask).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        if mode is None:
            file = open(tmp, "wb")
        else:
            tmp.unlink(missing_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)  # O_EXCL: never through a link
            os.chmod(fd if os.chmod in os.supports_fd else tmp, mode)  # the umask may have taken bits away
            file = os.fdopen(fd, "wb")
        with file:
            write(file)
            file.flush()
            os.fsync(file.fileno())  # on disk before the rename makes it the file
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


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

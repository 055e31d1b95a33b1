"""Files written whole or not at all, and a GeoJSON FeatureCollection given feature by feature.

Used by the agent's track files (`agent.track_rows`, `uavmm detect`) and the fusion server's export
(`fusion_server.history_export`): a reader never sees half a file, and a failed write (a full disk) leaves
what was there and no temporary file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["collection_chunks", "write_atomic", "write_chunks_atomic"]


def write_atomic(path: Path, write: Callable[[IO[bytes]], None]) -> None:
    """Call ``write`` on a hidden temporary file beside ``path`` (``.NAME.PID.tmp``), put it on disk, then rename it
    over ``path``; the temporary is removed whatever happens."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as file:
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

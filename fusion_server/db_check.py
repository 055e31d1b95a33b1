"""Start-up checks of the fusion server's SQLite file, and moving a bad one aside.

A database that cannot be trusted is refused with one clear sentence (the CLI exits 2) instead of
being started silently empty (a 0-byte file) or failing every later write (a damaged page):
:func:`check_database` says what is wrong, :func:`move_aside` keeps the bad file (and its WAL) next to
it under a new name so ``uavmm fusion --db-recover`` can start a new database without losing it.
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

__all__ = ["DatabaseProblem", "check_database", "move_aside"]

_SQLITE_MAGIC = b"SQLite format 3\x00"
#: Tables of the uavmm fusion schema that every database written by it has.
_REQUIRED_TABLES = ("meta", "tracks", "track_history", "joint_tiles")


class DatabaseProblem(ValueError):
    """The database file cannot be used; the message names the file, the problem and the way out."""


def check_database(path: Path, schema_version: int = 1) -> str | None:
    """What is wrong with the fusion database at ``path``, or None when it can be used.

    A missing file is fine (it will be created). Refused: an empty (0-byte) file, a file that is not
    SQLite, one whose pages fail ``PRAGMA quick_check`` (damaged pages or indexes), an SQLite file
    of another application, another schema version.
    """
    path = Path(path)
    if not path.exists():
        return None
    if path.is_dir():
        return "is a directory"
    size = path.stat().st_size
    if size == 0:
        return ("is empty (0 bytes): not a database written by uavmm fusion (a crash while it was created, "
                "a full disk or a truncated copy)")
    with open(path, "rb") as f:
        head = f.read(len(_SQLITE_MAGIC))
    if head != _SQLITE_MAGIC:
        return f"is not an SQLite database ({size} bytes, starts with {head[:8]!r})"
    try:
        conn = sqlite3.connect(str(path), timeout=10.0)
        try:
            rows = [row[0] for row in conn.execute("PRAGMA quick_check(5)")]
            if rows != ["ok"]:
                return "failed its integrity check: " + "; ".join(str(r) for r in rows)[:400]
            tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not tables:
                return None  # an empty SQLite file: the schema will be created
            missing = [t for t in _REQUIRED_TABLES if t not in tables]
            if missing:
                return (f"is not a uavmm fusion database (no table {', '.join(missing)}; it has "
                        f"{', '.join(sorted(tables))[:200]})")
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if row is None or str(row[0]) != str(schema_version):
                return f"has schema version {row[0] if row else 'none'}, this server reads {schema_version}"
        finally:
            conn.close()
    except sqlite3.DatabaseError as exc:
        return f"cannot be read: {exc}"
    return None


def move_aside(path: Path) -> Path:
    """Rename the database at ``path`` (and its ``-wal``/``-shm`` files) to ``NAME.bad-YYYYmmddTHHMMSS``
    next to it; returns the new path of the database file. Nothing is deleted."""
    path = Path(path)
    stamp = time.strftime("%Y%m%dT%H%M%S")
    target = path.with_name(f"{path.name}.bad-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.bad-{stamp}-{n}")
    for suffix in ("-wal", "-shm"):
        side = path.with_name(path.name + suffix)
        if side.exists():
            side.rename(target.with_name(target.name + suffix))
    path.rename(target)
    return target

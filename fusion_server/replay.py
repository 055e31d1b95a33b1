"""The global tracks over a time window, for `/v1/history` and the live page's time slider.

Each track's history rows inside ``[since, until]`` and its position at ``until`` (its last row then):
the map as it stood at an earlier time, from the SQLite history when the server keeps one (longer than
what the tracker holds in memory), else from the tracker's own bounded history.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fusion_server.history_export import read_history

__all__ = ["MAX_HISTORY_ROWS", "history_window", "stored_tracks", "window_rows"]

#: Largest number of history rows one answer carries (oldest rows of the window dropped first).
MAX_HISTORY_ROWS = 200_000


def stored_tracks(db_path: Path | None, live: list[dict[str, Any]] | Callable[[], list[dict[str, Any]]], *,
                  cls: str | None, since: float | None, until: float | None = None,
                  ends_only: bool = False) -> list[dict[str, Any]]:
    """Track features with history: from the database (read-only) when there is one, else ``live``.

    live: the tracker's features (`TrackRecord.to_geojson`), or a function giving them, called only when they
    answer (building them for a poll the database answers cost a shard 0.5 s of CPU and 40 MB at 1000 tracks
    held): used without a database or when the file cannot be read yet (a new server before its first write).
    ValueError is never raised for a missing database file: the live tracks answer instead. until, ends_only:
    `read_history`'s (the database's rows only: the live features carry theirs, bounded by the tracker, for
    `history_window` to clip).
    """
    if db_path is not None and db_path.is_file():
        try:
            return read_history(db_path, cls=cls, since=since, until=until, ends_only=ends_only).tracks
        except ValueError:
            pass
    features = live() if callable(live) else live
    return [f for f in features if cls is None or f["properties"]["cls"] == cls]


def window_rows(tracks: list[dict[str, Any]], since: float | None, until: float | None,
                ends_only: bool = False) -> list[dict[str, Any]]:
    """The tracks with ``history`` cut to the rows in [since, until] (None: open); ends_only: only the rows
    at each track's first and last time there, in their order (two rows, more only where rows share that
    time), as `read_history` (``ends_only=True``) reads them from a database.

    Every track stays, with ``history`` [] when no row is in the window: a shard's copy of a handed-over track
    still gives the merged track its properties (`fusion_server.shard_tracks.merge_tracks`), and
    `history_window` leaves it out. Cutting twice, or rows read already cut, changes nothing.
    """
    low = -math.inf if since is None else since
    high = math.inf if until is None else until
    cut = []
    for feature in tracks:
        props = feature["properties"]
        rows = [row for row in props.get("history", []) if low <= row[0] <= high]
        if ends_only and rows:
            first, last = min(row[0] for row in rows), max(row[0] for row in rows)
            rows = [row for row in rows if row[0] == first or row[0] == last]
        cut.append({**feature, "properties": {**props, "history": rows}})
    return cut


def history_window(tracks: list[dict[str, Any]], since: float | None, until: float | None) -> dict[str, Any]:
    """A GeoJSON FeatureCollection of the tracks with history rows in [since, until].

    Each feature is a Point at its last row at or before ``until`` with ``history`` clipped to the window;
    tracks without a row in the window are left out. The collection carries ``time_range``: [first,
    last] row time over all tracks (null when empty), so a slider knows its ends.
    """
    low = -math.inf if since is None else since
    high = math.inf if until is None else until
    features = []
    first, last = math.inf, -math.inf
    for feature in tracks:
        props = feature["properties"]
        rows = [row for row in props.get("history", []) if low <= row[0] <= high]
        if not rows:
            continue
        first, last = min(first, rows[0][0]), max(last, rows[-1][0])
        _, lat, lon = rows[-1]
        features.append({**feature, "geometry": {"type": "Point", "coordinates": [lon, lat]},
                         "properties": {**props, "history": rows}})
    total = sum(len(f["properties"]["history"]) for f in features)
    if total > MAX_HISTORY_ROWS:  # keep the newest rows of each track, in proportion
        keep = MAX_HISTORY_ROWS / total
        for f in features:
            rows = f["properties"]["history"]
            f["properties"]["history"] = rows[len(rows) - max(1, int(len(rows) * keep)):]
    return {"type": "FeatureCollection", "features": features,
            "time_range": [first, last] if features else None}

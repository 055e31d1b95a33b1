"""`uavmm export`: the fusion server's stored history (its SQLite file) as GeoPackage, KML or GeoJSON.

Reads the database read-only (a running server may keep writing) in short read transactions, into a private copy
every layer then reads (`_Reader`), a track at a time: each format streams from the copy's cursors into a temporary
file beside the output, renamed over it once complete, so memory does not grow with the history and a failed write
leaves the previous file. Layers: ``tracks`` (each global track at its last position), ``track_lines`` (its history
as a line) and, in a GeoPackage, ``track_points`` (one point per history row, with a DATETIME for QGIS's temporal
controller).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import sqlite3
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any, TypeVar
from zipfile import ZIP64_LIMIT

from fusion_server.geo_formats import track_line_feature
from fusion_server.gpkg import Layer, write_geopackage
from shared.files import collection_chunks, write_atomic
from shared.kml import kml_chunks, write_kmz

__all__ = ["EXPORT_FORMATS", "HistoryExport", "export_history", "read_history", "stored_classes"]

EXPORT_FORMATS = {".gpkg": "GeoPackage", ".kml": "KML", ".kmz": "KMZ", ".geojson": "GeoJSON", ".json": "GeoJSON"}
_TRACK_COLUMNS = "gid, cls, lat, lon, score, vel_e, vel_n, created, last_update, ended, members"
_HISTORY_ROWS = "SELECT gid, t, lat, lon FROM track_history WHERE t >= ? AND t <= ? ORDER BY gid, t, rowid"
#: history rows copied by one statement, each its own read transaction of the server's database (~10 ms)
_PAGE_ROWS = 5_000
_SNAPSHOT_TABLES = (
    "CREATE TEMP TABLE export_tracks(gid INTEGER PRIMARY KEY, cls, lat, lon, score, vel_e, vel_n, created, "
    "last_update, ended, members)",
    "CREATE TEMP TABLE export_history(gid INTEGER NOT NULL, t REAL NOT NULL, lat REAL NOT NULL, lon REAL NOT NULL, "
    "source_rowid INTEGER NOT NULL)")
# the selected tracks' rows after (gid, t, rowid) = key, up to the start's last rowid, in the order of _HISTORY_ROWS:
# tracks the outer loop (by gid), each one's rows by the (gid, t) index (which ends in the rowid): no sort
_COPY_PAGE = (
    "INSERT INTO temp.export_history SELECT h.gid, h.t, h.lat, h.lon, h.rowid FROM temp.export_tracks tr CROSS JOIN "
    "main.track_history h ON h.gid = tr.gid WHERE tr.gid >= ? AND (h.gid, h.t, h.rowid) > (?, ?, ?) AND h.rowid <= ? "
    "AND h.t >= ? AND h.t <= ? ORDER BY tr.gid, h.t, h.rowid LIMIT ?")
_T = TypeVar("_T")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HistoryExport:
    """The stored tracks as GeoJSON Features (Points at the last position, properties with history)."""

    tracks: list[dict[str, Any]]


def _connect(path: Path) -> sqlite3.Connection:
    if path.is_dir():
        raise ValueError(f"database {path} is a folder: give the fusion server's --db file (e.g. {path}/fusion.sqlite)")
    if not path.is_file():
        raise ValueError(f"database {path} does not exist")
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=10.0)
    except sqlite3.Error as exc:
        raise ValueError(f"cannot open database {path}: {exc}") from None
    try:
        connection.execute("SELECT 1 FROM sqlite_master LIMIT 1")  # a WAL database on read-only media fails here
    except sqlite3.OperationalError as exc:
        if "unable to open" in str(exc):
            connection.close()
            return _connect_immutable(path, exc)
    except sqlite3.Error:
        pass  # not a database at all: the first query says so (_not_fusion)
    return connection


def _connect_immutable(path: Path, exc: sqlite3.Error) -> sqlite3.Connection:
    """A WAL database whose -shm cannot be made (read-only media): nobody writes there, so it is read as it lies,
    unless a -wal beside it holds rows that reading so would miss."""
    wal = path.with_name(path.name + "-wal")
    if wal.is_file() and wal.stat().st_size > 0:
        raise ValueError(f"cannot open database {path} ({exc}): a WAL database on read-only media with its "
                         f"{wal.name}: copy both to a writable folder and export from there") from None
    try:
        return sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True, timeout=10.0)
    except sqlite3.Error as exc2:
        raise ValueError(f"cannot open database {path}: {exc2}") from None


def _not_fusion(path: Path, exc: sqlite3.Error) -> ValueError:
    return ValueError(f"{path} is not a uavmm fusion database ({exc})")


def _selection(cls: str | None, since: float | None) -> tuple[list[str], list[Any]]:
    """The tracks' WHERE terms and their arguments: updated at or after ``since``, of class ``cls``."""
    where = ["last_update >= ?"]
    args: list[Any] = [since if since is not None else float("-inf")]
    if cls is not None:
        where.append("cls = ?")
        args.append(cls)
    return where, args


def _feature(row: tuple[Any, ...], history: list[list[float]] | None) -> dict[str, Any]:
    """A ``tracks`` row as a Point Feature (`/v1/tracks`' form); ``history`` None: without that property."""
    gid, name, lat, lon, score, vel_e, vel_n, created, last_update, ended, members = row
    properties = {"gid": gid, "cls": name, "score": score, "vel_en": [vel_e, vel_n],
                  "status": "ended" if ended is not None else "tracked", "created": created,
                  "last_update": last_update, "ended": ended, "members": json.loads(members)}
    if history is not None:
        properties["history"] = history
    return {"type": "Feature", "id": gid, "geometry": {"type": "Point", "coordinates": [lon, lat]},
            "properties": properties}


def _features(tracks: Iterable[tuple[Any, ...]], rows: Iterator[tuple[Any, ...]]) -> Iterator[dict[str, Any]]:
    """Each track's Feature with its history rows, in gid order, one track at a time: the tracks (ordered by gid) and
    the history rows (gid, t, lat, lon, ordered by gid, then as `_HISTORY_ROWS`) are read side by side."""
    pending = next(rows, None)
    for track in tracks:
        gid = track[0]
        while pending is not None and pending[0] < gid:  # rows of tracks not selected
            pending = next(rows, None)
        history = []
        while pending is not None and pending[0] == gid:
            history.append([pending[1], pending[2], pending[3]])
            pending = next(rows, None)
        yield _feature(track, history)


def read_history(db_path: str | Path, *, cls: str | None = None, since: float | None = None,
                 until: float | None = None, ends_only: bool = False) -> HistoryExport:
    """The tracks (and their history rows) of a fusion database, opened read-only.

    cls: only that class. since: only tracks updated at or after this time (epoch seconds), and history
    rows from then on; until: history rows up to this time. ends_only: each track's rows at its first and last
    time in that window only (two rows, more only where rows share that time), found by the (gid, t) index (what
    `/v1/history?rows=false`, the map page's poll, needs: reading every row took 1.7 s and 194 MB a poll after a
    day). ValueError for a file that is missing or not a fusion database.
    """
    path = Path(db_path)
    conn = _connect(path)
    try:
        where, args = _selection(cls, since)
        window = (since if since is not None else float("-inf"), until if until is not None else float("inf"))
        if not ends_only:
            tracks = conn.execute(f"SELECT {_TRACK_COLUMNS} FROM tracks WHERE {' AND '.join(where)} ORDER BY gid", args)
            return HistoryExport(list(_features(tracks, conn.execute(_HISTORY_ROWS, window))))
        rows = conn.execute(f"SELECT {_TRACK_COLUMNS} FROM tracks WHERE {' AND '.join(where)} ORDER BY gid",
                            args).fetchall()
        # every row at each track's first and last time in the window (one each but for a tie, which keeps
        # all its rows: merging a handed-over track's copies across shards then finds the same last row as
        # the full read), by the index: one seek a track and end, not a scan of every row. CROSS JOIN keeps
        # tracks the outer loop: left to itself SQLite scanned track_history (0.19 s, not 4 ms, at 324k rows)
        ends: dict[int, dict[int, list[float]]] = {}  # gid -> rowid -> [t, lat, lon]
        for order in ("ASC", "DESC"):
            for rowid, gid, t, lat, lon in conn.execute(
                    "SELECT h.rowid, h.gid, h.t, h.lat, h.lon FROM tracks tr CROSS JOIN track_history h ON h.gid = "
                    "tr.gid AND h.t = (SELECT t FROM track_history WHERE gid = tr.gid AND t >= ? AND t <= ? "
                    f"ORDER BY t {order} LIMIT 1) WHERE {' AND '.join('tr.' + w for w in where)}",
                    (*window, *args)):
                ends.setdefault(gid, {})[rowid] = [t, lat, lon]  # a one-time window: its rows once
    except sqlite3.DatabaseError as exc:
        raise _not_fusion(path, exc) from None
    finally:
        conn.close()
    history = {  # rows of one time in the order written, as the full read
        gid: [row for _, row in sorted(found.items(), key=lambda item: (item[1][0], item[0]))]
        for gid, found in ends.items()}
    return HistoryExport([_feature(row, history.get(row[0], [])) for row in rows])


def stored_classes(db_path: str | Path) -> tuple[dict[str, int], float | None]:
    """The classes of a fusion database's tracks with their numbers of tracks, and the latest ``last_update``
    (epoch seconds; None without tracks): what to tell a user whose filter matched nothing. ValueError as
    `read_history`."""
    path = Path(db_path)
    conn = _connect(path)
    try:
        classes = dict(conn.execute("SELECT cls, count(*) FROM tracks GROUP BY cls ORDER BY cls"))
        (latest,) = conn.execute("SELECT max(last_update) FROM tracks").fetchone()
    except sqlite3.DatabaseError as exc:
        raise _not_fusion(path, exc) from None
    finally:
        conn.close()
    return classes, latest


class _Reader:
    """One export's reads of the database, in short read transactions: a reader open for the whole export (15-20 s
    for a day as a GeoPackage) kept the server from checkpointing its WAL past it, which grew by all the server wrote
    meanwhile. In one transaction the selected tracks' rows are copied with the last history rowid; then their
    history rows up to that rowid, `_PAGE_ROWS` a statement, each its own transaction. The copy is in the
    connection's TEMP database (a file in SQLite's temporary folder, ~40 bytes a row, for a moment in its cache),
    which every layer then reads, so all layers hold the same rows, read in order without the index.

    The server updates only track rows (copied at the start) and never updates history rows; it deletes the oldest
    rows of a live track beyond its history length and whole ended tracks past its retention (`FusionStore`). Rows
    it deletes before their page is copied are not exported (a live track's line then starts a little later), and
    tracks it deleted by the end of the copy are left out whole. A database error while reading is the ValueError
    of `read_history`; no room for the copy in the temporary folder is an OSError."""

    def __init__(self, path: Path, cls: str | None, since: float | None) -> None:
        self.path = path
        self.counts: dict[str, int] = {}
        self.conn = _connect(path)
        self.conn.isolation_level = None  # autocommit: each statement its own transaction but the first step's
        try:
            self._copy(*_selection(cls, since), (since if since is not None else float("-inf"), float("inf")))
        except sqlite3.DatabaseError as exc:
            self.conn.close()
            raise self._error(exc) from None

    def _copy(self, where: list[str], args: list[Any], window: tuple[float, float]) -> None:
        conn = self.conn
        conn.execute("BEGIN")  # the tracks as they stand and the last history row then: one snapshot
        for table in _SNAPSHOT_TABLES:
            conn.execute(table)
        conn.execute(f"INSERT INTO temp.export_tracks SELECT {_TRACK_COLUMNS} FROM main.tracks WHERE "
                     f"{' AND '.join(where)} ORDER BY gid", args)
        (last,) = conn.execute("SELECT COALESCE(max(rowid), 0) FROM main.track_history").fetchone()
        conn.execute("COMMIT")
        key: tuple[Any, ...] = (-(2**63), -math.inf, -(2**63))
        while conn.execute(_COPY_PAGE, (key[0], *key, last, *window, _PAGE_ROWS)).rowcount == _PAGE_ROWS:
            key = conn.execute("SELECT gid, t, source_rowid FROM temp.export_history ORDER BY rowid DESC LIMIT 1"
                               ).fetchone()
        # tracks the server's retention deleted meanwhile (some rows copied, maybe): left out whole
        conn.execute("CREATE TEMP TABLE export_gone AS SELECT gid FROM temp.export_tracks WHERE gid NOT IN "
                     "(SELECT gid FROM main.tracks)")
        if conn.execute("SELECT EXISTS (SELECT 1 FROM temp.export_gone)").fetchone()[0]:
            for table in ("export_tracks", "export_history"):
                conn.execute(f"DELETE FROM temp.{table} WHERE gid IN (SELECT gid FROM temp.export_gone)")

    def _error(self, exc: sqlite3.DatabaseError) -> Exception:
        name = getattr(exc, "sqlite_errorname", "")
        if name == "SQLITE_FULL" or name.startswith("SQLITE_IOERR"):  # the copy's file (or a failing disk)
            return OSError(f"cannot export {self.path}: {exc} (the export copies the history into SQLite's "
                           "temporary folder: SQLITE_TMPDIR or TMPDIR if set, else /var/tmp)")
        return _not_fusion(self.path, exc)

    def close(self) -> None:
        self.conn.close()

    def _guarded(self, items: Iterator[_T], layer: str | None = None) -> Iterator[_T]:
        try:
            for item in items:
                if layer is not None:
                    self.counts[layer] = self.counts.get(layer, 0) + 1
                yield item
        except sqlite3.DatabaseError as exc:
            raise self._error(exc) from None
        if layer is not None:
            self.counts.setdefault(layer, 0)

    def _track_rows(self) -> Iterator[tuple[Any, ...]]:
        yield from self.conn.execute(f"SELECT {_TRACK_COLUMNS} FROM temp.export_tracks ORDER BY gid")

    def _features(self) -> Iterator[dict[str, Any]]:
        rows = self.conn.execute("SELECT gid, t, lat, lon FROM temp.export_history ORDER BY rowid")
        return self._guarded(_features(self._track_rows(), rows))

    def positions(self) -> Iterator[dict[str, Any]]:
        """The ``tracks`` layer: each track's Point Feature (id ``track-GID``), without history."""
        for row in self._guarded(self._track_rows(), "tracks"):
            feature = _feature(row, None)
            feature["id"] = f"track-{row[0]}"  # unique beside its line, and a valid XML ID (KML's Placemark@id)
            yield feature

    def lines(self) -> Iterator[dict[str, Any]]:
        """The ``track_lines`` layer: each track with history as a LineString Feature (id ``track-GID-path``)."""
        for feature in self._features():
            line = track_line_feature(feature)
            if line is not None:
                self.counts["track_lines"] = self.counts.get("track_lines", 0) + 1
                line["id"] = f"track-{feature['id']}-path"
                yield line
        self.counts.setdefault("track_lines", 0)

    def layers(self) -> list[Layer]:
        """The three GeoPackage layers, each a stream of (coordinates, attributes)."""
        when = _datetime

        def tracks() -> Iterator[tuple[Any, dict[str, Any]]]:
            for gid, name, lat, lon, score, _ve, _vn, created, last_update, ended, members in self._guarded(
                    self._track_rows()):
                yield (lon, lat), {"gid": gid, "cls": name, "score": score,
                                   "status": "ended" if ended is not None else "tracked", "created": when(created),
                                   "last_update": when(last_update), "ended": when(ended),
                                   "members": json.dumps(json.loads(members))}

        def lines() -> Iterator[tuple[Any, dict[str, Any]]]:
            for feature in self.lines():
                p = feature["properties"]
                yield feature["geometry"]["coordinates"], {
                    "gid": p["gid"], "cls": p["cls"], "start": when(min(p["times"])), "end": when(max(p["times"])),
                    "points": len(p["times"])}

        def points() -> Iterator[tuple[Any, dict[str, Any]]]:
            for feature in self._features():
                gid, name = feature["id"], feature["properties"]["cls"]
                for t, lat, lon in feature["properties"]["history"]:
                    yield (lon, lat), {"gid": gid, "cls": name, "t": t, "time": when(t)}

        return [
            Layer("tracks", "POINT", {"gid": int, "cls": str, "score": float, "status": str, "created": datetime,
                                      "last_update": datetime, "ended": datetime, "members": str}, tracks(),
                  "global tracks at their last position"),
            Layer("track_lines", "LINESTRING", {"gid": int, "cls": str, "start": datetime, "end": datetime,
                                                "points": int}, lines(), "global tracks' history as lines"),
            Layer("track_points", "POINT", {"gid": int, "cls": str, "t": float, "time": datetime}, points(),
                  "global tracks' history, one point per row (time for a temporal controller)"),
        ]


def _datetime(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, timezone.utc)


def _write_file(out: Path, write: Callable[[IO[bytes]], None]) -> None:
    """`shared.files.write_atomic`: a failure (a full disk) leaves the previous file as it was and no temporary;
    OSError naming ``out`` when it cannot be written."""
    try:
        write_atomic(out, write)
    except OSError as exc:
        raise OSError(f"cannot write {out}: {exc.strerror or exc}") from None


def export_history(db_path: str | Path, out_path: str | Path, *, cls: str | None = None,
                   since: float | None = None, kmz_zip64_over: int = ZIP64_LIMIT) -> dict[str, int]:
    """Write the database's history to ``out_path`` (format by extension: .gpkg, .kml, .kmz, .geojson/.json).

    A GeoPackage has the layers tracks, track_lines and track_points; KML a folder of positions and one of lines;
    GeoJSON the lines, then the positions. Ids are ``track-GID`` (position) and ``track-GID-path`` (line). A KMZ
    of more than ``kmz_zip64_over`` bytes of KML (2 GiB) is written as ZIP64, with a warning logged (`write_kmz`).
    Returns the feature count per layer written. ValueError for an unknown extension, a non-finite ``since`` or a
    bad database; FileNotFoundError when the output folder does not exist; OSError naming the output when it
    cannot be written (nothing is left then, and an existing file stays as it was).
    """
    out = Path(out_path)
    suffix = out.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise ValueError(f"--out must end in {', '.join(EXPORT_FORMATS)}, got {out.name!r}")
    if since is not None and not math.isfinite(since):
        raise ValueError(f"since must be a finite time (epoch seconds), got {since}")
    if not out.parent.is_dir():
        raise FileNotFoundError(f"output directory {out.parent} does not exist (for {out})")
    if out.is_dir():
        raise ValueError(f"--out {out} is a directory")
    reader = _Reader(Path(db_path), cls, since)
    try:
        if suffix == ".gpkg":
            return write_geopackage(out, reader.layers())

        def write(file: IO[bytes]) -> None:
            if EXPORT_FORMATS[suffix] == "GeoJSON":  # one file (.geojson, .json): the lines, then the last positions
                for text in collection_chunks(itertools.chain(reader.lines(), reader.positions())):
                    file.write(text.encode())
                return

            def document() -> Iterator[bytes]:  # a KMZ past 2 GiB is written twice (ZIP64): counted once
                reader.counts.clear()
                return kml_chunks("uavmm tracks", {"tracks": reader.positions(), "track lines": reader.lines()})

            if suffix != ".kmz":
                file.writelines(document())
            elif write_kmz(file, document, zip64_over=kmz_zip64_over):
                log.warning("%s: more KML than a KMZ holds without ZIP64 (2 GiB): written as ZIP64, which unzip, "
                            "Python and Java read but libkml (GDAL's LIBKML driver) does not open", out)

        _write_file(out, write)
        return {"tracks": reader.counts["tracks"], "track_lines": reader.counts["track_lines"]}
    finally:
        reader.close()

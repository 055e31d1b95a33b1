"""SQLite persistence of the fusion server: global tracks, their history, the latest joint map, the UAVs.

WAL mode; all writes go through one writer thread that commits the changes collected since its last
flush in one transaction (latest value per track / tile / UAV wins), so Zenoh callbacks never touch
the disk. Joint tiles are queued as they are published; the tracks and UAVs are pulled from their
owners by the writer itself at the start of each flush (:attr:`FusionStore.sources`), so every
commit holds the tracks and UAVs as they stood when the tiles in it were queued: a process killed
(SIGKILL) after a commit restores its UAVs, their last state and the tracks with the tiles. A
failed flush keeps its batch (merged under what came since) and is retried with backoff;
:meth:`FusionStore.health` reports it (``/healthz`` says "degraded", ``/metrics`` counts the errors).
The file is checked when opened (:mod:`fusion_server.db_check`). A restarted server
:meth:`FusionStore.load` s what the previous run had flushed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusion_server.db_check import DatabaseProblem, check_database
from fusion_server.global_tracks import TrackRecord
from fusion_server.joint_map import JointTile, TileKey
from fusion_server.uav_registry import UavRecord
from shared.messages import MessageError, decode_state, encode_state
from shared.tilecodec import decode_tile

__all__ = ["DatabaseProblem", "FusionStore", "Restored", "UavRecord"]

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tracks(
    gid INTEGER PRIMARY KEY, cls TEXT NOT NULL, lat REAL NOT NULL, lon REAL NOT NULL,
    score REAL NOT NULL, vel_e REAL NOT NULL, vel_n REAL NOT NULL, created REAL NOT NULL,
    last_update REAL NOT NULL, ended REAL, members TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS tracks_ended ON tracks(ended);
CREATE TABLE IF NOT EXISTS track_history(gid INTEGER NOT NULL, t REAL NOT NULL, lat REAL NOT NULL, lon REAL NOT NULL);
CREATE INDEX IF NOT EXISTS track_history_gid_t ON track_history(gid, t);
CREATE TABLE IF NOT EXISTS joint_tiles(
    cls TEXT NOT NULL, z INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL,
    t REAL NOT NULL, seq INTEGER NOT NULL, updated REAL NOT NULL, payload BLOB NOT NULL,
    PRIMARY KEY(cls, z, x, y));
CREATE TABLE IF NOT EXISTS uavs(
    id TEXT PRIMARY KEY, last_seen REAL NOT NULL, online_since REAL, state BLOB);
"""
#: History rows kept in memory while the database cannot be written (oldest dropped beyond it).
MAX_HISTORY_BACKLOG = 200_000
#: Tracks queued for writing in full (beyond it the ended ones are queued without their members).
MAX_QUEUED_TRACKS = 50_000
#: Longest wait between retries of a failing flush, seconds.
_MAX_BACKOFF_S = 10.0




@dataclass(frozen=True, slots=True)
class Restored:
    """What a previous run left: tracks (alive and the most recent ended), joint tiles, next gid, UAVs."""

    tracks: list[TrackRecord]
    joint_tiles: list[JointTile]
    next_gid: int
    uavs: list[UavRecord] = ()  # type: ignore[assignment]


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(str(path), timeout=10.0, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    # NORMAL in WAL mode: a process crash loses nothing committed; a power cut may lose the last flush
    conn.execute("PRAGMA synchronous=NORMAL")
    return conn


class FusionStore:
    """The database file at ``path`` (parent folders are created).

    flush_interval_s: how often the writer thread commits. history_len: history rows kept per track.
    max_ended: ended tracks kept (older ones are deleted with their history at start-up and every
    few minutes); load_ended: how many of the most recent ones :meth:`load` returns.
    Raises :class:`DatabaseProblem` (a ValueError naming the file, what is wrong and
    ``--db-recover``) when an existing file is not a sound uavmm fusion database.
    """

    def __init__(self, path: Path, *, flush_interval_s: float = 0.5, history_len: int = 600,
                 max_ended: int = 10_000, load_ended: int = 1000) -> None:
        self.path = Path(path)
        self.load_ended = load_ended
        self.flush_interval_s = flush_interval_s
        self.history_len = history_len
        self.max_ended = max_ended
        problem = check_database(self.path, SCHEMA_VERSION)
        if problem is not None:
            raise DatabaseProblem(f"database {self.path} {problem}; run with --db-recover to move it aside and "
                                  "start a new one, or --no-db")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            conn = _connect(self.path)
        except (OSError, sqlite3.Error) as exc:  # a folder that cannot be made (a file on the way), /proc, ...
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise DatabaseProblem(f"database {self.path} cannot be opened: {reason}; give --db a file in a "
                                  "writable folder, or --no-db") from None
        try:
            conn.executescript(_SCHEMA)
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if row is None:
                conn.execute("INSERT INTO meta(key, value) VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
            elif int(row[0]) != SCHEMA_VERSION:
                raise ValueError(f"{self.path}: schema version {row[0]}, this server reads {SCHEMA_VERSION}")
        finally:
            conn.close()
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._tracks: dict[int, TrackRecord] = {}
        self._history: list[tuple[int, float, float, float]] = []
        self._compacted = 0  # queued tracks when the ended ones were last compacted (`_bound_queue`)
        self._joint: dict[TileKey, JointTile | None] = {}
        self._since_trim: dict[int, int] = {}
        self._uavs: dict[str, UavRecord | None] = {}
        self._next_gid: int | None = None
        #: called by the writer at the start of every flush (and the last one at close): each queues what
        #: changed since its last call (save_tracks, save_uavs); a failing source is logged and skipped
        self.sources: list[Callable[[], None]] = []
        self._stop = False
        self._thread: threading.Thread | None = None
        self.flushes = 0
        self.write_errors = 0
        self.history_dropped = 0  # rows dropped from the backlog while writes failed
        self.last_error: str | None = None
        self.failing_since: float | None = None  # wall time of the first failure of the current run of them
        self.last_success: float | None = None  # wall time

    # ---- reading at start-up -------------------------------------------------------------------
    def load(self) -> Restored:
        """Read the alive tracks, the ``load_ended`` most recent ended ones (with history), the joint
        tiles and the UAVs."""
        conn = _connect(self.path)
        try:
            self._prune_ended(conn)
            # alive tracks and the most recent ended ones (the API lists those), with their history
            row = conn.execute(
                "SELECT ended FROM tracks WHERE ended IS NOT NULL ORDER BY ended DESC LIMIT 1 OFFSET ?",
                (self.load_ended - 1,),
            ).fetchone()
            since = row[0] if row is not None else float("-inf")
            selected = "SELECT gid FROM tracks WHERE ended IS NULL OR ended >= ?"
            rows = conn.execute(
                "SELECT gid, cls, lat, lon, score, vel_e, vel_n, created, last_update, ended, members FROM tracks "
                "WHERE ended IS NULL OR ended >= ? ORDER BY gid", (since,)
            ).fetchall()
            history: dict[int, list[tuple[float, float, float]]] = {}
            for gid, t, lat, lon in conn.execute(
                f"SELECT gid, t, lat, lon FROM track_history WHERE gid IN ({selected}) ORDER BY gid, t", (since,)
            ):
                history.setdefault(gid, []).append((t, lat, lon))
            tracks = []
            for gid, cls, lat, lon, score, vel_e, vel_n, created, last_update, ended, members in rows:
                tracks.append(
                    TrackRecord(
                        gid=gid, cls=cls, lat=lat, lon=lon, score=score, vel_en=(vel_e, vel_n),
                        created=created, last_update=last_update,
                        members=tuple((str(u), int(i)) for u, i in json.loads(members)), ended=ended,
                        history=tuple(history.get(gid, [])[-self.history_len:]),
                    )
                )
            row = conn.execute("SELECT value FROM meta WHERE key = 'next_gid'").fetchone()
            (max_gid,) = conn.execute("SELECT COALESCE(MAX(gid), 0) FROM tracks").fetchone()
            next_gid = max(int(row[0]) if row else 1, max_gid + 1)
            joint = []
            for cls, z, x, y, updated, payload in conn.execute(
                "SELECT cls, z, x, y, updated, payload FROM joint_tiles"
            ):
                try:
                    msg = decode_tile(bytes(payload))
                except MessageError as exc:
                    log.warning("skipping unreadable joint tile %s/%s/%s/%s in %s: %s", cls, z, x, y, self.path, exc)
                    continue
                values = np.rint(msg.values * 255.0).astype(np.uint8)
                values.flags.writeable = False
                joint.append(JointTile(msg.cls, msg.z, msg.x, msg.y, values, msg.t, msg.seq, bytes(payload), (),
                                       updated))
            uavs = []
            for uav_id, last_seen, online_since, state in conn.execute(
                "SELECT id, last_seen, online_since, state FROM uavs ORDER BY id"
            ):
                try:
                    message = decode_state(bytes(state)) if state is not None else None
                except MessageError as exc:
                    log.warning("skipping the unreadable last state of UAV %s in %s: %s", uav_id, self.path, exc)
                    message = None
                uavs.append(UavRecord(str(uav_id), float(last_seen), online_since, message))
            return Restored(tracks, joint, next_gid, uavs)
        finally:
            conn.close()

    def _prune_ended(self, conn: sqlite3.Connection) -> None:
        cutoff = conn.execute(
            "SELECT ended FROM tracks WHERE ended IS NOT NULL ORDER BY ended DESC LIMIT 1 OFFSET ?",
            (self.max_ended,),
        ).fetchone()
        if cutoff is None:
            return
        with conn:
            conn.execute("BEGIN")
            conn.execute("DELETE FROM track_history WHERE gid IN (SELECT gid FROM tracks WHERE ended <= ?)", cutoff)
            conn.execute("DELETE FROM tracks WHERE ended <= ?", cutoff)

    # ---- writing -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the writer thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="uavmm-fusion-db", daemon=True)
            self._thread.start()

    def save_tracks(self, records: list[TrackRecord], history: list[tuple[int, float, float, float]],
                    next_gid: int) -> None:
        """Queue track upserts (latest per gid wins), history rows (gid, t, lat, lon) and the gid counter."""
        with self._lock:
            for record in records:  # the writer stores no record's history (the rows come apart): not held queued
                self._tracks[record.gid] = dataclasses.replace(record, history=()) if record.history else record
            self._history.extend(history)
            self._bound_queue()
            self._next_gid = next_gid

    def _bound_queue(self) -> None:
        """While the database cannot be written (lock held): history rows beyond MAX_HISTORY_BACKLOG go, oldest
        first (counted in history_dropped), and beyond MAX_QUEUED_TRACKS queued tracks the ended ones keep only what
        their row needs to say they ended (no members: ~0.2 KB each). Dropped, a track the database holds alive
        would have stayed alive there and been restored as live. A day without a database grew the queue by ~36 MB
        an hour."""
        if len(self._history) > MAX_HISTORY_BACKLOG:
            self.history_dropped += len(self._history) - MAX_HISTORY_BACKLOG
            del self._history[: len(self._history) - MAX_HISTORY_BACKLOG]
        if len(self._tracks) > MAX_QUEUED_TRACKS and len(self._tracks) >= self._compacted + MAX_QUEUED_TRACKS // 10:
            for gid, record in self._tracks.items():
                if record.ended is not None and record.members:
                    self._tracks[gid] = dataclasses.replace(record, members=())
            self._compacted = len(self._tracks)

    def save_joint(self, key: TileKey, tile: JointTile | None) -> None:
        """Queue the latest joint tile at key (None: the tile was dropped)."""
        with self._lock:
            self._joint[key] = tile

    def save_joints(self, tiles: list[tuple[TileKey, JointTile | None]]) -> None:
        """Queue a batch of :meth:`save_joint` changes under one lock."""
        with self._lock:
            self._joint.update(tiles)

    def save_uavs(self, records: list[UavRecord], forgotten: list[str] = ()) -> None:  # type: ignore[assignment]
        """Queue UAV rows (latest per id wins) and ids to delete."""
        with self._lock:
            for record in records:
                self._uavs[record.id] = record
            for uav in forgotten:
                self._uavs[uav] = None

    def pending(self) -> int:
        """Changes queued and not yet committed (tracks, history rows, tiles, UAVs)."""
        with self._lock:
            return len(self._tracks) + len(self._history) + len(self._joint) + len(self._uavs)

    def health(self) -> dict[str, Any]:
        """``{status: "ok" | "failing", pending, flushes, write_errors, history_dropped, last_error,
        failing_for_s, last_success}`` (times: epoch seconds)."""
        now = time.time()
        with self._lock:
            since = self.failing_since
            return {
                "status": "failing" if since is not None else "ok",
                "pending": len(self._tracks) + len(self._history) + len(self._joint) + len(self._uavs),
                "flushes": self.flushes,
                "write_errors": self.write_errors,
                "history_dropped": self.history_dropped,
                "last_error": self.last_error,
                "failing_for_s": round(now - since, 3) if since is not None else None,
                "last_success": self.last_success,
            }

    def close(self) -> None:
        """Flush what is queued (retrying a failing database a few times) and stop the writer thread.

        What still cannot be written is logged as an error with its size."""
        with self._lock:
            self._stop = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            self._thread = None
        else:
            self._final_flush()

    def _final_flush(self) -> None:
        for attempt in range(3):
            if self._attempt():
                return
            time.sleep(0.2 * (attempt + 1))
        log.error("database %s: %d changes could not be saved at shutdown: %s", self.path, self.pending(),
                  self.last_error)

    def _attempt(self, conn: sqlite3.Connection | None = None) -> bool:
        """One flush; on failure the batch goes back into the queue and the error is recorded."""
        own = conn is None
        try:
            if own:
                conn = _connect(self.path)
            try:
                self._flush(conn)  # type: ignore[arg-type]
            finally:
                if own and conn is not None:
                    conn.close()
        except (sqlite3.Error, OSError) as exc:
            self._attempt_failed(exc)
            return False
        return True

    def _run(self) -> None:
        conn: sqlite3.Connection | None = None
        backoff = 0.0
        flushes_since_prune = 0
        while True:
            with self._lock:
                if not self._stop:
                    self._wake.wait(backoff or self.flush_interval_s)
                stop = self._stop
            if stop:
                if conn is not None:
                    conn.close()
                self._final_flush()
                return
            try:
                if conn is None:
                    conn = _connect(self.path)
            except (sqlite3.Error, OSError) as exc:
                self._attempt_failed(exc)
                backoff = min(max(backoff * 2, self.flush_interval_s), _MAX_BACKOFF_S)
                continue
            if self._attempt(conn):
                backoff = 0.0
                flushes_since_prune += 1
                if flushes_since_prune * self.flush_interval_s >= 300.0:  # ended tracks beyond max_ended
                    flushes_since_prune = 0
                    self._attempt_prune(conn)
            else:
                log.error("database %s: writing failed (%s); %d changes kept, retrying", self.path,
                          self.last_error, self.pending())
                conn.close()  # a fresh connection for the retry: no stale page cache or lock
                conn = None
                backoff = min(max(backoff * 2, self.flush_interval_s), _MAX_BACKOFF_S)

    def _attempt_failed(self, exc: BaseException) -> None:
        self._pull_sources()  # into the bounded queue (also when connecting failed): the sources' buffers are not
        with self._lock:
            self.write_errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"[:300]
            if self.failing_since is None:
                self.failing_since = time.time()

    def _attempt_prune(self, conn: sqlite3.Connection) -> None:
        try:
            self._prune_ended(conn)
        except sqlite3.Error as exc:
            log.warning("database %s: pruning ended tracks failed: %s", self.path, exc)

    def _requeue(self, tracks, history, joint, uavs, next_gid) -> None:
        """Put a failed batch back under what was queued since (newer values win)."""
        with self._lock:
            for gid, record in tracks.items():
                self._tracks.setdefault(gid, record)
            self._history = history + self._history
            self._bound_queue()
            for key, tile in joint.items():
                self._joint.setdefault(key, tile)
            for uav, row in uavs.items():
                self._uavs.setdefault(uav, row)
            if self._next_gid is None:
                self._next_gid = next_gid

    def _pull_sources(self) -> None:
        for source in self.sources:
            try:
                source()
            except Exception:  # a bug in one source must not stop the writer (the tiles still get saved)
                log.exception("database %s: collecting changes from %s failed", self.path,
                              getattr(source, "__qualname__", source))

    def _flush(self, conn: sqlite3.Connection) -> None:
        self._pull_sources()
        with self._lock:
            tracks, self._tracks = self._tracks, {}
            self._compacted = 0
            history, self._history = self._history, []
            joint, self._joint = self._joint, {}
            uavs, self._uavs = self._uavs, {}
            next_gid, self._next_gid = self._next_gid, None
        if not (tracks or history or joint or uavs or next_gid is not None):
            return
        try:
            self._write(conn, tracks, history, joint, uavs, next_gid)
        except BaseException:
            self._requeue(tracks, history, joint, uavs, next_gid)
            raise
        for gid, *_ in history:  # counted once written (a failed attempt's batch comes again)
            self._since_trim[gid] = self._since_trim.get(gid, 0) + 1
        for record in tracks.values():  # an ended track was trimmed with its last rows: not counted on
            if record.ended is not None:
                self._since_trim.pop(record.gid, None)
        with self._lock:
            self.flushes += 1
            self.last_success = time.time()
            if self.failing_since is not None:
                log.warning("database %s: writing works again (%d errors)", self.path, self.write_errors)
            self.failing_since = None

    def _write(self, conn: sqlite3.Connection, tracks, history, joint, uavs, next_gid) -> None:
        # a track's rows beyond history_len go every 50 new rows, and once more when it ends (its entry goes: kept
        # for every ended track with fewer rows since its last trim, the dict grew all flight)
        ended = [r.gid for r in tracks.values() if r.ended is not None]
        trim = list(dict.fromkeys([g for g, count in self._since_trim.items() if count >= 50] + ended))
        with conn:
            conn.execute("BEGIN")
            conn.executemany(
                "INSERT OR REPLACE INTO tracks(gid, cls, lat, lon, score, vel_e, vel_n, created, last_update, ended, "
                "members) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (r.gid, r.cls, r.lat, r.lon, r.score, r.vel_en[0], r.vel_en[1], r.created, r.last_update, r.ended,
                     json.dumps([list(m) for m in r.members]))
                    for r in tracks.values()
                ],
            )
            conn.executemany("INSERT INTO track_history(gid, t, lat, lon) VALUES (?, ?, ?, ?)", history)
            for gid in trim:
                conn.execute(
                    "DELETE FROM track_history WHERE gid = ? AND rowid NOT IN "
                    "(SELECT rowid FROM track_history WHERE gid = ? ORDER BY t DESC LIMIT ?)",
                    (gid, gid, self.history_len),
                )
            conn.executemany(
                "INSERT OR REPLACE INTO joint_tiles(cls, z, x, y, t, seq, updated, payload) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                [(*key, t.t, t.seq, t.updated, t.payload) for key, t in joint.items() if t is not None],
            )
            conn.executemany(
                "DELETE FROM joint_tiles WHERE cls = ? AND z = ? AND x = ? AND y = ?",
                [key for key, tile in joint.items() if tile is None],
            )
            conn.executemany(
                "INSERT OR REPLACE INTO uavs(id, last_seen, online_since, state) VALUES (?, ?, ?, ?)",
                [(u.id, u.last_seen, u.online_since, encode_state(u.state) if u.state is not None else None)
                 for u in uavs.values() if u is not None],
            )
            conn.executemany("DELETE FROM uavs WHERE id = ?", [(uav,) for uav, u in uavs.items() if u is None])
            if next_gid is not None:
                conn.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('next_gid', ?)", (str(next_gid),))
        for gid in trim:
            self._since_trim.pop(gid, None)

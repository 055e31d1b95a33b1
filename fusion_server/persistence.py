"""SQLite persistence of the fusion server: global tracks, their history and the latest joint map.

WAL mode; all writes go through one writer thread that commits the changes collected since its last
flush in one transaction (latest value per track / tile wins), so Zenoh callbacks never touch the
disk. A restarted server :meth:`FusionStore.load` s what the previous run had flushed.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion_server.global_tracks import TrackRecord
from fusion_server.joint_map import JointTile, TileKey
from shared.messages import MessageError
from shared.tilecodec import decode_tile

__all__ = ["FusionStore", "Restored"]

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
"""


@dataclass(frozen=True, slots=True)
class Restored:
    """What a previous run left: tracks (alive and the most recent ended), joint tiles, next gid."""

    tracks: list[TrackRecord]
    joint_tiles: list[JointTile]
    next_gid: int


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(str(path), timeout=10.0, isolation_level=None)
    conn.execute("PRAGMA journal_mode=WAL")
    # NORMAL in WAL mode: a process crash loses nothing committed; a power cut may lose the last flush
    conn.execute("PRAGMA synchronous=NORMAL")
    return conn


class FusionStore:
    """The database file at ``path`` (parent folders are created).

    flush_interval_s: how often the writer thread commits. history_len: history rows kept per track.
    max_ended: ended tracks kept (older ones are deleted with their history at start-up);
    load_ended: how many of the most recent ones :meth:`load` returns.
    """

    def __init__(self, path: Path, *, flush_interval_s: float = 0.5, history_len: int = 600,
                 max_ended: int = 10_000, load_ended: int = 1000) -> None:
        self.path = Path(path)
        self.load_ended = load_ended
        self.flush_interval_s = flush_interval_s
        self.history_len = history_len
        self.max_ended = max_ended
        self.path.parent.mkdir(parents=True, exist_ok=True)
        conn = _connect(self.path)
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
        self._joint: dict[TileKey, JointTile | None] = {}
        self._since_trim: dict[int, int] = {}
        self._next_gid: int | None = None
        self._stop = False
        self._thread: threading.Thread | None = None
        self.flushes = 0

    # ---- reading at start-up -------------------------------------------------------------------
    def load(self) -> Restored:
        """Read the alive tracks, the ``load_ended`` most recent ended ones (with history) and the joint tiles."""
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
            return Restored(tracks, joint, next_gid)
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
            for record in records:
                self._tracks[record.gid] = record
            self._history.extend(history)
            self._next_gid = next_gid

    def save_joint(self, key: TileKey, tile: JointTile | None) -> None:
        """Queue the latest joint tile at key (None: the tile was dropped)."""
        with self._lock:
            self._joint[key] = tile

    def close(self) -> None:
        """Flush what is queued and stop the writer thread."""
        with self._lock:
            self._stop = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            self._thread = None
        else:
            conn = _connect(self.path)
            try:
                self._flush(conn)
            finally:
                conn.close()

    def _run(self) -> None:
        conn = _connect(self.path)
        try:
            while True:
                with self._lock:
                    if not self._stop:
                        self._wake.wait(self.flush_interval_s)
                    stop = self._stop
                try:
                    self._flush(conn)
                except sqlite3.Error:
                    log.exception("writing %s failed; will retry", self.path)
                if stop:
                    return
        finally:
            conn.close()

    def _flush(self, conn: sqlite3.Connection) -> None:
        with self._lock:
            tracks, self._tracks = self._tracks, {}
            history, self._history = self._history, []
            joint, self._joint = self._joint, {}
            next_gid, self._next_gid = self._next_gid, None
        if not (tracks or history or joint or next_gid is not None):
            return
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
            for gid, *_ in history:
                self._since_trim[gid] = self._since_trim.get(gid, 0) + 1
            for gid in [g for g, count in self._since_trim.items() if count >= 50]:
                del self._since_trim[gid]
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
            if next_gid is not None:
                conn.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('next_gid', ?)", (str(next_gid),))
        self.flushes += 1

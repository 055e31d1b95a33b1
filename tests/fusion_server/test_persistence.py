"""FusionStore: tracks, bounded history and joint tiles survive a reopen; writes are batched."""

import numpy as np

from fusion_server.global_tracks import TrackRecord
from fusion_server.joint_map import JointTile, encode_joint_tile
from fusion_server.persistence import FusionStore


def record(gid: int, ended: float | None = None) -> TrackRecord:
    return TrackRecord(gid=gid, cls="person", lat=47.0 + gid, lon=9.0, score=0.8, vel_en=(1.0, -2.0), created=1.0,
                       last_update=2.0, members=(("a", 3), ("b", 9)), ended=ended)


def joint_tile(value: int = 50) -> JointTile:
    key = ("person", 18, 5, 6)
    values = np.full((16, 16), value, np.uint8)
    payload = encode_joint_tile(key, 16, values, 123.0, 77)
    return JointTile(*key, values, 123.0, 77, payload, ("a",), 124.0)


def test_tracks_history_and_joint_tiles_survive_reopening(tmp_path):
    path = tmp_path / "sub" / "f.sqlite"
    store = FusionStore(path, flush_interval_s=0.05, history_len=10)
    store.start()
    store.save_tracks([record(1), record(2, ended=5.0)], [(1, float(t), 47.0, 9.0) for t in range(100)], next_gid=3)
    store.save_joint(("person", 18, 5, 6), joint_tile())
    store.save_joint(("person", 18, 7, 7), joint_tile())
    store.save_joint(("person", 18, 7, 7), None)  # dropped before the flush: never written
    store.close()
    assert (path.parent / "f.sqlite").exists()
    restored = FusionStore(path, history_len=10).load()
    assert [r.gid for r in restored.tracks] == [1, 2]
    assert restored.tracks[0].members == (("a", 3), ("b", 9))
    assert restored.tracks[0].vel_en == (1.0, -2.0)
    assert restored.tracks[1].ended == 5.0
    assert [row[0] for row in restored.tracks[0].history] == [float(t) for t in range(90, 100)]
    assert restored.next_gid == 3
    (tile,) = restored.joint_tiles
    assert tile.key == ("person", 18, 5, 6) and tile.seq == 77 and int(tile.values[3, 3]) == 50


def test_wal_mode_and_a_fresh_file_loads_empty(tmp_path):
    import sqlite3

    store = FusionStore(tmp_path / "x.sqlite")
    restored = store.load()
    assert restored.tracks == [] and restored.joint_tiles == [] and restored.next_gid == 1
    mode = sqlite3.connect(tmp_path / "x.sqlite").execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_load_returns_alive_tracks_and_only_the_most_recent_ended_ones(tmp_path):
    store = FusionStore(tmp_path / "f.sqlite", load_ended=2)
    store.save_tracks([record(1)] + [record(g, ended=float(g)) for g in range(2, 7)],
                      [(g, 1.0, 47.0, 9.0) for g in range(1, 7)], next_gid=7)
    store.close()
    restored = FusionStore(tmp_path / "f.sqlite", load_ended=2).load()
    assert [r.gid for r in restored.tracks] == [1, 5, 6]
    assert all(len(r.history) == 1 for r in restored.tracks)
    assert restored.next_gid == 7


def test_each_flush_pulls_the_sources_into_the_same_commit_and_survives_a_failing_one(tmp_path, caplog):
    from fusion_server.uav_registry import UavRecord, UavRegistry

    path = tmp_path / "f.sqlite"
    store = FusionStore(path)
    registry = UavRegistry()
    registry.message("uav-a", "state", 10)
    store.sources.append(lambda: store.save_uavs(*registry.drain_changes()))

    def broken() -> None:
        raise RuntimeError("a bug in a source")

    store.sources.insert(0, broken)
    store.save_joint(("person", 18, 5, 6), joint_tile())
    assert store._attempt()  # one flush (no writer thread): the tile and what the sources had, together
    assert "a bug in a source" in caplog.text
    restored = FusionStore(path).load()
    assert [t.key for t in restored.joint_tiles] == [("person", 18, 5, 6)]
    assert [u.id for u in restored.uavs] == ["uav-a"]
    registry.message("uav-b", "state", 10)
    store.close()  # the last flush pulls again
    assert [u.id for u in FusionStore(path).load().uavs] == ["uav-a", "uav-b"]
    assert isinstance(restored.uavs[0], UavRecord)


def test_an_ended_tracks_rows_are_trimmed_with_it_and_it_is_not_remembered(tmp_path):
    """A track that ended with fewer than 50 rows since its last trim kept an entry all flight (1,873 after 12
    minutes of a crowd soak), and its rows beyond history_len stayed in the file."""
    import sqlite3

    store = FusionStore(tmp_path / "f.sqlite", history_len=10)
    store.save_tracks([record(1)], [(1, float(t), 47.0, 9.0) for t in range(30)], next_gid=2)
    assert store._attempt()
    store.save_tracks([record(1, ended=40.0)], [(1, float(t), 47.0, 9.0) for t in range(30, 40)], next_gid=2)
    assert store._attempt()
    assert store._since_trim == {}
    rows = sqlite3.connect(tmp_path / "f.sqlite").execute(
        "SELECT t FROM track_history WHERE gid = 1 ORDER BY t").fetchall()
    assert [r[0] for r in rows] == [float(t) for t in range(30, 40)]
    store.close()


def test_rows_are_counted_towards_a_trim_once_written(tmp_path, monkeypatch):
    """A batch that failed to write and came again was counted once per attempt (13 rows after three failures: 39)."""
    import sqlite3

    store = FusionStore(tmp_path / "f.sqlite", history_len=10)
    real, fails = store._write, [3]

    def flaky(*args):
        if fails[0]:
            fails[0] -= 1
            raise sqlite3.OperationalError("database is locked")
        return real(*args)

    monkeypatch.setattr(store, "_write", flaky)
    store.save_tracks([record(1)], [(1, float(t), 47.0, 9.0) for t in range(13)], next_gid=2)
    assert [store._attempt() for _ in range(4)] == [False, False, False, True]
    assert store._since_trim == {1: 13}
    store.close()

"""The fusion database fails loudly: a file that is not a sound uavmm database is refused with one
clear error (the CLI exits 2), or moved aside with --db-recover; nothing is started silently empty."""

from __future__ import annotations

import sqlite3

import pytest

from fusion_server.db_check import DatabaseProblem, check_database, move_aside
from fusion_server.persistence import FusionStore
from tests.fusion_server.test_persistence import joint_tile, record


def written_store(path):
    store = FusionStore(path, flush_interval_s=0.05)
    store.save_tracks([record(g) for g in range(1, 400)], [(g, float(t), 47.0, 9.0) for g in range(1, 400)
                                                          for t in range(20)], next_gid=400)
    store.save_joint(("person", 18, 5, 6), joint_tile())
    store.close()


def corrupt_index(path) -> None:
    """Overwrite the b-tree page of the history index with garbage (as a bad sector would)."""
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        (root,) = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'track_history_gid_t'").fetchone()
        (page_size,) = conn.execute("PRAGMA page_size").fetchone()
    with open(path, "r+b") as f:
        f.seek((root - 1) * page_size + 8)
        f.write(b"\xde\xad\xbe\xef" * 64)


def test_a_sound_database_and_a_missing_file_pass(tmp_path):
    path = tmp_path / "f.sqlite"
    assert check_database(path) is None  # will be created
    written_store(path)
    assert check_database(path) is None
    assert len(FusionStore(path).load().tracks) == 399


@pytest.mark.parametrize(("damage", "words"), [
    ("empty", "empty (0 bytes)"),
    ("garbage", "not an SQLite database"),
    ("index", "integrity check"),
    ("other_app", "not a uavmm fusion database"),
])
def test_a_damaged_database_is_refused_with_a_clear_error(tmp_path, damage, words):
    path = tmp_path / "f.sqlite"
    if damage == "empty":  # probe: a file truncated to 0 B started silently empty
        path.write_bytes(b"")
    elif damage == "garbage":
        path.write_bytes(b"not a database at all\n" * 100)
    elif damage == "index":  # probe: /healthz said ok while every write failed
        written_store(path)
        corrupt_index(path)
    else:
        with sqlite3.connect(path) as conn:
            conn.execute("CREATE TABLE notes(text TEXT)")
    problem = check_database(path)
    assert problem is not None and words in problem
    with pytest.raises(DatabaseProblem, match="--db-recover") as info:
        FusionStore(path)
    assert str(path) in str(info.value) and words in str(info.value)


def test_move_aside_keeps_the_bad_file_and_its_wal(tmp_path):
    path = tmp_path / "f.sqlite"
    written_store(path)
    corrupt_index(path)
    (tmp_path / "f.sqlite-wal").write_bytes(b"wal")
    moved = move_aside(path)
    assert not path.exists() and moved.exists() and moved.name.startswith("f.sqlite.bad-")
    assert (tmp_path / (moved.name + "-wal")).read_bytes() == b"wal"
    assert FusionStore(path).load().tracks == []  # a new, empty database in its place
    assert check_database(moved) is not None


def test_the_cli_exits_2_on_a_damaged_database_and_recovers_with_db_recover(tmp_path, capsys):
    from uavmm.cli import main

    path = tmp_path / "f.sqlite"
    path.write_bytes(b"")
    assert main(["fusion", "--db", str(path), "--no-http", "--listen", "tcp/127.0.0.1:0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "empty (0 bytes)" in err[0] and "--db-recover" in err[0]
    assert path.exists() and path.stat().st_size == 0  # nothing touched without --db-recover


def test_db_recover_moves_a_bad_database_aside_and_starts_a_new_one(server_factory, tmp_path):
    path = tmp_path / "f.sqlite"
    path.write_bytes(b"")
    server = server_factory(db_path=path, db_recover=True)
    problem, moved = server.db_recovered
    assert "empty (0 bytes)" in problem and moved.exists() and moved.stat().st_size == 0
    assert check_database(path) is None and server.db_health()["status"] == "ok"
    server.close()
    sound = server_factory(db_path=tmp_path / "g.sqlite", db_recover=True)
    assert sound.db_recovered is None  # a sound database is left alone

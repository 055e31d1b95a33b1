"""`uavmm export` under load and failure: memory that does not grow with the history, a full disk or an unwritable
folder (the previous file kept, one line, exit 2), GeoPackage DATETIME columns, unique KML/GeoJSON ids, inputs that
match nothing, a KMZ past 2 GiB, and a server writing meanwhile (its WAL checkpointed; the history copied in short
reads) (databases written by the real FusionStore, the real CLI)."""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import tracemalloc
import warnings
import xml.etree.ElementTree as ET
import zipfile
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

import pytest

from fusion_server.geo_formats import track_lines_geojson
from fusion_server.global_tracks import TrackRecord
from fusion_server.history_export import _PAGE_ROWS, export_history, read_history
from fusion_server.persistence import FusionStore
from shared.kml import feature_collections_kml
from uavmm.cli import main

ROOT = Path(__file__).resolve().parents[2]
KML = "{http://www.opengis.net/kml/2.2}"
T0 = 1_790_000_000.0
NCNAME = re.compile(r"[A-Za-z_][\w.\-]*\Z")  # xsd:ID, what KML's Placemark@id is
GPKG_DATETIME = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z\Z")


def fusion_db(path: Path, tracks: int, rows: int, classes: tuple[str, ...] = ("person",)) -> Path:
    """A database as the server writes it: ``tracks`` ended tracks of ``rows`` history rows (1 s apart) each, a
    new one every 10 s, classes in turn; plus one live track without history."""
    store = FusionStore(path, history_len=max(rows, 1))
    records, history = [], []
    for gid in range(1, tracks + 1):
        start = T0 + 10.0 * gid + 0.1234567
        rows_of = [(gid, start + k, 48.5 + 1e-5 * k + 1e-4 * (gid % 100), 9.05 + 1e-5 * k) for k in range(rows)]
        history.extend(rows_of)
        end = rows_of[-1][1] if rows_of else start
        records.append(TrackRecord(gid=gid, cls=classes[gid % len(classes)], lat=rows_of[-1][2] if rows_of else 48.5,
                                   lon=rows_of[-1][3] if rows_of else 9.05, score=0.9, vel_en=(0.5, -0.25),
                                   created=start, last_update=end, members=(("uav1", gid), ("uav2", gid + 7)),
                                   ended=end))
    records.append(TrackRecord(gid=tracks + 1, cls=classes[0], lat=48.6, lon=9.1, score=0.7, vel_en=(0.0, 0.0),
                               created=T0, last_update=T0 + 10.0 * tracks, members=(("uav1", 999),)))
    store.save_tracks(records, history, next_gid=tracks + 2)
    store.close()  # the final flush
    return path


@pytest.fixture
def small_db(tmp_path: Path) -> Path:
    return fusion_db(tmp_path / "fusion.sqlite", 12, 20, classes=("person", "boat"))


def _peak_bytes(db: Path, out: Path) -> int:
    tracemalloc.start()
    try:
        export_history(db, out)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("ext", ["gpkg", "kml", "geojson"])
def test_export_memory_does_not_grow_with_the_history(tmp_path, ext):
    """Streamed from the database's cursors into the file: 4x the rows, the same peak (it held every row as lists
    and dicts, the layers twice: ~2 KB a row, 3 GB for a day)."""
    small = fusion_db(tmp_path / "small.sqlite", 40, 200)
    large = fusion_db(tmp_path / "large.sqlite", 160, 200)
    _peak_bytes(small, tmp_path / f"warm.{ext}")  # imports and caches first
    growth = _peak_bytes(large, tmp_path / f"large.{ext}") - _peak_bytes(small, tmp_path / f"small.{ext}")
    assert growth / (120 * 200) < 32, f"{growth / (120 * 200):.0f} B per history row"


def _cli(*argv: str, limit_bytes: int | None = None,
         env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """The real CLI in a child process; limit_bytes: a disk that fills after that many bytes a file (RLIMIT_FSIZE);
    env: added to the environment."""
    def full_disk() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run([sys.executable, "-m", "uavmm.cli", "export", *argv], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, preexec_fn=full_disk if limit_bytes is not None else None,
                          env={**os.environ, **(env or {})})


@pytest.mark.parametrize("ext", ["kml", "kmz", "geojson", "gpkg"])
def test_full_disk_keeps_the_previous_export_and_says_so_in_one_line(tmp_path, small_db, ext):
    """A write that fails half-way (disk full) replaced the previous .kml/.kmz/.geojson with a truncated file, and
    was a traceback (sqlite3.OperationalError, exit 1) for .gpkg."""
    with sqlite3.connect(small_db) as conn:  # a WAL file's read-only open writes a 32 KiB -shm: not this test's
        conn.execute("PRAGMA journal_mode = DELETE")
    folder = tmp_path / "out"
    folder.mkdir()
    out = folder / f"flight.{ext}"
    assert main(["export", "--db", str(small_db), "--out", str(out)]) == 0
    previous = out.read_bytes()
    result = _cli("--db", str(small_db), "--out", str(out), limit_bytes=len(previous) // 2)
    assert out.read_bytes() == previous
    assert sorted(p.name for p in folder.iterdir()) == [out.name]  # no temporary, no journal
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"uavmm export: error: cannot write {out}: ") and ".tmp" not in line


@pytest.mark.parametrize("ext", ["gpkg", "kml", "geojson"])
def test_unwritable_folder_is_one_line_and_exit_2(tmp_path, small_db, capsys, ext):
    if os.geteuid() == 0:  # root writes anywhere but in /proc
        if not Path("/proc/self").is_dir():
            pytest.skip("needs a folder root cannot write in")
        folder = Path("/proc")
    else:
        folder = tmp_path / "readonly"
        folder.mkdir()
        folder.chmod(0o555)
    out = folder / f"flight.{ext}"
    assert main(["export", "--db", str(small_db), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"uavmm export: error: cannot write {out}: ") and err.count("\n") == 1
    assert "Traceback" not in err and ".tmp" not in err
    assert not out.exists()


def test_geopackage_time_columns_are_datetime(tmp_path, small_db):
    """QGIS's temporal controller offers DateTime fields only: the columns were TEXT with '+00:00' strings."""
    out = tmp_path / "t.gpkg"
    assert main(["export", "--db", str(small_db), "--out", str(out)]) == 0
    rows = read_history(small_db).tracks
    with sqlite3.connect(out) as conn:
        for layer, columns in (("tracks", ("created", "last_update", "ended")), ("track_lines", ("start", "end")),
                               ("track_points", ("time",))):
            declared = {name: kind for _, name, kind, *_ in conn.execute(f'PRAGMA table_info("{layer}")')}
            assert {c: declared[c] for c in columns} == dict.fromkeys(columns, "DATETIME")
            for column in columns:
                values = [v for (v,) in conn.execute(f'SELECT "{column}" FROM "{layer}"') if v is not None]
                assert values and all(GPKG_DATETIME.match(v) for v in values), values[:3]
        points = conn.execute("SELECT gid, t, time FROM track_points ORDER BY fid").fetchall()
    expected = [(f["properties"]["gid"], t) for f in rows for t, _lat, _lon in f["properties"]["history"]]
    assert [(gid, t) for gid, t, _ in points] == expected
    for _gid, t, text in points:  # the row's time, to the millisecond (truncated)
        when = datetime.fromtimestamp(t, timezone.utc)
        assert text == when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"
    pyogrio = pytest.importorskip("pyogrio", reason="GDAL (pyogrio) reads the GeoPackage as QGIS does")
    for layer, columns in (("tracks", ("created", "last_update", "ended")), ("track_lines", ("start", "end")),
                           ("track_points", ("time",))):
        info = pyogrio.read_info(out, layer=layer)
        types = dict(zip(info["fields"], info["ogr_types"], strict=True))
        assert {c: types[c] for c in columns} == dict.fromkeys(columns, "OFTDateTime")


def test_kml_and_geojson_ids_are_unique_and_valid(tmp_path, small_db):
    """A track's position and its line had the same id (GDAL: "Several features with id = 1"), and a KML
    Placemark@id of digits is no XML ID. Otherwise the files are the REST API's form of the same tracks."""
    kml, geojson = tmp_path / "t.kml", tmp_path / "t.geojson"
    assert main(["export", "--db", str(small_db), "--out", str(kml)]) == 0
    assert main(["export", "--db", str(small_db), "--out", str(geojson)]) == 0
    ids = [mark.get("id") for mark in ET.parse(kml).getroot().iter(f"{KML}Placemark")]
    assert len(ids) == 12 + 13 and len(set(ids)) == len(ids) and all(NCNAME.match(i) for i in ids), ids
    assert {"track-1", "track-1-path", "track-13"} <= set(ids) and "track-13-path" not in ids  # 13: no history
    features = json.loads(geojson.read_text())["features"]
    assert not [i for i, n in Counter(f["id"] for f in features).items() if n > 1]
    # byte for byte what the REST API's builders make of read_history's features, with the ids renamed
    tracks = read_history(small_db).tracks
    lines = track_lines_geojson(tracks)["features"]
    points = [{**f, "id": f"track-{f['id']}", "properties": {k: v for k, v in f["properties"].items()
                                                              if k != "history"}} for f in tracks]
    for line in lines:
        line["id"] = f"track-{line['id']}-path"
    assert kml.read_bytes() == feature_collections_kml("uavmm tracks", {
        "tracks": {"features": points}, "track lines": {"features": lines}})
    assert geojson.read_text() == json.dumps({"type": "FeatureCollection", "features": lines + points})
    pyogrio = pytest.importorskip("pyogrio")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pyogrio.raw.read(geojson)
    assert not [str(w.message) for w in caught if "Several features with id" in str(w.message)]


@pytest.mark.parametrize("since", ["nan", "inf", "-inf"])
def test_non_finite_since_is_refused(tmp_path, small_db, capsys, since):
    """REST answers 400 for a non-finite time; the export wrote an empty file and exit 0."""
    out = tmp_path / "t.geojson"
    assert main(["export", "--db", str(small_db), "--out", str(out), f"--since={since}"]) == 2
    err = capsys.readouterr().err
    assert err == f"uavmm export: error: --since must be a finite time in seconds since the epoch, got {since}\n"
    assert not out.exists()
    with pytest.raises(ValueError, match="finite"):
        export_history(small_db, out, since=float(since))


def test_an_export_matching_nothing_warns_with_the_classes_held(tmp_path, small_db, capsys):
    out = tmp_path / "t.geojson"
    assert main(["export", "--db", str(small_db), "--out", str(out), "--cls", "Person"]) == 0
    captured = capsys.readouterr()
    assert "tracks=0" in captured.out and json.loads(out.read_text())["features"] == []
    (warning,) = captured.err.splitlines()
    assert warning.startswith("uavmm export: warning: no tracks match --cls Person; the database has tracks of "
                              "class boat (6), person (7), the last one updated at ")
    last = T0 + 10.0 * 12 + 0.1234567 + 19  # track 12's last row
    assert warning.endswith(f" at {last} s since the epoch (2026-09-21T14:15:39Z)")
    since_ms = str(int(T0 * 1000))  # milliseconds for seconds: the last update shows the scale
    assert main(["export", "--db", str(small_db), "--out", str(out), "--since", since_ms]) == 0
    assert f"no tracks match --since {float(since_ms)}; " in capsys.readouterr().err
    empty = fusion_db(tmp_path / "empty.sqlite", 0, 0)
    with sqlite3.connect(empty) as conn:
        conn.execute("DELETE FROM tracks")
    assert main(["export", "--db", str(empty), "--out", str(tmp_path / "e.kml")]) == 0
    assert capsys.readouterr().err == "uavmm export: warning: the database has no tracks yet\n"


def test_a_kmz_past_the_zip64_limit_is_written_as_zip64_and_says_so(tmp_path, small_db, caplog):
    """Past zipfile's limit without ZIP64 (2 GiB of KML; lowered here through the export's parameter) `uavmm export`
    refused a KMZ (OSError, exit 2): it is now written again as ZIP64, counted once, with a warning (libkml does not
    open ZIP64)."""
    assert main(["export", "--db", str(small_db), "--out", str(tmp_path / "t.kml")]) == 0
    kml = (tmp_path / "t.kml").read_bytes()
    out = tmp_path / "t.kmz"
    with caplog.at_level("WARNING", logger="fusion_server.history_export"):
        counts = export_history(small_db, out, kmz_zip64_over=len(kml) // 2)
    assert counts == {"tracks": 13, "track_lines": 12}
    assert out.read_bytes()[4:6] == (45).to_bytes(2, "little")  # version needed to extract: 4.5, ZIP64
    with zipfile.ZipFile(out) as archive:
        assert archive.read("doc.kml") == kml
    assert [r.getMessage() for r in caplog.records] == [
        f"{out}: more KML than a KMZ holds without ZIP64 (2 GiB): written as ZIP64, which unzip, Python and Java read "
        "but libkml (GDAL's LIBKML driver) does not open"]
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_the_export_lets_the_server_checkpoint_its_wal_while_it_writes(tmp_path):
    """The export held one read transaction for its whole run (15-20 s for a day as a GeoPackage): the server could
    not checkpoint its WAL past it, which grew by everything written meanwhile (2 to 8 MiB in a 20 s export at
    ~0.4 MiB/s). It now copies what it exports in short reads first: while it writes its file, a checkpoint of a
    row written then reaches the WAL's end."""
    db = fusion_db(tmp_path / "fusion.sqlite", 400, 300)  # 120k rows: the GeoPackage takes a second or more
    out = tmp_path / "t.gpkg"
    writing = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    export = threading.Thread(target=export_history, args=(db, out))
    export.start()
    try:
        deadline = time.monotonic() + 60.0
        while not writing.exists() and export.is_alive() and time.monotonic() < deadline:
            time.sleep(0.002)
        server = sqlite3.connect(db, timeout=10.0)  # the server's kind of write: a history row, committed
        with server:
            server.execute("INSERT INTO track_history(gid, t, lat, lon) VALUES (1, ?, 48.5, 9.05)", (T0 + 1e6,))
        busy, frames, checkpointed = server.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        server.close()
        assert writing.exists() and export.is_alive(), "the export was not writing at the check: give it more rows"
    finally:
        export.join()
    assert (busy, checkpointed) == (0, frames) and frames > 0
    with sqlite3.connect(out) as gpkg:  # the row written after the export began is not in it
        assert gpkg.execute("SELECT count(*) FROM track_points").fetchone() == (400 * 300,)


def test_history_over_several_copy_pages_is_exported_whole_and_in_order(tmp_path):
    """The history is copied `_PAGE_ROWS` rows a read, from where the last page ended (gid, t, rowid): rows of one
    track at one time that straddle a page's end, written out of time order and between other tracks' rows, come
    out once each, in the order `read_history`'s one query reads them."""
    db = fusion_db(tmp_path / "fusion.sqlite", 3, 0)  # tracks 1-3 without history, and live track 4
    rows = [(1, T0 + k, 48.5, 9.05 + 1e-6 * k) for k in range(_PAGE_ROWS - 3)]
    for k in range(6):  # six rows of track 1 at one time, around the first page's end, between track 2's rows
        rows += [(1, T0 + 1e5, 48.6 + 1e-6 * k, 9.1), (2, T0 + 1e5 - k, 48.7, 9.2 + 1e-6 * k)]
    rows += [(3, T0 + 2e5 - k, 48.8, 9.3 + 1e-6 * k) for k in range(_PAGE_ROWS + 7)]
    with sqlite3.connect(db) as conn:
        conn.executemany("INSERT INTO track_history(gid, t, lat, lon) VALUES (?, ?, ?, ?)", rows)
    out = tmp_path / "t.geojson"
    assert export_history(db, out) == {"tracks": 4, "track_lines": 3}
    tracks = read_history(db).tracks
    lines = track_lines_geojson(tracks)["features"]
    assert sum(len(line["properties"]["times"]) for line in lines) == len(rows)
    for line in lines:
        line["id"] = f"track-{line['id']}-path"
    points = [{**f, "id": f"track-{f['id']}", "properties": {k: v for k, v in f["properties"].items()
                                                              if k != "history"}} for f in tracks]
    assert out.read_text() == json.dumps({"type": "FeatureCollection", "features": lines + points})


def test_no_room_for_the_export_copy_is_one_line_and_exit_2(tmp_path):
    """The export copies the history into SQLite's temporary folder (~40 bytes a row): a full one is said as such
    in one line, exit 2, not as a database that is no fusion database."""
    db = fusion_db(tmp_path / "fusion.sqlite", 400, 250)  # 100k rows: the copy outgrows its cache into its file
    folder = tmp_path / "sqlite-tmp"
    folder.mkdir()
    out = tmp_path / "t.geojson"
    result = _cli("--db", str(db), "--out", str(out), limit_bytes=1 << 20, env={"SQLITE_TMPDIR": str(folder)})
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"uavmm export: error: cannot export {db}: ") and "temporary folder" in line, line
    assert not out.exists() and not list(folder.iterdir())


def test_a_json_export_is_geojson_as_the_cli_says(tmp_path, small_db, capsys):
    # review probe: --out X.json (listed as GeoJSON) wrote KML and printed "(GeoJSON)"
    assert main(["export", "--db", str(small_db), "--out", str(tmp_path / "t.json")]) == 0
    assert "(GeoJSON)" in capsys.readouterr().out
    assert main(["export", "--db", str(small_db), "--out", str(tmp_path / "t.geojson")]) == 0
    assert json.loads((tmp_path / "t.json").read_text())["type"] == "FeatureCollection"
    assert (tmp_path / "t.json").read_bytes() == (tmp_path / "t.geojson").read_bytes()


UNSHARE_RO = """set -e
mount -t tmpfs -o size=64m tmpfs "$1"
cp "$2" "$1/f.sqlite"
[ -z "$4" ] || cp "$4" "$1/f.sqlite-wal"
mount -o remount,ro "$1"
exec "$5" -m uavmm.cli export --db "$1/f.sqlite" --out "$3"
"""


@pytest.mark.parametrize("with_wal", [False, True])
def test_a_wal_database_on_read_only_media_is_exported_or_named(tmp_path, small_db, with_wal):
    # review probe: a server's WAL database copied to read-only media was refused as "not a uavmm fusion database
    # (unable to open database file)": its -shm cannot be made. Read as it lies (immutable) unless a -wal beside it
    # holds rows that would be missed. Run in a mount namespace of its own (a tmpfs remounted read-only).
    if os.geteuid() != 0 or subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode != 0:
        pytest.skip("needs root and unshare -m for a read-only mount")
    assert sqlite3.connect(small_db).execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    wal = tmp_path / "pending-wal"
    if with_wal:
        wal.write_bytes(b"\0" * 32)
    (tmp_path / "ro").mkdir()
    out = tmp_path / "t.geojson"
    run = subprocess.run(["unshare", "-m", "sh", "-c", UNSHARE_RO, "sh", str(tmp_path / "ro"), str(small_db), str(out),
                          str(wal) if with_wal else "", sys.executable], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    if with_wal:
        assert run.returncode == 2 and "copy both to a writable folder" in run.stderr and not out.exists()
    else:
        assert run.returncode == 0, run.stderr
        assert len(json.loads(out.read_text())["features"]) == 2 * 12 + 1  # 12 lines, 13 positions

"""Exports for GIS tools: `uavmm export` of a real server's database to GeoPackage (read back by GDAL, as QGIS
does), KML and GeoJSON; KML from the REST API; the GeoPackage geometry encoding; bad input."""

from __future__ import annotations

import json
import sqlite3
import struct
import time
import xml.etree.ElementTree as ET

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.gpkg import Layer, geometry_blob, write_geopackage
from fusion_server.history_export import read_history
from tests.fusion_server.fake_agent import LAT, LON
from tests.netutil import wait_until
from uavmm.cli import main

KML = "{http://www.opengis.net/kml/2.2}"


def decode_blob(blob: bytes) -> tuple[int, list[tuple[float, float]]]:
    """(srs id, points) of a GeoPackage point or line blob (checks the header on the way)."""
    assert blob[:2] == b"GP" and blob[2] == 0 and blob[3] == 0b11
    srs_id, min_x, max_x, min_y, max_y = struct.unpack_from("<i4d", blob, 4)
    wkb = blob[40:]
    order, kind = struct.unpack_from("<BI", wkb)
    assert order == 1
    if kind == 1:
        points = [struct.unpack_from("<2d", wkb, 5)]
    else:
        (n,) = struct.unpack_from("<I", wkb, 5)
        points = [struct.unpack_from("<2d", wkb, 9 + 16 * i) for i in range(n)]
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    assert (min_x, max_x, min_y, max_y) == (min(xs), max(xs), min(ys), max(ys))
    return srs_id, points


@pytest.fixture
def history_db(server_factory, agent_factory, tmp_path):
    """A real server's database after two UAVs reported two people walking east for a while."""
    db = tmp_path / "fusion.sqlite"
    server = server_factory(db_path=db, track_history_interval_s=0.05)
    agent = agent_factory("uav1")
    for step in range(12):
        agent.tracks([(1, "person", LAT, LON + step * 1e-5), (2, "person", LAT + 3e-4, LON - step * 1e-5)])
        time.sleep(0.06)
    wait_until(lambda: len(server.tracker) == 2 and all(len(r.history) >= 5 for r in server.tracker.records(
        include_ended=False)), 10.0)
    server.close()  # flushes the database
    return db


def test_geopackage_export_opens_in_gdal_as_three_layers(history_db, tmp_path, capsys):
    out = tmp_path / "history.gpkg"
    assert main(["export", "--db", str(history_db), "--out", str(out)]) == 0
    assert "tracks=2, track_lines=2, track_points=" in capsys.readouterr().out
    with sqlite3.connect(out) as conn:
        assert conn.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
        assert conn.execute("PRAGMA user_version").fetchone()[0] == 10300
        contents = {r[0]: r[1:] for r in conn.execute(
            "SELECT table_name, data_type, min_x, min_y, max_x, max_y, srs_id FROM gpkg_contents")}
        assert set(contents) == {"tracks", "track_lines", "track_points"}
        for data_type, min_x, min_y, max_x, max_y, srs in contents.values():
            assert data_type == "features" and srs == 4326
            assert min_x <= LON + 1.2e-4 and max_x >= LON - 1.2e-4 and min_y <= LAT <= max_y + 1e-9
        columns = dict(conn.execute("SELECT table_name, geometry_type_name FROM gpkg_geometry_columns"))
        assert columns == {"tracks": "POINT", "track_lines": "LINESTRING", "track_points": "POINT"}
        for (blob,) in conn.execute("SELECT geom FROM track_lines"):
            srs, points = decode_blob(blob)
            assert srs == 4326 and len(points) >= 5
            lons = [p[0] for p in points]
            assert lons == sorted(lons) or lons == sorted(lons, reverse=True)  # walking east or west
        # GeoPackage DATETIME text (UTC, milliseconds, 'Z'), what GDAL reads as DateTime: every row
        (timed,) = conn.execute("SELECT count(*) FROM track_points WHERE time LIKE '____-__-__T__:__:__.___Z'"
                                ).fetchone()
        assert timed >= 10 and timed == conn.execute("SELECT count(*) FROM track_points").fetchone()[0]
    pyogrio = pytest.importorskip("pyogrio", reason="GDAL (pyogrio) reads the GeoPackage as QGIS does")
    layers = {name: kind for name, kind in pyogrio.list_layers(out)}
    assert layers == {"tracks": "Point", "track_lines": "LineString", "track_points": "Point"}
    info = pyogrio.read_info(out, layer="track_lines")
    assert info["features"] == 2 and info["crs"] == "EPSG:4326"
    meta, _fids, geometry, fields = pyogrio.raw.read(out, layer="tracks")
    assert list(meta["fields"])[:2] == ["gid", "cls"] and set(fields[1]) == {"person"}


def test_kml_and_geojson_exports(history_db, tmp_path):
    kml_path, geojson_path = tmp_path / "tracks.kml", tmp_path / "tracks.geojson"
    assert main(["export", "--db", str(history_db), "--out", str(kml_path)]) == 0
    root = ET.parse(kml_path).getroot()
    folders = {f.find(f"{KML}name").text: f for f in root.iter(f"{KML}Folder")}
    assert set(folders) == {"tracks", "track lines"}
    lines = folders["track lines"].findall(f".//{KML}LineString/{KML}coordinates")
    assert len(lines) == 2
    lon, lat = (float(v) for v in lines[0].text.split()[0].split(","))
    assert abs(lon - LON) < 2e-4 and abs(lat - LAT) < 5e-4  # lon,lat order
    assert folders["track lines"].find(f".//{KML}TimeSpan/{KML}begin").text.endswith("Z")
    assert main(["export", "--db", str(history_db), "--out", str(geojson_path), "--cls", "person"]) == 0
    body = json.loads(geojson_path.read_text())
    kinds = sorted(f["geometry"]["type"] for f in body["features"])
    assert kinds == ["LineString", "LineString", "Point", "Point"]
    assert main(["export", "--db", str(history_db), "--out", str(geojson_path), "--cls", "boat"]) == 0
    assert json.loads(geojson_path.read_text())["features"] == []
    assert read_history(history_db, since=9e18).tracks == []


def test_kmz_export_is_the_kml_zipped_as_doc_kml(history_db, tmp_path):
    import zipfile

    from shared.kml import kmz

    assert main(["export", "--db", str(history_db), "--out", str(tmp_path / "t.kml")]) == 0
    assert main(["export", "--db", str(history_db), "--out", str(tmp_path / "t.kmz")]) == 0
    with zipfile.ZipFile(tmp_path / "t.kmz") as archive:
        assert archive.namelist() == ["doc.kml"] and archive.testzip() is None
        assert archive.read("doc.kml") == (tmp_path / "t.kml").read_bytes()
    assert (tmp_path / "t.kmz").read_bytes() == kmz((tmp_path / "t.kml").read_bytes())  # zipped as it streams
    pyogrio = pytest.importorskip("pyogrio")  # GDAL's KML driver reads a KMZ through /vsizip/, as QGIS does
    layers = {name for name, _ in pyogrio.list_layers(f"/vsizip/{tmp_path / 't.kmz'}/doc.kml")}
    assert {"tracks", "track lines"} <= layers


@pytest.mark.parametrize(("argv", "problem"), [
    (["--db", "{tmp}/missing.sqlite", "--out", "{tmp}/x.gpkg"], "does not exist"),
    (["--db", "{tmp}", "--out", "{tmp}/x.gpkg"], "is a folder: give the fusion server's --db file"),
    (["--db", "{tmp}/notes.txt", "--out", "{tmp}/x.gpkg"], "is not a uavmm fusion database"),
    (["--db", "{db}", "--out", "{tmp}/x.shp"], "--out must end in .gpkg, .kml, .kmz, .geojson"),
    (["--db", "{db}", "--out", "{tmp}/no/such/dir/x.gpkg"], "output directory"),
])
def test_export_errors_say_what_is_wrong(history_db, tmp_path, capsys, argv, problem):
    (tmp_path / "notes.txt").write_text("not a database, just text that is long enough to not be sqlite\n" * 20)
    argv = [a.format(tmp=tmp_path, db=history_db) for a in argv]
    assert main(["export", *argv]) == 2
    err = capsys.readouterr().err
    assert problem in err and "Traceback" not in err and ".tmp" not in err
    assert not (tmp_path / "x.gpkg").exists()


def test_rest_kml(server, http, agent_factory):
    agent = agent_factory("uav1")
    agent.state()
    agent.tracks([(1, "person", LAT, LON)])
    wait_until(lambda: len(server.tracker) == 1)
    wait_until(lambda: http.get("/v1/uavs").json()[0]["state"])
    for path, folder in (("/v1/tracks?format=kml", "tracks"), ("/v1/uavs?format=kml", "UAVs"),
                         ("/v1/objects?format=kml", "objects")):
        response = http.get(path)
        assert response.headers["content-type"] == "application/vnd.google-earth.kml+xml", path
        root = ET.fromstring(response.content)
        assert folder in [f.find(f"{KML}name").text for f in root.iter(f"{KML}Folder")]
    tracks = ET.fromstring(http.get("/v1/tracks?format=kml").content)
    ids = [mark.get("id") for mark in tracks.iter(f"{KML}Placemark")]
    # the position and the line of a track had one digit-only id (KML ids are unique XML ids)
    assert len(ids) == 2 and len(set(ids)) == 2 and all(i.startswith("track-") for i in ids), ids
    (point,) = tracks.findall(f".//{KML}Point/{KML}coordinates")
    assert [float(v) for v in point.text.split(",")] == pytest.approx([LON, LAT])
    # format=kmz: the same documents zipped, offered as a download
    import io
    import zipfile

    for path in ("/v1/tracks", "/v1/uavs", "/v1/objects"):
        response = http.get(f"{path}?format=kmz")
        assert response.headers["content-type"] == "application/vnd.google-earth.kmz", path
        assert response.headers["content-disposition"].startswith("attachment; filename=") and ".kmz" in \
            response.headers["content-disposition"]
        with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
            assert archive.namelist() == ["doc.kml"]
            assert ET.fromstring(archive.read("doc.kml")).tag == f"{KML}kml"
    with zipfile.ZipFile(io.BytesIO(http.get("/v1/tracks?format=kmz").content)) as archive:
        (point,) = ET.fromstring(archive.read("doc.kml")).findall(f".//{KML}Point/{KML}coordinates")
    assert [float(v) for v in point.text.split(",")] == pytest.approx([LON, LAT])


_COORD = st.tuples(st.floats(-180, 180), st.floats(-85, 85))


@given(st.one_of(st.tuples(st.just("POINT"), _COORD), st.tuples(st.just("LINESTRING"), st.lists(_COORD, min_size=2,
                                                                                                   max_size=20))))
def test_geometry_blob_round_trip(case):
    kind, coordinates = case
    srs, points = decode_blob(geometry_blob(kind, coordinates))
    assert srs == 4326 and points == ([coordinates] if kind == "POINT" else list(coordinates))


@pytest.mark.parametrize(("kind", "coordinates"), [("POINT", (float("nan"), 1.0)), ("LINESTRING", [(0.0, 0.0)]),
                                                   ("POLYGON", [(0, 0), (1, 1)])])
def test_bad_geometries_are_refused(tmp_path, kind, coordinates):
    with pytest.raises(ValueError):
        write_geopackage(tmp_path / "x.gpkg", [Layer("l", kind, {}, [(coordinates, {})])])
    assert list(tmp_path.iterdir()) == []  # no file, no temporary left behind

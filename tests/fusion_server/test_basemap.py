"""The basemap under the live page: an MBTiles file served by the server (TMS rows flipped to XYZ), an XYZ
URL handed to the page, the token rule, and bad --basemap values."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from fusion_server.basemap import open_basemap
from fusion_server.config import FusionSettings
from fusion_server.http_auth import HttpToken
from tests.fusion_server.fake_agent import GRID, LAT, LON

#: a colour per tile row, so a flipped row shows
ROW_COLOURS = [(40, 160, 60), (200, 80, 40), (50, 90, 210), (220, 200, 60)]


def tile_png(bgr: tuple[int, int, int]) -> bytes:
    image = np.zeros((256, 256, 3), np.uint8)
    image[:] = bgr
    return cv2.imencode(".png", image)[1].tobytes()


def make_mbtiles(path: Path, lat: float = LAT, lon: float = LON, zooms=(14, 15, 16, 17, 18, 19),
                 attribution: str = "test orthophoto") -> Path:
    """An MBTiles file with 4 x 4 tiles per zoom around (lat, lon); the colour tells the XYZ row."""
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        conn.execute("CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB)")
        conn.executemany("INSERT INTO metadata VALUES (?, ?)", [
            ("name", "test"), ("format", "png"), ("minzoom", str(min(zooms))), ("maxzoom", str(max(zooms))),
            ("attribution", attribution)])
        for z in zooms:
            n = 1 << z
            cx = int((lon + 180.0) / 360.0 * n)
            cy = int((1.0 - np.arcsinh(np.tan(np.radians(lat))) / np.pi) / 2.0 * n)
            for dx in range(-2, 2):
                for row, colour in enumerate(ROW_COLOURS):
                    y = cy - 2 + row
                    conn.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, cx + dx, n - 1 - y, tile_png(colour)))
    return path


def test_an_mbtiles_basemap_is_served_in_xyz_order(server_factory, tmp_path):
    path = make_mbtiles(tmp_path / "ortho.mbtiles")
    server = server_factory(basemap=str(path))
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10) as http:
        config = http.get("/v1/basemap.json").json()
        assert config == {"url": "/v1/basemap/{z}/{x}/{y}", "minzoom": 14, "maxzoom": 19,
                          "attribution": "test orthophoto", "local": True}
        x, y = (int(v) for v in GRID.tile_of(LAT, LON))
        z = GRID.z
        cy = y  # the fixture's row 2 (0-based) is the centre tile's row
        for row, colour in enumerate(ROW_COLOURS):
            response = http.get(f"/v1/basemap/{z}/{x}/{cy - 2 + row}")
            assert response.status_code == 200 and response.headers["content-type"] == "image/png"
            image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
            assert tuple(int(v) for v in image[128, 128]) == colour, f"row {row}"
        assert http.get(f"/v1/basemap/{z}/{x + 10}/{y}").status_code == 404
        assert http.get("/v1/basemap/40/0/0").status_code == 404
        assert http.get("/static/basemap.js").status_code == 200


def test_a_url_basemap_goes_to_the_page_and_none_is_a_404(server_factory):
    url = "https://tiles.example.org/{z}/{x}/{y}.png"
    server = server_factory(basemap=url, basemap_attribution="© example")
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10) as http:
        assert http.get("/v1/basemap.json").json() == {"url": url, "minzoom": 0, "maxzoom": 19,
                                                        "attribution": "© example", "local": False}
        assert http.get("/v1/basemap/1/0/0").status_code == 404  # nothing served locally


def test_no_basemap_by_default(server, http):
    assert http.get("/v1/basemap.json").status_code == 404
    assert "no basemap" in http.get("/v1/basemap.json").json()["detail"]


def test_basemap_tiles_need_the_token_like_all_data(server_factory, tmp_path):
    path = make_mbtiles(tmp_path / "ortho.mbtiles")
    token = "basemap-token-0123456789"
    server = server_factory(basemap=str(path), http_tokens=(HttpToken("x", token),))
    x, y = (int(v) for v in GRID.tile_of(LAT, LON))
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10) as http:
        assert http.get(f"/v1/basemap/18/{x}/{y}").status_code == 401
        assert http.get(f"/v1/basemap/18/{x}/{y}", params={"access_token": token}).status_code == 200


def test_bad_basemaps_are_refused_with_the_reason(tmp_path):
    (tmp_path / "notes.mbtiles").write_text("not sqlite " * 100)
    with sqlite3.connect(tmp_path / "vector.mbtiles") as conn:
        conn.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        conn.execute("CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB)")
        conn.execute("INSERT INTO metadata VALUES ('format', 'pbf')")
    cases = [
        ("https://tiles.example.org/{z}/{x}.png", "must contain {y}"),
        (str(tmp_path / "missing.mbtiles"), "does not exist"),
        (str(tmp_path / "notes.mbtiles"), "is not an MBTiles file"),
        (str(tmp_path / "vector.mbtiles"), "tile format 'pbf' is not an image"),
        ("tiles.png", "must be an http(s):// tile URL"),
    ]
    for spec, problem in cases:
        with pytest.raises(ValueError, match=problem.replace("(", r"\(").replace(")", r"\)")):
            open_basemap(spec)
        with pytest.raises(ValueError):
            FusionSettings(db_path=None, basemap=spec)

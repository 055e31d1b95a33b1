"""The REST API for web maps and GIS tools, over HTTP on a real server fed over Zenoh: opt-in CORS (with
tokens too), ETag revalidation of tiles, TileJSON, application/geo+json, UAVs as GeoJSON, track
histories as LineStrings, /docs and /redoc without any CDN."""

from __future__ import annotations

import re

import httpx
import numpy as np
import pytest

from fusion_server.config import FusionSettings
from fusion_server.http_auth import HttpToken
from tests.fusion_server.fake_agent import GRID, LAT, LON, TILE_X, TILE_Y, blob
from tests.netutil import wait_until

ORIGIN = "https://maps.example.org"
TILE = f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png"


def _client(server) -> httpx.Client:
    return httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0)


def test_no_cors_unless_asked(server, http):
    preflight = http.options("/v1/uavs", headers={"Origin": ORIGIN, "Access-Control-Request-Method": "GET"})
    assert preflight.status_code == 405
    assert "access-control-allow-origin" not in http.get("/v1/uavs", headers={"Origin": ORIGIN}).headers


def test_cors_for_the_listed_origins_with_tokens(server_factory):
    token = "cors-token-0123456789abcdef"
    server = server_factory(cors_origins=(ORIGIN,), http_tokens=(HttpToken("web", token),))
    with _client(server) as http:
        preflight = http.options("/v1/objects", headers={
            "Origin": ORIGIN, "Access-Control-Request-Method": "GET",
            "Access-Control-Request-Headers": "authorization"})
        assert preflight.status_code == 200  # answered before the token check: browsers send none here
        assert preflight.headers["access-control-allow-origin"] == ORIGIN
        assert "authorization" in preflight.headers["access-control-allow-headers"].lower()
        ok = http.get("/v1/objects", headers={"Origin": ORIGIN, "Authorization": f"Bearer {token}"})
        assert ok.status_code == 200 and ok.headers["access-control-allow-origin"] == ORIGIN
        # a page may read which classes have data when it asked for one without
        car = http.get("/v1/objects?cls=car", headers={"Origin": ORIGIN, "Authorization": f"Bearer {token}"})
        assert car.headers["x-classes-with-data"] == ""
        assert "x-classes-with-data" in car.headers["access-control-expose-headers"].lower()
        refused = http.get("/v1/objects", headers={"Origin": ORIGIN})
        # the page can read why it was refused
        assert refused.status_code == 401 and refused.headers["access-control-allow-origin"] == ORIGIN
        other = http.get("/v1/objects", headers={"Origin": "https://evil.example.com",
                                                 "Authorization": f"Bearer {token}"})
        assert "access-control-allow-origin" not in other.headers
        bad = http.options("/v1/objects", headers={"Origin": "https://evil.example.com",
                                                   "Access-Control-Request-Method": "GET"})
        assert bad.status_code == 400


@pytest.mark.parametrize("origin", ["maps.example.org", "https://maps.example.org/page", "ftp://x", ""])
def test_bad_cors_origins_are_refused(origin):
    with pytest.raises(ValueError, match="cors_origins"):
        FusionSettings(db_path=None, cors_origins=(origin,))


def test_tiles_revalidate_with_etags(server, http, agent_factory):
    agent = agent_factory("uav1")
    agent.tile(blob(50, 50, value=0.5))
    wait_until(lambda: server.joint.tiles())
    first = http.get(TILE)
    etag = first.headers["etag"]
    assert first.status_code == 200 and re.fullmatch(r'"[0-9a-f]{24}"', etag)
    again = http.get(TILE, headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.content == b"" and again.headers["etag"] == etag
    assert http.get(TILE, headers={"If-None-Match": f'"other", W/{etag}'}).status_code == 304
    assert http.get(TILE, headers={"If-None-Match": '"other"'}).status_code == 200
    other_cmap = http.get(TILE, params={"cmap": "viridis"}, headers={"If-None-Match": etag})
    assert other_cmap.status_code == 200 and other_cmap.headers["etag"] != etag
    agent.tile(blob(50, 50, value=0.9))  # the map changed: a new tile and a new tag
    wait_until(lambda: http.get(TILE, headers={"If-None-Match": etag}).status_code == 200)


def test_tilejson_points_at_the_tiles_of_a_class(server, http, agent_factory):
    agent = agent_factory("uav1")
    agent.tile(blob(50, 50))
    wait_until(lambda: server.joint.tiles())
    body = http.get("/v1/tiles/person.json").json()
    assert body["tilejson"] == "3.0.0" and body["scheme"] == "xyz" and body["maxzoom"] >= 18
    west, south, east, north = body["bounds"]
    assert west <= LON <= east and south <= LAT <= north
    assert body["bounds"] == pytest.approx(list(GRID.tile_bounds(TILE_X, TILE_Y)))
    (template,) = body["tiles"]
    assert template == f"{server.url}v1/tiles/person/{{z}}/{{x}}/{{y}}.png"
    url = template.format(z=18, x=TILE_X, y=TILE_Y)
    assert httpx.get(url, timeout=10).headers["content-type"] == "image/png"
    world = http.get("/v1/tiles/nobody-yet.json").json()  # a class without data: the whole world
    assert world["bounds"][0] == -180.0
    assert http.get("/v1/tiles/bad*name.json").status_code == 400


def test_geojson_media_type_uavs_and_track_lines(server, http, agent_factory):
    agent = agent_factory("uav1")
    footprint = ((LAT, LON), (LAT + 1e-4, LON), (LAT + 1e-4, LON + 1e-4), (LAT, LON + 1e-4))
    agent.state(footprint=footprint)
    for step in range(3):
        agent.tracks([(1, "person", LAT + step * 1e-5, LON + step * 2e-5)])
        wait_until(lambda step=step: server.tracker.records(include_ended=False)
                   and len(server.tracker.records(include_ended=False)[0].history) >= 1)
    # its state and its liveliness token travel apart: wait for both
    wait_until(lambda: (rows := http.get("/v1/uavs").json()) and rows[0]["state"] and rows[0]["online"])
    for path in ("/v1/objects", "/v1/tracks", "/v1/uavs?format=geojson"):
        assert http.get(path).headers["content-type"] == "application/geo+json", path
    assert http.get("/v1/uavs").headers["content-type"] == "application/json"

    points = http.get("/v1/uavs", params={"format": "geojson"}).json()
    (uav,) = points["features"]
    assert uav["geometry"] == {"type": "Point", "coordinates": [LON, LAT]}
    assert uav["properties"]["id"] == "uav1" and uav["properties"]["online"] is True
    both = http.get("/v1/uavs", params={"format": "geojson", "footprints": "true"}).json()["features"]
    (polygon,) = [f for f in both if f["geometry"]["type"] == "Polygon"]
    ring = polygon["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 5 and ring[1] == [LON, LAT + 1e-4]  # [lon, lat], closed

    lines = http.get("/v1/tracks", params={"geometry": "line"}).json()["features"]
    assert len(lines) == 1
    line = lines[0]
    assert line["geometry"]["type"] == "LineString" and len(line["geometry"]["coordinates"]) >= 2
    history = server.tracker.records(include_ended=False)[0].history
    expected = [[lon, lat] for _t, lat, lon in history]
    if len(expected) == 1:
        expected.append(expected[0])
    assert np.allclose(line["geometry"]["coordinates"], expected)
    assert len(line["properties"]["times"]) == len(history) and "history" not in line["properties"]
    assert http.get("/v1/uavs", params={"format": "shapefile"}).status_code == 422


def test_docs_and_redoc_need_no_cdn(server, http):
    for path in ("/docs", "/redoc"):
        page = http.get(path)
        assert page.status_code == 200
        assert not re.search(r"https?://", page.text.replace("http://www.w3.org", "")), f"{path} names a host"
        for asset in re.findall(r'(?:src|href)="(/docs-static/[^"]+)"', page.text) or ["missing"]:
            assert http.get(asset).status_code == 200, asset
    assert "swagger-ui-bundle.js" in http.get("/docs").text
    assert "redoc.standalone.js" in http.get("/redoc").text

"""The REST API over HTTP on a real server fed by fake agents over Zenoh (loopback, free ports)."""

import time

import cv2
import numpy as np
import pytest

from tests.fusion_server.fake_agent import GRID, LAT, LON, TILE_X, TILE_Y, blob
from tests.netutil import wait_until

KEY = ("person", GRID.z, TILE_X, TILE_Y)


def tile_bbox(margin: float = 0.0) -> str:
    west, south, east, north = GRID.tile_bounds(TILE_X, TILE_Y)
    return f"{west + margin},{south + margin},{east - margin},{north - margin}"


def joint_uavs(server) -> tuple[str, ...]:
    tile = server.joint.get(KEY)
    return tile.uavs if tile is not None else ()


def test_two_agents_mean_where_both_cover_single_where_one_covers_then_ttl(server, http, agent_factory):
    a, b = agent_factory("uav-a"), agent_factory("uav-b")
    values_a = np.zeros((256, 256), np.float32)
    values_a[:, :128] = 0.4
    values_b = np.zeros((256, 256), np.float32)
    values_b[:, 64:] = 0.8
    a.tile(values_a)
    b.tile(values_b)
    # a second tile that only b covers
    only_b = np.zeros((256, 256), np.float32)
    only_b[100:110, 100:110] = 0.6
    b.tile(only_b, x=TILE_X + 1)
    wait_until(lambda: joint_uavs(server) == ("uav-a", "uav-b"))
    wait_until(lambda: server.joint.get(("person", 18, TILE_X + 1, TILE_Y)) is not None)

    body = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7)}).json()
    values = np.array(body["values"])
    assert (body["z"], body["n"], body["width"], body["height"]) == (18, 256, 256, 256)
    assert (body["gx0"], body["gy0"]) == (TILE_X * 256, TILE_Y * 256)
    assert values[10, 10] == pytest.approx(0.2, abs=0.003)  # a: 0.4, b: 0 (covers, sees nothing)
    assert values[10, 100] == pytest.approx(0.6, abs=0.003)  # mean of 0.4 and 0.8
    assert values[10, 200] == pytest.approx(0.4, abs=0.003)  # a: 0, b: 0.8
    sparse = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7), "encoding": "sparse"}).json()
    assert len(sparse["cells"]["value"]) == 256 * 256

    west, south, east, north = GRID.tile_bounds(TILE_X + 1, TILE_Y)
    body = http.get("/v1/map", params={"cls": "person", "bbox": f"{west},{south},{east},{north}"}).json()
    assert np.array(body["values"])[105, 105] == pytest.approx(0.6, abs=0.003)  # the single value

    # refreshed: the TTL is 1 s and a loaded machine can take that long for the requests above
    a.tile(values_a)
    b.tile(values_b)
    wait_until(lambda: joint_uavs(server) == ("uav-a", "uav-b"))
    png = http.get(f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (256, 256, 4) and image[10, 10, 3] > 0
    low = http.get(f"/v1/tiles/person/16/{TILE_X // 4}/{TILE_Y // 4}.png")
    assert low.status_code == 200
    high = http.get(f"/v1/tiles/person/20/{TILE_X * 4}/{TILE_Y * 4}.png")
    assert cv2.imdecode(np.frombuffer(high.content, np.uint8), cv2.IMREAD_UNCHANGED)[0, 0, 3] > 0

    # a stops publishing; b keeps publishing: after the TTL (1 s) only b covers the tile. b publishes on
    # every poll because a single put leaves only a short window between a's expiry and b's own.
    def only_b_covers() -> bool:
        b.tile(values_b)
        return joint_uavs(server) == ("uav-b",)

    wait_until(only_b_covers, timeout_s=5.0, interval_s=0.2)
    assert server.joint.get(KEY).values[10, 200] == 204
    # and when nobody covers it, the joint tile is gone
    wait_until(lambda: server.joint.get(KEY) is None, timeout_s=3.0)
    assert http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7)}).json()["t"] is None


def test_objects_finds_a_peak_within_one_cell_of_where_it_was_put(server, http, agent_factory):
    a, b = agent_factory("uav-a"), agent_factory("uav-b")
    a.tile(blob(70, 90, value=0.9))
    b.tile(blob(70, 90, value=0.7) + blob(200, 30, value=0.3))
    wait_until(lambda: len(joint_uavs(server)) == 2)
    features = http.get("/v1/objects", params={"cls": "person", "min_score": 0.5}).json()["features"]
    assert len(features) == 1
    lon, lat = features[0]["geometry"]["coordinates"]
    gx, gy = GRID.latlon_to_cell(lat, lon)
    assert abs(gx - (TILE_X * 256 + 90.5)) <= 1.0 and abs(gy - (TILE_Y * 256 + 70.5)) <= 1.0
    assert features[0]["properties"]["cls"] == "person"
    assert features[0]["properties"]["score"] == pytest.approx(0.8, abs=0.01)
    inside = http.get("/v1/objects", params={"bbox": f"{lon - 1e-5},{lat - 1e-5},{lon + 1e-5},{lat + 1e-5}",
                                             "min_score": 0.1}).json()["features"]
    assert len(inside) == 1
    everything = http.get("/v1/objects", params={"min_score": 0.1}).json()["features"]
    assert len(everything) == 2


def test_uavs_shows_online_state_and_offline_within_3_s_after_close(server, http, agent_factory):
    agent = agent_factory("uav-live")
    agent.state()
    rows = wait_until(lambda: [r for r in http.get("/v1/uavs").json() if r["id"] == "uav-live" and r["state"]])
    row = rows[0]
    assert row["online"] is True and row["last_seen"] > 0
    assert row["state"]["lat"] == pytest.approx(LAT) and row["state"]["camera"]["fx"] == 1400.0
    assert row["rates"]["state"] > 0
    closed = time.monotonic()
    agent.close()
    wait_until(lambda: not http.get("/v1/uavs").json()[0]["online"], timeout_s=3.0)
    assert time.monotonic() - closed < 3.0


def test_tracks_endpoint_and_joint_tracks(server, http, agent_factory):
    a, b = agent_factory("uav-a"), agent_factory("uav-b")
    a.tracks([(1, "person", LAT, LON)])
    b.tracks([(5, "person", LAT + 2e-6, LON), (6, "person", LAT + 1e-3, LON)])
    wait_until(lambda: len(server.tracker) == 2)
    body = http.get("/v1/tracks").json()
    assert body["type"] == "FeatureCollection"
    shared = next(f for f in body["features"] if len(f["properties"]["members"]) == 2)
    assert sorted(map(tuple, shared["properties"]["members"])) == [("uav-a", 1), ("uav-b", 5)]
    assert shared["properties"]["history"] and shared["geometry"]["type"] == "Point"
    assert "history" not in http.get("/v1/tracks", params={"history": False}).json()["features"][0]["properties"]


def test_health_metrics_openapi_and_index(server, http):
    assert http.get("/healthz").json()["status"] == "ok"
    spec = http.get("/openapi.json").json()
    for path in ("/healthz", "/v1/uavs", "/v1/map", "/v1/tiles/{cls}/{z}/{x}/{y}.png", "/v1/objects", "/v1/tracks"):
        assert path in spec["paths"]
    metrics = http.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain")
    assert "uavmm_fusion_latency_seconds_bucket" in metrics.text
    index = http.get("/")
    assert index.status_code == 200 and "/v1/map" in index.text


@pytest.mark.parametrize(
    ("path", "params", "status"),
    [
        ("/v1/map", {"cls": "person", "bbox": "1,2,3"}, 400),
        ("/v1/map", {"cls": "person", "bbox": "10,50,9,51"}, 400),
        ("/v1/map", {"cls": "person"}, 422),
        ("/v1/map", {"cls": "bad/cls", "bbox": "9,47,9.1,47.1"}, 400),
        ("/v1/map", {"cls": "unicorn", "bbox": "9,47,9.001,47.001"}, 404),
        ("/v1/objects", {"min_score": 2}, 422),
        ("/v1/objects", {"cls": "unicorn"}, 404),
        ("/v1/tiles/person/18/1/1.png", {"cmap": "nope"}, 400),
        ("/v1/tiles/person/30/1/1.png", {}, 400),
        ("/v1/tiles/person/3/9/1.png", {}, 400),
        ("/v1/tiles/person/x/1/1.png", {}, 422),
    ],
)
def test_bad_parameters_get_clear_4xx(server, http, agent_factory, path, params, status):
    agent_factory("uav-a").tile(blob(10, 10))
    wait_until(lambda: server.joint.get(KEY) is not None)
    response = http.get(path, params=params)
    assert response.status_code == status, response.text
    assert response.json()["detail"]


def test_map_size_is_capped(server, http, agent_factory):
    agent_factory("uav-a").tile(blob(10, 10))
    wait_until(lambda: server.joint.get(KEY) is not None)
    response = http.get("/v1/map", params={"cls": "person", "bbox": "9.2,47.6,9.4,47.7"})
    assert response.status_code == 400 and "cells" in response.json()["detail"]


def test_png_of_a_class_without_data_is_a_transparent_tile(server, http):
    response = http.get(f"/v1/tiles/boat/18/{TILE_X}/{TILE_Y}.png")
    image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert response.status_code == 200 and image[..., 3].max() == 0

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
    # the liveliness token and the state message travel apart: either may be heard first (a CI run under load
    # heard the state first), so wait for both
    rows = wait_until(lambda: [r for r in http.get("/v1/uavs").json()
                               if r["id"] == "uav-live" and r["state"] and r["online"]])
    row = rows[0]
    assert row["online"] is True and row["last_seen"] > 0
    assert row["state"]["lat"] == pytest.approx(LAT) and row["state"]["camera"]["fx"] == 1400.0
    # the last state message as sent (DESIGN 4 and 7), its protocol version too
    assert set(row["state"]) == {"v", "uav", "t", "lat", "lon", "height_m", "pitch_deg", "heading_deg", "footprint",
                                 "camera"} and row["state"]["v"] == 1
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
        ("/v1/objects", {"min_score": 2}, 422),
        ("/v1/objects", {"min_score": "abc"}, 422),  # empty means the default, malformed stays an error
        ("/v1/objects", {"bbox": "x"}, 400),
        ("/v1/objects", {"cls": "bad/cls"}, 400),
        ("/v1/history", {"since": "yesterday"}, 422),
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
    assert "--map-max-cells" in response.json()["detail"]


def test_map_max_cells_admits_a_window_at_the_cap_and_names_the_flag_one_column_over(server_factory, http_of):
    server = server_factory(map_max_cells=256 * 256)
    http = http_of(server)
    at_cap = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7)})
    assert at_cap.status_code == 200, at_cap.text
    assert at_cap.json()["width"] * at_cap.json()["height"] == 256 * 256
    west, south, east, north = GRID.tile_bounds(TILE_X, TILE_Y)
    half_cell_deg = 0.5 * 360.0 / GRID.world_cells
    over = http.get("/v1/map", params={"cls": "person",
                                       "bbox": f"{west + 1e-7},{south + 1e-7},{east + half_cell_deg},{north - 1e-7}"})
    assert over.status_code == 400
    assert over.json()["detail"] == ("bbox covers 257 x 256 = 65792 cells, at most 65536 allowed (the server's "
                                     "--map-max-cells): use a smaller bbox (or the PNG tiles)")


def test_default_map_cap_serves_a_1_km_window_near_48_deg_north(server, http, agent_factory):
    """The old cap (262,144 cells, ~200 m) refused a flight area; 2**23 holds 1 km x 1 km (~2,500 x 2,500 cells)."""
    agent_factory("uav-a").tile(blob(70, 90, value=0.9))
    wait_until(lambda: server.joint.get(KEY) is not None)
    dlat = 500.0 / 111_320.0  # half a km around the tile's place, 47.67 N
    dlon = 500.0 / (111_320.0 * np.cos(np.radians(LAT)))
    bbox = f"{LON - dlon},{LAT - dlat},{LON + dlon},{LAT + dlat}"
    body = http.get("/v1/map", params={"cls": "person", "bbox": bbox, "encoding": "sparse"})
    assert body.status_code == 200, body.text
    window = body.json()
    assert window["width"] * window["height"] > 512 * 512
    assert 2400 <= window["width"] <= 2600 and 2400 <= window["height"] <= 2600
    peak = int(np.argmax(window["cells"]["value"]))
    assert window["cells"]["value"][peak] == pytest.approx(0.9, abs=0.01)
    gx = window["gx0"] + window["cells"]["col"][peak]
    gy = window["gy0"] + window["cells"]["row"][peak]
    assert (gx, gy) == (TILE_X * 256 + 90, TILE_Y * 256 + 70)


def test_dense_and_sparse_map_values_are_the_joint_cells_over_255_rounded_to_4_places(server, http, agent_factory):
    ramp = np.tile(np.linspace(0.0, 1.0, 256, dtype=np.float32), (256, 1))  # every quantised level
    agent_factory("uav-a").tile(ramp)
    tile = wait_until(lambda: server.joint.get(KEY))
    expected = np.round(tile.values.astype(np.float64) / 255.0, 4)
    assert len(np.unique(tile.values)) > 200
    dense = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7)})
    assert dense.headers["content-type"] == "application/json"
    assert np.array_equal(np.array(dense.json()["values"]), expected)
    sparse = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7), "encoding": "sparse"}).json()
    rows, cols = np.nonzero(tile.values)
    assert sparse["cells"]["row"] == rows.tolist() and sparse["cells"]["col"] == cols.tolist()
    assert sparse["cells"]["value"] == expected[rows, cols].tolist()


def test_empty_optional_parameters_take_their_defaults(server, http, agent_factory):
    """DESIGN.md 7 writes /v1/objects?cls=&bbox=&min_score=: a client filling the template sends empty values."""
    a = agent_factory("uav-a")
    a.state()
    a.tile(blob(70, 90, value=0.9) + blob(200, 30, value=0.3))
    a.tracks([(1, "person", LAT, LON)])
    wait_until(lambda: server.joint.get(KEY) is not None and len(server.tracker) == 1)
    for empty, given in [
        ("/v1/objects?cls=person&bbox=&min_score=", "/v1/objects?cls=person"),
        ("/v1/objects?cls=&bbox=&min_score=&limit=&format=", "/v1/objects"),
        (f"/v1/map?cls=person&bbox={tile_bbox(1e-7)}&encoding=", f"/v1/map?cls=person&bbox={tile_bbox(1e-7)}"),
        (f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png?agg=&cmap=", f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png"),
        ("/v1/tracks?include_ended=&history=&geometry=&format=", "/v1/tracks"),
        ("/v1/history?since=&until=&cls=&rows=", "/v1/history"),
        ("/v1/joint/tiles?cls=", "/v1/joint/tiles"),
        ("/v1/uavs?format=", "/v1/uavs"),
    ]:
        answer, reference = http.get(empty), http.get(given)
        assert answer.status_code == 200, (empty, answer.text)
        assert answer.headers["content-type"] == reference.headers["content-type"], empty
        if empty.startswith("/v1/uavs"):  # rates and last_seen move between the two requests
            assert [r["id"] for r in answer.json()] == [r["id"] for r in reference.json()] == ["uav-a"]
        elif "json" in answer.headers["content-type"]:
            assert answer.json() == reference.json(), empty
        else:
            assert answer.content == reference.content, empty
    features = http.get("/v1/objects?cls=person&bbox=&min_score=").json()["features"]
    assert [f["properties"]["score"] for f in features] == [pytest.approx(0.9, abs=0.01)]  # min_score 0.5
    # a bare flag is not taken for "not given" (a client may mean it as true): FastAPI's 422, as before
    assert http.get("/v1/uavs?footprints").status_code == 422


@pytest.mark.parametrize(("params", "named"), [
    ({"cls": "", "bbox": "9,47,9.001,47.001"}, "cls"),
    ({"cls": "person", "bbox": ""}, "bbox"),
])


def test_an_empty_required_parameter_is_a_400_naming_it(server, http, params, named):
    response = http.get("/v1/map", params=params)
    assert response.status_code == 400, response.text
    assert response.json()["detail"].startswith(f"bad {named}:")


def test_objects_and_map_of_a_class_without_data_are_empty_answers(server, http, agent_factory):
    """A checker that starts the server and asks at once gets 200 and the normal shape, not a 404."""
    before = http.get("/v1/objects", params={"cls": "person"})
    assert before.status_code == 200 and before.headers["content-type"] == "application/geo+json"
    assert before.json() == {"type": "FeatureCollection", "features": []}
    assert before.headers["x-classes-with-data"] == ""
    window = http.get("/v1/map", params={"cls": "person", "bbox": tile_bbox(1e-7)})
    assert window.status_code == 200 and window.headers["x-classes-with-data"] == ""
    body = window.json()
    assert (body["cls"], body["width"], body["height"], body["t"]) == ("person", 256, 256, None)
    assert not np.any(np.array(body["values"]))

    agent_factory("uav-a").tile(blob(70, 90, value=0.9))
    wait_until(lambda: server.joint.get(KEY) is not None)
    car = http.get("/v1/objects", params={"cls": "car", "format": "kml"})
    assert car.status_code == 200 and car.headers["x-classes-with-data"] == "person"
    sparse = http.get("/v1/map", params={"cls": "car", "bbox": tile_bbox(1e-7), "encoding": "sparse"})
    assert sparse.status_code == 200 and sparse.headers["x-classes-with-data"] == "person"
    assert sparse.json()["cells"] == {"row": [], "col": [], "value": []}
    person = http.get("/v1/objects", params={"cls": "person"})
    assert len(person.json()["features"]) == 1 and "x-classes-with-data" not in person.headers


def test_png_of_a_class_without_data_is_a_transparent_tile(server, http):
    response = http.get(f"/v1/tiles/boat/18/{TILE_X}/{TILE_Y}.png")
    image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert response.status_code == 200 and image[..., 3].max() == 0


def test_tracks_and_history_are_served_without_fastapis_per_value_encoder(server, http, agent_factory, monkeypatch):
    # FastAPI's jsonable_encoder walked every history row of /v1/tracks, which the page polls each second:
    # 0.5 s a poll at 540 global tracks in a 50-UAV scale run, 5-8 x the json.dumps of the same body
    a = agent_factory("uav-a")
    a.tracks([(1, "person", LAT, LON), (2, "person", LAT + 1e-3, LON)])
    wait_until(lambda: len(server.tracker) == 2)
    wait_until(lambda: len(http.get("/v1/history").json()["features"]) == 2)  # in the database (0.5 s flushes)
    expected = {path: http.get(path).json() for path in ("/v1/tracks", "/v1/tracks?geometry=line",
                                                           "/v1/tracks?include_ended=true", "/v1/history")}

    def no_encoder(*args, **kwargs):
        raise AssertionError("jsonable_encoder called")

    monkeypatch.setattr("fastapi.routing.jsonable_encoder", no_encoder)
    for path, body in expected.items():
        answer = http.get(path)
        assert answer.status_code == 200, path
        assert answer.headers["content-type"] == "application/geo+json"
        got = answer.json()
        assert len(got["features"]) == 2 and got.keys() == body.keys(), path
        assert [f["id"] for f in got["features"]] == [f["id"] for f in body["features"]]

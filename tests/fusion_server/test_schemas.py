"""Typed REST responses (fusion_server.schemas): every real body of a running server validates against the model
its OpenAPI entry names, so the schema clients are generated from cannot drift from the JSON served."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, TypeAdapter, ValidationError

from fusion_server import schemas
from tests.fusion_server.fake_agent import GRID, TILE_X, TILE_Y, blob
from tests.netutil import wait_until


def _check(model, text: str) -> None:
    TypeAdapter(model).validate_json(text, strict=True)


@pytest.fixture
def busy(server, agent_factory):
    """A server with two UAVs that sent tiles, states and tracks."""
    a, b = agent_factory("uav-a"), agent_factory("uav-b")
    for agent in (a, b):
        agent.state()
        agent.tile(blob(70, 90, value=0.9))
    a.tracks([(1, "person", 47.67, 9.27)])
    b.tracks([(5, "person", 47.67001, 9.27001)])
    wait_until(lambda: len(server.tracker) >= 1 and server.joint.get(("person", GRID.z, TILE_X, TILE_Y)) is not None
               and all(r["state"] for r in server.uavs.snapshot()))
    return server


def test_every_body_validates_against_its_model(busy, http):
    west, south, east, north = GRID.tile_bounds(TILE_X, TILE_Y)
    bbox = f"{west + 1e-7},{south + 1e-7},{east - 1e-7},{north - 1e-7}"
    cases = [
        ("/healthz", {}, schemas.Health),
        ("/v1/uavs", {}, list[schemas.Uav]),
        ("/v1/uavs", {"format": "geojson", "footprints": "true"}, schemas.UavCollection),
        ("/v1/map", {"cls": "person", "bbox": bbox}, schemas.JointMapWindow),
        ("/v1/map", {"cls": "person", "bbox": bbox, "encoding": "sparse"}, schemas.JointMapWindow),
        ("/v1/tiles/person.json", {}, schemas.TileJson),
        ("/v1/objects", {"min_score": 0.5}, schemas.ObjectCollection),
        ("/v1/tracks", {}, schemas.TrackCollection),
        ("/v1/tracks", {"history": "false", "include_ended": "true"}, schemas.TrackCollection),
        ("/v1/tracks", {"geometry": "line"}, schemas.TrackLineCollection),
        ("/v1/joint/tiles", {}, list[schemas.JointTileInfo]),
        ("/v1/history", {}, schemas.HistoryCollection),
        ("/v1/history", {"rows": "false"}, schemas.HistoryCollection),
    ]
    for path, params, model in cases:
        response = http.get(path, params=params)
        assert response.status_code == 200, (path, response.text[:300])
        _check(model, response.text)
    # the bodies are not empty: the models were checked against real content
    assert len(http.get("/v1/uavs").json()) == 2
    assert http.get("/v1/objects", params={"min_score": 0.5}).json()["features"]
    assert http.get("/v1/tracks").json()["features"]


def test_a_model_refuses_a_body_that_drifted(busy, http):
    body = http.get("/healthz").json()
    del body["zenoh"]
    with pytest.raises(ValidationError, match="zenoh"):
        schemas.Health.model_validate(body)
    track = http.get("/v1/tracks").json()
    track["features"][0]["properties"]["status"] = "wandering"
    with pytest.raises(ValidationError, match="status"):
        schemas.TrackCollection.model_validate(track)


def test_openapi_names_a_typed_schema_for_every_json_response(server, http):
    spec = http.get("/openapi.json").json()
    components = spec["components"]["schemas"]
    want = {
        "/healthz": ("application/json", "Health"), "/v1/map": ("application/json", "JointMapWindow"),
        "/v1/tiles/{cls}.json": ("application/json", "TileJson"), "/v1/basemap.json": ("application/json",
                                                                                       "BasemapConfig"),
        "/v1/objects": ("application/geo+json", "ObjectCollection"),
        "/v1/history": ("application/geo+json", "HistoryCollection"),
        "/v1/uavs": ("application/geo+json", "UavCollection"),
    }
    for path, (media, name) in want.items():
        schema = spec["paths"][path]["get"]["responses"]["200"]["content"][media]["schema"]
        assert schema == {"$ref": f"#/components/schemas/{name}"}, path
    uav_list = spec["paths"]["/v1/uavs"]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
    assert uav_list["items"] == {"$ref": "#/components/schemas/Uav"}
    tracks = spec["paths"]["/v1/tracks"]["get"]["responses"]["200"]["content"]["application/geo+json"]["schema"]
    assert {s["$ref"].rsplit("/", 1)[1] for s in tracks["anyOf"]} == {"TrackCollection", "TrackLineCollection"}

    def refs(node):
        if isinstance(node, dict):
            if "$ref" in node:
                yield node["$ref"].rsplit("/", 1)[1]
            for value in node.values():
                yield from refs(value)
        elif isinstance(node, list):
            for value in node:
                yield from refs(value)

    assert set(refs(spec)) <= set(components)  # every reference resolves: generators need nothing else
    for name in schemas.__all__:
        model = getattr(schemas, name)
        assert issubclass(model, BaseModel) and name in components, name


def test_every_error_status_the_server_answers_is_declared_in_its_openapi_entry(busy, http):
    # the contract audit (1 Dec 2026): every operation declared only 200 and 422, while bad parameters answer 400, a
    # missing basemap 404 and an unchanged tile 304 (a schemathesis-style check flags each)
    spec = http.get("/openapi.json").json()
    west, south, east, north = GRID.tile_bounds(TILE_X, TILE_Y)
    tile = f"/v1/tiles/person/{GRID.z}/{TILE_X}/{TILE_Y}.png"
    etag = http.get(tile).headers["etag"]
    cases = [
        ("/v1/map", "/v1/map", {"cls": "person", "bbox": "1,2"}, {}, 400),
        ("/v1/map", "/v1/map", {"cls": "", "bbox": f"{west},{south},{east},{north}"}, {}, 400),
        ("/v1/tiles/{cls}/{z}/{x}/{y}.png", "/v1/tiles/person/30/1/1.png", {}, {}, 400),
        ("/v1/tiles/{cls}/{z}/{x}/{y}.png", tile, {}, {"If-None-Match": etag}, 304),
        ("/v1/objects", "/v1/objects", {"bbox": "1,2"}, {}, 400),
        ("/v1/history", "/v1/history", {"since": "10", "until": "5"}, {}, 400),
        ("/v1/basemap.json", "/v1/basemap.json", {}, {}, 404),
    ]
    for template, path, params, headers, status in cases:
        response = http.get(path, params=params, headers=headers)
        assert response.status_code == status, (path, params, response.status_code, response.text[:200])
        assert str(status) in spec["paths"][template]["get"]["responses"], (template, status)
        if status >= 400:
            _check(schemas.HttpError, response.text)
    assert "401" not in spec["paths"]["/v1/map"]["get"]["responses"]  # no --http-token: no 401
    head = http.head("/healthz")
    assert head.status_code == 200 and head.content == b""

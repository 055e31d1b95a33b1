"""The read-only REST API of the fusion server (DESIGN.md 7), a FastAPI app over a running server.

Endpoints: ``/healthz``, ``/v1/uavs``, ``/v1/map``, ``/v1/tiles/{cls}/{z}/{x}/{y}.png``,
``/v1/objects``, ``/v1/tracks``, ``/metrics``, ``/`` (the live map page, its script and style under
``/static/``) and the extensions ``/v1/joint/tiles``, ``/v1/tiles/{cls}.json`` (TileJSON) and
``/v1/history`` (the tracks over a time window, for the page's time slider).
Bad parameters get a 400 (or FastAPI's 422 for wrong types) with a message saying what is wrong; an
optional query parameter given empty (``?bbox=``) takes its default. A well-formed class without data
gets an empty answer (200), never a 404.
``/docs`` and ``/redoc`` are served with local assets (no CDN); CORS only for ``--cors-origin`` origins.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from importlib import resources
from typing import TYPE_CHECKING, Any, Literal, Protocol
from urllib.parse import quote

import numpy as np
from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, PlainTextResponse, Response
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel

from fusion_server import schemas
from fusion_server.geo_formats import GEOJSON_MEDIA_TYPE, GeoJSONResponse, tilejson, track_lines_geojson, uavs_geojson
from fusion_server.http_auth import PUBLIC_PATHS, PUBLIC_PREFIXES, BearerAuth
from fusion_server.peaks import find_peaks, peaks_geojson
from fusion_server.query_params import EmptyMeansDefaultRoute
from fusion_server.render import (
    AGGREGATIONS,
    COLORMAPS,
    MAX_ZOOM,
    BBox,
    parse_bbox,
    paste_window,
    tile_bytes,
    window_bounds,
    window_for_bbox,
)
from fusion_server.replay import history_window
from shared.keys import name_problem
from shared.kml import KML_MEDIA_TYPE, KMZ_MEDIA_TYPE, feature_collections_kml, kmz

if TYPE_CHECKING:
    from fusion_server.basemap import Basemap
    from fusion_server.config import FusionSettings
    from fusion_server.global_tracks import TrackRecord
    from fusion_server.joint_map import JointTile
    from fusion_server.uav_registry import UavRegistry


class JointView(Protocol):
    """The read side of a joint map the API uses: `fusion_server.joint_map.JointMap` (a server's own)
    or `fusion_server.remote_joint.RemoteJoint` (a gateway's, asked of the shards)."""

    def tiles(self, cls: str | None = None) -> list[JointTile]: ...

    def tiles_in_range(self, cls: str, x0: int, x1: int, y0: int, y1: int) -> list[JointTile]: ...

    def uav_tile_counts(self) -> dict[str, int] | None: ...

    def stats(self) -> dict[str, int]: ...


class TracksView(Protocol):
    """The read side of the global tracks the API uses: `fusion_server.global_tracks.GlobalTracker` or a
    gateway's `fusion_server.merged_tracks.MergedTracks`."""

    def records(self, include_ended: bool = False) -> list[TrackRecord]: ...

    def __len__(self) -> int: ...


class FusionView(Protocol):
    """What the API reads of a running server (`fusion_server.server.FusionServer` is one, a gateway's
    `fusion_server.gateway.Gateway` another): the API depends on this view, not on the server module, so
    the server can build the app without a cycle."""

    @property
    def settings(self) -> FusionSettings: ...

    @property
    def started(self) -> float: ...

    @property
    def joint(self) -> JointView: ...

    @property
    def tracker(self) -> TracksView: ...

    @property
    def uavs(self) -> UavRegistry: ...

    @property
    def basemap(self) -> Basemap | None: ...

    def classes(self) -> set[str]: ...

    def db_health(self) -> dict[str, Any]: ...

    def zenoh_open(self) -> bool: ...

    def prometheus(self) -> str: ...

    def count_http_denied(self, reason: str) -> None: ...

    def history_tracks(self, cls: str | None = None, since: float | None = None, until: float | None = None,
                       ends_only: bool = False) -> list[dict[str, Any]]:
        """Track features with their history rows (class ``cls``, updated since ``since``; rows up to ``until``, and
        with ``ends_only`` each track's first and last row, where a database answers) for /v1/history."""
        ...

    def cluster_health(self) -> dict[str, Any]:
        """Extra /healthz fields: a fusion server's ``inbox``, a shard's ``shard``, a gateway's ``shards``;
        ``degraded`` True turns the status to degraded."""
        ...

__all__ = ["create_app"]

_BBOX_HELP = "minlon,minlat,maxlon,maxlat in degrees (WGS84)"


def _bbox(text: str | None) -> BBox | None:
    if text is None:
        return None
    try:
        return parse_bbox(text)
    except ValueError as exc:
        raise HTTPException(status_code=400, detail=f"bad bbox: {exc}") from None


#: Header on a /v1/map or /v1/objects answer for a class without data: the classes that have data.
CLASSES_HEADER = "X-Classes-With-Data"
_CLASSES_HEADER_MAX_CHARS = 4096


def _check_cls(cls: str) -> str:
    """``cls`` if it is a well-formed class name (with data or not), else a 400 saying why."""
    problem = name_problem(cls)
    if problem is not None:
        raise HTTPException(status_code=400, detail=f"bad cls: {problem}")
    return cls


def _classes_header(server: FusionView, cls: str) -> dict[str, str]:
    """For a class without data: ``{CLASSES_HEADER: "person,car"}``, the classes with data, sorted,
    each percent-encoded (names may hold commas or non-Latin-1 characters), as many as fit in 4096
    characters; empty (no header) when ``cls`` has data. The answer itself is the empty one (200)."""
    classes = server.classes()
    if cls in classes:
        return {}
    names: list[str] = []
    length = 0
    for name in sorted(classes):
        encoded = quote(name, safe="")
        length += len(encoded) + 1
        if length > _CLASSES_HEADER_MAX_CHARS:
            break
        names.append(encoded)
    return {CLASSES_HEADER: ",".join(names)}


def _json_text(content: Any) -> str:
    """JSON as FastAPI's JSONResponse writes it (compact, UTF-8, no NaN)."""
    return json.dumps(content, ensure_ascii=False, allow_nan=False, indent=None, separators=(",", ":"))


#: The JSON text of each map value: a uint8 cell v is written as round(v / 255, 4).
_VALUE_TEXT = np.array([_json_text(float(v)) for v in np.round(np.arange(256, dtype=np.float64) / 255.0, 4)],
                       dtype=object)


def _dense_values_json(values: np.ndarray) -> str:
    """(H, W) uint8 -> the JSON text of its rows of round(v / 255, 4) floats, exactly as json.dumps
    writes the float lists, without building H x W Python floats (a 1 km window has ~6 million cells)."""
    return "[" + ",".join("[" + ",".join(row) + "]" for row in _VALUE_TEXT[values]) + "]"


def _ref(name: str) -> dict[str, str]:
    """A reference to a schema of `fusion_server.schemas` in the OpenAPI components (see `_with_models`)."""
    return {"$ref": f"#/components/schemas/{name}"}


def _with_models(app: FastAPI, *models: type[BaseModel]) -> None:
    """Add models that responses reference by `_ref` only (another media type) to the OpenAPI components."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = generate()
            components = spec.setdefault("components", {}).setdefault("schemas", {})
            for model in models:
                schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
                for name, definition in schema.pop("$defs", {}).items():
                    components.setdefault(name, definition)
                components.setdefault(model.__name__, schema)
        return app.openapi_schema  # type: ignore[return-value]

    app.openapi = openapi  # type: ignore[method-assign]


def _index_html() -> str:
    try:
        return resources.files("fusion_server").joinpath("static/index.html").read_text(encoding="utf-8")
    except (FileNotFoundError, OSError):
        return "<!doctype html><title>uavmm fusion</title><p>uavmm fusion server: see <a href='/docs'>/docs</a>."


def _kml(name: str, folders: dict[str, dict[str, Any]], format: str = "kml") -> Response:
    """KML, or with format "kmz" the same document zipped (a download named after the document)."""
    document = feature_collections_kml(name, folders)
    if format == "kmz":
        filename = name.replace(" ", "-") + ".kmz"
        return Response(kmz(document), media_type=KMZ_MEDIA_TYPE,
                        headers={"Content-Disposition": f'attachment; filename="{filename}"'})
    return Response(document, media_type=KML_MEDIA_TYPE)


def _etags(header: str | None) -> set[str]:
    """The entity tags of an If-None-Match header (weak ones compare as strong: GET only)."""
    if not header:
        return set()
    return {tag.strip().removeprefix("W/") for tag in header.split(",")}


def _add_docs(app: FastAPI) -> None:
    """Swagger UI at /docs and ReDoc at /redoc with the assets of the fastapi-offline package: no CDN."""
    static = resources.files("fastapi_offline").joinpath("static")
    app.mount("/docs-static", StaticFiles(directory=str(static)), name="docs-static")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="uavmm fusion server - API",
                                   swagger_js_url="/docs-static/swagger-ui-bundle.js",
                                   swagger_css_url="/docs-static/swagger-ui.css",
                                   swagger_favicon_url="/docs-static/favicon.png")

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url="/openapi.json", title="uavmm fusion server - API",
                              redoc_js_url="/docs-static/redoc.standalone.js",
                              redoc_favicon_url="/docs-static/favicon.png", with_google_fonts=False)


def create_app(server: FusionView) -> FastAPI:
    """The FastAPI app serving ``server``'s state (read-only)."""
    app = FastAPI(
        title="uavmm fusion server",
        version="1",
        description="Joint memory map, global tracks and UAV status of a uav-memory-maps fusion server.",
        docs_url=None, redoc_url=None,  # served below with local assets
    )
    app.router.route_class = EmptyMeansDefaultRoute  # ?bbox=&min_score= means "not given"
    grid = server.settings.grid
    if server.settings.http_tokens:  # every path but the page shell, /healthz and the schema needs a token
        app.add_middleware(BearerAuth, tokens=server.settings.http_tokens, on_denied=server.count_http_denied)
    if server.settings.cors_origins:  # outermost: preflights and 401s carry the CORS headers too
        app.add_middleware(CORSMiddleware, allow_origins=list(server.settings.cors_origins),
                           allow_methods=["GET", "HEAD", "OPTIONS"], allow_headers=["Authorization"],
                           expose_headers=["ETag", CLASSES_HEADER], max_age=600)
    _add_docs(app)
    _with_models(app, schemas.UavCollection)

    @app.get("/", response_class=HTMLResponse, summary="Live map page")
    def index() -> str:
        return _index_html()

    # the page's script and style, shipped in the package: the page works offline (no CDN)
    app.mount("/static", StaticFiles(packages=[("fusion_server", "static")]), name="static")

    @app.head("/healthz", include_in_schema=False)  # curl -I, load balancers' probes: alive, no body
    def healthz_head() -> Response:
        return Response(status_code=200)

    @app.get("/healthz", summary="Liveness and a short status", response_model=None,
             responses={200: {"model": schemas.Health}})
    def healthz() -> dict[str, Any]:
        db = server.db_health()
        cluster = server.cluster_health()
        healthy = server.zenoh_open() and db["status"] != "failing" and not cluster.get("degraded", False)
        return {
            **cluster,
            "status": "ok" if healthy else "degraded",
            "db": db,
            "zenoh": "open" if server.zenoh_open() else "closed",
            "uptime_s": round(time.monotonic() - server.started, 3),
            "uavs_online": len(server.uavs.online()),
            "classes": sorted(server.classes()),
            **server.joint.stats(),
            "global_tracks": len(server.tracker),
        }

    @app.get("/v1/uavs", summary="The UAVs: liveliness, last seen, last state, message rates", response_model=None,
             responses={200: {"model": list[schemas.Uav], "description": "format=json: a list of UAVs; "
                              "format=geojson: a FeatureCollection (schema UavCollection); format=kml: KML; "
                              "format=kmz: zipped KML",
                              "content": {GEOJSON_MEDIA_TYPE: {"schema": _ref("UavCollection")}}}})
    def uavs(
        format: Literal["json", "geojson", "kml", "kmz"] = Query(
            "json", description="json list, or a GeoJSON FeatureCollection / KML / KMZ of Points (UAVs with a "
                                "position)"),
        footprints: bool = Query(False, description="geojson, kml, kmz: also each UAV's ground footprint as a "
                                                    "Polygon"),
    ) -> Any:
        rows = server.uavs.snapshot(server.joint.uav_tile_counts())
        if format == "geojson":
            return GeoJSONResponse(uavs_geojson(rows, footprints=footprints))
        if format in ("kml", "kmz"):
            return _kml("uavmm UAVs", {"UAVs": uavs_geojson(rows, footprints=footprints)}, format)
        return rows

    @app.get("/v1/map", summary="Joint map window over a bbox (grid geometry + values)", response_model=None,
             responses={200: {"model": schemas.JointMapWindow}})
    def joint_map(
        cls: str = Query(..., description="class name, e.g. person"),
        bbox: str = Query(..., description=_BBOX_HELP),
        encoding: Literal["dense", "sparse"] = Query("dense", description="dense rows or sparse non-zero cells"),
    ) -> Response:
        _check_cls(cls)
        box = _bbox(bbox)
        assert box is not None
        window = window_for_bbox(grid, box)
        cells = window.width * window.height
        if cells > server.settings.map_max_cells:
            raise HTTPException(
                status_code=400,
                detail=f"bbox covers {window.width} x {window.height} = {cells} cells, at most "
                f"{server.settings.map_max_cells} allowed (the server's --map-max-cells): use a smaller bbox "
                "(or the PNG tiles)",
            )
        n = grid.n
        tiles = server.joint.tiles_in_range(
            cls, window.gx0 // n, (window.gx0 + window.width - 1) // n,
            window.gy0 // n, (window.gy0 + window.height - 1) // n,
        )
        values = paste_window(window, tiles)
        west, south, east, north = window_bounds(grid, window)
        centre_lat = (box.min_lat + box.max_lat) / 2
        body: dict[str, Any] = {
            "cls": cls,
            "z": grid.z,
            "n": grid.n,
            "gx0": window.gx0,
            "gy0": window.gy0,
            "width": window.width,
            "height": window.height,
            "bbox": [west, south, east, north],
            "cell_size_m": float(grid.cell_size_m(centre_lat)),
            "t": max((t.t for t in tiles), default=None),
            "encoding": encoding,
        }
        headers = _classes_header(server, cls)  # a class without data: all-zero values, t null
        # the JSON is written here, not by FastAPI's encoder, which took 4 s for a 1 km dense window
        if encoding == "dense":
            text = _json_text(body)[:-1] + ',"values":' + _dense_values_json(values) + "}"
        else:
            rows, cols = np.nonzero(values)
            scaled = np.round(values[rows, cols].astype(np.float64) / 255.0, 4)
            body["cells"] = {"row": rows.tolist(), "col": cols.tolist(), "value": scaled.tolist()}
            text = _json_text(body)
        return Response(text.encode("utf-8"), media_type="application/json", headers=headers)

    @app.get(
        "/v1/tiles/{cls}/{z}/{x}/{y}.png",
        summary="Heatmap PNG tile of the joint map for slippy-map viewers",
        response_class=Response,
        responses={200: {"content": {"image/png": {}}}},
    )
    def tile_png(
        request: Request,
        cls: str,
        z: int,
        x: int,
        y: int,
        agg: str = Query("max", description=f"downsampling at zooms below the grid's: {', '.join(AGGREGATIONS)}"),
        cmap: str = Query("inferno", description=f"colormap: {', '.join(COLORMAPS)}"),
    ) -> Response:
        # a well-formed class without data yet gets a transparent tile, so map viewers show no errors
        _check_cls(cls)
        try:
            png = tile_bytes(server.joint.tiles_in_range, grid, cls, z, x, y, agg=agg, cmap=cmap)
        except ValueError as exc:
            raise HTTPException(status_code=400, detail=str(exc)) from None
        # the tile's content decides: a viewer revalidating an unchanged tile gets 304 and no body
        etag = '"' + hashlib.blake2b(png, digest_size=12).hexdigest() + '"'
        headers = {"Cache-Control": "no-cache", "ETag": etag}
        if etag in _etags(request.headers.get("if-none-match")):
            return Response(status_code=304, headers=headers)
        return Response(content=png, media_type="image/png", headers=headers)

    @app.get("/v1/tiles/{cls}.json", summary="TileJSON 3.0.0 of a class's heatmap tiles (extension)",
             response_model=None, responses={200: {"model": schemas.TileJson}})
    def tile_json(request: Request, cls: str) -> dict[str, Any]:
        _check_cls(cls)
        tiles = server.joint.tiles(cls)
        bounds = None
        if tiles:
            corners = [grid.tile_bounds(t.x, t.y) for t in tiles]
            bounds = [min(c[0] for c in corners), min(c[1] for c in corners),
                      max(c[2] for c in corners), max(c[3] for c in corners)]
        base = str(request.base_url).rstrip("/")
        return tilejson(cls, f"{base}/v1/tiles/{cls}/{{z}}/{{x}}/{{y}}.png", bounds=bounds, max_zoom=MAX_ZOOM,
                        grid_zoom=grid.z)

    @app.get("/v1/objects", summary="Fused object candidates (joint map peaks) as GeoJSON",
             response_class=GeoJSONResponse, response_model=None,
             responses={200: {"model": schemas.ObjectCollection,
                              "description": "format=geojson: GeoJSON; kml: KML; kmz: zipped KML"}})
    def objects(
        response: Response,
        cls: str | None = Query(None, description="class name (default: all classes)"),
        bbox: str | None = Query(None, description=_BBOX_HELP + " (default: everywhere)"),
        min_score: float = Query(0.5, ge=0.0, le=1.0, description="lowest peak value in [0, 1]"),
        limit: int = Query(1000, ge=1, le=100_000, description="most features returned"),
        format: Literal["geojson", "kml", "kmz"] = Query("geojson", description="geojson, kml or kmz (zipped KML)"),
    ) -> Any:
        box = _bbox(bbox)
        # a class without data has no peaks: an empty FeatureCollection (200)
        classes = [_check_cls(cls)] if cls is not None else sorted(server.classes())
        headers = _classes_header(server, cls) if cls is not None else {}
        response.headers.update(headers)
        peaks = []
        for name in classes:
            if box is not None:
                window = window_for_bbox(grid, box)
                n = grid.n
                # one tile of margin so peaks at the bbox edge see their neighbours
                tiles = server.joint.tiles_in_range(
                    name, window.gx0 // n - 1, (window.gx0 + window.width - 1) // n + 1,
                    window.gy0 // n - 1, (window.gy0 + window.height - 1) // n + 1,
                )
            else:
                tiles = server.joint.tiles(name)
            peaks.extend(find_peaks(tiles, grid, min_score, bbox=box, limit=limit))
        peaks.sort(key=lambda p: -p.score)
        if format in ("kml", "kmz"):
            answer = _kml("uavmm fused objects", {"objects": peaks_geojson(peaks[:limit])}, format)
            answer.headers.update(headers)
            return answer
        return peaks_geojson(peaks[:limit])

    @app.get("/v1/tracks", summary="Global tracks as GeoJSON Points with history", response_class=GeoJSONResponse,
             response_model=None,
             responses={200: {"model": schemas.TrackCollection | schemas.TrackLineCollection,
                              "description": "geometry=point: TrackCollection; geometry=line: TrackLineCollection; "
                                             "format=kml: KML; format=kmz: zipped KML"}})
    def tracks(
        include_ended: bool = Query(False, description="also list recently ended tracks"),
        history: bool = Query(True, description="include each track's (t, lat, lon) history"),
        geometry: Literal["point", "line"] = Query(
            "point", description="point: the current position; line: the history as a LineString [lon, lat] "
                                 "(its times in the times property)"),
        format: Literal["geojson", "kml", "kmz"] = Query(
            "geojson", description="geojson, or kml / kmz (positions and lines; kmz: zipped)"),
    ) -> Any:
        features = []
        for record in server.tracker.records(include_ended=include_ended):
            feature = record.to_geojson()
            if not history and geometry == "point":
                del feature["properties"]["history"]
            features.append(feature)
        if format in ("kml", "kmz"):  # Placemark ids unique and valid XML ids, as `uavmm export` writes them
            lines = track_lines_geojson(features)["features"]
            return _kml("uavmm global tracks", {
                "tracks": {"type": "FeatureCollection",
                           "features": [{**f, "id": f"track-{f['id']}"} for f in features]},
                "track lines": {"type": "FeatureCollection",
                                "features": [{**f, "id": f"track-{f['id']}-path"} for f in lines]}}, format)
        # answered as a Response: a returned dict goes through FastAPI's jsonable_encoder, which walks every
        # history row (~6 x the json.dumps of the body: 0.57 s a poll of the page at 540 tracks, 3.1 s for 600
        # tracks of 600 rows); the features hold JSON types only, so the bytes are the same
        if geometry == "line":
            return GeoJSONResponse(track_lines_geojson(features))
        return GeoJSONResponse({"type": "FeatureCollection", "features": features})

    @app.get("/v1/history", response_class=GeoJSONResponse, response_model=None,
             responses={200: {"model": schemas.HistoryCollection}},
             summary="Global tracks over a time window, from the stored history (extension; the page's slider)")
    def history(
        since: float | None = Query(None, description="earliest history row, seconds since the epoch"),
        until: float | None = Query(None, description="latest history row (the time shown), seconds since the epoch"),
        cls: str | None = Query(None, description="class name (default: all)"),
        rows: bool = Query(True, description="include the history rows (false: positions and time_range only)"),
    ) -> Any:
        for name, value in (("since", since), ("until", until)):
            if value is not None and not math.isfinite(value):
                raise HTTPException(status_code=400, detail=f"{name} must be a finite time, got {value}")
        if since is not None and until is not None and since > until:
            raise HTTPException(status_code=400, detail=f"since ({since}) is after until ({until})")
        if cls is not None:
            _check_cls(cls)
        found = server.history_tracks(cls=cls, since=since, until=until, ends_only=not rows)
        window = history_window(found, since, until)
        missing = getattr(found, "missing", ())  # a gateway's: the shards that did not answer in time
        if missing:  # else the answer is a single server's, byte for byte
            window["missing_shards"] = list(missing)
        if not rows:
            for feature in window["features"]:
                del feature["properties"]["history"]
        return GeoJSONResponse(window)  # not through jsonable_encoder: up to 200,000 rows (see /v1/tracks)

    @app.get("/v1/joint/tiles", summary="Index of the current joint tiles (extension)", response_model=None,
             responses={200: {"model": list[schemas.JointTileInfo]}})
    def joint_tiles(cls: str | None = Query(None, description="class name (default: all)")) -> list[dict[str, Any]]:
        if cls is not None:
            _check_cls(cls)
        return [
            {"cls": t.cls, "z": t.z, "x": t.x, "y": t.y, "t": t.t, "seq": t.seq, "uavs": list(t.uavs),
             "max": round(float(t.values.max()) / 255.0, 4)}
            for t in sorted(server.joint.tiles(cls), key=lambda t: t.key)
        ]

    @app.get("/v1/basemap.json", summary="The basemap the live page draws (extension; 404 without --basemap)",
             response_model=None, responses={200: {"model": schemas.BasemapConfig}})
    def basemap_config() -> dict[str, Any]:
        if server.basemap is None:
            raise HTTPException(status_code=404, detail="no basemap (uavmm fusion --basemap URL|FILE.mbtiles)")
        return server.basemap.page_config()

    @app.get("/v1/basemap/{z}/{x}/{y}", summary="A tile of the --basemap MBTiles file (extension)",
             response_class=Response, responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}})
    def basemap_tile(z: int, x: int, y: int) -> Response:
        tiles = server.basemap.mbtiles if server.basemap is not None else None
        if tiles is None:
            raise HTTPException(status_code=404, detail="no MBTiles basemap on this server")
        data = tiles.tile(z, x, y)
        if data is None:
            raise HTTPException(status_code=404, detail=f"the basemap has no tile {z}/{x}/{y}")
        return Response(data, media_type=tiles.media_type, headers={"Cache-Control": "max-age=86400"})

    @app.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics")
    def metrics() -> PlainTextResponse:
        return PlainTextResponse(server.prometheus(), media_type="text/plain; version=0.0.4; charset=utf-8")

    _declare_errors(app, auth=bool(server.settings.http_tokens))
    return app


_ERROR = {"model": schemas.HttpError}


def _declare_errors(app: FastAPI, *, auth: bool) -> None:
    """The error statuses each operation can answer, in its OpenAPI entry (the contract audit of 1 Dec 2026: every
    operation declared only 200 and 422, while bad parameters answer 400, a missing basemap 404, an unchanged tile
    304 and, with --http-token, a protected path without a token 401)."""
    for route in app.routes:
        if not isinstance(route, APIRoute) or not route.include_in_schema:
            continue
        declared = dict(route.responses)
        if route.path.startswith("/v1/") and (route.dependant.query_params or route.dependant.path_params):
            declared.setdefault(400, {**_ERROR, "description": "A malformed parameter (the detail names it)"})
        if route.path.startswith("/v1/basemap"):
            declared.setdefault(404, {**_ERROR, "description": "No basemap, or no such tile of it"})
        if route.path.startswith("/v1/tiles/") and route.path.endswith(".png"):
            declared.setdefault(304, {"description": "Not modified (If-None-Match matched the tile's ETag)"})
        if auth and not (route.path in PUBLIC_PATHS or route.path.startswith(PUBLIC_PREFIXES)):
            declared.setdefault(401, {**_ERROR, "description": "No valid bearer token (--http-token)"})
        route.responses = declared
    app.openapi_schema = None  # built again, with them

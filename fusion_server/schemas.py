"""Typed response bodies of the REST API (DESIGN.md 7), as pydantic models for the OpenAPI schema, so client
generators (openapi-generator, openapi-python-client, datamodel-code-generator) produce usable types.

The endpoints keep building their JSON as before (the models document it; `fusion_server.api` declares them per
response with ``response_model=None`` so nothing is re-serialised or filtered on the hot path); the tests check
every real body against its model, so the two cannot drift apart. Models accept extra keys (``extra="allow"``):
servers may add fields, as DESIGN.md allows, without breaking generated clients.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "BasemapConfig",
    "DbHealth",
    "Health",
    "HistoryCollection",
    "JointMapWindow",
    "JointTileInfo",
    "ObjectCollection",
    "TileJson",
    "TrackCollection",
    "TrackLineCollection",
    "Uav",
    "UavCollection",
]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


# ---- /healthz ------------------------------------------------------------------------------------------------

class HttpError(BaseModel):
    """An error answer: FastAPI's ``{"detail": ...}`` naming what is wrong."""

    detail: str


class DbHealth(_Open):
    """The SQLite history's health: ``off`` without ``--db``."""

    status: Literal["ok", "failing", "off"]
    pending: int | None = Field(None, description="rows queued for the writer")
    flushes: int | None = None
    write_errors: int | None = None
    history_dropped: int | None = None
    last_error: str | None = None
    failing_for_s: float | None = None
    last_success: float | None = Field(None, description="UNIX seconds of the last successful write")


class Health(_Open):
    """``GET /healthz``."""

    status: Literal["ok", "degraded"]
    db: DbHealth
    zenoh: Literal["open", "closed"]
    uptime_s: float
    uavs_online: int
    classes: list[str]
    joint_tiles: int
    uav_tiles: int
    pending: int = Field(description="tiles waiting to be fused")
    coverage_masks: int
    footprints: int
    global_tracks: int
    inbox: dict[str, float] | None = Field(None, description="a fusion server: UAV messages waiting for its fusion "
                                                            "thread (samples) and the oldest one's wait (oldest_s)")
    shard: str | None = Field(None, description="a shard: K/N (`uavmm fusion --shard K/N`)")
    shards: dict[str, Any] | None = Field(None, description="a gateway: each shard's liveliness and regions")
    degraded: bool | None = Field(None, description="a gateway: True while a shard is missing")
    down: list[int] | None = Field(None, description="a gateway: the shards that are missing")


# ---- /v1/uavs ------------------------------------------------------------------------------------------------

class CameraIntrinsics(_Open):
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


class UavState(_Open):
    """The UAV's last state message (DESIGN.md 4)."""

    v: int = Field(description="protocol version of the message")
    uav: str
    t: float = Field(description="UNIX seconds")
    lat: float
    lon: float
    height_m: float
    pitch_deg: float = Field(description="depression below the horizon, 90 = nadir")
    heading_deg: float = Field(description="clockwise from true north, [0, 360)")
    footprint: list[list[float]] = Field(description="ground polygon [[lat, lon], ...]")
    camera: CameraIntrinsics


class Uav(_Open):
    """One row of ``GET /v1/uavs`` (format=json)."""

    id: str
    online: bool = Field(description="its liveliness token is present")
    last_seen: float | None = Field(description="UNIX seconds of its last message")
    online_since: float | None
    state: UavState | None
    rates: dict[str, float] = Field(description="messages per second by kind over the last 10 s")
    bytes_per_s: float
    messages: dict[str, int]
    rejected: dict[str, int] = Field(description="dropped messages by reason")
    sessions: list[str]
    conflict: bool = Field(description="more than one Zenoh session speaks for this id")
    tiles: int | None = Field(None, description="fresh tiles it covers (a fusion server; not on a gateway)")
    shard: int | None = Field(None, description="a gateway: the shard owning the region under the UAV "
                                                "(None without a state)")
    degraded: bool | None = Field(None, description="a gateway: True while that shard is down")
    clock_lead_s: float | None = Field(None, description="how far its clock runs ahead of the server's, taken on "
                                                         "evidence (its messages are moved back by it); 0.0: none")
    clock_leads_s: dict[str, float] | None = Field(None, description="while it holds a lead: the lead of each kind "
                                                                     "of message (tile, state, tracks)")


# ---- GeoJSON ---------------------------------------------------------------------------------------------------

class PointGeometry(BaseModel):
    type: Literal["Point"]
    coordinates: list[float] = Field(description="[lon, lat]")


class LineStringGeometry(BaseModel):
    type: Literal["LineString"]
    coordinates: list[list[float]] = Field(description="[[lon, lat], ...]")


class PolygonGeometry(BaseModel):
    type: Literal["Polygon"]
    coordinates: list[list[list[float]]] = Field(description="rings of [lon, lat]; the first is the outline")


class ObjectProperties(_Open):
    cls: str
    score: float = Field(description="joint map value at the peak, [0, 1]")


class ObjectFeature(_Open):
    type: Literal["Feature"]
    geometry: PointGeometry
    properties: ObjectProperties


class ObjectCollection(_Open):
    """``GET /v1/objects``: fused object candidates (joint map peaks)."""

    type: Literal["FeatureCollection"]
    features: list[ObjectFeature]


class TrackProperties(_Open):
    gid: int
    cls: str
    score: float
    vel_en: list[float] = Field(description="[east, north] m/s")
    status: Literal["tracked", "lost", "ended"]
    created: float
    last_update: float
    ended: float | None
    members: list[list[str | int]] = Field(description="[uav, local track id] absorbed")
    active_members: list[list[str | int]] | None = Field(None, description="members reported now (live tracks)")
    history: list[list[float]] | None = Field(None, description="[t, lat, lon] rows (absent with history=false)")


class TrackFeature(_Open):
    type: Literal["Feature"]
    id: int
    geometry: PointGeometry
    properties: TrackProperties


class TrackCollection(_Open):
    """``GET /v1/tracks`` (geometry=point): global tracks at their current position."""

    type: Literal["FeatureCollection"]
    features: list[TrackFeature]


class HistoryCollection(_Open):
    """``GET /v1/history``: tracks over a time window, each at its last row in it, history clipped to it."""

    type: Literal["FeatureCollection"]
    features: list[TrackFeature]
    time_range: list[float] | None = Field(description="[first, last] row time over all tracks; null when empty")
    missing_shards: list[int] | None = Field(None, description="a gateway's, when a shard did not answer in time: "
                                                               "those shards (K); their tracks are not in this "
                                                               "answer")


class TrackLineProperties(TrackProperties):
    times: list[float] = Field(description="UNIX seconds of the vertices")


class TrackLineFeature(_Open):
    type: Literal["Feature"]
    id: int | None
    geometry: LineStringGeometry
    properties: TrackLineProperties


class TrackLineCollection(_Open):
    """``GET /v1/tracks?geometry=line``: each track's history as a LineString."""

    type: Literal["FeatureCollection"]
    features: list[TrackLineFeature]


class UavFeature(_Open):
    type: Literal["Feature"]
    id: str
    geometry: PointGeometry | PolygonGeometry
    properties: dict[str, object] = Field(description="kind (uav | footprint), id, t, and for uav: online, "
                                                      "last_seen, height_m, pitch_deg, heading_deg, rates")


class UavCollection(_Open):
    """``GET /v1/uavs?format=geojson``."""

    type: Literal["FeatureCollection"]
    features: list[UavFeature]


# ---- maps and tiles ---------------------------------------------------------------------------------------------

class SparseCells(BaseModel):
    row: list[int]
    col: list[int]
    value: list[float]


class JointMapWindow(_Open):
    """``GET /v1/map``: the joint map over a bbox on the shared grid (DESIGN.md 3)."""

    cls: str
    z: int
    n: int
    gx0: int = Field(description="global cell column of the window's west edge")
    gy0: int = Field(description="global cell row of the window's north edge")
    width: int
    height: int
    bbox: list[float] = Field(description="[west, south, east, north] of the window, degrees")
    cell_size_m: float
    t: float | None
    encoding: Literal["dense", "sparse"]
    values: list[list[float]] | None = Field(None, description="encoding=dense: rows north to south, [0, 1]")
    cells: SparseCells | None = Field(None, description="encoding=sparse: the non-zero cells")


class TileJson(_Open):
    """``GET /v1/tiles/{cls}.json`` (TileJSON 3.0.0)."""

    tilejson: str
    name: str
    description: str
    scheme: Literal["xyz"]
    tiles: list[str]
    minzoom: int
    maxzoom: int
    bounds: list[float]
    center: list[float]
    attribution: str


class JointTileInfo(_Open):
    """One row of ``GET /v1/joint/tiles``."""

    cls: str
    z: int
    x: int
    y: int
    t: float
    seq: int
    uavs: list[str]
    max: float


class BasemapConfig(_Open):
    """``GET /v1/basemap.json``."""

    url: str
    minzoom: int
    maxzoom: int
    attribution: str
    local: bool

"""The REST API's geographic formats beyond its own JSON: GeoJSON of UAVs and track lines, TileJSON.

Pure functions of the server's snapshots (lists and dicts), so GIS tools (QGIS, Leaflet, OpenLayers,
MapLibre) read the fleet directly. Coordinates are [lon, lat] as GeoJSON (RFC 7946) orders them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from fastapi.responses import JSONResponse

__all__ = ["GEOJSON_MEDIA_TYPE", "GeoJSONResponse", "tilejson", "track_line_feature", "track_lines_geojson",
           "uavs_geojson"]

GEOJSON_MEDIA_TYPE = "application/geo+json"


class GeoJSONResponse(JSONResponse):
    """JSON served as ``application/geo+json`` (RFC 7946), which GIS clients recognise."""

    media_type = GEOJSON_MEDIA_TYPE


def _ring(footprint: Sequence[Sequence[float]]) -> list[list[float]]:
    """A closed GeoJSON ring [[lon, lat], ...] from a footprint [[lat, lon], ...]."""
    ring = [[float(lon), float(lat)] for lat, lon in footprint]
    if ring and ring[0] != ring[-1]:
        ring.append(ring[0])
    return ring


def uavs_geojson(rows: Iterable[Mapping[str, Any]], *, footprints: bool = False) -> dict[str, Any]:
    """``/v1/uavs`` rows as a FeatureCollection: a Point per UAV with a known position.

    Properties: id, online, last_seen, height_m, pitch_deg, heading_deg, t (the state's time) and the
    message rates. UAVs without a state message yet are left out (no position). footprints: also a
    Polygon Feature per UAV (``kind: footprint``) with its camera's ground footprint (4 or more corners).
    """
    features: list[dict[str, Any]] = []
    for row in rows:
        state = row.get("state")
        if not state:
            continue
        properties = {
            "kind": "uav", "id": row["id"], "online": row["online"], "last_seen": row["last_seen"],
            "t": state["t"], "height_m": state["height_m"], "pitch_deg": state["pitch_deg"],
            "heading_deg": state["heading_deg"], "rates": row.get("rates", {}),
        }
        features.append({"type": "Feature", "id": row["id"], "properties": properties,
                         "geometry": {"type": "Point", "coordinates": [state["lon"], state["lat"]]}})
        ring = _ring(state.get("footprint") or ())
        if footprints and len(ring) >= 4:
            features.append({"type": "Feature", "id": f"{row['id']}/footprint",
                             "properties": {"kind": "footprint", "id": row["id"], "t": state["t"]},
                             "geometry": {"type": "Polygon", "coordinates": [ring]}})
    return {"type": "FeatureCollection", "features": features}


def track_lines_geojson(features: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Global tracks (the Point Features of ``/v1/tracks``) as LineStrings of their history.

    Each history ``[t, lat, lon]`` becomes a vertex ``[lon, lat]``; the times go to the ``times``
    property. A track with one history row is a LineString of that point twice (GeoJSON needs two
    positions); one without history is left out.
    """
    lines = (track_line_feature(feature) for feature in features)
    return {"type": "FeatureCollection", "features": [line for line in lines if line is not None]}


def track_line_feature(feature: Mapping[str, Any]) -> dict[str, Any] | None:
    """One `track_lines_geojson` LineString of a global track's Point Feature; None without history."""
    properties = dict(feature["properties"])
    history = properties.pop("history", None) or []
    if not history:
        return None
    coordinates = [[float(lon), float(lat)] for _t, lat, lon in history]
    if len(coordinates) == 1:
        coordinates.append(list(coordinates[0]))
    properties["times"] = [float(t) for t, _lat, _lon in history]
    return {"type": "Feature", "id": feature.get("id"), "properties": properties,
            "geometry": {"type": "LineString", "coordinates": coordinates}}


def tilejson(cls: str, tile_url: str, *, bounds: Sequence[float] | None, max_zoom: int,
             grid_zoom: int) -> dict[str, Any]:
    """TileJSON 3.0.0 for the heatmap tiles of one class.

    tile_url: the absolute URL template with ``{z}/{x}/{y}``. bounds: [west, south, east, north] of the
    class's joint tiles (None: the whole Web-Mercator world). Map clients center on the bounds.
    """
    west, south, east, north = bounds if bounds is not None else (-180.0, -85.0511, 180.0, 85.0511)
    return {
        "tilejson": "3.0.0",
        "name": f"uavmm joint map: {cls}",
        "description": f"Joint memory map of class {cls} (mean over the UAVs covering each cell), "
                       f"rendered at zoom {grid_zoom} and resampled at other zooms.",
        "scheme": "xyz",
        "tiles": [tile_url],
        "minzoom": 0,
        "maxzoom": max_zoom,
        "bounds": [west, south, east, north],
        "center": [(west + east) / 2, (south + north) / 2, grid_zoom - 2],
        "attribution": "uav-memory-maps",
    }

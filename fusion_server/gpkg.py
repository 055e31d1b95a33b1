"""A GeoPackage (OGC 12-128r18, version 1.3) writer for point and line layers, with the standard library.

A GeoPackage is an SQLite file with the OGC tables (``gpkg_spatial_ref_sys``, ``gpkg_contents``,
``gpkg_geometry_columns``) and geometries as GeoPackage binary (a small header + little-endian WKB):
QGIS, GDAL/OGR and ArcGIS open each feature table as a layer. WGS84 (EPSG:4326), x = lon, y = lat.
Features are written as they come (an iterable), so a layer of millions of rows is never held in memory.
"""

from __future__ import annotations

import math
import os
import re
import sqlite3
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

__all__ = ["Layer", "geometry_blob", "gpkg_datetime", "write_geopackage"]

APPLICATION_ID = 0x47504B47  # "GPKG"
USER_VERSION = 10300  # 1.3.0
_WGS84_WKT = (
    'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,AUTHORITY["EPSG","7030"]],'
    'AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0,AUTHORITY["EPSG","8901"]],'
    'UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],AUTHORITY["EPSG","4326"]]'
)
_TYPES = {"POINT": 1, "LINESTRING": 2}
_SQL_TYPES = {int: "INTEGER", float: "DOUBLE", str: "TEXT", bool: "BOOLEAN", datetime: "DATETIME"}
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_POINT_BLOB = struct.Struct("<2sBBi4dBI2d")  # `geometry_blob` of a point in one pack: header, envelope, WKB


@dataclass(frozen=True)
class Layer:
    """One feature table: its name, geometry type (POINT or LINESTRING), attribute columns and rows.

    columns: name -> Python type (int, float, str, bool, datetime). features: (coordinates, attributes)
    where coordinates is (lon, lat) for a point and a sequence of them for a line; attributes map column
    names to values (None allowed; a datetime column takes timezone-aware datetimes, stored as the
    GeoPackage DATETIME text, see `gpkg_datetime`). An iterator of features is read once, as written.
    """

    name: str
    geometry_type: str
    columns: Mapping[str, type]
    features: Iterable[tuple[Any, Mapping[str, Any]]] = field(default_factory=list)
    description: str = ""

    def __post_init__(self) -> None:
        if not _NAME.match(self.name) or self.name.lower().startswith("gpkg_"):
            raise ValueError(f"layer name must be an SQL identifier not starting with gpkg_, got {self.name!r}")
        if self.geometry_type not in _TYPES:
            raise ValueError(f"geometry_type must be one of {', '.join(_TYPES)}, got {self.geometry_type!r}")
        for name, kind in self.columns.items():
            if not _NAME.match(name) or name in ("fid", "geom"):
                raise ValueError(f"column name must be an SQL identifier other than fid/geom, got {name!r}")
            if kind not in _SQL_TYPES:
                raise ValueError(f"column {name}: type must be int, float, str, bool or datetime, got {kind!r}")


def _points(geometry_type: str, coordinates: Any) -> list[tuple[float, float]]:
    points = [coordinates] if geometry_type == "POINT" else list(coordinates)
    out = [(float(x), float(y)) for x, y in points]
    if not out or any(not (math.isfinite(x) and math.isfinite(y)) for x, y in out):
        raise ValueError(f"{geometry_type} coordinates must be finite, got {coordinates!r}")
    if geometry_type == "LINESTRING" and len(out) < 2:
        raise ValueError("a LINESTRING needs at least two positions")
    return out


def geometry_blob(geometry_type: str, coordinates: Any, srs_id: int = 4326) -> bytes:
    """GeoPackage binary of a point ``(x, y)`` or a line ``[(x, y), ...]``: header, xy envelope, WKB."""
    return _blob(geometry_type, _points(geometry_type, coordinates), srs_id)


def _blob(geometry_type: str, points: list[tuple[float, float]], srs_id: int = 4326) -> bytes:
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    flags = 0b0000_0011  # little endian, envelope [minx, maxx, miny, maxy]
    header = b"GP" + struct.pack("<BBi4d", 0, flags, srs_id, min(xs), max(xs), min(ys), max(ys))
    if geometry_type == "POINT":
        wkb = struct.pack("<BI2d", 1, _TYPES["POINT"], *points[0])
    else:
        wkb = struct.pack("<BII", 1, _TYPES["LINESTRING"], len(points)) + b"".join(
            struct.pack("<2d", x, y) for x, y in points)
    return header + wkb


def gpkg_datetime(when: datetime) -> str:
    """A timezone-aware datetime as GeoPackage 1.3 DATETIME text, ``YYYY-MM-DDTHH:MM:SS.SSSZ`` (UTC, the
    milliseconds truncated): what GDAL, and QGIS through it, read as a DateTime field. ValueError if naive."""
    if when.tzinfo is None:
        raise ValueError(f"a GeoPackage DATETIME needs a timezone-aware datetime, got {when!r}")
    utc = when.astimezone(timezone.utc)
    return f"{utc:%Y-%m-%dT%H:%M:%S}.{utc.microsecond // 1000:03d}Z"


def _now() -> str:
    return gpkg_datetime(datetime.now(timezone.utc))


def write_geopackage(path: str | Path, layers: Iterable[Layer]) -> dict[str, int]:
    """Write ``layers`` to a new GeoPackage at ``path``; returns the number of features per layer.

    Written to a hidden temporary beside ``path``, renamed over it on success: an existing file is replaced only
    then, and a failure (a full disk, a folder it may not write) leaves neither a half-written file nor the
    temporary. OSError naming ``path`` when the file cannot be written; FileNotFoundError when its folder does
    not exist; ValueError for a bad geometry (and whatever the layers' feature iterators raise, unchanged).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"output directory {path.parent} does not exist (for {path})")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # two exports to one file: each its own
    counts: dict[str, int] = {}
    try:
        tmp.unlink(missing_ok=True)
        conn = sqlite3.connect(tmp)
    except (OSError, sqlite3.Error) as exc:
        raise OSError(f"cannot write {path}: {exc}") from None
    try:
        # a new file thrown away on failure needs no rollback journal on disk (one could outlive a failed write)
        conn.execute("PRAGMA journal_mode = MEMORY")
        with conn:
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version = {USER_VERSION}")
            conn.executescript("""
                CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY,
                    organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL,
                    definition TEXT NOT NULL, description TEXT);
                CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
                    identifier TEXT UNIQUE, description TEXT DEFAULT '',
                    last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
                    min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
                    CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
                CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
                    geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL,
                    m TINYINT NOT NULL, CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
                    CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
                    CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
            """)
            conn.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", [
                ("Undefined cartesian SRS", -1, "NONE", -1, "undefined", "undefined cartesian coordinate reference"),
                ("Undefined geographic SRS", 0, "NONE", 0, "undefined", "undefined geographic coordinate reference"),
                ("WGS 84 geodetic", 4326, "EPSG", 4326, _WGS84_WKT, "longitude/latitude coordinates in decimal "
                 "degrees on the WGS 84 spheroid"),
            ])
            for layer in layers:
                counts[layer.name] = _write_layer(conn, layer)
        conn.close()
        tmp.replace(path)
    except _FeatureError as exc:  # the caller's (e.g. reading its source), passed on as raised
        conn.close()
        tmp.unlink(missing_ok=True)
        raise exc.error from None
    except (sqlite3.Error, OSError) as exc:  # the output's own: a full disk, a folder it may not write
        conn.close()
        tmp.unlink(missing_ok=True)  # nothing half-written is left behind
        raise OSError(f"cannot write {path}: {exc}") from None
    except BaseException:
        conn.close()
        tmp.unlink(missing_ok=True)
        raise
    return counts


def _write_layer(conn: sqlite3.Connection, layer: Layer) -> int:
    columns = "".join(f', "{name}" {_SQL_TYPES[kind]}' for name, kind in layer.columns.items())
    conn.execute(f'CREATE TABLE "{layer.name}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom {layer.geometry_type}'
                 f"{columns})")
    names = list(layer.columns)
    placeholders = ", ".join("?" * (len(names) + 1))
    quoted = "".join(f', "{n}"' for n in names)
    bounds = [math.inf, math.inf, -math.inf, -math.inf]  # min x, min y, max x, max y
    count = 0

    def rows() -> Iterator[tuple[Any, ...]]:  # one at a time into executemany: a layer is never a list
        nonlocal count
        dates = [i for i, n in enumerate(names) if layer.columns[n] is datetime]
        point = layer.geometry_type == "POINT"
        features = iter(layer.features)
        while True:
            try:
                coordinates, attributes = next(features)
            except StopIteration:
                return
            except Exception as exc:
                raise _FeatureError(exc) from exc
            if point:  # the common case (a point per history row), without the line's lists
                ((x, y),) = _points("POINT", coordinates)
                blob = _POINT_BLOB.pack(b"GP", 0, 0b11, 4326, x, x, y, y, 1, _TYPES["POINT"], x, y)
                bounds[:] = (min(bounds[0], x), min(bounds[1], y), max(bounds[2], x), max(bounds[3], y))
            else:
                points = _points(layer.geometry_type, coordinates)
                xs, ys = [p[0] for p in points], [p[1] for p in points]
                bounds[:] = (min(bounds[0], *xs), min(bounds[1], *ys), max(bounds[2], *xs), max(bounds[3], *ys))
                blob = _blob(layer.geometry_type, points)
            values = [attributes.get(n) for n in names]
            for i in dates:
                if values[i] is not None:
                    values[i] = _encode_datetime(values[i])
            count += 1
            yield (blob, *values)

    conn.executemany(f'INSERT INTO "{layer.name}" (geom{quoted}) VALUES ({placeholders})', rows())
    extent: list[float | None] = list(bounds) if count else [None, None, None, None]
    conn.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, description, last_change, min_x, "
                 "min_y, max_x, max_y, srs_id) VALUES (?, 'features', ?, ?, ?, ?, ?, ?, ?, 4326)",
                 (layer.name, layer.name, layer.description, _now(), *extent))
    conn.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, 4326, 0, 0)",
                 (layer.name, layer.geometry_type))
    return count


class _FeatureError(Exception):
    """An exception a layer's features raised: not the output's, so neither wrapped nor renamed."""

    def __init__(self, error: Exception) -> None:
        super().__init__(str(error))
        self.error = error


def _encode_datetime(value: Any) -> str:
    if not isinstance(value, datetime):
        raise ValueError(f"a DATETIME column takes datetimes, got {value!r}")
    return gpkg_datetime(value)

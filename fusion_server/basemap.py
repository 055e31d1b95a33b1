"""A basemap under the live map page: an XYZ tile URL, or an MBTiles file served by the fusion server itself.

A ground station is often offline: an MBTiles file (one SQLite file of map tiles, e.g. exported from
QGIS, TileMill or a survey's orthophoto) is served at ``/v1/basemap/{z}/{x}/{y}``. An ``http(s)://``
template with ``{z}``, ``{x}`` and ``{y}`` is handed to the page as it is (the browser fetches it).
"""

from __future__ import annotations

import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["Basemap", "MBTiles", "open_basemap"]

_MEDIA_TYPES = {"png": "image/png", "jpg": "image/jpeg", "jpeg": "image/jpeg", "webp": "image/webp"}


class MBTiles:
    """Read-only tiles of an MBTiles 1.x file (TMS rows: y is flipped from the XYZ scheme).

    Raises ValueError naming the file when it is missing, not SQLite, or has no ``tiles`` table.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise ValueError(f"basemap {self.path} does not exist")
        try:
            self._conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
            metadata = dict(self._conn.execute("SELECT name, value FROM metadata").fetchall())
            zooms = self._conn.execute("SELECT min(zoom_level), max(zoom_level) FROM tiles").fetchone()
        except sqlite3.DatabaseError as exc:
            raise ValueError(f"basemap {self.path} is not an MBTiles file ({exc})") from None
        self._lock = threading.Lock()
        fmt = str(metadata.get("format", "png")).lower()
        if fmt not in _MEDIA_TYPES:
            raise ValueError(f"basemap {self.path}: tile format {fmt!r} is not an image ({', '.join(_MEDIA_TYPES)})")
        self.media_type = _MEDIA_TYPES[fmt]
        self.min_zoom = int(metadata.get("minzoom", zooms[0] if zooms[0] is not None else 0))
        self.max_zoom = int(metadata.get("maxzoom", zooms[1] if zooms[1] is not None else 22))
        self.attribution = str(metadata.get("attribution", metadata.get("name", self.path.stem)))

    def tile(self, z: int, x: int, y: int) -> bytes | None:
        """The tile at XYZ z/x/y, or None where the file has none."""
        if not 0 <= z <= 30 or not (0 <= x < (1 << z) and 0 <= y < (1 << z)):
            return None
        with self._lock:
            row = self._conn.execute(
                "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? AND tile_row = ?",
                (z, x, (1 << z) - 1 - y)).fetchone()
        return bytes(row[0]) if row else None

    def close(self) -> None:
        self._conn.close()


@dataclass
class Basemap:
    """What the page draws under the map: a tile URL template, zooms and an attribution."""

    url: str
    min_zoom: int = 0
    max_zoom: int = 19
    attribution: str = ""
    mbtiles: MBTiles | None = None

    def page_config(self) -> dict[str, Any]:
        return {"url": self.url, "minzoom": self.min_zoom, "maxzoom": self.max_zoom,
                "attribution": self.attribution, "local": self.mbtiles is not None}


def open_basemap(spec: str, attribution: str | None = None) -> Basemap:
    """A basemap from ``--basemap``: an ``http(s)://`` template with {z}, {x}, {y}, or an MBTiles file.

    ValueError naming what is wrong (a template without its placeholders, a missing or bad file).
    """
    if spec.startswith(("http://", "https://")):
        missing = [p for p in ("{z}", "{x}", "{y}") if p not in spec]
        if missing:
            raise ValueError(f"--basemap URL must contain {', '.join(missing)}, got {spec!r}")
        return Basemap(spec, attribution=attribution or "")
    if not spec.lower().endswith(".mbtiles"):
        raise ValueError(f"--basemap must be an http(s):// tile URL with {{z}}/{{x}}/{{y}} or a .mbtiles file, "
                         f"got {spec!r}")
    tiles = MBTiles(spec)
    return Basemap("/v1/basemap/{z}/{x}/{y}", tiles.min_zoom, tiles.max_zoom,
                   attribution if attribution is not None else tiles.attribution, tiles)

"""KML 2.2 (Google Earth, QGIS, ATAK) from GeoJSON FeatureCollections: Points, LineStrings and Polygons.

Each Feature becomes a Placemark named after its id (or a property), its properties listed in
ExtendedData; a feature with ``times`` (track lines) gets a TimeSpan, one with ``t`` a TimeStamp.
KMZ is the same document zipped as ``doc.kml`` (what ATAK data packages and Google Earth exchange), with ZIP64 only
past 2 GiB of KML.
"""

from __future__ import annotations

import io
import json
import re
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from datetime import datetime, timezone
from typing import IO, Any

__all__ = ["KML_MEDIA_TYPE", "KMZ_MEDIA_TYPE", "feature_collections_kml", "kml_chunks", "kmz", "write_kmz"]

KML_MEDIA_TYPE = "application/vnd.google-earth.kml+xml"
KMZ_MEDIA_TYPE = "application/vnd.google-earth.kmz"
_NS = "http://www.opengis.net/kml/2.2"


def _when(t: float) -> str:
    return datetime.fromtimestamp(float(t), timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _coordinates(positions: Iterable[Iterable[float]]) -> str:
    return " ".join(f"{lon:.7f},{lat:.7f}" for lon, lat, *_ in positions)


def _geometry(parent: ET.Element, geometry: Mapping[str, Any]) -> None:
    kind = geometry["type"]
    if kind == "Point":
        ET.SubElement(ET.SubElement(parent, "Point"), "coordinates").text = _coordinates([geometry["coordinates"]])
    elif kind == "LineString":
        line = ET.SubElement(parent, "LineString")
        ET.SubElement(line, "tessellate").text = "1"
        ET.SubElement(line, "coordinates").text = _coordinates(geometry["coordinates"])
    elif kind == "Polygon":
        polygon = ET.SubElement(parent, "Polygon")
        for index, ring in enumerate(geometry["coordinates"]):
            boundary = ET.SubElement(polygon, "outerBoundaryIs" if index == 0 else "innerBoundaryIs")
            ET.SubElement(ET.SubElement(boundary, "LinearRing"), "coordinates").text = _coordinates(ring)
    else:
        raise ValueError(f"KML export supports Point, LineString and Polygon, got {kind!r}")


_NCNAME = re.compile(r"[A-Za-z_][\w.\-]*\Z", re.ASCII)  # xsd:ID, what a KML Placemark's id is


def _xml_id(value: Any) -> str:
    """A feature's id as a valid XML id: as it is when it is one (`track-12`), else its other characters made '-'
    and, when it does not start with a letter or '_', 'id-' in front (a UAV `3dr/footprint` -> `id-3dr-footprint`)."""
    text = str(value)
    if _NCNAME.match(text):
        return text
    text = re.sub(r"[^\w.\-]", "-", text, flags=re.ASCII)
    return text if _NCNAME.match(text) else f"id-{text}"


def _placemark(folder: ET.Element, feature: Mapping[str, Any]) -> None:
    props = feature.get("properties") or {}
    mark = ET.SubElement(folder, "Placemark", {"id": _xml_id(feature.get("id", ""))} if "id" in feature else {})
    label = props.get("cls")
    name = f"{label} {props['gid']}" if label is not None and "gid" in props else str(
        props.get("id", feature.get("id", "")))
    ET.SubElement(mark, "name").text = name
    times = props.get("times")
    if times:
        span = ET.SubElement(mark, "TimeSpan")
        ET.SubElement(span, "begin").text = _when(min(times))
        ET.SubElement(span, "end").text = _when(max(times))
    elif props.get("t") is not None:
        ET.SubElement(ET.SubElement(mark, "TimeStamp"), "when").text = _when(props["t"])
    data = ET.SubElement(mark, "ExtendedData")
    for key, value in props.items():
        if key in ("times", "history"):
            continue
        item = ET.SubElement(data, "Data", {"name": str(key)})
        text = value if isinstance(value, str) else json.dumps(value)
        ET.SubElement(item, "value").text = text
    _geometry(mark, feature["geometry"])


def feature_collections_kml(name: str, folders: Mapping[str, Mapping[str, Any]]) -> bytes:
    """A KML document with one Folder per FeatureCollection (``{folder name: collection}``)."""
    return b"".join(kml_chunks(name, {k: c.get("features", ()) for k, c in folders.items()}))


def kml_chunks(name: str, folders: Mapping[str, Iterable[Mapping[str, Any]]]) -> Iterator[bytes]:
    """`feature_collections_kml`'s bytes piece by piece, one Placemark at a time, from ``{folder name: features}``
    (iterables: a long video's tracks are never held as one document)."""
    kml = ET.Element("kml", {"xmlns": _NS})
    document = ET.SubElement(kml, "Document")
    ET.SubElement(document, "name").text = name
    for i, folder_name in enumerate(folders):
        folder = ET.SubElement(document, "Folder")
        ET.SubElement(folder, "name").text = folder_name
        ET.SubElement(folder, f"slot{i}")  # where the folder's placemarks go, cut out below
    text = ET.tostring(kml, encoding="utf-8")
    yield b'<?xml version="1.0" encoding="UTF-8"?>\n'
    for i, features in enumerate(folders.values()):
        head, text = text.split(f"<slot{i} />".encode(), 1)
        yield head
        for feature in features:
            holder = ET.Element("Folder")
            _placemark(holder, feature)
            yield ET.tostring(holder[0], encoding="utf-8")
    yield text


def _doc_kml() -> zipfile.ZipInfo:
    info = zipfile.ZipInfo("doc.kml", date_time=(1980, 1, 1, 0, 0, 0))  # fixed: same input, same bytes
    info.compress_type = zipfile.ZIP_DEFLATED
    return info


def kmz(kml: bytes) -> bytes:
    """A KMZ archive (ZIP, deflated) holding the KML document as ``doc.kml``, the name readers open first."""
    buffer = io.BytesIO()
    write_kmz(buffer, lambda: [kml])
    return buffer.getvalue()


def write_kmz(file: IO[bytes], document: Callable[[], Iterable[bytes]], *,
              zip64_over: int = zipfile.ZIP64_LIMIT) -> bool:
    """`kmz` of the document given piece by piece (``document()``: `kml_chunks`), written to a binary file as it
    comes: the same bytes as ``kmz(b"".join(document()))`` without holding the document.

    ZIP64 only where it is needed: a document of more than ``zip64_over`` bytes (zipfile's limit without ZIP64,
    2 GiB) is written again from its start with the ZIP64 extensions, calling ``document`` a second time (a stream
    cannot know its size in advance, and a header written without ZIP64 has no room for it). Not always ZIP64:
    libkml (GDAL's LIBKML driver, which opens a .kmz) does not open a ZIP64 archive, even a small one. Returns
    True when the archive was written with ZIP64. A file that cannot seek (a pipe) gets one pass without ZIP64, as
    before (OSError past the limit).
    """
    if not file.seekable():
        try:
            _write_doc_kml(file, document(), zip64=False, limit=None)
        except RuntimeError as exc:  # zipfile: "File size too large, try using force_zip64"
            raise OSError(f"the KML is over 2 GiB, more than a KMZ streamed to a file that cannot seek holds ({exc}); "
                          "write .kml, or the KMZ to a file") from None
        return False
    start = file.tell()
    if _write_doc_kml(file, document(), zip64=False, limit=zip64_over):
        return False
    file.seek(start)
    file.truncate()
    _write_doc_kml(file, document(), zip64=True, limit=None)
    return True


def _write_doc_kml(file: IO[bytes], chunks: Iterable[bytes], *, zip64: bool, limit: int | None) -> bool:
    """One archive of the chunks as ``doc.kml``; False (the archive then holds a part) once they pass ``limit``
    bytes. The deflated KML is smaller than its text, so the text's size is the one that can reach the limit."""
    size = 0
    with zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED) as archive, \
            archive.open(_doc_kml(), "w", force_zip64=zip64) as member:
        for chunk in chunks:
            size += len(chunk)
            if limit is not None and size > limit:
                return False
            member.write(chunk)
    return True

"""shared.kml's KMZ written as it streams: ZIP64 exactly when the KML passes zipfile's limit without it (2 GiB, lowered
here through `write_kmz`'s own parameter), read back by zipfile (and Info-ZIP's unzip where installed)."""

from __future__ import annotations

import shutil
import struct
import subprocess
import zipfile
from pathlib import Path

import pytest

from shared.kml import kml_chunks, kmz, write_kmz

LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")  # signature, version needed, flags, method, time, date, crc, sizes...


def _document(calls: list[int]):
    """A track line's KML as `kml_chunks` makes it (~6 KB), and a count of the times it was asked for."""
    feature = {"type": "Feature", "id": "track-1-path", "properties": {"gid": 1, "cls": "person",
                                                                        "times": [1.79e9, 1.79e9 + 199]},
               "geometry": {"type": "LineString", "coordinates": [[9.05 + 1e-5 * k, 48.5] for k in range(200)]}}

    def document():
        calls.append(1)
        return kml_chunks("t", {"lines": [feature]})

    return document


def _local_header(path: Path) -> tuple[int, int, int, bytes]:
    """(version needed, compressed size, size, extra field) of the archive's first local file header."""
    data = path.read_bytes()
    _sig, version, _flags, _method, _time, _date, _crc, csize, usize, name_len, extra_len = \
        LOCAL_HEADER.unpack_from(data)
    start = LOCAL_HEADER.size + name_len
    return version, csize, usize, data[start:start + extra_len]


def test_a_kmz_past_the_limit_is_zip64_and_reads_back(tmp_path):
    """Past zipfile's limit without ZIP64 (2 GiB of KML) a streamed KMZ was refused (OSError, exit 2 from `uavmm
    export`): it is written again, from the start, with the ZIP64 extensions."""
    calls: list[int] = []
    document = _document(calls)
    text = b"".join(document())
    out = tmp_path / "big.kmz"
    with out.open("wb") as file:
        assert write_kmz(file, document, zip64_over=len(text) - 1) is True
    assert len(calls) == 1 + 2  # the oracle's, the one cut at the limit, the ZIP64 one
    version, csize, usize, extra = _local_header(out)
    assert version == 45 and csize == usize == 0xFFFFFFFF  # ZIP64: the sizes are in the extra field
    header_id, size, zip64_usize, zip64_csize = struct.unpack("<HHQQ", extra)
    assert (header_id, size, zip64_usize) == (0x0001, 16, len(text)) and 0 < zip64_csize < len(text)
    with zipfile.ZipFile(out) as archive:
        assert archive.namelist() == ["doc.kml"]
        assert archive.read("doc.kml") == text  # CRC checked
    if shutil.which("unzip"):
        check = subprocess.run(["unzip", "-t", str(out)], capture_output=True, text=True, timeout=60)
        assert check.returncode == 0 and "No errors detected" in check.stdout, check.stdout + check.stderr


@pytest.mark.parametrize("margin", [0, 1000])
def test_a_kmz_within_the_limit_has_no_zip64(tmp_path, margin):
    """libkml (GDAL's LIBKML driver, which opens a .kmz) does not open a ZIP64 archive, even a small one: ZIP64 only
    when needed, and below the limit (up to it exactly) the bytes `kmz` makes, written once."""
    calls: list[int] = []
    document = _document(calls)
    text = b"".join(document())
    out = tmp_path / "small.kmz"
    with out.open("wb") as file:
        assert write_kmz(file, document, zip64_over=len(text) + margin) is False
    assert len(calls) == 2
    assert out.read_bytes() == kmz(text)
    version, csize, usize, extra = _local_header(out)
    assert version == 20 and usize == len(text) and csize < usize and extra == b""


def test_a_kmz_written_after_other_bytes_starts_over_where_it_began(tmp_path):
    """The ZIP64 rewrite goes back to where the archive began in the file, not to the file's start."""
    calls: list[int] = []
    document = _document(calls)
    text = b"".join(document())
    out = tmp_path / "after.bin"
    with out.open("wb") as file:
        file.write(b"HEAD")
        assert write_kmz(file, document, zip64_over=100)
    data = out.read_bytes()
    assert data[:4] == b"HEAD"
    with zipfile.ZipFile(out) as archive:  # zipfile finds the archive behind the prefix
        assert archive.read("doc.kml") == text


def test_a_kmz_streams_to_a_file_that_cannot_seek(tmp_path):
    # review probe: the two-pass writer asked the file where it stood and raised "Illegal seek" on a pipe, where the
    # one-pass writer before it wrote the archive
    import os
    import threading

    read_end, write_end = os.pipe()
    received = bytearray()
    reader = threading.Thread(target=lambda: received.extend(os.fdopen(read_end, "rb").read()))
    reader.start()
    calls: list[int] = []
    with os.fdopen(write_end, "wb") as pipe:
        assert not pipe.seekable()
        assert write_kmz(pipe, _document(calls)) is False
    reader.join(timeout=30)
    (tmp_path / "piped.kmz").write_bytes(bytes(received))
    with zipfile.ZipFile(tmp_path / "piped.kmz") as archive:
        assert archive.read("doc.kml") == b"".join(_document([])())
    assert calls == [1]


def test_a_kmz_past_the_limit_on_a_pipe_is_one_line_not_a_traceback(monkeypatch):
    # last read: the one-pass branch for a file that cannot seek let zipfile's RuntimeError out (uavmm's CLI turns
    # OSError into one line); zipfile's own limit lowered as the stand-in for 2 GiB
    import os

    monkeypatch.setattr(zipfile, "ZIP64_LIMIT", 1000)
    read_end, write_end = os.pipe()
    with os.fdopen(read_end, "rb") as drain, os.fdopen(write_end, "wb") as pipe:
        os.set_blocking(read_end, False)
        with pytest.raises(OSError, match="over 2 GiB"):
            write_kmz(pipe, _document([]))
        drain.read()


def test_placemark_ids_are_valid_xml_ids_whatever_the_feature_ids():
    # left open: /v1/uavs?format=kml&footprints=true wrote ids `UAV/footprint` ('/' is no XML id character), and a
    # UAV id may start with a digit; ids that are valid stay as they are (the exports' track-GID)
    import re
    import xml.etree.ElementTree as ET

    from shared.kml import feature_collections_kml

    def point(fid):
        return {"type": "Feature", "id": fid, "properties": {"id": str(fid)},
                "geometry": {"type": "Point", "coordinates": [9.05, 48.5]}}

    ids = ["uav1", "uav1/footprint", "3dr", "3dr/footprint", "track-12", 7, "dji mini"]
    root = ET.fromstring(feature_collections_kml("t", {"f": {"type": "FeatureCollection",
                                                             "features": [point(i) for i in ids]}}))
    got = [m.get("id") for m in root.iter("{http://www.opengis.net/kml/2.2}Placemark")]
    assert got == ["uav1", "uav1-footprint", "id-3dr", "id-3dr-footprint", "track-12", "id-7", "dji-mini"]
    assert all(re.fullmatch(r"[A-Za-z_][\w.\-]*", g, re.ASCII) for g in got) and len(set(got)) == len(got)

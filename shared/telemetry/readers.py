"""Reading a telemetry file of any supported format, chosen by its extension."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.telemetry.csv_table import read_csv
from shared.telemetry.klv import KLV_FILE_SUFFIXES, read_klv
from shared.telemetry.record import Telemetry
from shared.telemetry.seadronessee import read_seadronessee_json
from shared.telemetry.srt import read_srt
from shared.telemetry.tlog import read_tlog
from shared.telemetry.ulog import read_ulog


def read_telemetry(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read telemetry, choosing the reader by file extension.

    ``.srt`` -> `read_srt`, ``.csv`` -> `read_csv`, ``.json`` -> `read_seadronessee_json` (SeaDronesSee
    COCO ``images[*].meta``, ordered by ``frame_index``), ``.tlog`` -> `read_tlog` (MAVLink), ``.ulg`` ->
    `read_ulog` (PX4), ``.ts``, ``.m2ts``, ``.mts`` (MPEG-TS video with MISB ST 0601 KLV metadata) and ``.klv``
    (raw ST 0601 packets) -> `read_klv`. Keyword arguments go to the reader.

    Raises
    ------
    ValueError
        For another extension, or whatever the reader rejects.
    """
    readers: dict[str, Callable[..., list[Telemetry]]] = {
        ".srt": read_srt, ".csv": read_csv, ".json": read_seadronessee_json, ".tlog": read_tlog, ".ulg": read_ulog,
        **dict.fromkeys(KLV_FILE_SUFFIXES, read_klv),
    }
    suffix = Path(path).suffix.lower()
    if suffix not in readers:
        raise ValueError(f"{path}: unknown telemetry format {suffix!r} (supported: {', '.join(readers)})")
    return readers[suffix](path, **kw)

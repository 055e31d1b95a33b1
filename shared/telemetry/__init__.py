"""Drone telemetry ingestion: one validated `Telemetry` record per sample from DJI SRT, CSV and SeaDronesSee meta.

Also interpolates telemetry to video frame times and writes SeaDronesSee meta; angles follow DESIGN.md 2.
One module per concept: `record` (the record, DJI pitch), `dates`, `srt` (with `srt_blocks` and
`srt_clock`), `csv_table`, `seadronessee` (which video an image is of: `seadronessee_videos`), `mavlink`
(MAVLink messages, with `mavlink_clock`), `tlog` (MAVLink `.tlog`), `ulog` (PX4 `.ulg`), `gimbal_track` and
`recording` (a flight log's gimbal and camera recording, for both), `klv` (MISB ST 0601 KLV in MPEG-TS or raw,
with `mpegts`, `klv_packets` and `klv_sample`), `readers` (by extension) and `interpolation`; the public names are
re-exported here.
"""

from shared.telemetry.csv_table import CSV_COLUMNS, parse_csv, read_csv
from shared.telemetry.dates import parse_datetime
from shared.telemetry.interpolation import interpolate
from shared.telemetry.klv import KLV_FILE_SUFFIXES, KlvReport, parse_klv_report, read_klv, read_klv_report
from shared.telemetry.klv_sample import KlvSample, camera_angles_deg
from shared.telemetry.mavlink import MavlinkAssembler, MavlinkByteParser, MavlinkSample
from shared.telemetry.readers import read_telemetry
from shared.telemetry.record import (
    NO_HEIGHT_MESSAGE,
    PITCH_TOLERANCE_DEG,
    Telemetry,
    pitch_from_dji,
    recording_start,
)
from shared.telemetry.seadronessee import (
    SEADRONESSEE_META_FIELDS,
    from_seadronessee_meta,
    parse_seadronessee_coco,
    read_seadronessee_json,
    to_seadronessee_meta,
)
from shared.telemetry.srt import SrtReport, parse_srt, parse_srt_report, read_srt, read_srt_report
from shared.telemetry.tlog import parse_tlog, read_tlog, read_tlog_report
from shared.telemetry.ulog import read_ulog, read_ulog_report

__all__ = [
    "CSV_COLUMNS",
    "KLV_FILE_SUFFIXES",
    "KlvReport",
    "KlvSample",
    "MavlinkAssembler",
    "MavlinkByteParser",
    "MavlinkSample",
    "NO_HEIGHT_MESSAGE",
    "PITCH_TOLERANCE_DEG",
    "SEADRONESSEE_META_FIELDS",
    "SrtReport",
    "Telemetry",
    "camera_angles_deg",
    "from_seadronessee_meta",
    "interpolate",
    "parse_csv",
    "parse_klv_report",
    "parse_datetime",
    "parse_seadronessee_coco",
    "parse_srt",
    "parse_srt_report",
    "parse_tlog",
    "pitch_from_dji",
    "read_csv",
    "read_klv",
    "read_klv_report",
    "read_seadronessee_json",
    "read_srt",
    "read_srt_report",
    "read_telemetry",
    "read_tlog",
    "read_tlog_report",
    "read_ulog",
    "read_ulog_report",
    "recording_start",
    "to_seadronessee_meta",
]

"""Telemetry files beside a rendered video: DJI-style SRT subtitles and a CSV table, one record per frame.

The records are the dataset's NOISY telemetry (each image's SeaDronesSee ``meta``), stamped with the frame's
time, as a drone logs them: a DJI SRT carries one block per video frame with the latest telemetry sample.
Frames whose image has no meta (SeaDronesSee-style dropouts) repeat the previous frame's telemetry (the first
frames take the first available one): a drone's log has no gaps, and `uavmm agent --video` takes video time 0
from the first record. Both files parse with `shared.telemetry.read_telemetry`.

SRT precision is DJI's (lat/lon 6 decimals ~0.1 m, heights 3, angles 1); the CSV keeps the meta's precision.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import replace
from datetime import datetime, timezone
from typing import Any

from shared.telemetry import Telemetry, from_seadronessee_meta

#: Nominal take-off elevation above sea level added to the height for the SRT's abs_alt (metres).
ABS_ALT_OFFSET_M = 400.0
#: CSV columns written (names `shared.telemetry.read_csv` knows).
CSV_HEADER = ("frame", "time_s", "date_time", "lat", "lon", "height_m", "pitch_deg", "heading_deg", "roll_deg",
              "speed_mps")


def frame_records(frames: Sequence[tuple[int, float, dict[str, Any] | None]]) -> list[Telemetry]:
    """One telemetry record per frame from (frame_index, frame time in UNIX seconds, meta or None).

    Record i has t = the frame's time and frame = its index; its values come from the frame's meta, or
    for a frame without meta from the previous frame's record (the first available one before any).

    Raises
    ------
    ValueError
        When no frame has meta (nothing to write), or a meta cannot be read (naming the frame).
    """
    values: list[Telemetry | None] = []
    for frame_index, _, meta in frames:
        if meta is None:
            values.append(None)
            continue
        try:
            record = from_seadronessee_meta(meta, frame_index)
        except ValueError as exc:
            raise ValueError(f"frame {frame_index}: unusable meta: {exc}") from None
        values.append(record)
    known = [v for v in values if v is not None]
    if not known:
        raise ValueError("no frame of the video has telemetry (meta): nothing to write")
    held: Telemetry = known[0]
    out = []
    for (frame_index, t, _), value in zip(frames, values, strict=True):
        held = value if value is not None else held
        out.append(replace(held, t=float(t), frame=int(frame_index)))
    return out


def _srt_clock(seconds: float) -> str:
    ms = int(round(seconds * 1000.0))
    return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"


def _srt_date(t_unix: float) -> str:
    ms = int(round(t_unix * 1000.0))
    stamp = datetime.fromtimestamp(ms // 1000, tz=timezone.utc)
    return stamp.strftime("%Y-%m-%d %H:%M:%S") + f".{ms % 1000:03d}"


def format_srt(records: Sequence[Telemetry], fps: float) -> str:
    """DJI SRT text (Mini 3 / Mavic 3 style, UTC date lines): one block per record, record i at i / fps.

    Each block: index, timing line, ``FrameCnt``/``DiffTime``, the date-time, camera settings, ``latitude``,
    ``longitude``, ``rel_alt``/``abs_alt`` and the gimbal (``gb_yaw`` in -180..180, ``gb_pitch`` negative down).
    """
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps!r}")
    diff_ms = int(round(1000.0 / fps))
    blocks = []
    for i, r in enumerate(records):
        if r.height_m is None or r.pitch_deg is None or r.heading_deg is None:
            raise ValueError(f"record {i} lacks height, pitch or heading: the SRT writer needs all three")
        yaw = (r.heading_deg + 180.0) % 360.0 - 180.0
        blocks.append(
            f"{i + 1}\n{_srt_clock(i / fps)} --> {_srt_clock((i + 1) / fps)}\n"
            f'<font size="28">FrameCnt: {i + 1}, DiffTime: {diff_ms}ms\n{_srt_date(r.t)}\n'
            f"[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [color_md: default] [focal_len: 24.00] "
            f"[latitude: {r.lat:.6f}] [longitude: {r.lon:.6f}] "
            f"[rel_alt: {r.height_m:.3f} abs_alt: {r.height_m + ABS_ALT_OFFSET_M:.3f}] "
            f"[gb_yaw: {yaw:.1f} gb_pitch: {-r.pitch_deg:.1f} gb_roll: {r.roll_deg:.1f}] </font>\n"
        )
    return "\n".join(blocks)


def format_csv(records: Sequence[Telemetry], t0: float) -> str:
    """CSV text with `CSV_HEADER`: time_s = seconds since `t0` (video start), date_time ISO 8601 UTC."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for r in records:
        ms = int(round(r.t * 1000.0))
        iso = datetime.fromtimestamp(ms // 1000, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S") + f".{ms % 1000:03d}Z"
        writer.writerow([r.frame, f"{r.t - t0:.6f}", iso, f"{r.lat:.9f}", f"{r.lon:.9f}", _num(r.height_m),
                         _num(r.pitch_deg), _num(r.heading_deg), _num(r.roll_deg), _num(r.speed_mps)])
    return buf.getvalue()


def _num(value: float | None) -> str:
    return "" if value is None else repr(round(float(value), 6))

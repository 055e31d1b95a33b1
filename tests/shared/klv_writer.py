"""Test data for the KLV reader: MISB ST 0601 packets and MPEG transport streams, written from the standards.

Independent of the reader's code: its own mapping table (ST 0601 section 8), the checksum loop as the standard
prints it, a CRC-32/MPEG-2 done bit by bit, and a small TS multiplexer (PAT, PMT, PES with PTS; ISO 13818-1)
for what a real muxer cannot be made to write (synchronous metadata with AU cells, broken packets).
A real muxer, PyAV's FFmpeg, writes the asynchronous streams (`write_ts_with_pyav`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

KEY = bytes.fromhex("060E2B34020B01010E01030101000000")

#: field -> (tag, bytes, lo, hi, signed), from ST 0601's item table.
SPEC: dict[str, tuple[int, int, float, float, bool]] = {
    "platform_heading_deg": (5, 2, 0.0, 360.0, False),
    "platform_pitch_deg": (6, 2, -20.0, 20.0, True),
    "platform_roll_deg": (7, 2, -50.0, 50.0, True),
    "sensor_lat": (13, 4, -90.0, 90.0, True),
    "sensor_lon": (14, 4, -180.0, 180.0, True),
    "sensor_alt_msl_m": (15, 2, -900.0, 19000.0, False),
    "hfov_deg": (16, 2, 0.0, 180.0, False),
    "vfov_deg": (17, 2, 0.0, 180.0, False),
    "sensor_rel_azimuth_deg": (18, 4, 0.0, 360.0, False),
    "sensor_rel_elevation_deg": (19, 4, -180.0, 180.0, True),
    "sensor_rel_roll_deg": (20, 4, 0.0, 360.0, False),
    "frame_center_lat": (23, 4, -90.0, 90.0, True),
    "frame_center_lon": (24, 4, -180.0, 180.0, True),
    "frame_center_elevation_m": (25, 2, -900.0, 19000.0, False),
    "sensor_hae_m": (75, 2, -900.0, 19000.0, False),
    "frame_center_hae_m": (78, 2, -900.0, 19000.0, False),
    "vel_north_mps": (79, 2, -327.0, 327.0, True),
    "vel_east_mps": (80, 2, -327.0, 327.0, True),
    "platform_pitch_full_deg": (90, 4, -90.0, 90.0, True),
    "platform_roll_full_deg": (91, 4, -90.0, 90.0, True),
}

#: A packet's worth of values: camera heading 350 + 20 = 10 deg, 45 deg below the horizon, 40 m above the ground.
FULL_FIELDS: dict[str, float | None] = {
    "platform_heading_deg": 350.0, "platform_pitch_deg": 0.0, "platform_roll_deg": 0.0, "sensor_lat": 48.53,
    "sensor_lon": 9.06, "sensor_alt_msl_m": 512.0, "hfov_deg": 60.0, "vfov_deg": 34.0, "sensor_rel_azimuth_deg": 20.0,
    "sensor_rel_elevation_deg": -45.0, "sensor_rel_roll_deg": 0.0, "frame_center_lat": 48.5303,
    "frame_center_lon": 9.0604, "frame_center_elevation_m": 472.0,
}


def resolution(name: str) -> float:
    """One integer step of a field's mapping."""
    _tag, size, lo, hi, signed = SPEC[name]
    return (hi - lo) / ((1 << (8 * size)) - (2 if signed else 1))


def ber_length(n: int) -> bytes:
    if n < 128:
        return bytes([n])
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([0x80 | len(body)]) + body


def ber_oid(tag: int) -> bytes:
    groups = [tag & 0x7F]
    tag >>= 7
    while tag:
        groups.append(0x80 | (tag & 0x7F))
        tag >>= 7
    return bytes(reversed(groups))


def item(tag: int, value: bytes) -> bytes:
    return ber_oid(tag) + ber_length(len(value)) + value


def mapped(name: str, value: float | None) -> bytes:
    """The item bytes of a value (None: the signed items' error value)."""
    _tag, size, lo, hi, signed = SPEC[name]
    if value is None:
        return (-(1 << (8 * size - 1))).to_bytes(size, "big", signed=True)
    if signed:
        raw = round(value * ((1 << (8 * size)) - 2) / (hi - lo))
    else:
        raw = round((value - lo) * ((1 << (8 * size)) - 1) / (hi - lo))
    return raw.to_bytes(size, "big", signed=signed)


def standard_checksum(data: bytes) -> int:
    """The checksum loop as ST 0601 prints it: bcc += byte << (8 * ((i + 1) % 2))."""
    bcc = 0
    for i, byte in enumerate(data):
        bcc = (bcc + (byte << (8 * ((i + 1) % 2)))) & 0xFFFF
    return bcc


def packet(t: float | None, fields: Mapping[str, float | None] = (), *, extra: bytes = b"",  # type: ignore[assignment]
           checksum: bool = True, long_length: bool = False) -> bytes:
    """One ST 0601 packet: time stamp, the fields' items, `extra` raw items, the checksum (last)."""
    body = b"" if t is None else item(2, round(t * 1e6).to_bytes(8, "big"))
    for name, value in dict(fields).items():
        body += item(SPEC[name][0], mapped(name, value))
    body += extra
    if not checksum:
        return KEY + ber_length(len(body)) + body
    body += b"\x01\x02"
    length = len(body) + 2
    head = KEY + (bytes([0x82]) + length.to_bytes(2, "big") if long_length else ber_length(length))
    return head + body + standard_checksum(head + body).to_bytes(2, "big")


# ---- MPEG transport stream ---------------------------------------------------------------------------------
PMT_PID, VIDEO_PID, KLV_PID = 0x1000, 0x100, 0x101


def crc32_mpeg(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        for bit in range(7, -1, -1):
            top = ((crc >> 31) & 1) ^ ((byte >> bit) & 1)
            crc = ((crc << 1) & 0xFFFFFFFF) ^ (0x04C11DB7 if top else 0)
    return crc


def section(table_id: int, table_ext: int, body: bytes) -> bytes:
    length = 5 + len(body) + 4
    head = bytes([table_id, 0xB0 | (length >> 8), length & 0xFF, table_ext >> 8, table_ext & 0xFF, 0xC1, 0, 0])
    return head + body + crc32_mpeg(head + body).to_bytes(4, "big")


def pat() -> bytes:
    return section(0x00, 1, bytes([0x00, 0x01, 0xE0 | (PMT_PID >> 8), PMT_PID & 0xFF]))


def pmt(klv_stream_type: int = 0x15, *, video: bool = True, klv_descriptor: bytes | None = None) -> bytes:
    """PMT of program 1: an H.264 stream (optional) and the KLV stream (metadata descriptor with 'KLVA' for 0x15,
    registration descriptor 'KLVA' for 0x06, unless `klv_descriptor` is given)."""
    if klv_descriptor is None:
        klv_descriptor = (bytes([0x26, 9, 0x01, 0x00, 0xFF]) + b"KLVA" + bytes([0x00, 0x0F]) if klv_stream_type == 0x15
                          else bytes([0x05, 4]) + b"KLVA")
    streams = b""
    if video:
        streams += bytes([0x1B, 0xE0 | (VIDEO_PID >> 8), VIDEO_PID & 0xFF, 0xF0, 0x00])
    streams += bytes([klv_stream_type, 0xE0 | (KLV_PID >> 8), KLV_PID & 0xFF, 0xF0, len(klv_descriptor)])
    streams += klv_descriptor
    return section(0x02, 1, bytes([0xE0 | (VIDEO_PID >> 8), VIDEO_PID & 0xFF, 0xF0, 0x00]) + streams)


def pts_bytes(pts: int, marker: int = 0x20) -> bytes:
    pts %= 1 << 33
    return bytes([marker | ((pts >> 29) & 0x0E) | 1, (pts >> 22) & 0xFF, ((pts >> 14) & 0xFE) | 1,
                  (pts >> 7) & 0xFF, ((pts << 1) & 0xFE) | 1])


def pes(stream_id: int, data: bytes, pts: int | None, *, bounded: bool = True) -> bytes:
    header = bytes([0x84, 0x80, 5]) + pts_bytes(pts) if pts is not None else bytes([0x84, 0x00, 0])
    length = len(header) + len(data) if bounded else 0
    return b"\x00\x00\x01" + bytes([stream_id, length >> 8, length & 0xFF]) + header + data


def au_cells(packets: Sequence[bytes], seq: int = 0) -> bytes:
    """Metadata AU cells (ISO 13818-1 2.12.4): service id 0, sequence number, flags, length, data."""
    return b"".join(bytes([0, (seq + i) & 0xFF, 0xDF]) + len(p).to_bytes(2, "big") + p for i, p in enumerate(packets))


class TsWriter:
    """188-byte TS packets per PID with continuity counters; payload units split and stuffed as muxers do."""

    def __init__(self) -> None:
        self.cc: dict[int, int] = {}
        self.packets: list[bytes] = []

    def unit(self, pid: int, payload: bytes, *, psi: bool = False) -> None:
        data = (b"\x00" + payload) if psi else payload  # PSI: pointer_field 0
        for i in range(0, max(len(data), 1), 184):
            chunk = data[i:i + 184]
            cc = self.cc.get(pid, 0)
            self.cc[pid] = (cc + 1) & 0x0F
            head = bytes([0x47, (0x40 if i == 0 else 0) | (pid >> 8), pid & 0xFF])
            if len(chunk) == 184:
                self.packets.append(head + bytes([0x10 | cc]) + chunk)
                continue
            stuff = 184 - len(chunk)  # adaptation field: length byte, flags, 0xFF stuffing
            field = b"\x00" if stuff == 1 else bytes([stuff - 1, 0x00]) + b"\xff" * (stuff - 2)
            self.packets.append(head + bytes([0x30 | cc]) + field + chunk)

    def tables(self, **pmt_kw: object) -> None:
        self.unit(0, pat(), psi=True)
        self.unit(PMT_PID, pmt(**pmt_kw), psi=True)  # type: ignore[arg-type]

    def bytes(self, *, m2ts: bool = False) -> bytes:
        if m2ts:
            return b"".join(i.to_bytes(4, "big") + p for i, p in enumerate(self.packets))
        return b"".join(self.packets)


def write_ts(samples: Iterable[tuple[int, bytes]], *, video_pts: Sequence[int] = (), klv_stream_type: int = 0x15,
             cells: bool = True, m2ts: bool = False, tables_every: int = 5) -> bytes:
    """A transport stream with the KLV `samples` ((pts, packets) per PES) after the video PES of `video_pts`."""
    ts = TsWriter()
    ts.tables(klv_stream_type=klv_stream_type)
    for pts in video_pts:
        ts.unit(VIDEO_PID, pes(0xE0, b"\x00\x00\x00\x01\x09\xf0" + bytes(300), pts, bounded=False))
    for i, (pts, data) in enumerate(samples):
        if i and i % tables_every == 0:
            ts.tables(klv_stream_type=klv_stream_type)
        payload = au_cells([data], i) if cells and klv_stream_type == 0x15 else data
        ts.unit(KLV_PID, pes(0xFC if klv_stream_type == 0x15 else 0xBD, payload, pts))
    return ts.bytes(m2ts=m2ts)


def write_ts_with_pyav(path: Path, klv: Sequence[bytes], *, fps: int = 10, size: tuple[int, int] = (160, 96),
                       klv_delay_frames: int = 0) -> Path:
    """An MPEG-TS file from FFmpeg's muxer (PyAV): MPEG-2 video frames and one KLV packet per frame.

    KLV packet i has the PTS of frame i + `klv_delay_frames`; FFmpeg writes it as stream type 0x06 with a
    KLVA registration descriptor (asynchronous metadata).
    """
    import av

    with av.open(str(path), "w", format="mpegts") as out:
        video = out.add_stream("mpeg2video", rate=fps)
        video.width, video.height, video.pix_fmt = size[0], size[1], "yuv420p"
        data = out.add_data_stream("klv")
        tick = Fraction(1, 90_000)
        for i, packet_bytes in enumerate(klv):
            image = np.full((size[1], size[0], 3), (30 + 7 * i) % 256, np.uint8)
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = i
            for encoded in video.encode(frame):
                out.mux(encoded)
            pkt = av.Packet(packet_bytes)
            pkt.stream = data
            pkt.time_base = tick
            pkt.pts = pkt.dts = (i + klv_delay_frames) * 90_000 // fps
            out.mux(pkt)
        for encoded in video.encode():
            out.mux(encoded)
    return path

"""MPEG transport streams (``.ts``, ``.m2ts``): the payloads of their KLV metadata streams, with PTS.

Reads the file in chunks (NumPy picks the packets of the PIDs that matter), decodes no video: PAT -> PMT ->
the metadata elementary streams (ISO 13818-1 / MISB ST 1402) -> PES payloads. A synchronous stream
(stream_type 0x15) carries metadata AU cells with a 5-byte header, removed here; an asynchronous one
(stream_type 0x06 with a ``KLVA`` registration descriptor) carries KLV directly. The earliest PTS of the
first video stream is kept, so a KLV sample's PTS can be put on the video's clock.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

__all__ = ["PTS_HZ", "MetadataUnit", "TsStats", "iter_metadata_units", "mpeg_crc32", "strip_au_cells"]

log = logging.getLogger(__name__)

#: PTS ticks a second.
PTS_HZ = 90_000
TS_PACKET_BYTES = 188
_PTS_WRAP = 1 << 33
_SYNC = 0x47
_PAT_PID = 0
_NULL_PID = 0x1FFF
STREAM_TYPE_PRIVATE_DATA = 0x06
STREAM_TYPE_METADATA = 0x15
#: MPEG-1/2, MPEG-4 part 2, H.264, HEVC, VVC, AVS2/3, VC-1 and the like: the video whose first frame is time 0.
VIDEO_STREAM_TYPES = frozenset({0x01, 0x02, 0x10, 0x1B, 0x20, 0x24, 0x33, 0x42, 0xD1, 0xD2, 0xD4, 0xEA})
_KLVA = b"KLVA"
_SMPTE_UL_PREFIX = b"\x06\x0e\x2b\x34"  # every SMPTE universal key starts so; a payload that does has no AU cells
#: PES of the video whose PTS are compared for the earliest (B-frames are sent before earlier-shown frames).
_VIDEO_PES_LOOKED_AT = 32
#: PES stream ids without the optional PES header (ISO 13818-1 table 2-21).
_NO_PES_HEADER = frozenset({0xBC, 0xBE, 0xBF, 0xF0, 0xF1, 0xF2, 0xF8, 0xFF})
_SYNC_SEARCH_BYTES = 1 << 16


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else crc << 1
        table.append(crc & 0xFFFFFFFF)
    return table


_CRC_TABLE = _crc_table()


def mpeg_crc32(data: bytes) -> int:
    """CRC-32/MPEG-2 of PSI sections (polynomial 0x04C11DB7, not reflected, start 0xFFFFFFFF).

    Over a whole section, its own CRC included, the result is 0 when the section is intact.
    """
    crc = 0xFFFFFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ _CRC_TABLE[((crc >> 24) ^ byte) & 0xFF]
    return crc


@dataclass(frozen=True, slots=True)
class MetadataUnit:
    """The payload of one PES packet of a KLV metadata stream.

    pid: the stream's PID; pts: presentation time in 90 kHz ticks, unwrapped across the 33-bit wrap (None
    when the PES has none, as asynchronous metadata may); payload: the KLV bytes (AU cell headers removed);
    cut: True when the PES ended early (continuity error, end of file), so its last packet may be cut.
    """

    pid: int
    pts: int | None
    payload: bytes
    cut: bool = False


@dataclass
class TsStats:
    """What one pass over a transport stream saw; filled in while `iter_metadata_units` runs.

    Attributes
    ----------
    packet_bytes : int
        188 (TS) or 192 (BDAV ``.m2ts``: a 4-byte time code before each packet).
    packets : int
        TS packets read.
    sync_losses, skipped_bytes : int
        Times the 0x47 sync byte was missing, and bytes skipped to find it again.
    transport_errors : int
        Packets flagged by the demodulator, or with a broken adaptation field (skipped).
    continuity_errors : int
        Packets missing from a stream that is read (PSI, metadata, the video's first PES); a metadata PES
        being assembled is cut there.
    psi_crc_errors : int
        PAT / PMT sections with a bad CRC (ignored).
    streams : dict of int to int
        PID -> stream_type of every elementary stream in the PMTs.
    metadata_pids : list of int
        The KLV streams among them, in the order the PMTs list them.
    programs : dict of int to int
        PID -> program number of the PMT that lists it (a multi-program stream pairs each video with its KLV).
    pes, pes_cut : int
        Metadata PES read, and of those the ones cut short.
    video_pid : int or None
        The first video stream.
    video_start_pts : int or None
        Its earliest PTS in 90 kHz ticks (None without video): video time 0.
    """

    packet_bytes: int = TS_PACKET_BYTES
    packets: int = 0
    sync_losses: int = 0
    skipped_bytes: int = 0
    transport_errors: int = 0
    continuity_errors: int = 0
    psi_crc_errors: int = 0
    streams: dict[int, int] = field(default_factory=dict)
    metadata_pids: list[int] = field(default_factory=list)
    programs: dict[int, int] = field(default_factory=dict)
    pes: int = 0
    pes_cut: int = 0
    video_pid: int | None = None
    video_start_pts: int | None = None


def strip_au_cells(payload: bytes) -> bytes:
    """The data of the metadata AU cells of a synchronous metadata PES (ISO 13818-1 2.12.4), concatenated.

    Each cell: service id, sequence number, flags (1 byte each), a big-endian uint16 data length, the data.
    A payload that starts with a SMPTE key has no cells (FFmpeg's muxer writes 0x15 streams so), and one whose
    cell lengths do not add up is returned as it is: the KLV scanner then finds the packets by their key.
    """
    if payload.startswith(_SMPTE_UL_PREFIX):
        return payload
    cells, pos = [], 0
    while pos < len(payload):
        if pos + 5 > len(payload):
            return payload
        end = pos + 5 + ((payload[pos + 3] << 8) | payload[pos + 4])
        if end > len(payload):
            return payload
        cells.append(payload[pos + 5:end])
        pos = end
    return b"".join(cells)


def _pts(header: bytes, at: int) -> int:
    b = header[at:at + 5]
    return ((b[0] >> 1) & 0x07) << 30 | b[1] << 22 | (b[2] >> 1) << 15 | b[3] << 7 | b[4] >> 1


def _pes_header(pes: bytes) -> tuple[int | None, int, int | None] | None:
    """(pts or None, payload start, payload length or None when unbounded) of a PES, or None if it is no PES."""
    if len(pes) < 6 or pes[:3] != b"\x00\x00\x01":
        return None
    stream_id = pes[3]
    declared = (pes[4] << 8) | pes[5]
    if stream_id in _NO_PES_HEADER:
        return None, 6, declared or None
    if len(pes) < 9 or pes[6] & 0xC0 != 0x80:
        return None
    start = 9 + pes[8]
    pts = _pts(pes, 9) if pes[7] & 0x80 and len(pes) >= 14 else None
    return pts, start, (declared - 3 - pes[8]) if declared else None


def _format_identifiers(descriptors: bytes) -> set[bytes]:
    """Format identifiers in registration (tag 5) and metadata (tag 0x26) descriptors."""
    found: set[bytes] = set()
    pos = 0
    while pos + 2 <= len(descriptors):
        tag, size = descriptors[pos], descriptors[pos + 1]
        body = descriptors[pos + 2:pos + 2 + size]
        pos += 2 + size
        if tag == 0x05 and len(body) >= 4:
            found.add(bytes(body[:4]))
        elif tag == 0x26 and len(body) >= 3:
            at = 2
            if body[0:2] == b"\xff\xff" and len(body) >= 7:  # metadata_application_format: a 4-byte identifier
                found.add(bytes(body[2:6]))
                at = 6
            if at < len(body) and body[at] == 0xFF and len(body) >= at + 5:
                found.add(bytes(body[at + 1:at + 5]))
            elif at < len(body):
                found.add(bytes([body[at]]))  # a metadata_format code other than "identifier follows"
    return found


class _Demuxer:
    """Per-PID state of one transport stream: PSI sections, metadata PES being assembled, continuity."""

    def __init__(self, stats: TsStats) -> None:
        self.stats = stats
        self.pmt_pids: set[int] = set()
        self.metadata: dict[int, int] = {}  # pid -> stream_type
        self.psi: dict[int, bytearray] = {}
        self.last_section: dict[int, bytes] = {}  # PAT and PMT repeat unchanged ~10 times a second
        self.pes: dict[int, bytearray] = {}
        self.cc: dict[int, int] = {}
        self.video_pes = 0
        self.pts_ref: int | None = None
        self.wanted_changed = False

    def wanted(self) -> np.ndarray:
        pids = {_PAT_PID, *self.pmt_pids, *self.metadata}
        if self.stats.video_pid is not None and self.video_pes < _VIDEO_PES_LOOKED_AT:
            pids.add(self.stats.video_pid)
        return np.array(sorted(pids), dtype=np.uint16)

    def unwrap(self, pts: int) -> int:
        """PTS on one continuous tick count: the value nearest the last one, modulo 2**33."""
        if self.pts_ref is not None:
            pts += round((self.pts_ref - pts) / _PTS_WRAP) * _PTS_WRAP
        self.pts_ref = pts
        return pts

    # ---- packets ------------------------------------------------------------------------------------
    def packet(self, pkt: bytes) -> Iterator[MetadataUnit]:
        pid = ((pkt[1] & 0x1F) << 8) | pkt[2]
        if pkt[1] & 0x80:
            self.stats.transport_errors += 1
            yield from self._cut(pid)
            return
        control = (pkt[3] >> 4) & 0x3
        if not control & 0x1:
            return  # adaptation field only
        start = 4
        discontinuity = False
        if control == 0x3:
            start = 5 + pkt[4]
            discontinuity = pkt[4] > 0 and bool(pkt[5] & 0x80)
            if start > len(pkt):
                self.stats.transport_errors += 1
                return
        counter = pkt[3] & 0x0F
        last = self.cc.get(pid)
        self.cc[pid] = counter
        if last is not None and not discontinuity:
            if counter == last:
                return  # a duplicate packet, allowed once
            if counter != (last + 1) & 0x0F:
                self.stats.continuity_errors += 1
                self.psi.pop(pid, None)
                yield from self._cut(pid)
        payload = pkt[start:]
        unit_start = bool(pkt[1] & 0x40)
        if pid == _PAT_PID or pid in self.pmt_pids:
            self._psi(pid, payload, unit_start)
        elif pid in self.metadata:
            yield from self._metadata(pid, payload, unit_start)
        elif pid == self.stats.video_pid and unit_start:
            self._video(payload)

    def _video(self, payload: bytes) -> None:
        header = _pes_header(payload)
        self.video_pes += 1
        if self.video_pes >= _VIDEO_PES_LOOKED_AT:
            self.wanted_changed = True
        if header is None or header[0] is None:
            return
        pts = self.unwrap(header[0])
        start = self.stats.video_start_pts
        self.stats.video_start_pts = pts if start is None else min(start, pts)

    # ---- PSI ------------------------------------------------------------------------------------------
    def _psi(self, pid: int, payload: bytes, unit_start: bool) -> None:
        if unit_start:
            pointer = payload[0] if payload else 0
            if pid in self.psi:
                self.psi[pid] += payload[1:1 + pointer]
                self._sections(pid)
            self.psi[pid] = bytearray(payload[1 + pointer:])
        elif pid in self.psi:
            self.psi[pid] += payload
        else:
            return
        self._sections(pid)

    def _sections(self, pid: int) -> None:
        buf = self.psi[pid]
        while len(buf) >= 3 and buf[0] != 0xFF:
            end = 3 + (((buf[1] & 0x0F) << 8) | buf[2])
            if len(buf) < end:
                return
            section = bytes(buf[:end])
            del buf[:end]
            if self.last_section.get(pid) == section:
                continue
            self.last_section[pid] = section
            if end < 12 or mpeg_crc32(section) != 0:
                self.stats.psi_crc_errors += 1
            elif section[0] == 0x00 and pid == _PAT_PID:
                self._pat(section)
            elif section[0] == 0x02:
                self._pmt(section)
        if buf[:1] == b"\xff":
            buf.clear()  # stuffing to the end of the packet

    def _pat(self, section: bytes) -> None:
        for at in range(8, len(section) - 4 - 3, 4):
            program = (section[at] << 8) | section[at + 1]
            pid = ((section[at + 2] & 0x1F) << 8) | section[at + 3]
            if program != 0 and pid not in self.pmt_pids:  # program 0 points at the network table
                self.pmt_pids.add(pid)
                self.wanted_changed = True

    def _pmt(self, section: bytes) -> None:
        program = (section[3] << 8) | section[4]
        pos = 12 + (((section[10] & 0x0F) << 8) | section[11])
        end = len(section) - 4
        while pos + 5 <= end:
            stream_type = section[pos]
            pid = ((section[pos + 1] & 0x1F) << 8) | section[pos + 2]
            info_end = pos + 5 + (((section[pos + 3] & 0x0F) << 8) | section[pos + 4])
            identifiers = _format_identifiers(section[pos + 5:min(info_end, end)])
            pos = info_end
            if self.stats.streams.get(pid) == stream_type:
                continue
            self.stats.streams[pid] = stream_type
            self.stats.programs[pid] = program
            klv = _KLVA in identifiers or (stream_type == STREAM_TYPE_METADATA and not identifiers)
            if klv and stream_type in (STREAM_TYPE_METADATA, STREAM_TYPE_PRIVATE_DATA):
                self.metadata[pid] = stream_type
                self.stats.metadata_pids.append(pid)
                self.wanted_changed = True
            elif stream_type in VIDEO_STREAM_TYPES and self.stats.video_pid is None:
                self.stats.video_pid = pid
                self.wanted_changed = True

    # ---- metadata PES ---------------------------------------------------------------------------------
    def _metadata(self, pid: int, payload: bytes, unit_start: bool) -> Iterator[MetadataUnit]:
        if unit_start:
            yield from self.finish(pid, cut=False)
            self.pes[pid] = bytearray(payload)
        elif pid in self.pes:
            self.pes[pid] += payload
        else:
            return  # the middle of a PES whose start was not seen
        buf = self.pes[pid]
        if len(buf) >= 6 and (declared := (buf[4] << 8) | buf[5]) and len(buf) >= 6 + declared:
            yield from self.finish(pid, cut=False)

    def _cut(self, pid: int) -> Iterator[MetadataUnit]:
        if pid in self.pes:
            yield from self.finish(pid, cut=True)

    def finish(self, pid: int, *, cut: bool) -> Iterator[MetadataUnit]:
        """The PES being assembled on `pid` as a unit (nothing when there is none or it is no PES)."""
        buf = self.pes.pop(pid, None)
        if buf is None:
            return
        header = _pes_header(bytes(buf[:64]))
        if header is None:
            self.stats.pes_cut += 1
            return
        pts, start, length = header
        data = bytes(buf[start:] if length is None else buf[start:start + length])
        cut = cut or (length is not None and len(data) < length)
        self.stats.pes += 1
        self.stats.pes_cut += cut
        if self.metadata[pid] == STREAM_TYPE_METADATA:
            data = strip_au_cells(data)
        yield MetadataUnit(pid, None if pts is None else self.unwrap(pts), data, cut)


def _find_sync(buf: bytes, start: int, size: int, offset: int) -> int | None:
    """The first packet start at or after `start` whose sync byte and the next packet's (if in `buf`) are 0x47."""
    at = start + offset
    while True:
        at = buf.find(b"\x47", at)
        if at < 0:
            return None
        nxt = at + size
        if nxt >= len(buf) or buf[nxt] == _SYNC:
            if at - offset >= start:
                return at - offset
        at += 1


def _packet_layout(head: bytes, source: str) -> tuple[int, int, int]:
    """(packet size, sync offset in a packet, first packet start): (188, 0, _) for TS, (192, 4, _) for BDAV.

    The first packet is where five sync bytes (fewer in a shorter file) follow each other at the packet size.
    """
    for size, offset in ((TS_PACKET_BYTES, 0), (192, 4)):
        need = min(5, max(1, len(head) // size))
        at = head.find(b"\x47", offset)
        while 0 <= at and at + (need - 1) * size < len(head):
            if all(head[at + k * size] == _SYNC for k in range(need)):
                return size, offset, at - offset
            at = head.find(b"\x47", at + 1)
    raise ValueError(f"{source}: not an MPEG transport stream (no 0x47 sync byte every 188 or 192 bytes)")


def iter_metadata_units(stream: BinaryIO, stats: TsStats, *, source: str = "<ts>",
                        chunk_bytes: int = 1 << 20) -> Iterator[MetadataUnit]:
    """The PES payloads of the KLV metadata streams of a transport stream, in file order.

    Parameters
    ----------
    stream : binary file object
        Read with ``read(chunk_bytes)`` until it returns b"", so memory stays at about one chunk.
    stats : TsStats
        Filled in while iterating (and complete when the iterator ends).
    source : str
        Name used in messages.

    Raises
    ------
    ValueError
        If the start of the stream has no transport-stream packet structure.
    """
    head = stream.read(_SYNC_SEARCH_BYTES)
    size, offset, start = _packet_layout(head, source)
    stats.packet_bytes = size
    stats.skipped_bytes = start
    demux = _Demuxer(stats)
    wanted = demux.wanted()
    buf = head
    eof = not head
    lost = False  # searching for the sync byte (one loss however many chunks the search takes)
    starved = False  # the search needs bytes beyond the buffer
    while True:
        if not eof and (starved or len(buf) - start < max(chunk_bytes, size)):
            starved = False
            chunk = stream.read(chunk_bytes)
            eof = not chunk
            buf = buf[start:] + chunk
            start = 0
        count = (len(buf) - start) // size
        if count == 0:
            if eof:
                break
            continue
        rows = np.frombuffer(buf, np.uint8, count=count * size, offset=start).reshape(count, size)[:, offset:]
        in_sync = rows[:, 0] == _SYNC
        good = count if in_sync.all() else int(np.argmin(in_sync))
        stats.packets += good
        done = 0
        while done < good:
            pids = ((rows[done:good, 1].astype(np.uint16) & 0x1F) << 8) | rows[done:good, 2]
            hits = np.flatnonzero(np.isin(pids, wanted))
            demux.wanted_changed = False
            for hit in hits:
                yield from demux.packet(rows[done + hit].tobytes())
                if demux.wanted_changed:  # a PAT, PMT or the video start changed which PIDs are read
                    wanted = demux.wanted()
                    done += int(hit) + 1
                    break
            else:
                done = good
        start += good * size
        lost = lost and not good
        if good < count:
            resync = _find_sync(buf, start + 1, size, offset)
            stats.sync_losses += not lost
            lost = resync is None
            skip = (len(buf) - start if resync is None else resync - start)
            if resync is None and not eof:
                skip = max(len(buf) - start - 2 * size, 0)  # keep a tail: the next sync may be just after it
                starved = True
            stats.skipped_bytes += skip
            start += skip
    stats.skipped_bytes += len(buf) - start
    for pid in list(demux.pes):
        yield from demux.finish(pid, cut=False)  # cut only if its declared length is not reached
    if stats.sync_losses:
        log.warning("%s: lost the transport-stream sync %d times (%d bytes skipped)", source, stats.sync_losses,
                    stats.skipped_bytes)

"""MISB ST 0601 wire format: the UAS Datalink Local Set's key, BER fields, checksum and item mappings.

`KlvDecoder` finds packets by their key in byte buffers, verifies the checksum, decodes the items into
`KlvSample`s and counts what it skips (bad checksum, cut short, broken BER, unknown tags); it never raises
for malformed data.

Items decoded (tag: quantity, encoding -> range):
2 Precision Time Stamp (uint64 microseconds since 1970, POSIX), 5 Platform Heading (uint16 -> 0..360),
6 / 90 Platform Pitch (int16 -> +-20 / int32 -> +-90, the full-range one wins), 7 / 91 Platform Roll
(int16 -> +-50 / int32 -> +-90), 13 / 14 Sensor Latitude / Longitude (int32 -> +-90 / +-180),
15 Sensor True Altitude above MSL (uint16 -> -900..19000 m), 16 / 17 Sensor Horizontal / Vertical FoV
(uint16 -> 0..180), 18 Sensor Relative Azimuth (uint32 -> 0..360), 19 Sensor Relative Elevation
(int32 -> +-180, negative down), 20 Sensor Relative Roll (uint32 -> 0..360), 23 / 24 Frame Center
Latitude / Longitude, 25 Frame Center Elevation (MSL), 65 LS Version, 75 Sensor Ellipsoid Height,
78 Frame Center Height Above Ellipsoid, 79 / 80 Sensor North / East Velocity (int16 -> +-327 m/s).
Signed items use the standard's error value (the most negative integer) for "unknown": the item is then
treated as absent. Other tags are counted by number and skipped.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

from shared.telemetry.klv_sample import KlvSample

__all__ = [
    "DEFAULT_MAX_HOLD_S",
    "MAX_PACKET_BYTES",
    "UAS_LOCAL_SET_KEY",
    "KlvDecoder",
    "TruncatedKlv",
    "checksum16",
    "read_ber_length",
    "read_ber_oid",
]

#: The universal key of the UAS Datalink Local Set (ST 0601).
UAS_LOCAL_SET_KEY = bytes.fromhex("060E2B34020B01010E01030101000000")
#: An item a packet leaves out keeps its last value for this long (encoders send slow items less often).
DEFAULT_MAX_HOLD_S = 5.0
#: Longer "packets" are a corrupt length, not ST 0601 (a packet with every item is a few hundred bytes).
MAX_PACKET_BYTES = 1 << 20
_CHECKSUM_TAG = 1
_TIME_TAG = 2


class TruncatedKlv(ValueError):
    """The bytes end inside a BER field: more data may complete it."""


def read_ber_length(data: bytes, pos: int, end: int | None = None) -> tuple[int, int]:
    """Decode a BER length (short form < 128, or 0x81..0x88 and that many big-endian bytes).

    Returns (length, position after the field). Raises TruncatedKlv when ``data[:end]`` ends inside it and
    ValueError for the indefinite form (0x80) or more than 8 length bytes.
    """
    end = len(data) if end is None else end
    if pos >= end:
        raise TruncatedKlv("BER length cut off")
    first = data[pos]
    if first < 0x80:
        return first, pos + 1
    size = first & 0x7F
    if size == 0 or size > 8:
        raise ValueError(f"BER length byte 0x{first:02x} is not a definite length of 1-8 bytes")
    if pos + 1 + size > end:
        raise TruncatedKlv("BER length cut off")
    return int.from_bytes(data[pos + 1:pos + 1 + size], "big"), pos + 1 + size


def read_ber_oid(data: bytes, pos: int, end: int | None = None) -> tuple[int, int]:
    """Decode a BER-OID tag (7 bits a byte, high bit set on all but the last byte; at most 4 bytes).

    Returns (tag, position after it). Raises TruncatedKlv when ``data[:end]`` ends inside it, ValueError when
    it is longer than 4 bytes.
    """
    end = len(data) if end is None else end
    tag = 0
    for i in range(4):
        if pos + i >= end:
            raise TruncatedKlv("BER-OID tag cut off")
        byte = data[pos + i]
        tag = (tag << 7) | (byte & 0x7F)
        if not byte & 0x80:
            return tag, pos + i + 1
    raise ValueError("BER-OID tag longer than 4 bytes")


def checksum16(data: bytes) -> int:
    """ST 0601 checksum: the 16-bit sum of big-endian byte pairs (even offsets high), modulo 2**16.

    Computed from the first byte of the key through the checksum item's tag and length bytes.
    """
    return ((sum(data[0::2]) << 8) + sum(data[1::2])) & 0xFFFF


#: The key's share of a packet's checksum: an encoder that sums from the length on (a known bug: the key left out)
#: states the checksum less this, modulo 2**16; the rest of the packet is still checked by it.
_KEY_SUM = checksum16(UAS_LOCAL_SET_KEY)


@dataclass(frozen=True, slots=True)
class _Item:
    """One decoded item: the sample field it fills, its size in bytes, and its range (None: a plain uint)."""

    field: str
    size: int
    lo: float | None = None
    hi: float | None = None
    signed: bool = False

    def decode(self, raw: bytes) -> float | int | None:
        value = int.from_bytes(raw, "big", signed=self.signed)
        if self.lo is None or self.hi is None:
            return value
        bits = 8 * self.size
        if self.signed:
            if value == -(1 << (bits - 1)):
                return None  # the standard's "error / out of range" value
            return value * (self.hi - self.lo) / ((1 << bits) - 2)
        return self.lo + value * (self.hi - self.lo) / ((1 << bits) - 1)


_ITEMS: dict[int, _Item] = {
    5: _Item("platform_heading_deg", 2, 0.0, 360.0),
    6: _Item("platform_pitch_deg", 2, -20.0, 20.0, signed=True),
    7: _Item("platform_roll_deg", 2, -50.0, 50.0, signed=True),
    13: _Item("sensor_lat", 4, -90.0, 90.0, signed=True),
    14: _Item("sensor_lon", 4, -180.0, 180.0, signed=True),
    15: _Item("sensor_alt_msl_m", 2, -900.0, 19000.0),
    16: _Item("hfov_deg", 2, 0.0, 180.0),
    17: _Item("vfov_deg", 2, 0.0, 180.0),
    18: _Item("sensor_rel_azimuth_deg", 4, 0.0, 360.0),
    19: _Item("sensor_rel_elevation_deg", 4, -180.0, 180.0, signed=True),
    20: _Item("sensor_rel_roll_deg", 4, 0.0, 360.0),
    23: _Item("frame_center_lat", 4, -90.0, 90.0, signed=True),
    24: _Item("frame_center_lon", 4, -180.0, 180.0, signed=True),
    25: _Item("frame_center_elevation_m", 2, -900.0, 19000.0),
    65: _Item("version", 1),
    75: _Item("sensor_hae_m", 2, -900.0, 19000.0),
    78: _Item("frame_center_hae_m", 2, -900.0, 19000.0),
    79: _Item("vel_north_mps", 2, -327.0, 327.0, signed=True),
    80: _Item("vel_east_mps", 2, -327.0, 327.0, signed=True),
    90: _Item("platform_pitch_deg", 4, -90.0, 90.0, signed=True),  # after tag 6: the full-range value wins
    91: _Item("platform_roll_deg", 4, -90.0, 90.0, signed=True),
}
#: The short platform attitude items, whose "out of range" value means beyond their range, and the full-range ones.
_SHORT_ATTITUDE_TAGS = frozenset({6, 7})
_FULL_RANGE_ATTITUDE_TAGS = frozenset({90, 91})
#: Items read and not used (slant range, target width, ...): not reported as "not decoded".
KNOWN_UNUSED_TAGS = frozenset({3, 4, 8, 9, 10, 11, 12, 21, 22, 26, 27, 28, 29, 30, 31, 32, 33, 47, 56, 57, 59, 64,
                               72, 82, 83, 84, 85, 86, 87, 88, 89, 94})


@dataclass
class KlvDecoder:
    """ST 0601 packets from byte buffers to samples; counts what it skips and holds items across packets.

    Feed it the bytes of a stream in order (`feed`). The counts mean what `klv.KlvReport`'s do; bytes_seen and
    bytes_decoded are the bytes consumed and the bytes of decoded packets. samples: (sample, PTS or None) in
    stream order; held: field -> (last value, time stamp of the packet that gave it); sent: per sample, the fields
    its own packet sent (the others in it are held). checksum_without_key: packets accepted whose checksum leaves the
    16-byte key out (a known encoder bug; the sum still checks the rest of the packet).
    """

    max_hold_s: float = DEFAULT_MAX_HOLD_S
    packets: int = 0
    decoded: int = 0
    bad_checksum: int = 0
    missing_checksum: int = 0
    checksum_without_key: int = 0
    truncated: int = 0
    malformed: int = 0
    bad_items: int = 0
    no_time: int = 0
    bytes_seen: int = 0
    bytes_decoded: int = 0
    unknown_tags: Counter[int] = field(default_factory=Counter)
    samples: list[tuple[KlvSample, int | None]] = field(default_factory=list)
    held: dict[str, tuple[float | int, float]] = field(default_factory=dict)
    sent: list[frozenset[str]] = field(default_factory=list)
    _full_range_t: dict[str, float] = field(default_factory=dict)  # field -> time of its last tag 90 / 91 value

    def feed(self, data: bytes, pts: int | None = None, *, final: bool = True) -> int:
        """Decode the packets in `data`; returns the bytes consumed.

        Not `final`: a packet running past the end is left (consumed < len(data)) for the next call with more
        bytes. `final`: the data ends there (a PES payload, the end of a file), so such a packet is truncated.
        """
        pos, size = 0, len(data)
        key = UAS_LOCAL_SET_KEY
        while True:
            start = data.find(key, pos)
            if start < 0:
                keep = 0 if final else min(size - pos, len(key) - 1)  # a key may straddle the chunks
                self.bytes_seen += size - keep
                return size - keep
            problem: str | None = None
            try:
                length, value_start = read_ber_length(data, start + len(key))
                end = value_start + length
                if length > MAX_PACKET_BYTES:
                    problem = "malformed"
                elif end > size:
                    problem = "truncated"
            except TruncatedKlv:
                problem = "truncated"
            except ValueError:
                problem = "malformed"
            if problem == "truncated" and not final:
                self.bytes_seen += start  # the rest may come with the next call
                return start
            self.packets += 1
            if problem is not None:
                if problem == "truncated":
                    self.truncated += 1
                else:
                    self.malformed += 1
                pos = start + len(key)
                continue
            if self._packet(data, start, value_start, end, pts):
                self.bytes_decoded += end - start
                pos = end
            else:
                pos = start + len(key)  # a cut packet may hide the next key inside its claimed length

    def _packet(self, data: bytes, start: int, value_start: int, end: int, pts: int | None) -> bool:
        has_checksum = end - value_start >= 4 and data[end - 4] == _CHECKSUM_TAG and data[end - 3] == 2
        ok = False
        if has_checksum:
            stated, summed = int.from_bytes(data[end - 2:end], "big"), checksum16(data[start:end - 2])
            ok = summed == stated
            if not ok and (summed - _KEY_SUM) % 65536 == stated:  # an encoder's sum that leaves the key out
                ok = True
                self.checksum_without_key += 1
        if not ok:
            if data.find(UAS_LOCAL_SET_KEY, value_start, end) >= 0:
                self.truncated += 1  # cut short, then the next packet began inside its claimed length
            elif has_checksum:
                self.bad_checksum += 1
            else:
                self.missing_checksum += 1
            return False
        items: dict[int, bytes] = {}
        pos = value_start
        try:
            while pos < end - 4:
                tag, pos = read_ber_oid(data, pos, end - 4)
                length, pos = read_ber_length(data, pos, end - 4)
                if pos + length > end - 4:
                    raise TruncatedKlv("item runs past the checksum")
                items[tag] = data[pos:pos + length]
                pos += length
        except ValueError:  # TruncatedKlv included: inside a checked packet, the lengths are wrong
            self.malformed += 1
            return False
        self.decoded += 1
        self._sample(items, pts)
        return True

    def _sample(self, items: dict[int, bytes], pts: int | None) -> None:
        stamp = items.get(_TIME_TAG)
        if stamp is None or len(stamp) != 8:
            self.no_time += 1  # tag 2 is mandatory: without it the packet has no place in time
            return
        t = int.from_bytes(stamp, "big") / 1e6
        before = dict(self.held)  # an item the packet sends is stored as a new tuple: `sent` compares identities
        for tag in sorted(items):
            if tag in (_CHECKSUM_TAG, _TIME_TAG):
                continue
            spec = _ITEMS.get(tag)
            if spec is None:
                if tag not in KNOWN_UNUSED_TAGS:
                    self.unknown_tags[tag] += 1
                continue
            raw = items[tag]
            if len(raw) != spec.size:
                self.bad_items += 1
                continue
            value = spec.decode(raw)
            if value is None and tag in _SHORT_ATTITUDE_TAGS:
                # "out of range" of the short item (pitch beyond +-20 deg, roll beyond +-50: a dive, a bank): a
                # full-range value (tags 90, 91) held from a recent packet still stands; else the attitude is
                # unknown now, which is not level (NaN: the camera's angles cannot be composed)
                full = self._full_range_t.get(spec.field)
                if full is None or abs(t - full) > self.max_hold_s:
                    self.held[spec.field] = (math.nan, t)
            elif value is None:
                self.held.pop(spec.field, None)  # "unknown now": an older value must not stand in
            else:
                self.held[spec.field] = (value, t)
                if tag in _FULL_RANGE_ATTITUDE_TAGS:
                    self._full_range_t[spec.field] = t
        values = {name: value for name, (value, t_item) in self.held.items() if abs(t - t_item) <= self.max_hold_s}
        self.samples.append((KlvSample(t=t, **values), pts))  # type: ignore[arg-type]
        self.sent.append(frozenset(name for name, entry in self.held.items() if entry is not before.get(name)))


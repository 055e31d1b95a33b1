"""MISB ST 0601 UAS Datalink Local Set (KLV) to `Telemetry` records, from raw ``.klv`` files or MPEG-TS video.

Reads files in chunks: transport streams are demultiplexed by `mpegts`, packets decoded by `klv_packets`,
samples turned into records by `klv_sample`; `KlvReport` counts everything skipped.

The decoder is written here, not taken from klvdata (PyPI): its last release is from 2018 (ST 0601.8 era),
it reads no transport stream (it expects FFmpeg to pipe the data stream out) and does not report what it
skipped. BER lengths, BER-OID tags, a checksum and a table of mappings are about 150 lines.
"""

from __future__ import annotations

import logging
import math
import statistics
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from shared.telemetry.klv_packets import DEFAULT_MAX_HOLD_S, KlvDecoder
from shared.telemetry.klv_sample import KlvSample
from shared.telemetry.klv_series import sample_times, with_positions_in_time
from shared.telemetry.mpegts import PTS_HZ, TsStats, iter_metadata_units
from shared.telemetry.record import Telemetry

__all__ = ["KLV_FILE_SUFFIXES", "KlvReport", "parse_klv_report", "read_klv", "read_klv_report"]

log = logging.getLogger(__name__)

#: Suffixes `read_klv_report` reads: raw concatenated packets, or MPEG transport streams.
KLV_FILE_SUFFIXES = (".klv", ".ts", ".m2ts", ".mts")
_CHUNK_BYTES = 1 << 20


@dataclass(frozen=True, slots=True)
class KlvReport:
    """What reading ST 0601 KLV gave: records, samples and the count of everything skipped.

    Attributes
    ----------
    source : str
        The name used in messages.
    records : list of Telemetry
        One per sample with a sensor position, sorted by ``t`` (UNIX seconds).
    samples : tuple of KlvSample
        Every decoded packet with a time stamp, in stream order (fields of view, frame centre, raw angles); their
        ``t`` is the sample's time (`times_from`).
    packets : int
        Local-set keys found. Of these: decoded, bad_checksum, missing_checksum (no checksum item at the end),
        truncated (cut short), malformed (broken BER inside a checked packet, or an absurd length).
    checksum_without_key : int
        Decoded packets whose checksum leaves the 16-byte key out (a known encoder bug): accepted, as the sum still
        checks the rest of each packet; said at info level.
    bad_items : int
        Known items of the wrong size (skipped; the rest of the packet is used).
    no_time : int
        Decoded packets without a Precision Time Stamp (skipped).
    no_position : int
        Samples without sensor latitude / longitude (no record).
    no_recent_position : int
        Samples whose packet sent no sensor position, with no two packets that did within
        `klv_series.POSITION_BRACKET_S` around them and none within `POSITION_HOLD_S` before (a GPS outage; no
        record). A position sent less often than the angles is interpolated in time between the packets that sent
        it (`klv_series.positions_in_time`), not held.
    no_pitch : int
        Records without pitch: the camera above the horizon or past nadir.
    attitude_out_of_range : int
        Records without camera angles because the platform pitch or roll was sent as "out of range" (a dive or a
        bank beyond tags 6 / 7, no full-range tag 90 / 91): the line of sight is unknown, not level.
    unknown_tags : dict of int to int
        Tags this reader does not decode and does not know as unused (slant range, corner points, ...) -> how
        often they came (skipped).
    skipped_bytes : int
        Bytes outside decoded packets (garbage between packets, the bytes of skipped ones).
    video_start_t : float or None
        UNIX time of the video's first frame: the median of ``t - video_time_s`` over the samples with a
        video time (None without): the telemetry time of video time 0.
    heights_missing : int
        Records with no height above ground; of them, heights_above_sea_level_only have a sensor altitude
        above MSL but no frame centre elevation (``height_offset_m`` fixes them).
    ts : TsStats or None
        The transport stream's counts (None for raw KLV).
    ignored_streams : dict of int to int
        Further ST 0601 streams of the transport stream, not read (PID -> their ST 0601 packets): a payload with
        several sensors (EO and IR) writes one stream each, and merged their records would alternate between
        two cameras. Read is the first stream the PMT lists in the first video's program (else the first listed).
    repeated_stamps : int
        Samples whose Precision Time Stamp equals the one before: an encoder holding the stamp (e.g. from the
        GPS's 1 Hz PPS) while it writes a packet per frame.
    times_from : str
        Where the samples' and records' ``t`` come from (`klv_series.sample_times`): "stamps" (no stamp repeats:
        the stamps themselves), "pts" (stamps repeat: each sample's PTS, on the stamps' clock by the offset where
        each stamp is new) or "spread" (stamps repeat without PTS: spread evenly between the stamps).
    """

    source: str
    records: list[Telemetry]
    samples: tuple[KlvSample, ...]
    packets: int = 0
    decoded: int = 0
    bad_checksum: int = 0
    missing_checksum: int = 0
    checksum_without_key: int = 0
    truncated: int = 0
    malformed: int = 0
    bad_items: int = 0
    no_time: int = 0
    no_position: int = 0
    no_recent_position: int = 0
    no_pitch: int = 0
    attitude_out_of_range: int = 0
    unknown_tags: dict[int, int] = field(default_factory=dict)
    skipped_bytes: int = 0
    video_start_t: float | None = None
    heights_missing: int = 0
    heights_above_sea_level_only: int = 0
    ts: TsStats | None = None
    ignored_streams: dict[int, int] = field(default_factory=dict)
    repeated_stamps: int = 0
    times_from: str = "stamps"

    def problems(self) -> dict[str, int]:
        """The non-zero counts of skipped packets and items and of records without pitch, by reason."""
        names = ("bad_checksum", "missing_checksum", "truncated", "malformed", "bad_items", "no_time",
                 "no_position", "no_recent_position", "no_pitch", "attitude_out_of_range")
        return {name: getattr(self, name) for name in names if getattr(self, name)}


def _report(source: str, decoder: KlvDecoder, *, height_offset_m: float | None, ts: TsStats | None) -> KlvReport:
    video_start_pts = None if ts is None else ts.video_start_pts
    times = sample_times([s.t for s, _ in decoder.samples],
                         [None if pts is None else pts / PTS_HZ for _, pts in decoder.samples])
    samples = []
    for (sample, pts), t in zip(decoder.samples, times.t.tolist(), strict=True):
        if t != sample.t:
            sample = replace(sample, t=t)
        if pts is not None and video_start_pts is not None:
            sample = replace(sample, video_time_s=(pts - video_start_pts) / PTS_HZ)
        samples.append(sample)
    samples, stale = with_positions_in_time(samples, decoder.sent)
    timed = [s.t - s.video_time_s for s in samples if s.video_time_s is not None]
    records, no_position, no_recent_position, no_pitch, above_sea_level_only = [], 0, 0, 0, 0
    attitude_out_of_range = 0
    for sample, position_too_old in zip(samples, stale, strict=True):
        record = sample.to_telemetry(height_offset_m)
        if record is None:
            no_recent_position += position_too_old
            no_position += not position_too_old
            continue
        no_pitch += (record.pitch_deg is None and sample.sensor_rel_elevation_deg is not None
                     and not sample.attitude_out_of_range)
        attitude_out_of_range += sample.attitude_out_of_range and sample.sensor_rel_elevation_deg is not None
        above_sea_level_only += record.height_m is None and sample.sensor_alt_msl_m is not None
        records.append(record)
    records.sort(key=lambda r: r.t)
    return KlvReport(
        source=source, records=records, samples=tuple(samples), packets=decoder.packets, decoded=decoder.decoded,
        bad_checksum=decoder.bad_checksum, missing_checksum=decoder.missing_checksum,
        checksum_without_key=decoder.checksum_without_key, truncated=decoder.truncated,
        malformed=decoder.malformed, bad_items=decoder.bad_items, no_time=decoder.no_time, no_position=no_position,
        no_recent_position=no_recent_position, no_pitch=no_pitch, attitude_out_of_range=attitude_out_of_range,
        unknown_tags=dict(sorted(decoder.unknown_tags.items())),
        skipped_bytes=decoder.bytes_seen - decoder.bytes_decoded,
        video_start_t=statistics.median(timed) if timed else None,
        heights_missing=sum(r.height_m is None for r in records), heights_above_sea_level_only=above_sea_level_only,
        ts=ts, repeated_stamps=times.repeated, times_from=times.method,
    )


def _decoder(max_hold_s: float, height_offset_m: float | None) -> KlvDecoder:
    if not (math.isfinite(max_hold_s) and max_hold_s >= 0.0):
        raise ValueError(f"max_hold_s={max_hold_s!r} must be finite and >= 0")
    if height_offset_m is not None and not math.isfinite(height_offset_m):
        raise ValueError(f"height_offset_m={height_offset_m!r} must be finite")
    return KlvDecoder(max_hold_s=float(max_hold_s))


def parse_klv_report(data: bytes, *, source: str = "<klv>", height_offset_m: float | None = None,
                     max_hold_s: float = DEFAULT_MAX_HOLD_S) -> KlvReport:
    """Decode raw concatenated ST 0601 packets (what a ``.klv`` file holds) held in memory.

    Parameters as in `read_klv_report`; garbage between packets is skipped and counted. Never raises for
    malformed data: the report has no records then.
    """
    decoder = _decoder(max_hold_s, height_offset_m)
    decoder.feed(bytes(data))
    return _report(source, decoder, height_offset_m=height_offset_m, ts=None)


def _one_stream(decoders: dict[int, KlvDecoder], ts: TsStats) -> tuple[int | None, dict[int, int]]:
    """The KLV stream to read when a transport stream has several, and the others' PID -> ST 0601 packets.

    The first the PMT lists in the program of the first video stream, else the first listed; a stream with no
    ST 0601 packet with a time stamp is passed over (another local set, e.g. a stand-alone VMTI stream).
    Ignored streams without ST 0601 packets are not named.
    """
    video_program = None if ts.video_pid is None else ts.programs.get(ts.video_pid)
    listed = [pid for pid in dict.fromkeys(ts.metadata_pids) if pid in decoders]
    listed.sort(key=lambda pid: ts.programs.get(pid) != video_program)  # stable: the video's program first
    chosen = next((pid for pid in listed if decoders[pid].samples), listed[0] if listed else None)
    return chosen, {pid: decoders[pid].packets for pid in listed if pid != chosen and decoders[pid].packets}


def _no_record_message(report: KlvReport) -> str:
    if report.ts is not None and not report.ts.metadata_pids:
        listed = ", ".join(f"0x{kind:02x} on PID {pid}" for pid, kind in sorted(report.ts.streams.items()))
        return (f"{report.source}: no KLV metadata stream in the transport stream (stream types: {listed or 'none'}; "
                "KLV is stream type 0x15, or 0x06 with a KLVA registration descriptor)")
    problems = ", ".join(f"{n} {name.replace('_', ' ')}" for name, n in report.problems().items())
    return (f"{report.source}: no ST 0601 packet with a time stamp and a sensor position "
            f"({report.packets} UAS Datalink Local Set packets found{': ' + problems if problems else ''})")


def _log_report(report: KlvReport) -> None:
    log.info("telemetry %s: %d records from %d ST 0601 packets; video starts at t=%s", report.source,
             len(report.records), report.packets,
             "unknown" if report.video_start_t is None else f"{report.video_start_t:.3f}")
    if report.checksum_without_key:
        log.info("telemetry %s: %d of %d packets' checksums leave out the 16-byte key (an encoder's known bug): read, "
                 "as the sum still checks the rest of each packet", report.source, report.checksum_without_key,
                 report.decoded)
    problems = report.problems()
    if problems or report.unknown_tags:
        log.warning("telemetry %s: %s; tags not decoded: %s", report.source,
                    ", ".join(f"{n} {name.replace('_', ' ')}" for name, n in problems.items()) or "nothing",
                    ", ".join(f"{tag} (x{n})" for tag, n in report.unknown_tags.items()) or "none")


def read_klv_report(path: str | Path, *, height_offset_m: float | None = None,
                    max_hold_s: float = DEFAULT_MAX_HOLD_S) -> KlvReport:
    """Read ST 0601 KLV from a raw ``.klv`` file or from the metadata streams of an MPEG-TS file.

    Parameters
    ----------
    path : path
        ``.klv``: concatenated packets. ``.ts``, ``.m2ts``, ``.mts``: a transport stream (188- or 192-byte
        packets) with a KLV metadata stream; its PTS put the samples on the video's clock
        (`KlvReport.video_start_t`). Read in chunks: memory does not grow with the file.
    height_offset_m : float, optional
        Minus the ground elevation above MSL: heights become sensor altitude + offset, for streams without the
        frame centre elevation (see `KlvSample.height_above_ground_m`).
    max_hold_s : float
        An item a packet leaves out keeps its last value this long (an item sent as "unknown" is dropped).

    Returns
    -------
    KlvReport

    Raises
    ------
    ValueError
        One line naming the file: unreadable, not a transport stream, no KLV stream, or no packet with a time
        and a sensor position (the counts of what was skipped are in the message).
    """
    source = str(path)
    decoder = _decoder(max_hold_s, height_offset_m)
    ts: TsStats | None = None
    ignored: dict[int, int] = {}
    try:
        with open(path, "rb") as stream:
            if Path(path).suffix.lower() == ".klv":
                carry = b""
                while chunk := stream.read(_CHUNK_BYTES):
                    carry += chunk
                    carry = carry[decoder.feed(carry, final=False):]
                decoder.feed(carry)
            else:
                ts = TsStats()
                decoders: dict[int, KlvDecoder] = {}
                for unit in iter_metadata_units(stream, ts, source=source):
                    if unit.pid not in decoders:  # one decoder a stream: items are held within a stream only
                        decoders[unit.pid] = _decoder(max_hold_s, height_offset_m)
                    decoders[unit.pid].feed(unit.payload, unit.pts)
                chosen, ignored = _one_stream(decoders, ts)
                decoder = decoder if chosen is None else decoders[chosen]
    except OSError as exc:
        raise ValueError(f"{source}: cannot read the file ({exc.strerror or exc})") from None
    if ignored:
        log.warning("telemetry %s: %d ST 0601 KLV streams (one per sensor?); reading PID %s only, ignoring %s",
                    source, len(ignored) + 1, chosen,
                    ", ".join(f"PID {pid} ({n} packets)" for pid, n in ignored.items()))
    report = replace(_report(source, decoder, height_offset_m=height_offset_m, ts=ts), ignored_streams=ignored)
    if report.repeated_stamps:
        log.info("telemetry %s: %d of %d packets repeat the time stamp before them (held stamps): %s", source,
                 report.repeated_stamps, len(report.samples),
                 "their times are their PTS on the stamps' clock (offset where each stamp is new)"
                 if report.times_from == "pts" else
                 "without PTS, they are spread evenly up to the next stamp (a whole-second stamp over its second)")
    if not report.records:
        raise ValueError(_no_record_message(report))
    _log_report(report)
    return report


def read_klv(path: str | Path, **kw: Any) -> list[Telemetry]:
    """The records of `read_klv_report` (same arguments)."""
    return read_klv_report(path, **kw).records

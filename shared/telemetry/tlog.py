"""MAVLink ``.tlog`` files (QGroundControl, MAVProxy) to `Telemetry` records: the vehicle, its boots and clocks,
its gimbal interpolated to each position, and when its camera recorded.

The messages are turned into samples by `shared.telemetry.mavlink.MavlinkAssembler`; here the whole log is known,
so the gimbal is interpolated between its readings (`shared.telemetry.gimbal_track`) and the recording is found in
the camera's messages (`shared.telemetry.recording`).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from shared.telemetry.gimbal_track import camera_angles, describe_spans, hold_limit_s
from shared.telemetry.mavlink import _BOOT_CLOCKED, _HANDLERS, MavlinkAssembler, MavlinkByteParser, MavlinkSample
from shared.telemetry.mavlink_clock import BootTimeUnwrap, boot_segments, interpolate_yaw_deg, receive_offset_s
from shared.telemetry.record import Telemetry, pitch_or_none
from shared.telemetry.recording import FlightLogReport, LogRecording, from_commands, from_status, mark_recording

__all__ = ["parse_tlog", "parse_tlog_report", "read_tlog", "read_tlog_report"]

log = logging.getLogger(__name__)

#: MAV_CMD_VIDEO_START_CAPTURE, MAV_CMD_VIDEO_STOP_CAPTURE; MAV_RESULT_ACCEPTED.
_VIDEO_START, _VIDEO_STOP, _ACCEPTED = 2500, 2501, 0
#: A gimbal's own ``time_boot_ms`` times its readings (steadier than their receive times, which carry the link's
#: latency jitter) where it runs with the receive clock: receive minus own time within this of its low percentile.
_OWN_CLOCK_S = 1.0


@dataclass(slots=True)
class _Camera:
    """The camera's messages of a log, on the records' clock: status (t, video_status, recording_time_ms) of the
    first camera that sends one; accepted start/stop acknowledgements; start/stop commands sent to the vehicle."""

    status: list[tuple[float, float, float]] = field(default_factory=list)
    status_from: tuple[int, int] | None = None
    acks: dict[int, list[float]] = field(default_factory=lambda: {_VIDEO_START: [], _VIDEO_STOP: []})
    acked: set[int] = field(default_factory=set)  # commands with any acknowledgement (accepted or not)
    commands: dict[int, list[float]] = field(default_factory=lambda: {_VIDEO_START: [], _VIDEO_STOP: []})

    def add(self, m: _Message, t: float) -> None:
        f = m.fields
        if m.type == "CAMERA_CAPTURE_STATUS":
            self.status_from = self.status_from or (m.system, m.component)
            if (m.system, m.component) == self.status_from:
                self.status.append((t, float(f.get("video_status", math.nan)),
                                    float(f.get("recording_time_ms", math.nan))))
        elif m.type == "COMMAND_ACK" and f.get("command") in self.acks:
            self.acked.add(f["command"])
            if f.get("result") == _ACCEPTED:
                self.acks[f["command"]].append(t)
        elif m.type == "COMMAND_LONG" and f.get("command") in self.commands:
            self.commands[f["command"]].append(t)

    def recording(self) -> LogRecording:
        """The recording the messages say: the status with its elapsed time first, then accepted commands (a
        command whose acknowledgement the log lacks altogether counts: a logger that kept only one direction),
        then the status's transitions; a note when there are messages but no start."""
        status = LogRecording()
        if self.status:
            t, video, elapsed = (np.array(c) for c in zip(*sorted(self.status), strict=True))
            status = from_status(t, video, elapsed)
        if status.precise:
            return status
        starts = self.acks[_VIDEO_START] or ([] if _VIDEO_START in self.acked else self.commands[_VIDEO_START])
        stops = self.acks[_VIDEO_STOP] or ([] if _VIDEO_STOP in self.acked else self.commands[_VIDEO_STOP])
        kind = "COMMAND_ACK" if self.acks[_VIDEO_START] else "COMMAND_LONG"
        commands = from_commands(starts, stops, f"MAV_CMD_VIDEO_START_CAPTURE ({kind})")
        if commands.spans:
            return commands
        if not status.spans and _VIDEO_START in self.acked:
            return replace(status, note="; ".join(filter(None, [status.note, "MAV_CMD_VIDEO_START_CAPTURE was not "
                                                                  "accepted (COMMAND_ACK)"])))
        return status


def _packet_size(data: bytes, at: int) -> int | None:
    """Length of the MAVLink packet starting at `at` (v1 0xFE or v2 0xFD), or None."""
    if at + 3 > len(data):
        return None
    if data[at] == 0xFD:
        return 12 + data[at + 1] + (13 if data[at + 2] & 0x01 else 0)
    if data[at] == 0xFE:
        return 8 + data[at + 1]
    return None


def parse_tlog_report(data: bytes, *, source: str = "<tlog>", height_offset_m: float = 0.0,
                      system_id: int | None = None) -> FlightLogReport:
    """Records of a ``.tlog`` (what QGroundControl and MAVProxy write: per packet a big-endian uint64 UNIX time
    in microseconds, then the MAVLink packet), sorted by time, and what the log says about the camera's recording.

    The vehicle: ``system_id``, else the system with the most ``GLOBAL_POSITION_INT`` (a warning names every system
    that sent positions, with its count, when there are several; ties go to the first to send one). Of several
    gimbals the first seen is used (a warning names the others).

    Times: per boot of the autopilot (a reboot restarts ``time_boot_ms``; a warning names it) its boot clock,
    anchored to UNIX by its own ``SYSTEM_TIME`` (the clock after its last jump: a warning gives the jumps), else by
    the log's receive times (`receive_offset_s`: a low percentile of receive minus boot time, a ground station's
    clock). ``height_offset_m`` is added to every height (e.g. the take-off point's height above the ground under
    the flight).

    The gimbal's readings are timed on the boot clock (by their own ``time_boot_ms`` where it runs with the log's
    clock, else by their receive times) and interpolated to each position: pitch and roll linearly, heading on the
    short arc, each in the frame of the reading in effect; none is carried more than `hold_limit_s` beyond the
    readings (a gimbal that stopped reporting): those positions get no gimbal pitch and the vehicle's yaw as heading
    (one warning counts them). The recording: `_Camera.recording` (CAMERA_CAPTURE_STATUS, the video start/stop
    commands), set on the records as `Telemetry.recording`.

    Raises ValueError naming `source` when no position of a vehicle (of ``system_id``) is in the log.
    """
    messages = _tlog_messages(data)
    vehicle, autopilot = _choose_vehicle(messages, system_id, source)
    messages = [m for m in messages if m.system == vehicle
                or (m.type == "COMMAND_LONG" and m.fields.get("target_system") in (vehicle, 0))]
    clock = BootTimeUnwrap()  # as each boot's assembler unwraps it (a wrap is no reboot)
    boots = np.array([clock.unwrap(m.values[_BOOT_MS_AT[m.type]], m.stamp_s) / 1e3
                      if m.type in _BOOT_CLOCKED and m.component in (autopilot, None) and m.system == vehicle
                      else math.nan for m in messages])
    stamps = np.array([m.stamp_s for m in messages])
    segment_of = boot_segments(stamps, boots)
    starts = [0, *(np.flatnonzero(np.diff(segment_of)) + 1).tolist(), len(messages)]
    if len(starts) > 2:
        _warn_reboots(source, stamps, boots, starts)
    timed: list[tuple[Telemetry, bool]] = []  # (record, its gimbal reading too far away)
    jumps: list[tuple[float, float]] = []
    gimbal_used: str | None = None
    gimbals_ignored: dict[str, int] = {}
    hold_s = math.nan
    camera = _Camera()
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        assembler = MavlinkAssembler(vehicle, keep_attitudes=True, component_id=autopilot)
        assembler.gimbal_used = gimbal_used  # one gimbal for the whole log
        samples = [s for m in messages[a:b]
                   if (s := assembler.add(m.type, m.fields, m.system, m.component, m.stamp_s)) is not None]
        gimbal_used = assembler.gimbal_used
        for key, count in assembler.gimbals_ignored.items():
            gimbals_ignored[key] = gimbals_ignored.get(key, 0) + count
        rx_offset = receive_offset_s(stamps[a:b], boots[a:b])  # the receive clock's time of boot 0
        offset = assembler.unix_offset_s
        if offset is None:
            offset = rx_offset
        for m in messages[a:b]:
            if m.type in _CAMERA_MESSAGES and math.isfinite(rx_offset):
                camera.add(m, m.stamp_s - rx_offset + offset)
        if not samples:
            continue
        stale = np.zeros(len(samples), dtype=bool)
        gimbal = np.array(assembler.gimbal_samples or [], dtype=float).reshape(-1, 6)
        if len(gimbal):
            t_gimbal = _gimbal_boot_s(gimbal[:, 0], gimbal[:, 1], rx_offset)
            hold_s = hold_limit_s(t_gimbal) if math.isnan(hold_s) else hold_s
            samples, stale = _with_gimbal(samples, t_gimbal, gimbal[:, 2:], assembler.attitudes or [], hold_s)
        else:
            samples = _with_attitude_yaw(samples, assembler.attitudes or [])
        jumps.extend(assembler.clock_jumps)
        by_boot: dict[float, tuple[Telemetry, bool]] = {}
        for s, old in zip(samples, stale, strict=True):  # one record per boot time (a router's repeat counts once)
            by_boot.setdefault(s.boot_s, (s.to_telemetry(offset, height_offset_m), bool(old)))
        timed.extend(by_boot.values())
    if not timed:
        raise ValueError(f"{source}: no vehicle position (GLOBAL_POSITION_INT) in the MAVLink log")
    if jumps:
        log.warning("%s: the vehicle's UNIX clock (SYSTEM_TIME) jumped %s (first set from the ground station, then "
                    "from GPS?): times use its clock after the last jump", source,
                    ", ".join(f"by {step:+.3f} s at boot {boot:.1f} s" for boot, step in jumps))
    if gimbals_ignored:
        log.warning("%s: several gimbals: using %s (the first seen), ignoring %s", source, gimbal_used,
                    ", ".join(f"{key} ({count} messages)" for key, count in gimbals_ignored.items()))
    timed.sort(key=lambda item: item[0].t)
    records = [r for r, _ in timed]
    stale_mask = np.array([old for _, old in timed])
    if stale_mask.any():
        log.warning("%s: the gimbal's readings are more than %.1f s away from %d of %d positions (%s after the "
                    "first record): they get no gimbal pitch (pass --pitch-deg for a fixed camera) and the vehicle's "
                    "yaw as heading", source, hold_s, int(stale_mask.sum()), len(records),
                    describe_spans([r.t for r in records], stale_mask, records[0].t))
    recording = camera.recording()
    if recording.note:
        log.warning("%s: %s", source, recording.note)
    return FlightLogReport(mark_recording(records, recording), recording)


def parse_tlog(data: bytes, **kw: Any) -> list[Telemetry]:
    """The records of `parse_tlog_report`."""
    return parse_tlog_report(data, **kw).records


def read_tlog_report(path: str | Path, **kw: Any) -> FlightLogReport:
    """`parse_tlog_report` of a file."""
    return parse_tlog_report(Path(path).read_bytes(), source=str(path), **kw)


def read_tlog(path: str | Path, **kw: Any) -> list[Telemetry]:
    """`parse_tlog` of a file."""
    return read_tlog_report(path, **kw).records


def _gimbal_boot_s(rx_s: np.ndarray, own_s: np.ndarray, rx_offset_s: float) -> np.ndarray:
    """(M,) gimbal readings' times on the autopilot's boot clock, from their receive times (M,) and their own
    ``time_boot_ms`` in seconds (M,; NaN: none). The own clock (a gimbal device's, or the autopilot's in
    MOUNT_ORIENTATION) is put on the boot clock through the receive clock, as the autopilot's is
    (`receive_offset_s`), and used for the readings it agrees with (receive minus own time within `_OWN_CLOCK_S` of
    that offset: not a wrapped, restarted or zero clock) when half of them do; the others are placed at their
    receive time (late by their latency above the link's smallest)."""
    by_rx = rx_s - rx_offset_s
    own_offset = receive_offset_s(rx_s, np.where(own_s > 0, own_s, np.nan))
    if not math.isfinite(own_offset):
        return by_rx
    agree = np.abs(rx_s - own_s - own_offset) <= _OWN_CLOCK_S  # NaN: False
    return np.where(agree, own_s + own_offset - rx_offset_s, by_rx) if agree.mean() >= 0.5 else by_rx


def _with_gimbal(samples: list[MavlinkSample], t_gimbal: np.ndarray, angles: np.ndarray,
                 attitudes: list[tuple[float, float]], hold_s: float) -> tuple[list[MavlinkSample], np.ndarray]:
    """The samples with the gimbal's readings (times (M,), angles (M, 4): pitch up, roll, yaw deg, earth frame)
    interpolated to their boot times (`camera_angles`), and (N,) bool: no reading within hold_s."""
    order = np.argsort(t_gimbal, kind="stable")
    t_g, (pitch_g, roll_g, yaw_g, earth_g) = t_gimbal[order], angles[order].T
    if attitudes:
        t_v, yaw_v = np.array(attitudes, dtype=float).T
    else:  # no ATTITUDE: the positions' own heading (hdg)
        t_v, yaw_v = np.array([(s.boot_s, math.nan if s.vehicle_yaw_deg is None else s.vehicle_yaw_deg)
                               for s in samples], dtype=float).T
    t = np.array([s.boot_s for s in samples])
    pitch, roll, heading, stale = camera_angles(t, t_g, pitch_g, roll_g, yaw_g, earth_g.astype(bool), t_v, yaw_v,
                                                hold_s)
    out = [replace(s, pitch_deg=None if not math.isfinite(p) else pitch_or_none(-p, f"MAVLink gimbal pitch {p:g} deg",
                                                                                 warn=False),
                   roll_deg=float(r), heading_deg=None if not math.isfinite(h) else h % 360.0, yaw_rel_deg=None)
           for s, p, r, h in zip(samples, pitch, roll, heading, strict=True)]
    return out, stale


@dataclass(frozen=True, slots=True)
class _Message:
    stamp_s: float  # the log's receive time, UNIX seconds
    type: str
    values: tuple[Any, ...]  # of _FIELDS[type], None where the message lacks the field (an older dialect)
    system: int
    component: int

    @property
    def fields(self) -> dict[str, Any]:
        return {name: v for name, v in zip(_FIELDS[self.type], self.values, strict=True) if v is not None}


#: The fields the assembler reads, per message it uses: a log is held decoded before the vehicle is chosen, and
#: pymavlink's whole dict of a message cost ~0.8 kB (a 30-minute log with 50 Hz ATTITUDE: 290k of them); a tuple
#: of these values ~0.2 kB.
_FIELDS: dict[str, tuple[str, ...]] = {
    "GLOBAL_POSITION_INT": ("time_boot_ms", "lat", "lon", "relative_alt", "vx", "vy", "hdg"),
    "ATTITUDE": ("time_boot_ms", "yaw"),
    "GIMBAL_DEVICE_ATTITUDE_STATUS": ("q", "flags", "gimbal_device_id", "time_boot_ms"),
    "MOUNT_ORIENTATION": ("pitch", "roll", "yaw", "yaw_absolute", "time_boot_ms"),
    "MOUNT_STATUS": ("pointing_a", "pointing_b", "pointing_c"),
    "CAMERA_FOV_STATUS": ("hfov", "camera_device_id"),
    "SYSTEM_TIME": ("time_unix_usec", "time_boot_ms"),
    "CAMERA_CAPTURE_STATUS": ("video_status", "recording_time_ms"),
    "COMMAND_ACK": ("command", "result"),
    "COMMAND_LONG": ("command", "target_system"),
}
#: The camera's messages that say when it recorded (`_Camera`).
_CAMERA_MESSAGES = frozenset({"CAMERA_CAPTURE_STATUS", "COMMAND_ACK", "COMMAND_LONG"})
_USED = frozenset(_HANDLERS) | {"SYSTEM_TIME"} | _CAMERA_MESSAGES
_BOOT_MS_AT = {kind: _FIELDS[kind].index("time_boot_ms") for kind in _BOOT_CLOCKED}


def _tlog_messages(data: bytes) -> list[_Message]:
    """The messages of a ``.tlog`` that the assembler uses, in log order; noise and broken packets skipped."""
    parser = MavlinkByteParser()
    out: list[_Message] = []
    pos = 0
    while pos + 8 < len(data):
        size = _packet_size(data, pos + 8)
        if size is None or pos + 8 + size > len(data):
            pos += 1  # not a record start: resynchronise byte by byte
            continue
        msg = parser.decode_packet(data[pos + 8:pos + 8 + size])
        if msg is None:
            pos += 1
            continue
        kind = msg.get_type()
        if kind in _USED:
            (stamp_us,) = struct.unpack(">Q", data[pos:pos + 8])
            values = tuple(getattr(msg, name, None) for name in _FIELDS[kind])
            out.append(_Message(stamp_us / 1e6, kind, values, msg.get_srcSystem(), msg.get_srcComponent()))
        pos += 8 + size
    return out


def _choose_vehicle(messages: list[_Message], system_id: int | None, source: str) -> tuple[int, int]:
    """(system id, autopilot component id) of the vehicle: `system_id`, else the system with the most positions."""
    counts: dict[int, int] = {}
    components: dict[int, int] = {}
    for m in messages:
        if m.type == "GLOBAL_POSITION_INT":
            counts[m.system] = counts.get(m.system, 0) + 1
            components.setdefault(m.system, m.component)
    named = ", ".join(f"system {sysid} ({n} positions)" for sysid, n in counts.items())
    if system_id is not None:
        if system_id not in counts:
            raise ValueError(f"{source}: no vehicle position (GLOBAL_POSITION_INT) of system {system_id} in the "
                             f"MAVLink log ({named or 'no system sent one'})")
        return system_id, components[system_id]
    if not counts:
        raise ValueError(f"{source}: no vehicle position (GLOBAL_POSITION_INT) in the MAVLink log")
    chosen = max(counts, key=lambda sysid: counts[sysid])  # the first of equal counts: the first to send one
    if len(counts) > 1:
        log.warning("%s: positions (GLOBAL_POSITION_INT) of %d vehicles: %s; reading system %d (the most positions; "
                    "read_tlog's system_id chooses another)", source, len(counts), named, chosen)
    return chosen, components[chosen]


def _warn_reboots(source: str, stamps: np.ndarray, boots: np.ndarray, starts: list[int]) -> None:
    """One warning naming each reboot: the log time and the boot time before and after."""
    parts = []
    for a, b, c in zip(starts[:-2], starts[1:-1], starts[2:], strict=True):
        before, after = np.nanmax(boots[a:b]), boots[b:c][np.isfinite(boots[b:c])][0]
        parts.append(f"at {_utc(stamps[b])} (time_boot_ms {before:.1f} s -> {after:.1f} s)")
    log.warning("%s: the autopilot rebooted %d time(s) %s: each boot is read on its own clock (its own SYSTEM_TIME, "
                "else the log's receive times)", source, len(parts), ", ".join(parts))


def _utc(stamp_s: float) -> str:
    try:
        return datetime.fromtimestamp(stamp_s, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, OSError, ValueError):
        return f"log time {stamp_s:.3f} s"


def _with_attitude_yaw(samples: list[MavlinkSample], attitudes: list[tuple[float, float]]) -> list[MavlinkSample]:
    """Samples whose heading follows the vehicle's yaw (a fixed camera) get the yaw interpolated to their boot time
    where two ``ATTITUDE`` bracket it (messages come at their own rates); others keep theirs (the latest, held)."""
    if not attitudes:
        return samples
    t_att, yaw_att = np.array(attitudes, dtype=float).T
    rel = np.array([math.nan if s.yaw_rel_deg is None else s.yaw_rel_deg for s in samples])
    heading = (interpolate_yaw_deg(t_att, yaw_att, [s.boot_s for s in samples]) + rel) % 360.0
    held = np.array([math.nan if s.heading_deg is None else s.heading_deg for s in samples])
    moved = np.isfinite(heading) & ~(np.abs((heading - held + 180.0) % 360.0 - 180.0) < 1e-9)  # NaN held: moved
    out = list(samples)
    for i in np.flatnonzero(moved):  # only those that change: most logs stream ATTITUDE with each position
        out[i] = replace(samples[i], heading_deg=float(heading[i]))
    return out

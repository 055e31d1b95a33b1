"""MAVLink telemetry (PX4, ArduPilot): decoded messages to `Telemetry` records, and `.tlog` files read from bytes.

No sockets here (the live UDP link is `agent.mavlink_feed`); the bytes are decoded by pymavlink's generated
parser (optional extra ``mavlink``), imported when first needed.

Messages used (one record per ``GLOBAL_POSITION_INT`` of the vehicle, with the latest attitude and gimbal):
- ``GLOBAL_POSITION_INT``: lat, lon (1e-7 deg), ``relative_alt`` (mm above home: the height above the ground
  when the ground is level with the take-off point), vx, vy (cm/s north, east), ``time_boot_ms``;
- ``ATTITUDE``: the vehicle's yaw (rad): the heading of a gimbal whose yaw is in the vehicle frame, and of a
  fixed forward camera when no gimbal message comes;
- ``GIMBAL_DEVICE_ATTITUDE_STATUS``: quaternion; pitch and roll relative to the horizon, yaw in the earth frame
  or the vehicle frame as the flags say (``YAW_IN_EARTH_FRAME`` / ``YAW_IN_VEHICLE_FRAME``, else ``YAW_LOCK``
  = earth frame, as MAVLink specifies);
- ``MOUNT_ORIENTATION`` (ArduPilot: pitch, roll, yaw relative to the vehicle, ``yaw_absolute``) and the older
  ``MOUNT_STATUS`` (centidegrees; yaw relative to the vehicle);
- ``SYSTEM_TIME``: UNIX time of the boot clock, so records are stamped in UNIX seconds.

Pitch becomes our depression (MAVLink: negative down, -90 = nadir); heading is wrapped to [0, 360).
"""

from __future__ import annotations

import math
import statistics
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.telemetry.record import Telemetry, pitch_or_none

__all__ = [
    "MAVLINK_EXTRA_HINT",
    "MavlinkAssembler",
    "MavlinkByteParser",
    "MavlinkSample",
    "parse_tlog",
    "read_tlog",
]

#: What to install when pymavlink is missing.
MAVLINK_EXTRA_HINT = "MAVLink telemetry needs pymavlink: pip install 'uav-memory-maps[mavlink]'"

_YAW_LOCK = 16
_YAW_IN_VEHICLE_FRAME = 32
_YAW_IN_EARTH_FRAME = 64
_UNKNOWN_HDG = 65535


#: Within this (the horizontal length of the unit optical axis: ~0.06 deg of the vertical) a camera looks straight
#: down or up: its yaw and roll turn about one axis (gimbal lock) and cannot be told apart.
_VERTICAL = 1e-3


def quaternion_to_euler_deg(q: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """(w, x, y, z) -> (roll, pitch, yaw) in degrees, aerospace order (yaw about z down, then pitch, roll).

    The quaternion need not be normalised; a zero quaternion raises ValueError. Pitch comes from the optical axis
    (exact at any angle); a camera looking straight down or up (within ~0.06 deg, as a nadir mapping gimbal or one
    at its end stop does, its float32 quaternion rounded) has no roll told apart from its yaw: the turn about the
    vertical is the yaw (the heading the top of the image points to when looking down), roll 0.
    """
    w, x, y, z = (float(v) for v in q)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not norm > 0 or not math.isfinite(norm):
        raise ValueError(f"gimbal quaternion {q!r} is not a rotation")
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    # the body axes in north-east-down: forward (the optical axis) and down (the image's bottom, roll 0)
    fn, fe, fd = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)
    dn, de = 2 * (x * z + w * y), 2 * (y * z - w * x)
    level = math.hypot(fn, fe)
    pitch = math.atan2(-fd, level)
    if level > _VERTICAL:
        yaw = math.atan2(fe, fn)
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    else:  # looking down, the top of the image (-down) points along the heading; looking up, the bottom does
        sign = 1.0 if fd > 0 else -1.0
        yaw = math.atan2(-sign * de, -sign * dn)
        roll = 0.0
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


@dataclass(frozen=True, slots=True)
class MavlinkSample:
    """One position of the vehicle with the camera's angles, on the flight controller's boot clock.

    boot_s: seconds since the autopilot booted; pitch_deg: depression 0..90 or None (no gimbal message, or the
    camera looking up); heading_deg: camera heading or None; vel_en: (east, north) m/s.
    """

    boot_s: float
    lat: float
    lon: float
    height_m: float
    pitch_deg: float | None
    heading_deg: float | None
    roll_deg: float
    vel_en: tuple[float, float]

    def to_telemetry(self, clock_offset_s: float = 0.0, height_offset_m: float = 0.0) -> Telemetry:
        """The record at time ``boot_s + clock_offset_s`` with ``height_offset_m`` added to the height."""
        return Telemetry(t=self.boot_s + clock_offset_s, lat=self.lat, lon=self.lon,
                         height_m=self.height_m + height_offset_m, pitch_deg=self.pitch_deg,
                         heading_deg=self.heading_deg, roll_deg=self.roll_deg,
                         speed_mps=math.hypot(*self.vel_en), vel_en_mps=self.vel_en)


@dataclass(slots=True)
class _Gimbal:
    pitch_deg: float  # MAVLink convention: positive up
    roll_deg: float
    yaw_deg: float
    earth_frame: bool


class MavlinkAssembler:
    """Turns a stream of decoded MAVLink messages into `MavlinkSample`s.

    Call `add(type, fields, src_system)` per message (``fields`` as pymavlink's ``to_dict()``); it returns a
    sample for each ``GLOBAL_POSITION_INT`` of the vehicle, else None. The vehicle is ``system_id``, or the
    first system that sends a position; messages of other systems are ignored (a GCS, another drone).
    ``unix_offset_s`` is the UNIX time of boot once a ``SYSTEM_TIME`` with a UNIX time has come (else None).
    """

    def __init__(self, system_id: int | None = None) -> None:
        self.system_id = system_id
        self.vehicle_yaw_deg: float | None = None
        self.gimbal: _Gimbal | None = None
        self.unix_offset_s: float | None = None
        self.counts: dict[str, int] = {}

    def add(self, msg_type: str, fields: Mapping[str, Any], src_system: int | None = None) -> MavlinkSample | None:
        """Take one message; a sample when it was the vehicle's position."""
        if msg_type == "GLOBAL_POSITION_INT" and self.system_id is None and src_system is not None:
            self.system_id = src_system
        if self.system_id is not None and src_system is not None and src_system != self.system_id:
            return None
        handler = _HANDLERS.get(msg_type)
        if handler is None:
            return None
        self.counts[msg_type] = self.counts.get(msg_type, 0) + 1
        return handler(self, fields)

    # ---- handlers --------------------------------------------------------------------------------
    def _system_time(self, f: Mapping[str, Any]) -> None:
        unix_us, boot_ms = int(f["time_unix_usec"]), int(f["time_boot_ms"])
        if unix_us > 0 and self.unix_offset_s is None:
            self.unix_offset_s = unix_us / 1e6 - boot_ms / 1e3
        return None

    def _attitude(self, f: Mapping[str, Any]) -> None:
        yaw = float(f["yaw"])
        if math.isfinite(yaw):
            self.vehicle_yaw_deg = math.degrees(yaw)
        return None

    def _gimbal_device(self, f: Mapping[str, Any]) -> None:
        try:
            roll, pitch, yaw = quaternion_to_euler_deg(tuple(f["q"]))  # type: ignore[arg-type]
        except ValueError:
            return None
        flags = int(f["flags"])
        if flags & _YAW_IN_EARTH_FRAME:
            earth = True
        elif flags & _YAW_IN_VEHICLE_FRAME:
            earth = False
        else:
            earth = bool(flags & _YAW_LOCK)
        self.gimbal = _Gimbal(pitch, roll, yaw, earth)
        return None

    def _mount_orientation(self, f: Mapping[str, Any]) -> None:
        absolute = float(f.get("yaw_absolute", math.nan))
        earth = math.isfinite(absolute) and absolute != 0.0
        yaw = absolute if earth else float(f["yaw"])
        self.gimbal = _Gimbal(float(f["pitch"]), float(f["roll"]), yaw, earth)
        return None

    def _mount_status(self, f: Mapping[str, Any]) -> None:
        self.gimbal = _Gimbal(f["pointing_a"] / 100.0, f["pointing_b"] / 100.0, f["pointing_c"] / 100.0, False)
        return None

    def _position(self, f: Mapping[str, Any]) -> MavlinkSample | None:
        lat, lon = f["lat"] / 1e7, f["lon"] / 1e7
        if (lat, lon) == (0.0, 0.0):  # no GPS fix yet
            return None
        vehicle_yaw = self.vehicle_yaw_deg
        if vehicle_yaw is None and int(f.get("hdg", _UNKNOWN_HDG)) != _UNKNOWN_HDG:
            vehicle_yaw = f["hdg"] / 100.0
        gimbal = self.gimbal
        pitch: float | None
        if gimbal is None:  # a fixed camera: it looks where the vehicle heads; its tilt comes from --pitch-deg
            pitch, roll, heading = None, 0.0, vehicle_yaw
        else:
            pitch = pitch_or_none(-gimbal.pitch_deg, f"MAVLink gimbal pitch {gimbal.pitch_deg:g} deg")
            roll = gimbal.roll_deg
            heading = gimbal.yaw_deg if gimbal.earth_frame else (
                None if vehicle_yaw is None else vehicle_yaw + gimbal.yaw_deg)
        return MavlinkSample(boot_s=f["time_boot_ms"] / 1e3, lat=lat, lon=lon, height_m=f["relative_alt"] / 1e3,
                             pitch_deg=pitch, heading_deg=None if heading is None else heading % 360.0,
                             roll_deg=roll, vel_en=(f["vy"] / 100.0, f["vx"] / 100.0))


_HANDLERS = {
    "GLOBAL_POSITION_INT": MavlinkAssembler._position,
    "ATTITUDE": MavlinkAssembler._attitude,
    "GIMBAL_DEVICE_ATTITUDE_STATUS": MavlinkAssembler._gimbal_device,
    "MOUNT_ORIENTATION": MavlinkAssembler._mount_orientation,
    "MOUNT_STATUS": MavlinkAssembler._mount_status,
    "SYSTEM_TIME": MavlinkAssembler._system_time,
}


class MavlinkByteParser:
    """MAVLink 1/2 bytes -> decoded messages (pymavlink's ardupilotmega dialect, a superset of common).

    Bytes that are no valid packet (noise, a packet cut by a lost datagram, a bad CRC) are skipped.
    """

    def __init__(self) -> None:
        try:
            from pymavlink.dialects.v20 import ardupilotmega
        except ImportError:
            raise ImportError(MAVLINK_EXTRA_HINT) from None
        self._mav = ardupilotmega.MAVLink(None)
        self._mav.robust_parsing = True

    def feed(self, data: bytes) -> list[Any]:
        """The messages completed by these bytes of a stream (pymavlink message objects; bad packets dropped)."""
        return [m for m in (self._mav.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]

    def decode_packet(self, packet: bytes) -> Any | None:
        """One complete packet -> its message, or None (bad CRC, unknown message, cut short)."""
        try:
            msg = self._mav.decode(bytearray(packet))
        except Exception:  # pymavlink raises MAVError and struct/index errors alike for broken packets
            return None
        return None if msg is None or msg.get_type() == "BAD_DATA" else msg


def _packet_size(data: bytes, at: int) -> int | None:
    """Length of the MAVLink packet starting at `at` (v1 0xFE or v2 0xFD), or None."""
    if at + 3 > len(data):
        return None
    if data[at] == 0xFD:
        return 12 + data[at + 1] + (13 if data[at + 2] & 0x01 else 0)
    if data[at] == 0xFE:
        return 8 + data[at + 1]
    return None


def parse_tlog(data: bytes, *, source: str = "<tlog>", height_offset_m: float = 0.0,
               system_id: int | None = None) -> list[Telemetry]:
    """Records of a ``.tlog`` (what QGroundControl and MAVProxy write: per packet a big-endian uint64 UNIX time
    in microseconds, then the MAVLink packet).

    Times: the autopilot's boot clock anchored to UNIX by its first ``SYSTEM_TIME`` with a UNIX time, else by the
    log's own receive times (the median over the positions: a ground station's clock). ``height_offset_m`` is
    added to every height (e.g. the take-off point's height above the ground under the flight).

    Raises ValueError naming `source` when no position of a vehicle is in the log.
    """
    parser = MavlinkByteParser()
    assembler = MavlinkAssembler(system_id)
    samples: list[tuple[float, MavlinkSample]] = []
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
        (stamp_us,) = struct.unpack(">Q", data[pos:pos + 8])
        sample = assembler.add(msg.get_type(), msg.to_dict(), msg.get_srcSystem())
        if sample is not None:
            samples.append((stamp_us / 1e6, sample))
        pos += 8 + size
    if not samples:
        raise ValueError(f"{source}: no vehicle position (GLOBAL_POSITION_INT) in the MAVLink log")
    offset = assembler.unix_offset_s
    if offset is None:
        offset = statistics.median(stamp - s.boot_s for stamp, s in samples)
    records: dict[float, Telemetry] = {}
    for _, s in samples:  # one record per boot time (a position repeated by a router counts once)
        records.setdefault(s.boot_s, s.to_telemetry(offset, height_offset_m))
    return [records[k] for k in sorted(records)]


def read_tlog(path: str | Path, **kw: Any) -> list[Telemetry]:
    """`parse_tlog` of a file."""
    return parse_tlog(Path(path).read_bytes(), source=str(path), **kw)

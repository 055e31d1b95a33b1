"""MAVLink test data written with pymavlink's own encoder: packets for a flight (from `Telemetry` records), as a
``.tlog`` file or as datagrams to replay over UDP; a minimal PX4 ULog file per the documented format."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Sequence
from pathlib import Path

import pytest

from shared.telemetry import Telemetry

BOOT_MS0 = 20_000  # the autopilot booted 20 s before the first record


def euler_to_quaternion(roll_deg: float, pitch_deg: float, yaw_deg: float) -> list[float]:
    """(w, x, y, z) of the aerospace rotation yaw, then pitch, then roll (degrees)."""
    r, p, y = (math.radians(v) / 2 for v in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy]


def flight_packets(records: Sequence[Telemetry], *, gimbal: str = "device-earth", system_time: bool = True,
                   vehicle_yaw_offset_deg: float = -20.0, system_id: int = 1, boot_ms0: int = BOOT_MS0,
                   gimbal_component: int = 154) -> list[tuple[float, bytes]]:
    """(UNIX receive time, packet) per message of a flight whose camera follows `records`.

    gimbal: "device-earth" (GIMBAL_DEVICE_ATTITUDE_STATUS, yaw in the earth frame), "device-vehicle" (yaw in the
    vehicle frame), "mount-orientation" (ArduPilot MOUNT_ORIENTATION, degrees, with yaw_absolute),
    "mount-orientation-relative" (yaw_absolute NaN: only the yaw relative to the vehicle), "mount-status" (ArduPilot
    MOUNT_STATUS, centidegrees, yaw relative to the vehicle), "none"
    (a fixed camera: the vehicle's yaw is the camera heading). The vehicle heads `vehicle_yaw_offset_deg` off the
    camera (0 for "none"). The autopilot (component 1) has been up `boot_ms0` ms at the first record; a
    "device-*" gimbal is component `gimbal_component`.
    """
    from pymavlink.dialects.v20 import ardupilotmega

    mav = ardupilotmega.MAVLink(None, srcSystem=system_id, srcComponent=1)
    gimbal_mav = ardupilotmega.MAVLink(None, srcSystem=system_id, srcComponent=gimbal_component)
    t0 = records[0].t
    out: list[tuple[float, bytes]] = []
    for rec in records:
        boot_ms = boot_ms0 + int(round((rec.t - t0) * 1000))
        heading = rec.heading_deg or 0.0
        yaw_vehicle = heading - (vehicle_yaw_offset_deg if gimbal != "none" else 0.0)
        msgs = []  # (message, the link that packs it: the autopilot's or the gimbal's component)
        if system_time:
            msgs.append((mav.system_time_encode(int(round(rec.t * 1e6)), boot_ms), mav))
        msgs.append((mav.attitude_encode(boot_ms, 0.0, 0.0, math.radians((yaw_vehicle + 180) % 360 - 180), 0, 0, 0),
                     mav))
        pitch_up = -(rec.pitch_deg or 0.0)
        if gimbal == "device-earth":
            msgs.append((gimbal_mav.gimbal_device_attitude_status_encode(
                0, 0, boot_ms, 16 | 64, euler_to_quaternion(rec.roll_deg, pitch_up, heading), 0, 0, 0, 0), gimbal_mav))
        elif gimbal == "device-vehicle":
            q = euler_to_quaternion(rec.roll_deg, pitch_up, heading - yaw_vehicle)
            msgs.append((gimbal_mav.gimbal_device_attitude_status_encode(0, 0, boot_ms, 32, q, 0, 0, 0, 0), gimbal_mav))
        elif gimbal in ("mount-orientation", "mount-orientation-relative"):  # ArduPilot 4.x: degrees
            absolute = heading % 360.0 if gimbal == "mount-orientation" else math.nan  # NaN: unknown (older firmware)
            msgs.append((mav.mount_orientation_encode(boot_ms, rec.roll_deg, pitch_up, heading - yaw_vehicle,
                                                      absolute), mav))
        elif gimbal == "mount-status":
            msgs.append((mav.mount_status_encode(0, 0, int(round(pitch_up * 100)), int(round(rec.roll_deg * 100)),
                                                 int(round((heading - yaw_vehicle) * 100))), mav))
        vel_e, vel_n = rec.vel_en_mps or (0.0, 0.0)
        height_mm = int(round((rec.height_m or 0.0) * 1e3))
        msgs.append((mav.global_position_int_encode(
            boot_ms, int(round(rec.lat * 1e7)), int(round(rec.lon * 1e7)), height_mm + 400_000, height_mm,
            int(round(vel_n * 100)), int(round(vel_e * 100)), 0, int(round(yaw_vehicle % 360 * 100))), mav))
        out.extend((rec.t + 0.02, msg.pack(link)) for msg, link in msgs)
    return out


def write_tlog(path: Path, packets: Sequence[tuple[float, bytes]]) -> Path:
    """A ``.tlog``: per packet a big-endian uint64 UNIX time in microseconds, then the packet."""
    path.write_bytes(b"".join(struct.pack(">Q", int(round(t * 1e6))) + p for t, p in packets))
    return path


def port_is_bound(port: int) -> bool:
    """True when some process listens on 127.0.0.1:port (UDP): binding it ourselves fails."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


def replay_udp(packets: Sequence[tuple[float, bytes]], port: int, *, wait_bound_s: float = 30.0,
               rounds: int = 2, pause_s: float = 0.002) -> int:
    """Send the packets to 127.0.0.1:port once the port is bound (the listener is up), `rounds` times.

    Returns the datagrams sent; raises pytest's failure when nobody binds the port in time.
    """
    deadline = time.monotonic() + wait_bound_s
    while not port_is_bound(port):
        if time.monotonic() > deadline:
            pytest.fail(f"nobody listened on udp:127.0.0.1:{port} within {wait_bound_s} s")
        time.sleep(0.05)
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for _ in range(rounds):
            for _t, packet in packets:
                sock.sendto(packet, ("127.0.0.1", port))
                sent += 1
                time.sleep(pause_s)  # a 2 ms pace: a real link's rate, and no loopback buffer overflow
    return sent


# ---- ULog (PX4), written per the format spec (docs.px4.io, "ULog File Format"): pyulog can write a log it has
# read (ULog.write_ulog) but offers no public way to build one from scratch ------------------------------------

_ULOG_MAGIC = b"ULog\x01\x12\x35"
SYNC_MAGIC = bytes([0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12])
_TYPES = {"uint64_t": "Q", "double": "d", "float": "f", "uint32_t": "I", "uint16_t": "H", "uint8_t": "B",
          "int32_t": "i", "bool": "?"}


def ulog_bytes(topics: dict[str | tuple[str, int], tuple[list[tuple[str, str]], list[tuple]]], start_us: int = 0,
               *, sync_every: int = 0) -> bytes:
    """A ULog file: {topic: ([(type, field name), ...], rows)}; the first field must be ``uint64_t timestamp``.

    A topic is a name (instance 0) or (name, multi_id) for another instance of it (each instance gives its fields).
    Array fields are given element by element (``("float", "q[0]")``, ...), which ULog parsers read the same way.
    sync_every > 0 writes a sync message ('S', the magic a reader resyncs at after corrupt data) before every
    sync_every-th data message.
    """
    out = bytearray(_ULOG_MAGIC + bytes([1]) + struct.pack("<Q", start_us))

    def message(kind: str, payload: bytes) -> None:
        out.extend(struct.pack("<HB", len(payload), ord(kind)) + payload)

    named = [((key, 0) if isinstance(key, str) else key, spec) for key, spec in topics.items()]
    message("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))  # flag bits: no compat/incompat flags, no appended data
    for name, fields in dict((name, fields) for (name, _), (fields, _rows) in named).items():
        message("F", f"{name}:{''.join(f'{t} {f};' for t, f in fields)}".encode())
    items = []
    for msg_id, ((name, multi_id), (fields, rows)) in enumerate(named):
        message("A", struct.pack("<BH", multi_id, msg_id) + name.encode())
        fmt = "<" + "".join(_TYPES[t] for t, _ in fields)
        for row in rows:
            items.append((row[0], struct.pack("<H", msg_id) + struct.pack(fmt, *row)))
    for i, (_t, payload) in enumerate(sorted(items, key=lambda item: item[0])):
        if sync_every and i % sync_every == 0:
            message("S", SYNC_MAGIC)
        message("D", payload)
    return bytes(out)

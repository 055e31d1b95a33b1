"""MAVLink telemetry (PX4, ArduPilot): decoded messages to `MavlinkSample`s (a ``.tlog`` file is read in
`shared.telemetry.tlog`, the live UDP link in `agent.mavlink_feed`).

No sockets here; the bytes are decoded by pymavlink's generated parser (optional extra ``mavlink``), imported when
first needed.

Messages used (one record per ``GLOBAL_POSITION_INT`` of the vehicle, with its attitude and the latest gimbal):
- ``GLOBAL_POSITION_INT``: lat, lon (1e-7 deg), ``relative_alt`` (mm above home: the height above the ground
  when the ground is level with the take-off point), vx, vy (cm/s north, east), ``time_boot_ms``;
- ``ATTITUDE``: the vehicle's yaw (rad), interpolated to the position's ``time_boot_ms`` where two bracket it:
  the heading of a gimbal whose yaw is in the vehicle frame, and of a fixed forward camera when no gimbal message
  comes;
- ``GIMBAL_DEVICE_ATTITUDE_STATUS``: quaternion; pitch and roll relative to the horizon, yaw in the earth frame
  or the vehicle frame as the flags say (``YAW_IN_EARTH_FRAME`` / ``YAW_IN_VEHICLE_FRAME``, else ``YAW_LOCK``
  = earth frame, as MAVLink specifies);
- ``MOUNT_ORIENTATION`` (ArduPilot: pitch, roll, yaw relative to the vehicle, ``yaw_absolute``) and the older
  ``MOUNT_STATUS`` (centidegrees; yaw relative to the vehicle);
- ``CAMERA_FOV_STATUS``: the camera's horizontal field of view (a zoom lens; `Telemetry.hfov_deg`), of the first
  camera that sends one (NaN: unknown, none);
- ``SYSTEM_TIME`` of the vehicle's autopilot: UNIX time of the boot clock, so records are stamped in UNIX seconds
  (`shared.telemetry.mavlink_clock`: the clock's jumps, reboots; `BootTimeUnwrap`: a wrap of ``time_boot_ms``).

Pitch becomes our depression (MAVLink: negative down, -90 = nadir); heading is wrapped to [0, 360).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from shared.telemetry.gimbal_track import MIN_HOLD_S, hold_limit_s
from shared.telemetry.mavlink_clock import BootTimeUnwrap, UnixClock, yaw_between_deg
from shared.telemetry.record import Telemetry, pitch_or_none

__all__ = [
    "MAVLINK_EXTRA_HINT",
    "BootTimeUnwrap",
    "MavlinkAssembler",
    "MavlinkByteParser",
    "MavlinkSample",
    "quaternion_to_euler_deg",
]

log = logging.getLogger(__name__)

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

    boot_s: seconds since the autopilot booted (on past a wrap of ``time_boot_ms``); pitch_deg: depression 0..90 or
    None (no gimbal message, or the camera looking up); heading_deg: camera heading or None; vel_en: (east, north)
    m/s; yaw_rel_deg: the camera's yaw relative to the vehicle when the heading is the vehicle's yaw plus it (0 for a
    fixed camera, a gimbal's vehicle-frame yaw), None when the heading is in the earth frame or unknown;
    vehicle_yaw_deg: the vehicle's yaw used (ATTITUDE, else the position's ``hdg``), None when unknown.
    """

    boot_s: float
    lat: float
    lon: float
    height_m: float
    pitch_deg: float | None
    heading_deg: float | None
    roll_deg: float
    vel_en: tuple[float, float]
    yaw_rel_deg: float | None = None
    hfov_deg: float | None = None
    vehicle_yaw_deg: float | None = None

    def to_telemetry(self, clock_offset_s: float = 0.0, height_offset_m: float = 0.0) -> Telemetry:
        """The record at time ``boot_s + clock_offset_s`` with ``height_offset_m`` added to the height."""
        return Telemetry(t=self.boot_s + clock_offset_s, lat=self.lat, lon=self.lon,
                         height_m=self.height_m + height_offset_m, pitch_deg=self.pitch_deg,
                         heading_deg=self.heading_deg, roll_deg=self.roll_deg,
                         speed_mps=math.hypot(*self.vel_en), vel_en_mps=self.vel_en, hfov_deg=self.hfov_deg)


@dataclass(slots=True)
class _Gimbal:
    pitch_deg: float  # MAVLink convention: positive up
    roll_deg: float
    yaw_deg: float
    earth_frame: bool


_EarlyMessage = tuple[str, Mapping[str, Any], int, "int | None", "float | None"]  # (type, fields, sys, comp, rx)


class MavlinkAssembler:
    """Turns a stream of decoded MAVLink messages into `MavlinkSample`s.

    Call `add(type, fields, src_system, src_component)` per message (``fields`` as pymavlink's ``to_dict()``); it
    returns a sample for each ``GLOBAL_POSITION_INT`` of the vehicle, else None. The vehicle is ``system_id``, or the
    first system that sends a position; messages of other systems are ignored (a GCS, another drone), and its
    autopilot is the component that sends the positions (``ATTITUDE`` and ``SYSTEM_TIME`` of its other components,
    e.g. a companion computer's, are ignored too). ``position_counts`` counts every system's positions.

    ``unix_offset_s`` is the UNIX time of boot once the vehicle's autopilot has sent a ``SYSTEM_TIME`` with a UNIX
    time (else None): the one after its clock's last jump (``clock_jumps``). ``SYSTEM_TIME`` of every system is kept
    until the vehicle is known, so a ground station's (its own UNIX time and uptime) never sets it.

    Of several gimbals (``GIMBAL_DEVICE_ATTITUDE_STATUS`` of several ``gimbal_device_id``, or of several components
    when the id is 0) the first seen is used (``gimbal_used``); ``gimbals_ignored`` counts the others' messages.
    ``keep_attitudes`` keeps every ``ATTITUDE`` as (boot s, yaw deg) in ``attitudes`` and every reading of the gimbal
    used in ``gimbal_samples`` (a log read as a whole: `shared.telemetry.tlog` interpolates them to the positions).
    ``time_boot_ms`` is unwrapped per sender (`BootTimeUnwrap`, on ``add``'s receive times ``rx_s`` where given).
    """

    def __init__(self, system_id: int | None = None, *, keep_attitudes: bool = False,
                 component_id: int | None = None) -> None:
        self.system_id = system_id
        self.component_id: int | None = component_id
        self.vehicle_yaw_deg: float | None = None
        self.gimbal: _Gimbal | None = None
        self.gimbal_used: str | None = None
        self.gimbals_ignored: dict[str, int] = {}
        #: The latest horizontal field of view of the first camera that sent a ``CAMERA_FOV_STATUS`` (None: none yet,
        #: or it said unknown), and that camera (camera_device_id, component).
        self.hfov_deg: float | None = None
        self._fov_camera: tuple[int, int | None] | None = None
        self.position_counts: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.attitudes: list[tuple[float, float]] | None = [] if keep_attitudes else None
        #: (receive s or NaN, the message's own time_boot_ms in s or NaN, pitch, roll, yaw deg, yaw in earth frame)
        self.gimbal_samples: list[tuple[float, float, float, float, float, bool]] | None = (
            [] if keep_attitudes else None)
        #: Positions taken without the gimbal because its latest reading was older than `hold_limit_s` of its own
        #: intervals (a gimbal that stopped reporting: its last angles are not carried on), on a live stream.
        self.gimbal_stale = 0
        self._gimbal_rx: deque[float] = deque(maxlen=16)  # receive times of the gimbal's latest readings
        self._rx_s: float | None = None
        self._attitude_prev: tuple[float, float] | None = None  # (boot s, yaw deg) of the two latest ATTITUDEs
        self._attitude_last: tuple[float, float] | None = None
        self._clocks: dict[tuple[int | None, int | None], UnixClock] = {}
        self._boot_clocks: dict[tuple[int | None, int | None], BootTimeUnwrap] = {}  # per sender
        #: system -> (type, component, gimbal id, camera id) -> (arrival, message) of the latest, before the vehicle
        self._early: dict[int, dict[tuple[Any, ...], deque[tuple[int, _EarlyMessage]]]] = {}
        self._arrivals = 0
        self._src: tuple[int | None, int | None] = (None, None)

    @property
    def clock(self) -> UnixClock | None:
        """The vehicle autopilot's UNIX clock (None before it is known or before its first ``SYSTEM_TIME``)."""
        if self.system_id is None:
            return None
        clock = self._clocks.get((self.system_id, self.component_id)) or self._clocks.get((self.system_id, None))
        if clock is None and self.component_id is None:  # positions given without a component id
            clock = next((c for (sysid, _), c in self._clocks.items() if sysid == self.system_id), None)
        return clock

    @property
    def unix_offset_s(self) -> float | None:
        """UNIX time of the vehicle's boot (after its clock's last jump), or None without its ``SYSTEM_TIME``."""
        clock = self.clock
        return None if clock is None else clock.offset_s

    @property
    def clock_jumps(self) -> list[tuple[float, float]]:
        """(boot s, step s) per jump of the vehicle's UNIX clock so far."""
        clock = self.clock
        return [] if clock is None else list(clock.jumps)

    def add(self, msg_type: str, fields: Mapping[str, Any], src_system: int | None = None,
            src_component: int | None = None, rx_s: float | None = None) -> MavlinkSample | None:
        """Take one message (``rx_s``: its UNIX receive time or None); a sample when it was the vehicle's position."""
        if msg_type == "SYSTEM_TIME":  # kept per system until the vehicle is known
            src = (src_system, src_component)
            self._system_time(src, self._unwrapped(msg_type, fields, src, rx_s))
            return None
        if msg_type == "GLOBAL_POSITION_INT" and src_system is not None:
            self.position_counts[src_system] = self.position_counts.get(src_system, 0) + 1
            if self.system_id is None:
                self.system_id = src_system
            if src_system == self.system_id and self.component_id is None:
                self.component_id = src_component
            early = self._early.pop(src_system, None) if src_system == self.system_id else None
            self._early.clear()
            for _, msg in sorted((item for kept in (early or {}).values() for item in kept), key=lambda i: i[0]):
                self.add(*msg)  # the vehicle's own messages from before it was known, in their order
        if src_system is not None and src_system != self.system_id:
            if self.system_id is None and msg_type in _HANDLERS:  # kept per system until the vehicle is known (a
                # second drone's gimbal took the vehicle's place for the whole flight): the latest of each kind and
                # sender, the two latest ATTITUDEs (to interpolate between)
                source = (msg_type, src_component, fields.get("gimbal_device_id"), fields.get("camera_device_id"))
                kept = self._early.setdefault(src_system, {}).setdefault(
                    source, deque(maxlen=2 if msg_type == "ATTITUDE" else 1))
                self._arrivals += 1
                kept.append((self._arrivals, (msg_type, fields, src_system, src_component, rx_s)))
            return None
        if msg_type == "ATTITUDE" and src_component is not None and src_component != self.component_id:
            return None  # another component's (a companion computer's, on its own boot clock), or before it is known
        handler = _HANDLERS.get(msg_type)
        if handler is None:
            return None
        self.counts[msg_type] = self.counts.get(msg_type, 0) + 1
        self._src, self._rx_s = (src_system, src_component), rx_s
        return handler(self, self._unwrapped(msg_type, fields, self._src, rx_s))

    def _unwrapped(self, msg_type: str, f: Mapping[str, Any], src: tuple[int | None, int | None],
                   rx_s: float | None) -> Mapping[str, Any]:
        """The fields with ``time_boot_ms`` unwrapped on the sender's boot clock (a gimbal's is its own: left)."""
        if msg_type not in _BOOT_CLOCKED or "time_boot_ms" not in f:
            return f
        boot_ms = self._boot_clocks.setdefault(src, BootTimeUnwrap()).unwrap(f["time_boot_ms"], rx_s)
        return f if boot_ms == f["time_boot_ms"] else {**f, "time_boot_ms": boot_ms}

    # ---- handlers --------------------------------------------------------------------------------
    def _system_time(self, src: tuple[int | None, int | None], f: Mapping[str, Any]) -> None:
        unix_us, boot_ms = int(f["time_unix_usec"]), int(f["time_boot_ms"])
        if unix_us > 0:
            self._clocks.setdefault(src, UnixClock()).add(boot_ms / 1e3, unix_us / 1e6 - boot_ms / 1e3)

    def _attitude(self, f: Mapping[str, Any]) -> None:
        yaw = float(f["yaw"])
        if math.isfinite(yaw):
            self.vehicle_yaw_deg = math.degrees(yaw)
            if "time_boot_ms" in f:
                sample = (f["time_boot_ms"] / 1e3, self.vehicle_yaw_deg)
                self._attitude_prev, self._attitude_last = self._attitude_last, sample
                if self.attitudes is not None:
                    self.attitudes.append(sample)

    def _yaw_at(self, boot_s: float) -> float | None:
        """The vehicle's yaw at `boot_s`: interpolated between the two latest ``ATTITUDE`` where they bracket it,
        else the latest (held)."""
        prev, last = self._attitude_prev, self._attitude_last
        if prev is not None and last is not None and prev[0] <= boot_s <= last[0]:
            return yaw_between_deg(*prev, *last, boot_s)
        return self.vehicle_yaw_deg

    def _gimbal_device(self, f: Mapping[str, Any]) -> None:
        device_id = int(f.get("gimbal_device_id", 0))  # 1..6: the autopilot speaks for it; 0: the sender is it
        key = f"gimbal_device_id {device_id}" if device_id else f"gimbal component {self._src[1]}"
        if self.gimbal_used is None:
            self.gimbal_used = key
        elif key != self.gimbal_used:
            self.gimbals_ignored[key] = self.gimbals_ignored.get(key, 0) + 1
            return None
        try:
            roll, pitch, yaw = quaternion_to_euler_deg(tuple(f["q"]))  # type: ignore[arg-type]
        except ValueError:
            return None
        flags = int(f["flags"])
        if flags == _PX4_RC_FLAGS and self._src[1] is not None and self._src[1] == self.component_id:
            earth = False  # PX4's own servo (RC/AUX) gimbal, sent by the autopilot: the outputs, vehicle-relative
        elif flags & _YAW_IN_EARTH_FRAME:
            earth = True
        elif flags & _YAW_IN_VEHICLE_FRAME:
            earth = False
        else:
            earth = bool(flags & _YAW_LOCK)
        self._set_gimbal(_Gimbal(pitch, roll, yaw, earth), f)

    def _set_gimbal(self, gimbal: _Gimbal, f: Mapping[str, Any]) -> None:
        self.gimbal = gimbal
        if self._rx_s is not None:
            self._gimbal_rx.append(self._rx_s)
        if self.gimbal_samples is not None:
            own = f.get("time_boot_ms")
            self.gimbal_samples.append((math.nan if self._rx_s is None else self._rx_s,
                                        math.nan if own is None else own / 1e3, gimbal.pitch_deg, gimbal.roll_deg,
                                        gimbal.yaw_deg, gimbal.earth_frame))

    def _mount_orientation(self, f: Mapping[str, Any]) -> None:
        absolute = float(f.get("yaw_absolute", math.nan))
        earth = math.isfinite(absolute) and absolute != 0.0
        yaw = absolute if earth else float(f["yaw"])
        pitch, roll = float(f["pitch"]), float(f["roll"])
        if not (math.isfinite(pitch) and math.isfinite(yaw)):  # NaN: invalid (ardupilotmega.xml): no reading
            return None
        self._set_gimbal(_Gimbal(pitch, roll if math.isfinite(roll) else 0.0, yaw, earth), f)

    def _mount_status(self, f: Mapping[str, Any]) -> None:
        self._set_gimbal(_Gimbal(f["pointing_a"] / 100.0, f["pointing_b"] / 100.0, f["pointing_c"] / 100.0, False), f)

    def _camera_fov(self, f: Mapping[str, Any]) -> None:
        camera = (int(f.get("camera_device_id") or 0), self._src[1])
        if self._fov_camera is None:
            self._fov_camera = camera
        elif camera != self._fov_camera:  # another camera's (an IR beside the EO)
            return None
        hfov = float(f["hfov"])
        self.hfov_deg = hfov if math.isfinite(hfov) and 0.0 < hfov < 180.0 else None

    def _position(self, f: Mapping[str, Any]) -> MavlinkSample | None:
        lat, lon = f["lat"] / 1e7, f["lon"] / 1e7
        if (lat, lon) == (0.0, 0.0):  # no GPS fix yet
            return None
        boot_s = f["time_boot_ms"] / 1e3
        vehicle_yaw = self._yaw_at(boot_s)
        if vehicle_yaw is None and int(f.get("hdg", _UNKNOWN_HDG)) != _UNKNOWN_HDG:
            vehicle_yaw = f["hdg"] / 100.0
        gimbal = self.gimbal
        age = math.nan if self._rx_s is None or not self._gimbal_rx else self._rx_s - self._gimbal_rx[-1]
        if gimbal is not None and self.gimbal_samples is None and len(self._gimbal_rx) >= 3 \
                and age > MIN_HOLD_S and age > hold_limit_s(self._gimbal_rx):  # (the limit is >= MIN_HOLD_S)
            gimbal = None  # live, its last reading is stale: not carried on (a log read whole interpolates instead;
            self.gimbal_stale += 1  # fewer than 3 readings tell no interval to judge by)
        pitch: float | None
        yaw_rel: float | None
        if gimbal is None:  # a fixed camera: it looks where the vehicle heads; its tilt comes from --pitch-deg
            pitch, roll, heading, yaw_rel = None, 0.0, vehicle_yaw, 0.0
        else:
            pitch = pitch_or_none(-gimbal.pitch_deg, f"MAVLink gimbal pitch {gimbal.pitch_deg:g} deg")
            roll = gimbal.roll_deg
            yaw_rel = None if gimbal.earth_frame else gimbal.yaw_deg
            heading = gimbal.yaw_deg if gimbal.earth_frame else (
                None if vehicle_yaw is None else vehicle_yaw + gimbal.yaw_deg)
        return MavlinkSample(boot_s=boot_s, lat=lat, lon=lon, height_m=f["relative_alt"] / 1e3,
                             pitch_deg=pitch, heading_deg=None if heading is None else heading % 360.0,
                             roll_deg=roll, vel_en=(f["vy"] / 100.0, f["vx"] / 100.0), yaw_rel_deg=yaw_rel,
                             hfov_deg=self.hfov_deg, vehicle_yaw_deg=vehicle_yaw)


#: The flags PX4's gimbal module sends for a servo (RC/AUX) gimbal whatever its mode: NEUTRAL and the three locks,
#: with the servo outputs' angles, relative to the vehicle (src/modules/gimbal/output_rc.cpp).
_PX4_RC_FLAGS = 2 | 4 | 8 | 16
#: Messages stamped with the autopilot's boot clock (a gimbal device's ``time_boot_ms`` is its own clock).
_BOOT_CLOCKED = frozenset({"GLOBAL_POSITION_INT", "ATTITUDE", "SYSTEM_TIME"})
_HANDLERS = {
    "GLOBAL_POSITION_INT": MavlinkAssembler._position,
    "ATTITUDE": MavlinkAssembler._attitude,
    "GIMBAL_DEVICE_ATTITUDE_STATUS": MavlinkAssembler._gimbal_device,
    "MOUNT_ORIENTATION": MavlinkAssembler._mount_orientation,
    "MOUNT_STATUS": MavlinkAssembler._mount_status,
    "CAMERA_FOV_STATUS": MavlinkAssembler._camera_fov,
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



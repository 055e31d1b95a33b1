"""PX4 flight logs (``.ulg``, ULog) to `Telemetry` records, read with pyulog (optional extra ``ulog``).

Topics used, all on the log's microsecond boot clock and interpolated to the times of the positions:
- ``vehicle_global_position``: lat, lon (one record per sample);
- ``vehicle_local_position``: ``z`` (metres down from the local origin, where the EKF started) and ``vx, vy``
  (north, east m/s); without it the records have no height (``--height-m``);
- ``home_position``: ``z`` of home (the take-off point, set at arming) in the same local frame: the height is
  ``-(z - home z)``, above the take-off point, with the latest home before each position (home may be reset; the
  first one before it is set). Without ``home_position`` the height is ``-z``, above the EKF origin (where PX4
  started its estimate: off the take-off point when PX4 was powered on elsewhere or the baro drifted on the
  ground), and a warning says so;
- ``vehicle_attitude``: quaternion ``q[0..3]`` (w, x, y, z): the vehicle's yaw;
- ``gimbal_device_attitude_status``: quaternion and ``device_flags`` (yaw in the earth or the vehicle frame, as
  in MAVLink's GIMBAL_DEVICE_ATTITUDE_STATUS; each sample's own, as the pilot may switch follow and lock in
  flight); without it the camera is taken as fixed, facing forward (heading = the vehicle's yaw, pitch from
  ``--pitch-deg``);
- ``vehicle_gps_position`` or ``sensor_gps`` (the first instance with UTC time): ``time_utc_usec`` anchors the
  boot clock to UNIX time; without it times are seconds since boot, and a warning says so.

A damaged log is read as far as pyulog gets, with a warning (`_warn_if_damaged`); pyulog's own messages go to the
log, not stdout.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.telemetry.mavlink import quaternion_to_euler_deg
from shared.telemetry.record import Telemetry, pitch_or_none

__all__ = ["ULOG_EXTRA_HINT", "read_ulog"]

log = logging.getLogger(__name__)

ULOG_EXTRA_HINT = "PX4 .ulg logs need pyulog: pip install 'uav-memory-maps[ulog]'"
_TOPICS = ["vehicle_global_position", "vehicle_local_position", "vehicle_attitude",
           "gimbal_device_attitude_status", "vehicle_gps_position", "sensor_gps", "home_position"]
_YAW_LOCK, _YAW_IN_VEHICLE_FRAME, _YAW_IN_EARTH_FRAME = 16, 32, 64
#: The flags PX4's gimbal module publishes for a servo (RC/AUX) gimbal: NEUTRAL | ROLL_LOCK | PITCH_LOCK | YAW_LOCK,
#: whatever the mode, with the servo outputs' angles, relative to the vehicle (src/modules/gimbal/output_rc.cpp).
_PX4_RC_FLAGS = 2 | 4 | 8 | 16


def _topic(ulog: Any, name: str) -> dict[str, NDArray] | None:
    """The first instance of a topic as {field: array}, or None when the log lacks it or it is empty."""
    for dataset in ulog.data_list:
        if dataset.name == name and dataset.multi_id == 0 and len(dataset.data["timestamp"]):
            return dataset.data
    return None


#: Positions ending more than this before the log's last message (µs) are reported: the log lost its end.
_EARLY_END_US = 2_000_000


class _ReadWatch(io.BufferedReader):
    """The file pyulog reads. pyulog stops at the first read that comes back short: at the end of the file that
    read finds 0 bytes, in a log cut mid-message or at a message length it cannot trust (corrupt data without a
    sync marker after it) it finds the rest of the file, which it then drops. ``unread_bytes`` counts those."""

    unread_bytes = 0

    def read(self, size: int | None = -1, /) -> bytes:
        data = super().read(size)
        if size is not None and 0 <= size and len(data) < size:
            self.unread_bytes = len(data)
        return data


def _warn_if_damaged(path: str | Path, ulog: Any, unread_bytes: int, last_position_us: float) -> None:
    """Warnings for a log pyulog could not read whole: it skipped corrupt data (``file_corruption``: pyulog
    resyncs at the next sync marker, the messages in between are lost), it stopped before the end of the file
    (`_ReadWatch`), or the positions end well before the log's last message of the topics read."""
    if ulog.file_corruption:
        log.warning("%s: pyulog found corrupt data and skipped it (to the next sync marker): the records in the "
                    "damaged stretch are missing", path)
    if unread_bytes:
        log.warning("%s: pyulog stopped reading %d bytes before the end of the file (the log was cut while "
                    "writing, or holds corrupt data pyulog cannot resync past): the records end at %.1f s after "
                    "boot", path, unread_bytes, last_position_us / 1e6)
    if ulog.last_timestamp - last_position_us > _EARLY_END_US:
        log.warning("%s: the positions (vehicle_global_position) end at %.1f s after boot, %.1f s before the log's "
                    "last message: no records after that", path, last_position_us / 1e6,
                    (ulog.last_timestamp - last_position_us) / 1e6)


def _utc_offset_s(ulog: Any) -> float | None:
    """UNIX time minus boot time in seconds, from the first GPS topic and instance with UTC time (the median over
    its samples with ``time_utc_usec`` > 0), or None when none has: a receiver without time output, or before its
    fix, logs 0. ``vehicle_gps_position`` instances come first (PX4 <= 1.12 logs one per receiver), then
    ``sensor_gps`` (the receivers of newer PX4)."""
    for name in ("vehicle_gps_position", "sensor_gps"):
        for dataset in sorted((d for d in ulog.data_list if d.name == name), key=lambda d: d.multi_id):
            gps = dataset.data
            if "time_utc_usec" not in gps:
                continue
            utc = gps["time_utc_usec"].astype(np.float64)
            valid = utc > 0
            if valid.any():
                return float(np.median(utc[valid] - gps["timestamp"][valid].astype(np.float64))) / 1e6
    return None


def _interp(t: NDArray, t_src: NDArray, values: NDArray) -> NDArray:
    return np.interp(t, t_src, values)


def _interp_finite(t: NDArray, t_src: NDArray, values: NDArray) -> NDArray:
    """`values` (M,) at times `t_src` (M,) interpolated to `t` (N,) over their finite entries; all NaN without any."""
    ok = np.isfinite(values)
    return np.interp(t, t_src[ok], values[ok]) if ok.any() else np.full(len(t), np.nan)


def _unwrapped_deg(yaw_deg: NDArray) -> NDArray:
    """Angles (degrees) with their 360-degree jumps removed over the finite entries, for interpolation."""
    out = np.array(yaw_deg, dtype=np.float64)
    ok = np.isfinite(out)
    out[ok] = np.degrees(np.unwrap(np.radians(out[ok])))
    return out


def _home_z_at(home: dict[str, NDArray] | None, t: NDArray) -> NDArray | None:
    """Home's local z (metres, down) in effect at times `t` (N,): the latest home set at or before each time, the
    first one before any (home is set at arming and may be reset). None without a valid home (no topic, or no
    sample with a finite z and, where logged, ``valid_lpos``)."""
    if home is None or "z" not in home:
        return None
    z = home["z"].astype(np.float64)
    ok = np.isfinite(z)
    if "valid_lpos" in home:
        ok &= home["valid_lpos"].astype(bool)
    if not ok.any():
        return None
    t_home, z = home["timestamp"][ok].astype(np.float64), z[ok]
    order = np.argsort(t_home, kind="stable")
    t_home, z = t_home[order], z[order]
    return z[np.clip(np.searchsorted(t_home, t, side="right") - 1, 0, None)]


def _yaws_deg(data: dict[str, NDArray]) -> tuple[NDArray, NDArray, NDArray]:
    """(roll, pitch, yaw) in degrees per sample of a topic with q[0..3]; yaw unwrapped for interpolation."""
    q = np.column_stack([data[f"q[{i}]"] for i in range(4)]).astype(np.float64)
    # a zero or NaN quaternion (a gimbal not ready, a MAVLink gimbal's invalid reading copied in) is no reading
    euler = np.array([quaternion_to_euler_deg(tuple(row)) if np.any(row) and np.all(np.isfinite(row)) else
                      (np.nan,) * 3 for row in q])
    return euler[:, 0], euler[:, 1], _unwrapped_deg(euler[:, 2])


def _yaw_in_earth_frame(device_flags: NDArray) -> NDArray:
    """(M,) bool per gimbal sample: its yaw is in the earth frame (else relative to the vehicle), as MAVLink's
    GIMBAL_DEVICE_FLAGS say: YAW_IN_EARTH_FRAME, else YAW_IN_VEHICLE_FRAME, else YAW_LOCK (older gimbals)."""
    flags = np.asarray(device_flags).astype(np.int64)
    earth = (flags & _YAW_IN_EARTH_FRAME) != 0
    vehicle = (flags & _YAW_IN_VEHICLE_FRAME) != 0
    return earth | (~vehicle & ((flags & _YAW_LOCK) != 0))


def _camera_heading_deg(t: NDArray, t_gimbal: NDArray, yaw_gimbal: NDArray, earth_gimbal: NDArray,
                        t_vehicle: NDArray, yaw_vehicle: NDArray) -> NDArray:
    """The camera heading (degrees, not wrapped; NaN where unknown) at times `t` (N,).

    t_gimbal, yaw_gimbal, earth_gimbal: (M,) gimbal samples, their yaw in the earth frame where earth_gimbal, else
    relative to the vehicle; t_vehicle, yaw_vehicle: (K,) the vehicle's yaw (K may be 0). Each time takes the frame
    of the gimbal sample in effect (the latest at or before it, the first before any): the pilot may switch the
    gimbal between follow (vehicle frame) and lock (earth frame) mid-flight. The samples are brought into that frame
    with the vehicle's yaw at their own time before interpolating, so no interpolation mixes the two frames.
    """
    def vehicle_yaw_at(times: NDArray) -> NDArray:
        return _interp_finite(times, t_vehicle, yaw_vehicle) if len(t_vehicle) else np.full(len(times), np.nan)

    vehicle_at_gimbal = vehicle_yaw_at(t_gimbal)
    in_earth = _unwrapped_deg(np.where(earth_gimbal, yaw_gimbal, yaw_gimbal + vehicle_at_gimbal))
    relative = _unwrapped_deg(np.where(earth_gimbal, yaw_gimbal - vehicle_at_gimbal, yaw_gimbal))
    earth = earth_gimbal[np.clip(np.searchsorted(t_gimbal, t, side="right") - 1, 0, None)]
    heading = np.full(len(t), np.nan)
    heading[earth] = _interp_finite(t[earth], t_gimbal, in_earth)
    heading[~earth] = vehicle_yaw_at(t[~earth]) + _interp_finite(t[~earth], t_gimbal, relative)
    return heading


def read_ulog(path: str | Path, *, height_offset_m: float = 0.0) -> list[Telemetry]:
    """Records of a PX4 ULog file, one per ``vehicle_global_position`` sample (see the module docstring).

    height_offset_m is added to every height. Raises ValueError naming the file when pyulog rejects it or it
    has no ``vehicle_global_position``; ImportError with the install hint without pyulog.
    """
    try:
        from pyulog import ULog
    except ImportError:
        raise ImportError(ULOG_EXTRA_HINT) from None
    said = io.StringIO()
    try:
        with _ReadWatch(io.FileIO(path, "rb")) as handle, contextlib.redirect_stdout(said):
            ulog = ULog(handle, _TOPICS)  # pyulog prints its warnings: logged below, stdout is the CLI's
    except Exception as exc:  # pyulog raises its own and struct/IO errors for damaged files
        raise ValueError(f"{path}: not a readable ULog file ({exc})") from None
    for line in dict.fromkeys(said.getvalue().splitlines()):
        log.warning("%s: pyulog: %s", path, line)
    position = _topic(ulog, "vehicle_global_position")
    if position is None:
        raise ValueError(f"{path}: no vehicle_global_position in the ULog (was the position logged?)")
    t_us = position["timestamp"].astype(np.float64)
    _warn_if_damaged(path, ulog, handle.unread_bytes, float(t_us[-1]))
    n = len(t_us)
    height = np.full(n, np.nan)
    vel_e = np.full(n, np.nan)
    vel_n = np.full(n, np.nan)
    local = _topic(ulog, "vehicle_local_position")
    if local is not None:
        t_local = local["timestamp"].astype(np.float64)
        height = -_interp(t_us, t_local, local["z"].astype(np.float64))
        home_z = _home_z_at(_topic(ulog, "home_position"), t_us)
        if home_z is None:
            log.warning("%s: no home_position in the log: heights are above the EKF origin (where PX4 started its "
                        "estimate), which is the take-off point only if PX4 was powered on there; correct with "
                        "--height-offset-m", path)
        else:
            height += home_z
        if "vx" in local and "vy" in local:
            vel_n = _interp(t_us, t_local, local["vx"].astype(np.float64))
            vel_e = _interp(t_us, t_local, local["vy"].astype(np.float64))
    t_vehicle, yaw_vehicle = np.zeros(0), np.zeros(0)
    attitude = _topic(ulog, "vehicle_attitude")
    if attitude is not None:
        t_vehicle, yaw_vehicle = attitude["timestamp"].astype(np.float64), _yaws_deg(attitude)[2]
    vehicle_yaw = _interp_finite(t_us, t_vehicle, yaw_vehicle)
    pitch = np.full(n, np.nan)
    roll = np.zeros(n)
    heading = vehicle_yaw.copy()  # a fixed camera looks where the vehicle heads
    gimbal = _topic(ulog, "gimbal_device_attitude_status")
    if gimbal is not None:
        g_roll, g_pitch, g_yaw = _yaws_deg(gimbal)
        ok = np.isfinite(g_yaw)
        if ok.any():
            t_g = gimbal["timestamp"][ok].astype(np.float64)
            pitch = _interp(t_us, t_g, g_pitch[ok])
            roll = _interp(t_us, t_g, g_roll[ok])
            flags = gimbal["device_flags"][ok] if "device_flags" in gimbal else np.full(len(t_g), _YAW_LOCK)
            earth = _yaw_in_earth_frame(flags)
            if "received_from_mavlink" in gimbal:  # PX4's own servo (RC/AUX) output: flags fixed at NEUTRAL and the
                # three locks, angles the servo outputs, relative to the vehicle (gimbal/output_rc.cpp)
                own = np.asarray(gimbal["received_from_mavlink"])[ok] == 0
                servo = own & (flags.astype(np.int64) == _PX4_RC_FLAGS)
                if servo.any():
                    log.info("%s: %d gimbal samples of PX4's own servo output (flags %d, not from a MAVLink gimbal): "
                             "their yaw is relative to the vehicle", path, int(servo.sum()), _PX4_RC_FLAGS)
                earth = earth & ~servo
            heading = _camera_heading_deg(t_us, t_g, g_yaw[ok], earth, t_vehicle, yaw_vehicle)
    offset_s = _utc_offset_s(ulog)
    if offset_s is None:
        log.warning("%s: no GPS UTC time in the log (time_utc_usec of vehicle_gps_position or sensor_gps, any "
                    "instance): the records are on the boot clock (seconds since boot), so a "
                    "--telemetry-offset-s in UNIX time will not match them", path)
        offset_s = 0.0
    records: list[Telemetry] = []
    for i in range(n):
        lat, lon = float(position["lat"][i]), float(position["lon"][i])
        if not (math.isfinite(lat) and math.isfinite(lon)) or (lat, lon) == (0.0, 0.0):
            continue
        p = None if math.isnan(pitch[i]) else pitch_or_none(-float(pitch[i]), f"{path}: gimbal pitch {pitch[i]:g}")
        records.append(Telemetry(
            t=t_us[i] / 1e6 + offset_s, lat=lat, lon=lon,
            height_m=None if math.isnan(height[i]) else float(height[i]) + height_offset_m,
            pitch_deg=p, heading_deg=None if math.isnan(heading[i]) else float(heading[i]) % 360.0,
            roll_deg=float(roll[i]),
            speed_mps=None if math.isnan(vel_e[i]) else math.hypot(vel_e[i], vel_n[i]),
            vel_en_mps=None if math.isnan(vel_e[i]) else (float(vel_e[i]), float(vel_n[i])),
        ))
    if not records:
        raise ValueError(f"{path}: vehicle_global_position has no valid fix")
    return records

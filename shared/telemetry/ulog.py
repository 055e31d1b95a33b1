"""PX4 flight logs (``.ulg``, ULog) to `Telemetry` records, read with pyulog (optional extra ``ulog``).

Topics used, all on the log's microsecond boot clock and interpolated to the times of the positions:
- ``vehicle_global_position``: lat, lon (one record per sample);
- ``vehicle_local_position``: ``z`` (metres down from the local origin, where the EKF started) and ``vx, vy``
  (north, east m/s); without it the records have no height (``--height-m``). Positions next to a sample whose
  ``z`` is NaN or whose ``z_valid`` is false (the estimate not converged yet, or lost) are dropped, with one warning
  counting them; when (nearly) every one would be, none is and the heights are unknown;
- ``home_position``: ``z`` of home (the take-off point, set at arming) in the same local frame: the height is
  ``-(z - home z)``, above the take-off point, with the latest home before each position (home may be reset; the
  first one before it is set). Without ``home_position`` the height is ``-z``, above the EKF origin (where PX4
  started its estimate: off the take-off point when PX4 was powered on elsewhere or the baro drifted on the
  ground), and a warning says so;
- ``vehicle_attitude``: quaternion ``q[0..3]`` (w, x, y, z): the vehicle's yaw;
- ``gimbal_device_attitude_status``: quaternion and ``device_flags`` (yaw in the earth or the vehicle frame, as
  in MAVLink's GIMBAL_DEVICE_ATTITUDE_STATUS; each sample's own, as the pilot may switch follow and lock in
  flight); interpolated to each position (`shared.telemetry.gimbal_track.camera_angles`: pitch and roll linearly,
  heading on the short arc) and carried no more than `hold_limit_s` beyond its samples (a gimbal that starts late,
  pauses or stops reporting: one warning counts the positions beyond, which get no gimbal pitch and the vehicle's yaw
  as heading); without it the camera is taken as fixed, facing forward (heading = the vehicle's yaw, pitch from
  ``--pitch-deg``);
- ``vehicle_gps_position`` or ``sensor_gps`` (the first instance with UTC time): ``time_utc_usec`` anchors the
  boot clock to UNIX time; without it times are seconds since boot, and a warning says so;
- ``vehicle_command`` (and ``vehicle_command_ack``): MAV_CMD_VIDEO_START_CAPTURE / STOP_CAPTURE, when the camera
  recorded (`_recording`; `Telemetry.recording`, `FlightLogReport.recording`).

A damaged log is read as far as pyulog gets, with a warning (`_warn_if_damaged`); pyulog's own messages go to the
log, not stdout.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.telemetry.gimbal_track import camera_angles, describe_spans, hold_limit_s, unwrapped_deg
from shared.telemetry.mavlink import quaternion_to_euler_deg
from shared.telemetry.record import Telemetry, pitch_or_none
from shared.telemetry.recording import FlightLogReport, LogRecording, from_commands, mark_recording

__all__ = ["ULOG_EXTRA_HINT", "read_ulog", "read_ulog_report"]

log = logging.getLogger(__name__)

ULOG_EXTRA_HINT = "PX4 .ulg logs need pyulog: pip install 'uav-memory-maps[ulog]'"
_TOPICS = ["vehicle_global_position", "vehicle_local_position", "vehicle_attitude",
           "gimbal_device_attitude_status", "vehicle_gps_position", "sensor_gps", "home_position", "vehicle_command",
           "vehicle_command_ack"]
#: MAV_CMD_VIDEO_START_CAPTURE, MAV_CMD_VIDEO_STOP_CAPTURE; an acknowledgement this long after a command is its.
_VIDEO_COMMANDS = (2500, 2501)
_ACK_S = 3.0
_YAW_LOCK, _YAW_IN_VEHICLE_FRAME, _YAW_IN_EARTH_FRAME = 16, 32, 64
#: The flags PX4's gimbal module publishes for a servo (RC/AUX) gimbal: NEUTRAL | ROLL_LOCK | PITCH_LOCK | YAW_LOCK,
#: whatever the mode, with the servo outputs' angles, relative to the vehicle (src/modules/gimbal/output_rc.cpp).
_PX4_RC_FLAGS = 2 | 4 | 8 | 16


_QUATERNION = ("timestamp", "q[0]", "q[1]", "q[2]", "q[3]")
#: The fields a topic is read for (the optional ones are looked up where used).
_FIELDS = {"vehicle_global_position": ("timestamp", "lat", "lon"), "vehicle_local_position": ("timestamp", "z"),
           "vehicle_attitude": _QUATERNION, "gimbal_device_attitude_status": _QUATERNION}


def _topic(ulog: Any, name: str, path: str | Path) -> dict[str, NDArray] | None:
    """The first instance of a topic as {field: array}, or None when the log lacks it or it is empty. One whose format
    lacks a field it is read for (a damaged format definition: pyulog reads the bytes of a flipped name as another
    field) is not used, with a warning; for ``vehicle_global_position`` that is a ValueError naming the field."""
    for dataset in ulog.data_list:
        if dataset.name != name or dataset.multi_id != 0:
            continue
        missing = [f for f in _FIELDS.get(name, ("timestamp",)) if f not in dataset.data]
        if missing:
            fields = ", ".join(repr(f) for f in sorted(dataset.data))
            if name == "vehicle_global_position":
                raise ValueError(f"{path}: {name} has no field {missing[0]!r} (its fields: {fields}; a damaged log?)")
            log.warning("%s: %s has no field %r (its fields: %s; a damaged log?): the topic is not used", path, name,
                        missing[0], fields)
            return None
        if len(dataset.data["timestamp"]):
            return dataset.data
    return None


#: Positions ending more than this before the log's last message (µs) are reported: the log lost its end.
_EARLY_END_US = 2_000_000


class _ReadWatch(io.BufferedReader):
    """The file pyulog reads. pyulog stops at the first read that comes back short: at the end of the file that
    read finds 0 bytes, in a log cut mid-message or at a message length it cannot trust (corrupt data without a
    sync marker after it) it finds the rest of the file, which it then drops. ``unread_bytes`` counts those. It also
    stops without a short read, at a data message of a topic whose format has no ``timestamp`` (a damaged format
    definition): `close` adds the bytes it never asked for."""

    unread_bytes = 0

    def read(self, size: int | None = -1, /) -> bytes:
        data = super().read(size)
        if size is not None and 0 <= size and len(data) < size:
            self.unread_bytes = len(data)
        return data

    def close(self) -> None:  # pyulog closes the file when it is done: the bytes it never asked for, before that
        if not self.closed:
            self.unread_bytes += max(os.fstat(self.fileno()).st_size - self.tell(), 0)
        super().close()


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
            if "time_utc_usec" not in gps or "timestamp" not in gps:
                continue
            utc = gps["time_utc_usec"].astype(np.float64)
            valid = utc > 0
            if valid.any():
                return float(np.median(utc[valid] - gps["timestamp"][valid].astype(np.float64))) / 1e6
    return None


def _interp(t: NDArray, t_src: NDArray, values: NDArray) -> NDArray:
    return np.interp(t, t_src, values)


def _valid_heights(local: dict[str, NDArray], t: NDArray) -> tuple[NDArray, NDArray]:
    """(heights -z, valid) at the position times `t` (N,) from ``vehicle_local_position``: interpolated over its
    samples with a finite ``z`` (and ``z_valid`` where logged); valid False at a time next to an invalid sample
    (the estimate not yet converged, or lost: its neighbours say nothing better)."""
    t_local = local["timestamp"].astype(np.float64)
    z = local["z"].astype(np.float64)
    ok = np.isfinite(z)
    if "z_valid" in local:
        ok &= local["z_valid"].astype(bool)
    if not ok.any():
        return np.full(len(t), np.nan), np.zeros(len(t), dtype=bool)
    valid = np.interp(t, t_local, ok.astype(np.float64)) == 1.0
    return -np.interp(t, t_local[ok], z[ok]), valid


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
    return euler[:, 0], euler[:, 1], unwrapped_deg(euler[:, 2])


def _yaw_in_earth_frame(device_flags: NDArray) -> NDArray:
    """(M,) bool per gimbal sample: its yaw is in the earth frame (else relative to the vehicle), as MAVLink's
    GIMBAL_DEVICE_FLAGS say: YAW_IN_EARTH_FRAME, else YAW_IN_VEHICLE_FRAME, else YAW_LOCK (older gimbals)."""
    flags = np.asarray(device_flags).astype(np.int64)
    earth = (flags & _YAW_IN_EARTH_FRAME) != 0
    vehicle = (flags & _YAW_IN_VEHICLE_FRAME) != 0
    return earth | (~vehicle & ((flags & _YAW_LOCK) != 0))


def read_ulog(path: str | Path, **kw: Any) -> list[Telemetry]:
    """The records of `read_ulog_report`."""
    return read_ulog_report(path, **kw).records


def read_ulog_report(path: str | Path, *, height_offset_m: float = 0.0) -> FlightLogReport:
    """Records of a PX4 ULog file, one per ``vehicle_global_position`` sample with a height (see the module
    docstring), and what the log says about the camera's recording (`_recording`).

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
            handle.close()
    except Exception as exc:  # pyulog raises its own and struct/IO errors for damaged files
        raise ValueError(f"{path}: not a readable ULog file ({exc})") from None
    for line in dict.fromkeys(said.getvalue().splitlines()):
        log.warning("%s: pyulog: %s", path, line)
    position = _topic(ulog, "vehicle_global_position", path)
    if position is None:
        raise ValueError(f"{path}: no vehicle_global_position in the ULog (was the position logged?)")
    t_us = position["timestamp"].astype(np.float64)
    _warn_if_damaged(path, ulog, handle.unread_bytes, float(t_us[-1]))
    n = len(t_us)
    height = np.full(n, np.nan)
    has_height = np.ones(n, dtype=bool)  # False: dropped (the estimate gave no valid height there)
    vel_e = np.full(n, np.nan)
    vel_n = np.full(n, np.nan)
    local = _topic(ulog, "vehicle_local_position", path)
    if local is not None:
        t_local = local["timestamp"].astype(np.float64)
        height, has_height = _valid_heights(local, t_us)
        home_z = _home_z_at(_topic(ulog, "home_position", path), t_us)
        if home_z is None:
            log.warning("%s: no home_position in the log: heights are above the EKF origin (where PX4 started its "
                        "estimate), which is the take-off point only if PX4 was powered on there; correct with "
                        "--height-offset-m", path)
        else:
            height += home_z
        if "vx" in local and "vy" in local:
            vel_n = _interp(t_us, t_local, local["vx"].astype(np.float64))
            vel_e = _interp(t_us, t_local, local["vy"].astype(np.float64))
        height[~has_height] = np.nan
        has_height = _drop_without_height(path, t_us, has_height)
    pitch, roll, heading = _camera(ulog, path, t_us)
    offset_s = _utc_offset_s(ulog)
    if offset_s is None:
        log.warning("%s: no GPS UTC time in the log (time_utc_usec of vehicle_gps_position or sensor_gps, any "
                    "instance): the records are on the boot clock (seconds since boot), so a "
                    "--telemetry-offset-s in UNIX time will not match them", path)
        offset_s = 0.0
    records: list[Telemetry] = []
    for i in np.flatnonzero(has_height):
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
    recording = _recording(ulog, offset_s, path)
    if recording.note:
        log.warning("%s: %s", path, recording.note)
    return FlightLogReport(mark_recording(records, recording), recording)


#: Keep the positions with a valid height only when at least this share of them has one; fewer: the log has no
#: usable height (the run needs --height-m, as without vehicle_local_position).
_MIN_HEIGHT_SHARE = 0.1


def _drop_without_height(path: str | Path, t_us: NDArray, valid: NDArray) -> NDArray:
    """Which positions to keep: all of them when every one has a valid height or (nearly) none has (those without
    have no height, None: the run asks for --height-m), else those with one, and one warning counts the others and
    names when they are."""
    if valid.all():
        return valid
    if valid.mean() < _MIN_HEIGHT_SHARE or valid.sum() < 2:
        log.warning("%s: vehicle_local_position gives a valid height (finite z, z_valid) at only %d of %d positions: "
                    "none is dropped, the others have no height", path, int(valid.sum()), len(valid))
        return np.ones(len(valid), dtype=bool)
    log.warning("%s: %d of %d positions have no valid height (vehicle_local_position z NaN or z_valid false: %s "
                "after the log's first position): dropped, no pose there", path, int((~valid).sum()), len(valid),
                describe_spans(t_us / 1e6, ~valid, t_us[0] / 1e6))
    return valid


def _camera(ulog: Any, path: str | Path, t_us: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """(pitch up, roll, heading) in degrees at the position times (N,) from the gimbal's samples (`camera_angles`:
    interpolated, carried no further than `hold_limit_s`; one warning counts the positions beyond), else a fixed
    camera facing forward: pitch NaN, roll 0, the vehicle's yaw (NaN without ``vehicle_attitude``)."""
    t_vehicle, yaw_vehicle = np.zeros(0), np.zeros(0)
    attitude = _topic(ulog, "vehicle_attitude", path)
    if attitude is not None:
        t_vehicle, yaw_vehicle = attitude["timestamp"].astype(np.float64), _yaws_deg(attitude)[2]
    ok_v = np.isfinite(yaw_vehicle)
    heading = np.interp(t_us, t_vehicle[ok_v], yaw_vehicle[ok_v]) if ok_v.any() else np.full(len(t_us), np.nan)
    pitch, roll = np.full(len(t_us), np.nan), np.zeros(len(t_us))
    gimbal = _topic(ulog, "gimbal_device_attitude_status", path)
    if gimbal is None:
        return pitch, roll, heading
    g_roll, g_pitch, g_yaw = _yaws_deg(gimbal)
    ok = np.isfinite(g_yaw)
    if not ok.any():
        return pitch, roll, heading
    t_g = gimbal["timestamp"][ok].astype(np.float64)
    flags = gimbal["device_flags"][ok] if "device_flags" in gimbal else np.full(len(t_g), _YAW_LOCK)
    earth = _yaw_in_earth_frame(flags)
    if "received_from_mavlink" in gimbal:  # PX4's own servo (RC/AUX) output: flags fixed at NEUTRAL and the three
        # locks, angles the servo outputs, relative to the vehicle (gimbal/output_rc.cpp)
        own = np.asarray(gimbal["received_from_mavlink"])[ok] == 0
        servo = own & (flags.astype(np.int64) == _PX4_RC_FLAGS)
        if servo.any():
            log.info("%s: %d gimbal samples of PX4's own servo output (flags %d, not from a MAVLink gimbal): their yaw "
                     "is relative to the vehicle", path, int(servo.sum()), _PX4_RC_FLAGS)
        earth = earth & ~servo
    hold_us = hold_limit_s(t_g / 1e6) * 1e6
    pitch, roll, heading, stale = camera_angles(t_us, t_g, g_pitch[ok], g_roll[ok], g_yaw[ok], earth, t_vehicle,
                                                yaw_vehicle, hold_us)
    if stale.any():
        log.warning("%s: the gimbal's samples (gimbal_device_attitude_status, %.1f s to %.1f s after boot) are more "
                    "than %.1f s away from %d of %d positions (%s after the log's first position): they get no gimbal "
                    "pitch (pass --pitch-deg for a fixed camera) and the vehicle's yaw as heading", path,
                    t_g[0] / 1e6, t_g[-1] / 1e6, hold_us / 1e6, int(stale.sum()), len(t_us),
                    describe_spans(t_us / 1e6, stale, t_us[0] / 1e6))
    return pitch, roll, heading


def _recording(ulog: Any, offset_s: float, path: str | Path) -> LogRecording:
    """When the camera recorded, from ``vehicle_command`` (PX4 logs every command it handles or forwards:
    MAV_CMD_VIDEO_START_CAPTURE 2500, MAV_CMD_VIDEO_STOP_CAPTURE 2501), less those ``vehicle_command_ack`` refused
    (an acknowledgement of the command with a result other than ACCEPTED within `_ACK_S` after it). PX4's
    ``camera_trigger`` and ``camera_capture`` are photos, not video: not used. Times on the records' clock."""
    commands = _topic(ulog, "vehicle_command", path)
    if commands is None or "command" not in commands:
        return LogRecording()
    t_s = commands["timestamp"].astype(np.float64) / 1e6 + offset_s
    kind = commands["command"].astype(np.int64)
    refused = np.zeros(0)
    acks = _topic(ulog, "vehicle_command_ack", path)
    if acks is not None and {"command", "result"} <= set(acks):
        no = (np.isin(acks["command"].astype(np.int64), _VIDEO_COMMANDS)) & (acks["result"].astype(np.int64) != 0)
        refused = acks["timestamp"][no].astype(np.float64) / 1e6 + offset_s
    accepted = np.array([not np.any((refused >= t) & (refused <= t + _ACK_S)) for t in t_s], dtype=bool)
    return from_commands(t_s[(kind == _VIDEO_COMMANDS[0]) & accepted].tolist(),
                         t_s[(kind == _VIDEO_COMMANDS[1]) & accepted].tolist(),
                         "vehicle_command MAV_CMD_VIDEO_START_CAPTURE")

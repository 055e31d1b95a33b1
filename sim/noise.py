"""Telemetry noise as consumer drones have it: per-flight bias, AR(1) jitter, latency, 10 Hz sample-and-hold.

`TelemetryNoise` holds the levels (defaults: a consumer DJI drone); `TelemetryStream` turns a flight's true
states into the noisy SeaDronesSee ``meta`` dicts attached to video frames.

Model, per flight (video):
- bias: constant, drawn once from N(0, level) (GPS: a horizontal vector whose RMS length is `gps_bias_m`);
- jitter: per telemetry sample, AR(1) with correlation time `jitter_corr_s` and stationary std = level
  (GPS: RMS horizontal length `gps_jitter_m`);
- timing: telemetry is sampled at `telemetry_hz` (random phase) and lags the frames by `time_offset_s`; a
  frame gets the newest sample measured at or before its time minus the offset (sample and hold);
- dropouts: a frame has no meta (None) with probability `missing_meta_rate`;
- defects of real logs (all off by default): white jitter per telemetry sample on top of the AR(1) one
  (`white_gps_m`, `white_heading_deg`, `white_pitch_deg`; at `telemetry_hz` = the frame rate it is
  per-frame jitter), GPS rounded to `gps_decimals` decimals (old DJI SRT: 4 = 11 m steps), the altitude
  reported in steps of `altitude_step_m`, and a time offset that drifts by `time_offset_drift` seconds per
  second (clocks of video and telemetry running apart). Their random numbers come from a generator of
  their own, so a scenario without them gives exactly the telemetry it gave before they existed.
The compass (aircraft) heading shares the heading bias and jitter (the gimbal yaw is referenced to it).

Clocks and layout as real files write them (`CLOCK_FIELDS`, all off by default; they change how the meta
and the frame's ``date_time`` are written, never what is measured, and draw no random numbers): the meta's
stamp truncated to `stamp_resolution_s` (1 s: a flight log's ``datetime(utc)`` column), the flight-log
layout of SeaDronesSee Object Detection v2 (`meta_layout` "flight_log"), and frames stamped in local time
(`frame_clock_utc_offset_s`, applied by the simulator through `format_frame_time`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from datetime import datetime, timezone
from typing import Any

import numpy as np

from shared.geo import local_to_latlon
from sim.flight import Flight, FlightState

#: Layouts of the written meta: SeaDronesSee's ``gps_latitude ... date_time`` and the flight-log column names
#: of SeaDronesSee Object Detection v2 (``datetime(utc)``, ``latitude``, ``height_above_takeoff(meter)``, ...).
META_LAYOUTS = ("seadronessee", "flight_log")
#: TelemetryNoise fields that set how clocks and meta are written, not how large the errors are.
CLOCK_FIELDS = ("stamp_resolution_s", "meta_layout", "frame_clock_utc_offset_s")
#: Largest time-zone offset in use (UTC+14), seconds.
MAX_UTC_OFFSET_S = 14 * 3600.0


def format_time(t_s: float) -> str:
    """UNIX seconds -> ISO 8601 UTC with milliseconds, e.g. ``2023-06-01T10:00:00.033Z``."""
    ms = int(round(t_s * 1000.0))
    stamp = datetime.fromtimestamp(ms // 1000, tz=timezone.utc)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S") + f".{ms % 1000:03d}Z"


def format_frame_time(t_s: float, utc_offset_s: float = 0.0) -> str:
    """A frame's ``date_time``: `format_time` when utc_offset_s is 0, else naive local time (UTC + offset,
    seconds) with microseconds as SeaDronesSee's frames have it, e.g. ``2023-06-01T12:00:00.033333``."""
    if utc_offset_s == 0:
        return format_time(t_s)
    us = int(round((t_s + utc_offset_s) * 1e6))
    stamp = datetime.fromtimestamp(us // 1_000_000, tz=timezone.utc)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S") + f".{us % 1_000_000:06d}"


def format_log_time(t_s: float) -> str:
    """UNIX seconds -> a flight log's naive UTC ``YYYY-MM-DD HH:MM:SS`` (milliseconds appended only when
    the time is not a whole second), e.g. ``2023-06-01 10:00:01``."""
    ms = int(round(t_s * 1000.0))
    text = datetime.fromtimestamp(ms // 1000, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    return text + (f".{ms % 1000:03d}" if ms % 1000 else "")


def truncate_stamp(t_s: float, resolution_s: float) -> float:
    """t_s cut down to a multiple of resolution_s (0: unchanged), on a millisecond grid so that float
    round-off cannot push a whole second into the one before."""
    if resolution_s <= 0:
        return t_s
    ms = int(round(t_s * 1000.0))
    step = max(1, int(round(resolution_s * 1000.0)))
    return (ms // step * step) / 1000.0


@dataclass(frozen=True, slots=True)
class TelemetryNoise:
    """Telemetry error levels (1-sigma unless stated); see the module docstring for the model.

    Attributes
    ----------
    gps_bias_m, gps_jitter_m : float
        RMS horizontal (2-D) GPS bias per flight and jitter per sample, metres.
    heading_bias_deg, heading_jitter_deg : float
        Gimbal (and compass) heading bias and jitter, degrees.
    pitch_bias_deg, pitch_jitter_deg : float
        Gimbal pitch bias and jitter, degrees (the reported pitch is clamped to 0..90).
    height_bias_m, height_jitter_m : float
        Barometric height bias and jitter, metres.
    speed_jitter_mps : float
        Jitter of each velocity component, m/s.
    time_offset_s : float
        Telemetry lag behind the frames, seconds (constant).
    telemetry_hz : float
        Telemetry sample rate (frames run at the scenario's fps; sample and hold in between).
    jitter_corr_s : float
        Correlation time of the AR(1) jitter, seconds.
    missing_meta_rate : float
        Probability that a frame has no meta at all.
    white_gps_m, white_heading_deg, white_pitch_deg : float
        White (independent per telemetry sample) jitter added to the AR(1) one: GPS RMS horizontal
        length (m), gimbal heading and pitch (deg).
    gps_decimals : int
        Latitude/longitude rounded to this many decimals (0 = full precision; 4, 5, 6 as DJI logs).
    altitude_step_m : float
        Reported altitude rounded to multiples of this (0 = off).
    time_offset_drift : float
        The telemetry lag grows by this many seconds per second of flight (clock drift).
    camera_roll_deg : float
        White per-frame roll of the camera that the telemetry does not report (gimbal wobble), deg.
    stamp_resolution_s : float
        The meta's stamp is the sample's stamp truncated down to a multiple of this (0 = not truncated,
        milliseconds; 1 = whole seconds, as a flight log's ``datetime(utc)`` column). 0 or >= 0.001.
    meta_layout : str
        One of `META_LAYOUTS`: "seadronessee" (``gps_latitude ... date_time``, UTC ISO 8601) or
        "flight_log" (SeaDronesSee Object Detection v2's column names, ``datetime(utc)`` naive UTC
        ``YYYY-MM-DD HH:MM:SS``; see `TelemetryStream.meta`).
    frame_clock_utc_offset_s : float
        The frames' own ``date_time`` is naive local time = UTC + this (seconds, e.g. 7200 for CEST;
        within +-14 h), with microseconds; 0 = UTC with milliseconds as before. Only the written string
        changes: simulation time, true poses and truth.json stay in UTC.
    gps_hz : float
        The GPS updates this often (random phase) and every telemetry sample in between repeats its latitude and
        longitude while the other fields move on (sample and hold field by field, as a 1 Hz GPS in a subtitle
        block per frame); 0 = a new position with every telemetry sample. At most `telemetry_hz`.
    """

    gps_bias_m: float = 1.5
    gps_jitter_m: float = 0.3
    heading_bias_deg: float = 2.0
    heading_jitter_deg: float = 0.5
    pitch_bias_deg: float = 0.5
    pitch_jitter_deg: float = 0.3
    height_bias_m: float = 1.0
    height_jitter_m: float = 0.2
    speed_jitter_mps: float = 0.1
    time_offset_s: float = 0.05
    telemetry_hz: float = 10.0
    jitter_corr_s: float = 0.5
    missing_meta_rate: float = 0.0
    white_gps_m: float = 0.0
    white_heading_deg: float = 0.0
    white_pitch_deg: float = 0.0
    gps_decimals: int = 0
    altitude_step_m: float = 0.0
    time_offset_drift: float = 0.0
    camera_roll_deg: float = 0.0
    stamp_resolution_s: float = 0.0
    meta_layout: str = "seadronessee"
    frame_clock_utc_offset_s: float = 0.0
    gps_hz: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name in ("meta_layout", "frame_clock_utc_offset_s"):
                continue  # checked below: a name, and an offset that may be negative
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"TelemetryNoise.{f.name}={value!r} must be a finite number >= 0")
        if self.telemetry_hz <= 0 or self.jitter_corr_s <= 0:
            raise ValueError("TelemetryNoise.telemetry_hz and jitter_corr_s must be > 0")
        if self.gps_hz > self.telemetry_hz:
            raise ValueError(f"TelemetryNoise.gps_hz={self.gps_hz!r} must be at most telemetry_hz "
                             f"({self.telemetry_hz!r}): the GPS is held on the telemetry's samples")
        if self.missing_meta_rate > 1:
            raise ValueError(f"TelemetryNoise.missing_meta_rate={self.missing_meta_rate!r} must be in [0, 1]")
        if isinstance(self.gps_decimals, bool) or not isinstance(self.gps_decimals, int) or self.gps_decimals > 8:
            raise ValueError(f"TelemetryNoise.gps_decimals={self.gps_decimals!r} must be an integer in 0..8")
        if 0 < self.stamp_resolution_s < 0.001:
            raise ValueError(f"TelemetryNoise.stamp_resolution_s={self.stamp_resolution_s!r} must be 0 or >= 0.001 s")
        if self.meta_layout not in META_LAYOUTS:
            raise ValueError(f"TelemetryNoise.meta_layout={self.meta_layout!r} must be one of "
                             f"{', '.join(META_LAYOUTS)}")
        offset = self.frame_clock_utc_offset_s
        if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not math.isfinite(offset) \
                or abs(offset) > MAX_UTC_OFFSET_S:
            raise ValueError(f"TelemetryNoise.frame_clock_utc_offset_s={offset!r} must be a finite number of "
                             f"seconds within +-{MAX_UTC_OFFSET_S:g}")

    def scaled(self, k: float) -> TelemetryNoise:
        """The same noise with every bias, jitter and the time offset multiplied by k (k >= 0).

        The telemetry and GPS rates, correlation time, dropout rate, the log format (GPS decimals, altitude
        step) and the clocks and layout (`CLOCK_FIELDS`) are kept.
        """
        if not math.isfinite(k) or k < 0:
            raise ValueError(f"noise scale must be a finite number >= 0, got {k!r}")
        keep = {"telemetry_hz", "gps_hz", "jitter_corr_s", "missing_meta_rate", "gps_decimals", "altitude_step_m",
                *CLOCK_FIELDS}
        return replace(self, **{f.name: getattr(self, f.name) * k for f in fields(self) if f.name not in keep})


def _wrap360(deg: float) -> float:
    """Degrees wrapped to [0, 360) after rounding to 3 decimals (359.9999 must not become 360.0)."""
    return round(deg % 360.0, 3) % 360.0


# channel order of the bias/jitter vectors
_CH = ("east", "north", "heading", "pitch", "height", "v_east", "v_north", "v_up")


class TelemetryStream:
    """Noisy telemetry of one flight, generated on the fly and deterministically from `rng`.

    Parameters
    ----------
    noise : TelemetryNoise
        Levels (already scaled).
    flight : Flight
        The true trajectory.
    rng : numpy.random.Generator
        Private generator of this stream.
    origin_lat, origin_lon : float
        World origin of the flight's local metres.
    t0_unix_s : float
        UNIX time of the flight's t = 0 (the first frame).

    Attributes
    ----------
    bias : dict
        The realised per-flight biases (east_m, north_m, heading_deg, pitch_deg, height_m).
    phase_s : float
        Time of the first telemetry sample after t = 0, seconds.
    """

    def __init__(self, noise: TelemetryNoise, flight: Flight, rng: np.random.Generator,
                 origin_lat: float, origin_lon: float, t0_unix_s: float) -> None:
        self.noise, self.flight = noise, flight
        self.origin = (origin_lat, origin_lon)
        self.t0_unix_s = t0_unix_s
        self._rng = rng
        # Draw standard normals and scale them, so the same seed with a larger scale gives scaled errors.
        z = rng.standard_normal(5)
        g = noise.gps_bias_m / math.sqrt(2.0)
        self._bias = np.array([g * z[0], g * z[1], noise.heading_bias_deg * z[2],
                               noise.pitch_bias_deg * z[3], noise.height_bias_m * z[4], 0.0, 0.0, 0.0])
        gj = noise.gps_jitter_m / math.sqrt(2.0)
        sj = noise.speed_jitter_mps
        self._sigma = np.array([gj, gj, noise.heading_jitter_deg, noise.pitch_jitter_deg,
                                noise.height_jitter_m, sj, sj, sj])
        self.phase_s = float(rng.uniform(0.0, 1.0 / noise.telemetry_hz))
        self._a = math.exp(-1.0 / (noise.telemetry_hz * noise.jitter_corr_s))
        self._z = rng.standard_normal(len(_CH))  # stationary start
        self._k: int | None = None
        self._missing_rng = np.random.default_rng(rng.integers(0, 2**63))
        # The log defects draw from a child of the seed (spawning consumes nothing from `rng`).
        seed_seq = getattr(rng.bit_generator, "seed_seq", None)
        self._defect_rng = np.random.default_rng(seed_seq.spawn(1)[0] if seed_seq is not None
                                                 else rng.integers(0, 2**63))
        wg = noise.white_gps_m / math.sqrt(2.0)
        self._white_sigma = np.array([wg, wg, noise.white_heading_deg, noise.white_pitch_deg])
        self._white = np.zeros(4)
        self._white_k: int | None = None
        # a GPS updating slower than the telemetry: its phase, drawn only then and from a child of its own (the other
        # fields of the stream are those it has without the hold), and the last update's index and position (metres
        # east, north with their errors)
        self._gps_phase = 0.0
        if noise.gps_hz > 0:
            gps_rng = np.random.default_rng(seed_seq.spawn(1)[0] if seed_seq is not None
                                            else self._defect_rng.integers(0, 2**63))
            self._gps_phase = float(gps_rng.uniform(0.0, 1.0 / noise.gps_hz))
        self._gps_k: int | None = None
        self._gps_en = (0.0, 0.0)
        self.bias = {"east_m": float(self._bias[0]), "north_m": float(self._bias[1]),
                     "heading_deg": float(self._bias[2]), "pitch_deg": float(self._bias[3]),
                     "height_m": float(self._bias[4])}

    def _advance(self, k: int) -> None:
        if self._k is None:
            self._k = k
            return
        for _ in range(max(0, k - self._k)):
            self._z = self._a * self._z + math.sqrt(1.0 - self._a * self._a) * self._rng.standard_normal(len(_CH))
        self._k = max(self._k, k)

    def offset_s(self, t_s: float) -> float:
        """Telemetry lag behind the frame at flight time t_s (constant plus drift), seconds."""
        return self.noise.time_offset_s + self.noise.time_offset_drift * max(t_s, 0.0)

    def sample_time(self, t_s: float) -> float:
        """Flight time (s) at which the telemetry attached to the frame at t_s was measured."""
        k = math.floor((t_s - self.offset_s(t_s) - self.phase_s) * self.noise.telemetry_hz + 1e-9)
        return self.phase_s + k / self.noise.telemetry_hz

    def camera_roll_deg(self) -> float:
        """The camera's true roll in the next frame (white, unreported), degrees; 0 when off."""
        if self.noise.camera_roll_deg <= 0:
            return 0.0
        return float(np.clip(self.noise.camera_roll_deg * self._defect_rng.standard_normal(), -30.0, 30.0))

    def _white_at(self, k: int) -> np.ndarray:
        """White jitter (east, north, heading, pitch) of telemetry sample k (one draw per new sample)."""
        if not self._white_sigma.any():
            return self._white
        if self._white_k != k:
            self._white = self._white_sigma * self._defect_rng.standard_normal(4)
            self._white_k = k
        return self._white

    def meta(self, t_s: float) -> tuple[dict[str, Any] | None, FlightState]:
        """The SeaDronesSee meta for the frame at flight time t_s (frames must come in time order).

        Returns
        -------
        meta : dict or None
            Layout "seadronessee": ``gps_latitude, gps_latitude_ref, gps_longitude, gps_longitude_ref,
            altitude, gimbal_pitch, compass_heading, gimbal_heading, speed, xspeed, yspeed, zspeed,
            date_time``: positive lat/lon with N/S/E/W refs, altitude = height above ground (m), gimbal_pitch
            = depression (deg, 0..90), headings in [0, 360), speeds m/s with xspeed north, yspeed east,
            zspeed down (DJI), date_time the sample's stamp on the video clock (ISO 8601 UTC, ms).
            Layout "flight_log": the same values as ``datetime(utc)`` (naive UTC ``YYYY-MM-DD HH:MM:SS``),
            ``latitude``, ``longitude`` (signed degrees), ``height_above_takeoff(meter)``, ``speed(m/s)``,
            ``xspeed(m/s)``, ``yspeed(m/s)``, ``zspeed(m/s)``, ``compass_heading(degrees)``,
            ``gimbal_heading(degrees)``, ``gimbal_pitch(degrees)`` (positive below the horizon).
            Either stamp is truncated to `TelemetryNoise.stamp_resolution_s`. None for a dropout.
        state : FlightState
            The true state at the sample time (what the meta measures, before noise).
        """
        ts = self.sample_time(t_s)
        k = round((ts - self.phase_s) * self.noise.telemetry_hz)
        self._advance(k)
        missing = self._missing_rng.uniform() < self.noise.missing_meta_rate
        st = self.flight.state(ts)
        err = self._bias + self._sigma * self._z
        white = self._white_at(k)
        if missing:
            return None, st
        east, north = st.east_m + err[0] + white[0], st.north_m + err[1] + white[1]
        if self.noise.gps_hz > 0:  # the position of the GPS's last update, held
            kg = math.floor((ts - self._gps_phase) * self.noise.gps_hz + 1e-9)
            if kg != self._gps_k:
                g = self.flight.state(self._gps_phase + kg / self.noise.gps_hz)
                self._gps_k, self._gps_en = kg, (g.east_m + err[0] + white[0], g.north_m + err[1] + white[1])
            east, north = self._gps_en
        lat_arr, lon_arr = local_to_latlon(east, north, *self.origin)
        lat, lon = float(lat_arr), float(lon_arr)
        digits = self.noise.gps_decimals or 8
        height = max(st.height_m + err[4], 0.1)
        if self.noise.altitude_step_m > 0:
            height = max(round(height / self.noise.altitude_step_m) * self.noise.altitude_step_m, 0.1)
        pitch = min(max(st.pitch_deg + err[3] + white[3], 0.0), 90.0)
        err[2] += white[2]
        ve, vn, vu = st.vel_east_mps + err[5], st.vel_north_mps + err[6], st.vel_up_mps + err[7]
        stamp = truncate_stamp(self.t0_unix_s + ts + self.offset_s(t_s), self.noise.stamp_resolution_s)
        compass, gimbal = _wrap360(st.aircraft_heading_deg + err[2]), _wrap360(st.heading_deg + err[2])
        speed, xspeed, yspeed, zspeed = round(math.hypot(ve, vn), 3), round(vn, 3), round(ve, 3), round(-vu, 3)
        if self.noise.meta_layout == "flight_log":
            return {
                "datetime(utc)": format_log_time(stamp),
                "latitude": round(lat, digits),
                "longitude": round(lon, digits),
                "height_above_takeoff(meter)": round(height, 3),
                "speed(m/s)": speed,
                "xspeed(m/s)": xspeed,
                "yspeed(m/s)": yspeed,
                "zspeed(m/s)": zspeed,
                "compass_heading(degrees)": compass,
                "gimbal_heading(degrees)": gimbal,
                "gimbal_pitch(degrees)": round(pitch, 3),
            }, st
        meta = {
            "gps_latitude": round(abs(lat), digits),
            "gps_latitude_ref": "N" if lat >= 0 else "S",
            "gps_longitude": round(abs(lon), digits),
            "gps_longitude_ref": "E" if lon >= 0 else "W",
            "altitude": round(height, 3),
            "gimbal_pitch": round(pitch, 3),
            "compass_heading": compass,
            "gimbal_heading": gimbal,
            "speed": speed,
            "xspeed": xspeed,
            "yspeed": yspeed,
            "zspeed": zspeed,
            "date_time": format_time(stamp),
        }
        return meta, st

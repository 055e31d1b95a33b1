"""Telemetry put on the frame clock: time zones removed, sample-and-hold repeats recognised, poses at frame time.

Real files stamp their telemetry on another clock than their frames. SeaDronesSee writes the flight log's
``datetime(utc)`` at whole seconds beside frames in local time (two hours ahead), and repeats one log
sample on every frame until the next one (sample and hold). Used as written, every time-based stage
compares times two hours apart. This stage, per video:

1. estimates the zone offset: the median of frame time - telemetry stamp over the frames that have both.
   When it lies within `zone_tolerance_s` of a non-zero whole number of quarter hours (every zone in use
   is) and the differences agree (their spread is below `max_spread_s`), that multiple of 15 minutes is
   removed from the stamps; the rest (latency, whole-second rounding) is left to the clock-offset estimate
   (agent.clock_offset), which applies only what it measures. A difference that is not a zone (or a
   spread that says the stamps do not follow the frames) makes the stage stand down: the stamps are not
   used for timing and each sample is placed where its values first appear in the frames;
2. finds the telemetry's own samples: consecutive frames whose stamp and values repeat are one sample
   (sample and hold); several samples under one stamp (a 10 Hz log stamped at whole seconds) are spread
   evenly up to the next stamp;
3. gives every frame the telemetry interpolated at its own time between those samples (`TelemetryTrack`).

The report says what it found and what it did. Arrays in, arrays out: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from shared.telemetry.interpolation import spread_repeated_stamps

__all__ = ["ClockReport", "TelemetryClockSettings", "TelemetryTrack", "reconcile_clock"]


@dataclass(frozen=True, slots=True)
class TelemetryClockSettings:
    """Settings of the stage (see the module docstring).

    zone_step_s: time zones differ by whole multiples of this (15 minutes).
    zone_tolerance_s: the median frame - stamp difference may be this far from a multiple of zone_step_s
        (whole-second stamps, telemetry latency, a camera clock set by hand a minute off).
    max_spread_s: the differences' inter-quartile range must be below this for the stamps to be trusted
        (a few seconds: stamps and frames run together).
    min_frames: frames with both clocks needed to estimate a zone.
    """

    zone_step_s: float = 900.0
    zone_tolerance_s: float = 120.0
    max_spread_s: float = 5.0
    min_frames: int = 2

    def __post_init__(self) -> None:
        for name in ("zone_step_s", "zone_tolerance_s", "max_spread_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"telemetry clock {name} must be a finite number > 0, got {value!r}")
        if self.zone_tolerance_s >= self.zone_step_s / 2:
            raise ValueError(f"telemetry clock zone_tolerance_s must be below zone_step_s / 2, "
                             f"got {self.zone_tolerance_s!r}")
        if self.min_frames < 1:
            raise ValueError(f"telemetry clock min_frames must be >= 1, got {self.min_frames!r}")


@dataclass(frozen=True, slots=True)
class ClockReport:
    """What the stage found for one video and whether it acted.

    frames: frames with telemetry; samples: distinct telemetry samples among them; whole_seconds: every
    stamp is a whole second; zone_offset_s: removed from the stamps (a multiple of 15 min; 0: none);
    residual_s: median frame - stamp left after that; stamps_used: the samples are timed by their stamps
    (else by where their values first appear in the frames); reason: why the stamps were not used, or ''.
    """

    frames: int = 0
    samples: int = 0
    whole_seconds: bool = False
    zone_offset_s: float = 0.0
    residual_s: float = 0.0
    stamps_used: bool = True
    reason: str = ""

    @property
    def held_frames(self) -> int:
        """Frames that repeat an earlier frame's sample (sample and hold)."""
        return self.frames - self.samples

    def describe(self) -> str:
        """One line for logs and summaries."""
        parts = [f"{self.samples} samples on {self.frames} frames"]
        if self.whole_seconds:
            parts.append("stamps at whole seconds")
        if self.zone_offset_s:
            parts.append(f"zone offset {self.zone_offset_s / 3600:+g} h removed")
        if self.stamps_used:
            parts.append(f"residual {self.residual_s:+.2f} s left to the clock-offset estimate")
        else:
            parts.append(f"stamps not used ({self.reason})")
        return ", ".join(parts)


class TelemetryTrack:
    """One video's distinct telemetry samples on the frame clock, interpolated at any time.

    t (M,) increasing seconds; values (M, 5): lat, lon (degrees, unwrapped across the antimeridian), height (m),
    heading (degrees, unwrapped), pitch (degrees). Interpolation is linear (heading and longitude along the shorter
    way) and holds the end values outside the samples.
    """

    COLUMNS = ("lat", "lon", "height_m", "heading_deg", "pitch_deg")

    def __init__(self, t: NDArray, values: NDArray) -> None:
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        values = np.asarray(values, dtype=np.float64).reshape(len(t), len(self.COLUMNS))
        if len(t) and not np.all(np.diff(t) > 0):
            raise ValueError("TelemetryTrack times must increase strictly")
        values = values.copy()
        if len(t):  # heading, and longitude across the antimeridian, along the shorter way
            values[:, 3] = np.degrees(np.unwrap(np.radians(values[:, 3])))
            values[:, 1] = np.degrees(np.unwrap(np.radians(values[:, 1])))
        self.t = t
        self.values = values
        # each column contiguous: np.interp copies a strided column whole on every call (90 us a call on an
        # hour's 10 Hz log, per frame twice: the cost grew with the log's length)
        self._columns = np.ascontiguousarray(values.T)

    def __len__(self) -> int:
        return len(self.t)

    def column(self, name: str) -> NDArray:
        """The samples' values of one column (COLUMNS), (M,)."""
        return self.values[:, self.COLUMNS.index(name)]

    def replace_column(self, name: str, values: NDArray) -> TelemetryTrack:
        """A copy with one column's samples replaced (e.g. dequantised positions)."""
        out = self.values.copy()
        out[:, self.COLUMNS.index(name)] = np.asarray(values, dtype=np.float64).reshape(-1)
        return TelemetryTrack(self.t, out)

    def at(self, times: NDArray | float) -> NDArray:
        """(N, 5) values at times (N,): lat, lon in [-180, 180), height, heading in [0, 360), pitch."""
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if not len(self.t):
            raise ValueError("TelemetryTrack has no samples")
        out = np.stack([np.interp(times, self.t, column) for column in self._columns], axis=1)
        out[:, 3] %= 360.0
        out[:, 1] = (out[:, 1] + 180.0) % 360.0 - 180.0
        return out


def _samples(stamps: NDArray, values: NDArray) -> NDArray[np.int64]:
    """Index of the distinct sample each frame carries: a new sample where the stamp or a value changes."""
    n = len(stamps)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    same = np.zeros(n, dtype=bool)
    same[1:] = (stamps[1:] == stamps[:-1]) & np.all(values[1:] == values[:-1], axis=1)
    return np.cumsum(~same) - 1


def reconcile_clock(frame_t: NDArray, stamp_t: NDArray, values: NDArray, frame_clock: NDArray,
                    settings: TelemetryClockSettings | None = None) -> tuple[TelemetryTrack, ClockReport]:
    """One video's telemetry samples on the frame clock.

    frame_t: (N,) frame times (s) in frame order; stamp_t: (N,) each frame's telemetry stamp (s, its own
    clock); values: (N, 5) the telemetry each frame carries (TelemetryTrack.COLUMNS, heading in degrees);
    frame_clock: (N,) bool, the frame time comes from the frame's own clock (else it was taken from the
    stamp). Returns the track (times on the frame clock) and the report.
    """
    s = settings or TelemetryClockSettings()
    frame_t = np.asarray(frame_t, dtype=np.float64).reshape(-1)
    stamp_t = np.asarray(stamp_t, dtype=np.float64).reshape(-1)
    values = np.asarray(values, dtype=np.float64).reshape(len(frame_t), len(TelemetryTrack.COLUMNS))
    frame_clock = np.asarray(frame_clock, dtype=bool).reshape(-1)
    n = len(frame_t)
    if not (len(stamp_t) == n == len(frame_clock)):
        raise ValueError("frame_t, stamp_t, values and frame_clock must have the same length")
    if n == 0:
        return TelemetryTrack(np.zeros(0), np.zeros((0, 5))), ClockReport()
    finite = np.isfinite(stamp_t)
    whole = bool(finite.all() and np.all(stamp_t == np.round(stamp_t)))
    sample_of = _samples(np.where(finite, stamp_t, -np.inf), values)
    m = int(sample_of[-1]) + 1
    first = np.searchsorted(sample_of, np.arange(m))  # first frame of each sample
    both = frame_clock & finite
    zone = residual = 0.0
    stamps_used = bool(finite.all())
    reason = "" if stamps_used else "some frames have no telemetry stamp"
    if stamps_used and both.sum() >= s.min_frames:
        diff = frame_t[both] - stamp_t[both]
        median = float(np.median(diff))
        q75, q25 = np.percentile(diff, [75, 25])
        zone = round(median / s.zone_step_s) * s.zone_step_s
        if q75 - q25 > s.max_spread_s:
            stamps_used, zone = False, 0.0
            reason = f"frame - stamp differences spread over {q75 - q25:.1f} s"
        elif abs(median - zone) > s.zone_tolerance_s:
            stamps_used, zone = False, 0.0
            reason = f"the clocks differ by {median:+.1f} s, not a whole number of quarter hours"
        else:
            residual = median - zone
    elif stamps_used and both.any():
        stamps_used = False
        reason = f"only {int(both.sum())} frame(s) carry both clocks"
    if stamps_used:
        t = spread_repeated_stamps(stamp_t[first] + zone, whole)
    else:
        t = frame_t[first].copy()  # where each sample's values first appear
    # a log that goes back in time (or repeats a stamp after other values) keeps its order: nudge forward
    for k in range(1, len(t)):
        if t[k] <= t[k - 1]:
            t[k] = t[k - 1] + 1e-3
    track = TelemetryTrack(t, values[first])
    return track, ClockReport(frames=n, samples=m, whole_seconds=whole, zone_offset_s=float(zone),
                              residual_s=float(residual), stamps_used=stamps_used, reason=reason)

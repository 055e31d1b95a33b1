"""When a flight log says the camera recorded video: the start of the video on the log's clock, from a camera's
status messages or its start/stop commands, judged on their own evidence (`.tlog` and `.ulg` readers alike).

A flight controller's log starts at connection or arming, seconds to minutes before the video; where the log says
when recording started, the records carry it as AirData's ``isVideo`` does (`Telemetry.recording`), and the exact
start (it may precede the log's first record) is `LogRecording.start_t`. Pure: arrays in, values out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from shared.telemetry.record import Telemetry

__all__ = ["CONSISTENT_S", "FlightLogReport", "LogRecording", "first_movement_t", "from_commands", "from_status",
           "mark_recording", "no_start_placement"]

#: Starts told by a status's elapsed recording time (now - recording_time_ms) agree this closely (median absolute
#: deviation, seconds) when that time counts up with the clock; a camera that leaves it 0 or counts otherwise says
#: nothing about the start.
CONSISTENT_S = 0.5


@dataclass(frozen=True, slots=True)
class LogRecording:
    """What a log says about the camera's recording.

    spans: (start, stop) per recording on the records' clock (stop inf while it goes on to the end of the log; a
    start may be before the log's first record); source: the evidence used ("" without any); note: why a log with
    camera messages gives no start ("" otherwise); precise: the start is known to within a link's latency (the
    recording's own elapsed time, or the command's acknowledgement), not only to a status interval.
    """

    spans: tuple[tuple[float, float], ...] = ()
    source: str = ""
    note: str = ""
    precise: bool = False

    @property
    def start_t(self) -> float | None:
        """The first recording's start, or None."""
        return self.spans[0][0] if self.spans else None


@dataclass(frozen=True, slots=True)
class FlightLogReport:
    """A flight controller's log read: its records (time order, `Telemetry.recording` set where the log says) and
    what it says about the recording (`LogRecording`)."""

    records: list[Telemetry]
    recording: LogRecording


def from_status(t_s: ArrayLike, video_status: ArrayLike, recording_time_ms: ArrayLike,
                what: str = "CAMERA_CAPTURE_STATUS") -> LogRecording:
    """Recordings from a camera's status messages: (N,) times (sorted, on the records' clock), ``video_status``
    (1 = recording) and ``recording_time_ms`` (elapsed time of the recording; 0 or NaN when not sent).

    A recording starts where the status turns to 1 and stops where it turns back. Its start is the status times
    minus their elapsed times where those agree (`CONSISTENT_S`; precise, and it may be before the first
    message), else halfway between the last idle status and the first recording one. A status that says recording
    from its first message, without an elapsed time that counts up with the clock, says nothing about the start:
    that recording is left out and `note` says so.
    """
    t = np.asarray(t_s, dtype=float)
    recording = np.asarray(video_status, dtype=float) == 1
    elapsed_s = np.asarray(recording_time_ms, dtype=float) / 1e3
    if not len(t):
        return LogRecording()
    if not recording.any():
        return LogRecording(note=f"{what} never says recording (video_status 1) in its {len(t)} messages")
    edges = np.flatnonzero(np.diff(np.concatenate([[0], recording.astype(np.int8), [0]])))
    spans, notes, precise = [], [], True
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        told = t[a:b] - elapsed_s[a:b]
        told = told[np.isfinite(told) & (elapsed_s[a:b] > 0)]
        middle = float(np.median(told)) if len(told) >= 2 else math.nan
        agree = len(told) >= 2 and float(np.median(np.abs(told - middle))) <= CONSISTENT_S and middle <= t[a] + 0.1 \
            and (a == 0 or middle >= t[a - 1] - CONSISTENT_S)
        stop = float(t[b]) if b < len(t) else math.inf
        if agree:
            spans.append((middle, stop))
        elif a > 0:
            spans.append((float(t[a - 1] + t[a]) / 2.0, stop))
            precise = False
        else:
            notes.append(f"{what} says recording from its first message ({b} of {len(t)} messages) without a "
                         "recording_time_ms that counts up with the clock: it does not say when that recording "
                         "started")
    return LogRecording(tuple(spans), f"{what} video_status" + (" and recording_time_ms" if precise else ""),
                        "; ".join(notes), precise and bool(spans))


def from_commands(start_t: Sequence[float], stop_t: Sequence[float], what: str) -> LogRecording:
    """Recordings from accepted start and stop commands (times on the records' clock, any order): each start opens
    a recording (a start while one is open is a repeat), each stop closes the open one."""
    events = sorted([(float(t), 1) for t in start_t] + [(float(t), 0) for t in stop_t])
    spans: list[tuple[float, float]] = []
    opened: float | None = None
    for t, is_start in events:
        if is_start and opened is None:
            opened = t
        elif not is_start and opened is not None:
            spans.append((opened, t))
            opened = None
    if opened is not None:
        spans.append((opened, math.inf))
    return LogRecording(tuple(spans), what if spans else "", "", bool(spans))


def mark_recording(records: list[Telemetry], recording: LogRecording) -> list[Telemetry]:
    """The records with `Telemetry.recording` True inside a recording's span and False elsewhere; unchanged when
    the log says nothing (no spans)."""
    if not recording.spans:
        return records
    return [replace(r, recording=any(a <= r.t < b for a, b in recording.spans)) for r in records]


def first_movement_t(records: Sequence[Telemetry], *, speed_mps: float = 1.0, height_m: float = 2.0) -> float | None:
    """The time of the first record (time order) where the vehicle moves (speed >= speed_mps) or is up (height >=
    height_m), None when it never does: where a flight log's flight, and usually its video, begins."""
    for r in records:
        moving = r.speed_mps is not None and r.speed_mps >= speed_mps
        if moving or (r.height_m is not None and r.height_m >= height_m):
            return r.t
    return None


def no_start_placement(records: Sequence[Telemetry]) -> str:
    """What to tell when a flight log (records in time order, not empty) gives no recording start and the video
    is placed at its first record: how long before the vehicle first moves that is (`first_movement_t`)."""
    moves = first_movement_t(records)
    where = ("where the vehicle already moves" if moves == records[0].t else "and the vehicle never moves"
             if moves is None else f"{moves - records[0].t:.1f} s before the vehicle first moves or climbs")
    return (f"no recording start in the log; the video is placed at the log's first record, {where}; pass "
            "--telemetry-offset-s if the video started later")

"""Benchmark of the fusion server's global tracker (`fusion_server.global_tracks`): the cost of a UAV's tracks
message with re-association (`fusion_server.reassociation`, the default) against the same messages without it,
measured in the same run.

A fleet of UAVs in pairs over one field of people (each pair sees the same 100 people, each UAV with its own
1-3 m telemetry offset and 0.3 m of noise a report, the people walking at 1 m/s); every UAV sends its tracks
message at 5 Hz for 20 s (60 s without --quick) on a simulated clock. Cases: the whole run's messages with and
without re-association (the two in turns, one sample each a round; the ratio the median of the per-round ratios),
in ms per message; and the share of people both UAVs of their pair track under one global id at the end (a pair's
two offsets are up to 8 m apart, about the people's spacing: the first association is often another person).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmarks.timing import interleaved_samples_s, paired_ratio
from fusion_server.global_tracks import GlobalTracker
from shared.messages import TrackItem, TracksMessage

DESCRIPTION = "ms per tracks message of the global tracker with re-association vs without"

_LAT, _LON = 47.67, 9.27
_M_LAT = 1.0 / 111_320.0
_HZ = 5.0


def _messages(pairs: int, people: int, seconds: float) -> list[TracksMessage]:
    """Every UAV's tracks messages of the run, in time order (UAV pairs side by side, 500 m apart)."""
    rng = np.random.default_rng(0)
    m_lon = _M_LAT / np.cos(np.radians(_LAT))
    start = rng.uniform(-40.0, 40.0, (pairs, people, 2))
    heading = rng.uniform(0.0, 2 * np.pi, (pairs, people))
    vel = np.stack([np.sin(heading), np.cos(heading)], axis=-1)  # east, north m/s
    offset = rng.uniform(-3.0, 3.0, (pairs, 2, 2))
    out = []
    for k in range(int(seconds * _HZ)):
        t = k / _HZ
        for p in range(pairs):
            for side in range(2):
                at = start[p] + vel[p] * t + offset[p, side] + rng.normal(0.0, 0.3, (people, 2))
                lat, lon = _LAT + at[:, 1] * _M_LAT, _LON + (at[:, 0] + 500.0 * p) * m_lon
                out.append(TracksMessage(uav=f"uav{2 * p + side}", t=t, tracks=tuple(
                    TrackItem(id=i, cls="person", lat=float(lat[i]), lon=float(lon[i]), score=0.9,
                              vel_en=(float(vel[p, i, 0]), float(vel[p, i, 1]))) for i in range(people))))
    return out


def _replay(messages: list[TracksMessage], reassociate_m: float) -> GlobalTracker:
    now = [0.0]
    tracker = GlobalTracker(gate_m=10.0, hold_s=10.0, member_ttl_s=2.0, keep_changes=False,
                            clock=lambda: now[0], wall=lambda: now[0], reassociate_m=reassociate_m)
    for msg in messages:
        now[0] = msg.t
        tracker.update(msg)
    return tracker


def run(quick: bool = False) -> list[dict[str, Any]]:
    pairs, people = (2, 50) if quick else (5, 100)
    messages = _messages(pairs, people, 20.0 if quick else 60.0)
    times = interleaved_samples_s({"without": lambda: _replay(messages, 0.0), "with": lambda: _replay(messages, 6.0)},
                                  repeat=3 if quick else 5, min_time_s=0.0)
    n = len(messages)
    plain, moving = _replay(messages, 0.0), _replay(messages, 6.0)
    paired = {name: 100.0 * float(np.mean([tracker.gid_of(f"uav{2 * p}", i) == tracker.gid_of(f"uav{2 * p + 1}", i)
                                           for p in range(pairs) for i in range(people)]))
              for name, tracker in (("without", plain), ("with", moving))}
    return [
        {"case": f"{2 * pairs} UAVs x {people} tracks at 5 Hz, without re-association", "unit": "ms/message",
         "value": float(np.median(times["without"])) / n * 1e3},
        {"case": f"the same with re-association ({moving.stats()['reassociated']} moves)", "unit": "ms/message",
         "value": float(np.median(times["with"])) / n * 1e3, "baseline_name": "without",
         "ratio": paired_ratio(times["with"], times["without"])},
        {"case": "people on one global id on both UAVs at the end, without re-association", "unit": "%",
         "value": paired["without"]},
        {"case": "the same with re-association", "unit": "%", "value": paired["with"], "baseline_name": "without",
         "ratio": paired["with"] / max(paired["without"], 1e-9)},
    ]

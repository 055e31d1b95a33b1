"""Benchmark of the live MAVLink feed (`agent.mavlink_feed`): the records a video frame's pose needs, late in a long
flight.

A flight of 10 Hz positions with a gimbal (30 minutes, 18,000 records; quick: 5 minutes) is sent over loopback UDP
to a real `MavlinkUdpFeed`; then, per frame, the records around one time: `records_between` (what the video source
asks for) against the baseline `records` (every record so far, converted: what it asked for before), measured in
the same run. The cost of the baseline grows with the flight; the window's does not.
"""

from __future__ import annotations

import math
import socket
import time
from typing import Any

from benchmarks.timing import median_time_s

DESCRIPTION = "ms per frame of the live feed's records around a frame's time vs every record so far"

_T0 = 1_685_613_600.0
_RATE_HZ = 10.0


def _send_flight(port: int, n: int) -> None:
    """n positions at _RATE_HZ with a gimbal in the earth frame, the vehicle's SYSTEM_TIME first; 100 positions to a
    datagram (MAVLink over UDP may pack several messages in one)."""
    from pymavlink.dialects.v20 import ardupilotmega

    autopilot = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=1)
    gimbal = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=154)
    half = math.radians(45.0) / 2.0
    q = [math.cos(half), 0.0, -math.sin(half), 0.0]  # 45 deg down, heading north
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.sendto(autopilot.system_time_encode(int(_T0 * 1e6), 20_000).pack(autopilot), ("127.0.0.1", port))
        for start in range(0, n, 100):
            chunk = b""
            for i in range(start, min(start + 100, n)):
                boot_ms = 20_000 + int(round(i * 1000.0 / _RATE_HZ))
                chunk += gimbal.gimbal_device_attitude_status_encode(0, 0, boot_ms, 16 | 64, q, 0, 0, 0, 0).pack(gimbal)
                chunk += autopilot.global_position_int_encode(boot_ms, int(48.53e7) + i, int(9.06e7), 500_000, 40_000,
                                                              100, 0, 0, 0).pack(autopilot)
            sock.sendto(chunk, ("127.0.0.1", port))
            time.sleep(0.002)  # let the receiving thread keep up (a datagram ~8 kB)
    finally:
        sock.close()


def run(quick: bool = False) -> list[dict[str, Any]]:
    from agent.mavlink_feed import MavlinkUdpFeed

    try:
        import pymavlink  # noqa: F401  (the optional mavlink extra)
    except ImportError:
        return []  # no MAVLink: nothing to measure (as the other benchmarks without their extras)

    minutes = 5 if quick else 30
    n = int(minutes * 60 * _RATE_HZ)
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    feed = MavlinkUdpFeed(f"udp:127.0.0.1:{port}")
    try:
        _send_flight(port, n)
        feed.start(timeout_s=10.0)
        deadline = time.monotonic() + 60.0
        while len(feed.records()) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        got = len(feed.records())
        t = _T0 + (n - 5) / _RATE_HZ  # a frame near the end of the flight
        base = median_time_s(feed.records, repeat=5, min_time_s=0.2)
        window = median_time_s(lambda: feed.records_between(t - 1.0, t + 1.0), repeat=5, min_time_s=0.2)
    finally:
        feed.close()
    return [
        {"case": f"every record so far ({got} of {n}, {minutes} min at 10 Hz)", "value": base * 1e3,
         "unit": "ms/frame"},
        {"case": "records around the frame's time (records_between, +-1 s)", "value": window * 1e3,
         "unit": "ms/frame", "baseline_name": "every record", "ratio": window / base},
    ]

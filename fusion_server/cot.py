"""Cursor-on-Target (CoT) events for TAK clients (ATAK, WinTAK, iTAK, a TAK server): the fleet on their map.

Every interval, one event per UAV (its position, heading and camera as a sensor) and per global track
(class, score, course and speed), each with a stale time; an ended track gets one last event that is
already stale, so TAK removes it. Sent as UDP datagrams (unicast or multicast, e.g. the SA group
``udp://239.2.3.1:6969``) or streamed over TCP to a TAK server's plain input (``tcp://HOST:8087``).
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any
from urllib.parse import urlsplit

__all__ = ["CLASS_TYPES", "CotSender", "CotTarget", "parse_cot_url", "track_event", "uav_event"]

log = logging.getLogger(__name__)

#: CoT type per class (MIL-STD-2525 in CoT form, affiliation unknown); others get "a-u-G" (ground)
CLASS_TYPES = {
    "person": "a-u-G", "swimmer": "a-u-S", "boat": "a-u-S", "buoy": "a-u-S", "life_saving_appliance": "a-u-S",
    "car": "a-u-G-E-V", "vehicle": "a-u-G-E-V", "truck": "a-u-G-E-V",
}
UAV_TYPE = "a-f-A-M-F-Q"  # friendly, air, military, fixed wing, UAV (TAK's drone icon)
UNKNOWN = "9999999.0"  # CoT's value for an unknown height or error


@dataclass(frozen=True, slots=True)
class CotTarget:
    """Where events go: ``udp`` or ``tcp``, a host and a port."""

    scheme: str
    host: str
    port: int


def parse_cot_url(url: str) -> CotTarget:
    """``udp://HOST:PORT`` or ``tcp://HOST:PORT``; ValueError naming what is wrong."""
    parts = urlsplit(url)
    if parts.scheme not in ("udp", "tcp"):
        raise ValueError(f"--cot-url must start with udp:// or tcp://, got {url!r}")
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None or port == 0 or parts.path not in ("", "/"):
        raise ValueError(f"--cot-url must be {parts.scheme}://HOST:PORT, got {url!r}")
    return CotTarget(parts.scheme, parts.hostname, port)


def _stamp(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _event(uid: str, cot_type: str, lat: float, lon: float, now: float, stale_s: float,
           ce_m: float | None = None) -> tuple[ET.Element, ET.Element]:
    event = ET.Element("event", {
        "version": "2.0", "uid": uid, "type": cot_type, "how": "m-f",
        "time": _stamp(now), "start": _stamp(now), "stale": _stamp(now + stale_s),
    })
    ET.SubElement(event, "point", {"lat": f"{lat:.7f}", "lon": f"{lon:.7f}", "hae": UNKNOWN,
                                   "ce": UNKNOWN if ce_m is None else f"{ce_m:.1f}", "le": UNKNOWN})
    return event, ET.SubElement(event, "detail")


def _bytes(event: ET.Element) -> bytes:
    return b'<?xml version="1.0" encoding="UTF-8" standalone="yes"?>' + ET.tostring(event, encoding="utf-8")


def track_event(feature: Mapping[str, Any], now: float, stale_s: float, *, uid_prefix: str = "uavmm") -> bytes:
    """The CoT event of one global track (a Feature of ``/v1/tracks``); ended tracks are already stale."""
    props = feature["properties"]
    lon, lat = feature["geometry"]["coordinates"]
    cls = str(props["cls"])
    ended = props.get("status") == "ended"
    event, detail = _event(f"{uid_prefix}.track.{props['gid']}", CLASS_TYPES.get(cls, "a-u-G"), lat, lon, now,
                           0.0 if ended else stale_s, ce_m=5.0)
    ET.SubElement(detail, "contact", {"callsign": f"{cls} {props['gid']}"})
    east, north = props.get("vel_en") or (0.0, 0.0)
    course = math.degrees(math.atan2(east, north)) % 360.0
    ET.SubElement(detail, "track", {"course": f"{course:.1f}", "speed": f"{math.hypot(east, north):.2f}"})
    uavs = sorted({str(m[0]) for m in props.get("active_members") or props.get("members") or ()})
    ET.SubElement(detail, "remarks").text = (
        f"uavmm global track {props['gid']} ({cls}), score {float(props['score']):.2f}, "
        f"{props.get('status', 'tracked')}, seen by {', '.join(uavs) or 'nobody now'}")
    return _bytes(event)


def uav_event(row: Mapping[str, Any], now: float, stale_s: float, *, uid_prefix: str = "uavmm") -> bytes | None:
    """The CoT event of one UAV (a row of ``/v1/uavs``), or None without a position (no state yet)."""
    state = row.get("state")
    if not state:
        return None
    event, detail = _event(f"{uid_prefix}.uav.{row['id']}", UAV_TYPE, state["lat"], state["lon"], now, stale_s)
    ET.SubElement(detail, "contact", {"callsign": str(row["id"])})
    ET.SubElement(detail, "track", {"course": f"{float(state['heading_deg']) % 360.0:.1f}", "speed": "0.0"})
    camera = state.get("camera") or {}
    fov = 2.0 * math.degrees(math.atan2(camera["width"] / 2.0, camera["fx"])) if camera.get("fx") else 0.0
    ground_m = float(state["height_m"]) / max(math.sin(math.radians(max(float(state["pitch_deg"]), 1.0))), 1e-3)
    ET.SubElement(detail, "sensor", {
        "azimuth": f"{float(state['heading_deg']) % 360.0:.1f}", "elevation": f"{-float(state['pitch_deg']):.1f}",
        "fov": f"{fov:.1f}", "range": f"{ground_m:.0f}", "type": "r-e",
    })
    ET.SubElement(detail, "remarks").text = (
        f"uavmm UAV {row['id']} ({'online' if row.get('online') else 'offline'}), "
        f"{float(state['height_m']):.0f} m above ground, gimbal pitch {float(state['pitch_deg']):.0f} deg")
    return _bytes(event)


class CotSender:
    """A background thread sending the fleet's CoT events every ``interval_s``; never raises into the server.

    tracks: () -> Features of the global tracks (with recently ended ones). uavs: () -> ``/v1/uavs`` rows.
    Failures (no route, a TAK server that is down) are logged once per state change, counted and retried
    at the next interval (TCP reconnects).
    """

    def __init__(self, target: CotTarget, tracks: Callable[[], Iterable[Mapping[str, Any]]],
                 uavs: Callable[[], Iterable[Mapping[str, Any]]], *, interval_s: float = 1.0,
                 stale_s: float = 10.0, clock: Callable[[], float] = time.time) -> None:
        self.target = target
        self._tracks = tracks
        self._uavs = uavs
        self.interval_s = interval_s
        self.stale_s = stale_s
        self._clock = clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="uavmm-cot", daemon=True)
        self._sock: socket.socket | None = None
        self._ended_sent: set[int] = set()
        self.sent = 0
        self.failed = 0
        self._failing = False

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._disconnect()

    def events(self) -> list[bytes]:
        """This round's events: every UAV with a position, every live track, each ended track once."""
        now = self._clock()
        out = [e for row in self._uavs() if (e := uav_event(row, now, self.stale_s)) is not None]
        for feature in self._tracks():
            gid = feature["properties"]["gid"]
            if feature["properties"].get("status") == "ended":
                if gid in self._ended_sent:
                    continue
                self._ended_sent.add(gid)
            out.append(track_event(feature, now, self.stale_s))
        if len(self._ended_sent) > 100_000:  # ended tracks age out of the tracker long before this
            self._ended_sent.clear()
        return out

    def send_once(self) -> int:
        """Send one round; returns the number of events sent (0 when sending failed)."""
        events = self.events()
        try:
            sock = self._connect()
            for payload in events:
                if self.target.scheme == "udp":
                    sock.sendto(payload, (self.target.host, self.target.port))
                else:
                    sock.sendall(payload)
        except OSError as exc:
            self.failed += 1
            self._disconnect()
            if not self._failing:
                log.warning("CoT to %s://%s:%d failed (retrying every %.1f s): %s", self.target.scheme,
                            self.target.host, self.target.port, self.interval_s, exc)
            self._failing = True
            return 0
        if self._failing:
            log.info("CoT to %s://%s:%d works again", self.target.scheme, self.target.host, self.target.port)
        self._failing = False
        self.sent += len(events)
        return len(events)

    def _connect(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        if self.target.scheme == "udp":
            ipv6 = ":" in self.target.host
            sock = socket.socket(socket.AF_INET6 if ipv6 else socket.AF_INET, socket.SOCK_DGRAM)
            if not ipv6:  # a multicast SA group may sit a few routers away on a ground network
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 4)
        else:
            sock = socket.create_connection((self.target.host, self.target.port), timeout=5.0)
        self._sock = sock
        return sock

    def _disconnect(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.send_once()
            except Exception:  # a bug here must not stop the server's other work
                self.failed += 1
                log.exception("CoT round failed")

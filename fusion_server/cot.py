"""Cursor-on-Target (CoT) events for TAK clients (ATAK, WinTAK, iTAK, a TAK server): the fleet on their map.

Every interval, one event per UAV (its position, heading and camera as a sensor), per global track
(class, score, course and speed) and per fused object (a joint-map peak) that no global track of its class
explains (an early sighting not tracked yet, an anomaly), each with a stale time; an ended track gets one
last event that is already stale, so TAK removes it. Sent as UDP datagrams (unicast or multicast, e.g. the SA group
``udp://239.2.3.1:6969``) or streamed over TCP to a TAK server's plain input (``tcp://HOST:8087``).
"""

from __future__ import annotations

import dataclasses
import itertools
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

from fusion_server.global_tracks import TrackRecord
from fusion_server.peaks import Peak

__all__ = ["CLASS_TYPES", "CotSender", "CotTarget", "object_event", "parse_cot_url", "track_event", "uav_event"]

log = logging.getLogger(__name__)

#: CoT type per class (MIL-STD-2525 in CoT form, affiliation unknown); others get "a-u-G" (ground)
CLASS_TYPES = {
    "person": "a-u-G", "swimmer": "a-u-S", "boat": "a-u-S", "buoy": "a-u-S", "life_saving_appliance": "a-u-S",
    "car": "a-u-G-E-V", "vehicle": "a-u-G-E-V", "truck": "a-u-G-E-V",
}
UAV_TYPE = "a-f-A-M-F-Q"  # friendly, air, military, fixed wing, UAV (TAK's drone icon)
UNKNOWN = "9999999.0"  # CoT's value for an unknown height or error
#: A fused object within this many metres of a live global track of its class is that track (no own event).
OBJECT_GATE_M = 5.0
#: Fused objects sent per round at most (the strongest first), so a noisy map cannot flood a TAK network.
MAX_OBJECTS = 100


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


def object_event(peak: Peak, now: float, stale_s: float, *, uid_prefix: str = "uavmm") -> bytes:
    """The CoT event of one fused object (a joint-map peak, `fusion_server.peaks.Peak`).

    The uid names the peak's map cell (``uavmm.object.CLS.GX.GY``, cells of 0.6 m at the default zoom): a peak
    that drifts to another cell is a new event and the old one goes stale, so keep ``stale_s`` short.
    """
    event, detail = _event(f"{uid_prefix}.object.{peak.cls}.{int(peak.gx)}.{int(peak.gy)}",
                           CLASS_TYPES.get(peak.cls, "a-u-G"), peak.lat, peak.lon, now, stale_s, ce_m=5.0)
    ET.SubElement(detail, "contact", {"callsign": f"{peak.cls} {peak.score:.2f}"})
    ET.SubElement(detail, "remarks").text = (
        f"uavmm fused object ({peak.cls}): joint memory map peak {peak.score:.2f}, not a global track (yet)")
    return _bytes(event)


def _explained(peak: Peak, tracks: list[tuple[str, float, float]], gate_m: float) -> bool:
    """True when a live track of the peak's class lies within gate_m of it (equirectangular metres; the longitude
    difference taken the short way round, across the antimeridian too)."""
    cos_lat = math.cos(math.radians(peak.lat))
    for cls, lat, lon in tracks:
        d_lon = (lon - peak.lon + 180.0) % 360.0 - 180.0
        if cls == peak.cls and math.hypot(d_lon * cos_lat, lat - peak.lat) * 111_320.0 <= gate_m:
            return True
    return False


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

    tracks: () -> the global tracks (with recently ended ones): Features of ``/v1/tracks``, or better their
    ``TrackRecord``s, which are converted here only when sent (an ended track that went out already is skipped
    before anything is built) and without their history (CoT sends none). uavs: () -> ``/v1/uavs`` rows.
    objects: () -> the fused objects (joint-map peaks, strongest first) or None for none; those within
    ``OBJECT_GATE_M`` of a live track of their class are left out, at most ``MAX_OBJECTS`` are sent, and they
    go stale after ``object_stale_s`` (3 intervals by default: a peak that moves on leaves no ghost for long).
    Failures (no route, a TAK server that is down) are logged once per state change, counted and retried
    at the next interval (TCP reconnects).
    """

    def __init__(self, target: CotTarget, tracks: Callable[[], Iterable[Mapping[str, Any] | TrackRecord]],
                 uavs: Callable[[], Iterable[Mapping[str, Any]]], *, interval_s: float = 1.0,
                 stale_s: float = 10.0, clock: Callable[[], float] = time.time,
                 objects: Callable[[], Iterable[Peak]] | None = None, object_stale_s: float | None = None) -> None:
        self.target = target
        self._tracks = tracks
        self._uavs = uavs
        self._objects = objects
        self.interval_s = interval_s
        self.stale_s = stale_s
        self.object_stale_s = 3.0 * interval_s if object_stale_s is None else object_stale_s
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
        """This round's events: every UAV with a position, every live track, each ended track once, and the
        fused objects no live track explains."""
        now = self._clock()
        out = [e for row in self._uavs() if (e := uav_event(row, now, self.stale_s)) is not None]
        live: list[tuple[str, float, float]] = []
        for track in self._tracks():
            if isinstance(track, TrackRecord):
                gid, ended = track.gid, track.ended is not None
            else:
                gid, ended = track["properties"]["gid"], track["properties"].get("status") == "ended"
            if ended:
                if gid in self._ended_sent:
                    continue
                self._ended_sent.add(gid)
            feature = dataclasses.replace(track, history=()).to_geojson() if isinstance(track, TrackRecord) else track
            if not ended:
                lon, lat = feature["geometry"]["coordinates"]
                live.append((str(feature["properties"]["cls"]), float(lat), float(lon)))
            out.append(track_event(feature, now, self.stale_s))
        if self._objects is not None:
            untracked = (p for p in self._objects() if not _explained(p, live, OBJECT_GATE_M))
            out.extend(object_event(p, now, self.object_stale_s) for p in itertools.islice(untracked, MAX_OBJECTS))
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

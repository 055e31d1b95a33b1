"""Live MAVLink telemetry over UDP: listen where the flight controller (or a MAVLink router / ground station
forwarding its stream) sends, decode in a thread, and hand `Telemetry` records to the video source.

``--telemetry udp:HOST:PORT`` (or ``udpin:HOST:PORT``) binds HOST:PORT and receives, as pymavlink's ``udpin``
does; point the autopilot's telemetry or ``mavlink-routerd`` / MAVProxy ``--out`` at it. The decoding of the
messages is `shared.telemetry.mavlink` (no sockets there).

Clock: the records are on the autopilot's boot clock, anchored to UNIX time by the vehicle's own ``SYSTEM_TIME``
(waited for up to ``anchor_wait_s`` at start; a ground station's is ignored), else by this machine's clock at the
first message. The anchor is fixed at start, so the records' times never jump: when the vehicle's UNIX clock jumps
later (set from the ground station, then from GPS) a warning gives the step, and the records keep the start's clock.
"""

from __future__ import annotations

import bisect
import logging
import socket
import threading
import time
from pathlib import Path

from shared.telemetry import MavlinkAssembler, MavlinkByteParser, MavlinkSample, Telemetry

__all__ = ["LIVE_TELEMETRY_PREFIXES", "MavlinkUdpFeed", "is_live_telemetry", "parse_udp_endpoint"]

log = logging.getLogger(__name__)

#: Telemetry "paths" that are a live MAVLink stream, not a file.
LIVE_TELEMETRY_PREFIXES = ("udp:", "udpin:")


def is_live_telemetry(spec: str | Path) -> bool:
    """True for ``udp:HOST:PORT`` / ``udpin:HOST:PORT`` (a live stream), False for a file path."""
    return str(spec).lower().startswith(LIVE_TELEMETRY_PREFIXES)


def parse_udp_endpoint(spec: str) -> tuple[str, int]:
    """``udp:HOST:PORT`` -> (HOST, PORT); ValueError naming the spec otherwise (HOST may be 0.0.0.0)."""
    _scheme, _, rest = spec.partition(":")
    host, sep, port_text = rest.rpartition(":")
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not sep or not host or not 0 < port < 65536:
        raise ValueError(f"--telemetry {spec!r}: a live MAVLink stream is udp:HOST:PORT (e.g. udp:0.0.0.0:14550)")
    return host, port


class MavlinkUdpFeed:
    """Receive MAVLink on a UDP port in a background thread; records sorted by time.

    Parameters
    ----------
    spec : str
        ``udp:HOST:PORT`` or ``udpin:HOST:PORT``: the address to listen on.
    system_id : int, optional
        The vehicle's MAVLink system id (default: the first system that sends a position).
    height_offset_m : float
        Added to every height (``relative_alt`` is above the take-off point).

    Raises OSError naming the endpoint when it cannot be bound, ValueError for a bad spec, ImportError (with
    the install hint) without pymavlink.
    """

    def __init__(self, spec: str, *, system_id: int | None = None, height_offset_m: float = 0.0) -> None:
        self.spec = spec
        host, port = parse_udp_endpoint(spec)
        self._parser = MavlinkByteParser()
        self._assembler = MavlinkAssembler(system_id)
        self._system_id_given = system_id is not None
        self.height_offset_m = float(height_offset_m)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(f"cannot listen for MAVLink on {spec}: {exc.strerror or exc}") from None
        self._sock.settimeout(0.1)
        self._cond = threading.Condition()
        self._samples: list[MavlinkSample] = []  # sorted by boot_s, one per boot time
        self._times: list[float] = []
        self._first_rx: tuple[float, float] | None = None  # (wall time, boot s) of the first sample
        self._last_rx = 0.0
        self._anchor: float | None = None
        self._warned_jumps = self._warned_gimbals = 0  # clock jumps, ignored gimbals already warned about
        self._warned_systems = 1  # systems with positions: the vehicle alone needs no warning
        self.datagrams = 0
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._receive, name=f"mavlink {spec}", daemon=True)
        self._thread.start()

    # ---- receiving -----------------------------------------------------------------------------
    def _receive(self) -> None:
        while not self._closed.is_set():
            try:
                data = self._sock.recv(65535)
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            self.datagrams += 1
            now = time.time()
            for msg in self._parser.feed(data):
                sample = self._assembler.add(msg.get_type(), msg.to_dict(), msg.get_srcSystem(),
                                             msg.get_srcComponent())
                with self._cond:
                    self._last_rx = time.monotonic()
                    if sample is not None:
                        i = bisect.bisect_left(self._times, sample.boot_s)
                        if i == len(self._times) or self._times[i] != sample.boot_s:  # repeats count once
                            self._times.insert(i, sample.boot_s)
                            self._samples.insert(i, sample)
                        if self._first_rx is None:
                            self._first_rx = (now, sample.boot_s)
                    self._cond.notify_all()
                    self._warn_news()

    def _warn_news(self) -> None:
        """Warn once about each new thing the stream shows: a jump of the vehicle's UNIX clock after the anchor was
        fixed, a gimbal ignored, another system sending positions (called with the lock held)."""
        a = self._assembler
        jumps, gimbals, systems = a.clock_jumps, a.gimbals_ignored, a.position_counts
        if self._anchor is not None and len(jumps) > self._warned_jumps:
            for boot_s, step_s in jumps[self._warned_jumps:]:
                log.warning("MAVLink on %s: the vehicle's UNIX clock (SYSTEM_TIME) jumped by %+.3f s at boot %.1f s "
                            "(set from GPS, or a reboot?); the records keep the clock fixed at start: a "
                            "--telemetry-offset-s read from the new clock is %+.3f s off", self.spec, step_s, boot_s,
                            step_s)
            self._warned_jumps = len(jumps)
        if len(gimbals) > self._warned_gimbals:
            log.warning("MAVLink on %s: several gimbals: using %s (the first seen), ignoring %s", self.spec,
                        a.gimbal_used, ", ".join(gimbals))
            self._warned_gimbals = len(gimbals)
        if len(systems) > self._warned_systems:
            log.warning("MAVLink on %s: positions from %d systems (%s): using system %s%s", self.spec, len(systems),
                        ", ".join(str(sysid) for sysid in systems), a.system_id,
                        "" if self._system_id_given else ", the first to send one (system_id chooses another)")
            self._warned_systems = len(systems)

    # ---- records -------------------------------------------------------------------------------
    def start(self, timeout_s: float = 10.0, anchor_wait_s: float = 1.5) -> list[Telemetry]:
        """Wait for the first position (ValueError after `timeout_s`) and fix the clock anchor; the records so far."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._samples:
                left = deadline - time.monotonic()
                if left <= 0:
                    others = self._assembler.position_counts
                    seen = (f"; positions came from system {', '.join(str(sysid) for sysid in others)} only"
                            if others and self._system_id_given else "")
                    raise ValueError(f"no MAVLink position (GLOBAL_POSITION_INT) on {self.spec} within {timeout_s:g} s "
                                     f"({self.datagrams} datagrams received{seen}): is the autopilot's stream sent "
                                     "here?")
                self._cond.wait(left)
            anchor_deadline = time.monotonic() + anchor_wait_s
            while self._assembler.unix_offset_s is None and time.monotonic() < anchor_deadline:
                self._cond.wait(anchor_deadline - time.monotonic())
            if self._assembler.unix_offset_s is not None:
                self._anchor = self._assembler.unix_offset_s  # after the clock's jumps so far
                self._warned_jumps = len(self._assembler.clock_jumps)
            else:
                assert self._first_rx is not None
                wall, boot = self._first_rx
                self._anchor = wall - boot
                log.warning("MAVLink on %s: no SYSTEM_TIME with a UNIX time: times are this machine's clock at the "
                            "first message", self.spec)
        return self.records()

    def records(self) -> list[Telemetry]:
        """The records received so far, sorted by time (call `start` first)."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before records()")
        with self._cond:
            samples = list(self._samples)
        return [s.to_telemetry(self._anchor, self.height_offset_m) for s in samples]

    def records_between(self, t_first: float, t_last: float) -> list[Telemetry]:
        """The records from the last one at or before `t_first` to the first one at or after `t_last` (telemetry
        clock), sorted: what interpolating to times within [t_first, t_last] needs. Its cost does not grow with the
        flight (`records` converts every record so far: 97 ms a call after 30 minutes at 10 Hz, this VM)."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before records_between()")
        with self._cond:
            anchor = self._anchor
            lo = max(bisect.bisect_right(self._times, t_first - anchor) - 1, 0)
            hi = bisect.bisect_left(self._times, t_last - anchor) + 1
            samples = self._samples[lo:hi]
        return [s.to_telemetry(anchor, self.height_offset_m) for s in samples]

    def wait_for(self, t_first: float, t_last: float, *, timeout_s: float = 5.0, idle_s: float = 1.0) -> None:
        """Wait until the records span [t_first, t_last] (telemetry clock), the stream has been silent for
        `idle_s`, or `timeout_s` passed: whichever comes first. Frames then take what is there."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before wait_for()")
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                anchor = self._anchor
                if self._times and self._times[0] + anchor <= t_first and self._times[-1] + anchor >= t_last:
                    return
                now = time.monotonic()
                if now >= deadline or now - self._last_rx >= idle_s:
                    return
                self._cond.wait(min(deadline - now, idle_s))

    def close(self) -> None:
        """Stop receiving and release the port (idempotent)."""
        self._closed.set()
        self._sock.close()
        self._thread.join(timeout=1.0)

"""Live MAVLink telemetry over UDP: listen where the flight controller (or a MAVLink router / ground station
forwarding its stream) sends, decode in a thread, and hand `Telemetry` records to the video source.

``--telemetry udp:HOST:PORT`` (or ``udpin:HOST:PORT``) binds HOST:PORT and receives, as pymavlink's ``udpin``
does; point the autopilot's telemetry or ``mavlink-routerd`` / MAVProxy ``--out`` at it. The decoding of the
messages is `shared.telemetry.mavlink` (no sockets there).

Clock: the records are on the autopilot's boot clock, anchored to UNIX time by the vehicle's own ``SYSTEM_TIME``
(waited for up to ``anchor_wait_s`` at start; a ground station's is ignored), else by this machine's clock at the
first message. The anchor is fixed at start, so the records' times never jump: when the vehicle's UNIX clock jumps
later (set from the ground station, then from GPS) a warning gives the step, and the records keep the start's clock.

Reboots: an autopilot that reboots mid-flight restarts its boot clock, so its new positions would land in the past.
A position whose boot time falls more than `REBOOT_S` behind the current boot's latest, on a receive clock that
moved on (receive time minus boot time off by more than REBOOT_S), starts a pending boot; it becomes a new boot once
`reboot_confirm_s` of receive time passed without the old boot's stream going on (else it was a late repeat of old
positions, a second link with more latency: they join the old boot), as `.tlog` reading decides
(shared.telemetry.mavlink_clock.boot_segments). The new boot's clock continues the old one's: its anchor is the old
one's plus the step of (receive time - boot time) between the two boots' fastest messages, and the vehicle's own
``SYSTEM_TIME`` of the new boot replaces that when it agrees within `CLOCK_JUMP_S` (it has no latency jitter). Frames
before the reboot is confirmed get no pose.

A wrap of ``time_boot_ms`` (uint32 milliseconds: at 49.7 days up) is no reboot: from within 60 s of 2**32 ms to within
60 s of 0 while the receive time moves on as much (within REBOOT_S), the assembler counts the boot time on past 2**32 ms
(`shared.telemetry.mavlink.BootTimeUnwrap`), so the boot, its clock, gimbal and records go on.

Memory: each boot keeps the positions of its last `KEEP_S` (5 minutes; a frame reads those around its own time).
"""

from __future__ import annotations

import bisect
import collections
import logging
import socket
import threading
import time
from pathlib import Path

from shared.telemetry import MavlinkAssembler, MavlinkByteParser, MavlinkSample, Telemetry
from shared.telemetry.mavlink_clock import CLOCK_JUMP_S, REBOOT_S, REPEAT_WINDOW_S

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


#: Positions older (boot time) than this behind a boot's latest are let go, TRIM_STEP at a time: a frame reads the
#: records around its own time, seconds behind the stream at most; kept, a flight's whole stream grew ~6 MB an hour
#: at 10 Hz (~32 MB at 50 Hz).
KEEP_S = 300.0
TRIM_STEP = 1024


class _Boot:
    """The positions of one boot of the autopilot, sorted by boot time (one per boot time; the last KEEP_S), and its
    clock. first_boot: the earliest boot time it ever held (where the boot begins, after a trim too)."""

    __slots__ = ("times", "samples", "top_boot", "first_boot", "first_rx", "last_rx", "recent_offsets", "anchor",
                 "by_vehicle", "clock_seen")

    def __init__(self, sample: MavlinkSample, rx: float) -> None:
        self.times = [sample.boot_s]
        self.samples = [sample]
        self.top_boot = self.first_boot = sample.boot_s
        self.first_rx = self.last_rx = rx
        # receive time - boot time of the latest messages: their minimum is the fastest path's, latency jitter aside
        self.recent_offsets: collections.deque[float] = collections.deque([rx - sample.boot_s], maxlen=64)
        self.anchor: float | None = None  # UNIX time of the boot's zero on the records' clock (None: not known yet)
        self.by_vehicle = False  # the anchor is the vehicle's SYSTEM_TIME of this boot
        self.clock_seen = False  # a UNIX time (SYSTEM_TIME) of this boot came after the reboot was confirmed

    def add(self, sample: MavlinkSample, rx: float | None) -> None:
        """File a position received at `rx` (None: received late, its receive time says nothing of the clock)."""
        i = bisect.bisect_left(self.times, sample.boot_s)
        if i == len(self.times) or self.times[i] != sample.boot_s:  # repeats count once
            self.times.insert(i, sample.boot_s)
            self.samples.insert(i, sample)
        self.top_boot = max(self.top_boot, sample.boot_s)
        self.first_boot = min(self.first_boot, sample.boot_s)
        if len(self.times) > 2 * TRIM_STEP and self.top_boot - self.times[TRIM_STEP] > KEEP_S:
            del self.times[:TRIM_STEP], self.samples[:TRIM_STEP]
        if rx is not None:
            self.recent_offsets.append(rx - sample.boot_s)
            self.last_rx = max(self.last_rx, rx)

    def on_clock(self, sample: MavlinkSample, rx: float) -> bool:
        """Whether a position received at `rx` is of this boot: its boot time not far behind the boot's latest nor
        further ahead of it than the receive time moved on (a stream replayed faster than real time moves its boot
        time ahead of the receive time step by step, never by more than REBOOT_S at once), or its receive time minus
        boot time near this boot's."""
        ahead = sample.boot_s - self.top_boot
        return (-REBOOT_S <= ahead <= max(rx - self.last_rx, 0.0) + REBOOT_S
                or abs(rx - sample.boot_s - min(self.recent_offsets)) <= REBOOT_S)

    @property
    def fastest_offset(self) -> float:
        return min(self.recent_offsets)


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
    reboot_confirm_s : float
        Receive time after which a boot time that went back is a reboot, not a late repeat (module docstring).

    Raises OSError naming the endpoint when it cannot be bound, ValueError for a bad spec, ImportError (with
    the install hint) without pymavlink.
    """

    def __init__(self, spec: str, *, system_id: int | None = None, height_offset_m: float = 0.0,
                 reboot_confirm_s: float = REPEAT_WINDOW_S) -> None:
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
        self.reboot_confirm_s = float(reboot_confirm_s)
        self._boots: list[_Boot] = []  # in time order; the records' clock is fixed for boot 0 by start()
        self._pending: _Boot | None = None  # a boot time that went back, not yet known to be a reboot
        self._first_rx: tuple[float, float] | None = None  # (wall time, boot s) of the first sample
        self._last_rx = 0.0
        self._anchor: float | None = None
        self._anchored_by_vehicle = False  # boot 0's anchor is the vehicle's SYSTEM_TIME (else this machine's clock)
        self.reboots = 0
        self.late_repeats = 0  # pending boots that turned out to be old positions received late
        self._warned_jumps = self._warned_gimbals = 0  # clock jumps, ignored gimbals already warned about
        self._warned_stale = False  # a gimbal that stopped reporting
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
                                             msg.get_srcComponent(), now)
                with self._cond:
                    self._last_rx = time.monotonic()
                    if sample is not None:
                        self._take(sample, now)
                    self._confirm_reboot(now)
                    self._cond.notify_all()
                    self._warn_news()

    def _take(self, sample: MavlinkSample, rx: float) -> None:
        """File one position under its boot (called with the lock held)."""
        if not self._boots:
            self._boots.append(_Boot(sample, rx))
            self._first_rx = (rx, sample.boot_s)
            return
        current, pending = self._boots[-1], self._pending
        if pending is not None and pending.on_clock(sample, rx) and not current.on_clock(sample, rx):
            pending.add(sample, rx)
        elif current.on_clock(sample, rx):
            current.add(sample, rx)
            if pending is not None:  # the current boot's stream goes on: the pending positions were received late
                if pending.top_boot < current.top_boot:  # repeated late: they join the boot (as a .tlog reads them)
                    for old in pending.samples:
                        current.add(old, None)
                self._pending = None  # (ahead of it: an earlier boot's, dropped)
                self.late_repeats += 1
        else:  # a boot time far off on a receive clock that moved on: perhaps a reboot
            self._pending = _Boot(sample, rx)

    def _confirm_reboot(self, now: float) -> None:
        """Make the pending boot a new boot once the old one's stream has not gone on for reboot_confirm_s."""
        pending = self._pending
        if pending is None or now - pending.first_rx < self.reboot_confirm_s:
            return
        self._pending = None
        previous = self._boots[-1]
        self._boots.append(pending)
        self.reboots += 1
        if self._anchor is not None:
            self._anchor_boots()
        log.warning("MAVLink on %s: the autopilot rebooted (its boot time went from %.1f s back to %.1f s): the new "
                    "boot's positions are placed %s; frames of the %.0f s before the reboot was certain got no pose",
                    self.spec, previous.top_boot, pending.first_boot,
                    "by the vehicle's SYSTEM_TIME" if pending.by_vehicle else
                    "by continuing the receive clock (+- the link's latency jitter)", self.reboot_confirm_s)

    def _anchor_boots(self) -> None:
        """Give every later boot without one its anchor: the previous boot's plus the step of the fastest receive
        time - boot time between them; the vehicle's SYSTEM_TIME of the new boot where it agrees within CLOCK_JUMP_S
        (called with the lock held, once boot 0's anchor is fixed)."""
        jumps = self._assembler.clock_jumps
        for prev, boot in zip(self._boots, self._boots[1:], strict=False):
            if boot.anchor is not None:
                continue
            assert prev.anchor is not None
            boot.anchor = prev.anchor + boot.fastest_offset - prev.fastest_offset
            vehicle = self._assembler.unix_offset_s  # after the UNIX clock's last jump: this boot's if that was
            if (self._anchored_by_vehicle and vehicle is not None and jumps  # at one of its boot times
                    and boot.first_boot - REBOOT_S <= jumps[-1][0] <= boot.top_boot + REBOOT_S
                    and abs(vehicle - boot.anchor) <= CLOCK_JUMP_S):
                boot.anchor = vehicle
                boot.by_vehicle = True

    def _warn_news(self) -> None:
        """Warn once about each new thing the stream shows: a jump of the vehicle's UNIX clock after the anchor was
        fixed, a gimbal ignored, another system sending positions (called with the lock held)."""
        a = self._assembler
        jumps, gimbals, systems = a.clock_jumps, a.gimbals_ignored, a.position_counts
        if self._anchor is not None and len(jumps) > self._warned_jumps:
            latest = self._boots[-1]
            for boot_s, step_s in jumps[self._warned_jumps:]:
                if boot_s < latest.top_boot - REBOOT_S:
                    continue  # at a boot time far behind the latest: a reboot's (its own warning)
                if len(self._boots) > 1 and not latest.clock_seen and boot_s >= latest.first_boot - REBOOT_S:
                    latest.clock_seen = True  # the rebooted autopilot's first UNIX time: the reboot's step, which
                    continue  # the records do not take (they continue the clock); no clock of the vehicle jumped
                log.warning("MAVLink on %s: the vehicle's UNIX clock (SYSTEM_TIME) jumped by %+.3f s at boot %.1f s "
                            "(set from the ground station or GPS); the records keep the clock fixed at start: a "
                            "--telemetry-offset-s read from the new clock is %+.3f s off", self.spec, step_s, boot_s,
                            step_s)
            self._warned_jumps = len(jumps)
        if a.gimbal_stale and not self._warned_stale:
            log.warning("MAVLink on %s: the gimbal stopped reporting (its last reading is older than 3 of its "
                        "intervals, at least 1 s): positions go without its angles (no pitch: no pose unless "
                        "--pitch-deg; heading: the vehicle's yaw) until it reports again", self.spec)
            self._warned_stale = True
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
            while not self._boots:
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
            self._anchored_by_vehicle = self._assembler.unix_offset_s is not None
            if self._assembler.unix_offset_s is not None:
                self._anchor = self._assembler.unix_offset_s  # after the clock's jumps so far
                self._warned_jumps = len(self._assembler.clock_jumps)
            else:
                assert self._first_rx is not None
                wall, boot = self._first_rx
                self._anchor = wall - boot
                log.warning("MAVLink on %s: no SYSTEM_TIME with a UNIX time: times are this machine's clock at the "
                            "first message", self.spec)
            self._boots[0].anchor = self._anchor
            self._anchor_boots()
        return self.records()

    def records(self) -> list[Telemetry]:
        """The records received so far, sorted by time (call `start` first)."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before records()")
        with self._cond:
            boots = [(boot.anchor, list(boot.samples)) for boot in self._boots if boot.anchor is not None]
        out = [s.to_telemetry(anchor, self.height_offset_m) for anchor, samples in boots for s in samples]
        if len(boots) > 1:  # boots follow each other in time: sorted unless a clock estimate overlaps them
            out.sort(key=lambda record: record.t)
        return out

    def records_between(self, t_first: float, t_last: float) -> list[Telemetry]:
        """The records from the last one at or before `t_first` to the first one at or after `t_last` (telemetry
        clock), sorted: what interpolating to times within [t_first, t_last] needs. Its cost does not grow with the
        flight (`records` converts every record so far: 97 ms a call after 30 minutes at 10 Hz, this VM)."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before records_between()")
        with self._cond:
            self._confirm_reboot(time.time())
            pairs: list[tuple[MavlinkSample, float]] = []
            for boot in self._boots:  # each boot's slice around the span, then the slice of those
                if boot.anchor is None:
                    continue
                lo = max(bisect.bisect_right(boot.times, t_first - boot.anchor) - 1, 0)
                hi = bisect.bisect_left(boot.times, t_last - boot.anchor) + 1
                pairs.extend((s, boot.anchor) for s in boot.samples[lo:hi])
        if len(self._boots) > 1:
            pairs.sort(key=lambda pair: pair[0].boot_s + pair[1])
            times = [s.boot_s + anchor for s, anchor in pairs]
            lo = max(bisect.bisect_right(times, t_first) - 1, 0)
            pairs = pairs[lo:bisect.bisect_left(times, t_last) + 1]
        return [s.to_telemetry(anchor, self.height_offset_m) for s, anchor in pairs]

    def wait_for(self, t_first: float, t_last: float, *, timeout_s: float = 5.0, idle_s: float = 1.0) -> None:
        """Wait until the records span [t_first, t_last] (telemetry clock), the stream has been silent for
        `idle_s`, the autopilot seems to have rebooted (a pending boot: no record of the current boot will come), or
        `timeout_s` passed: whichever comes first. Frames then take what is there."""
        if self._anchor is None:
            raise RuntimeError("MavlinkUdpFeed.start() must be called before wait_for()")
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                first, last = self._boots[0], self._boots[-1]
                if last.anchor is None:  # a reboot confirmed before start(): wait on the boots anchored
                    last = next(b for b in reversed(self._boots) if b.anchor is not None)
                assert first.anchor is not None and last.anchor is not None
                if first.first_boot + first.anchor <= t_first and last.times[-1] + last.anchor >= t_last:
                    return
                now = time.monotonic()
                if now >= deadline or now - self._last_rx >= idle_s or self._pending is not None:
                    return
                self._cond.wait(min(deadline - now, idle_s))

    def close(self) -> None:
        """Stop receiving and release the port (idempotent)."""
        self._closed.set()
        self._sock.close()
        self._thread.join(timeout=1.0)

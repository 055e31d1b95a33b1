"""What the server knows about each UAV: liveliness, last message, last state, message rates, drops.

Fed by the Zenoh side (liveliness samples, valid messages, drops), read by ``GET /v1/uavs``. Both
kinds of entries are bounded so a flood of made-up ids cannot exhaust memory or lock real UAVs out:
UAVs that sent data (at most ``max_uavs``; offline ones are forgotten first) and liveliness tokens
(at most ``4 * max_uavs``; tokens of ids that never sent data are forgotten first, oldest first); so are
the forgotten ids kept for persistence (at most ``4 * max_uavs``, oldest dropped: a server without a
database never drains them).
A UAV id heard from more than one Zenoh session at once (two drones configured with the same id,
or an impostor) is reported. Thread-safe.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from fusion_server.metrics import RateWindow
from shared.messages import VERSION, StateMessage

if TYPE_CHECKING:
    from fusion_server.uav_clocks import UavClocks

__all__ = ["SESSION_WINDOW_S", "UavRecord", "UavRegistry", "state_to_dict"]

log = logging.getLogger(__name__)

#: Sessions seen within this many seconds count as "at once" for the two-sessions report.
SESSION_WINDOW_S = 10.0
#: Sessions remembered per UAV.
_MAX_SESSIONS = 8
#: Label of messages that carry no session id (agents older than this check, other clients).
NO_SESSION = "unknown"


def state_to_dict(state: StateMessage) -> dict[str, Any]:
    """A state message as JSON-ready data: its wire fields (DESIGN.md 4), ``v`` (the protocol version) first."""
    return {
        "v": VERSION,
        "uav": state.uav,
        "t": state.t,
        "lat": state.lat,
        "lon": state.lon,
        "height_m": state.height_m,
        "pitch_deg": state.pitch_deg,
        "heading_deg": state.heading_deg,
        "footprint": [[lat, lon] for lat, lon in state.footprint],
        "camera": state.camera.to_dict(),
    }


@dataclass(frozen=True, slots=True)
class UavRecord:
    """A UAV as persisted: id, last_seen and online_since (epoch s), its last state message (or None)."""

    id: str
    last_seen: float
    online_since: float | None
    state: StateMessage | None


@dataclass(slots=True)
class _Uav:
    last_seen: float | None = None  # wall time
    online_since: float | None = None
    state: StateMessage | None = None
    rates: dict[str, RateWindow] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    sessions: OrderedDict[str, float] = field(default_factory=OrderedDict)  # session -> monotonic time
    conflict_reported: bool = False


class UavRegistry:
    """Per-UAV status. max_uavs bounds the UAVs that sent data; 4 * max_uavs the liveliness tokens."""

    def __init__(self, max_uavs: int = 256, clock=time.monotonic, wall=time.time,
                 clocks: UavClocks | None = None) -> None:
        self.max_uavs = max_uavs
        #: the UAVs' clock leads the validator took (fusion_server.uav_clocks): shown in snapshot() when given
        self.clocks = clocks
        self.max_tokens = 4 * max_uavs
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        self._uavs: dict[str, _Uav] = {}
        self._tokens: OrderedDict[str, float] = OrderedDict()  # uav -> online since (wall), oldest first
        self._token_rejected: dict[str, dict[str, int]] = {}  # token-only uav -> its dropped messages by reason
        self._dirty: set[str] = set()  # UAVs changed since the last drain_changes (persistence)
        # ids forgotten since the last drain_changes, oldest first (a dict as an ordered set)
        self._forgotten: dict[str, None] = {}
        self.max_forgotten = 4 * max_uavs
        self.tokens_evicted = 0
        self.conflicts_total = 0

    def _get(self, uav: str) -> _Uav | None:
        entry = self._uavs.get(uav)
        if entry is None:
            if len(self._uavs) >= self.max_uavs:
                self._evict_offline()
                if len(self._uavs) >= self.max_uavs:
                    return None
            entry = self._uavs[uav] = _Uav(online_since=self._tokens.get(uav))
            entry.rejected.update(self._token_rejected.pop(uav, {}))  # what it had dropped while known by token
            self._forgotten.pop(uav, None)
        self._dirty.add(uav)
        return entry

    def _evict_offline(self) -> None:
        # forget the offline UAV seen longest ago, so a fleet that changes over a long mission fits
        offline = [(e.last_seen or 0.0, uav) for uav, e in self._uavs.items() if uav not in self._tokens]
        if offline:
            victim = min(offline)[1]
            del self._uavs[victim]
            self._forget(victim)
            self._dirty.discard(victim)

    def _forget(self, uav: str) -> None:
        # only persistence drains these: without a database (--no-db) nobody does, so keep the newest few
        self._forgotten[uav] = None
        while len(self._forgotten) > self.max_forgotten:
            del self._forgotten[next(iter(self._forgotten))]

    def alive(self, uav: str, online: bool) -> bool:
        """Record a liveliness token appearing (online) or disappearing; False if refused (full)."""
        now = self._wall()
        with self._lock:
            if not online:
                self._tokens.pop(uav, None)
                self._token_rejected.pop(uav, None)
                entry = self._uavs.get(uav)
                if entry is not None:
                    entry.last_seen = now
                    self._dirty.add(uav)
                return True
            if uav not in self._tokens:
                if len(self._tokens) >= self.max_tokens and not self._evict_token():
                    return False
                self._tokens[uav] = now
                entry = self._uavs.get(uav)
                if entry is not None:
                    entry.online_since = now
                    entry.last_seen = now
                    self._dirty.add(uav)
            return True

    def _evict_token(self) -> bool:
        # a token whose id never sent data costs nothing to forget: if it is real, its first message
        # makes it a UAV again (shown offline until its token is seen anew)
        victim = next((uav for uav in self._tokens if uav not in self._uavs), None)
        if victim is None:
            return False
        del self._tokens[victim]
        self._token_rejected.pop(victim, None)
        self.tokens_evicted += 1
        return True

    def message(self, uav: str, kind: str, nbytes: int, state: StateMessage | None = None,
                session: str | None = None) -> bool:
        """Record a valid message (kind "tile", "state" or "tracks") from Zenoh session ``session``
        (None: unknown); False if refused (full)."""
        now_mono = self._clock()
        with self._lock:
            entry = self._get(uav)
            if entry is None:
                return False
            entry.last_seen = self._wall()
            window = entry.rates.get(kind)
            if window is None:
                window = entry.rates[kind] = RateWindow()
            window.add(now_mono, 1, nbytes)
            entry.counts[kind] = entry.counts.get(kind, 0) + 1
            if state is not None:
                entry.state = state
            self._seen_session(uav, entry, session or NO_SESSION, now_mono)
            return True

    def _seen_session(self, uav: str, entry: _Uav, session: str, now: float) -> None:
        sessions = entry.sessions
        if len(sessions) == 1 and session in sessions:  # the common case: one session, no conflict
            sessions[session] = now
            entry.conflict_reported = False
            return
        sessions[session] = now
        sessions.move_to_end(session)
        while len(sessions) > _MAX_SESSIONS:
            sessions.popitem(last=False)
        fresh = [s for s, t in sessions.items() if now - t <= SESSION_WINDOW_S]
        if len(fresh) > 1 and not entry.conflict_reported:
            entry.conflict_reported = True
            self.conflicts_total += 1
            log.warning("UAV id %s is used by %d Zenoh sessions at once (%s): two drones with the same id, "
                        "or an impostor", uav, len(fresh), ", ".join(fresh))
        elif len(fresh) <= 1:
            entry.conflict_reported = False

    def rejected(self, uav: str, reason: str) -> None:
        """Count a dropped message of a UAV that is known: by its messages, or by its liveliness token alone (a UAV
        online whose every message is dropped, its clock minutes ahead, showed no rejection at all). A token-only
        UAV's counts are kept apart (bounded by the tokens, gone with its token, never an entry that counts against
        max_uavs or is persisted); other ids are not counted (a forged id costs nothing)."""
        with self._lock:
            entry = self._uavs.get(uav)
            counts = entry.rejected if entry is not None else (
                self._token_rejected.setdefault(uav, {}) if uav in self._tokens else None)
            if counts is not None:
                counts[reason] = counts.get(reason, 0) + 1

    def drain_changes(self) -> tuple[list[UavRecord], list[str]]:
        """UAVs changed since the last call (for persistence) and the ids forgotten since."""
        with self._lock:
            records = [UavRecord(uav, entry.last_seen or self._wall(), entry.online_since, entry.state)
                       for uav in sorted(self._dirty) if (entry := self._uavs.get(uav)) is not None]
            forgotten = sorted(self._forgotten)
            self._dirty.clear()
            self._forgotten.clear()
        return records, forgotten

    def restore(self, records: list[UavRecord], keep_s: float) -> int:
        """Take the UAVs a previous run saved (offline, with their last state) that were seen within
        ``keep_s``; returns how many."""
        cutoff = self._wall() - keep_s
        count = 0
        with self._lock:
            for record in records:
                if record.last_seen < cutoff or record.id in self._uavs or len(self._uavs) >= self.max_uavs:
                    continue
                self._uavs[record.id] = _Uav(last_seen=record.last_seen, online_since=record.online_since,
                                             state=record.state)
                count += 1
        return count

    def forget_offline(self, keep_s: float) -> list[str]:
        """Forget UAVs offline and not seen for ``keep_s`` seconds; returns their ids."""
        cutoff = self._wall() - keep_s
        with self._lock:
            old = [uav for uav, e in self._uavs.items()
                   if uav not in self._tokens and (e.last_seen or 0.0) < cutoff]
            for uav in old:
                del self._uavs[uav]
                self._dirty.discard(uav)
                self._forget(uav)
        return old

    def online(self) -> list[str]:
        """Ids of the UAVs whose liveliness token is present."""
        with self._lock:
            return sorted(self._tokens)

    def conflicts(self) -> list[str]:
        """Ids heard from more than one Zenoh session within SESSION_WINDOW_S."""
        now = self._clock()
        with self._lock:
            return sorted(uav for uav, entry in self._uavs.items()
                          if sum(now - t <= SESSION_WINDOW_S for t in entry.sessions.values()) > 1)

    def snapshot(self, tile_counts: dict[str, int] | None = None) -> list[dict[str, Any]]:
        """``GET /v1/uavs`` rows, sorted by id: the UAVs that sent data and the ids with only a token.

        Each: id, online, last_seen (epoch seconds or None), online_since, state (last state message
        or None), rates ({kind: messages/s} over 10 s), bytes_per_s, messages ({kind: count}),
        rejected ({reason: count} of its dropped messages), sessions (Zenoh sessions it was heard
        from within SESSION_WINDOW_S), conflict (more than one of them), tiles (fresh tiles it
        covers, when tile_counts is given). With the UAVs' clocks: clock_lead_s (how far its clock runs ahead,
        the largest lead taken among its kinds of message, 0.0 when none; its messages are moved back by it)
        and, while it holds one, clock_leads_s ({kind: s}).
        """
        now = self._clock()
        leads = self.clocks.leads() if self.clocks is not None else None
        rows = []
        with self._lock:
            for uav in sorted(set(self._uavs) | set(self._tokens)):
                entry = self._uavs.get(uav) or _Uav(online_since=self._tokens.get(uav))
                rates = {kind: window.rates(now) for kind, window in entry.rates.items()}
                sessions = sorted(s for s, t in entry.sessions.items() if now - t <= SESSION_WINDOW_S)
                row = {
                    "id": uav,
                    "online": uav in self._tokens,
                    "last_seen": entry.last_seen if uav in self._uavs else self._tokens.get(uav),
                    "online_since": entry.online_since,
                    "state": state_to_dict(entry.state) if entry.state is not None else None,
                    "rates": {kind: round(r[0], 3) for kind, r in rates.items()},
                    "bytes_per_s": round(sum(r[1] for r in rates.values()), 1),
                    "messages": dict(entry.counts),
                    "rejected": dict(entry.rejected) if uav in self._uavs else dict(self._token_rejected.get(uav, {})),
                    "sessions": sessions,
                    "conflict": len(sessions) > 1,
                }
                if tile_counts is not None:
                    row["tiles"] = tile_counts.get(uav, 0)
                if leads is not None:
                    found = leads.get(uav, {})
                    row["clock_lead_s"] = round(max(found.values(), default=0.0), 3)
                    if found:
                        row["clock_leads_s"] = {kind: round(lead, 3) for kind, lead in sorted(found.items())}
                rows.append(row)
        return rows

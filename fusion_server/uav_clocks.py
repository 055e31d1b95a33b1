"""How far each UAV's clock runs ahead of the fusion server's: a companion computer without NTP, or one that stamps
local time as UTC east of Greenwich, is minutes to hours ahead, and every message it sends would look forged.

The server rejects a message whose t is more than the clock skew ahead of its own clock (``t_in_future``). Per UAV
and kind of message ("tile", "state", "tracks"), when such messages keep coming (shared.clock_lead: at least
CONFIRM_MESSAGES over CONFIRM_S, none of that kind on time in between) that UAV's clock is taken to lead by the
smallest lead among them, and from then on its messages that need it are moved back by the lead, so the joint map,
the tracks, persistence and ``/v1/*`` see them on the server's clock. The mirror of agent.joint_clock, per UAV:
one UAV's lead never moves another's, a forged stamp or a burst moves nothing, an absurd t (1e300) stays rejected.

A message on time (t at most the skew ahead of the server clock) is taken as it is, never moved, whatever lead is
held: a UAV restarted with its clock set right is fused, in order, from its first message. It clears the pending
evidence of its kind, and is evidence that the lead is over; so is a message in the past by more than the skew
against the lead. When those keep coming (the same rule) the lead is dropped, or set to theirs when they still
lead by more than the skew (a clock hours ahead put back to minutes ahead). One message on time, such as a replayed
old one, drops nothing: a single replay cannot make a UAV whose clock really is ahead be rejected again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from shared.clock_lead import LeadEvidence, plausible_lead

__all__ = ["MAX_CLOCKS", "UavClocks"]

log = logging.getLogger(__name__)

#: UAVs whose clock is followed (those that sent a message ahead of the server clock): beyond, the one heard from
#: longest ago is forgotten, those without an adopted lead first (a flood of made-up ids costs a real UAV nothing).
MAX_CLOCKS = 1024
#: UAV ids remembered for the "warned once" of the first adoption.
_MAX_WARNED = 4096


@dataclass(slots=True)
class _KindClock:
    lead_s: float = 0.0  # adopted lead of this UAV's messages of this kind (0: none)
    ahead: LeadEvidence = field(default_factory=LeadEvidence)  # messages beyond lead + skew since the last not
    back: LeadEvidence = field(default_factory=LeadEvidence)  # messages behind lead - skew since the last not

    def idle(self) -> bool:
        return self.lead_s == 0.0 and not self.ahead and not self.back


class UavClocks:
    """Per UAV and kind, the lead of its clock over this server's, taken on evidence. Thread-safe.

    skew_s: how far a message's t may be ahead of the server clock (plus the lead); wall: epoch seconds;
    monotonic: receive times of the evidence, seconds. max_clocks: UAVs followed at once.
    """

    def __init__(self, skew_s: float, *, wall: Callable[[], float] = time.time,
                 monotonic: Callable[[], float] = time.monotonic, max_clocks: int = MAX_CLOCKS) -> None:
        self.skew_s = float(skew_s)
        self.max_clocks = int(max_clocks)
        self._wall = wall
        self._monotonic = monotonic
        self._lock = threading.Lock()
        # uav -> kind -> its clock, least recently heard first; only UAVs that sent a message ahead
        self._clocks: OrderedDict[str, dict[str, _KindClock]] = OrderedDict()
        self._warned: set[str] = set()

    def lead_for(self, uav: str, kind: str, t: float, wall: float | None = None) -> float | None:
        """The seconds to take off ``t`` of a message of ``uav`` and ``kind`` that is otherwise valid, or None when
        it is too far ahead (rejected, ``t_in_future``; it counts as evidence unless absurd).

        0.0 for a message on time (t at most ``skew_s`` ahead of ``wall``, the server clock now, read when None):
        such a message is never moved. A return above 0 is the adopted lead, t minus it is at most ``skew_s``
        ahead of the server clock. Every message of a UAV counts, so call it once per message.
        """
        lead = t - (self._wall() if wall is None else wall)
        skew = self.skew_s
        if lead <= skew and uav not in self._clocks:
            return 0.0  # the common case: on time, and the UAV never ran ahead
        with self._lock:
            kinds = self._clocks.get(uav)
            if kinds is None:
                if not plausible_lead(lead):
                    return None  # an absurd t: no evidence, nothing to follow
                kinds = self._follow(uav)
            else:
                self._clocks.move_to_end(uav)
            clock = kinds.get(kind)
            if clock is None:
                clock = kinds[kind] = _KindClock()
            before = clock.lead_s
            shift = self._judge(clock, lead, skew)
            after = clock.lead_s
            if clock.idle():
                del kinds[kind]
                if not kinds:
                    del self._clocks[uav]
            first = after != before and after > 0.0 and uav not in self._warned
            if first:
                if len(self._warned) >= _MAX_WARNED:
                    self._warned.clear()
                self._warned.add(uav)
        if after != before:
            self._report(uav, kind, before, after, first)
        return shift

    def _judge(self, clock: _KindClock, lead: float, skew: float) -> float | None:
        """Update one kind's clock for a message leading by ``lead`` (s); the shift or None (see lead_for)."""
        now = self._monotonic()
        if lead <= skew:  # on time: taken as it is; what was ahead is not this clock's
            clock.ahead.clear()
            if clock.lead_s > 0.0 and clock.back.add(now, lead) is not None:
                clock.lead_s = 0.0  # its run holds this message: its smallest lead is on time too
            return 0.0
        if lead <= clock.lead_s + skew:  # within the adopted lead
            clock.ahead.clear()
            if lead >= clock.lead_s - skew:
                clock.back.clear()
            elif (back := clock.back.add(now, lead)) is not None:
                clock.lead_s = back if back > skew else 0.0  # the smaller lead, or none when it is on time
        else:
            if not plausible_lead(lead):
                return None  # an absurd t says nothing of the UAV's clock
            clock.back.clear()
            adopted = clock.ahead.add(now, lead)
            if adopted is None:
                return None
            clock.lead_s = adopted
        # the lead taken is the smallest of its run: a message further ahead than it (and the skew) stays out
        return clock.lead_s if lead <= clock.lead_s + skew else None

    def _follow(self, uav: str) -> dict[str, _KindClock]:
        """A new entry for ``uav``, forgetting one when full (held with the lock)."""
        clocks = self._clocks
        if len(clocks) >= self.max_clocks:
            victim = next((other for other, kinds in clocks.items()
                           if all(clock.lead_s == 0.0 for clock in kinds.values())), None)
            del clocks[victim if victim is not None else next(iter(clocks))]
        kinds: dict[str, _KindClock] = {}
        clocks[uav] = kinds
        return kinds

    def _report(self, uav: str, kind: str, before: float, after: float, first: bool) -> None:
        if first:
            log.warning("UAV %s: its %s messages run %.0f s ahead of this server's clock (no NTP? local time "
                        "stamped as UTC?): taken as its clock's lead, its messages are moved back by it; set its "
                        "clock", uav, kind, after)
        elif after == 0.0:
            log.info("UAV %s: its %s messages are on time again (their clock lead of %.0f s is dropped)", uav, kind,
                     before)
        else:
            log.info("UAV %s: its %s messages now run %.0f s ahead of this server's clock (were %.0f s)", uav, kind,
                     after, before)

    def leads(self) -> dict[str, dict[str, float]]:
        """The adopted leads (s), ``{uav: {kind: lead}}``, of the UAVs and kinds that hold one."""
        with self._lock:
            return {uav: found for uav, kinds in self._clocks.items()
                    if (found := {kind: clock.lead_s for kind, clock in kinds.items() if clock.lead_s > 0.0})}

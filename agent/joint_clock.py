"""How far the joint messages' clock leads this machine's: a companion computer without a real-time clock
or NTP can boot minutes to years behind, and every joint message would look like it came from the future.

The joint side's times are the fusion server's wall clock (joint tracks, emptied tiles) and the UAVs'
source clocks (a tile carries its newest contributor's t), which the server keeps within its own clock
skew. A message ahead of this clock by more than the skew is rejected (``t_in_future``: a corrupt or
forged t). When such messages of one kind (tiles, tracks) keep coming, at least CONFIRM_MESSAGES over CONFIRM_S
of receive time, all of them ahead and none of that kind on time in between, this clock is taken to be behind
by the smallest lead among them, which from then on is added to this clock before the skew check (warned once per
step, and in the agent's summary). A message on time clears its kind's evidence: forged stamps among the server's
own messages, or tiles of a UAV whose clock runs ahead, never move it, while the server's tracks all ahead still
do when the tiles carry a replayed UAV's past clock. One message ahead, or a few within a moment, never moves it;
the lead only grows (a clock set right later just leaves the check looser by the lead), and is bounded by
MAX_LEAD_S so an absurd t (1e300) stays rejected. The rule of evidence is shared.clock_lead's, which the
fusion server applies per UAV the other way round (fusion_server.uav_clocks: a UAV's clock ahead of the server's).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from shared.clock_lead import CONFIRM_MESSAGES, CONFIRM_S, EVIDENCE_S, MAX_LEAD_S, LeadEvidence, plausible_lead

__all__ = ["CONFIRM_MESSAGES", "CONFIRM_S", "EVIDENCE_S", "MAX_CLOCK_SKEW_S", "MAX_LEAD_S", "JointClock"]

log = logging.getLogger(__name__)

#: A joint message whose t is further ahead of this clock (plus the lead) is dropped ("t_in_future"), seconds.
MAX_CLOCK_SKEW_S = 30.0


class JointClock:
    """Thread-safe: ``accepts(t)`` from the Zenoh callbacks. ``lead_s``: the lead adopted (0 until then)."""

    def __init__(self, skew_s: float, *, wall: Callable[[], float] = time.time,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.skew_s = float(skew_s)
        self.lead_s = 0.0
        self._wall = wall
        self._monotonic = monotonic
        self._lock = threading.Lock()
        # per kind of message: the rejected ones since the last on time (shared.clock_lead)
        self._ahead: dict[str, LeadEvidence] = {}

    def accepts(self, t: float, kind: str = "") -> bool:
        """Whether a joint message of `kind` ("tiles", "tracks") stamped t is not ahead of this clock (plus the lead
        adopted) by more than the skew; a rejected one counts as evidence that this clock is behind, one on time
        clears its kind's."""
        lead = t - self._wall()
        with self._lock:
            ahead = self._ahead.setdefault(kind, LeadEvidence())
            if lead <= self.lead_s + self.skew_s:
                ahead.clear()  # on time: what was ahead is not this clock's lag (forged, or a UAV's clock)
                return True
            if not plausible_lead(lead):
                return False
            adopted = ahead.add(self._monotonic(), lead)
            if adopted is None:
                return False
            self.lead_s = adopted  # every lead of the run is beyond lead_s + skew: the lead only grows
            for evidence in self._ahead.values():
                evidence.clear()
        log.warning("the joint messages run %.0f s ahead of this machine's clock (no RTC or NTP?): taken as this "
                    "clock's lead from now on; set this machine's clock", self.lead_s)
        # the lead taken is the smallest of its run: the message that confirmed it may still be too far ahead of it
        return lead <= self.lead_s + self.skew_s

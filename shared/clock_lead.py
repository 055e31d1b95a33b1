"""Evidence that another machine's clock leads this one's: the rule the agent (agent.joint_clock) and the fusion
server (fusion_server.uav_clocks) share before they take a clock lead, so a forged stamp or a burst never moves one.

A lead is taken only when messages keep pointing at it: at least CONFIRM_MESSAGES over at least CONFIRM_S of receive
time, all within EVIDENCE_S, none in between saying otherwise (the caller clears the run then). The lead taken is the
smallest of the run (the clock's offset less the longest latency seen), so every message of the run still passes.
A lead beyond MAX_LEAD_S (~100 years) or not finite is no clock's: it is never evidence (an absurd t stays rejected).
"""

from __future__ import annotations

import math
from collections import deque

__all__ = ["CONFIRM_MESSAGES", "CONFIRM_S", "EVIDENCE_S", "MAX_LEAD_S", "LeadEvidence", "plausible_lead"]

#: Messages pointing at a lead needed before it is taken.
CONFIRM_MESSAGES = 5
#: ...over at least this much receive time (s), within the last EVIDENCE_S.
CONFIRM_S = 2.0
EVIDENCE_S = 10.0
#: A lead beyond this (s, ~100 years) is no clock's: such messages stay rejected.
MAX_LEAD_S = 3.2e9
#: Messages received within this long of the first of a group are held as one entry (count, smallest lead): the
#: evidence of a UAV that publishes hundreds of tiles a cycle stays at most EVIDENCE_S / _MERGE_S entries.
_MERGE_S = 0.05


def plausible_lead(lead_s: float) -> bool:
    """Whether a lead (s) may be a clock's: finite and at most MAX_LEAD_S (negative leads are plausible)."""
    return math.isfinite(lead_s) and lead_s <= MAX_LEAD_S


class LeadEvidence:
    """One run of messages pointing at a lead, as ``[first receive time, count, smallest lead]`` groups.

    Not thread-safe: the owner holds its lock. Receive times are monotonic seconds.
    """

    __slots__ = ("_count", "_groups")

    def __init__(self) -> None:
        self._groups: deque[list[float]] = deque()
        self._count = 0

    def __len__(self) -> int:
        """Messages in the run (within EVIDENCE_S of the last one added)."""
        return self._count

    def clear(self) -> None:
        """Forget the run (a message said otherwise)."""
        self._groups.clear()
        self._count = 0

    def add(self, now_s: float, lead_s: float) -> float | None:
        """Add a message received at ``now_s`` that points at ``lead_s`` (s, plausible: see plausible_lead).

        Returns the lead confirmed, the smallest of the run, once it holds CONFIRM_MESSAGES over CONFIRM_S
        (the run is cleared then); None while the evidence is short.
        """
        groups = self._groups
        if groups and now_s - groups[-1][0] < _MERGE_S:
            last = groups[-1]
            last[1] += 1.0
            last[2] = min(last[2], lead_s)
        else:
            groups.append([now_s, 1.0, lead_s])
        self._count += 1
        while groups and now_s - groups[0][0] > EVIDENCE_S:
            self._count -= int(groups.popleft()[1])
        if self._count < CONFIRM_MESSAGES or now_s - groups[0][0] < CONFIRM_S:
            return None
        confirmed = min(group[2] for group in groups)
        self.clear()
        return confirmed

"""A wall clock and a monotonic clock that tests step by hand (the clock-lead tests of the agent and the server)."""

from __future__ import annotations


class Clocks:
    """wall (UNIX seconds) and mono (monotonic seconds), moved together by step(dt)."""

    def __init__(self, wall: float = 1.7e9) -> None:
        self.wall = wall
        self.mono = 100.0

    def step(self, dt: float) -> None:
        self.wall += dt
        self.mono += dt

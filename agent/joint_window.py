"""Which joint tiles, tracks and other UAVs' states reach the agent: those of its window only.

A fleet's joint map is the sum of every UAV's window; a UAV needs the tiles of its own. Subscribing to
``{prefix}/joint/tiles/**`` would bring every joint tile of the fleet over the UAV's radio link
(~70 kB/s per UAV at defaults, so 14 MB/s in a fleet of 200). With one subscriber per window tile,
``{prefix}/joint/tiles/*/{z}/{x}/{y}`` (the DESIGN.md key space as it is: all classes of one tile),
Zenoh routes only those (a router or peer sends a sample only to sessions whose subscriptions match).
The global tracks likewise: instead of ``{prefix}/joint/tracks`` (every track of the fleet: 425 kB
for 4,000 tracks, at 5 Hz) the regions the window touches, ``{prefix}/region/tracks/{z}/{x}/{y}``
(shared.keys.track_region, published by the fusion server beside the global message), and the
other UAVs' states (for their footprints) as the fusion server forwards them to those regions,
``{prefix}/region/states/{z}/{x}/{y}/*``, instead of ``{prefix}/uav/*/state`` (every UAV's).
Until the first window is known, and with ``set(None)``, it subscribes to every joint tile, to the
global tracks and to every state.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from shared.keys import KeySpace, track_region

__all__ = ["JointWindowSubscriptions", "window_tiles"]

log = logging.getLogger(__name__)


def window_tiles(origin: tuple[int, int], size_cells: int, n: int, margin: int = 1,
                 tiles_per_side: int | None = None) -> set[tuple[int, int]]:
    """(x, y) of the tiles a window of ``size_cells`` cells at global cell ``origin`` (north-west)
    overlaps, plus ``margin`` tiles around it (so a tile is subscribed before the window reaches it).
    With ``tiles_per_side`` (the grid's 2**z) x wraps at the antimeridian and y stops at the map's edge, as
    `shared.tiles.CellWindow` does: a window at the world's east edge asked for tile 2**z, which no key holds,
    and the agent stopped (without it, x below 0 is cut and x past the edge kept, as before)."""
    if size_cells <= 0:
        return set()
    gx0, gy0 = origin
    tx0, ty0 = gx0 // n - margin, gy0 // n - margin
    tx1, ty1 = (gx0 + size_cells - 1) // n + margin, (gy0 + size_cells - 1) // n + margin
    if tiles_per_side is None:
        return {(x, y) for y in range(max(ty0, 0), ty1 + 1) for x in range(max(tx0, 0), tx1 + 1)}
    return {(x % tiles_per_side, y) for y in range(max(ty0, 0), min(ty1, tiles_per_side - 1) + 1)
            for x in range(tx0, tx1 + 1)}


class JointWindowSubscriptions:
    """The joint-tile subscribers of one session: every tile, or one per tile of a window.

    session: an open Zenoh session; callback: the sample handler (must not raise); z: the grid's zoom.
    Use from one thread (the agent's loop).
    """

    def __init__(self, session: zenoh.Session, keys: KeySpace, z: int, callback: Callable[[zenoh.Sample], Any]) -> None:
        self.session = session
        self.z = int(z)
        self.callback = callback
        self.keys = keys
        self._base = keys.joint_tiles_all()[: -len("*/**")]  # "{prefix}/joint/tiles/"
        self._all: Any = session.declare_subscriber(keys.joint_tiles_all(), callback)
        self._all_tracks: Any = session.declare_subscriber(keys.joint_tracks(), callback)
        self._all_states: Any = session.declare_subscriber(keys.uav_state("*"), callback)
        self._tiles: dict[tuple[int, int], Any] = {}
        self._regions: dict[tuple[int, int, int], tuple[Any, Any]] = {}  # tracks and states subscribers

    @property
    def tiles(self) -> set[tuple[int, int]] | None:
        """The (x, y) subscribed to, or None while every joint tile is."""
        return None if self._all is not None else set(self._tiles)

    @property
    def regions(self) -> set[tuple[int, int, int]] | None:
        """The track regions (z, x, y) subscribed to, or None while the global tracks are."""
        return None if self._all_tracks is not None else set(self._regions)

    def selectors(self) -> list[str]:
        """What the window receives, as query selectors: its tiles' and its track regions' keys
        (empty while every joint tile is subscribed to)."""
        return ([self.key(x, y) for x, y in sorted(self._tiles)]
                + [self.keys.region_tracks(*region) for region in sorted(self._regions)])

    def key(self, x: int, y: int) -> str:
        """The selector of one tile's joint tiles, all classes."""
        return f"{self._base}*/{self.z}/{int(x)}/{int(y)}"

    def set(self, tiles: Iterable[tuple[int, int]] | None,
            track_tiles: Iterable[tuple[int, int]] | None = None) -> None:
        """Subscribe to the joint tiles of ``tiles`` only and to the track regions of ``track_tiles``
        (default: of ``tiles``); None: to every joint tile and the global tracks. New subscribers are
        declared before the old ones and the all-tiles ones are undeclared, so nothing in both the
        old and the new window is missed."""
        if tiles is None:
            if self._all is None:
                self._all = self.session.declare_subscriber(f"{self._base}*/**", self.callback)
            if self._all_tracks is None:
                self._all_tracks = self.session.declare_subscriber(self.keys.joint_tracks(), self.callback)
            if self._all_states is None:
                self._all_states = self.session.declare_subscriber(self.keys.uav_state("*"), self.callback)
            for subscribers in (self._tiles, self._regions):
                self._undeclare(subscribers, list(subscribers))  # type: ignore[arg-type]
            return
        wanted = set(tiles)
        regions = {track_region(self.z, x, y) for x, y in (wanted if track_tiles is None else track_tiles)}
        for xy in wanted - self._tiles.keys():
            self._tiles[xy] = self.session.declare_subscriber(self.key(*xy), self.callback)
        for region in regions - self._regions.keys():
            self._regions[region] = (
                self.session.declare_subscriber(self.keys.region_tracks(*region), self.callback),
                self.session.declare_subscriber(self.keys.region_states(*region), self.callback))
        self._undeclare(self._tiles, [xy for xy in self._tiles if xy not in wanted])
        self._undeclare(self._regions, [r for r in self._regions if r not in regions])
        for name in ("_all", "_all_tracks", "_all_states"):
            if getattr(self, name) is not None:
                _undeclare(getattr(self, name))
                setattr(self, name, None)

    @staticmethod
    def _undeclare(subscribers: dict[Any, Any], keys: list[Any]) -> None:
        for key in keys:
            entry = subscribers.pop(key)
            for subscriber in entry if isinstance(entry, tuple) else (entry,):
                _undeclare(subscriber)

    def clear(self) -> None:
        """Forget the subscribers (they go with the session when it closes)."""
        self._all = self._all_tracks = self._all_states = None
        self._tiles.clear()
        self._regions.clear()


def _undeclare(subscriber: Any) -> None:
    try:
        subscriber.undeclare()
    except zenoh.ZError as exc:  # the session is closing
        log.debug("undeclaring a joint-tile subscriber: %s", exc)

"""A fake agent for the tests: its own Zenoh session publishing real encoded tiles, state and tracks."""

from __future__ import annotations

import json
import time

import numpy as np
import zenoh

from shared.keys import KeySpace
from shared.messages import CameraInfo, StateMessage, TrackItem, TracksMessage, encode_state, encode_tracks
from shared.tilecodec import TileMessage, encode_tile
from shared.tiles import TileGrid

GRID = TileGrid()
KEYS = KeySpace()
#: A place (Lake Constance) and its z18 tile.
LAT, LON = 47.67, 9.27
TILE_X, TILE_Y = (int(v) for v in GRID.tile_of(LAT, LON))


def client_config(endpoint: str, *, mode: str = "peer", user: str | None = None,
                  password: str | None = None, extra: dict | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/timeout_ms", "2000")
    conf.insert_json5("connect/exit_on_failure", "true")
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    for key, value in (extra or {}).items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class FakeAgent:
    """One UAV: a Zenoh session, a liveliness token, and helpers that publish valid messages."""

    def __init__(self, uav: str, endpoint: str | None, *, alive: bool = True,
                 conf: zenoh.Config | None = None, **config) -> None:
        """Connect to ``endpoint`` with `client_config` options, or open ``conf`` as it is (endpoint None)."""
        self.uav = uav
        self.session = zenoh.open(conf if conf is not None else client_config(endpoint, **config))
        self.token = self.session.liveliness().declare_token(KEYS.uav_alive(uav)) if alive else None
        self.seq = 0

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def tile(self, values: np.ndarray, x: int = TILE_X, y: int = TILE_Y, cls: str = "person",
             t: float | None = None) -> None:
        self.seq += 1
        msg = TileMessage(uav=self.uav, cls=cls, z=GRID.z, x=x, y=y, n=GRID.n,
                          t=time.time() if t is None else t, seq=self.seq, values=values)
        self.put(KEYS.uav_tile(self.uav, cls, GRID.z, x, y), encode_tile(msg))

    def state(self, lat: float = LAT, lon: float = LON, footprint=None) -> None:
        camera = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
        if footprint is None:
            footprint = ((lat, lon), (lat + 1e-4, lon), (lat, lon + 1e-4))
        msg = StateMessage(uav=self.uav, t=time.time(), lat=lat, lon=lon, height_m=40.0, pitch_deg=60.0,
                           heading_deg=90.0, footprint=tuple((float(a), float(b)) for a, b in footprint),
                           camera=camera)
        self.put(KEYS.uav_state(self.uav), encode_state(msg))

    def tracks(self, items: list[tuple[int, str, float, float]], score: float = 0.9) -> None:
        msg = TracksMessage(uav=self.uav, t=time.time(), tracks=tuple(
            TrackItem(id=i, cls=cls, lat=lat, lon=lon, score=score, vel_en=(0.0, 0.0)) for i, cls, lat, lon in items
        ))
        self.put(KEYS.uav_tracks(self.uav), encode_tracks(msg))

    def close(self) -> None:
        if self.session is not None and not self.session.is_closed():
            self.session.close()


def blob(row: int, col: int, value: float = 0.8, sigma: float = 3.0, n: int = GRID.n) -> np.ndarray:
    """(n, n) float32 Gaussian bump of peak ``value`` at (row, col), cut below 0.05."""
    r = np.arange(n)[:, None] - row
    c = np.arange(n)[None, :] - col
    out = value * np.exp(-0.5 * (r**2 + c**2) / sigma**2)
    out[out < 0.05] = 0.0
    return out.astype(np.float32)

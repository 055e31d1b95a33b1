"""Settings of the fusion server process, validated once at start-up, and its Zenoh configuration.

`FusionSettings` holds every tunable of `uavmm fusion`; :func:`zenoh_config` turns the Zenoh options
(``--mode/--connect/--listen/--config/--cfg``, as in zenoh-python's examples) into a ``zenoh.Config``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from fusion_server.rules import FUSION_RULES
from shared.keys import DEFAULT_PREFIX, KeySpace
from shared.tiles import TileGrid

__all__ = [
    "ZENOH_MODES",
    "FusionSettings",
    "ZenohOptions",
    "default_db_path",
    "zenoh_config",
]

ZENOH_MODES = ("peer", "router", "client")


def default_db_path() -> Path:
    """Default SQLite file: ``$XDG_DATA_HOME/uavmm/fusion.sqlite`` (``~/.local/share/uavmm/...``)."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "uavmm" / "fusion.sqlite"


def _positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class ZenohOptions:
    """The Zenoh options every uavmm process accepts.

    mode: "peer", "router" or "client", or None to keep the config file's (Zenoh's default: peer).
    connect, listen: endpoints such as ``tcp/127.0.0.1:7447``; None keeps the config file's.
    config_file: a Zenoh JSON5 config file (usrpwd, TLS, ACL, ... pass through from it).
    multicast_scouting: False disables multicast scouting, None keeps the file's/Zenoh's default.
    cfg: extra ``KEY:VALUE`` overrides (KEY a config path, VALUE JSON5), applied last.
    """

    mode: str | None = None
    connect: tuple[str, ...] | None = None
    listen: tuple[str, ...] | None = None
    config_file: Path | None = None
    multicast_scouting: bool | None = None
    cfg: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in ZENOH_MODES:
            raise ValueError(f"zenoh mode must be one of {', '.join(ZENOH_MODES)}, got {self.mode!r}")
        for item in self.cfg:
            if ":" not in item:
                raise ValueError(f"--cfg expects KEY:VALUE, got {item!r}")


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config`` from the file (if any) with the options' overrides applied.

    Raises ValueError for an unreadable config file or a bad ``--cfg`` value.
    """
    try:
        conf = zenoh.Config.from_file(str(options.config_file)) if options.config_file else zenoh.Config()
    except zenoh.ZError as exc:
        raise ValueError(f"cannot read zenoh config {options.config_file}: {exc}") from None
    if options.mode is not None:
        conf.insert_json5("mode", json.dumps(options.mode))
    if options.connect is not None:
        conf.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
    if options.listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
    if options.multicast_scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(options.multicast_scouting))
    for item in options.cfg:
        key, value = item.split(":", 1)
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:
            raise ValueError(f"--cfg {item!r}: {exc}") from None
    return conf


@dataclass(frozen=True, slots=True)
class FusionSettings:
    """Everything `uavmm fusion` can be told; invalid values raise ValueError naming the field.

    Times in seconds, rates in Hz, distances in metres. ``db_path`` None disables persistence.
    ``http_port`` 0 picks a free port (the chosen one is reported by the server).
    """

    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    http_host: str = "127.0.0.1"
    http_port: int = 8000
    db_path: Path | None = field(default_factory=default_db_path)
    prefix: str = DEFAULT_PREFIX
    ttl_s: float = 2.0
    fusion_rule: str = "mean"
    grid_z: int = 18
    grid_n: int = 256
    joint_max_hz: float = 5.0
    tracks_max_hz: float = 5.0
    track_gate_m: float = 10.0
    track_hold_s: float = 10.0
    track_history_len: int = 600
    track_history_interval_s: float = 1.0
    max_uavs: int = 256
    max_uav_tiles: int = 20_000
    restore_grace_s: float | None = None
    map_max_cells: int = 512 * 512
    persist_interval_s: float = 0.5

    def __post_init__(self) -> None:
        if self.fusion_rule not in FUSION_RULES:
            raise ValueError(f"fusion_rule must be one of {', '.join(FUSION_RULES)}, got {self.fusion_rule!r}")
        KeySpace(self.prefix)  # raises ValueError naming the bad chunk
        TileGrid(self.grid_z, self.grid_n)
        if not isinstance(self.http_port, int) or not 0 <= self.http_port <= 65535:
            raise ValueError(f"http_port must be in 0..65535, got {self.http_port!r}")
        for name in ("ttl_s", "joint_max_hz", "tracks_max_hz", "track_gate_m", "track_hold_s",
                     "track_history_interval_s", "persist_interval_s"):
            _positive(name, getattr(self, name))
        if self.restore_grace_s is not None:
            _positive("restore_grace_s", self.restore_grace_s)
        for name in ("track_history_len", "max_uavs", "max_uav_tiles", "map_max_cells"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")

    @property
    def grid(self) -> TileGrid:
        """The shared tile grid the server accepts (tiles of another z or n are rejected)."""
        return TileGrid(self.grid_z, self.grid_n)

    @property
    def keys(self) -> KeySpace:
        """The key space under ``prefix``."""
        return KeySpace(self.prefix)

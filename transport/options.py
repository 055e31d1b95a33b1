"""The Zenoh options every uavmm process accepts (``--mode/--connect/--listen/--config/--cfg``).

One value object and one function turning it into a ``zenoh.Config``, shared by the agent and the fusion
server so an agent on a drone needs neither the server package nor its dependencies. Opens no session.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

__all__ = ["ZENOH_MODES", "ZenohOptions", "zenoh_config"]

ZENOH_MODES = ("peer", "router", "client")


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
    import zenoh  # only here: the value object above is usable (and testable) without zenoh

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

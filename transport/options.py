"""The Zenoh options every uavmm process accepts (``--mode/--connect/--listen/--config/--cfg``).

One value object and one function turning it into a ``zenoh.Config``, shared by the agent and the fusion
server so an agent on a drone needs neither the server package nor its dependencies. Opens no session.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zenoh

__all__ = ["ZENOH_MODES", "ZenohOptions", "config_file_value", "zenoh_config"]

ZENOH_MODES = ("peer", "router", "client")


#: A Zenoh endpoint's shape: a protocol, a slash, an address (tcp/HOST:PORT, udp/..., tls/..., unixsock-stream/PATH).
_ENDPOINT = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*/\S+$")


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


def _refuse_non_object(path: Path) -> None:
    """ValueError for a config file that is plain JSON but no object (a list: Zenoh took it silently as an empty
    config, the contract audit of 1 Dec 2026) or one of `uavmm boost`'s pipeline settings (Zenoh called it an
    invalid config). JSON5 with comments, or an unreadable file, is left to Zenoh, which names its problem."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return
    if not isinstance(data, dict):
        raise ValueError(f"zenoh config {path}: a Zenoh config is a JSON5 object, got a {type(data).__name__}")
    if data and ("memory" in data or "nms_iou" in data) and not {"mode", "connect", "listen"} & set(data):
        raise ValueError(f"zenoh config {path}: these are pipeline settings (as uavmm boost --config reads; the agent "
                         "takes them with --pipeline-config), not a Zenoh config (nor a uavmm tune parameters "
                         "file)")


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """A ``zenoh.Config`` from the file (if any) with the options' overrides applied.

    Raises ValueError for an unreadable config file or a bad ``--cfg`` value.
    """
    import zenoh  # only here: the value object above is usable (and testable) without zenoh

    if options.config_file:
        _refuse_non_object(Path(options.config_file))
    try:
        conf = zenoh.Config.from_file(str(options.config_file)) if options.config_file else zenoh.Config()
    except zenoh.ZError as exc:
        raise ValueError(f"cannot read zenoh config {options.config_file}: {exc}") from None
    if options.mode is not None:
        conf.insert_json5("mode", json.dumps(options.mode))
    for flag, endpoints in (("--connect", options.connect), ("--listen", options.listen)):
        if endpoints is None:
            continue
        for endpoint in endpoints:
            if not _ENDPOINT.match(endpoint):
                raise ValueError(f"{flag} {endpoint!r} is not a Zenoh endpoint: <protocol>/<address>, e.g. "
                                 "tcp/192.168.1.10:7447")
        try:
            conf.insert_json5(f"{flag[2:]}/endpoints", json.dumps(list(endpoints)))
        except zenoh.ZError as exc:
            raise ValueError(f"{flag} {', '.join(endpoints)}: {exc}") from None
    if options.multicast_scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(options.multicast_scouting))
    for item in options.cfg:
        key, value = item.split(":", 1)
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:
            raise ValueError(f"--cfg {item!r}: {exc}") from None
    return conf


def config_file_value(path: Path, key: str) -> Any:
    """The value the Zenoh config file at ``path`` itself gives ``key`` (a config path such as
    ``"listen/endpoints"``), or None where the file leaves it to Zenoh (absent, or null).

    Unlike ``zenoh.Config.get_json``, which also answers with Zenoh's defaults (``listen/endpoints`` is
    a per-mode table that is never empty), this reads the file's own keys: JSON5 for ``.json`` and
    ``.json5``, YAML for ``.yaml`` and ``.yml`` (the formats Zenoh reads). ValueError naming the file
    when it cannot be read or parsed, or its top level is not a map.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read zenoh config {path}: {exc}") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            document = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"cannot parse zenoh config {path}: {exc}") from None
    else:
        import json5

        try:
            document = json5.loads(text)
        except ValueError as exc:
            raise ValueError(f"cannot parse zenoh config {path}: {exc}") from None
    if not isinstance(document, dict):
        raise ValueError(f"zenoh config {path}: the top level is not a map")
    value: Any = document
    for part in key.strip("/").split("/"):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value

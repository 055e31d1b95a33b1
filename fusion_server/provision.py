"""`uavmm secure init`: the files a fleet needs to run authenticated, encrypted and access-controlled.

Writes a folder per identity (fusion server, optional zenohd router, each UAV, each operator) holding its
Zenoh config, the CA certificate and its own key and certificate (or password), plus the REST tokens.
Files are 0600 and folders 0700. Re-running on the same folder adds identities and keeps existing keys.
Everything is checked and every key made before the first file is written: a refusal writes nothing.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

from fusion_server.acl import FUSION_IDENTITY, MAX_IDENTITY_LEN, ROUTER_IDENTITY, FleetIdentities, access_control
from fusion_server.http_auth import read_token_file
from shared import pki
from shared.files import write_atomic
from shared.keys import KeySpace
from shared.pki import CA_DAYS, host_problem

__all__ = ["AUTH_MODES", "FleetPlan", "ProvisionResult", "provision"]

log = logging.getLogger(__name__)

AUTH_MODES = ("mtls", "usrpwd")
MANIFEST = "fleet.json"
_FILE_MODE = 0o600
_DIR_MODE = 0o700


@dataclass(frozen=True, slots=True)
class FleetPlan:
    """What `uavmm secure init` is asked to make.

    uavs, operators: identities (see `FleetIdentities`). server_hosts: names and addresses the agents dial
    (the first one goes into their configs; all go into the server certificate). port: the Zenoh port.
    auth: ``mtls`` (a client certificate per identity, its common name is the identity) or ``usrpwd``
    (server-authenticated TLS plus a generated password per identity). mount_path: where each identity's
    folder will be mounted (e.g. ``/etc/uavmm`` in a container); None writes the folders' real paths.
    """

    uavs: tuple[str, ...]
    operators: tuple[str, ...] = ("operator",)
    server_hosts: tuple[str, ...] = ("localhost", "127.0.0.1")
    port: int = 7447
    auth: str = "mtls"
    prefix: str = "uavmm/v1"
    mount_path: str | None = None
    days: int = 825
    identities: FleetIdentities = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "identities", FleetIdentities(tuple(self.uavs), tuple(self.operators)))
        if self.auth not in AUTH_MODES:
            raise ValueError(f"auth must be one of {', '.join(AUTH_MODES)}, got {self.auth!r}")
        if self.auth == "mtls":  # user names (usrpwd) are no certificate's: an earlier fleet may have longer ones
            for group, members in (("uavs", self.uavs), ("operators", self.operators)):
                for name in members:
                    if len(name) > MAX_IDENTITY_LEN:
                        raise ValueError(f"{group} {name!r} has {len(name)} characters: with client certificates "
                                         f"an identity is a certificate common name, at most {MAX_IDENTITY_LEN} "
                                         "characters")
        if not self.server_hosts:
            raise ValueError("server_hosts: give at least one host name or address the agents dial")
        for host in self.server_hosts:
            problem = host_problem(host)
            if problem is not None:
                raise ValueError(f"server_hosts: {host!r} is not a host name or IP address: {problem}")
        if isinstance(self.days, bool) or not isinstance(self.days, int) or not 1 <= self.days <= CA_DAYS:
            raise ValueError(f"days must be an int in 1..{CA_DAYS}, got {self.days!r} (a certificate cannot "
                             f"outlive the fleet's CA, {CA_DAYS} days)")
        if isinstance(self.port, bool) or not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ValueError(f"port must be in 1..65535, got {self.port!r}")
        KeySpace(self.prefix)
        if self.mount_path is not None and not self.mount_path.startswith("/"):
            raise ValueError(f"mount_path must be absolute, got {self.mount_path!r}")


@dataclass(frozen=True, slots=True)
class ProvisionResult:
    """What was written: the folder, the identities added this time and every identity's folder.

    without_token: operators left without a REST token because their line was deleted from
    ``fusion/http-tokens`` (a withdrawn token stays withdrawn until the operator is named again).
    """

    root: Path
    added: tuple[str, ...]
    folders: dict[str, Path]
    without_token: tuple[str, ...] = ()


def _write(path: Path, content: bytes | str) -> None:
    """Write a file readable by its owner only: whole or not at all, created 0600 before a byte goes in
    (`shared.files.write_atomic`; a file planted at the temporary's name is replaced, never written through)."""
    data = content.encode() if isinstance(content, str) else content

    def put(handle: IO[bytes]) -> None:
        handle.write(data)

    write_atomic(path, put, mode=_FILE_MODE)


def _mkdir(path: Path) -> Path:
    path.mkdir(mode=_DIR_MODE, parents=True, exist_ok=True)
    os.chmod(path, _DIR_MODE)
    return path


def _json5(config: dict[str, Any], comment: str) -> str:
    lines = "".join(f"// {line}\n" for line in comment.splitlines())
    return lines + json.dumps(config, indent=2) + "\n"


class _Fleet:
    """The folder being written: its CA, plan and the identities' material."""

    def __init__(self, root: Path, plan: FleetPlan) -> None:
        self.root = root
        self.plan = plan

    def where(self, folder: Path, name: str) -> str:
        """The path a config names for ``folder/name``: under the mount path if one was given."""
        if self.plan.mount_path is not None:
            return f"{self.plan.mount_path.rstrip('/')}/{name}"
        return str((folder / name).resolve())

    def endpoint(self, host: str | None = None) -> str:
        host = host or self.plan.server_hosts[0]
        shown = f"[{host}]" if ":" in host else host
        return f"tls/{shown}:{self.plan.port}"

    def tls(self, folder: Path, *, listen: bool, client_cert: bool) -> dict[str, Any]:
        tls: dict[str, Any] = {"root_ca_certificate": self.where(folder, "ca.pem")}
        if listen:
            tls["listen_private_key"] = self.where(folder, "key.pem")
            tls["listen_certificate"] = self.where(folder, "cert.pem")
        if client_cert:
            tls["connect_private_key"] = self.where(folder, "key.pem")
            tls["connect_certificate"] = self.where(folder, "cert.pem")
        if self.plan.auth == "mtls":
            tls["enable_mtls"] = True
        return tls


def _load_manifest(root: Path, plan: FleetPlan) -> dict[str, Any] | None:
    """The folder's manifest if it holds a fleet; ValueError if it holds anything else or disagrees."""
    if not root.exists():
        return None
    if not root.is_dir():
        raise ValueError(f"{root} exists and is not a folder")
    manifest_path = root / MANIFEST
    if not manifest_path.exists():
        if any(root.iterdir()):
            raise ValueError(f"{root} is not empty and holds no {MANIFEST}: give a new folder "
                             "(nothing was written)")
        return None
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot read {manifest_path}: {exc}") from None
    for name in ("auth", "prefix", "port", "server_hosts", "mount_path"):
        ours = list(getattr(plan, name)) if name == "server_hosts" else getattr(plan, name)
        if manifest.get(name) != ours:
            raise ValueError(f"{root} was made with {name} {manifest.get(name)!r}, not {ours!r}: "
                             f"use the same {name} to add identities (nothing was written)")
    for name in ("ca.key", "ca.pem"):
        if not (root / "ca" / name).exists():
            raise ValueError(f"{root / 'ca' / name} is missing: the CA is needed to add identities (put it back "
                             "from where you keep it offline; nothing was written)")
    return manifest


def _check_identity_files(folders: dict[str, Path]) -> None:
    """ValueError for an identity folder holding a certificate without its key or a key without its certificate."""
    for folder in folders.values():
        has = {name: (folder / name).exists() for name in ("cert.pem", "key.pem")}
        if has["cert.pem"] != has["key.pem"]:
            there, lost = ("cert.pem", "key.pem") if has["cert.pem"] else ("key.pem", "cert.pem")
            raise ValueError(f"{folder} holds {there} but no {lost}: put {lost} back, or delete {there} to issue "
                             "a new key and certificate (nothing was written)")


def _load_ca(root: Path) -> pki.CertifiedKey:
    """The folder's CA; ValueError if it cannot be read."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    try:
        key = serialization.load_pem_private_key((root / "ca" / "ca.key").read_bytes(), password=None)
        certificate = x509.load_pem_x509_certificate((root / "ca" / "ca.pem").read_bytes())
    except (OSError, ValueError, TypeError) as exc:
        raise ValueError(f"cannot read the fleet's CA in {root / 'ca'}: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{root / 'ca' / 'ca.key'} is not the ECDSA key `uavmm secure init` makes")
    return pki.CertifiedKey(key, certificate)


def _check_ca_days(ca: pki.CertifiedKey, root: Path, days: int, identities: list[str]) -> None:
    """ValueError when the folder's CA cannot sign the certificates of ``identities`` (to be issued) for ``days``
    days; nothing to issue, nothing to check (a UAV added to a usrpwd fleet gets no certificate)."""
    end = ca.certificate.not_valid_after_utc
    left = (end - datetime.now(timezone.utc)).days
    if identities and days > left:
        raise ValueError(f"the fleet's CA ({root / 'ca' / 'ca.pem'}) is valid until {end:%Y-%m-%d}, {max(left, 0)} "
                         f"days from now, too short for the new certificates of {', '.join(identities)}: give days "
                         f"of at most {max(left, 0)} (nothing was written)")


def provision(root: Path, plan: FleetPlan) -> ProvisionResult:
    """Write (or extend) the fleet folder ``root`` for ``plan``; see the module docstring.

    Existing keys, certificates, passwords and tokens are kept; identities of an earlier run stay in the ACL.
    An earlier operator whose line was deleted from ``fusion/http-tokens`` gets no new token unless
    ``plan.operators`` names it (`ProvisionResult.without_token`). Raises ValueError naming the problem (a
    non-empty folder of something else, settings that differ from the folder's, a missing CA file, a
    certificate without its key, days beyond the CA's end) before writing anything.
    """
    # ---- check and make everything in memory: a refusal below leaves the folder as it was
    manifest = _load_manifest(root, plan)
    named_operators = set(plan.operators)
    earlier_operators: set[str] = set()
    if manifest is not None:  # the union of the earlier identities and the new ones
        earlier_operators = set(manifest.get("operators", []))
        uavs = tuple(dict.fromkeys([*manifest.get("uavs", []), *plan.uavs]))
        operators = tuple(dict.fromkeys([*manifest.get("operators", []), *plan.operators]))
        plan = FleetPlan(uavs=uavs, operators=operators, server_hosts=plan.server_hosts, port=plan.port,
                         auth=plan.auth, prefix=plan.prefix, mount_path=plan.mount_path, days=plan.days)
    fleet = _Fleet(root, plan)
    folders = {FUSION_IDENTITY: root / "fusion", ROUTER_IDENTITY: root / "router"}
    folders.update({uav: root / "uavs" / uav for uav in plan.uavs})
    folders.update({name: root / "operators" / name for name in plan.operators})
    _check_identity_files(folders)
    new_ca = manifest is None
    ca = pki.new_ca(f"uavmm fleet CA {datetime.now(timezone.utc):%Y-%m-%d}") if new_ca else _load_ca(root)
    servers = (FUSION_IDENTITY, ROUTER_IDENTITY)
    to_issue = [identity for identity, folder in folders.items()
                if (identity in servers or plan.auth == "mtls") and not (folder / "cert.pem").exists()]
    if not new_ca:  # a new CA outlives every certificate it signs (FleetPlan's days, pki.issue)
        _check_ca_days(ca, root, plan.days, to_issue)
    issued = {identity: pki.issue(ca, identity, hosts=plan.server_hosts if identity in servers else (),
                                  days=plan.days) for identity in to_issue}
    passwords = _read_passwords(root / "fusion" / "users.txt")
    if plan.auth == "usrpwd":
        for identity in folders:
            if identity != ROUTER_IDENTITY:
                passwords.setdefault(identity, secrets.token_urlsafe(24))
    tokens = _read_tokens(root / "fusion" / "http-tokens")
    without_token: list[str] = []
    for name in plan.operators:
        if name in tokens:
            continue
        if name in earlier_operators and name not in named_operators:
            without_token.append(name)  # its line was deleted from http-tokens: withdrawn, not renewed
            continue
        tokens[name] = secrets.token_urlsafe(32)
    acl = access_control(plan.identities, prefix=plan.prefix,
                         subject_field="cert_common_names" if plan.auth == "mtls" else "usernames")

    # ---- write
    _mkdir(root)
    ca_dir = _mkdir(root / "ca")
    if new_ca:
        _write(ca_dir / "ca.key", ca.key_pem)
        _write(ca_dir / "ca.pem", ca.certificate_pem)
    for group in ("uavs", "operators"):
        _mkdir(root / group)
    added = []
    for identity, folder in folders.items():
        if not folder.exists() and identity != ROUTER_IDENTITY:
            added.append(identity)
        _mkdir(folder)
        _write(folder / "ca.pem", ca.certificate_pem)
        if identity in issued:
            _write(folder / "key.pem", issued[identity].key_pem)
            _write(folder / "cert.pem", issued[identity].certificate_pem)
    if plan.auth == "usrpwd":
        _write(root / "fusion" / "users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
        _write(root / "router" / "users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    _write_server_configs(fleet, folders, acl, passwords)
    for identity in (*plan.uavs, *plan.operators):
        _write_client_config(fleet, identity, folders[identity], passwords, operator=identity in plan.operators)
    for name in plan.operators:
        if name in tokens:
            _write(folders[name] / "http-token", tokens[name] + "\n")
    _write(root / "fusion" / "http-tokens",
           "# name:token, one REST API bearer token per operator (uavmm fusion --http-token-file)\n"
           + "".join(f"{n}:{t}\n" for n, t in tokens.items()))
    _write(root / MANIFEST, json.dumps({
        "auth": plan.auth, "prefix": plan.prefix, "port": plan.port, "server_hosts": list(plan.server_hosts),
        "mount_path": plan.mount_path, "uavs": list(plan.uavs), "operators": list(plan.operators),
        "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }, indent=2) + "\n")
    _write(root / "README.md", _readme(fleet, folders))
    return ProvisionResult(root, tuple(added), folders, tuple(without_token))


def _read_passwords(path: Path) -> dict[str, str]:
    if not path.exists():
        return {}
    pairs = (line.split(":", 1) for line in path.read_text().splitlines() if ":" in line)
    return {user: password for user, password in pairs}


def _read_tokens(path: Path) -> dict[str, str]:
    """The operators' tokens already in the fleet's token file (the format `uavmm fusion` reads)."""
    if not path.exists() or not any(line.strip() and not line.lstrip().startswith("#")
                                    for line in path.read_text().splitlines()):
        return {}
    return {token.name: token.token for token in read_token_file(path)}


def _auth(fleet: _Fleet, identity: str, passwords: dict[str, str], *, dictionary: Path | None = None) -> dict:
    if fleet.plan.auth != "usrpwd":
        return {}
    usrpwd: dict[str, Any] = {"user": identity, "password": passwords[identity]}
    if dictionary is not None:
        usrpwd["dictionary_file"] = fleet.where(dictionary.parent, dictionary.name)
    return {"auth": {"usrpwd": usrpwd}}


def _write_server_configs(fleet: _Fleet, folders: dict[str, Path], acl: dict, passwords: dict[str, str]) -> None:
    plan = fleet.plan
    listen = {"endpoints": [f"tls/0.0.0.0:{plan.port}"]}
    fusion = folders[FUSION_IDENTITY]
    # the fusion server as the router every agent connects to (the default layout)
    config = {
        "mode": "router", "listen": listen, "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": fleet.tls(fusion, listen=True, client_cert=False)},
                      **_auth(fleet, FUSION_IDENTITY, passwords, dictionary=fusion / "users.txt")},
        "access_control": acl,
    }
    _write(fusion / "zenoh.json5", _json5(config, (
        "uavmm fusion --config zenoh.json5: the fusion server as the fleet's router.\n"
        "Every UAV may put only on its own keys; only this server puts joint tiles and tracks.")))
    # the fusion server behind a zenohd router (the router holds the ACL)
    client = {
        "mode": "client", "connect": {"endpoints": [fleet.endpoint()]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": fleet.tls(fusion, listen=False, client_cert=plan.auth == "mtls")},
                      **_auth(fleet, FUSION_IDENTITY, passwords)},
    }
    _write(fusion / "zenoh-client.json5", _json5(client, (
        "uavmm fusion --config zenoh-client.json5: the fusion server as a client of a zenohd router\n"
        "that runs with ../router/zenohd.json5.")))
    router = folders[ROUTER_IDENTITY]
    router_config = {
        "mode": "router", "listen": listen, "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": fleet.tls(router, listen=True, client_cert=False)},
                      **({"auth": {"usrpwd": {"dictionary_file": fleet.where(router, "users.txt")}}}
                         if plan.auth == "usrpwd" else {})},
        "access_control": acl,
    }
    _write(router / "zenohd.json5", _json5(router_config, (
        "zenohd -c zenohd.json5: a Zenoh router holding the fleet's ACL; the fusion server then runs\n"
        "with ../fusion/zenoh-client.json5.")))


def _write_client_config(fleet: _Fleet, identity: str, folder: Path, passwords: dict[str, str], *,
                         operator: bool) -> None:
    config = {
        "mode": "client", "connect": {"endpoints": [fleet.endpoint()]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": fleet.tls(folder, listen=False, client_cert=fleet.plan.auth == "mtls")},
                      **_auth(fleet, identity, passwords)},
    }
    what = (f"an operator's read-only session ({identity})" if operator else
            f"uavmm agent --uav-id {identity} --config zenoh.json5 ...: this UAV may put only on its own keys")
    _write(folder / "zenoh.json5", _json5(config, what))


def _readme(fleet: _Fleet, folders: dict[str, Path]) -> str:
    plan = fleet.plan
    uav = plan.uavs[0]

    def conf(identity: str, name: str) -> str:
        return fleet.where(folders[identity], name)

    return f"""# uavmm fleet credentials ({plan.auth})

Made by `uavmm secure init`. Keep this folder private. `ca/ca.key` signs new identities: keep it
offline (only `uavmm secure init` on this folder needs it, to add UAVs or operators).

- `fusion/` goes to the ground station:
  `uavmm fusion --config {conf(FUSION_IDENTITY, 'zenoh.json5')} \\
      --http-token-file {conf(FUSION_IDENTITY, 'http-tokens')}`
- `uavs/ID/` goes to drone ID's companion computer:
  `uavmm agent --uav-id {uav} --config {conf(uav, 'zenoh.json5')} ...`
- `operators/NAME/` goes to an operator: the REST token (`Authorization: Bearer $(cat http-token)`,
  or the page at `http://GROUND:8000/#token=...`) and a read-only Zenoh config.
- `router/` is for a zenohd router, if you use one: `zenohd -c {conf(ROUTER_IDENTITY, 'zenohd.json5')}`;
  the fusion server then runs with `fusion/zenoh-client.json5`.

Agents dial `{fleet.endpoint()}` (server names in the certificate: {', '.join(plan.server_hosts)}).
UAVs: {', '.join(plan.uavs)}. Operators: {', '.join(plan.operators) or 'none'}.
Add identities later with the same command and folder: `uavmm secure init DIR --uavs NEW_ID`.
"""

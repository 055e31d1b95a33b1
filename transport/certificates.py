"""The TLS certificates a Zenoh config names, checked for their dates before a process starts.

A certificate that has run out, or that this machine's clock places before its start (a drone without
GPS time or NTP), makes every TLS handshake fail, and Zenoh only retries: an agent then flies without a
word reaching the ground station (docs/deploy.md, "Clocks"). `certificate_notices` reads the CA, listen
and connect certificates of ``transport/link/tls`` (files, or inline as ``*_base64``) and of the endpoints' own
``#..._file`` / ``#..._base64`` parameters and says which have run out (the process stops), which the
clock places before their start (it starts and says so loudly: the clock may be set later) and which run out
within `EXPIRY_WARNING_DAYS` (a warning).
Files it cannot read or parse, and inline values it cannot decode, are left to Zenoh, which names them itself.
"""

from __future__ import annotations

import base64
import datetime as dt
import logging
from dataclasses import dataclass, field

import zenoh

from transport.session import config_value

__all__ = ["EXPIRY_WARNING_DAYS", "CertificateNotices", "certificate_notices", "check_certificates", "uses_tls"]

log = logging.getLogger(__name__)

#: a certificate ending within this many days gets a warning at start
EXPIRY_WARNING_DAYS = 30
#: the Zenoh TLS parameters holding certificates, and what each is for: ``transport/link/tls/NAME`` names a file and
#: ``NAME_base64`` holds the PEM inline (base64); an endpoint's ``#NAME_file=`` / ``#NAME_base64=`` the same
_CERTIFICATE_KEYS = (
    ("root_ca_certificate", "CA certificate"),
    ("listen_certificate", "listen certificate"),
    ("connect_certificate", "connect certificate"),
)
_RENEW = ("renew it: delete the identity's cert.pem and key.pem and re-run `uavmm secure init` (docs/deploy.md); "
          "for the CA, make a new fleet")


@dataclass
class CertificateNotices:
    """What `certificate_notices` found: problems (expired: no TLS session can work), early (not valid yet by this
    clock: none works until the clock is set) and warnings (ending soon)."""

    problems: list[str] = field(default_factory=list)
    early: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _date(when: dt.datetime) -> str:
    return when.strftime("%Y-%m-%d %H:%M UTC")


def certificate_notices(conf: zenoh.Config, now: dt.datetime | None = None, *,
                        warn_days: float = EXPIRY_WARNING_DAYS) -> CertificateNotices:
    """The date problems and warnings of the certificates ``conf`` names or holds inline (`_certificate_sources`): every
    certificate of a listen or connect certificate's chain; of the CA bundle, the CA valid now that lasts longest
    (any one of a bundle will do). An inline one is named "inline NAME_base64", a file by its path.

    now: the time to judge by (default: this machine's clock, UTC). A certificate past its end is a problem, one not
    yet started by this clock is early, one ending within ``warn_days`` days a warning. Unset entries, files that
    cannot be read or parsed and inline values that are not base64 of a PEM give nothing (Zenoh reports those).
    """
    from shared.pki import certificate_validities

    now = dt.datetime.now(dt.timezone.utc) if now is None else now
    notices = CertificateNotices()
    seen: set[str] = set()
    for key, role, name, value in _certificate_sources(conf):
        if value in seen:
            continue
        seen.add(value)
        try:
            if name:  # inline: base64 of the PEM, as Zenoh decodes it
                validities = certificate_validities(base64.b64decode(value, validate=True))
            else:
                with open(value, "rb") as handle:
                    validities = certificate_validities(handle.read())
        except (OSError, ValueError) as exc:  # binascii.Error is a ValueError
            log.debug("%s %s not checked: %s", role, name or value, exc)
            continue
        if key == "root_ca_certificate":
            # a bundle of CAs works while any of them does: judge the one that lasts longest of those valid now
            # (an expired CA among valid ones is no problem), or, with none valid, the first
            valid = [v for v in validities if v.not_before <= now <= v.not_after]
            validities = [max(valid, key=lambda v: v.not_after)] if valid else validities[:1]
        for validity in validities:
            who = f"{role} {name or value}" + (f" ({validity.common_name})" if validity.common_name else "")
            if now > validity.not_after:
                notices.problems.append(f"the {who} expired on {_date(validity.not_after)}: no TLS session can "
                                        f"open with it; {_RENEW}")
            elif now < validity.not_before:
                notices.early.append(
                    f"the {who} is valid only from {_date(validity.not_before)}, and this machine's clock says "
                    f"{_date(now)}: set the clock (GPS or NTP), or no TLS session can open")
            else:
                left = validity.not_after - now
                if left <= dt.timedelta(days=warn_days):
                    notices.warnings.append(f"the {who} expires on {_date(validity.not_after)}, in "
                                            f"{left.total_seconds() / 86400:.1f} days; {_RENEW}")
    return notices


def _certificate_sources(conf: zenoh.Config) -> list[tuple[str, str, str, str]]:
    """Every certificate ``conf`` gives: (parameter, role, name, value) with name "" and value a file path, or name
    "inline NAME_base64" and value the base64 text; from ``transport/link/tls`` first, then from the listen
    (CA, listen certificate) and connect (CA, connect certificate) endpoints' ``#`` parameters."""
    sources = []
    for key, role in _CERTIFICATE_KEYS:
        path = config_value(conf, f"transport/link/tls/{key}")
        if isinstance(path, str) and path:
            sources.append((key, role, "", path))
        inline = config_value(conf, f"transport/link/tls/{key}_base64")
        if isinstance(inline, str) and inline:
            sources.append((key, role, f"inline {key}_base64", inline))
    for side in ("listen", "connect"):
        for endpoint in _strings(config_value(conf, f"{side}/endpoints")):
            # proto/address?metadata#key=value;key=value (Zenoh splits each at its first "=": base64 keeps its "=")
            parameters = dict(p.split("=", 1) for p in endpoint.partition("#")[2].split(";") if "=" in p)
            for key, role in _CERTIFICATE_KEYS:
                if key not in ("root_ca_certificate", f"{side}_certificate"):
                    continue
                if parameters.get(f"{key}_file"):
                    sources.append((key, role, "", parameters[f"{key}_file"]))
                if parameters.get(f"{key}_base64"):
                    sources.append((key, role, f"inline {key}_base64", parameters[f"{key}_base64"]))
    return sources


def _strings(value: object) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [s for v in value.values() for s in _strings(v)]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    return []


def uses_tls(conf: zenoh.Config) -> bool:
    """Whether a listen or connect endpoint of ``conf`` is TLS (``tls/``, ``quic/``: both use the certificates);
    endpoints may be a list or a table per mode."""
    endpoints = _strings(config_value(conf, "listen/endpoints")) + _strings(config_value(conf, "connect/endpoints"))
    return any(e.startswith(("tls/", "quic/")) for e in endpoints)


def check_certificates(conf: zenoh.Config, logger: logging.Logger) -> None:
    """Before a process opens its session: ValueError naming every expired certificate when a listen or connect
    endpoint is TLS (the CLI prints it and exits 2: no later moment makes it work; with no TLS endpoint, e.g. a
    fleet's config run with ``--listen tcp/...``, a warning); an error logged for each that this machine's clock
    places before its start (the process starts: a companion computer often gets its time from GPS or NTP after
    boot, and Zenoh's retries then connect), a warning for each that runs out within `EXPIRY_WARNING_DAYS`."""
    notices = certificate_notices(conf)
    if notices.problems and not uses_tls(conf):  # the files are named, but no endpoint is TLS: nothing stops
        notices.warnings[:0] = [f"{p} (no tls/ or quic/ endpoint is configured, so it is not needed now)"
                                for p in notices.problems]
        notices.problems = []
    if notices.problems:
        raise ValueError("; ".join(notices.problems))
    for early in notices.early:
        logger.error("%s; starting anyway: the sessions open once the clock is set", early)
    for warning in notices.warnings:
        logger.warning("%s", warning)

"""The TLS certificates a Zenoh config names, checked for their dates before a process starts.

A certificate that has run out, or that this machine's clock places before its start (a drone without
GPS time or NTP), makes every TLS handshake fail, and Zenoh only retries: an agent then flies without a
word reaching the ground station (docs/deploy.md, "Clocks"). `certificate_notices` reads the CA, listen
and connect certificates of ``transport/link/tls`` and says which have run out (the process stops), which the
clock places before their start (it starts and says so loudly: the clock may be set later) and which run out
within `EXPIRY_WARNING_DAYS` (a warning).
Files it cannot read or parse are left to Zenoh, which names them itself.
"""

from __future__ import annotations

import datetime as dt
import logging
from dataclasses import dataclass, field

import zenoh

from transport.session import config_value

__all__ = ["EXPIRY_WARNING_DAYS", "CertificateNotices", "certificate_notices", "check_certificates", "uses_tls"]

log = logging.getLogger(__name__)

#: a certificate ending within this many days gets a warning at start
EXPIRY_WARNING_DAYS = 30
#: the Zenoh config entries naming certificate files, and what each is for
_CERTIFICATE_KEYS = (
    ("transport/link/tls/root_ca_certificate", "CA certificate"),
    ("transport/link/tls/listen_certificate", "listen certificate"),
    ("transport/link/tls/connect_certificate", "connect certificate"),
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
    """The date problems and warnings of the certificates ``conf`` names: every certificate of a listen or connect
    certificate's chain; of the CA file, the CA valid now that lasts longest (any one of a bundle will do).

    now: the time to judge by (default: this machine's clock, UTC). A certificate past its end is a problem, one not
    yet started by this clock is early, one ending within ``warn_days`` days a warning. Unset entries and files that
    cannot be read or parsed give nothing (Zenoh reports those itself).
    """
    from shared.pki import certificate_validities

    now = dt.datetime.now(dt.timezone.utc) if now is None else now
    notices = CertificateNotices()
    seen: set[str] = set()
    for key, role in _CERTIFICATE_KEYS:
        path = config_value(conf, key)
        if not isinstance(path, str) or not path or path in seen:
            continue
        seen.add(path)
        try:
            with open(path, "rb") as handle:
                validities = certificate_validities(handle.read())
        except (OSError, ValueError) as exc:
            log.debug("%s %s not checked: %s", role, path, exc)
            continue
        if key.endswith("root_ca_certificate"):
            # a bundle of CAs works while any of them does: judge the one that lasts longest of those valid now
            # (an expired CA among valid ones is no problem), or, with none valid, the first
            valid = [v for v in validities if v.not_before <= now <= v.not_after]
            validities = [max(valid, key=lambda v: v.not_after)] if valid else validities[:1]
        for validity in validities:
            who = f"{role} {path}" + (f" ({validity.common_name})" if validity.common_name else "")
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

"""A small certificate authority for one fleet: a CA, server certificates and one client certificate per identity.

ECDSA P-256 keys and X.509 certificates made with the `cryptography` package (no openssl binary needed).
The certificate's common name is the identity Zenoh's access control matches (``cert_common_names``).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
from collections.abc import Sequence
from dataclasses import dataclass

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = ["CA_DAYS", "CertifiedKey", "Validity", "certificate_common_name", "certificate_validities", "host_problem",
           "issue", "new_ca", "pem_certificate", "pem_private_key"]

_BACKDATE = dt.timedelta(minutes=10)  # tolerate clocks a little behind the ground station's
#: validity of a new CA in days (10 years); no certificate it signs is valid longer
CA_DAYS = 3650
#: one DNS label: ASCII letters, digits, '-' and '_' (compose service names), not starting or ending with '-'
_DNS_LABEL = re.compile(r"[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?\Z")


@dataclass(frozen=True)
class CertifiedKey:
    """A private key and its certificate."""

    key: ec.EllipticCurvePrivateKey
    certificate: x509.Certificate

    @property
    def key_pem(self) -> bytes:
        return pem_private_key(self.key)

    @property
    def certificate_pem(self) -> bytes:
        return pem_certificate(self.certificate)


def pem_private_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    """PKCS#8 PEM, unencrypted (Zenoh reads unencrypted keys; the file is written 0600)."""
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def pem_certificate(certificate: x509.Certificate) -> bytes:
    return certificate.public_bytes(serialization.Encoding.PEM)


def certificate_common_name(pem: bytes) -> str:
    """The subject common name of a PEM certificate; ValueError if it is not a certificate or has none."""
    try:
        certificate = x509.load_pem_x509_certificate(pem)
    except ValueError as exc:
        raise ValueError(f"not a PEM certificate: {exc}") from None
    names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise ValueError("the certificate has no common name")
    return str(names[0].value)


@dataclass(frozen=True)
class Validity:
    """When one certificate of a PEM file holds: its subject's common name ('' without one) and its bounds (UTC)."""

    common_name: str
    not_before: dt.datetime
    not_after: dt.datetime


def certificate_validities(pem: bytes) -> list[Validity]:
    """The validity of every certificate in ``pem`` (a chain may hold several); ValueError if it holds none."""
    try:
        certificates = x509.load_pem_x509_certificates(pem)
    except ValueError as exc:
        raise ValueError(f"not a PEM certificate: {exc}") from None
    out = []
    for certificate in certificates:
        names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        out.append(Validity(str(names[0].value) if names else "", certificate.not_valid_before_utc,
                            certificate.not_valid_after_utc))
    return out


def _key_usage(*, ca: bool) -> x509.KeyUsage:
    return x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                         data_encipherment=False, key_agreement=False, key_cert_sign=ca, crl_sign=ca,
                         encipher_only=False, decipher_only=False)


def _validity(days: int, now: dt.datetime | None = None) -> tuple[dt.datetime, dt.datetime]:
    if not isinstance(days, int) or isinstance(days, bool) or days < 1:
        raise ValueError(f"days must be an int >= 1, got {days!r}")
    now = dt.datetime.now(dt.timezone.utc) if now is None else now
    return now - _BACKDATE, now + dt.timedelta(days=days)


def new_ca(name: str, *, days: int = CA_DAYS, now: dt.datetime | None = None) -> CertifiedKey:
    """A self-signed CA that may only sign end-entity certificates (path length 0).

    now: the time it is made (default: the clock's; valid from 10 minutes before it for ``days`` days)."""
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    start, end = _validity(days, now)
    certificate = (
        x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return CertifiedKey(key, certificate)


def host_problem(host: object) -> str | None:
    """Why ``host`` cannot be a server certificate's name and the host clients dial, or None.

    Valid: an IPv4 or IPv6 address (without brackets) or a DNS name of 1..253 characters whose dot-separated
    labels (1..63 characters) use ASCII letters, digits, ``-`` and ``_``. Not a port, a wildcard, a URL or an
    internationalised name (give its ``xn--`` form).
    """
    if not isinstance(host, str) or not host:
        return "it is empty"
    try:
        ipaddress.ip_address(host)
        return None
    except ValueError:
        pass
    if len(host) > 253:
        return f"a DNS name has at most 253 characters, this one {len(host)}"
    if not all(_DNS_LABEL.match(label) for label in host.split(".")):
        return ("give an IP address (IPv6 without brackets) or a DNS name of ASCII letters, digits, '-' and '_' "
                "in dot-separated labels (no port, no wildcard, no scheme)")
    return None


def _san(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def issue(ca: CertifiedKey, common_name: str, *, hosts: Sequence[str] = (), days: int = 825,
          now: dt.datetime | None = None) -> CertifiedKey:
    """A certificate for ``common_name`` signed by ``ca``.

    hosts: DNS names or IP addresses the holder serves under (subject alternative names, see `host_problem`);
    given, the certificate is good for TLS servers and clients, else for clients only. The certificate ends
    after ``days`` days or with the CA, whichever is first (a verifier refuses it after the CA's end anyway).
    now: the time it is made (default: the clock's).
    """
    if not common_name:
        raise ValueError("common_name must not be empty")
    for host in hosts:
        problem = host_problem(host)
        if problem is not None:
            raise ValueError(f"host {host!r} is not a host name or IP address: {problem}")
    key = ec.generate_private_key(ec.SECP256R1())
    start, end = _validity(days, now)
    end = min(end, ca.certificate.not_valid_after_utc)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if hosts:
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(ca.certificate.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()), critical=False)
    )
    if hosts:
        builder = builder.add_extension(x509.SubjectAlternativeName([_san(h) for h in hosts]), critical=False)
    return CertifiedKey(key, builder.sign(ca.key, hashes.SHA256()))

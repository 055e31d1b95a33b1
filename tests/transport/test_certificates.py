"""Certificates checked for their dates before a process opens its session (transport.certificates): an expired
or not-yet-valid certificate stops `uavmm agent` / `uavmm fusion` at once with a message naming it (Zenoh would
only retry in silence); one ending within 30 days is a warning; a re-run of `uavmm secure init` lists them."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.zenoh_config import agent_zenoh_config
from shared.pki import CertifiedKey, certificate_validities, issue, new_ca, pem_certificate
from transport.certificates import EXPIRY_WARNING_DAYS, certificate_notices, check_certificates, uses_tls
from transport.options import ZenohOptions
from uavmm.cli import main

NOW = dt.datetime(2026, 11, 30, 12, 0, tzinfo=dt.timezone.utc)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("certs") / "fleet"
    assert main(["secure", "init", str(root), "--uavs", "uav1", "--server-host", "localhost"]) == 0
    return root


def _ca(root: Path) -> CertifiedKey:
    key = serialization.load_pem_private_key((root / "ca" / "ca.key").read_bytes(), password=None)
    return CertifiedKey(key, x509.load_pem_x509_certificate((root / "ca" / "ca.pem").read_bytes()))  # type: ignore[arg-type]


def _copy(fleet: Path, tmp_path: Path) -> Path:
    import shutil

    root = tmp_path / "fleet"
    shutil.copytree(fleet, root)
    for config in root.rglob("zenoh.json5"):  # the configs name the files by absolute path
        config.write_text(config.read_text().replace(str(fleet), str(root)))
    return root


def _uav_config(root: Path):
    return agent_zenoh_config(ZenohOptions(config_file=root / "uavs" / "uav1" / "zenoh.json5"))


def test_a_new_fleet_has_nothing_to_say(fleet):
    notices = certificate_notices(_uav_config(fleet))
    assert notices.problems == [] and notices.warnings == []
    # the same files judged 900 days on: the UAV's certificate (825 days) has run out, the CA (10 years) not
    later = certificate_notices(_uav_config(fleet), dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=900))
    assert len(later.problems) == 1 and "connect certificate" in later.problems[0]
    assert "(uav1) expired on" in later.problems[0] and "uavmm secure init" in later.problems[0]


def test_a_clock_before_the_certificates_is_named_and_the_process_starts(fleet, caplog):
    """A companion computer often gets its time after boot (GPS, NTP): said loudly, not a reason to stop."""
    notices = certificate_notices(_uav_config(fleet), dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc))
    assert notices.problems == [] and len(notices.early) == 2  # the CA and the UAV's certificate (one file each)
    assert all("this machine's clock says 1970-01-01" in p and "GPS or NTP" in p for p in notices.early)
    future = issue(_ca(fleet), "uav1", days=30, now=dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=2))
    early = fleet.parent / "early.pem"
    early.write_bytes(future.certificate_pem)
    conf = agent_zenoh_config(ZenohOptions(cfg=(f'transport/link/tls/connect_certificate:"{early}"',)))
    with caplog.at_level(logging.ERROR, logger="test"):
        check_certificates(conf, logging.getLogger("test"))  # no ValueError
    assert len(caplog.records) == 1 and "starting anyway" in caplog.records[0].getMessage()


@settings(max_examples=60, deadline=None)
@given(offset_days=st.floats(-30.0, 60.0, allow_nan=False), warn_days=st.floats(0.0, 45.0, allow_nan=False))
def test_each_certificate_is_judged_by_its_own_dates(tmp_path_factory, offset_days, warn_days):
    """A certificate valid over [start, start + 20 days] is a problem after it, early before it, a warning within
    warn_days of its end, else nothing; the CA (ten years) never speaks."""
    root = tmp_path_factory.mktemp("one")
    ca = new_ca("test-ca", now=NOW - dt.timedelta(days=100))
    leaf = issue(ca, "uav9", days=20, now=NOW)
    (root / "ca.pem").write_bytes(pem_certificate(ca.certificate))
    (root / "cert.pem").write_bytes(leaf.certificate_pem)
    conf = agent_zenoh_config(ZenohOptions(cfg=(f'transport/link/tls/root_ca_certificate:"{root / "ca.pem"}"',
                                                f'transport/link/tls/connect_certificate:"{root / "cert.pem"}"')))
    when = NOW + dt.timedelta(days=offset_days)
    notices = certificate_notices(conf, when, warn_days=warn_days)
    (validity,) = certificate_validities(leaf.certificate_pem)
    assert bool(notices.problems) == (when > validity.not_after) and len(notices.problems) <= 1
    assert bool(notices.early) == (when < validity.not_before) and len(notices.early) <= 1
    outside = when < validity.not_before or when > validity.not_after
    expect_warning = not outside and validity.not_after - when <= dt.timedelta(days=warn_days)
    assert bool(notices.warnings) == expect_warning
    assert all("uav9" in line for line in notices.problems + notices.early + notices.warnings)


def test_files_zenoh_will_complain_about_are_left_to_it(tmp_path):
    (tmp_path / "junk.pem").write_text("not a certificate")
    conf = agent_zenoh_config(ZenohOptions(cfg=(f'transport/link/tls/connect_certificate:"{tmp_path / "junk.pem"}"',
                                                f'transport/link/tls/root_ca_certificate:"{tmp_path / "none.pem"}"')))
    notices = certificate_notices(conf, NOW)
    assert notices.problems == [] and notices.early == [] and notices.warnings == []


def test_an_agent_with_an_expired_certificate_stops_before_it_starts(fleet, tmp_path, capsys):
    root = _copy(fleet, tmp_path)
    old = issue(_ca(root), "uav1", days=30, now=dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=60))
    (root / "uavs" / "uav1" / "cert.pem").write_bytes(old.certificate_pem)
    (root / "uavs" / "uav1" / "key.pem").write_bytes(old.key_pem)
    code = main(["agent", "--uav-id", "uav1", "--config", str(root / "uavs" / "uav1" / "zenoh.json5"),
                 "--sim", "coop", "--uav-index", "0", "--frames", "5"])
    err = capsys.readouterr().err
    assert code == 2 and "connect certificate" in err and "(uav1) expired on" in err
    assert "summary" not in capsys.readouterr().out


def test_a_server_certificate_near_its_end_is_a_warning_and_a_dead_one_stops_the_server(fleet, tmp_path, capsys,
                                                                                      caplog):
    root = _copy(fleet, tmp_path)
    now = dt.datetime.now(dt.timezone.utc)
    soon = issue(_ca(root), "fusion", hosts=("localhost",), days=EXPIRY_WARNING_DAYS + 400,
                 now=now - dt.timedelta(days=400 + EXPIRY_WARNING_DAYS - 5))  # 5 days left
    (root / "fusion" / "cert.pem").write_bytes(soon.certificate_pem)
    (root / "fusion" / "key.pem").write_bytes(soon.key_pem)
    conf = agent_zenoh_config(ZenohOptions(config_file=root / "fusion" / "zenoh.json5"))
    notices = certificate_notices(conf)
    assert notices.problems == [] and len(notices.warnings) == 1  # its listen and connect certificate: one file
    with caplog.at_level(logging.WARNING, logger="test"):
        check_certificates(conf, logging.getLogger("test"))  # starts, and says so
    assert [r.getMessage() for r in caplog.records] == notices.warnings and "in 5.0 days" in notices.warnings[0]
    # a re-run of `uavmm secure init` names it too (it keeps existing certificates)
    assert main(["secure", "init", str(root), "--uavs", "uav1"]) == 0
    out = capsys.readouterr().out
    assert f"fusion's certificate expires on {soon.certificate.not_valid_after_utc:%Y-%m-%d}" in out
    assert "uav1's certificate" not in out
    dead = issue(_ca(root), "fusion", hosts=("localhost",), days=10, now=now - dt.timedelta(days=11))
    (root / "fusion" / "cert.pem").write_bytes(dead.certificate_pem)
    code = main(["fusion", "--config", str(root / "fusion" / "zenoh.json5"), "--no-db", "--no-http",
                 "--listen", "tls/127.0.0.1:0"])
    err = capsys.readouterr().err
    assert code == 2 and "(fusion) expired on" in err
    # a sharded deployment's gateway runs with the fusion identity's config: the same check
    code = main(["gateway", "--shards", "2", "--config", str(root / "fusion" / "zenoh.json5"), "--mode", "client",
                 "--connect", "tls/localhost:1", "--http", "127.0.0.1:0"])
    err = capsys.readouterr().err
    assert code == 2 and "(fusion) expired on" in err


def test_a_ca_bundle_works_while_one_of_its_cas_does(tmp_path):
    """An expired CA among valid ones (a bundle) is no problem; a bundle of expired CAs is one, named once."""
    old = new_ca("old-ca", days=30, now=NOW - dt.timedelta(days=400))
    good = new_ca("fleet-ca", days=3650, now=NOW - dt.timedelta(days=10))
    bundle = tmp_path / "bundle.pem"
    bundle.write_bytes(pem_certificate(old.certificate) + pem_certificate(good.certificate))
    conf = agent_zenoh_config(ZenohOptions(cfg=(f'transport/link/tls/root_ca_certificate:"{bundle}"',)))
    notices = certificate_notices(conf, NOW)
    assert notices.problems == [] and notices.warnings == []
    bundle.write_bytes(pem_certificate(old.certificate) * 2)
    notices = certificate_notices(conf, NOW)
    assert len(notices.problems) == 1 and "(old-ca) expired on" in notices.problems[0]


def test_an_expired_certificate_stops_only_a_process_that_uses_tls(fleet, tmp_path, caplog):
    """A fleet's config run with --listen tcp/... (debugging on a LAN) started before the check: it still does, with
    a warning (the review's finding)."""
    root = _copy(fleet, tmp_path)
    dead = issue(_ca(root), "fusion", hosts=("localhost",), days=10,
                 now=dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=11))
    (root / "fusion" / "cert.pem").write_bytes(dead.certificate_pem)
    config = root / "fusion" / "zenoh.json5"
    tcp = agent_zenoh_config(ZenohOptions(config_file=config, listen=("tcp/127.0.0.1:0",), connect=()))
    assert not uses_tls(tcp)
    with caplog.at_level(logging.WARNING, logger="test"):
        check_certificates(tcp, logging.getLogger("test"))  # no ValueError
    assert any("(fusion) expired on" in r.getMessage() and "not needed now" in r.getMessage() for r in caplog.records)
    tls = agent_zenoh_config(ZenohOptions(config_file=config))  # the fleet's own endpoints: tls/
    assert uses_tls(tls)
    with pytest.raises(ValueError, match=r"\(fusion\) expired on"):
        check_certificates(tls, logging.getLogger("test"))


def _inline(pem: bytes) -> str:
    import base64

    return base64.b64encode(pem).decode()


@pytest.mark.parametrize("where", ["config", "endpoint"])
@pytest.mark.parametrize("key", ["root_ca_certificate", "listen_certificate", "connect_certificate"])
def test_an_inline_certificate_is_judged_as_its_file_would_be(tmp_path, caplog, where, key):
    """Left open: a certificate given inline (``transport/link/tls/*_base64``, or an endpoint's ``#..._base64=``)
    was never date-checked. Expired stops a TLS process and warns a TCP one, early is an error log, near its end a
    warning, each named "inline NAME_base64"; an expired CA in a bundle with a valid one is no problem."""
    now = dt.datetime.now(dt.timezone.utc)
    ca = new_ca("inline-ca", now=now - dt.timedelta(days=100))
    side = "connect" if key == "root_ca_certificate" else key.split("_")[0]

    def conf(pem: bytes, endpoint: str):
        if where == "config":
            return agent_zenoh_config(ZenohOptions(cfg=(f'transport/link/tls/{key}_base64:"{_inline(pem)}"',),
                                                   **{side: (endpoint,)}))  # type: ignore[arg-type]
        return agent_zenoh_config(ZenohOptions(**{side: (f"{endpoint}#{key}_base64={_inline(pem)}",)}))  # type: ignore[arg-type]

    name = f"inline {key}_base64"
    dead = issue(ca, "uav7", days=10, now=now - dt.timedelta(days=30)).certificate_pem
    with pytest.raises(ValueError, match=rf"{name} \(uav7\) expired on"):
        check_certificates(conf(dead, "tls/127.0.0.1:7447"), logging.getLogger("test"))
    if where == "config":  # a #parameter only exists on a tls/ or quic/ endpoint
        with caplog.at_level(logging.WARNING, logger="test"):
            check_certificates(conf(dead, "tcp/127.0.0.1:7447"), logging.getLogger("test"))
        assert any(f"{name} (uav7) expired on" in r.getMessage() and "not needed now" in r.getMessage()
                   for r in caplog.records)
    early = issue(ca, "uav7", days=30, now=now + dt.timedelta(days=2)).certificate_pem
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="test"):
        check_certificates(conf(early, "quic/127.0.0.1:7447"), logging.getLogger("test"))
    assert len(caplog.records) == 1 and f"{name} (uav7) is valid only from" in caplog.records[0].getMessage()
    soon = issue(ca, "uav7", days=30, now=now - dt.timedelta(days=25)).certificate_pem
    notices = certificate_notices(conf(soon, "tls/127.0.0.1:7447"))
    assert notices.problems == [] and len(notices.warnings) == 1 and f"{name} (uav7) expires on" in notices.warnings[0]
    if key == "root_ca_certificate":
        old = new_ca("old-ca", days=30, now=now - dt.timedelta(days=400)).certificate
        bundle = pem_certificate(old) + pem_certificate(ca.certificate)
        assert certificate_notices(conf(bundle, "tls/127.0.0.1:7447")).problems == []
        (problem,) = certificate_notices(conf(pem_certificate(old), "tls/127.0.0.1:7447")).problems
        assert "(old-ca) expired on" in problem


def test_an_agent_with_an_expired_inline_certificate_stops_before_it_starts(fleet, capsys):
    dead = issue(_ca(fleet), "uav1", days=10, now=dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=30))
    code = main(["agent", "--uav-id", "uav1", "--connect", "tls/127.0.0.1:1", "--cfg",
                 f'transport/link/tls/connect_certificate_base64:"{_inline(dead.certificate_pem)}"',
                 "--sim", "coop", "--uav-index", "0", "--frames", "5"])
    err = capsys.readouterr().err
    assert code == 2 and "inline connect_certificate_base64 (uav1) expired on" in err


@settings(max_examples=80, deadline=None)
@given(before=st.lists(st.sampled_from(["mtu=1500", "enable_mtls=true", "a=b=c", "", "x"]), max_size=3),
       after=st.lists(st.sampled_from(["so_sndbuf=4096", "verify_name_on_connect=false", ""]), max_size=3),
       metadata=st.sampled_from(["", "?prio=1-7"]), in_config=st.booleans())
def test_endpoint_parameters_are_read_as_zenoh_splits_them(before, after, metadata, in_config):
    """``proto/address?metadata#k=v;k=v``: each parameter split at its first "=", so base64 padding stays; other
    parameters around it change nothing; the same certificate in the config and the endpoint is named once."""
    leaf = issue(new_ca("p-ca", now=NOW - dt.timedelta(days=100)), "uav5", days=20, now=NOW - dt.timedelta(days=40))
    value = _inline(leaf.certificate_pem + b"\n")  # 1 byte more than a multiple of 3 would: "=" padding
    params = ";".join([*before, f"connect_certificate_base64={value}", *after])
    cfg = (f'transport/link/tls/connect_certificate_base64:"{value}"',) if in_config else ()
    conf = agent_zenoh_config(ZenohOptions(connect=(f"tls/127.0.0.1:7447{metadata}#{params}",), cfg=cfg))
    notices = certificate_notices(conf, NOW)
    assert len(notices.problems) == 1 and "inline connect_certificate_base64 (uav5) expired" in notices.problems[0]

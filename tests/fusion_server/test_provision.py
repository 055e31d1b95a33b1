"""`uavmm secure init`: the files, their permissions, the certificates and ACL they hold, re-runs that add
identities without touching existing keys, and refusals that write nothing."""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import stat
from pathlib import Path

import httpx
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fusion_server.acl import ACL_MESSAGES, FleetIdentities, access_control
from fusion_server.http_auth import read_token_file
from fusion_server.provision import FleetPlan, provision
from shared.pki import certificate_common_name, issue, new_ca, pem_certificate
from uavmm.cli import main


def _json5(path: Path) -> dict:
    return json.loads("".join(line for line in path.read_text().splitlines() if not line.startswith("//")))


def _verify(cert_path: Path, ca_path: Path) -> x509.Certificate:
    """The certificate, checked to be signed by the CA."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
    public_key = ca.public_key()
    assert isinstance(public_key, ec.EllipticCurvePublicKey)
    cert.verify_directly_issued_by(ca)
    return cert


def test_cli_writes_every_identity_with_private_permissions(tmp_path, capsys):
    root = tmp_path / "fleet"
    assert main(["secure", "init", str(root), "--uavs", "uav1,uav2", "--operators", "alice",
                 "--server-host", "ground.local,10.0.0.2"]) == 0
    out = capsys.readouterr().out
    assert "new identities: fusion, uav1, uav2, alice" in out and "ca.key offline" in out
    for path in [root, *root.rglob("*")]:
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode == (0o700 if path.is_dir() else 0o600), f"{path} is {oct(mode)}"
    ca = root / "ca" / "ca.pem"
    server = _verify(root / "fusion" / "cert.pem", ca)
    names = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["ground.local"]
    assert [str(a) for a in names.get_values_for_type(x509.IPAddress)] == ["10.0.0.2"]
    usages = server.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert ExtendedKeyUsageOID.SERVER_AUTH in usages
    for identity, folder in (("uav1", "uavs/uav1"), ("uav2", "uavs/uav2"), ("alice", "operators/alice")):
        cert = _verify(root / folder / "cert.pem", ca)
        assert certificate_common_name((root / folder / "cert.pem").read_bytes()) == identity
        usages = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert list(usages) == [ExtendedKeyUsageOID.CLIENT_AUTH]  # a UAV's certificate cannot serve TLS
        config = _json5(root / folder / "zenoh.json5")
        assert config["mode"] == "client" and config["connect"]["endpoints"] == ["tls/ground.local:7447"]
        tls = config["transport"]["link"]["tls"]
        assert tls["connect_certificate"] == str((root / folder / "cert.pem").resolve())
        assert tls["enable_mtls"] is True
        zenoh.Config.from_file(str(root / folder / "zenoh.json5"))  # Zenoh reads it
    fusion = _json5(root / "fusion" / "zenoh.json5")
    assert fusion["mode"] == "router" and fusion["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
    assert fusion["access_control"]["default_permission"] == "deny"
    for name in ("zenoh.json5", "zenoh-client.json5"):
        zenoh.Config.from_file(str(root / "fusion" / name))
    zenoh.Config.from_file(str(root / "router" / "zenohd.json5"))
    tokens = read_token_file(root / "fusion" / "http-tokens")
    assert [t.name for t in tokens] == ["alice"]
    assert (root / "operators" / "alice" / "http-token").read_text().strip() == tokens[0].token


def test_a_second_run_adds_identities_and_keeps_every_existing_key(tmp_path):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",)))
    before = {p: p.read_bytes() for p in root.rglob("*.pem")} | {p: p.read_bytes() for p in root.rglob("key.pem")}
    token = (root / "operators" / "operator" / "http-token").read_text()
    result = provision(root, FleetPlan(uavs=("uav2",), operators=()))
    assert result.added == ("uav2",)
    for path, content in before.items():
        assert path.read_bytes() == content, f"{path} changed"
    assert (root / "operators" / "operator" / "http-token").read_text() == token
    manifest = json.loads((root / "fleet.json").read_text())
    assert manifest["uavs"] == ["uav1", "uav2"] and manifest["operators"] == ["operator"]
    policies = {p["id"] for p in _json5(root / "fusion" / "zenoh.json5")["access_control"]["policies"]}
    assert {"uav:uav1", "uav:uav2", "operators", "fusion"} <= policies
    _verify(root / "uavs" / "uav2" / "cert.pem", root / "ca" / "ca.pem")  # signed by the same CA


def test_cli_rerun_takes_the_folders_settings(tmp_path):
    root = tmp_path / "fleet"
    assert main(["secure", "init", str(root), "--uavs", "uav1", "--port", "9447", "--auth", "usrpwd",
                 "--mount-path", "/etc/uavmm"]) == 0
    assert main(["secure", "init", str(root), "--uavs", "uav2"]) == 0  # port, auth and paths from fleet.json
    config = _json5(root / "uavs" / "uav2" / "zenoh.json5")
    assert config["connect"]["endpoints"] == ["tls/localhost:9447"]
    assert config["transport"]["link"]["tls"] == {"root_ca_certificate": "/etc/uavmm/ca.pem"}
    users = dict(line.split(":", 1) for line in (root / "fusion" / "users.txt").read_text().splitlines())
    assert set(users) == {"fusion", "uav1", "uav2", "operator"}
    assert config["transport"]["auth"]["usrpwd"] == {"user": "uav2", "password": users["uav2"]}
    assert not (root / "uavs" / "uav2" / "cert.pem").exists()  # usrpwd: no client certificates


@pytest.mark.parametrize(("argv", "problem"), [
    (["--uavs", "uav1", "--port", "9000"], "made with port 7447, not 9000"),
    (["--uavs", "uav1", "--auth", "usrpwd"], "made with auth 'mtls'"),
    (["--uavs", "bad id"], "must not contain whitespace"),
    (["--uavs", "uаv1"], "must use only ASCII letters"),  # a Cyrillic a
    (["--uavs", "joint"], "reserved"),
    (["--uavs", "uav1,uav1"], "repeated: uav1"),
    (["--uavs", "fusion"], "repeated: fusion"),
    (["--uavs", ""], "at least one UAV"),
    # found by the audit: these were refused only after files were written (or not at all)
    (["--uavs", "router"], "repeated: router"),  # the router's folder, config and server certificate
    (["--uavs", "uav2", "--operators", "router"], "repeated: router"),
    (["--uavs", "u" * 65], "at most 64 characters"),  # a certificate common name's limit
    (["--uavs", "uav2", "--days", "0"], "days must be an int in 1..3650, got 0"),
    (["--uavs", "uav2", "--days", "10000000"], "days must be an int in 1..3650"),
])
def test_bad_requests_are_refused_and_change_nothing(tmp_path, capsys, argv, problem):
    root = tmp_path / "fleet"
    assert main(["secure", "init", str(root), "--uavs", "uav1"]) == 0
    files = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(["secure", "init", str(root), *argv]) == 2
    assert problem in capsys.readouterr().err
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file() if p.name != "fleet.json"} == {
        p: c for p, c in files.items() if p.name != "fleet.json"}
    assert json.loads((root / "fleet.json").read_text())["uavs"] == ["uav1"]


def test_a_folder_of_something_else_is_never_touched(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert main(["secure", "init", str(tmp_path), "--uavs", "uav1"]) == 2
    assert "not empty and holds no fleet.json" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",)))
    (root / "ca" / "ca.key").unlink()
    with pytest.raises(ValueError, match="ca.key is missing"):
        provision(root, FleetPlan(uavs=("uav2",)))
    assert not (root / "uavs" / "uav2").exists()


_IDS = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,15}", fullmatch=True).filter(
    lambda s: s.casefold() not in ("joint", "fusion", "router"))


@settings(max_examples=60)
@given(st.lists(_IDS, min_size=1, max_size=6, unique_by=str.casefold),
       st.sampled_from(["cert_common_names", "usernames"]))
def test_acl_gives_each_uav_only_its_own_keys(uavs, field):
    acl = access_control(FleetIdentities(tuple(uavs), ()), subject_field=field)
    rules = {r["id"]: r for r in acl["rules"]}
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules)
    for uav in uavs:
        (policy,) = [p for p in acl["policies"] if p["subjects"] == [f"uav:{uav}"]]
        (subject,) = [s for s in acl["subjects"] if s["id"] == f"uav:{uav}"]
        assert subject[field] == [uav]
        ingress_puts = [k for r in policy["rules"] for k in rules[r]["key_exprs"]
                        if rules[r]["flows"] == ["ingress"] and {"put", "delete"} & set(rules[r]["messages"])]
        assert ingress_puts == [f"uavmm/v1/uav/{uav}/**"]
        tokens = [k for r in policy["rules"] for k in rules[r]["key_exprs"]
                  if rules[r]["flows"] == ["ingress"] and "liveliness_token" in rules[r]["messages"]]
        assert tokens == [f"uavmm/v1/uav/{uav}/alive"]
        for r in policy["rules"]:  # nothing else a UAV sends may be a put, a queryable or a token
            if rules[r]["flows"] == ["ingress"] and r not in (f"{uav}-put", f"{uav}-alive"):
                assert not {"put", "delete", "declare_queryable", "liveliness_token", "reply"} & set(
                    rules[r]["messages"])
    for rule in acl["rules"]:
        assert set(rule["messages"]) <= set(ACL_MESSAGES) and rule["permission"] == "allow"
    conf = zenoh.Config()
    conf.insert_json5("access_control", json.dumps(acl))  # Zenoh accepts the section


def test_acl_rejects_a_bad_subject_field_and_prefix():
    with pytest.raises(ValueError, match="subject_field"):
        access_control(FleetIdentities(("uav1",)), subject_field="zids")
    with pytest.raises(ValueError, match="prefix chunk"):
        access_control(FleetIdentities(("uav1",)), prefix="uavmm/**")


@pytest.mark.parametrize(("argv", "problem"), [
    (["--uavs", "uav1", "--days", "0"], "days must be an int in 1..3650, got 0"),
    (["--uavs", "uav1", "--days", "5000"], "days must be an int in 1..3650, got 5000"),
    (["--uavs", "u" * 65], "at most 64 characters"),
    (["--uavs", "uav1,router"], "repeated: router"),
    (["--uavs", "uav1", "--server-host", "ground.local:7447"], "'ground.local:7447' is not a host name"),
    (["--uavs", "uav1", "--server-host", "grönd.local"], "'grönd.local' is not a host name"),
    (["--uavs", "uav1", "--server-host", "*.example.org"], "'*.example.org' is not a host name"),
    (["--uavs", "uav1", "--server-host", "[::1]"], "'[::1]' is not a host name"),
    (["--uavs", "uav1", "--server-host", "ground..local"], "'ground..local' is not a host name"),
])
def test_a_refused_new_fleet_writes_nothing(tmp_path, capsys, argv, problem):
    """Refused before a byte is written, so the corrected command works on the same folder."""
    root = tmp_path / "fleet"
    assert main(["secure", "init", str(root), *argv]) == 2
    assert problem in capsys.readouterr().err
    assert not root.exists()
    assert main(["secure", "init", str(root), "--uavs", "uav1"]) == 0


@pytest.mark.parametrize("host", ["ground.local", "fusion", "fusion_server", "10.0.0.2", "fd00::2",
                                  "a" * 63 + ".example"])
def test_server_hosts_go_into_the_certificate_and_the_endpoint(tmp_path, host):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",), server_hosts=(host,)))
    names = _verify(root / "fusion" / "cert.pem", root / "ca" / "ca.pem").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert [str(getattr(n.value, "compressed", n.value)) for n in names] == [host]
    shown = f"[{host}]" if ":" in host else host
    assert _json5(root / "uavs" / "uav1" / "zenoh.json5")["connect"]["endpoints"] == [f"tls/{shown}:7447"]


_SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


@settings(max_examples=150)
@given(st.one_of(st.text(max_size=70), st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,70}", fullmatch=True),
                 st.sampled_from(["*", "a/b", "$x", "a b", "..", ".", "-a", "uav1/**", "joint", "fusion", "router"])))
def test_an_identity_is_a_safe_id_of_at_most_64_characters(identity):
    """Accepted exactly when it is one key chunk, a file name and a certificate common name; else a
    ValueError naming the field."""
    assume(identity != "uav0")
    safe = _SAFE_ID.fullmatch(identity) is not None and identity not in ("joint", "fusion", "router")
    for field in ("uavs", "operators"):
        try:
            FleetIdentities(("uav0",) if field == "operators" else (identity,),
                            (identity,) if field == "operators" else ())
        except ValueError as exc:
            assert not safe and (field in str(exc) or "repeated" in str(exc)), str(exc)
        else:
            assert safe
            assert identity not in (".", "..") and "/" not in identity
            cert = issue(new_ca("test CA"), identity)  # a certificate common name X.509 accepts
            assert certificate_common_name(cert.certificate_pem) == identity


def test_days_beyond_what_the_ca_has_left_are_refused(tmp_path):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",), days=3650))  # a new CA: its full 10 years
    ca = x509.load_pem_x509_certificate((root / "ca" / "ca.pem").read_bytes())
    leaf = x509.load_pem_x509_certificate((root / "uavs" / "uav1" / "cert.pem").read_bytes())
    assert leaf.not_valid_after_utc <= ca.not_valid_after_utc  # never valid beyond its CA
    keys = {p: p.read_bytes() for p in root.rglob("*") if p.name in ("key.pem", "cert.pem", "ca.key", "http-token")}
    (root / "ca" / "ca.pem").write_bytes(pem_certificate(_aged(root, days_left=100)))
    with pytest.raises(ValueError, match=r"valid until .* 100 days from now, too short for the new certificates of "
                                         r"uav2: give days of at most 100"):
        provision(root, FleetPlan(uavs=("uav2",), days=825))
    assert not (root / "uavs" / "uav2").exists()
    provision(root, FleetPlan(uavs=("uav2",), days=100))
    assert {p: p.read_bytes() for p in keys} == keys


def test_a_usrpwd_fleet_adds_without_certificates_whatever_the_ca_has_left(tmp_path):
    # review probe: a usrpwd fleet whose CA had 300 days left refused adding a UAV at the default --days 825,
    # though a UAV or operator there gets a password, no certificate
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",), auth="usrpwd"))
    (root / "ca" / "ca.pem").write_bytes(pem_certificate(_aged(root, days_left=300)))
    result = provision(root, FleetPlan(uavs=("uav2",), operators=("op2",), auth="usrpwd"))
    assert set(result.added) == {"uav2", "op2"} and not (root / "uavs" / "uav2" / "cert.pem").exists()
    other = tmp_path / "other"  # with mtls the new UAV needs a certificate: refused
    provision(other, FleetPlan(uavs=("uav1",)))
    (other / "ca" / "ca.pem").write_bytes(pem_certificate(_aged(other, days_left=300)))
    with pytest.raises(ValueError, match="too short for the new certificates of uav3"):
        provision(other, FleetPlan(uavs=("uav3",)))


def test_user_names_of_a_usrpwd_fleet_are_not_bound_to_a_common_names_length(tmp_path):
    # review probe: a usrpwd fleet made with a 70-character UAV id (a user name, no certificate) could no longer be
    # extended: every re-run refused it as "a certificate common name"
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("u" * 70,), auth="usrpwd"))
    assert "uav2" in provision(root, FleetPlan(uavs=("uav2",), auth="usrpwd")).added
    with pytest.raises(ValueError, match="at most 64 characters"):
        FleetPlan(uavs=("u" * 70,), auth="mtls")


def _aged(root: Path, days_left: int) -> x509.Certificate:
    """The fleet's CA certificate re-signed (same key and name) to end ``days_left`` days (and an hour) from now."""
    key = serialization.load_pem_private_key((root / "ca" / "ca.key").read_bytes(), password=None)
    ca = x509.load_pem_x509_certificate((root / "ca" / "ca.pem").read_bytes())
    now = dt.datetime.now(dt.timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(ca.subject).issuer_name(ca.subject).public_key(ca.public_key())
               .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(days=3000))
               .not_valid_after(now + dt.timedelta(days=days_left, hours=1)))
    for extension in ca.extensions:
        builder = builder.add_extension(extension.value, extension.critical)
    return builder.sign(key, hashes.SHA256())  # type: ignore[arg-type]


def test_a_damaged_fleet_is_refused_before_writing(tmp_path):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1", "uav2")))
    (root / "uavs" / "uav1" / "key.pem").unlink()  # its certificate is still there, its config names the key
    files = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match=r"uavs/uav1 holds cert.pem but no key.pem: .*delete cert.pem"):
        provision(root, FleetPlan(uavs=("uav3",)))
    (root / "ca" / "ca.pem").rename(root / "ca" / "ca.pem.bak")
    with pytest.raises(ValueError, match=r"ca/ca.pem is missing"):
        provision(root, FleetPlan(uavs=("uav3",)))
    (root / "ca" / "ca.pem.bak").rename(root / "ca" / "ca.pem")
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == files
    (root / "uavs" / "uav1" / "cert.pem").unlink()  # both gone: the documented way to renew an identity
    provision(root, FleetPlan(uavs=("uav3",)))
    assert certificate_common_name((root / "uavs" / "uav1" / "cert.pem").read_bytes()) == "uav1"
    assert (root / "uavs" / "uav1" / "cert.pem").read_bytes() != files[root / "uavs" / "uav1" / "cert.pem"]


def test_a_withdrawn_rest_token_stays_withdrawn_until_named_again(tmp_path, server_factory):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",), operators=("alice", "bob")))
    tokens_file = root / "fusion" / "http-tokens"
    bob = (root / "operators" / "bob" / "http-token").read_text().strip()
    # docs/deploy.md's revocation: delete bob's line
    tokens_file.write_text("".join(f"{line}\n" for line in tokens_file.read_text().splitlines()
                                   if not line.startswith("bob:")))
    result = provision(root, FleetPlan(uavs=("uav2",), operators=()))  # adding a UAV later
    assert [t.name for t in read_token_file(tokens_file)] == ["alice"]
    assert result.without_token == ("bob",)
    server = server_factory(http_tokens=read_token_file(tokens_file))
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0) as http:
        for token in (bob, (root / "operators" / "bob" / "http-token").read_text().strip()):
            assert http.get("/v1/uavs", headers={"Authorization": f"Bearer {token}"}).status_code == 401
    result = provision(root, FleetPlan(uavs=("uav2",), operators=("bob",)))  # named again: a new token
    assert result.without_token == ()
    new = (root / "operators" / "bob" / "http-token").read_text().strip()
    assert new != bob and ("bob", new) in {(t.name, t.token) for t in read_token_file(tokens_file)}


def test_private_files_are_written_0600_whatever_the_umask_and_never_through_a_planted_file(tmp_path):
    root = tmp_path / "fleet"
    provision(root, FleetPlan(uavs=("uav1",)))
    outside = tmp_path / "outside.pem"
    outside.write_text("")
    (root / "uavs" / "uav2").mkdir(mode=0o700)
    for name in ("key.pem.tmp", f".key.pem.{os.getpid()}.tmp"):  # the temporary names, old and new
        (root / "uavs" / "uav2" / name).symlink_to(outside)
    old = os.umask(0)
    try:
        provision(root, FleetPlan(uavs=("uav2",), operators=()))
    finally:
        os.umask(old)
    assert outside.read_text() == ""  # the new private key did not go through the link
    key = root / "uavs" / "uav2" / "key.pem"
    assert not key.is_symlink() and stat.S_IMODE(key.stat().st_mode) == 0o600
    assert b"PRIVATE KEY" in key.read_bytes()
    assert not [p for p in root.rglob("*.tmp") if not p.is_symlink()]  # no temporary of ours left behind


def test_identities_differing_only_in_case_are_refused(tmp_path, capsys):
    """uav1 and UAV1 were both taken: one folder on a case-insensitive file system (macOS, Windows), where the
    second's keys would overwrite the first's."""
    with pytest.raises(ValueError, match="differ in more than case.*(uav1 and UAV1|UAV1 and uav1)"):
        FleetPlan(uavs=("uav1", "UAV1"))
    root = tmp_path / "fleet"
    assert main(["secure", "init", str(root), "--uavs", "uav1"]) == 0
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    assert main(["secure", "init", str(root), "--uavs", "UAV1"]) == 2  # added to the folder's uav1
    assert "differ in more than case" in capsys.readouterr().err
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before
    with pytest.raises(ValueError, match="differ in more than case"):
        FleetPlan(uavs=("Fusion",))

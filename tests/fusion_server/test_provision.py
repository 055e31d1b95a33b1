"""`uavmm secure init`: the files, their permissions, the certificates and ACL they hold, re-runs that add
identities without touching existing keys, and refusals that write nothing."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_server.acl import ACL_MESSAGES, FleetIdentities, access_control
from fusion_server.http_auth import read_token_file
from fusion_server.provision import FleetPlan, provision
from shared.pki import certificate_common_name
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


_IDS = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,15}", fullmatch=True).filter(lambda s: s not in ("joint", "fusion"))


@settings(max_examples=60)
@given(st.lists(_IDS, min_size=1, max_size=6, unique=True), st.sampled_from(["cert_common_names", "usernames"]))
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

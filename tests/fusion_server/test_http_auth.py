"""REST bearer tokens: the real app over HTTP refuses data without a valid token, keeps the page shell and
/healthz public, counts refusals; settings refuse an open API beyond loopback; the token file parser."""

from __future__ import annotations

import argparse
from pathlib import Path

import httpx
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.config import FusionSettings
from fusion_server.http_auth import HttpToken, is_loopback_host, read_token_file
from tests.fusion_server.fake_agent import TILE_X, TILE_Y, blob
from tests.netutil import wait_until

TOKEN = "s3cret-token-for-the-tests-0123456789"
OTHER = "another-operator-token-abcdefghij"


@pytest.fixture
def secured(server_factory):
    server = server_factory(http_tokens=(HttpToken("alice", TOKEN), HttpToken("bob", OTHER)))
    with httpx.Client(base_url=server.url.rstrip("/"), timeout=10.0) as http:
        yield server, http


def test_data_needs_a_valid_token(secured, agent_factory):
    server, http = secured
    agent = agent_factory("uav1")
    agent.state()
    agent.tile(blob(10, 10))
    wait_until(lambda: server.joint.tiles())
    for path in ("/v1/uavs", "/v1/objects", "/v1/tracks", "/v1/joint/tiles", "/metrics",
                 f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png", "/v1/map?cls=person&bbox=9.26,47.66,9.28,47.68",
                 "/v1/no-such-endpoint"):
        response = http.get(path)
        assert response.status_code == 401, path
        assert response.headers["www-authenticate"].startswith("Bearer")
        assert "bearer token" in response.json()["detail"]
        assert http.get(path, headers={"Authorization": "Bearer wrong-token-wrong-token"}).status_code == 401
        assert http.get(path, headers={"Authorization": f"Basic {TOKEN}"}).status_code == 401
    ok = {"Authorization": f"Bearer {TOKEN}"}
    assert [u["id"] for u in http.get("/v1/uavs", headers=ok).json()] == ["uav1"]
    assert http.get("/v1/uavs", headers={"Authorization": f"Bearer {OTHER}"}).status_code == 200  # any listed token
    assert http.get("/v1/no-such-endpoint", headers=ok).status_code == 404  # authenticated, then routed
    # an <img> tile (the page) and map viewers pass it as access_token
    png = http.get(f"/v1/tiles/person/18/{TILE_X}/{TILE_Y}.png", params={"access_token": TOKEN})
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    metrics = http.get("/metrics", headers=ok).text
    assert 'uavmm_fusion_http_denied_total{reason="no_token"} 16' in metrics
    assert 'uavmm_fusion_http_denied_total{reason="bad_token"} 8' in metrics


def test_the_page_shell_schema_and_healthz_stay_public(secured):
    _, http = secured
    for path in ("/", "/healthz", "/static/map.js", "/openapi.json"):
        assert http.get(path).status_code == 200, path
    assert http.get("/healthz").json()["status"] in ("ok", "degraded")
    page = http.get("/static/map.js").text
    assert "access_token" in page and "Authorization" in page  # the page passes its token on
    # the schema says which operations answer 401 (the contract audit: none was declared)
    paths = http.get("/openapi.json").json()["paths"]
    assert "401" in paths["/v1/map"]["get"]["responses"] and "401" in paths["/metrics"]["get"]["responses"]
    assert "401" not in paths["/healthz"]["get"]["responses"]
    assert http.head("/healthz").status_code == 200


def test_without_tokens_the_loopback_api_is_open(server_factory):
    server = server_factory()
    with httpx.Client(base_url=server.url) as http:
        assert http.get("/v1/uavs").status_code == 200


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.10.1", "ground-station"])
def test_settings_refuse_an_open_api_beyond_loopback(host):
    with pytest.raises(ValueError, match="--http-token-file FILE or UAVMM_HTTP_TOKEN.*--insecure-public"):
        FusionSettings(http_host=host, db_path=None)
    assert FusionSettings(http_host=host, db_path=None, insecure_public=True).insecure_public
    assert FusionSettings(http_host=host, db_path=None, http_tokens=(HttpToken("x", TOKEN),)).http_tokens


@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.8.9.10", True), ("localhost", True), ("::1", True), ("[::1]", True),
    ("0.0.0.0", False), ("::", False), ("10.0.0.1", False), ("example.org", False), ("", False)])
def test_is_loopback_host(host, loopback):
    assert is_loopback_host(host) is loopback


def _fusion_args(tmp_path: Path, http: str, **flags) -> argparse.Namespace:
    from uavmm.cli import build_parser

    argv = ["fusion", "--http", http, "--no-db"]
    for name, value in flags.items():
        argv += [f"--{name.replace('_', '-')}"] + ([] if value is True else [str(value)])
    return build_parser().parse_args(argv)


def test_cli_generates_a_token_beyond_loopback_and_reads_file_and_env(tmp_path, monkeypatch):
    from uavmm.cmd_fusion import settings_from_args

    monkeypatch.delenv("UAVMM_HTTP_TOKEN", raising=False)
    generated = settings_from_args(_fusion_args(tmp_path, "0.0.0.0:8000")).http_tokens
    assert len(generated) == 1 and generated[0].name == "generated" and len(generated[0].token) >= 32
    assert settings_from_args(_fusion_args(tmp_path, "127.0.0.1:8000")).http_tokens == ()
    assert settings_from_args(_fusion_args(tmp_path, "0.0.0.0:8000", insecure_public=True)).http_tokens == ()
    monkeypatch.setenv("UAVMM_HTTP_TOKEN", TOKEN)
    assert settings_from_args(_fusion_args(tmp_path, "0.0.0.0:8000")).http_tokens == (
        HttpToken("UAVMM_HTTP_TOKEN", TOKEN),)
    monkeypatch.setenv("UAVMM_HTTP_TOKEN", "short")
    with pytest.raises(ValueError, match="UAVMM_HTTP_TOKEN: .* at least 16 characters"):
        settings_from_args(_fusion_args(tmp_path, "0.0.0.0:8000"))
    tokens = tmp_path / "tokens"
    tokens.write_text(f"# operators\nalice:{TOKEN}\n\n{OTHER}\n")
    tokens.chmod(0o600)
    read = settings_from_args(_fusion_args(tmp_path, "0.0.0.0:8000", http_token_file=tokens)).http_tokens
    assert read == (HttpToken("alice", TOKEN), HttpToken("line 4", OTHER))


@pytest.mark.parametrize(("text", "problem"), [
    ("", "holds no token"), ("# only a comment\n\n", "holds no token"), ("alice:short\n", r":1: .*at least 16"),
    (f"ok:{TOKEN}\nbob:has a space in it 0123456789\n", r":2: .*without spaces")])
def test_token_file_errors_name_the_file_and_line(tmp_path, text, problem):
    path = tmp_path / "tokens"
    path.write_text(text)
    with pytest.raises(ValueError, match=problem):
        read_token_file(path)
    with pytest.raises(ValueError, match="cannot read the token file"):
        read_token_file(tmp_path / "missing")


_NAMES = st.from_regex(r"[a-z][a-z0-9_-]{0,11}", fullmatch=True)
_TOKENS = st.from_regex(r"[A-Za-z0-9_\-]{16,64}", fullmatch=True)


@given(st.lists(st.tuples(_NAMES, _TOKENS), min_size=1, max_size=6), st.sampled_from(["\n", "\r\n"]),
       st.booleans())
def test_token_file_round_trip(tmp_path_factory, entries, newline, comments):
    path = tmp_path_factory.mktemp("tokens") / "tokens"
    lines = [f"{name}:{token}" for name, token in entries]
    if comments:
        lines = ["# header", *(f"  {line}  " for line in lines), ""]
    path.write_bytes(newline.join(lines).encode())
    path.chmod(0o600)
    assert read_token_file(path) == tuple(HttpToken(name, token) for name, token in entries)
    assert TOKEN not in repr(HttpToken("x", TOKEN))  # the secret stays out of logs

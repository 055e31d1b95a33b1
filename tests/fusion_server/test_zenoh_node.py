"""The Zenoh side with real sessions: joint publications, late joiners, malformed floods, usrpwd."""

import json
import os
import shutil
import subprocess
import threading
import time

import httpx
import msgpack
import numpy as np
import pytest
import zenoh

from shared.keys import track_region
from shared.messages import decode_joint_tracks
from shared.tilecodec import decode_tile
from tests.fusion_server.fake_agent import (
    GRID,
    KEYS,
    LAT,
    LON,
    TILE_X,
    TILE_Y,
    FakeAgent,
    blob,
    client_config,
)
from tests.netutil import wait_until


class Collector:
    """Subscriber callback that keeps every sample (key, payload bytes)."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def keys(self) -> list[str]:
        with self.lock:
            return [k for k, _ in self.samples]


def test_agents_receive_joint_tiles_and_an_empty_tile_when_coverage_ends(server, agent_factory):
    agent = agent_factory("uav-a")
    seen = Collector()
    sub = agent.session.declare_subscriber(KEYS.joint_tiles_all(), seen)
    time.sleep(0.2)
    agent.tile(blob(50, 50))
    key = KEYS.joint_tile("person", 18, TILE_X, TILE_Y)
    wait_until(lambda: key in seen.keys())
    first = decode_tile(seen.samples[0][1])
    assert first.uav == "joint" and first.values[50, 50] == pytest.approx(0.8, abs=0.003)
    wait_until(lambda: len(seen.keys()) >= 2, timeout_s=3.0)  # TTL is 1 s
    last = decode_tile(seen.samples[-1][1])
    assert not last.values.any() and last.seq > first.seq
    sub.undeclare()


def test_a_uav_whose_footprint_misses_a_cell_does_not_dilute_it(server, agent_factory):
    seen_by_a = blob(50, 50) + blob(200, 200)
    a, b = agent_factory("uav-a"), agent_factory("uav-b")
    seen = Collector()
    sub = a.session.declare_subscriber(KEYS.joint_tiles_all(), seen)
    time.sleep(0.2)
    # b looks at cells 170..230 of the tile only (its state message's footprint) and sees nothing there
    gx = np.array([170, 230, 230, 170]) + TILE_X * GRID.n
    gy = np.array([170, 170, 230, 230]) + TILE_Y * GRID.n
    b.state(footprint=np.column_stack(GRID.cell_to_latlon(gx, gy)))
    b.tile(np.zeros((GRID.n, GRID.n), np.float32))
    a.tile(seen_by_a)

    def fused() -> tuple[np.ndarray] | None:
        with seen.lock:
            samples = list(seen.samples)
        for _, payload in reversed(samples):
            msg = decode_tile(payload)
            if 0 < msg.values[200, 200] < 0.6:
                return (msg.values,)
        return None

    (values,) = wait_until(fused)
    assert values[200, 200] == pytest.approx(0.4, abs=0.005)  # b covers it: "I look here and see nothing"
    assert values[50, 50] == pytest.approx(0.8, abs=0.005)  # b does not see it: a's value stands
    sub.undeclare()


def test_late_joiner_gets_the_joint_map_and_tracks_at_once(server, agent_factory):
    agent = agent_factory("uav-a")
    agent.tile(blob(50, 50))
    agent.tile(blob(20, 20), x=TILE_X + 1)
    agent.tracks([(3, "person", LAT, LON)])
    wait_until(lambda: len(server.joint.tiles()) == 2 and len(server.tracker) == 1)
    time.sleep(0.3)  # the joint tracks message is rate-limited
    region = KEYS.region_tracks(*track_region(18, TILE_X, TILE_Y))

    late = FakeAgent("late", f"tcp/{server.settings.zenoh.listen[0].split('/', 1)[1]}", alive=False)
    try:
        # the region's tracks are published (and so held for queries) twice a second
        wait_until(lambda: [r for r in late.session.get(region, timeout=2.0) if r.ok is not None],
                   what="the region's tracks")
        t0 = time.monotonic()
        replies = [r.ok for r in late.session.get(KEYS.joint_all(), timeout=5.0) if r.ok is not None]
        elapsed = time.monotonic() - t0
        keys = sorted(str(s.key_expr) for s in replies)
        # joint/** is DESIGN.md's late-join answer exactly: the joint tiles and the global tracks
        assert keys == sorted([KEYS.joint_tile("person", 18, TILE_X, TILE_Y),
                               KEYS.joint_tile("person", 18, TILE_X + 1, TILE_Y), KEYS.joint_tracks()])
        region_replies = [r.ok for r in late.session.get(KEYS.region_all(), timeout=5.0) if r.ok is not None]
        assert [str(s.key_expr) for s in region_replies] == [region]
        assert elapsed < 2.0
        tracks = next(s for s in replies if str(s.key_expr) == KEYS.joint_tracks())
        joint = decode_joint_tracks(tracks.payload.to_bytes())
        assert [t.members for t in joint.tracks] == [(("uav-a", 3),)]
        only_tiles = list(late.session.get(KEYS.joint_tiles_all(), timeout=5.0))
        assert len(only_tiles) == 2
    finally:
        late.close()


def _malformed(i: int, rng: np.random.Generator) -> tuple[str, bytes]:
    good_key = KEYS.uav_tile("evil", "person", 18, TILE_X, TILE_Y)
    kind = i % 10
    if kind == 0:
        return good_key, rng.bytes(int(rng.integers(0, 200)))
    if kind == 1 and i % 20 == 1:
        return KEYS.uav_state("evil"), msgpack.packb({"v": 1, "uav": "evil", "t": "now"})
    if kind == 1:
        return good_key, msgpack.packb({"v": 1, "uav": "evil", "cls": "person", "z": "18", "x": TILE_X, "y": TILE_Y,
                                        "n": 256, "t": 1.0, "seq": 1, "val": b""}, use_bin_type=True)
    if kind == 2:  # mismatched uav: a UAV may only publish under its own key
        return KEYS.uav_tracks("evil"), msgpack.packb({"v": 1, "uav": "victim", "t": 1.0, "tracks": []})
    if kind == 3:  # wrong key shapes
        return f"uavmm/v1/uav/evil/tiles/person/18/{i}", b"x"
    if kind == 4:
        return "uavmm/v1/uav/evil/unknown", b"x"
    if kind == 5:  # tile fields that disagree with the key
        payload = msgpack.packb({"v": 1, "uav": "evil", "cls": "person", "z": 18, "x": 0, "y": 0, "n": 256, "t": 1.0,
                                 "seq": i, "val": b"\x00" * 65536}, use_bin_type=True)
        return good_key, payload
    if kind == 6:
        return good_key, msgpack.packb({"v": 99})
    if kind == 7:
        return KEYS.uav_tracks("evil"), msgpack.packb({"v": 1, "uav": "evil", "t": 1.0, "tracks": [{"id": -1}]})
    if kind == 8:
        return good_key, msgpack.packb({"v": 1, "uav": "evil", "cls": "person", "z": 18, "x": TILE_X, "y": TILE_Y,
                                        "n": 256, "t": float("inf"), "seq": 1, "val": b""}, use_bin_type=True)
    return "uavmm/v1/uav/evil/alive", b"not a token"


def test_ten_thousand_malformed_messages_leave_the_server_up_and_counted(server_factory, http_of, agent_factory):
    # rate limits off: this test is about validation (test_hostile.py floods with them on)
    server = server_factory(ttl_s=1.0, uav_max_msgs_per_s=1e9, uav_max_bytes_per_s=1e12)
    http = http_of(server)
    attacker = agent_factory("evil")
    rng = np.random.default_rng(0)
    sent = 0
    for i in range(10_000 - 10):
        attacker.put(*_malformed(i, rng))
        sent += 1
    huge = rng.bytes(2 * 1024 * 1024)
    for _ in range(10):  # huge payloads
        attacker.put(KEYS.uav_tile("evil", "person", 18, TILE_X, TILE_Y), huge)
        sent += 1
    good = agent_factory("good")
    good.tile(blob(30, 30))

    def total_rejected() -> int:
        return sum(server.metrics.rejected_by_reason().values())

    try:  # 1 s alone; a loaded 2-core CI machine has taken longer (a bound, not a wait: it ends when all are in)
        wait_until(lambda: total_rejected() >= sent, timeout_s=120.0)
    except AssertionError as error:  # seen once in CI under load (stop 54) with no count behind: name it
        raise AssertionError(f"{total_rejected()} of {sent} rejected: {server.metrics.rejected_by_reason()}, "
                             f"skipped {server.node.skipped}, inbox {len(server.node._inbox)}") from error
    assert total_rejected() == sent
    wait_until(lambda: server.joint.get(("person", 18, TILE_X, TILE_Y)) is not None)
    reasons = server.metrics.rejected_by_reason()
    for reason in ("not_msgpack", "bad_type", "missing_field", "out_of_range", "not_a_map", "uav_mismatch",
                   "bad_key", "tile_mismatch", "bad_version", "non_finite", "too_large", "unexpected_key"):
        assert reasons.get(reason, 0) > 0, reason
    text = http.get("/metrics").text
    assert 'uavmm_fusion_rejected_total{kind="tile",reason="too_large"} 10' in text
    assert 'reason="uav_mismatch"' in text
    assert http.get("/healthz").json()["status"] == "ok"
    # the attacker never became a UAV with tiles; the good agent did
    assert server.joint.get(("person", 18, TILE_X, TILE_Y)).uavs == ("good",)


@pytest.fixture
def credentials(tmp_path):
    dictionary = tmp_path / "users.txt"
    dictionary.write_text("uav-a:right-password\nfusion:server-password\n")
    config = tmp_path / "fusion.json5"
    config.write_text(json.dumps({"transport": {"auth": {"usrpwd": {
        "user": "fusion", "password": "server-password", "dictionary_file": str(dictionary)}}}}))
    os.chmod(dictionary, 0o600)
    return config


@pytest.mark.parametrize("mode", ["router", "peer"])
def test_usrpwd_a_client_with_a_wrong_password_cannot_publish(server_factory, zenoh_port, credentials, mode):
    server = server_factory(config_file=credentials, cfg=(f'mode:"{mode}"',))
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(endpoint, user="uav-a", password="wrong"))
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(endpoint))  # no credentials at all
    # a peer that opens without connecting (no exit_on_failure) reaches nobody either
    conf = client_config(endpoint, user="uav-a", password="wrong")
    conf.insert_json5("connect/exit_on_failure", "false")
    with zenoh.open(conf) as session:
        for _ in range(5):
            session.put(KEYS.uav_tile("uav-a", "person", 18, TILE_X, TILE_Y), b"\x80")
        time.sleep(0.5)
    assert server.metrics.rejected_by_reason() == {} and server.joint.tiles() == []
    agent = FakeAgent("uav-a", endpoint, user="uav-a", password="right-password")
    try:
        agent.tile(blob(5, 5))
        wait_until(lambda: server.joint.get(("person", GRID.z, TILE_X, TILE_Y)) is not None)
    finally:
        agent.close()
    with httpx.Client(base_url=server.url) as http:
        assert http.get("/v1/uavs").json()[0]["id"] == "uav-a"


def _make_certificates(folder) -> None:
    """A test CA and a server certificate for localhost / 127.0.0.1, made with the openssl CLI."""
    (folder / "ext.cnf").write_text("subjectAltName = DNS:localhost, IP:127.0.0.1\n")
    steps = [
        ["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
         "-subj", "/CN=uavmm-test-ca"],
        ["req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
         "-subj", "/CN=localhost"],
        ["x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out",
         "server.pem", "-days", "2", "-extfile", "ext.cnf"],
    ]
    for args in steps:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True, timeout=60)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make certificates")
def test_tls_only_tls_clients_that_trust_the_ca_reach_the_server(server_factory, zenoh_port, tmp_path):
    _make_certificates(tmp_path)
    config = tmp_path / "fusion-tls.json5"
    config.write_text(json.dumps({"transport": {"link": {"tls": {
        "listen_private_key": str(tmp_path / "server.key"), "listen_certificate": str(tmp_path / "server.pem")}}}}))
    server = server_factory(config_file=config, listen=f"tls/127.0.0.1:{zenoh_port}")
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(f"tcp/127.0.0.1:{zenoh_port}"))  # plain TCP
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(f"tls/localhost:{zenoh_port}"))  # TLS without trusting the CA
    agent = FakeAgent("uav-tls", f"tls/localhost:{zenoh_port}",
                      extra={"transport/link/tls/root_ca_certificate": str(tmp_path / "ca.pem")})
    try:
        agent.tile(blob(5, 5))
        wait_until(lambda: server.joint.get(("person", GRID.z, TILE_X, TILE_Y)) is not None)
    finally:
        agent.close()

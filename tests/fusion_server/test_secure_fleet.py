"""The fleet files of `uavmm secure init` in real Zenoh sessions: each UAV puts only on its own keys, only
the fusion identity on the joint keys, strangers cannot connect, with the server as router or behind one."""

from __future__ import annotations

import json
import time
from pathlib import Path

import httpx
import pytest
import zenoh

from fusion_server.provision import FleetPlan, provision
from tests.fusion_server.fake_agent import GRID, KEYS, TILE_X, TILE_Y, FakeAgent, blob, client_config
from tests.netutil import wait_until

AUTH = ["mtls", "usrpwd"]
TILE = ("person", GRID.z, TILE_X, TILE_Y)


def fleet(tmp_path: Path, port: int, auth: str) -> Path:
    root = tmp_path / f"fleet-{auth}"
    provision(root, FleetPlan(uavs=("uav1", "uav2"), operators=("ops",), server_hosts=("localhost",),
                              port=port, auth=auth))
    return root


def identity_config(folder: Path, name: str = "zenoh.json5", **overrides) -> zenoh.Config:
    """An identity's generated config, failing fast if it cannot connect (for the tests)."""
    conf = zenoh.Config.from_file(str(folder / name))
    conf.insert_json5("connect/timeout_ms", "3000")
    conf.insert_json5("connect/exit_on_failure", "true")
    for key, value in overrides.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class Inbox:
    """Payloads received by a subscriber callback."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        self.items.append((str(sample.key_expr), sample.payload.to_bytes()))


def _server(server_factory, root: Path, port: int, ttl_s: float = 2.0, **overrides):
    return server_factory(config_file=root / "fusion" / "zenoh.json5", listen=f"tls/127.0.0.1:{port}",
                          cfg=('mode:"router"',), ttl_s=ttl_s, **overrides)


@pytest.mark.parametrize("auth", AUTH)
def test_a_uav_can_put_only_on_its_own_keys_and_never_on_the_joint_keys(server_factory, zenoh_port, tmp_path,
                                                                        auth):
    root = fleet(tmp_path, zenoh_port, auth)
    # tiles live 60 s: uav1's must still be in the joint tile when it is read after the spoofing (a 2 s TTL ran out
    # there under load, CI's two test workers), and a spoofed one, had it been taken, would be there too
    server = _server(server_factory, root, zenoh_port, ttl_s=60.0)
    uav1 = FakeAgent("uav1", None, conf=identity_config(root / "uavs" / "uav1"))
    uav2 = FakeAgent("uav2", None, conf=identity_config(root / "uavs" / "uav2"), alive=False)
    inbox = Inbox()
    subscriber = uav2.session.declare_subscriber(KEYS.joint_tiles_all(), inbox)
    try:
        def delivered():
            # put again until it arrives: a put before the routers know the subscriptions is lost (under load)
            uav1.state()
            uav1.tile(blob(20, 20, value=0.8))
            return server.joint.get(TILE) is not None and inbox.items

        wait_until(delivered, 10.0, interval_s=0.25)
        genuine = server.joint.get(TILE)
        assert genuine.uavs == ("uav1",)

        # uav1 as uav2: a tile, a state, a liveliness token; and a joint tile of its own making
        spoof = FakeAgent("uav2", None, conf=identity_config(root / "uavs" / "uav1"))  # uav1's identity
        try:
            spoof.tile(blob(100, 100, value=1.0))
            spoof.state()
            spoof.put(KEYS.joint_tile(*TILE), b"spoofed joint tile")
            spoof.put(KEYS.joint_tracks(), b"spoofed joint tracks")
            time.sleep(1.5)
        finally:
            spoof.close()
        # the server never saw any of it: nothing rejected (it was not even delivered), no uav2
        assert server.metrics.rejected_by_reason() == {}
        with httpx.Client(base_url=server.url) as http:
            ids = [u["id"] for u in http.get("/v1/uavs").json()]
        assert ids == ["uav1"]
        assert server.joint.get(TILE).uavs == ("uav1",)
        # and the other UAV never got the forged joint tile: only the server's real ones
        assert inbox.items and all(payload not in (b"spoofed joint tile", b"spoofed joint tracks")
                                   for _, payload in inbox.items)

        # uav2 with its own identity is welcome
        uav2.tile(blob(30, 30, value=0.6))
        wait_until(lambda: set(server.joint.get(TILE).uavs) == {"uav1", "uav2"}, 10.0)
    finally:
        subscriber.undeclare()
        uav1.close()
        uav2.close()


@pytest.mark.parametrize("auth", AUTH)
def test_strangers_cannot_connect(server_factory, zenoh_port, tmp_path, auth):
    root = fleet(tmp_path, zenoh_port, auth)
    _server(server_factory, root, zenoh_port)
    tls = f"tls/localhost:{zenoh_port}"
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(f"tcp/127.0.0.1:{zenoh_port}", mode="client"))  # plain TCP
    with pytest.raises(zenoh.ZError):  # TLS trusting the CA, but no certificate / password
        zenoh.open(client_config(tls, mode="client",
                                 extra={"transport/link/tls/root_ca_certificate": str(root / "fusion" / "ca.pem")}))
    other = fleet(tmp_path / "other", zenoh_port, auth)  # a valid identity of another fleet (another CA)
    with pytest.raises(zenoh.ZError):
        zenoh.open(identity_config(other / "uavs" / "uav1"))
    if auth == "usrpwd":  # the right CA and user with a wrong password
        conf = identity_config(root / "uavs" / "uav1", **{"transport/auth/usrpwd/password": "wrong-password"})
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf)
    # the fleet's own identity connects
    with zenoh.open(identity_config(root / "uavs" / "uav1")) as session:
        assert not session.is_closed()


def test_an_operator_reads_the_joint_map_and_cannot_publish(server_factory, zenoh_port, tmp_path):
    root = fleet(tmp_path, zenoh_port, "mtls")
    server = _server(server_factory, root, zenoh_port)
    uav1 = FakeAgent("uav1", None, conf=identity_config(root / "uavs" / "uav1"))
    try:
        uav1.state()
        uav1.tile(blob(20, 20))
        wait_until(lambda: server.joint.get(TILE) is not None, 10.0)
        with zenoh.open(identity_config(root / "operators" / "ops")) as operator:
            replies = [r.ok for r in operator.get(KEYS.joint_all(), timeout=3.0) if r.ok is not None]
            assert str(replies[0].key_expr).startswith(KEYS.prefix + "/joint/")  # late-joiner query answered
            states = Inbox()
            sub = operator.declare_subscriber(KEYS.uav_all(), states)
            time.sleep(0.5)
            uav1.state()
            wait_until(lambda: any(k == KEYS.uav_state("uav1") for k, _ in states.items), 5.0)
            sub.undeclare()
            operator.put(KEYS.uav_tile("uav1", *TILE), b"operator tile")
            operator.put(KEYS.joint_tile(*TILE), b"operator joint")
            time.sleep(1.0)
        assert server.metrics.rejected_by_reason() == {}
        assert server.joint.get(TILE).uavs == ("uav1",)
    finally:
        uav1.close()


def test_behind_a_router_holding_the_acl(server_factory, zenoh_port, tmp_path):
    """The router layout: the ACL in router/zenohd.json5 (a Python router session stands in for zenohd), the
    fusion server as a client with fusion/zenoh-client.json5, the UAVs dialling the router."""
    root = fleet(tmp_path, zenoh_port, "mtls")
    router_conf = zenoh.Config.from_file(str(root / "router" / "zenohd.json5"))
    router_conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{zenoh_port}"]))
    with zenoh.open(router_conf):
        server = server_factory(config_file=root / "fusion" / "zenoh-client.json5", listen="tcp/127.0.0.1:0",
                                cfg=('mode:"client"', "listen/endpoints:[]"), ttl_s=2.0)
        uav1 = FakeAgent("uav1", None, conf=identity_config(root / "uavs" / "uav1"))
        uav2 = FakeAgent("uav2", None, conf=identity_config(root / "uavs" / "uav2"), alive=False)
        inbox = Inbox()
        subscriber = uav2.session.declare_subscriber(KEYS.joint_tiles_all(), inbox)
        try:
            time.sleep(0.5)
            uav1.state()
            uav1.tile(blob(20, 20))
            wait_until(lambda: server.joint.get(TILE) is not None, 10.0)
            wait_until(lambda: inbox.items, 10.0)  # the fusion identity's joint tiles pass the router
            uav1.put(KEYS.uav_tile("uav2", *TILE), b"spoof")
            uav1.put(KEYS.joint_tile(*TILE), b"spoofed joint tile")
            time.sleep(1.0)
            assert server.metrics.rejected_by_reason() == {}
            assert all(payload != b"spoofed joint tile" for _, payload in inbox.items)
        finally:
            subscriber.undeclare()
            uav1.close()
            uav2.close()

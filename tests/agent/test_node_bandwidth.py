"""Bandwidth of one agent on the wire with ~20 objects in view: within the 100 kB/s budget per UAV,
uplink and downlink.

The bytes are counted by a TCP relay between the agent and a real fusion server (which sends the
joint tiles and tracks back), with Zenoh's same-host shared memory off on both sides (it would
bypass the socket), so they are what a radio link would carry. docs/agent.md quotes the numbers
this measures.
"""

from __future__ import annotations

import dataclasses
import socket
import threading

import numpy as np
import pytest

from agent.node import AgentNode, AgentSettings
from agent.zenoh_config import ZenohOptions
from fusion_server.config import FusionSettings
from fusion_server.server import FusionServer
from sim.scenarios import get_scenario
from sim.source import SimSource
from tests.netutil import free_port, wait_until

BUDGET_BYTES_PER_S = 100_000
SECONDS = 8.0


class ByteCountingRelay:
    """A TCP relay 127.0.0.1:port -> 127.0.0.1:target_port counting the bytes in each direction."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.up = 0  # client -> server
        self.down = 0
        self._lock = threading.Lock()
        self._listener = socket.socket()
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(8)
        self.port = self._listener.getsockname()[1]
        self._sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
                server = socket.create_connection(("127.0.0.1", self.target_port))
            except OSError:
                return
            self._sockets += [client, server]
            threading.Thread(target=self._pipe, args=(client, server, "up"), daemon=True).start()
            threading.Thread(target=self._pipe, args=(server, client, "down"), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, direction: str) -> None:
        try:
            while data := src.recv(65536):
                with self._lock:
                    setattr(self, direction, getattr(self, direction) + len(data))
                dst.sendall(data)
        except OSError:
            pass

    def close(self) -> None:
        for sock in [self._listener, *self._sockets]:
            sock.close()


def crowded_meadow(n_objects: int = 20):
    """The grass scenario with ``n_objects`` people within 30 m: all in view of its first flight."""
    scenario = get_scenario("grass")
    world = dataclasses.replace(scenario.world, n_objects=n_objects, spawn_radius_m=30.0)
    return dataclasses.replace(scenario, world=world, name=f"grass{n_objects}")


def test_one_uav_with_20_objects_in_view_stays_within_100_kB_per_s_up_and_down():
    source = SimSource(crowded_meadow(), uav_index=0, frames=int(SECONDS * 30) + 60)
    in_view = [sum(o.in_view for o in fs.objects) for fs in source.sim.frames() if fs.video_id == 1]
    assert np.mean(in_view) >= 18
    port = free_port()
    server = FusionServer(FusionSettings(
        zenoh=ZenohOptions(mode="router", listen=(f"tcp/127.0.0.1:{port}",), multicast_scouting=False,
                                 cfg=("transport/shared_memory/enabled:false",)), db_path=None))
    server.start(http=False)
    relay = ByteCountingRelay(port)
    options = ZenohOptions(connect=(f"tcp/127.0.0.1:{relay.port}",), multicast_scouting=False,
                           cfg=("transport/shared_memory/enabled:false",))
    node = AgentNode(AgentSettings(uav_id="uav1", zenoh=options, duration_s=SECONDS), source)
    try:
        summary = node.run()
        sent_tiles = summary["link"]["counts"]["sent_tile"]
        wait_until(lambda: server.metrics.received.get("tile", 0) + sum(server.metrics.rejected.values())
                   >= sent_tiles, timeout_s=10.0)
        received = dict(server.metrics.received)
    finally:
        server.close()
        relay.close()
    elapsed = summary["elapsed_s"]
    sent = summary["link"]["bytes"]
    assert summary["tiles_deferred_by_budget"] > 0  # the budget is what holds it down, not an empty map
    assert received["tile"] == sent_tiles  # the server took every tile
    assert summary["joint_tiles_applied"] > 0  # and the joint map came back
    up = relay.up / elapsed
    down = relay.down / elapsed
    print(f"\nwire up {up / 1000:.1f} kB/s, down {down / 1000:.1f} kB/s; payload kB/s: "
          + ", ".join(f"{k} {v / elapsed / 1000:.1f}" for k, v in sorted(sent.items())))
    assert up <= BUDGET_BYTES_PER_S
    assert down <= BUDGET_BYTES_PER_S
    assert sent["sent_tile"] / elapsed == pytest.approx(70_000, rel=0.25)  # the default tile budget


def test_the_map_alone_would_not_fit_without_the_budget():
    """Why the budget exists: the same flight without it sends more than the 100 kB/s budget in tiles alone."""
    from agent.pipeline import DetectionPipeline
    from agent.tile_updates import TileChangeTracker

    source = SimSource(crowded_meadow(), uav_index=0, frames=90)
    pipeline = DetectionPipeline(source.camera, source.class_names)
    clock = [0.0]
    tracker = TileChangeTracker("u", list(source.class_names.values()), pipeline.grid, min_value=0.05,
                                clock=lambda: clock[0])
    total = 0
    for frame in source.frames():
        pipeline.process(frame.boxes_xyxy, frame.scores, frame.class_ids, frame.pose, frame.t)
        clock[0] = frame.index / 30.0
        if frame.index % 6 == 0 and frame.index >= 30:  # 5 Hz, after the first second
            total += sum(len(m[3]) for m in tracker.messages(pipeline.memory, frame.t))
    assert total / 2.0 > BUDGET_BYTES_PER_S

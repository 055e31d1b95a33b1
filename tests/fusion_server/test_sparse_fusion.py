"""The fusion server at fleet rates: decode_tile_sparse agrees with decode_tile, fusion over the union
of non-zero cells equals the dense rule, batched puts, the fusion node's bounded inbox, and joint
tracks per region."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_server.joint_map import JointMap
from fusion_server.rules import FUSION_RULES, get_fusion_rule
from shared.keys import KeySpace, track_region
from shared.messages import decode_joint_tracks
from shared.tilecodec import TileDecodeError, decode_tile, decode_tile_sparse
from shared.tiles import TileGrid
from tests.fusion_server.fake_agent import GRID as GRID_FULL
from tests.fusion_server.fake_agent import LAT, LON, TILE_X, client_config
from tests.netutil import wait_until
from tests.shared.test_tilecodec import MALFORMED, mutated

N = 8
GRID = TileGrid(18, N)
KEY = ("person", 18, 100, 200)


# ---- decode_tile_sparse == decode_tile -----------------------------------------------------------
@pytest.mark.parametrize(("reason", "payload"), MALFORMED)
def test_sparse_decoder_rejects_what_the_dense_one_rejects_for_the_same_reason(reason: str, payload: bytes):
    with pytest.raises(TileDecodeError) as dense:
        decode_tile(payload)
    with pytest.raises(TileDecodeError) as sparse:
        decode_tile_sparse(payload)
    assert sparse.value.reason == dense.value.reason == reason


@settings(max_examples=300)
@given(data=st.data(), sparse=st.booleans())
def test_sparse_decoder_agrees_with_the_dense_one_on_corrupted_payloads(data: st.DataObject, sparse: bool):
    payload = bytearray(mutated(sparse=sparse))
    for _ in range(data.draw(st.integers(1, 4))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    payload = bytes(payload[: data.draw(st.integers(0, len(payload)))])
    try:
        dense = decode_tile(payload)
    except TileDecodeError as exc:
        with pytest.raises(TileDecodeError) as info:
            decode_tile_sparse(payload)
        assert info.value.reason == exc.reason
        return
    cells = decode_tile_sparse(payload)
    assert (cells.uav, cells.cls, cells.z, cells.x, cells.y, cells.n, cells.t, cells.seq) == (
        dense.uav, dense.cls, dense.z, dense.x, dense.y, dense.n, dense.t, dense.seq)
    flat = np.rint(dense.values.reshape(-1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(cells.idx, np.flatnonzero(flat))
    np.testing.assert_array_equal(cells.val, flat[cells.idx])


@settings(max_examples=200)
@given(cells=st.dictionaries(st.integers(0, N * N - 1), st.integers(0, 255), max_size=N * N),
       shuffle=st.randoms())
def test_unsorted_indices_and_zero_values_decode_to_sorted_non_zero_cells(cells: dict[int, int], shuffle):
    items = list(cells.items())
    shuffle.shuffle(items)
    idx = np.array([i for i, _ in items], dtype="<u2")
    val = np.array([v for _, v in items], dtype=np.uint8)
    record = {"v": 1, "uav": "a", "cls": "person", "z": 18, "x": 1, "y": 2, "n": N, "t": 1.0, "seq": 1,
              "idx": idx.tobytes(), "val": val.tobytes()}
    tile = decode_tile_sparse(msgpack.packb(record, use_bin_type=True))
    expected = sorted((i, v) for i, v in cells.items() if v)
    assert tile.idx.tolist() == [i for i, _ in expected]
    assert tile.val.tolist() == [v for _, v in expected]


def test_duplicate_indices_are_refused_also_unsorted():
    record = {"v": 1, "uav": "a", "cls": "person", "z": 18, "x": 1, "y": 2, "n": N, "t": 1.0, "seq": 1,
              "idx": np.array([5, 3, 5], "<u2").tobytes(), "val": bytes([1, 2, 3])}
    with pytest.raises(TileDecodeError) as info:
        decode_tile_sparse(msgpack.packb(record, use_bin_type=True))
    assert info.value.reason == "duplicate_index"


# ---- fusion over the union of non-zero cells == the dense rule -----------------------------------
layers = st.lists(st.lists(st.sampled_from([0, 0, 0, 1, 17, 128, 254, 255]), min_size=N * N, max_size=N * N),
                  min_size=2, max_size=4)


@settings(max_examples=150, deadline=None)
@given(values=layers, rule=st.sampled_from(sorted(FUSION_RULES)), data=st.data())
def test_sparse_fusion_equals_the_rule_on_dense_stacks(values, rule: str, data: st.DataObject):
    stack = np.array(values, dtype=np.uint8).reshape(-1, N, N)
    jm = JointMap(GRID, get_fusion_rule(rule), 2.0, 5.0, coverage="footprint", clock=lambda: 0.0, wall=lambda: 1e9)
    covered = np.ones_like(stack, dtype=bool)
    for k, layer in enumerate(stack):
        jm.put(f"u{k}", KEY, layer, t=1.0, seq=1, now=0.0)
        if data.draw(st.booleans(), label=f"footprint of u{k}"):  # u{k} sees columns [c0, c1) only
            c0 = data.draw(st.integers(0, N - 1))
            c1 = data.draw(st.integers(c0 + 1, N))
            gx = np.array([c0, c1, c1, c0]) + KEY[2] * N
            gy = np.array([0, 0, N, N]) + KEY[3] * N
            assert jm.put_footprint(f"u{k}", np.column_stack(GRID.cell_to_latlon(gx, gy)), now=0.0)
            covered[k] = jm._coverage_mask(f"u{k}", KEY, 0.0)
    jm.step(now=0.0)
    expected = get_fusion_rule(rule)(stack, covered)
    tile = jm.get(KEY)
    if not expected.any():
        assert tile is None or not tile.values.any()
        return
    np.testing.assert_array_equal(tile.values, expected)
    decoded = decode_tile(tile.payload)
    np.testing.assert_array_equal(np.rint(decoded.values * 255).astype(np.uint8), expected)


def test_put_many_takes_a_batch_and_reports_each_tile():
    jm = JointMap(GRID, get_fusion_rule("mean"), 2.0, 5.0, max_tiles_per_uav=1, clock=lambda: 0.0, wall=lambda: 1e9)
    idx = np.array([0, 9], dtype=np.uint16)
    val = np.array([100, 200], dtype=np.uint8)
    other = ("person", 18, 101, 200)
    reasons = jm.put_many([("a", KEY, idx, val, 1.0, 2), ("a", KEY, idx, val, 1.0, 1),
                           ("a", other, idx, val, 1.0, 1), ("b", KEY, idx, val // 2, 1.0, 1)], now=0.0)
    assert reasons == [None, "stale", "too_many_tiles", None]
    jm.step(now=0.0)
    values = jm.get(KEY).values.reshape(-1)
    assert (values[0], values[9], int(values.sum())) == (75, 150, 225)
    assert jm.get(other) is None


def test_an_unchanged_fused_tile_is_not_published_again_until_the_refresh():
    jm = JointMap(GRID, get_fusion_rule("mean"), 5.0, 100.0, refresh_s=1.0, clock=lambda: 0.0, wall=lambda: 1e9)
    layer = np.zeros((N, N), np.uint8)
    layer[2, 3] = 90
    jm.put("a", KEY, layer, t=1.0, seq=1, now=0.0)
    assert len(jm.step(now=0.0)[0]) == 1
    jm.put("a", KEY, layer, t=1.1, seq=2, now=0.1)
    assert jm.step(now=0.1)[0] == []
    jm.put("a", KEY, layer, t=2.2, seq=3, now=1.2)
    assert len(jm.step(now=1.2)[0]) == 1


# ---- the fusion node's inbox ---------------------------------------------------------------------
def test_the_node_fuses_what_its_callback_enqueued(server_factory, agent_factory):
    server = server_factory()
    agent = agent_factory("u1")
    values = np.zeros((GRID_FULL.n, GRID_FULL.n), np.float32)
    values[0, 5], values[0, 7] = 100 / 255, 200 / 255
    for x in range(3):
        agent.tile(values, x=TILE_X + x)
    assert wait_until(lambda: len(server.joint.tiles()) == 3)
    tile = server.joint.tiles()[0]
    assert tile.values.reshape(-1)[[5, 7]].tolist() == [100, 200]
    assert server.metrics.received.get("tile") == 3


def test_a_full_inbox_drops_and_counts_samples_as_overloaded(server_factory, agent_factory):
    server = server_factory()
    server.node.inbox_max = 0  # as if the fusion thread had fallen behind by a whole inbox
    agent = agent_factory("u1")
    for x in range(3):
        agent.tile(np.full((GRID_FULL.n, GRID_FULL.n), 0.5, np.float32), x=TILE_X + x)
    assert wait_until(lambda: server.metrics.rejected.get(("unknown", "overloaded"), 0) == 3)
    assert server.joint.tiles() == []
    assert 'reason="overloaded"' in server.prometheus()


def test_samples_that_waited_too_long_are_dropped_unread_and_the_wait_is_reported(server_factory, agent_factory):
    # A soak of 50 UAVs on a shared 2-core machine: the fusion thread fell behind, the inbox held up to
    # 65,536 samples (~36 s of them, RssAnon 0.43 -> 1.83 GB), and what it then fused was that old while
    # /healthz and the latency metric showed nothing.
    server = server_factory(inbox_max_age_s=1.0)
    node = server.node
    entered, gate = threading.Event(), threading.Event()
    ingest = node._ingest

    def stalled_ingest(batch):  # the fusion thread stalls in its first batch (a busy CPU, a long GC)
        entered.set()
        gate.wait(10.0)
        return ingest(batch)

    node._ingest = stalled_ingest
    agent = agent_factory("u1")
    values = np.full((GRID_FULL.n, GRID_FULL.n), 0.5, np.float32)
    try:
        agent.tile(values, x=TILE_X)
        assert entered.wait(5.0)
        agent.tile(values, x=TILE_X + 1)
        agent.tile(values, x=TILE_X + 2)
        assert wait_until(lambda: node.inbox_health()["samples"] == 2)
        time.sleep(1.2)
        inbox = server.cluster_health()["inbox"]
        assert inbox["samples"] == 2 and inbox["oldest_s"] >= 1.0
        assert "uavmm_fusion_inbox_samples 2" in server.prometheus()
    finally:
        gate.set()
    assert wait_until(lambda: server.metrics.rejected.get(("unknown", "overloaded"), 0) == 2)
    agent.tile(values, x=TILE_X + 3)  # fresh data is fused at once
    assert wait_until(lambda: {t.x for t in server.joint.tiles()} == {TILE_X, TILE_X + 3})
    assert node.inbox_health() == {"samples": 0, "oldest_s": 0.0}


# ---- joint tracks per region ---------------------------------------------------------------------
def test_joint_tracks_are_also_published_per_region_with_only_their_tracks(server_factory, agent_factory):
    server = server_factory()
    keys = KeySpace()
    got: dict[str, list[int]] = {}
    port = server.settings.zenoh.listen[0]
    with zenoh.open(client_config(port)) as session:
        sub = session.declare_subscriber(f"{keys.prefix}/region/tracks/*/*/*",
                                         lambda s: got.__setitem__(str(s.key_expr), [
                                             t.gid for t in decode_joint_tracks(s.payload.to_bytes()).tracks]))
        near = agent_factory("u1")
        far = agent_factory("u2")
        wait_until(lambda: len(server.uavs.online()) == 2)
        far_lat = LAT + 0.1  # ~11 km north: another region
        region_near = keys.region_tracks(*track_region(18, *(int(v) for v in GRID_FULL.tile_of(LAT, LON))))
        region_far = keys.region_tracks(*track_region(18, *(int(v) for v in GRID_FULL.tile_of(far_lat, LON))))
        for _ in range(3):
            near.tracks([(1, "person", LAT, LON), (2, "person", LAT + 1e-4, LON)])
            far.tracks([(1, "person", far_lat, LON)])
        wait_until(lambda: region_near in got and region_far in got, what="both regions' tracks")
        tracks = {t.gid: t for t in server.tracker.joint_message().tracks}
        assert len(tracks) == 3
        assert sorted(got[region_near]) == sorted(g for g, t in tracks.items() if t.lat < LAT + 0.05)
        assert len(got[region_far]) == 1
        sub.undeclare()


def test_states_are_forwarded_to_the_regions_their_footprint_touches(server_factory, agent_factory):
    server = server_factory()
    keys = KeySpace()
    got: list[str] = []
    with zenoh.open(client_config(server.settings.zenoh.listen[0])) as session:
        sub = session.declare_subscriber(f"{keys.prefix}/region/states/**", lambda s: got.append(str(s.key_expr)))
        agent = agent_factory("u1")
        time.sleep(0.5)
        x, y = (int(v) for v in GRID_FULL.tile_of(LAT, LON))
        region = track_region(18, x, y)
        agent.state()  # a small footprint at LAT, LON: one region
        wait_until(lambda: got, what="the forwarded state")
        assert got == [keys.region_state(*region, "u1")]
        sub.undeclare()

"""Tests of the tile message codec: round trips, sparse/dense choice and strict rejection of bad payloads."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.messages import MESSAGE_ERROR_REASONS, MessageError
from shared.tilecodec import (
    DEFAULT_MAX_TILE_BYTES,
    TileDecodeError,
    TileMessage,
    decode_tile,
    encode_tile,
    encode_tile_sparse,
    quantise,
)

QUANT_TOL = 0.5 / 255 + 1e-6


def make_msg(values: np.ndarray, **overrides: Any) -> TileMessage:
    fields: dict[str, Any] = {
        "uav": "uav1",
        "cls": "person",
        "z": 18,
        "x": 137625,
        "y": 91125,
        "n": values.shape[0],
        "t": 1.7e9,
        "seq": 7,
        "values": values,
    }
    fields.update(overrides)
    return TileMessage(**fields)


def assert_same_header(a: TileMessage, b: TileMessage) -> None:
    for name in ("uav", "cls", "z", "x", "y", "n", "t", "seq"):
        assert getattr(a, name) == getattr(b, name), name


@st.composite
def tiles(draw: st.DrawFn) -> np.ndarray:
    n = draw(st.sampled_from([1, 2, 3, 16, 31, 64, 256]))
    density = draw(st.sampled_from([0.0, 0.001, 0.05, 0.3, 0.34, 1.0]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    values = rng.random((n, n), dtype=np.float32)
    values[rng.random((n, n)) >= density] = 0.0
    if draw(st.booleans()):
        values[0, 0] = 1.0
    return values


# ---- round trips -------------------------------------------------------------------------------
@settings(max_examples=150)
@given(values=tiles(), z=st.integers(0, 24), data=st.data())
def test_round_trip_sparse_and_dense(values: np.ndarray, z: int, data: st.DataObject) -> None:
    x = data.draw(st.integers(0, 2**z - 1))
    y = data.draw(st.integers(0, 2**z - 1))
    msg = make_msg(values, z=z, x=x, y=y, seq=data.draw(st.integers(0, 2**64 - 1)))
    payload = encode_tile(msg)
    out = decode_tile(payload)
    assert_same_header(out, msg)
    assert out.values.dtype == np.float32 and out.values.shape == values.shape
    assert np.max(np.abs(out.values - values)) <= QUANT_TOL
    assert np.all((out.values == 0) == (quantise(values) == 0))
    assert np.array_equal(quantise(out.values), quantise(values))
    # the encoder picked the smaller form
    record = msgpack.unpackb(payload)
    nonzero = int(np.count_nonzero(quantise(values)))
    n = values.shape[0]
    assert ("idx" in record) == (3 * nonzero < n * n)
    assert len(record["val"]) == (nonzero if "idx" in record else n * n)


@given(values=tiles())
def test_encode_tile_sparse_matches_encode_tile(values: np.ndarray) -> None:
    msg = make_msg(values)
    q = quantise(values).ravel()
    idx = np.flatnonzero(q)
    perm = np.random.default_rng(0).permutation(idx.size)  # order must not matter
    n = values.shape[0]
    payload = encode_tile_sparse("uav1", "person", 18, 137625, 91125, n, 1.7e9, 7, idx[perm], q[idx][perm])
    assert payload == encode_tile(msg)


def test_empty_tile_is_small_and_valid() -> None:
    payload = encode_tile(make_msg(np.zeros((256, 256), np.float32)))
    assert len(payload) < 100
    out = decode_tile(payload)
    assert out.values.shape == (256, 256) and not out.values.any()


def test_full_tile_is_dense_and_at_most_64_kib_plus_header() -> None:
    payload = encode_tile(make_msg(np.ones((256, 256), np.float32)))
    assert 65536 < len(payload) < 65536 + 200
    assert "idx" not in msgpack.unpackb(payload)
    assert np.all(decode_tile(payload).values == 1.0)


def test_known_quantisation_values() -> None:
    values = np.array([[0.0, 0.5 / 255 - 1e-4], [0.5, 1.0]], dtype=np.float32)
    assert quantise(values).tolist() == [[0, 0], [128, 255]]
    record = msgpack.unpackb(encode_tile(make_msg(values)))
    assert record["v"] == 1
    # 2 non-zero cells: 6 sparse bytes vs 4 dense bytes -> dense
    assert "idx" not in record and record["val"] == bytes([0, 0, 128, 255])
    values = np.zeros((4, 4), np.float32)
    values[1, 2] = 1.0
    record = msgpack.unpackb(encode_tile(make_msg(values)))
    assert record["idx"] == (6).to_bytes(2, "little") and record["val"] == b"\xff"


def test_numpy_scalars_in_the_header_are_normalised() -> None:
    msg = make_msg(np.zeros((2, 2)), z=np.int64(18), x=np.int32(137625), seq=np.uint64(3), t=np.float32(2.5))
    assert type(msg.z) is int and type(msg.seq) is int and type(msg.t) is float
    assert msg.values.dtype == np.float32
    assert decode_tile(encode_tile(msg)).seq == 3


def test_the_grid_does_not_know_the_codec() -> None:
    # the codec builds on the grid (shared.tilecodec imports shared.tiles), never the other way round
    import shared.tiles

    assert not hasattr(shared.tiles, "TileMessage") and not hasattr(shared.tiles, "decode_tile")


# ---- constructor validation --------------------------------------------------------------------
@pytest.mark.parametrize(
    ("overrides", "reason"),
    [
        ({"values": np.full((4, 4), 1.01)}, "out_of_range"),
        ({"values": np.full((4, 4), -0.01)}, "out_of_range"),
        ({"values": np.full((4, 4), np.nan)}, "non_finite"),
        ({"values": np.zeros((4, 5))}, "bad_length"),
        ({"values": np.zeros((4, 4)), "n": 5}, "bad_length"),
        ({"values": np.array([["a"]])}, "bad_type"),
        ({"z": 25}, "bad_zoom"),
        ({"x": 2**18}, "tile_out_of_range"),
        ({"seq": -1}, "bad_seq"),
        ({"uav": "a/b"}, "bad_name"),
        ({"t": math.inf}, "non_finite"),
    ],
)
def test_tile_message_validates_itself(overrides: dict, reason: str) -> None:
    overrides.setdefault("values", np.zeros((4, 4)))
    with pytest.raises(MessageError) as info:
        make_msg(**overrides)
    assert info.value.reason == reason
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    ("idx", "val", "reason"),
    [
        ([1, 1], [3, 4], "duplicate_index"),
        ([16], [3], "index_out_of_range"),
        ([-1], [3], "index_out_of_range"),
        ([1], [256], "out_of_range"),
        ([1, 2], [3], "bad_length"),
        ([1.0], [3], "bad_type"),
        ([1], [0.5], "bad_type"),
    ],
)
def test_encode_tile_sparse_validates_arrays(idx: list, val: list, reason: str) -> None:
    with pytest.raises(MessageError) as info:
        encode_tile_sparse("u", "c", 1, 0, 0, 4, 0.0, 0, np.array(idx), np.array(val))
    assert info.value.reason == reason


# ---- strict decoding: one case per malformed field ---------------------------------------------
def valid_record(n: int = 4, sparse: bool = True) -> dict[str, Any]:
    record: dict[str, Any] = {
        "v": 1,
        "uav": "uav1",
        "cls": "person",
        "z": 3,
        "x": 5,
        "y": 2,
        "n": n,
        "t": 12.5,
        "seq": 3,
    }
    if sparse:
        record["idx"] = np.array([0, 5, n * n - 1], "<u2").tobytes()
        record["val"] = bytes([10, 20, 255])
    else:
        record["val"] = bytes(range(n * n))
    return record


def mutated(sparse: bool = True, drop: tuple[str, ...] = (), **changes: Any) -> bytes:
    record = valid_record(sparse=sparse)
    record.update(changes)
    for key in drop:
        del record[key]
    return msgpack.packb(record, use_bin_type=True)


MALFORMED: list[tuple[str, bytes]] = [
    ("not_msgpack", b""),
    ("not_msgpack", b"\xc1"),
    ("not_msgpack", b"\x85\xa1v\x01"),
    ("not_msgpack", msgpack.packb({"v": 1}) + b"\x00"),
    ("not_a_map", msgpack.packb([1, 2, 3])),
    ("not_a_map", msgpack.packb(b"bytes")),
    ("not_a_map", msgpack.packb(None)),
    ("too_large", mutated(pad=b"x" * DEFAULT_MAX_TILE_BYTES)),
    ("bad_version", mutated(v=2)),
    ("bad_version", mutated(v=0)),
    ("bad_type", mutated(v=True)),
    ("bad_type", mutated(v="1")),
    ("bad_type", mutated(uav=7)),
    ("bad_type", mutated(cls=b"person")),
    ("bad_type", mutated(z=True)),
    ("bad_type", mutated(z=3.0)),
    ("bad_type", mutated(x=None)),
    ("bad_type", mutated(y="2")),
    ("bad_type", mutated(n=False)),
    ("bad_type", mutated(t="12.5")),
    ("bad_type", mutated(t=True)),
    ("bad_type", mutated(t=None)),
    ("bad_type", mutated(seq=3.0)),
    ("bad_type", mutated(seq=True)),
    ("bad_type", mutated(val="abc")),
    ("bad_type", mutated(val=[10, 20, 255])),
    ("bad_type", mutated(idx=[0, 5, 15])),
    ("bad_type", mutated(idx=None)),
    ("non_finite", mutated(t=float("nan"))),
    ("non_finite", mutated(t=float("inf"))),
    ("non_finite", mutated(t=float("-inf"))),
    ("bad_zoom", mutated(z=25)),
    ("bad_zoom", mutated(z=-1)),
    ("tile_out_of_range", mutated(x=8)),
    ("tile_out_of_range", mutated(y=8)),
    ("tile_out_of_range", mutated(x=-1)),
    ("tile_out_of_range", mutated(y=2**64 - 1)),
    ("bad_n", mutated(n=0)),
    ("bad_n", mutated(n=257)),
    ("bad_n", mutated(n=-4)),
    ("bad_seq", mutated(seq=-1)),
    ("bad_length", mutated(sparse=False, val=bytes(15))),
    ("bad_length", mutated(sparse=False, val=bytes(17))),
    ("bad_length", mutated(idx=b"\x00\x00\x05")),
    ("bad_length", mutated(val=bytes([10, 20]))),
    ("bad_length", mutated(idx=np.array([0, 5], "<u2").tobytes())),
    ("index_out_of_range", mutated(idx=np.array([0, 5, 16], "<u2").tobytes())),
    ("index_out_of_range", mutated(idx=np.array([0, 65535, 1], "<u2").tobytes())),
    ("duplicate_index", mutated(idx=np.array([5, 0, 5], "<u2").tobytes())),
    ("bad_name", mutated(uav="")),
    ("bad_name", mutated(uav="a/b")),
    ("bad_name", mutated(uav="a*")),
    ("bad_name", mutated(cls="$x")),
    ("bad_name", mutated(cls="a?")),
    ("bad_name", mutated(cls="a#")),
    ("bad_name", mutated(uav="a b")),
    ("bad_name", mutated(uav="a\x00")),
    ("bad_name", mutated(cls="\u200b")),
    ("bad_name", mutated(uav="u\u0430v1")),
] + [("missing_field", mutated(drop=(key,))) for key in ("v", "uav", "cls", "z", "x", "y", "n", "t", "seq", "val")]


@pytest.mark.parametrize(("reason", "payload"), MALFORMED, ids=[f"{r}-{i}" for i, (r, _) in enumerate(MALFORMED)])
def test_malformed_payload_is_rejected_with_its_reason(reason: str, payload: bytes) -> None:
    with pytest.raises(TileDecodeError) as info:
        decode_tile(payload)
    assert info.value.reason == reason, str(info.value)
    assert reason in MESSAGE_ERROR_REASONS
    assert str(info.value)


def test_every_tile_reason_is_covered() -> None:
    covered = {reason for reason, _ in MALFORMED}
    tile_reasons = {
        "not_msgpack",
        "not_a_map",
        "missing_field",
        "bad_type",
        "bad_version",
        "non_finite",
        "bad_zoom",
        "tile_out_of_range",
        "bad_n",
        "bad_length",
        "index_out_of_range",
        "duplicate_index",
        "too_large",
        "bad_name",
        "bad_seq",
    }
    assert tile_reasons <= covered


def test_error_message_names_the_field_and_value() -> None:
    with pytest.raises(TileDecodeError) as info:
        decode_tile(mutated(x=8))
    assert info.value.field == "x" and "x" in str(info.value) and "8" in str(info.value)
    with pytest.raises(TileDecodeError) as info:
        decode_tile(mutated(drop=("seq",)))
    assert "seq" in str(info.value)


def test_the_valid_base_records_decode() -> None:
    sparse = decode_tile(mutated())
    assert sparse.values.ravel()[[0, 5, 15]].tolist() == pytest.approx([10 / 255, 20 / 255, 1.0])
    assert np.count_nonzero(sparse.values) == 3
    dense = decode_tile(mutated(sparse=False))
    assert dense.values.ravel()[7] == pytest.approx(7 / 255)


def test_unsorted_indices_int_timestamps_and_unknown_keys_are_accepted() -> None:
    out = decode_tile(mutated(idx=np.array([15, 0, 5], "<u2").tobytes(), t=12, future_field={"a": [1]}))
    assert out.values.ravel()[15] == pytest.approx(10 / 255) and out.t == 12.0
    assert decode_tile(bytearray(mutated())).n == 4
    assert decode_tile(memoryview(mutated())).n == 4


def test_max_bytes_is_configurable() -> None:
    payload = mutated()
    with pytest.raises(TileDecodeError) as info:
        decode_tile(payload, max_bytes=len(payload) - 1)
    assert info.value.reason == "too_large"
    assert decode_tile(payload, max_bytes=len(payload)).n == 4


@pytest.mark.parametrize("payload", ["text", None, 12, [b"x"]])
def test_non_bytes_payload_is_rejected(payload: object) -> None:
    with pytest.raises(TileDecodeError) as info:
        decode_tile(payload)  # type: ignore[arg-type]
    assert info.value.reason == "bad_type"


# ---- fuzzing: nothing but TileDecodeError escapes ----------------------------------------------
@settings(max_examples=500)
@given(payload=st.binary(max_size=300))
def test_random_bytes_raise_only_tile_decode_error(payload: bytes) -> None:
    try:
        decode_tile(payload)
    except TileDecodeError as exc:
        assert exc.reason in MESSAGE_ERROR_REASONS


@settings(max_examples=500)
@given(data=st.data(), sparse=st.booleans())
def test_corrupted_valid_payloads_raise_only_tile_decode_error(data: st.DataObject, sparse: bool) -> None:
    payload = bytearray(mutated(sparse=sparse))
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(payload) - 1))
        payload[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(payload)))
    try:
        msg = decode_tile(bytes(payload[:cut]))
    except TileDecodeError as exc:
        assert exc.reason in MESSAGE_ERROR_REASONS
    else:
        assert msg.values.shape == (msg.n, msg.n)
        assert np.all((msg.values >= 0) & (msg.values <= 1))


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=5)
    | st.binary(max_size=40),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=4), children, max_size=4),
    max_leaves=10,
)


@settings(max_examples=500, suppress_health_check=[HealthCheck.too_slow])
@given(
    changes=st.dictionaries(
        st.sampled_from(["v", "uav", "cls", "z", "x", "y", "n", "t", "seq", "idx", "val", "extra"]),
        msgpack_values,
        max_size=3,
    ),
    sparse=st.booleans(),
)
def test_random_field_values_raise_only_tile_decode_error(changes: dict, sparse: bool) -> None:
    try:
        decode_tile(mutated(sparse=sparse, **changes))
    except TileDecodeError as exc:
        assert exc.reason in MESSAGE_ERROR_REASONS

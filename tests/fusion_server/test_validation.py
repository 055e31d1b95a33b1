"""MessageValidator: every malformed message is refused with a reason, never another exception."""

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion_server.validation import REJECT_REASONS, MessageValidator, Rejected
from shared.keys import KeySpace
from shared.tilecodec import TileMessage, encode_tile
from shared.tiles import TileGrid
from tests.fusion_server.fake_agent import KEYS, TILE_X, TILE_Y

VALIDATOR = MessageValidator(KeySpace(), TileGrid())


def tile_payload(**fields) -> bytes:
    base = dict(uav="a", cls="person", z=18, x=TILE_X, y=TILE_Y, n=256, t=1.0, seq=1,
                values=np.zeros((256, 256), np.float32))
    base.update(fields)
    return encode_tile(TileMessage(**base))


def reason(key: str, payload: bytes) -> str:
    with pytest.raises(Rejected) as info:
        VALIDATOR.validate(key, payload)
    assert info.value.reason in REJECT_REASONS
    return info.value.reason


GOOD_KEY = KEYS.uav_tile("a", "person", 18, TILE_X, TILE_Y)


def test_a_valid_tile_passes():
    received = VALIDATOR.validate(GOOD_KEY, tile_payload())
    assert received.kind == "tile" and received.key.uav == "a"


@pytest.mark.parametrize(
    ("key", "payload", "expected"),
    [
        ("uavmm/v1/uav/a/tiles/person/18/1/2/3", b"", "bad_key"),
        ("uavmm/v1/uav/a/alive", b"", "unexpected_key"),
        ("other/v1/uav/a/state", b"", "bad_key"),
        (GOOD_KEY, b"\xc1garbage", "not_msgpack"),
        (GOOD_KEY, msgpack.packb([1, 2]), "not_a_map"),
        (GOOD_KEY, tile_payload(uav="b"), "uav_mismatch"),
        (KEYS.uav_tile("a", "person", 18, TILE_X + 1, TILE_Y), tile_payload(), "tile_mismatch"),
        (KEYS.uav_tile("a", "boat", 18, TILE_X, TILE_Y), tile_payload(), "tile_mismatch"),
        (KEYS.uav_tile("a", "person", 17, TILE_X // 2, TILE_Y // 2),
         tile_payload(z=17, x=TILE_X // 2, y=TILE_Y // 2), "wrong_grid"),
        (GOOD_KEY, tile_payload(n=128, values=np.zeros((128, 128))), "wrong_grid"),
        (GOOD_KEY, b"\x00" * (300 * 1024), "too_large"),
        (KEYS.uav_state("a"), msgpack.packb({"v": 2}), "bad_version"),
        (KEYS.uav_tracks("a"), msgpack.packb({"v": 1, "uav": "a", "t": float("nan"), "tracks": []}), "non_finite"),
        (KEYS.uav_tracks("a"), msgpack.packb({"v": 1, "uav": "b", "t": 1.0, "tracks": []}), "uav_mismatch"),
    ],
)
def test_malformed_messages_are_refused_with_their_reason(key, payload, expected):
    assert reason(key, payload) == expected


class _Sized:
    """Stands in for zenoh.ZBytes: the size is checked before the payload is copied."""

    def __len__(self) -> int:
        return 10**9

    def to_bytes(self) -> bytes:  # pragma: no cover - must not be called
        raise AssertionError("copied a payload that was too large")


def test_huge_payload_is_refused_before_copying():
    assert reason(GOOD_KEY, _Sized()) == "too_large"


@settings(max_examples=300, deadline=None)
@given(
    key=st.sampled_from([GOOD_KEY, KEYS.uav_state("a"), KEYS.uav_tracks("a")]),
    payload=st.one_of(
        st.binary(max_size=300),
        st.dictionaries(st.sampled_from(["v", "uav", "cls", "z", "x", "y", "n", "t", "seq", "idx", "val", "tracks",
                                         "lat", "lon", "camera", "footprint"]),
                        st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(),
                                  st.text(max_size=5),
                                  st.binary(max_size=20), st.lists(st.integers(-(2**63), 2**63), max_size=3))).map(
            lambda d: msgpack.packb(d, use_bin_type=True)),
    ),
)
def test_random_payloads_only_ever_raise_rejected(key, payload):
    try:
        VALIDATOR.validate(key, payload)
    except Rejected as exc:
        assert exc.reason in REJECT_REASONS

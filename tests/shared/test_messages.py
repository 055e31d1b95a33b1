"""Tests of the state, tracks and joint-tracks message schemas: round trips and strict validation."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.messages import (
    MAX_FOOTPRINT_POINTS,
    MAX_TRACKS,
    MESSAGE_ERROR_REASONS,
    CameraInfo,
    JointTrackItem,
    JointTracksMessage,
    MessageError,
    StateMessage,
    TrackItem,
    TracksMessage,
    decode_joint_tracks,
    decode_state,
    decode_tracks,
    encode_joint_tracks,
    encode_state,
    encode_tracks,
)

CAMERA = CameraInfo(width=3840, height=2160, fx=2900.0, fy=2900.0, cx=1920.0, cy=1080.0)


def make_state(**overrides: Any) -> StateMessage:
    fields: dict[str, Any] = {
        "uav": "uav1",
        "t": 1.7e9,
        "lat": 47.67,
        "lon": 9.27,
        "height_m": 30.0,
        "pitch_deg": 45.0,
        "heading_deg": 140.0,
        "footprint": ((47.6701, 9.2701), (47.6702, 9.2703), (47.6699, 9.2704)),
        "camera": CAMERA,
    }
    fields.update(overrides)
    return StateMessage(**fields)


finite = st.floats(-1e6, 1e6, allow_nan=False)
lat_st = st.floats(-90.0, 90.0)
lon_st = st.floats(-180.0, 180.0)
names = st.text(st.sampled_from("abcXYZ012-_."), min_size=1, max_size=8)
uav_ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,7}", fullmatch=True).filter(lambda s: s != "joint")
track_items = st.builds(
    TrackItem,
    id=st.integers(0, 2**63 - 1),
    cls=names,
    lat=lat_st,
    lon=lon_st,
    score=st.floats(0.0, 1.0),
    vel_en=st.tuples(finite, finite),
)
joint_items = st.builds(
    JointTrackItem,
    gid=st.integers(0, 2**63 - 1),
    cls=names,
    lat=lat_st,
    lon=lon_st,
    score=st.floats(0.0, 1.0),
    vel_en=st.tuples(finite, finite),
    members=st.lists(st.tuples(uav_ids, st.integers(0, 2**63 - 1)), max_size=5, unique=True).map(tuple),
)


# ---- round trips -------------------------------------------------------------------------------
@given(
    lat=lat_st,
    lon=lon_st,
    height_m=finite,
    pitch=st.floats(-90.0, 90.0),
    heading=st.floats(-360.0, 360.0),
    footprint=st.lists(st.tuples(lat_st, lon_st), max_size=MAX_FOOTPRINT_POINTS // 8),
    t=st.floats(0.0, 4e9),
)
def test_state_round_trip(
    lat: float, lon: float, height_m: float, pitch: float, heading: float, footprint: list, t: float
) -> None:
    msg = make_state(
        lat=lat, lon=lon, height_m=height_m, pitch_deg=pitch, heading_deg=heading, footprint=footprint, t=t
    )
    assert isinstance(msg.footprint, tuple)
    assert decode_state(encode_state(msg)) == msg


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(items=st.lists(track_items, max_size=20, unique_by=lambda item: item.id), t=finite)
def test_tracks_round_trip(items: list[TrackItem], t: float) -> None:
    msg = TracksMessage(uav="uav-2", t=t, tracks=items)
    out = decode_tracks(encode_tracks(msg))
    assert out == msg and isinstance(out.tracks, tuple)


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(items=st.lists(joint_items, max_size=10, unique_by=lambda item: item.gid), t=finite)
def test_joint_tracks_round_trip(items: list[JointTrackItem], t: float) -> None:
    msg = JointTracksMessage(t=t, tracks=items)
    out = decode_joint_tracks(encode_joint_tracks(msg))
    assert out == msg and out.uav == "joint"


def test_wire_layout_matches_the_design() -> None:
    record = msgpack.unpackb(encode_state(make_state()))
    assert set(record) == {"v", "uav", "t", "lat", "lon", "height_m", "pitch_deg", "heading_deg", "footprint", "camera"}
    assert record["v"] == 1 and record["camera"] == {
        "width": 3840,
        "height": 2160,
        "fx": 2900.0,
        "fy": 2900.0,
        "cx": 1920.0,
        "cy": 1080.0,
    }
    assert record["footprint"][0] == [47.6701, 9.2701]
    tracks = TracksMessage("u", 1.0, [TrackItem(4, "person", 1.0, 2.0, 0.5, (0.1, -0.2))])
    assert msgpack.unpackb(encode_tracks(tracks)) == {
        "v": 1,
        "uav": "u",
        "t": 1.0,
        "tracks": [{"id": 4, "cls": "person", "lat": 1.0, "lon": 2.0, "score": 0.5, "vel_en": [0.1, -0.2]}],
    }
    joint = JointTracksMessage(1.0, [JointTrackItem(9, "person", 1.0, 2.0, 0.5, (0.0, 0.0), (("u", 4),))])
    record = msgpack.unpackb(encode_joint_tracks(joint))
    assert record["uav"] == "joint" and record["tracks"][0]["members"] == [["u", 4]]
    assert record["tracks"][0]["gid"] == 9


def test_numpy_scalars_are_normalised_to_python_types() -> None:
    item = TrackItem(np.int64(3), "person", np.float32(1.5), np.float64(2.0), np.float32(0.25), np.zeros(2))
    assert type(item.id) is int and type(item.lat) is float and item.vel_en == (0.0, 0.0)
    assert decode_tracks(encode_tracks(TracksMessage("u", np.float64(1.0), [item]))).tracks == (item,)
    camera = CameraInfo(np.int64(640), np.int32(480), np.float32(500.0), 500, 320, 240)
    assert type(camera.width) is int and type(camera.fx) is float


def test_unknown_keys_and_integer_floats_are_accepted() -> None:
    record = msgpack.unpackb(encode_state(make_state()))
    record.update(future={"x": 1}, lat=47, t=1700000000)
    record["camera"]["k1"] = 0.1
    out = decode_state(msgpack.packb(record))
    assert out.lat == 47.0 and out.t == 1.7e9


def test_limits_are_enforced() -> None:
    with pytest.raises(MessageError) as info:
        make_state(footprint=[(0.0, 0.0)] * (MAX_FOOTPRINT_POINTS + 1))
    assert info.value.reason == "too_many"
    assert len(make_state(footprint=[(0.0, 0.0)] * MAX_FOOTPRINT_POINTS).footprint) == MAX_FOOTPRINT_POINTS
    items = [TrackItem(i, "p", 0.0, 0.0, 0.5, (0.0, 0.0)) for i in range(MAX_TRACKS + 1)]
    with pytest.raises(MessageError) as info:
        TracksMessage("u", 0.0, items)
    assert info.value.reason == "too_many"
    full = TracksMessage("u", 0.0, items[:MAX_TRACKS])
    assert len(decode_tracks(encode_tracks(full)).tracks) == MAX_TRACKS
    record = msgpack.unpackb(encode_tracks(full))
    record["tracks"].append(record["tracks"][0] | {"id": MAX_TRACKS})
    with pytest.raises(MessageError) as info:
        decode_tracks(msgpack.packb(record))
    assert info.value.reason == "too_many"


# ---- strict decoding: one case per malformed field ---------------------------------------------
def state_record() -> dict[str, Any]:
    return msgpack.unpackb(encode_state(make_state()))


def tracks_record() -> dict[str, Any]:
    msg = TracksMessage(
        "uav1",
        5.0,
        [TrackItem(1, "person", 47.0, 9.0, 0.9, (1.0, 0.0)), TrackItem(2, "boat", 47.1, 9.1, 0.4, (0.0, 1.0))],
    )
    return msgpack.unpackb(encode_tracks(msg))


def joint_record() -> dict[str, Any]:
    msg = JointTracksMessage(
        5.0,
        [
            JointTrackItem(1, "person", 47.0, 9.0, 0.9, (1.0, 0.0), (("a", 1), ("b", 7))),
            JointTrackItem(2, "person", 47.1, 9.1, 0.4, (0.0, 1.0), ()),
        ],
    )
    return msgpack.unpackb(encode_joint_tracks(msg))


def edit(base: Callable[[], dict[str, Any]], path: str, value: Any = None, *, delete: bool = False) -> bytes:
    """Pack ``base()`` with the field at a dotted path (list indices as numbers) replaced or deleted."""
    record = base()
    keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
    target = record
    for key in keys[:-1]:
        target = target[key]
    if delete:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return msgpack.packb(record, use_bin_type=True)


NAN, INF = float("nan"), float("inf")
CASES: list[tuple[str, Callable[..., Any], bytes]] = [
    # state
    ("not_msgpack", decode_state, b"\xc1"),
    ("not_msgpack", decode_state, b"\x82\xa1v"),
    ("not_a_map", decode_state, msgpack.packb([1])),
    ("too_large", decode_state, edit(state_record, "pad", b"x" * 70000)),
    ("bad_version", decode_state, edit(state_record, "v", 2)),
    ("bad_type", decode_state, edit(state_record, "v", True)),
    ("bad_type", decode_state, edit(state_record, "lat", "47")),
    ("bad_type", decode_state, edit(state_record, "height_m", True)),
    ("bad_type", decode_state, edit(state_record, "footprint", "poly")),
    ("bad_type", decode_state, edit(state_record, "footprint.0.0", None)),
    ("bad_type", decode_state, edit(state_record, "camera.width", 640.0)),
    ("bad_type", decode_state, edit(state_record, "camera.fx", "f")),
    ("bad_type", decode_state, edit(state_record, "uav", 3)),
    ("not_a_map", decode_state, edit(state_record, "camera", [640, 480])),
    ("non_finite", decode_state, edit(state_record, "t", NAN)),
    ("non_finite", decode_state, edit(state_record, "lon", INF)),
    ("non_finite", decode_state, edit(state_record, "height_m", -INF)),
    ("non_finite", decode_state, edit(state_record, "footprint.1.0", NAN)),
    ("non_finite", decode_state, edit(state_record, "camera.cx", NAN)),
    ("out_of_range", decode_state, edit(state_record, "lat", 90.5)),
    ("out_of_range", decode_state, edit(state_record, "lon", -181.0)),
    ("out_of_range", decode_state, edit(state_record, "pitch_deg", 91.0)),
    ("out_of_range", decode_state, edit(state_record, "heading_deg", 361.0)),
    ("out_of_range", decode_state, edit(state_record, "footprint.2.1", 200.0)),
    ("out_of_range", decode_state, edit(state_record, "camera.width", 0)),
    ("out_of_range", decode_state, edit(state_record, "camera.fy", 0.0)),
    ("bad_length", decode_state, edit(state_record, "footprint.0", [1.0, 2.0, 3.0])),
    ("too_many", decode_state, edit(state_record, "footprint", [[0.0, 0.0]] * 257)),
    ("bad_name", decode_state, edit(state_record, "uav", "a/b")),
    ("bad_name", decode_state, edit(state_record, "uav", "")),
    ("bad_name", decode_state, edit(state_record, "uav", "u\u0430v1")),  # Cyrillic a: a homoglyph of uav1
    ("bad_name", decode_state, edit(state_record, "uav", "joint")),  # the fusion server's id
    ("missing_field", decode_state, edit(state_record, "camera.cy", delete=True)),
    *[
        ("missing_field", decode_state, edit(state_record, key, delete=True))
        for key in ("v", "uav", "t", "lat", "lon", "height_m", "pitch_deg", "heading_deg", "footprint", "camera")
    ],
    # local tracks
    ("not_msgpack", decode_tracks, b""),
    ("not_a_map", decode_tracks, msgpack.packb("tracks")),
    ("too_large", decode_tracks, edit(tracks_record, "pad", b"x" * (8 * 1024 * 1024))),
    ("bad_version", decode_tracks, edit(tracks_record, "v", 0)),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks", {"0": {}})),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks.0.id", "1")),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks.0.id", True)),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks.0.id", 1.0)),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks.0.score", None)),
    ("bad_type", decode_tracks, edit(tracks_record, "tracks.0.vel_en", 1.0)),
    ("not_a_map", decode_tracks, edit(tracks_record, "tracks.1", [1, 2])),
    ("non_finite", decode_tracks, edit(tracks_record, "tracks.0.vel_en.1", NAN)),
    ("non_finite", decode_tracks, edit(tracks_record, "t", INF)),
    ("out_of_range", decode_tracks, edit(tracks_record, "tracks.0.score", 1.5)),
    ("out_of_range", decode_tracks, edit(tracks_record, "tracks.0.id", -1)),
    ("out_of_range", decode_tracks, edit(tracks_record, "tracks.1.lat", -91.0)),
    ("bad_length", decode_tracks, edit(tracks_record, "tracks.0.vel_en", [1.0])),
    ("duplicate_id", decode_tracks, edit(tracks_record, "tracks.1.id", 1)),
    ("bad_name", decode_tracks, edit(tracks_record, "tracks.0.cls", "per son")),
    ("bad_name", decode_tracks, edit(tracks_record, "uav", "*")),
    ("bad_name", decode_tracks, edit(tracks_record, "uav", "joint")),
    ("missing_field", decode_tracks, edit(tracks_record, "tracks", delete=True)),
    *[
        ("missing_field", decode_tracks, edit(tracks_record, f"tracks.0.{key}", delete=True))
        for key in ("id", "cls", "lat", "lon", "score", "vel_en")
    ],
    # joint tracks
    ("not_msgpack", decode_joint_tracks, b"\xdc\x00"),
    ("bad_version", decode_joint_tracks, edit(joint_record, "v", 3)),
    ("bad_name", decode_joint_tracks, edit(joint_record, "uav", "uav1")),
    ("bad_type", decode_joint_tracks, edit(joint_record, "tracks.0.gid", 1.5)),
    ("bad_type", decode_joint_tracks, edit(joint_record, "tracks.0.members", "a")),
    ("bad_type", decode_joint_tracks, edit(joint_record, "tracks.0.members.0.1", "1")),
    ("bad_type", decode_joint_tracks, edit(joint_record, "tracks.0.members.0.0", 5)),
    ("bad_length", decode_joint_tracks, edit(joint_record, "tracks.0.members.0", ["a"])),
    ("bad_name", decode_joint_tracks, edit(joint_record, "tracks.0.members.0.0", "a/b")),
    ("out_of_range", decode_joint_tracks, edit(joint_record, "tracks.0.members.1.1", -3)),
    ("duplicate_id", decode_joint_tracks, edit(joint_record, "tracks.1.gid", 1)),
    ("duplicate_id", decode_joint_tracks, edit(joint_record, "tracks.0.members.1", ["a", 1])),
    ("too_many", decode_joint_tracks, edit(joint_record, "tracks.0.members", [["a", i] for i in range(1025)])),
    ("non_finite", decode_joint_tracks, edit(joint_record, "tracks.1.lon", NAN)),
    ("missing_field", decode_joint_tracks, edit(joint_record, "tracks.0.members", delete=True)),
    ("missing_field", decode_joint_tracks, edit(joint_record, "tracks.0.gid", delete=True)),
]


@pytest.mark.parametrize(
    ("reason", "decode", "payload"), CASES, ids=[f"{d.__name__}-{r}-{i}" for i, (r, d, _) in enumerate(CASES)]
)
def test_malformed_message_is_rejected_with_its_reason(reason: str, decode: Callable, payload: bytes) -> None:
    with pytest.raises(MessageError) as info:
        decode(payload)
    assert info.value.reason == reason, str(info.value)
    assert reason in MESSAGE_ERROR_REASONS


def test_valid_base_records_decode() -> None:
    assert decode_state(msgpack.packb(state_record())).uav == "uav1"
    assert len(decode_tracks(msgpack.packb(tracks_record())).tracks) == 2
    assert decode_joint_tracks(msgpack.packb(joint_record())).tracks[0].members == (("a", 1), ("b", 7))


def test_error_names_the_nested_field() -> None:
    with pytest.raises(MessageError) as info:
        decode_tracks(edit(tracks_record, "tracks.1.lat", -91.0))
    assert info.value.field == "tracks[1].lat" and "tracks[1].lat" in str(info.value) and "-91" in str(info.value)
    with pytest.raises(MessageError) as info:
        decode_joint_tracks(edit(joint_record, "tracks.0.members.1.1", -3))
    assert info.value.field == "tracks[0].members[1][1]"


@pytest.mark.parametrize(
    ("factory", "reason"),
    [
        (lambda: CameraInfo(0, 480, 500.0, 500.0, 320.0, 240.0), "out_of_range"),
        (lambda: CameraInfo(640, 480, -1.0, 500.0, 320.0, 240.0), "out_of_range"),
        (lambda: make_state(pitch_deg=math.nan), "non_finite"),
        (lambda: make_state(camera={"width": 1}), "bad_type"),
        (lambda: TrackItem(1, "p", 0.0, 0.0, 0.5, (0.0,)), "bad_length"),
        (lambda: TracksMessage("u", 0.0, [object()]), "bad_type"),
        (lambda: TracksMessage("u", 0.0, [TrackItem(1, "p", 0.0, 0.0, 0.5, (0, 0))] * 2), "duplicate_id"),
        (lambda: JointTracksMessage(0.0, [], uav="uav1"), "bad_name"),
        (lambda: JointTrackItem(1, "p", 0.0, 0.0, 0.5, (0, 0), (("a", 1), ("a", 1))), "duplicate_id"),
    ],
)
def test_dataclasses_validate_themselves(factory: Callable[[], Any], reason: str) -> None:
    with pytest.raises(ValueError) as info:
        factory()
    assert isinstance(info.value, MessageError) and info.value.reason == reason


# ---- fuzzing: nothing but MessageError escapes -------------------------------------------------
DECODERS = [decode_state, decode_tracks, decode_joint_tracks]
BASES = [state_record, tracks_record, joint_record]


@settings(max_examples=300)
@given(payload=st.binary(max_size=300))
def test_random_bytes_raise_only_message_error(payload: bytes) -> None:
    for decode in DECODERS:
        try:
            decode(payload)
        except MessageError as exc:
            assert exc.reason in MESSAGE_ERROR_REASONS


@settings(max_examples=300)
@given(data=st.data(), which=st.integers(0, 2))
def test_corrupted_valid_payloads_raise_only_message_error(data: st.DataObject, which: int) -> None:
    payload = bytearray(msgpack.packb(BASES[which]()))
    for _ in range(data.draw(st.integers(1, 4))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    try:
        DECODERS[which](bytes(payload[: data.draw(st.integers(0, len(payload)))]))
    except MessageError as exc:
        assert exc.reason in MESSAGE_ERROR_REASONS


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=5)
    | st.binary(max_size=10),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=6), children, max_size=3),
    max_leaves=8,
)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.integers(0, 2),
    path=st.sampled_from(
        [
            "v",
            "uav",
            "t",
            "lat",
            "footprint",
            "footprint.0",
            "camera",
            "camera.fx",
            "tracks",
            "tracks.0",
            "tracks.0.id",
            "tracks.0.vel_en",
            "tracks.0.members",
            "tracks.0.gid",
            "tracks.0.members.0",
        ]
    ),
    value=msgpack_values,
)
def test_random_field_values_raise_only_message_error(which: int, path: str, value: Any) -> None:
    try:
        payload = edit(BASES[which], path, value)
    except (KeyError, IndexError, TypeError):
        return  # the path does not exist in this message kind
    try:
        DECODERS[which](payload)
    except MessageError as exc:
        assert exc.reason in MESSAGE_ERROR_REASONS


# ---- joint track items: the optional `active` extension (docs/protocol.md) -----------------------
def test_active_members_round_trip_and_are_left_out_when_all_members_report() -> None:
    held = JointTrackItem(1, "person", 47.0, 9.0, 0.9, (0.0, 0.0), (("a", 1), ("b", 7)), active=())
    half = JointTrackItem(2, "person", 47.0, 9.0, 0.9, (0.0, 0.0), (("a", 2), ("b", 8)), active=(1,))
    every = JointTrackItem(3, "person", 47.0, 9.0, 0.9, (0.0, 0.0), (("a", 3),))
    payload = encode_joint_tracks(JointTracksMessage(5.0, [held, half, every]))
    raw = msgpack.unpackb(payload)
    assert [t.get("active") for t in raw["tracks"]] == [[], [1], None]
    assert "active" not in raw["tracks"][2]  # nothing added to the common case
    decoded = decode_joint_tracks(payload).tracks
    assert decoded == (held, half, every)
    assert [t.active_members for t in decoded] == [(), (("b", 8),), (("a", 3),)]


def test_a_message_without_active_reads_as_every_member_reporting_and_unknown_fields_are_ignored() -> None:
    record = joint_record()  # as an older server wrote it: no "active"
    record["tracks"][0]["future_field"] = {"anything": [1, 2]}
    record["future_envelope"] = "ignored"
    (first, second) = decode_joint_tracks(msgpack.packb(record, use_bin_type=True)).tracks
    assert first.active is None and first.active_members == (("a", 1), ("b", 7))
    assert second.active is None and second.active_members == ()


@pytest.mark.parametrize(("active", "reason"), [
    ([2], "out_of_range"),  # two members: indexes 0 and 1
    ([-1], "out_of_range"),
    ([1, 1], "duplicate_index"),
    (["a"], "bad_type"),
    ([True], "bad_type"),
    ("0", "bad_type"),
])
def test_a_malformed_active_field_is_refused_naming_it(active: Any, reason: str) -> None:
    with pytest.raises(MessageError) as info:
        decode_joint_tracks(edit(joint_record, "tracks.0.active", active))
    assert info.value.reason == reason and info.value.field.startswith("tracks[0].active")
    assert reason in MESSAGE_ERROR_REASONS


def test_active_indexes_of_a_track_without_members_are_refused_and_kept_increasing() -> None:
    with pytest.raises(MessageError) as info:
        JointTrackItem(1, "p", 0.0, 0.0, 0.5, (0, 0), (), active=(0,))
    assert info.value.reason == "out_of_range"
    item = JointTrackItem(1, "p", 0.0, 0.0, 0.5, (0, 0), (("a", 1), ("b", 2)), active=(1, 0))
    assert item.active == (0, 1)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 3000), max_bytes=st.integers(1, 200_000))
def test_joint_tracks_within_a_byte_bound_keep_the_first_tracks_and_fit(n, max_bytes):
    """The fusion server's and the gateway's joint/tracks cap (one function since 30 Nov 2026): the message holds
    the first tracks `make` orders, as many as fit after halving, within max_bytes unless one track alone is more."""
    from shared.messages import decode_joint_tracks, encode_joint_tracks_within

    items = [JointTrackItem(i, "person", 47.0, 9.0, 0.5, (0.0, 0.0), (("u", i),)) for i in range(n)]
    asked: list[int] = []

    def make(limit: int) -> JointTracksMessage:
        asked.append(limit)
        return JointTracksMessage(1.0, items[:limit])

    message, payload = encode_joint_tracks_within(make, max_bytes)
    assert [t.gid for t in message.tracks] == list(range(len(message.tracks)))
    assert len(payload) <= max_bytes or len(message.tracks) <= 1
    assert [t.gid for t in decode_joint_tracks(payload, max_bytes=10**7).tracks] == [t.gid for t in message.tracks]
    assert asked[0] == MAX_TRACKS and all(b < a for a, b in zip(asked[:-1], asked[1:], strict=True))

"""Tests of the Zenoh key space: builders, selectors, parser and name validation."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from shared.keys import KeySpace, ParsedKey, name_problem, uav_id_problem, validate_name, validate_uav_id

KS = KeySpace()

# printable, no whitespace, none of / * $ ? #, not starting with '@'
name_chars = st.characters(
    min_codepoint=33, max_codepoint=0x2FF, blacklist_characters="/*$?#", blacklist_categories=("Cc", "Z")
)
names = st.text(name_chars, min_size=1, max_size=20).filter(lambda s: s.isprintable() and not s.startswith("@"))
# UAV ids: ASCII letters, digits, _ . -, starting with a letter or digit, not "joint"
uav_ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,19}", fullmatch=True).filter(lambda s: s != "joint")


def tiles_at(z: int) -> st.SearchStrategy[tuple[int, int, int]]:
    return st.tuples(st.just(z), st.integers(0, 2**z - 1), st.integers(0, 2**z - 1))


tiles = st.integers(0, 24).flatmap(tiles_at)


def test_builders_produce_the_documented_keys() -> None:
    assert KS.uav_tile("uav1", "person", 18, 137625, 91125) == "uavmm/v1/uav/uav1/tiles/person/18/137625/91125"
    assert KS.uav_tiles_all() == "uavmm/v1/uav/*/tiles/**"
    assert KS.uav_tiles_all("uav1") == "uavmm/v1/uav/uav1/tiles/**"
    assert KS.uav_tiles_all("*", "person") == "uavmm/v1/uav/*/tiles/person/**"
    assert KS.uav_state("uav1") == "uavmm/v1/uav/uav1/state"
    assert KS.uav_state("*") == "uavmm/v1/uav/*/state"
    assert KS.uav_tracks("uav1") == "uavmm/v1/uav/uav1/tracks"
    assert KS.uav_alive("uav1") == "uavmm/v1/uav/uav1/alive"
    assert KS.uav_all() == "uavmm/v1/uav/**"
    assert KS.joint_tile("person", 18, 1, 2) == "uavmm/v1/joint/tiles/person/18/1/2"
    assert KS.joint_tiles_all() == "uavmm/v1/joint/tiles/*/**"
    assert KS.joint_tracks() == "uavmm/v1/joint/tracks"
    assert KS.joint_all() == "uavmm/v1/joint/**"


def test_custom_prefix_is_used_everywhere() -> None:
    ks = KeySpace("demo/a/v1")
    assert ks.uav_state("u") == "demo/a/v1/uav/u/state"
    assert ks.parse("demo/a/v1/joint/tracks") == ParsedKey(kind="joint_tracks", uav="joint")
    with pytest.raises(ValueError, match="prefix"):
        ks.parse("uavmm/v1/joint/tracks")


@pytest.mark.parametrize("prefix", ["", "/uavmm", "uavmm/", "uavmm//v1", "uavmm/*", "uavmm/**", "a b", "a/@b"])
def test_bad_prefix_is_rejected(prefix: str) -> None:
    with pytest.raises(ValueError, match="prefix"):
        KeySpace(prefix)


def test_numpy_integers_are_accepted_as_tile_coordinates() -> None:
    assert KS.uav_tile("u", "c", np.int64(3), np.int32(1), np.uint16(7)) == "uavmm/v1/uav/u/tiles/c/3/1/7"


@given(uav=uav_ids, cls=names, tile=tiles)
def test_tile_keys_round_trip_through_parse(uav: str, cls: str, tile: tuple[int, int, int]) -> None:
    z, x, y = tile
    assert KS.parse(KS.uav_tile(uav, cls, z, x, y)) == ParsedKey("uav_tile", uav, cls, z, x, y)
    assert KS.parse(KS.joint_tile(cls, z, x, y)) == ParsedKey("joint_tile", "joint", cls, z, x, y)


@given(uav=uav_ids)
def test_uav_keys_round_trip_through_parse(uav: str) -> None:
    assert KS.parse(KS.uav_state(uav)) == ParsedKey("uav_state", uav)
    assert KS.parse(KS.uav_tracks(uav)) == ParsedKey("uav_tracks", uav)
    assert KS.parse(KS.uav_alive(uav)) == ParsedKey("uav_alive", uav)


@given(uav=uav_ids, cls=names, tile=tiles)
def test_keys_are_valid_zenoh_keys_matched_by_the_selectors(uav: str, cls: str, tile: tuple[int, int, int]) -> None:
    key = zenoh.KeyExpr(KS.uav_tile(uav, cls, *tile))
    assert zenoh.KeyExpr(KS.uav_tiles_all()).includes(key)
    assert zenoh.KeyExpr(KS.uav_tiles_all(uav, cls)).includes(key)
    assert zenoh.KeyExpr(KS.uav_all()).includes(key)
    assert not zenoh.KeyExpr(KS.joint_all()).includes(key)
    joint = zenoh.KeyExpr(KS.joint_tile(cls, *tile))
    assert zenoh.KeyExpr(KS.joint_all()).includes(joint)
    assert zenoh.KeyExpr(KS.joint_tiles_all()).includes(joint)
    assert zenoh.KeyExpr(KS.joint_all()).includes(zenoh.KeyExpr(KS.joint_tracks()))
    assert zenoh.KeyExpr(KS.uav_state("*")).includes(zenoh.KeyExpr(KS.uav_state(uav)))


BAD_NAMES = ["", "a/b", "a*", "$a", "a?", "a#b", "a b", "a\tb", "a\nb", "a\x00", "\x7f", "@admin", "x" * 129, 5, None]


@pytest.mark.parametrize("bad", BAD_NAMES)
def test_bad_names_are_rejected_naming_the_field(bad: object) -> None:
    assert name_problem(bad) is not None
    with pytest.raises(ValueError, match="uav"):
        KS.uav_state(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cls"):
        KS.uav_tile("u", bad, 1, 0, 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cls"):
        KS.joint_tile(bad, 1, 0, 0)  # type: ignore[arg-type]


@pytest.mark.parametrize("good", ["uav1", "person", "a-b_c.d", "M\u00fcller", "a@b", "x" * 128])
def test_good_names_pass(good: str) -> None:
    assert name_problem(good) is None
    assert validate_name(good, "cls") == good


@pytest.mark.parametrize("good", ["uav1", "UAV-7", "a-b_c.d", "0drone", "x" * 128])
def test_good_uav_ids_pass(good: str) -> None:
    assert uav_id_problem(good) is None
    assert KS.parse(KS.uav_state(good)).uav == good


# homoglyphs (Cyrillic a, Greek omicron, fullwidth digit), invisible characters, the fusion server's
# own id, leading punctuation, and names that are only valid class names
BAD_UAV_IDS = ["u\u0430v1", "uav\u03bf", "uav\uff11", "uav1\u200b", "joint", "-uav", ".uav", "_uav",
               "M\u00fcller", "a@b", "a:b", "a~b", "a+b", *BAD_NAMES]


@pytest.mark.parametrize("bad", BAD_UAV_IDS)
def test_uav_ids_outside_the_safe_set_are_refused_in_keys_and_messages(bad: object) -> None:
    assert uav_id_problem(bad) is not None
    with pytest.raises(ValueError, match="uav"):
        validate_uav_id(bad)
    for build in (KS.uav_state, KS.uav_tracks, KS.uav_alive, lambda u: KS.uav_tile(u, "person", 18, 0, 0)):
        with pytest.raises(ValueError, match="uav"):
            build(bad)
    if isinstance(bad, str) and name_problem(bad) is None:  # a valid chunk: the parser must refuse it
        with pytest.raises(ValueError, match="uav"):
            KS.parse(f"uavmm/v1/uav/{bad}/state")


@pytest.mark.parametrize(
    ("z", "x", "y", "field"),
    [
        (25, 0, 0, "z"),
        (-1, 0, 0, "z"),
        (3, 8, 0, "x"),
        (3, 0, 8, "y"),
        (3, -1, 0, "x"),
        (True, 0, 0, "z"),
        (3, 1.0, 0, "x"),
        (3, 0, "1", "y"),
    ],
)
def test_tile_coordinates_are_validated(z: object, x: object, y: object, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field} "):
        KS.uav_tile("u", "c", z, x, y)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=f"^{field} "):
        KS.joint_tile("c", z, x, y)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "key",
    [
        "uavmm/v2/uav/a/state",
        "uavmm/v1",
        "uavmm/v1/",
        "uavmm/v1/uav/a",
        "uavmm/v1/uav/a/",
        "uavmm/v1/uav/a/state/",
        "uavmm/v1/uav/a/status",
        "uavmm/v1/uav//state",
        "uavmm/v1/uav/*/state",
        "uavmm/v1/uav/a/tiles/person/18/1",
        "uavmm/v1/uav/a/tiles/person/18/1/2/3",
        "uavmm/v1/uav/a/tiles/person/18/1/x",
        "uavmm/v1/uav/a/tiles/person/018/1/2",
        "uavmm/v1/uav/a/tiles/person/+18/1/2",
        "uavmm/v1/uav/a/tiles/person/18/-1/2",
        "uavmm/v1/uav/a/tiles/person/ 18/1/2",
        "uavmm/v1/uav/a/tiles/person/25/0/0",
        "uavmm/v1/uav/a/tiles/person/3/8/0",
        "uavmm/v1/uav/a/tiles/**",
        "uavmm/v1/uav/a b/state",
        "uavmm/v1/joint",
        "uavmm/v1/joint/tracks/x",
        "uavmm/v1/joint/tiles/person/3/0",
        "uavmm/v1/joint/tiles/*/3/0/0",
        "uavmm/v1/joint/**",
        "uavmm/v1/other/tracks",
        "uavmm/v1uav/a/state",
        "",
    ],
)
def test_parse_rejects_keys_outside_the_space(key: str) -> None:
    with pytest.raises(ValueError):
        KS.parse(key)


def test_parse_rejects_non_strings() -> None:
    with pytest.raises(ValueError, match="str"):
        KS.parse(b"uavmm/v1/joint/tracks")  # type: ignore[arg-type]


@given(z=st.integers(0, 24), data=st.data())
def test_track_region_keys_round_trip_and_hold_their_tile(z: int, data: st.DataObject) -> None:
    from shared.keys import TRACK_REGION_ZOOM_DROP, track_region

    x = data.draw(st.integers(0, 2**z - 1))
    y = data.draw(st.integers(0, 2**z - 1))
    rz, rx, ry = track_region(z, x, y)
    assert rz == max(z - TRACK_REGION_ZOOM_DROP, 0)
    assert (x >> (z - rz), y >> (z - rz)) == (rx, ry)
    keys = KeySpace()
    parsed = keys.parse(keys.region_tracks(rz, rx, ry))
    assert (parsed.kind, parsed.uav, parsed.z, parsed.x, parsed.y) == ("region_tracks", "joint", rz, rx, ry)


@pytest.mark.parametrize("tail", ["tracks/15/1", "tracks/15/01/2", "tracks/15/1/2/3", "tracks/3/8/0", "tracks/x/1/2"])
def test_malformed_track_region_keys_are_refused(tail: str) -> None:
    with pytest.raises(ValueError):
        KeySpace().parse(f"uavmm/v1/region/{tail}")


def test_region_keys_stay_outside_the_joint_selector() -> None:
    """`{prefix}/joint/**` (DESIGN.md's subscription and late-join query) keeps only joint tiles and tracks."""
    joint = zenoh.KeyExpr(KS.joint_all())
    regions = zenoh.KeyExpr(KS.region_all())
    for key in (KS.region_tracks(16, 1, 2), KS.region_state(16, 1, 2, "uav1")):
        assert regions.includes(zenoh.KeyExpr(key)) and not joint.intersects(zenoh.KeyExpr(key))
    assert KS.parse(KS.region_state(16, 1, 2, "uav1")).uav == "uav1"
    with pytest.raises(ValueError):
        KS.parse("uavmm/v1/joint/tracks/16/1/2")  # the region keys live under region/ only


def test_shard_tracks_keys_round_trip_and_the_gateways_selector_matches_every_shard():
    key = KS.shard_tracks(2, 3)
    assert key == "uavmm/v1/fusion/tracks/3/2" and KS.parse_shard_tracks(key) == (2, 3)
    selector = zenoh.KeyExpr(KS.shard_tracks("*", 3))
    assert all(selector.intersects(zenoh.KeyExpr(KS.shard_tracks(k, 3))) for k in range(3))
    assert not selector.intersects(zenoh.KeyExpr(KS.shard_tracks(0, 4)))
    for bad in ("uavmm/v1/fusion/tracks/3/3", "uavmm/v1/fusion/tracks/3/02", "uavmm/v1/fusion/shards/3/2/14",
                "uavmm/v1/fusion/tracks/3"):
        with pytest.raises(ValueError):
            KS.parse_shard_tracks(bad)
    with pytest.raises(ValueError):
        KS.shard_tracks(-1, 3)

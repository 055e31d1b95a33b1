"""GlobalTracker: gated association into global ids, keeping ids, holding lost tracks, re-adoption."""

import numpy as np
import pytest

from fusion_server.global_tracks import GlobalTracker, ground_distance_m
from shared.messages import TrackItem, TracksMessage

LAT, LON = 47.67, 9.27
M_LAT = 1.0 / 111_320.0  # degrees of latitude per metre


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def msg(uav: str, *items: tuple[int, float, float], cls: str = "person") -> TracksMessage:
    """items: (local id, metres north of LAT, metres east of LON)."""
    m_lon = M_LAT / np.cos(np.radians(LAT))
    return TracksMessage(uav=uav, t=0.0, tracks=tuple(
        TrackItem(id=i, cls=cls, lat=LAT + n * M_LAT, lon=LON + e * m_lon, score=0.9, vel_en=(0.0, 0.0))
        for i, n, e in items
    ))


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def tracker(clock: Clock) -> GlobalTracker:
    return GlobalTracker(gate_m=5.0, hold_s=10.0, member_ttl_s=2.0, history_interval_s=0.0,
                         clock=clock, wall=clock)


def gids(tracker: GlobalTracker) -> dict[tuple[str, int], int]:
    return {m: r.gid for r in tracker.records() for m in r.active}


def test_ground_distance_is_metres():
    assert ground_distance_m(LAT, LON, LAT + 10 * M_LAT, LON) == pytest.approx(10.0, rel=1e-3)


def test_two_uavs_seeing_one_object_share_a_global_id_and_far_objects_do_not(tracker):
    tracker.update(msg("a", (1, 0.0, 0.0), (2, 50.0, 0.0)))
    tracker.update(msg("b", (7, 1.0, 1.0), (8, -40.0, 0.0)))
    ids = gids(tracker)
    assert ids[("a", 1)] == ids[("b", 7)]
    assert len({ids[("a", 2)], ids[("b", 8)], ids[("a", 1)]}) == 3
    joint = tracker.joint_message()
    shared = next(t for t in joint.tracks if t.gid == ids[("a", 1)])
    assert set(shared.members) == {("a", 1), ("b", 7)}
    assert shared.lat == pytest.approx(LAT + 0.5 * M_LAT, abs=1e-9)  # mean of the two reports


def test_classes_never_associate(tracker):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    tracker.update(msg("b", (1, 0.0, 0.0), cls="boat"))
    assert len(tracker.records()) == 2


def test_a_mapped_local_id_keeps_its_global_id_even_when_it_moves_away(tracker):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    first = gids(tracker)[("a", 1)]
    tracker.update(msg("a", (1, 30.0, 0.0)))
    assert gids(tracker)[("a", 1)] == first


def test_track_survives_while_another_uav_reports_it_then_for_the_hold_time(tracker, clock):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    tracker.update(msg("b", (5, 0.5, 0.0)))
    gid = gids(tracker)[("a", 1)]
    clock.now = 1.0
    tracker.update(msg("a"))  # a lost it
    tracker.update(msg("b", (5, 0.5, 0.0)))
    rec = tracker.records()[0]
    assert rec.gid == gid and rec.status == "tracked" and rec.active == (("b", 5),)
    clock.now = 2.0
    tracker.update(msg("b"))  # nobody reports it: held
    assert tracker.records()[0].status == "lost"
    clock.now = 11.0
    tracker.expire()
    assert tracker.records()[0].status == "lost"
    clock.now = 12.5
    tracker.expire()
    assert tracker.records() == []
    assert [r.status for r in tracker.records(include_ended=True)] == ["ended"]


def test_a_returning_uav_readopts_the_global_id_with_a_new_local_id(tracker, clock):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    gid = gids(tracker)[("a", 1)]
    clock.now = 1.0
    tracker.update(msg("a"))
    clock.now = 5.0
    tracker.update(msg("a", (42, 1.0, -1.0)))
    assert gids(tracker)[("a", 42)] == gid
    assert set(tracker.records()[0].members) == {("a", 1), ("a", 42)}


def test_members_of_a_silent_uav_are_lost_after_the_member_ttl(tracker, clock):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    clock.now = 2.5
    assert tracker.expire()
    assert tracker.records()[0].status == "lost"


def test_history_is_bounded(clock):
    tracker = GlobalTracker(history_len=5, history_interval_s=0.0, clock=clock, wall=clock)
    for i in range(20):
        clock.now = float(i)
        tracker.update(msg("a", (1, float(i), 0.0)))
    history = tracker.records()[0].history
    assert len(history) == 5 and history[-1][0] == 19.0


def test_restore_holds_tracks_and_keeps_the_local_id_mapping(tracker, clock):
    tracker.update(msg("a", (1, 0.0, 0.0)), now=0.0)
    saved, history = tracker.drain_changes()
    assert history and saved
    clock.now = 100.0
    fresh = GlobalTracker(gate_m=5.0, hold_s=10.0, clock=clock, wall=clock)
    assert fresh.restore(saved) == 1
    assert fresh.records()[0].status == "lost"
    fresh.update(msg("a", (1, 20.0, 0.0)))  # same local id, outside the gate: still the same gid
    assert gids(fresh)[("a", 1)] == saved[0].gid
    fresh.update(msg("b", (3, 0.0, 50.0)))
    assert max(r.gid for r in fresh.records()) == saved[0].gid + 1


def grid_msg(uav: str, n: int, first_id: int = 0, spacing_m: float = 1.0, north0_m: float = 0.0) -> TracksMessage:
    """n tracks on a square grid spacing_m apart starting north0_m north of (LAT, LON)."""
    side = int(np.ceil(np.sqrt(n)))
    return msg(uav, *((first_id + i, north0_m + (i // side) * spacing_m, (i % side) * spacing_m) for i in range(n)))


def test_a_huge_tracks_message_is_truncated_to_its_best_tracks(clock):
    tracker = GlobalTracker(gate_m=5.0, max_tracks_per_message=100, clock=clock, wall=clock)
    items = list(grid_msg("evil", 300).tracks)
    best = {item.id for item in items[:100]}
    scored = [TrackItem(id=item.id, cls=item.cls, lat=item.lat, lon=item.lon, score=0.9 if item.id in best else 0.1,
                        vel_en=item.vel_en) for item in items]
    tracker.update(TracksMessage(uav="evil", t=0.0, tracks=tuple(scored)))
    assert len(tracker) == 100
    assert {m[1] for r in tracker.records() for m in r.members} == best
    assert tracker.dropped() == {"too_many_tracks": 200}


def test_association_of_thousands_in_the_gate_is_one_to_one_and_gated(clock):
    # probe: 2 UAV ids x 4,000 tracks inside the gate blocked /healthz for 6 s (cubic assignment)
    tracker = GlobalTracker(gate_m=5.0, clock=clock, wall=clock)
    tracker.update(grid_msg("uav1", 4000))
    tracker.update(grid_msg("uav2", 4000, first_id=10_000))
    stats = tracker.stats()
    assert stats["greedy_components"] >= 1  # too large for the exact assignment: greedy
    records = tracker.records()
    per_uav: dict[str, list[int]] = {"uav1": [], "uav2": []}
    for record in records:
        uavs = [m[0] for m in record.members]
        assert sorted(uavs) in (["uav1"], ["uav1", "uav2"]), record.members  # one-to-one
        for uav in uavs:
            per_uav[uav].append(record.gid)
    assert len(per_uav["uav1"]) == 1000 and len(per_uav["uav2"]) == 1000  # each message truncated
    shared = [r for r in records if len(r.members) == 2]
    assert len(shared) >= 900  # the same grid: nearly everything pairs up
    for record in shared:  # and only inside the gate (positions are the members' mean)
        assert record.lat == pytest.approx(LAT, abs=40 * M_LAT)


def test_small_components_keep_the_optimal_assignment(tracker):
    # greedy (nearest first) would pair 0 with 11 (1.5 m) and leave 10 alone (7 m from 1, beyond the
    # gate); the optimal assignment pairs 0-10 (3 m) and 1-11 (2.5 m)
    tracker.update(msg("uav1", (0, 0.0, 0.0), (1, 0.0, 4.0)))
    tracker.update(msg("uav2", (10, 0.0, -3.0), (11, 0.0, 1.5)))
    by_member = {m: r.gid for r in tracker.records() for m in r.members}
    assert by_member[("uav2", 10)] == by_member[("uav1", 0)]
    assert by_member[("uav2", 11)] == by_member[("uav1", 1)]
    assert tracker.stats()["greedy_components"] == 0


def test_the_global_tracks_are_capped_and_a_flooding_uav_pays_with_its_own(clock):
    tracker = GlobalTracker(gate_m=5.0, hold_s=60.0, max_tracks_per_message=20, max_global_tracks=50,
                            clock=clock, wall=clock)
    tracker.update(msg("honest", (1, 0.0, 0.0)))
    for k in range(10):  # 200 fresh ids, far from each other and from the honest track
        clock.now += 0.1
        tracker.update(grid_msg("flood", 20, first_id=1000 * k, spacing_m=100.0, north0_m=1000.0 + 10 * k))
    assert len(tracker) <= 50
    clock.now += 0.1
    tracker.update(msg("honest", (1, 0.0, 0.0), (2, 5000.0, 0.0)))  # a new object still gets an id
    members = {m for r in tracker.records() for m in r.members}
    assert {("honest", 1), ("honest", 2)} <= members
    assert len(tracker) <= 50
    assert tracker.dropped().get("evicted_lost", 0) > 0


# ---- shards: disjoint id series, adoption of another shard's id, handing a held id over ----------------
def test_id_series_of_a_shard_survives_restore(clock):
    shard1 = GlobalTracker(gate_m=5.0, next_gid=2, gid_step=3, clock=clock, wall=clock)  # shard 1 of 3
    shard1.update(msg("a", (1, 0, 0), (2, 100, 0)))
    assert sorted(r.gid for r in shard1.records()) == [2, 5]
    again = GlobalTracker(gate_m=5.0, next_gid=2, gid_step=3, clock=clock, wall=clock)
    again.restore(shard1.records())
    again.update(msg("b", (1, 500, 0)))
    assert max(r.gid for r in again.records()) == 8  # after 5 in the series 2, 5, 8: never another shard's
    with pytest.raises(ValueError, match="gid_step"):
        GlobalTracker(gid_step=0)


def test_adopted_id_and_hand_over(clock):
    asked = []

    def adopt(uav, local_id, cls, lat, lon):
        asked.append((uav, local_id, cls))
        return 41 if local_id == 7 else None

    tracker = GlobalTracker(gate_m=5.0, hold_s=10.0, member_ttl_s=2.0, next_gid=2, gid_step=2, adopt=adopt,
                            clock=clock, wall=clock)
    tracker.update(msg("a", (7, 0, 0), (8, 100, 0)))
    assert sorted(r.gid for r in tracker.records()) == [2, 41] and tracker.handovers["in"] == 1
    assert asked == [("a", 7, "person"), ("a", 8, "person")]
    tracker.update(msg("a", (7, 0, 1)))  # a known local track: no question asked
    assert len(asked) == 2
    assert not tracker.hand_over(41)  # still reported here: it stays
    tracker.update(msg("a", (8, 100, 0)))  # 7 not reported any more: 41 is held
    clock.now += 0.1
    tracker.expire()
    assert tracker.hand_over(41) and tracker.handovers["out"] == 1
    assert [r.gid for r in tracker.records()] == [2]
    assert not tracker.hand_over(12345)


def test_joint_message_says_which_members_still_report_each_track(tracker, clock):
    tracker.update(msg("a", (1, 0.0, 0.0)))
    tracker.update(msg("b", (7, 1.0, 1.0)))
    (item,) = tracker.joint_message().tracks
    assert item.active is None and item.active_members == item.members  # all report it: left out
    tracker.update(msg("a"))  # a no longer sees it, b does
    (item,) = tracker.joint_message().tracks
    assert item.members == (("a", 1), ("b", 7)) and item.active == (1,)
    assert (item.active_members == (("b", 7),)) and tracker.records()[0].status == "tracked"
    clock.now += 3.0  # b's member times out: held, nobody reports it
    tracker.expire()
    (item,) = tracker.joint_message().tracks
    assert item.active == () and tracker.records()[0].status == "lost"


def test_a_held_track_in_a_crowd_keeps_its_recent_members_only(tracker, clock):
    """A crowd: every second the UAV's local track there ends and a new one starts within the gate, so the held
    global track takes each in and never ends. Every ended member was kept and sent with every joint/tracks
    message (a soak: the message doubled in 12 minutes, heading for 256 members a track in an hour)."""
    from fusion_server.global_tracks import MAX_INACTIVE_MEMBERS

    for k in range(200):
        clock.now = float(k)
        tracker.update(msg("a", (k, 0.1 * (k % 7), 0.0), (10_000, 0.0, 30.0)))  # plus one steady track
    (track, steady) = tracker.records()
    assert len(track.active) == 1 and len(track.members) == 1 + MAX_INACTIVE_MEMBERS
    assert track.members[-1] == ("a", 199) and ("a", 191) in track.members and ("a", 190) not in track.members
    message = tracker.joint_message()
    assert max(len(item.members) for item in message.tracks) == 1 + MAX_INACTIVE_MEMBERS
    assert tracker.stats()["local_ids"] == 1 + MAX_INACTIVE_MEMBERS + 1  # the ids forgotten with their members
    # a recently ended local id that comes back keeps its global id
    clock.now = 200.0
    tracker.update(msg("a", (195, 0.0, 0.0), (10_000, 0.0, 30.0)))
    assert gids(tracker)[("a", 195)] == track.gid and steady.members == (("a", 10_000),)


def test_without_a_database_the_changes_are_not_collected(clock):
    """A server run without --db never drains the changes: history rows, ended tracks and changed ids grew all
    flight (63k rows in 8 minutes of a soak)."""
    kept = GlobalTracker(hold_s=1.0, history_interval_s=0.0, clock=clock, wall=clock)
    quiet = GlobalTracker(hold_s=1.0, history_interval_s=0.0, keep_changes=False, clock=clock, wall=clock)
    for k in range(50):
        clock.now = float(k)
        for t in (kept, quiet):
            t.update(msg("a", (k // 10, 100.0 * (k // 10), 0.0)))
            t.expire()
    records, history = kept.drain_changes()
    assert len(records) == 5 and len(history) == 50
    assert quiet.drain_changes() == ([], [])
    assert [r.gid for r in quiet.records(include_ended=True)] == [r.gid for r in kept.records(include_ended=True)]


def test_a_long_reported_member_that_ends_is_the_most_recent_one_kept(tracker, clock):
    """The trim kept the members inserted last: a UAV's local id reported all along (updated in place, first in the
    list) was the first one dropped when it missed one report, and came back under another global id."""
    tracker.update(msg("a", (1, 0.0, 0.0)))
    gid = gids(tracker)[("a", 1)]
    for k in range(12):  # b's local tracks come and go there while a keeps reporting its id 1
        clock.now = 0.1 * (k + 1)
        tracker.update(msg("a", (1, 0.0, 0.0)))
        tracker.update(msg("b", (100 + k, 0.5, 0.0)))
    clock.now = 1.5
    tracker.update(msg("a"))  # one missed report
    (track,) = tracker.records()
    assert ("a", 1) in track.members  # the most recent of the ended ones
    clock.now = 1.6
    tracker.update(msg("a", (1, 6.0, 0.0)))  # back, 6 m off (beyond this tracker's 5 m gate)
    assert gids(tracker)[("a", 1)] == gid


def test_a_held_track_ended_to_make_room_is_not_given_to_a_later_item(clock):
    """Making room for a new track could end the held track a later item of the same message was matched to: the
    item joined the ended track and its local id pointed at a global id that no longer existed."""
    tracker = GlobalTracker(gate_m=10.0, max_tracks_per_uav=1, clock=clock, wall=clock)
    tracker.update(msg("a", (1, 0.0, 0.0)))
    clock.now = 0.1
    tracker.update(msg("a"))  # its track is held
    clock.now = 0.2
    tracker.update(msg("a", (5, 1000.0, 0.0), (6, 0.0, 0.0)))  # 5: new and far (ends the held one), 6: at it
    live = {r.gid for r in tracker.records()}
    assert set(gids(tracker).values()) <= live and set(tracker._local.values()) <= live
    assert {m for item in tracker.joint_message().tracks for m in item.members} == {("a", 5)}


def test_a_held_track_reported_again_is_not_evicted_for_a_new_one_in_the_same_message(clock):
    """Its id missed once, then back together with a new id: making room for the new one ended the held track
    the returning id had just re-claimed (its mark of held is cleared after the message), and the id was refused
    from then on."""
    tracker = GlobalTracker(gate_m=10.0, max_tracks_per_uav=1, clock=clock, wall=clock)
    tracker.update(msg("a", (1, 0.0, 0.0)))
    gid = gids(tracker)[("a", 1)]
    clock.now = 0.5
    tracker.update(msg("a"))
    clock.now = 1.0
    tracker.update(msg("a", (1, 0.0, 0.0), (2, 1000.0, 0.0)))
    clock.now = 1.5
    tracker.update(msg("a", (1, 0.0, 0.0), (2, 1000.0, 0.0)))
    assert gids(tracker) == {("a", 1): gid} and tracker.dropped() == {"uav_track_quota": 2}


def test_a_uavs_new_local_track_does_not_join_a_global_track_it_sees_elsewhere(clock):
    """Two people 6 m apart; the UAV's track of the first goes unreported for one message (a missed detection)
    while its new track of the second appears: the second joined the first's global track (nearest, unclaimed),
    and the global track then held two people as they parted (the crowd soak: 78 of 152 such tracks spanned more
    than 10 m after 9 minutes)."""
    tracker = GlobalTracker(gate_m=10.0, clock=clock, wall=clock)
    tracker.update(msg("a", (1, 0.0, 0.0)))
    tracker.update(msg("b", (7, 0.5, 0.0)))
    gid = gids(tracker)[("a", 1)]
    clock.now = 0.2
    tracker.update(msg("a", (2, 6.0, 0.0)))  # id 1 missed in this message; id 2 is someone else, 6 m away
    assert gids(tracker)[("a", 2)] != gid
    clock.now = 0.4
    tracker.update(msg("a", (1, 0.0, 0.0), (2, 6.0, 0.0)))
    assert gids(tracker)[("a", 1)] == gid == gids(tracker)[("b", 7)]


@pytest.mark.parametrize(("north_m", "speed_mps"), [(1.0, 0.0), (4.0, 20.0)])
def test_a_tracker_id_switch_keeps_the_global_id(clock, north_m, speed_mps):
    """The same object under a new local id in the message where the old one ends, 1 m on, or 4 m on at 20 m/s
    (a jetski): the old member's place moved on by its velocity, so not 'elsewhere'."""
    tracker = GlobalTracker(gate_m=10.0, clock=clock, wall=clock)
    m_lon = M_LAT / np.cos(np.radians(LAT))
    item = TrackItem(id=1, cls="person", lat=LAT, lon=LON, score=0.9, vel_en=(0.0, speed_mps))
    tracker.update(TracksMessage(uav="a", t=0.0, tracks=(item,)))
    gid = gids(tracker)[("a", 1)]
    clock.now = 0.2
    moved = TrackItem(id=5, cls="person", lat=LAT + north_m * M_LAT, lon=LON + 0.0 * m_lon, score=0.9,
                      vel_en=(0.0, speed_mps))
    tracker.update(TracksMessage(uav="a", t=0.2, tracks=(moved,)))
    assert gids(tracker)[("a", 5)] == gid


def test_a_local_id_that_moves_to_another_global_track_stops_being_a_member_of_its_old_one():
    # probe (audit): person 1 (local 1) leaves; person 2 (local 2), 6 m away, joins person 1's held global track; person
    # 1 comes back under its old local id beside person 2: local 1 takes its track back, local 2 moves to a new one but
    # stayed an active member of the old: that track stayed "tracked" forever (1,999 such after 48 h of one episode a
    # minute, then the UAV's new tracks refused as uav_track_quota)
    now = [0.0]
    tracker = GlobalTracker(clock=lambda: now[0], wall=lambda: 1.7e9 + now[0])
    m = 1 / 111_320.0

    def send(items: list[tuple[int, float]], n: int) -> None:
        for _ in range(n):
            tracker.update(TracksMessage(uav="uav1", t=1.7e9 + now[0], tracks=tuple(
                TrackItem(id=i, cls="person", lat=48 + dn * m, lon=9.0, score=0.8, vel_en=(0.0, 0.0))
                for i, dn in items)))
            now[0] += 0.2
            tracker.expire()

    send([(1, 0.0)], 10)
    send([], 5)
    send([(2, 6.0)], 10)
    first = {r.gid: r for r in tracker.records()}
    assert len(first) == 1 and set(next(iter(first.values())).active) == {("uav1", 2)}
    send([(1, 0.0), (2, 6.0)], 10)
    records = {r.gid: r for r in tracker.records()}
    assert len(records) == 2
    assert sorted(len(r.active) for r in records.values()) == [1, 1]  # each local id active on one track only
    assert {k for r in records.values() for k in r.active} == {("uav1", 1), ("uav1", 2)}
    send([], 5)
    for _ in range(300):  # a minute of silence: both held, then ended
        now[0] += 0.2
        tracker.expire()
    assert tracker.records() == [] or all(r.status == "ended" for r in tracker.records())

"""One object, one id across UAVs: the fusion server's global tracker on the frame clock and the MTMC scoring."""

import numpy as np
import pytest

from shared.messages import TrackItem, TracksMessage
from sim.cross_uav import CROSS_METRICS, CrossUavRecorder, cross_uav_metrics
from sim.track_eval import SequenceTracks, SequenceTruth

LAT, LON = 47.0, 9.0
M = 1.0 / 111_320.0  # degrees of latitude per metre


def _truth(frames: int, objects: list[int]) -> SequenceTruth:
    boxes = np.array([[100.0 * k, 100.0, 100.0 * k + 50.0, 150.0] for k in range(len(objects))]).reshape(-1, 4)
    return SequenceTruth({f: (np.array(objects, dtype=np.int64), boxes.copy()) for f in range(frames)}, 30.0)


def _tracks(frames: int, local_ids: list[int]) -> SequenceTracks:
    boxes = np.array([[100.0 * k, 100.0, 100.0 * k + 50.0, 150.0] for k in range(len(local_ids))]).reshape(-1, 4)
    return SequenceTracks({f: (np.array(local_ids, dtype=np.int64), boxes.copy(), np.ones(len(local_ids)))
                           for f in range(frames)})


def _msg(uav: str, t: float, *tracks: tuple[int, float]) -> TracksMessage:
    """Tracks (local id, metres north of LAT, LON) of class person."""
    return TracksMessage(uav=uav, t=t, tracks=tuple(TrackItem(id=i, cls="person", lat=LAT + north * M, lon=LON,
                                                               score=0.9, vel_en=(0.0, 0.0)) for i, north in tracks))


def test_one_global_id_on_both_uavs_scores_as_one_identity():
    truths = {1: _truth(10, [7]), 2: _truth(10, [7])}
    seqs = {1: _tracks(10, [3]), 2: _tracks(10, [5])}  # local ids differ, as two UAVs' trackers number them
    same = cross_uav_metrics(truths, seqs, {1: {f: {3: 40} for f in range(10)}, 2: {f: {5: 40} for f in range(10)}})
    assert same["IDF1"] == pytest.approx(100.0) and same["same_id"] == pytest.approx(100.0)
    assert same["shared_objects"] == 1 and same["IDs"] == 0
    # kept apart, the object has two ids: half its frames carry the one IDF1 picks
    assert same["IDF1_separate"] == pytest.approx(50.0) and same["IDs_separate"] == 1
    apart = cross_uav_metrics(truths, seqs, {1: {f: {3: 40} for f in range(10)}, 2: {f: {5: 41} for f in range(10)}})
    assert apart["IDF1"] == pytest.approx(50.0) and apart["same_id"] == pytest.approx(0.0)
    assert set(CROSS_METRICS) <= set(same) and np.isnan(same["IDF1_first_look"])  # no first-look ids given
    both = cross_uav_metrics(truths, seqs, {1: {f: {3: 40} for f in range(10)}, 2: {f: {5: 40} for f in range(10)}},
                             {1: {f: {3: 40} for f in range(10)}, 2: {f: {5: 41} for f in range(10)}})
    assert both["IDF1"] == pytest.approx(100.0) and both["IDF1_first_look"] == pytest.approx(50.0)
    assert both["same_id_first_look"] == pytest.approx(0.0)


def test_frames_before_the_first_global_id_carry_it_and_without_any_the_local_id_stays_apart():
    truths = {1: _truth(10, [7]), 2: _truth(10, [7])}
    seqs = {1: _tracks(10, [3]), 2: _tracks(10, [3])}  # the same local number on both UAVs: still two tracks
    late = {1: {f: {3: 40} for f in range(10)}, 2: {f: ({3: 40} if f >= 6 else {}) for f in range(10)}}
    assert cross_uav_metrics(truths, seqs, late)["IDF1"] == pytest.approx(100.0)
    none = cross_uav_metrics(truths, seqs, {1: {f: {3: 40} for f in range(10)}})
    assert none["IDF1"] == pytest.approx(50.0) and none["same_id"] == pytest.approx(0.0)


def test_objects_one_uav_alone_tracks_are_not_shared():
    truths = {1: _truth(5, [7, 8]), 2: _truth(5, [9])}
    seqs = {1: _tracks(5, [1, 2]), 2: _tracks(5, [1])}
    out = cross_uav_metrics(truths, seqs, {})
    assert out["shared_objects"] == 0 and np.isnan(out["same_id"])
    assert out["IDF1"] == pytest.approx(100.0) == out["IDF1_separate"]


def test_the_recorder_joins_tracks_within_the_gate_at_the_publish_rate():
    rec = CrossUavRecorder(period_s=0.2)
    rec(1, 0, _msg("uav1", 0.0, (3, 0.0), (4, 40.0)))
    rec(2, 0, _msg("uav2", 0.0, (8, 2.0), (9, 80.0)))  # 2 m from uav1's track 3: one object; 9 is 40 m from 4
    g = rec.gids
    assert g[2][0][8] == g[1][0][3] and g[2][0][9] not in (g[1][0][3], g[1][0][4])
    assert rec.first_look_gids[2][0] == {8: g[1][0][3], 9: g[2][0][9]}  # the baseline tracker saw the same
    # within the publish period a new track is not heard yet: no global id for it in that frame
    rec(2, 1, _msg("uav2", 0.1, (8, 2.0), (9, 80.0), (10, 40.5)))
    assert 10 not in rec.gids[2][1]
    rec(2, 2, _msg("uav2", 0.2, (8, 2.0), (9, 80.0), (10, 40.5)))
    assert rec.gids[2][2][10] == g[1][0][4]


def test_one_global_id_on_two_tracks_of_a_frame_counts_once():
    truths = {1: _truth(10, [7, 8])}
    seqs = {1: _tracks(10, [3, 4])}  # two people, two local tracks, both mapped to global id 40
    out = cross_uav_metrics(truths, seqs, {1: {f: {3: 40, 4: 40} for f in range(10)}})
    assert out["IDF1"] == pytest.approx(100.0) and out["IDs"] == 0  # the second keeps an id of its own

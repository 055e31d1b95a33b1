"""A partner's confidence lent along a shared global track (agent.track_lending): which local tracks qualify, how
far a detection's score moves, and an agent on real Zenoh whose written detections take it."""

from __future__ import annotations

import math
import threading

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.frame_result import FrameResult
from agent.node import AgentNode
from agent.pipeline_config import PipelineConfig
from agent.track_lending import TrackLending, lend_scores, partner_scores
from agent.tracking.tracker import TrackOutput
from shared.messages import JointTrackItem, JointTracksMessage, TrackItem, TracksMessage, encode_joint_tracks
from tests.agent.test_node_zenoh import BOX_A, KEYS, RunningAgent, ScriptedSource, agent_settings
from tests.netutil import wait_until


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def joint(*tracks: tuple[float, tuple[tuple[str, int], ...], tuple[int, ...] | None]) -> JointTracksMessage:
    return JointTracksMessage(t=0.0, tracks=tuple(
        JointTrackItem(gid=i + 1, cls="person", lat=48.5, lon=9.0, score=score, vel_en=(0.0, 0.0), members=members,
                       active=active)
        for i, (score, members, active) in enumerate(tracks)))


def result(boxes: list[tuple[float, float, float, float]], scores: list[float]) -> FrameResult:
    k = len(scores)
    return FrameResult(boxes_xyxy=np.array(boxes, np.float32).reshape(-1, 4), scores=np.array(scores, np.float32),
                       raw_scores=np.array(scores, np.float32), class_ids=np.ones(k, np.int64),
                       lat=np.full(k, 48.5), lon=np.full(k, 9.0), n_candidates=k, n_size_filtered=0,
                       n_georeferenced=k, from_joint=np.zeros(k, bool))


def track(tid: int, box: tuple[float, float, float, float], *, matched: bool = True) -> TrackOutput:
    return TrackOutput(id=tid, cls=1, box_xyxy=box, lat=48.5, lon=9.0, vel_en=(0.0, 0.0), score=0.5, confirmed=True,
                       matched=matched, hits=5, time_since_update_s=0.0)


BOXES = [(10.0, 10.0, 30.0, 50.0), (100.0, 10.0, 120.0, 50.0), (200.0, 10.0, 220.0, 50.0)]


# ---- which local tracks take a partner's confidence ------------------------------------------------
def test_a_track_shared_with_another_active_uav_takes_the_global_score():
    msg = joint((0.95, (("uav1", 7), ("uav2", 3)), None),      # shared, both active: lent
                (0.90, (("uav1", 8),), None),                  # this UAV's alone: nothing to lend
                (0.90, (("uav1", 9), ("uav2", 4)), (0,)),      # the partner no longer reports it
                (0.60, (("uav1", 10), ("uav2", 5)), None),     # the global score is this UAV's own
                (0.97, (("uav2", 6), ("uav3", 1)), None))      # none of this UAV's tracks
    assert partner_scores(msg, "uav1", {7: 0.4, 8: 0.3, 9: 0.3, 10: 0.6}) == {7: 0.95}
    assert partner_scores(None, "uav1", {7: 0.4}) == {}


def test_a_track_this_uav_has_not_reported_takes_nothing():
    msg = joint((0.95, (("uav1", 7), ("uav2", 3)), None))
    assert partner_scores(msg, "uav1", {}) == {}


# ---- how far a detection's score moves ---------------------------------------------------------------
def test_the_detection_of_a_lent_track_moves_the_weights_share_in_log_odds_and_the_order_follows():
    res = result(BOXES, [0.9, 0.6, 0.2])
    out = lend_scores(res, [track(1, BOXES[0]), track(2, BOXES[2])], {2: 0.98}, 0.5)
    expected = 1 / (1 + math.exp(-(logit(0.2) + 0.5 * (logit(0.98) - logit(0.2)))))
    assert np.allclose(out.scores, [0.9, expected, 0.6], atol=1e-6)  # 0.2 -> 0.78: now second
    assert np.allclose(out.boxes_xyxy[1], BOXES[2]) and np.allclose(out.raw_scores, [0.9, 0.2, 0.6])
    assert len(out) == 3 and out.n_candidates == 3


def test_a_lower_partner_score_an_unmatched_track_or_weight_zero_change_nothing():
    res = result(BOXES, [0.9, 0.6, 0.2])
    assert lend_scores(res, [track(1, BOXES[0])], {1: 0.5}, 0.5) is res           # lower than its own
    assert lend_scores(res, [track(3, BOXES[2], matched=False)], {3: 0.99}, 1.0) is res
    assert lend_scores(res, [track(3, BOXES[2])], {3: 0.99}, 0.0) is res


@given(own=st.floats(0.01, 0.99), partner=st.floats(0.01, 0.99), weight=st.floats(0.0, 1.0))
def test_a_lent_score_lies_between_its_own_and_the_partners(own, partner, weight):
    out = lend_scores(result(BOXES[:1], [own]), [track(1, BOXES[0])], {1: partner}, weight)
    lent = float(out.scores[0])
    assert min(own, max(own, partner)) - 1e-5 <= lent <= max(own, partner) + 1e-5


@pytest.mark.parametrize("weight", [-0.1, 1.5, float("nan")])
def test_a_weight_outside_zero_to_one_is_refused(weight):
    with pytest.raises(ValueError, match="weight"):
        TrackLending("uav1", weight)
    with pytest.raises(ValueError, match="track_lending"):
        PipelineConfig(track_lending=weight)


def test_track_lending_follows_what_the_uav_reported():
    lending = TrackLending("uav1", 1.0)
    msg = joint((0.95, (("uav1", 7), ("uav2", 3)), None))
    res = result(BOXES[:1], [0.3])
    assert lending.apply(res, [track(7, BOXES[0])], msg, 0.0) is res  # nothing reported yet: its own score unknown
    lending.reported(TracksMessage(uav="uav1", t=0.0, tracks=()))
    assert lending.apply(res, [track(7, BOXES[0])], msg, 0.1) is res
    lending.reported(TracksMessage(uav="uav1", t=0.0, tracks=(TrackItem(7, "person", 48.5, 9.0, 0.3, (0.0, 0.0)),)))
    out = lending.apply(res, [track(7, BOXES[0])], msg, 0.2)
    assert out.scores[0] == pytest.approx(0.95, abs=1e-6) and lending.lent_detections == 1


def test_a_track_keeps_the_best_lent_score_for_memory_s_of_frame_time():
    lending = TrackLending("uav1", 1.0, memory_s=2.0)
    lending.reported(TracksMessage(uav="uav1", t=0.0, tracks=(TrackItem(7, "person", 48.5, 9.0, 0.3, (0.0, 0.0)),)))
    res, tracks = result(BOXES[:1], [0.3]), [track(7, BOXES[0])]
    assert lending.apply(res, tracks, joint((0.95, (("uav1", 7), ("uav2", 3)), None)), 10.0).scores[0] == \
        pytest.approx(0.95, abs=1e-6)
    weaker = joint((0.6, (("uav1", 7), ("uav2", 3)), None))  # the partner's latest frame saw it less well
    assert lending.apply(res, tracks, weaker, 11.9).scores[0] == pytest.approx(0.95, abs=1e-6)
    assert lending.apply(res, tracks, weaker, 12.1).scores[0] == pytest.approx(0.6, abs=1e-6)
    gone = joint((0.95, (("uav1", 7),), None))  # no partner on the track any more
    assert lending.apply(res, tracks, gone, 14.2) is res
    assert lending.apply(res, tracks, gone, 5.0) is res  # a replay starting again: nothing from its future


# ---- an agent on Zenoh ---------------------------------------------------------------------------------
def test_the_agent_writes_its_detection_with_the_confidence_a_partner_reports_on_the_shared_track(server, server_port):
    seen: list[float] = []
    source = ScriptedSource(150, lambda i: [(BOX_A, 0.6)])  # no memory map: its score stays the detector's
    node = AgentNode(agent_settings(server_port, "uav1", speed=1.0, joint_window=False), source,
                     PipelineConfig(use_memory=False, track_lending=0.5),
                     on_frame=lambda frame, res, tracks: seen.extend(float(s) for s in res.scores))
    stop = threading.Event()
    reported: dict[int, float] = {}

    def serve_joint_tracks() -> None:  # the server's 5 Hz joint tracks: uav2 reports this UAV's object at 0.97
        while not stop.wait(0.2):
            mine = [msgpack.unpackb(p) for _, p in server.latest("uav_tracks")]
            items = [t for m in mine[-1:] for t in m["tracks"]]
            if items:
                reported.update({t["id"]: t["score"] for t in items})
                lid = items[0]["id"]
                server.put(KEYS.joint_tracks(), encode_joint_tracks(joint((0.97, (("uav1", lid), ("uav2", 5)), None))))

    publisher = threading.Thread(target=serve_joint_tracks, daemon=True)
    publisher.start()
    try:
        with RunningAgent(node) as agent:
            wait_until(lambda: node.link.joint_tracks() is not None, timeout_s=15.0)
            summary = agent.join(30.0)
    finally:
        stop.set()
        publisher.join()
    assert summary["detections_lent"] > 0
    assert list(reported.values()) == pytest.approx([0.6] * len(reported))  # its own score, as it reported it
    assert seen[:3] == pytest.approx([0.6] * 3)  # before any joint tracks
    assert seen[-1] == pytest.approx(1 / (1 + math.exp(-(logit(0.6) + 0.5 * (logit(0.97) - logit(0.6))))))

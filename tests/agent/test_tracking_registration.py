"""The tracker's registration to its predicted tracks: a common offset of all detections is found; a
crowd, too few pairs or disagreeing pairs give none. The tracker applies it before gating."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.tracking.registration import track_offset

TRACKS = np.array([[0.0, 0.0], [12.0, 3.0], [-9.0, 14.0], [20.0, -11.0], [-15.0, -8.0]])


@settings(max_examples=40, deadline=None)
@given(st.floats(-2.5, 2.5), st.floats(-2.5, 2.5), st.integers(0, 2**31))
def test_a_common_offset_is_recovered(dx: float, dy: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    dets = TRACKS - np.array([dx, dy]) + rng.normal(0.0, 0.1, TRACKS.shape)
    off = track_offset(dets, TRACKS, gate_m=4.0, min_pairs=3)
    assert off is not None
    assert off[0] == pytest.approx(dx, abs=0.2) and off[1] == pytest.approx(dy, abs=0.2)


def test_too_few_pairs_or_no_agreement_give_none() -> None:
    assert track_offset(TRACKS[:2] + 1.0, TRACKS[:2], gate_m=4.0, min_pairs=3) is None
    rng = np.random.default_rng(0)
    scattered = TRACKS + rng.uniform(-3.5, 3.5, TRACKS.shape) * np.array([[1, 1], [-1, 1], [1, -1], [-1, -1], [0, 1]])
    off = track_offset(scattered, TRACKS, gate_m=4.0, min_pairs=3, inlier_m=0.5)
    assert off is None
    assert track_offset(np.zeros((0, 2)), TRACKS, gate_m=4.0, min_pairs=3) is None


def test_the_tracker_removes_a_per_frame_common_offset_before_gating() -> None:
    from agent.tracking import GpsTracker, TrackerConfig
    from tests.agent.test_tracker import CAM, CLASSES, FPS, observe, pose_at

    people = [(-8.0, 25.0), (0.0, 30.0), (7.0, 26.0), (-3.0, 38.0), (9.0, 40.0)]
    east, north = (np.array(v) for v in zip(*people, strict=True))
    pose = pose_at()
    rng = np.random.default_rng(5)
    tracker = GpsTracker(TrackerConfig(register_tracks=True), CLASSES)  # off by default
    ids: list[set[int]] = [set() for _ in people]
    residual = []
    for k in range(90):
        jitter = rng.normal(0.0, 1.2, 2)  # the whole frame moves: GPS/gimbal jitter
        result = observe(east + jitter[0], north + jitter[1], pose, noise_m=0.05, rng=rng)
        assert len(result) == len(people)
        outs = tracker.update(result, pose, 1.7e9 + k / FPS, CAM)
        if k < 10:
            continue
        # the tracks keep the frame they were born in: offset + jitter is that frame's constant
        assert tracker.last_offset_en is not None
        residual.append(np.add(tracker.last_offset_en, jitter))
        boxes = {tr.id: tr.box_xyxy for tr in outs if tr.confirmed and tr.matched}
        for i, box in enumerate(result.boxes_xyxy):
            ids[i].update(tid for tid, b in boxes.items() if np.allclose(b, box))
    assert np.std(np.array(residual), axis=0).max() < 0.2
    assert all(len(s) == 1 for s in ids), ids  # every person keeps one id

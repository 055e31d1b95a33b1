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

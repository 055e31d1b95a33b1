"""agent.tracking.image_motion: the shift most tracks agree on, among clutter, and the offset it accumulates."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.tracking import TrackerConfig
from agent.tracking.image_motion import ImageMotion, common_shift


def _shift(pred: np.ndarray, det: np.ndarray, min_tracks: int = 3, size: float = 9.0, det_cls: np.ndarray | None = None,
           det_size: np.ndarray | None = None) -> np.ndarray | None:
    """common_shift of boxes of one size (9 px) and class, radius 8 sizes, agreeing within 1 size."""
    return common_shift(pred, np.full(len(pred), size), np.zeros(len(pred), int), det,
                        np.full(len(det), size) if det_size is None else det_size,
                        np.zeros(len(det), int) if det_cls is None else det_cls, 8.0, 1.0, min_tracks)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(3, 12), shift=st.tuples(st.floats(-45.0, 45.0), st.floats(-45.0, 45.0)),  # within 8 sizes
       clutter=st.integers(0, 30), seed=st.integers(0, 2**31 - 1))
def test_the_common_shift_is_found_among_clutter_and_missed_boxes(n, shift, clutter, seed):
    rng = np.random.default_rng(seed)
    pred = rng.uniform([0.0, 0.0], [3840.0, 2160.0], (n, 2))
    seen = pred[rng.random(n) < 0.8]  # a fifth of the objects missed by the detector
    det = np.vstack([seen + np.asarray(shift) + rng.uniform(-1.0, 1.0, seen.shape),
                     rng.uniform([0.0, 0.0], [3840.0, 2160.0], (clutter, 2))])
    found = _shift(pred, det)
    if len(seen) < 3:
        assert found is None
    else:
        assert found is not None and np.hypot(*(found - np.asarray(shift))) <= 1.5


def test_too_few_tracks_agreeing_measure_nothing():
    pred = np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 100.0]])
    det = pred[:2] + [20.0, 0.0]
    assert _shift(pred, det) is None
    found = _shift(pred, det, min_tracks=2)
    assert found is not None and found.tolist() == [20.0, 0.0]


def test_pairs_out_of_reach_or_of_another_class_do_not_vote():
    pred = np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 100.0]])
    assert _shift(pred, pred + [100.0, 0.0]) is None  # 100 px is beyond 8 sizes of 9 px
    assert _shift(pred, pred + [30.0, 0.0], det_cls=np.array([0, 0, 1])) is None
    # the smaller box's size: 100 px boxes 100 px off are no closer
    assert _shift(pred, pred + [100.0, 0.0], det_size=np.full(3, 100.0)) is None


def test_equal_votes_take_the_smaller_shift():
    pred = np.array([[100.0, 100.0]])
    found = _shift(pred, np.array([[140.0, 100.0], [95.0, 100.0]]), min_tracks=1)
    assert found is not None and found.tolist() == [-5.0, 0.0]


def test_the_offset_moves_at_its_rate_and_the_rate_follows_the_measured_shifts():
    motion = ImageMotion()
    assert motion.offset_at(5.0).tolist() == [0.0, 0.0]
    motion.update(1.0, None, 0.5, 0.3)
    motion.update(1.1, np.array([3.0, -1.0]), 0.5, 0.3)  # measured 3 px right of the expectation after 0.1 s
    assert motion.offset.tolist() == [3.0, -1.0] and motion.rate == pytest.approx([15.0, -5.0])
    assert motion.offset_at(1.3) == pytest.approx([6.0, -2.0])
    motion.update(1.3, None, 0.5, 0.3)  # nothing measured: on at the rate
    assert motion.offset == pytest.approx([6.0, -2.0]) and motion.rate == pytest.approx([15.0, -5.0])
    assert motion.offset_at(1.2) == pytest.approx([6.0, -2.0])  # never backwards
    # hold_s after the last measurement (1.1 + 0.3 s) the offset stops, and the next frame forgets the rate
    assert motion.offset_at(1.4) == pytest.approx([7.5, -2.5]) and motion.offset_at(9.0) == pytest.approx([7.5, -2.5])
    motion.update(9.0, None, 0.5, 0.3)
    assert motion.offset == pytest.approx([7.5, -2.5]) and motion.rate.tolist() == [0.0, 0.0]
    motion.update(9.1, np.array([-2.0, 0.0]), 0.5, 0.3)  # measured again: the rate starts from 0
    assert motion.offset == pytest.approx([5.5, -2.5]) and motion.rate == pytest.approx([-10.0, 0.0])


@pytest.mark.parametrize("field, bad", [("far_shift_radius", -1.0), ("far_shift_min_tracks", 0),
                                        ("far_shift_min_tracks", 2.5), ("far_shift_min_tracks", True),
                                        ("far_shift_rate_gain", float("nan")), ("far_image_sigma_m", -5.0)])
def test_the_image_motion_settings_are_checked(field, bad):
    with pytest.raises(ValueError, match=field):
        TrackerConfig(**{field: bad})

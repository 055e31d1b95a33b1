"""Score calibration: the logit scale of an over- or under-confident detector is estimated online from the
spread of each frame's strongest detections and undone; a reference detector is left as it is."""

from __future__ import annotations

import numpy as np
import pytest

from agent.score_calibration import CalibrationSettings, ScoreCalibration


def _frames(rng: np.random.Generator, temperature: float, frames: int = 300) -> list[np.ndarray]:
    """Per frame: 30 kept scores whose logits (reference spread 1.35 among the top 10) are scaled."""
    out = []
    for _ in range(frames):
        shift = rng.normal(0.0, 1.0)  # a whole frame moves (blur, scene): must not matter
        logits = np.concatenate([rng.normal(1.0 + shift, 1.35, 10), rng.normal(-4.0 + shift, 1.0, 20)])
        out.append(1.0 / (1.0 + np.exp(-temperature * logits)))
    return out


def _calibration() -> ScoreCalibration:
    """A calibration whose input check has seen pre-NMS candidates (scores down to the detector's floor)."""
    cal = ScoreCalibration()
    cal.check.observe(np.linspace(0.001, 1.0, 200))
    assert cal.check.acts
    return cal


@pytest.mark.parametrize("temperature", [0.6, 1.0, 1.6])
def test_the_scale_undoes_the_detectors_temperature(temperature: float) -> None:
    cal = _calibration()
    rng = np.random.default_rng(0)
    for k, scores in enumerate(_frames(rng, temperature)):
        cal.observe(k / 30.0, scores)
    assert cal.scale == pytest.approx(1.0 / temperature, rel=0.15)
    s = np.array([0.1, 0.5, 0.9], dtype=np.float32)
    logit = np.log(s / (1 - s))
    out = cal.apply(s)
    assert out.dtype == np.float32
    assert np.log(out / (1 - out)) == pytest.approx(cal.scale * logit, abs=1e-4)


def test_it_starts_at_the_reference_and_reset_returns_there() -> None:
    cal = _calibration()
    scores = np.array([0.2, 0.6, 0.99], dtype=np.float32)
    assert np.array_equal(cal.apply(scores), scores)  # no data: identity
    rng = np.random.default_rng(1)
    for k, frame in enumerate(_frames(rng, 2.0, 60)):
        cal.observe(k / 30.0, frame)
    assert cal.scale < 0.8
    cal.reset()
    assert cal.scale == 1.0 and not cal.check.acts  # another video: judged afresh


def test_the_estimate_is_frame_rate_independent() -> None:
    rng = np.random.default_rng(2)
    frames = _frames(rng, 1.6, 240)
    a, b = _calibration(), _calibration()
    for k, f in enumerate(frames):
        a.observe(k / 60.0, f)  # 4 s at 60 fps
    for k, f in enumerate(frames[::2]):
        b.observe(k / 30.0, f)  # the same 4 s at 30 fps
    assert a.scale < 0.9 and a.scale == pytest.approx(b.scale, rel=0.1)


def test_frames_with_few_detections_do_not_count_and_bad_settings_fail() -> None:
    cal = _calibration()
    cal.observe(0.0, np.array([0.99, 0.01]))
    cal.observe(0.1, np.array([0.99, 0.01]))
    assert cal.scale == 1.0
    with pytest.raises(ValueError, match="tau_s"):
        CalibrationSettings(tau_s=0.0)
    with pytest.raises(ValueError, match="top_k"):
        CalibrationSettings(top_k=1)
    with pytest.raises(ValueError, match="max_floor"):
        CalibrationSettings(max_floor=1.5)
    with pytest.raises(ValueError, match="min_candidates"):
        CalibrationSettings(min_candidates=0)


def test_thresholded_input_stands_the_calibration_down_and_says_why() -> None:
    # a detector's final output (scores >= 0.25): the spread of its strongest boxes is the threshold's
    cal = ScoreCalibration()
    rng = np.random.default_rng(3)
    scores = [np.clip(f, 0.25, 1.0) for f in _frames(rng, 2.0, 60)]
    for k, frame in enumerate(scores):
        out = cal.apply(frame.astype(np.float32))
        assert np.array_equal(out, frame.astype(np.float32))  # untouched
        cal.observe(k / 30.0, frame)
    assert not cal.check.acts and cal.scale == 1.0
    report = cal.report()
    assert not report.acted and "thresholded input" in report.why


def test_the_input_check_waits_for_evidence_then_acts_on_pre_nms_input() -> None:
    cal = ScoreCalibration(CalibrationSettings(min_candidates=50))
    cal.apply(np.array([0.01, 0.9], dtype=np.float32))
    assert not cal.check.acts and "needed" in cal.report().why  # 2 scores say nothing yet
    cal.apply(np.linspace(0.001, 0.999, 60).astype(np.float32))
    assert cal.check.acts and cal.report().acted
    cal.check.freeze()  # a file's video decided: thresholded scores later do not change it
    cal.apply(np.full(10_000, 0.9, dtype=np.float32))
    assert cal.check.acts

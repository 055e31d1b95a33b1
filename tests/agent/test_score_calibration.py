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


@pytest.mark.parametrize("temperature", [0.6, 1.0, 1.6])
def test_the_scale_undoes_the_detectors_temperature(temperature: float) -> None:
    cal = ScoreCalibration()
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
    cal = ScoreCalibration()
    scores = np.array([0.2, 0.6, 0.99], dtype=np.float32)
    assert np.array_equal(cal.apply(scores), scores)  # no data: identity
    rng = np.random.default_rng(1)
    for k, frame in enumerate(_frames(rng, 2.0, 60)):
        cal.observe(k / 30.0, frame)
    assert cal.scale < 0.8
    cal.reset()
    assert cal.scale == 1.0


def test_the_estimate_is_frame_rate_independent() -> None:
    rng = np.random.default_rng(2)
    frames = _frames(rng, 1.6, 240)
    a, b = ScoreCalibration(), ScoreCalibration()
    for k, f in enumerate(frames):
        a.observe(k / 60.0, f)  # 4 s at 60 fps
    for k, f in enumerate(frames[::2]):
        b.observe(k / 30.0, f)  # the same 4 s at 30 fps
    assert a.scale == pytest.approx(b.scale, rel=0.1)


def test_frames_with_few_detections_do_not_count_and_bad_settings_fail() -> None:
    cal = ScoreCalibration()
    cal.observe(0.0, np.array([0.99, 0.01]))
    cal.observe(0.1, np.array([0.99, 0.01]))
    assert cal.scale == 1.0
    with pytest.raises(ValueError, match="tau_s"):
        CalibrationSettings(tau_s=0.0)
    with pytest.raises(ValueError, match="top_k"):
        CalibrationSettings(top_k=1)

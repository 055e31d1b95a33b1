"""Detector emulator: dense clusters, fluctuating scores, blur collapse, implausible false-positive sizes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from shared.geo import Camera, Pose, horizon_row, metres_per_pixel
from sim.detector_emulator import KIND_OBJECT, KIND_OCCLUDED, DetectorEmulator, EmulatorParams
from sim.world import CLASS_BOX_M

CAM = Camera.from_preset("dji-mavic2-pro")
POSE = Pose(lat=48.53, lon=9.06, height_m=30.0, pitch_deg=40.0, heading_deg=10.0)
BOX = np.array([[1800.0, 1000.0, 1830.0, 1080.0], [600.0, 1500.0, 640.0, 1600.0]])


def _emulator(seed: int = 0, **over) -> DetectorEmulator:
    params = dataclasses.replace(EmulatorParams(), **over)
    return DetectorEmulator(params, CAM, np.random.default_rng(seed), 4, CLASS_BOX_M["person"], 1)


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K, 4) xywh vs one xyxy box -> (K,)"""
    x0 = np.maximum(a[:, 0], b[0])
    y0 = np.maximum(a[:, 1], b[1])
    x1 = np.minimum(a[:, 0] + a[:, 2], b[2])
    y1 = np.minimum(a[:, 1] + a[:, 3], b[3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    return inter / (a[:, 2] * a[:, 3] + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def _run(emu: DetectorEmulator, frames: int, kinds=(KIND_OBJECT, KIND_OBJECT), blurred=False, **kw):
    out = []
    for f in range(frames):
        out.append(emu.detect(BOX, np.array([0, 1]), np.array(kinds), np.array([1, 1]), POSE, f / 30.0,
                              blurred, **kw))
    return out


def test_same_seed_same_candidates_other_seed_differs() -> None:
    a = _run(_emulator(1), 5)
    b = _run(_emulator(1), 5)
    c = _run(_emulator(2), 5)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.boxes_xywh, y.boxes_xywh)
        np.testing.assert_array_equal(x.scores, y.scores)
    assert any(len(x) != len(z) or not np.array_equal(x.scores, z.scores) for x, z in zip(a, c, strict=True))


def test_objects_get_dense_clusters_with_high_recall_and_fluctuating_best_scores() -> None:
    emu = _emulator(3, fp_per_frame=0.0)
    found, best = [], []
    for cands in _run(emu, 600):
        iou = _iou(cands.boxes_xywh, BOX[0])
        cluster = iou >= 0.5
        found.append(cluster.any())
        if cluster.any():
            assert 1 <= cluster.sum() <= 30
            best.append(cands.scores[cluster].max())
    assert np.mean(found) >= 0.95  # pre-NMS recall
    best = np.array(best)
    assert np.std(best) > 0.1  # confidence fluctuates frame to frame
    assert 0.6 < np.mean(best >= 0.25) < 0.98  # a typical threshold drops some
    assert np.abs(np.diff(best)).mean() > 0.05


def test_cluster_sizes_span_5_to_30_boxes_and_boxes_stay_inside_the_image() -> None:
    emu = _emulator(4, fp_per_frame=0.0, score_threshold=1e-6, blur_random_rate=0.0)
    counts = []
    for cands in _run(emu, 200):
        iou = _iou(cands.boxes_xywh, BOX[0])
        counts.append(int((iou > 0.2).sum()))
        b = cands.boxes_xywh
        assert (b[:, 0] >= 0).all() and (b[:, 1] >= 0).all()
        assert (b[:, 0] + b[:, 2] <= CAM.width + 1e-9).all() and (b[:, 1] + b[:, 3] <= CAM.height + 1e-9).all()
    counts = np.array([c for c in counts if c])
    assert counts.min() >= 5 and counts.max() <= 31  # + an occasional part box


def test_scores_respect_the_candidate_threshold() -> None:
    for cands in _run(_emulator(5), 50):
        assert (cands.scores >= 0.02).all() and (cands.scores < 1.0).all()
        assert cands.category_ids.dtype == np.int64 and set(cands.category_ids.tolist()) <= {1}


def test_blurred_frames_collapse_every_confidence() -> None:
    sharp = np.concatenate([c.scores for c in _run(_emulator(6), 100, blurred=False)])
    blurred = np.concatenate([c.scores for c in _run(_emulator(6), 100, blurred=True)])
    assert blurred.max() <= 0.3
    assert np.quantile(sharp, 0.99) > 0.8


def test_fast_turns_blur_and_random_blur_is_rare() -> None:
    emu = _emulator(7)
    assert all(emu.is_blurred(45.0) for _ in range(20))
    rate = np.mean([emu.is_blurred(0.0) for _ in range(4000)])
    assert rate == pytest.approx(0.03, abs=0.01)


def test_occluded_objects_score_lower() -> None:
    vis = np.concatenate([c.scores for c in _run(_emulator(8, fp_per_frame=0.0), 300)])
    occ = np.concatenate([c.scores for c in _run(_emulator(8, fp_per_frame=0.0), 300,
                                                   kinds=(KIND_OCCLUDED, KIND_OCCLUDED))])
    assert np.median(occ) < 0.5 * np.median(vis)


def test_background_false_positives_lie_below_the_horizon_some_with_implausible_sizes() -> None:
    pose = Pose(lat=48.53, lon=9.06, height_m=30.0, pitch_deg=20.0, heading_deg=0.0)
    emu = _emulator(9, fp_per_frame=30.0, fp_cluster_mean=1.0, blur_random_rate=0.0, score_threshold=1e-6)
    top = horizon_row(CAM, pose)
    assert 0 < top < CAM.height
    ratios = []
    for f in range(100):
        cands = emu.detect(np.zeros((0, 4)), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int), pose, f / 30.0,
                           False)
        b = cands.boxes_xywh
        centre = b[:, :2] + b[:, 2:] / 2
        inside = (b[:, 2] < 0.2 * CAM.width) & (b[:, 3] < 0.2 * CAM.height)  # clipped giant boxes aside
        assert (centre[inside, 1] >= top - 1.0).all()
        mpp = metres_per_pixel(centre[inside], CAM, pose)
        ratios.append(b[inside, 2] / (CLASS_BOX_M["person"][0] / mpp))
    r = np.concatenate(ratios)
    implausible = np.mean((r < 0.4) | (r > 2.5))
    assert 0.2 < implausible < 0.5
    assert np.mean((r > 0.6) & (r < 1.6)) > 0.4


def test_bad_params_are_rejected() -> None:
    with pytest.raises(ValueError, match="score_threshold"):
        EmulatorParams(score_threshold=0.0)
    with pytest.raises(ValueError, match="cluster_boxes"):
        EmulatorParams(cluster_boxes=(10, 5))
    with pytest.raises(ValueError, match="miss_rate"):
        EmulatorParams(miss_rate=1.5)


def _appearance_emulator(seed: int = 0, **over) -> DetectorEmulator:
    from sim.detector_emulator import object_appearance

    params = dataclasses.replace(EmulatorParams(fp_per_frame=0.0), **over)
    looks = object_appearance(4, params, np.random.default_rng(100))
    return DetectorEmulator(params, CAM, np.random.default_rng(seed), 4, CLASS_BOX_M["person"], 1,
                            appearance=looks, appearance_rng=np.random.default_rng(seed + 1))


def test_appearance_descriptors_resemble_their_object_and_leave_boxes_unchanged() -> None:
    emu = _appearance_emulator()
    frames = _run(emu, 30)
    plain = _run(_emulator(fp_per_frame=0.0), 30)
    for a, b in zip(frames, plain, strict=True):  # the descriptors draw from a generator of their own
        assert np.array_equal(a.boxes_xywh, b.boxes_xywh) and np.array_equal(a.scores, b.scores)
        assert b.embeddings is None
    looks = emu.appearance
    sims = {0: [], 1: []}
    for c in frames:
        carry = np.isfinite(c.embeddings).all(axis=1)
        assert np.array_equal(carry, c.scores >= emu.params.appearance_min_score)
        assert np.allclose(np.linalg.norm(c.embeddings[carry], axis=1), 1.0, atol=1e-5)
        for obj, box in enumerate(BOX):
            mine = carry & (_iou(c.boxes_xywh, box) > 0.5)
            sims[obj].extend((c.embeddings[mine] @ looks.T).tolist())
    for obj in (0, 1):
        s = np.array(sims[obj])
        assert len(s) > 20
        # closer to its own vector than to the other object's (here a look-alike: cosine ~0.8), on
        # average and in most boxes
        assert s[:, obj].mean() > s[:, 1 - obj].mean() + 0.1
        assert (s[:, obj] > s[:, 1 - obj]).mean() > 0.8


def test_appearance_noise_grows_for_small_boxes() -> None:
    emu = _appearance_emulator(appearance_min_score=0.0)
    looks = np.tile(emu.appearance[:1], (2000, 1))
    big = emu._descriptors(looks, np.full(2000, 64.0), np.ones(2000), False) @ emu.appearance[0]
    small = emu._descriptors(looks, np.full(2000, 12.0), np.ones(2000), False) @ emu.appearance[0]
    blurred = emu._descriptors(looks, np.full(2000, 64.0), np.ones(2000), True) @ emu.appearance[0]
    assert big.mean() > blurred.mean() + 0.05 and big.mean() > small.mean() + 0.2

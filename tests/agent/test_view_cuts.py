"""View cuts hidden between sparse telemetry samples (agent.view_cuts): a 60 deg gimbal jump logged at 1 Hz and
interpolated at the frames' times is put back at the frame where the detections jump; smooth sweeps, detector
dropouts and sparse boxes are left alone. Real camera geometry (shared.geo), no mocks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.dataset import Frame, ImageRecord
from agent.telemetry_clock import TelemetryTrack
from agent.view_cuts import ViewCutReport, ViewCutSettings, continuity, place_view_cuts
from shared.geo import Camera, Pose, local_to_pixel

CAM = Camera(width=1920, height=1080, fx=1500.0, fy=1500.0, cx=960.0, cy=540.0)
FPS = 30.0
HEIGHT_M, PITCH_DEG = 30.0, 35.0


def _field(seed: int = 0, n: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """Static ground points all around the UAV, 30-70 m away."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0.0, 360.0, n)
    dist = rng.uniform(30.0, 70.0, n)
    return dist * np.sin(np.radians(ang)), dist * np.cos(np.radians(ang))


def _clip(true_heading, seconds: float = 4.0, telemetry_hz: float = 1.0, dropout: int | None = None):
    """Frames at FPS whose poses interpolate a telemetry track sampled at telemetry_hz from the true heading, and
    the detections (24 x 60 px boxes) of the static field seen with the true heading. dropout: a frame that has
    no detections."""
    east, north = _field()
    stamps = np.arange(0.0, seconds + 1e-9, 1.0 / telemetry_hz)
    values = np.array([[0.0, 0.0, HEIGHT_M, true_heading(t), PITCH_DEG] for t in stamps])
    values[:, 3] = np.degrees(np.unwrap(np.radians(values[:, 3])))
    track = TelemetryTrack(stamps, values)
    frames, dets = [], {}
    for i in range(int(seconds * FPS)):
        t = i / FPS
        _, _, h, heading, pitch = track.at(t)[0]
        told = Pose(0.0, 0.0, h, pitch, heading)
        seen_from = Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, true_heading(t) % 360.0)
        uv, ok = local_to_pixel(east, north, CAM, seen_from)
        ok &= (uv[:, 0] > 15) & (uv[:, 0] < CAM.width - 15) & (uv[:, 1] > 60) & (uv[:, 1] < CAM.height)
        uv = uv[ok] if i != dropout else np.zeros((0, 2))
        boxes = np.column_stack([uv[:, 0] - 12, uv[:, 1] - 60, uv[:, 0] + 12, uv[:, 1]]).astype(np.float32)
        dets[i] = (boxes, np.full(len(boxes), 0.9, np.float32), np.zeros(len(boxes), np.int64))
        frames.append(Frame(ImageRecord(i, CAM.width, CAM.height, 1, i, None, None), told, t, CAM, t,
                            pose_retimed=True, track=track))
    return [(f, None) for f in frames], dets


def _jump_at(t_jump: float, step: float = 60.0):
    return lambda t: 10.0 + (step if t >= t_jump else 0.0)


def _headings(frames) -> np.ndarray:
    return np.array([f.pose.heading_deg for f, _ in frames])


def test_a_jump_between_one_hertz_samples_is_put_at_the_frame_where_the_detections_jump() -> None:
    frames, dets = _clip(_jump_at(1.4))
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    cut = int(math.ceil(1.4 * FPS))
    h = _headings(out)
    assert (report.intervals, report.cuts) == (1, 1)
    assert np.allclose(h[:cut], 10.0) and np.allclose(h[cut:], 70.0)
    # before: the interpolated headings were up to 36 deg off inside the second that hides the jump
    assert np.abs(_headings(frames) - np.where(np.arange(len(h)) < cut, 10.0, 70.0)).max() > 30.0
    assert report.stage_report().acted


def test_pitch_steps_with_the_heading_and_positions_stay() -> None:
    frames, dets = _clip(_jump_at(2.5))
    track = frames[0][0].track
    values = track.values.copy()
    values[3:, 4] = 50.0  # the gimbal also tilted down in the jump
    values[:, 2] = np.linspace(30.0, 34.0, len(values))
    tilted = TelemetryTrack(track.t, values)
    frames = [(Frame(f.image, Pose(0.0, 0.0, float(tilted.at(f.t)[0, 2]), float(tilted.at(f.t)[0, 4]),
                                   float(tilted.at(f.t)[0, 3])), f.t, CAM, f.t, True, tilted), o) for f, o in frames]
    out = place_view_cuts(frames, lambda f: dets[f.image.id])
    cut = int(math.ceil(2.5 * FPS))
    pitch = np.array([f.pose.pitch_deg for f, _ in out])
    assert np.allclose(pitch[60:cut], PITCH_DEG) and np.allclose(pitch[cut:90], 50.0)
    assert [f.pose.height_m for f, _ in out] == [f.pose.height_m for f, _ in frames]


def test_a_smooth_sweep_keeps_its_interpolated_poses() -> None:
    # 60 deg/s for one second: each frame's boxes shift together by ~2 deg, nothing to cut
    frames, dets = _clip(lambda t: 10.0 + 60.0 * min(max(t - 1.0, 0.0), 1.0))
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    assert report.intervals == 1 and report.cuts == 0
    assert np.array_equal(_headings(out), _headings(frames))
    assert not report.stage_report().acted


def test_a_detector_dropout_is_not_a_cut() -> None:
    # the heading turns smoothly over the interval and one frame in it has no boxes at all
    frames, dets = _clip(lambda t: 10.0 + 40.0 * min(max(t - 1.0, 0.0), 1.0), dropout=45)
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    assert report.cuts == 0 and np.array_equal(_headings(out), _headings(frames))


def test_dense_telemetry_and_too_few_boxes_leave_the_frames_alone() -> None:
    frames, dets = _clip(_jump_at(1.4), telemetry_hz=30.0)  # every frame has its own sample: nothing hidden
    report = ViewCutReport()
    assert place_view_cuts(frames, lambda f: dets[f.image.id], report=report) == frames
    assert report.intervals == 0 and "no telemetry interval" in report.stage_report().why
    frames, dets = _clip(_jump_at(1.4))
    empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
    report = ViewCutReport()
    assert place_view_cuts(frames, lambda f: empty, report=report) == frames
    assert (report.intervals, report.cuts) == (1, 0)


def test_frames_without_pose_or_track_pass_through() -> None:
    frames, dets = _clip(_jump_at(1.4))
    bare = [(Frame(f.image, None, f.t, CAM), o) for f, o in frames]
    assert place_view_cuts(bare, lambda f: dets[f.image.id]) == bare


@settings(max_examples=60, deadline=None)
@given(st.integers(3, 25), st.floats(-400.0, 400.0), st.floats(-400.0, 400.0), st.integers(0, 10_000))
def test_continuity_of_a_shifted_copy_is_one_and_of_nothing_zero(n: int, dx: float, dy: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = np.column_stack([rng.uniform(0, 1920, n), rng.uniform(0, 1080, n), rng.uniform(20, 80, n)])
    b = a.copy()
    b[:, :2] += (dx, dy)
    assert continuity(a, b) == 1.0
    assert continuity(a, np.zeros((0, 3))) == 0.0
    assert continuity(np.zeros((0, 3)), b) == 0.0 and math.isnan(continuity(a[:1], b[:1]))
    assert 0.0 <= continuity(a, b[: max(1, n // 2)]) <= 1.0
    # a few boxes against a dense unrelated view: some shift matches two of them, none matches many of the view's
    dense = np.column_stack([rng.uniform(0, 1920, 40), rng.uniform(0, 1080, 40), np.full(40, 60.0)])
    assert continuity(a[:3], dense) <= 0.25


def test_continuity_of_an_unrelated_view_is_low() -> None:
    rng = np.random.default_rng(1)
    a = np.column_stack([rng.uniform(0, 1920, 12), rng.uniform(0, 1080, 12), np.full(12, 40.0)])
    b = np.column_stack([rng.uniform(0, 1920, 12), rng.uniform(0, 1080, 12), np.full(12, 40.0)])
    assert continuity(a, b) <= 0.25


@pytest.mark.parametrize("field", ["min_turn_deg", "match_frac", "max_continuity", "max_gap_s"])
def test_bad_settings_are_named(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        ViewCutSettings(**{field: -1.0})
    with pytest.raises(ValueError, match="max_boxes"):
        ViewCutSettings(max_boxes=0)


def test_a_jump_just_after_the_sample_that_already_shows_it_is_cut_at_the_image() -> None:
    # whole-second stamps: the sample stamped 2.0 s was taken after the jump at 2.1 s; the image jumps at 2.1 s
    frames, dets = _clip(_jump_at(2.1))
    track = frames[0][0].track
    values = track.values.copy()
    values[2, 3] = 70.0  # the sample stamped 2.0 s already shows the new heading
    early = TelemetryTrack(track.t, values)
    frames = [(Frame(f.image, Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, float(early.at(f.t)[0, 3])), f.t, CAM, f.t, True,
                     early), o) for f, o in frames]
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    h = _headings(out)
    cut = int(math.ceil(2.1 * FPS))
    assert report.cuts == 1
    assert np.allclose(h[45:cut], 10.0) and np.allclose(h[cut:75], 70.0)


def test_a_view_of_false_positives_alone_is_not_cut_before_the_jump_back() -> None:
    # away (heading 70) the confident boxes are a few false positives in new places every frame; at 2.4 s the view
    # jumps back to the field (heading 10): the cut is there, not at a chance gap among the false positives
    frames, dets = _clip(lambda t: 70.0 if t < 2.4 else 10.0)
    rng = np.random.default_rng(3)
    for f, _ in frames:
        if f.t < 2.4:
            k = int(rng.integers(3, 6))
            xy = np.column_stack([rng.uniform(50, CAM.width - 50, k), rng.uniform(100, CAM.height - 10, k)])
            boxes = np.column_stack([xy[:, 0] - 12, xy[:, 1] - 60, xy[:, 0] + 12, xy[:, 1]]).astype(np.float32)
            dets[f.image.id] = (boxes, np.full(k, 0.6, np.float32), np.zeros(k, np.int64))
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    h = _headings(out)
    cut = int(math.ceil(2.4 * FPS))
    assert report.cuts == 1
    assert np.allclose(h[31:cut], 70.0) and np.allclose(h[cut:89], 10.0)


def test_two_frames_a_second_cannot_tell_a_cut_from_a_turn() -> None:
    # 2 fps against 1 Hz telemetry (the real SeaDronesSee dev file's rates): a jump is left interpolated, and said so
    frames, dets = _clip(_jump_at(1.4))
    sparse = [(f, o) for f, o in frames if f.image.id % 15 == 0]
    report = ViewCutReport()
    assert place_view_cuts(sparse, lambda f: dets[f.image.id], report=report) == sparse
    assert (report.intervals, report.cuts, report.too_few_frames) == (1, 0, 1)
    assert "too few frames" in report.stage_report().why and not report.stage_report().acted


def _blurred(heading, start_s: float, end_s: float):
    """The clip of a heading (a function of t), its frames strictly between start_s and end_s blurred to no boxes."""
    frames, dets = _clip(heading)
    empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
    for f, _ in frames:
        if start_s < f.t < end_s:
            dets[f.image.id] = empty
    return frames, dets


def test_a_sweep_that_blur_empties_is_not_a_cut() -> None:
    # still at 10 deg, a 0.6 s sweep to 50 deg whose frames blur leaves without boxes, still again: the old and the
    # new view are apart by many empty frames, not a jump's few
    frames, dets = _blurred(lambda t: 10.0 + 40.0 * min(max((t - 1.2) / 0.6, 0.0), 1.0), 1.2, 1.8)
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    assert report.intervals == 1 and report.cuts == 0
    assert np.array_equal(_headings(out), _headings(frames))


def test_a_turn_that_blur_empties_for_a_few_tenths_is_cut_after_it() -> None:
    # still at 10 deg, a 0.4 s gimbal turn to 70 deg whose 11 frames blur leaves without boxes, still again (the
    # turns of grass-jumps-biased): the new view's first boxes are 12 frames after the old one's last, more than
    # 5 frames, within max_gap_s
    frames, dets = _blurred(lambda t: 10.0 + 60.0 * min(max((t - 1.3) / 0.4, 0.0), 1.0), 1.3, 1.7)
    report = ViewCutReport()
    out = place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    assert (report.intervals, report.cuts) == (1, 1)
    h, t = _headings(out), np.array([f.t for f, _ in out])
    assert np.allclose(h[t <= 1.3], 10.0) and np.allclose(h[t >= 1.7], 70.0)
    # with max_gap_s 0 (the span at most 6 frames) the interval keeps its interpolated poses
    report = ViewCutReport()
    kept = place_view_cuts(frames, lambda f: dets[f.image.id], ViewCutSettings(max_gap_s=0.0), report=report)
    assert report.cuts == 0 and np.array_equal(_headings(kept), _headings(frames))


def _brute_shift_matches(a: np.ndarray, b: np.ndarray, match_frac: float) -> tuple[np.ndarray, np.ndarray]:
    """Every box of a moved by every candidate shift, against every box of b (the first implementation)."""
    shifts = (b[None, :, :2] - a[:, None, :2]).reshape(-1, 2)
    moved = a[None, :, None, :2] + shifts[:, None, None, :]
    dist = np.hypot(*(moved - b[None, None, :, :2]).transpose(3, 0, 1, 2))
    radius = match_frac * 0.5 * (a[:, 2][:, None] + b[:, 2][None, :])
    return shifts, (dist <= radius[None]).any(axis=2).sum(axis=1)


@settings(max_examples=60, deadline=None)
@given(na=st.integers(1, 25), nb=st.integers(1, 25), seed=st.integers(0, 2**31 - 1),
       spread=st.floats(50.0, 2000.0), match_frac=st.floats(0.1, 1.0))
def test_the_shift_search_counts_what_moving_every_box_counts(na, nb, seed, spread, match_frac) -> None:
    from agent.view_cuts import _shift_matches

    rng = np.random.default_rng(seed)
    a = np.column_stack([rng.uniform(0, spread, (na, 2)), rng.uniform(20, 80, na)])
    # b: a shifted copy of part of a, jittered, plus unrelated boxes (crowds give many near shifts)
    part = a[rng.random(na) < 0.6] + np.array([rng.uniform(-300, 300), rng.uniform(-200, 200), 0.0])
    part[:, :2] += rng.normal(0.0, 5.0, (len(part), 2))
    b = np.vstack([part, np.column_stack([rng.uniform(0, spread, (nb, 2)), rng.uniform(20, 80, nb)])])
    shifts, matched = _shift_matches(a, b, match_frac)
    ref_shifts, ref_matched = _brute_shift_matches(a, b, match_frac)
    np.testing.assert_array_equal(shifts, ref_shifts)
    np.testing.assert_array_equal(matched, ref_matched)


@pytest.mark.parametrize(("empty", "cut"), [(15, True), (16, False)])
def test_the_gap_a_jump_may_blur_empty_ends_at_max_gap_s(empty: int, cut: bool) -> None:
    # 30 fps, a 1 Hz log: 29 frames between two samples, so max_gap_s 0.5 allows ceil(0.5 * 29) = 15 frames without
    # boxes between the old view's last boxes and the new view's first (a span of 16 frames, 0.53 s)
    first = 40  # the first frame without boxes; the view jumps at the last one
    frames, dets = _clip(_jump_at((first + empty - 1) / FPS))
    none = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
    for k in range(first, first + empty):
        dets[k] = none
    report = ViewCutReport()
    place_view_cuts(frames, lambda f: dets[f.image.id], report=report)
    assert report.intervals == 1 and report.cuts == int(cut)


@settings(max_examples=60, deadline=None)
@given(na=st.integers(1, 12), nb=st.integers(1, 12), seed=st.integers(0, 2**31 - 1), diag=st.sampled_from([0, 2, 4]),
       match_frac=st.sampled_from([0.0, 0.5, 1.0]))
def test_the_shift_search_agrees_on_integer_grids_with_ties_and_duplicates(na, nb, seed, diag, match_frac) -> None:
    # centres on a 2 px grid and diagonals of 0-4 px: duplicate boxes, shifts landing exactly on a radius, zero radii
    from agent.view_cuts import _shift_matches

    rng = np.random.default_rng(seed)
    a = np.column_stack([2.0 * rng.integers(0, 6, (na, 2)), np.full(na, float(diag))])
    b = np.column_stack([2.0 * rng.integers(0, 6, (nb, 2)), np.full(nb, float(diag))])
    np.testing.assert_array_equal(_shift_matches(a, b, match_frac)[1], _brute_shift_matches(a, b, match_frac)[1])

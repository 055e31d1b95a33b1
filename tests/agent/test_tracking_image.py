"""The tracker's image cues on synthetic scenes made with the real camera geometry: boxes expected where
their image velocity takes them, and the image gate that keeps a narrow camera's wide ground gates from
chaining a track through scattered false positives."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.boxes import box_iou, paired_iou
from agent.frame_result import FrameResult
from agent.tracking import GpsTracker, TrackerConfig
from agent.tracking.association import expected_boxes, image_cost
from shared.geo import Camera, Pose, latlon_to_local, local_to_latlon, local_to_pixel, pixel_to_local

LAT0, LON0 = 48.53, 9.06
FPS = 30.0
CLASSES = {1: "person"}
#: a 4K camera behind a 70 mm-class tele lens: 1 m on the ground at 70 m is about 120 px
TELE = Camera(width=3840, height=2160, fx=8400.0, fy=8400.0, cx=1920.0, cy=1080.0)
#: the image registration, image velocity and image gate (the defaults), and the tracker without them
IMAGE_CUES = {"image_register": True, "image_velocity": True, "image_gate": 2.0, "image_gate_age_s": 1.0,
              "image_gate_growth_per_s": 4.0}
GROUND_ONLY = {"image_register": False, "image_velocity": False, "image_gate": 0.0}


def pose_at(heading_deg: float = 0.0) -> Pose:
    return Pose(lat=LAT0, lon=LON0, height_m=40.0, pitch_deg=30.0, heading_deg=heading_deg)


def detections(points_en: np.ndarray, pose: Pose, camera: Camera, raw: np.ndarray,
               half_w: float = 30.0, height: float = 110.0) -> FrameResult:
    """A box standing on each ground point (metres around LAT0/LON0) the camera sees, with its lat/lon."""
    uav_e, uav_n = latlon_to_local(pose.lat, pose.lon, LAT0, LON0)
    uv, ok = local_to_pixel(points_en[:, 0] - uav_e, points_en[:, 1] - uav_n, camera, pose)
    ok &= (uv[:, 0] > half_w) & (uv[:, 0] < camera.width - half_w) & (uv[:, 1] > height) & (uv[:, 1] < camera.height)
    pts, uv, raw = points_en[ok], uv[ok], raw[ok]
    lat, lon = local_to_latlon(pts[:, 0], pts[:, 1], LAT0, LON0)
    boxes = np.column_stack([uv[:, 0] - half_w, uv[:, 1] - height, uv[:, 0] + half_w, uv[:, 1]]).astype(np.float32)
    k = len(pts)
    return FrameResult(boxes, raw.astype(np.float32), raw.astype(np.float32), np.ones(k, np.int64),
                       np.atleast_1d(lat), np.atleast_1d(lon), k, 0, k)


def test_expected_boxes_move_with_the_image_velocity() -> None:
    """A slow pan moves every box steadily; a track expects its box where that motion takes it."""
    people = np.array([[-3.0, 60.0], [2.0, 64.0], [5.0, 58.0]])
    tracker = GpsTracker(TrackerConfig(**IMAGE_CUES), CLASSES)
    heading = 0.0
    for k in range(20):
        heading = 0.1 * k  # 3 deg/s: about 15 px a frame on this lens
        tracker.update(detections(people, pose_at(heading), TELE, np.full(3, 0.9)), pose_at(heading),
                       1.7e9 + k / FPS, TELE)
    state = tracker._state  # noqa: SLF001 - the expected boxes are the stage under test
    rows = np.arange(len(state.active))
    last = state.active["box"].copy()
    ahead = expected_boxes(state, rows, 1.7e9 + 21 / FPS)  # two frames after the last match
    now = detections(people, pose_at(0.1 * 21), TELE, np.full(3, 0.9)).boxes_xyxy
    order = np.argsort(last[:, 0])
    shift_seen = now[np.argsort(now[:, 0])][:, 0] - last[order, 0]
    shift_expected = ahead[order, 0] - last[order, 0]
    assert np.all(np.abs(shift_seen) > 10.0)  # the boxes did move
    assert np.allclose(shift_expected, shift_seen, atol=0.25 * np.abs(shift_seen).max())
    assert np.allclose(expected_boxes(state, rows, 1.7e9 + 19 / FPS), last)  # at the last match: the last box


def _run_with_false_positives(config: TrackerConfig, seed: int = 0) -> tuple[set[int], set[int]]:
    """Three people in a tele view and, every frame, 6 false positives anywhere in the image (a sea of
    glints): 1 m on the ground is ~100 px here, so the ground gate of a track spans several hundred
    pixels. Returns the ids reported on the people's boxes and the ids reported anywhere else."""
    rng = np.random.default_rng(seed)
    people = np.array([[-4.0, 66.0], [0.0, 68.0], [5.0, 70.0]])
    pose = pose_at()
    on_people: set[int] = set()
    elsewhere: set[int] = set()
    tracker = GpsTracker(config, CLASSES)
    for k in range(150):
        uv = rng.uniform([100.0, 300.0], [3700.0, 2100.0], (6, 2))
        east, north, ok = pixel_to_local(uv, TELE, pose)  # the UAV is at the origin
        pts = np.vstack([people + rng.normal(0.0, 0.03, people.shape), np.column_stack([east, north])[ok]])
        raw = np.concatenate([np.full(3, 0.9), rng.uniform(0.55, 0.8, int(ok.sum()))])
        result = detections(pts, pose, TELE, raw)
        outs = tracker.report(tracker.update(result, pose, 1.7e9 + k / FPS, TELE))
        for tr in outs:
            on = any(np.allclose(tr.box_xyxy, b) for b in result.boxes_xyxy[:3])
            (on_people if on else elsewhere).add(tr.id)
    return on_people, elsewhere


def test_the_image_gate_keeps_scattered_false_positives_from_forming_tracks() -> None:
    assert all(getattr(TrackerConfig(), k) == v for k, v in IMAGE_CUES.items())  # the defaults
    on_people, elsewhere = _run_with_false_positives(TrackerConfig(**IMAGE_CUES))
    assert len(on_people) == 3  # every person keeps one id
    # without the image cues the ground gate chains tracks through the false positives
    on_people_ground, elsewhere_ground_only = _run_with_false_positives(TrackerConfig(**GROUND_ONLY))
    assert len(elsewhere) < len(elsewhere_ground_only)


def _one_steady_track(config: TrackerConfig) -> tuple[GpsTracker, float]:
    """A person followed for 10 frames by a still tele camera; returns the tracker and the next frame's time."""
    person = np.array([[0.0, 60.0]])
    tracker = GpsTracker(config, CLASSES)
    for k in range(10):
        tracker.update(detections(person, pose_at(), TELE, np.full(1, 0.9)), pose_at(), 1.7e9 + k / FPS, TELE)
    return tracker, 1.7e9 + 10 / FPS


@settings(max_examples=60, deadline=None)
@given(dx=st.floats(-800.0, 800.0), dy=st.floats(-400.0, 400.0), grow=st.floats(0.5, 2.0))
def test_giou_image_cost_is_bounded_and_never_below_the_iou_cost(dx: float, dy: float, grow: float) -> None:
    """The generalised IoU's cost lies in [0, 2] and is never below the IoU cost (the hull's empty share only
    adds)."""
    costs = {}
    for overlap in ("iou", "giou"):
        tracker, t = _one_steady_track(TrackerConfig(image_overlap=overlap))
        state = tracker._state  # noqa: SLF001 - the image cost is the stage under test
        e = expected_boxes(state, np.array([0]), t)[0]
        w, h = (e[2] - e[0]) * grow, (e[3] - e[1]) * grow
        cx, cy = 0.5 * (e[0] + e[2]) + dx, 0.5 * (e[1] + e[3]) + dy
        box = np.array([[cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]])
        costs[overlap] = float(image_cost(state, np.array([0]), box, t)[0])
    assert 0.0 <= costs["iou"] <= 1.0 + 1e-9
    assert 0.0 <= costs["giou"] <= 2.0 + 1e-9
    assert costs["giou"] >= costs["iou"] - 1e-9


def test_giou_image_cost_keeps_growing_past_no_overlap_where_the_iou_cost_stops() -> None:
    """Boxes moved ever further right of a track's expected box: the IoU cost stops at 1 once they no longer
    overlap, the generalised IoU's keeps growing (a far false positive costs more than a neighbour's box)."""
    out = {}
    for overlap in ("iou", "giou"):
        tracker, t = _one_steady_track(TrackerConfig(image_overlap=overlap))
        state = tracker._state  # noqa: SLF001
        e = expected_boxes(state, np.array([0]), t)[0]
        w = e[2] - e[0]
        shifts = w * np.array([0.0, 0.5, 1.5, 3.0, 6.0])
        boxes = np.tile(e, (len(shifts), 1)) + np.column_stack([shifts, 0 * shifts, shifts, 0 * shifts])
        out[overlap] = image_cost(state, np.zeros(len(shifts), np.int64), boxes, t)
    assert out["iou"][0] < 1e-9 and out["giou"][0] < 1e-9
    np.testing.assert_allclose(out["iou"][2:], 1.0)
    assert np.all(np.diff(out["giou"]) > 0) and out["giou"][-1] > 1.5


def test_a_track_the_image_no_longer_shows_costs_the_neutral_half() -> None:
    """After a 1 s gap the image says nothing either way: 0.5 whatever the box, with either overlap."""
    for overlap in ("iou", "giou"):
        tracker, t = _one_steady_track(TrackerConfig(image_overlap=overlap))
        state = tracker._state  # noqa: SLF001
        far = expected_boxes(state, np.array([0]), t) + 2000.0
        assert float(image_cost(state, np.array([0]), far, t + 1.0)[0]) == 0.5


def test_image_overlap_must_be_a_known_kind() -> None:
    with pytest.raises(ValueError, match="image_overlap"):
        TrackerConfig(image_overlap="diou")


def test_giou_gives_way_to_iou_where_a_shake_moved_the_whole_image() -> None:
    """In a frame the registration could not pair with the tracks (image_steady False: the whole image moved
    unlike the telemetry says), a box's distance from its expected place is the shake's, not the object's:
    the cost is the IoU's (at most 1), not the generalised IoU's."""
    tracker, t = _one_steady_track(TrackerConfig(image_overlap="giou"))
    state = tracker._state  # noqa: SLF001
    far = expected_boxes(state, np.array([0]), t) + np.array([400.0, 0.0, 400.0, 0.0])
    state.image_steady = True
    steady = float(image_cost(state, np.array([0]), far, t)[0])
    state.image_steady = False
    shaken = float(image_cost(state, np.array([0]), far, t)[0])
    assert steady > 1.5 and shaken == 1.0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 30), st.integers(0, 2**31))
def test_paired_iou_is_the_diagonal_of_box_iou(n: int, seed: int) -> None:
    """The row-wise IoU the image cue and the registration share equals the dense matrix's diagonal; its
    generalised form never exceeds it and stays in [-1, 1]."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 200, (2, n, 2))
    wh = rng.uniform(0, 60, (2, n, 2))
    a, b = np.concatenate([xy[0], xy[0] + wh[0]], axis=1), np.concatenate([xy[1], xy[1] + wh[1]], axis=1)
    iou = paired_iou(a, b)
    np.testing.assert_allclose(iou, np.diag(box_iou(a, b)))
    giou = paired_iou(a, b, generalised=True)
    assert np.all(giou <= iou + 1e-12) and np.all((giou >= -1 - 1e-12) & (giou <= 1 + 1e-12))

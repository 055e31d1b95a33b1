"""The clock-offset estimate (agent.clock_offset): a synthetic 0.3 s video/telemetry offset during heading
sweeps is recovered from the detections alone; a hover gets no invented offset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.clock_offset import ClockOffsetSettings, HeadingTrack, frame_points, retime_frames
from agent.dataset import Frame, ImageRecord
from shared.geo import Camera, Pose, local_to_pixel
from shared.terrain import ElevationGrid, Terrain

FPS = 30.0
TELEMETRY_HZ = 10.0
CAMERA = Camera(960, 540, 800.0, 800.0, 480.0, 270.0)  # narrow (tele-like) view
HEIGHT_M, PITCH_DEG = 40.0, 30.0


def _heading(t: float, sweeping: bool) -> float:
    """True gimbal heading (deg): dwell 0.5 s, then turns of 50 deg at up to ~80 deg/s (cosine profile)
    left and right with 0.4 s pauses; constant when hovering."""
    if not sweeping:
        return 10.0
    period, turn_s, amp = 2.0, 1.0, 50.0
    k, u = divmod(max(t - 0.5, 0.0), period)
    sign = 1.0 if int(k) % 2 == 0 else -1.0
    base = 0.0 if sign > 0 else amp
    frac = min(u / turn_s, 1.0)
    return base + sign * amp * (1.0 - math.cos(math.pi * frac)) / 2.0


def _clip(sweeping: bool, offset_s: float, seconds: float = 5.0) -> tuple[list[Frame], dict[int, tuple]]:
    """Frames whose telemetry lags by offset_s (10 Hz sample-and-hold, stamps on the telemetry clock) and
    the detections of static ground points projected with the TRUE pose."""
    rng = np.random.default_rng(0)
    ang = rng.uniform(-20.0, 75.0, 40)  # a field of static objects around the swept bearings
    rng_m = rng.uniform(50.0, 90.0, 40)
    east, north = rng_m * np.sin(np.radians(ang)), rng_m * np.cos(np.radians(ang))
    frames, dets = [], {}
    for i in range(int(seconds * FPS)):
        t = i / FPS
        k = math.floor((t - offset_s) * TELEMETRY_HZ)
        ts = k / TELEMETRY_HZ  # the telemetry sample's true time; its stamp is ts + offset_s
        true_pose = Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, _heading(t, sweeping) % 360.0)
        told = Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, _heading(ts, sweeping) % 360.0)
        uv, valid = local_to_pixel(east, north, CAMERA, true_pose)
        inside = valid & (uv[:, 0] > 20) & (uv[:, 0] < CAMERA.width - 20) & (uv[:, 1] > 20) & (uv[:, 1] < CAMERA.height)
        uv = uv[inside]
        boxes = np.column_stack([uv[:, 0] - 8, uv[:, 1] - 24, uv[:, 0] + 8, uv[:, 1]]).astype(np.float32)
        dets[i] = (boxes, np.full(len(boxes), 0.9, np.float32), np.zeros(len(boxes), np.int64))
        image = ImageRecord(i, CAMERA.width, CAMERA.height, 1, i, None, None)
        frames.append(Frame(image, told, t, CAMERA, ts + offset_s))
    return frames, dets


def _final_offset(frames: list[Frame], dets: dict[int, tuple]) -> tuple[float, int]:
    out = retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings())
    offsets = [o for _, o in out if o is not None]
    return offsets[-1].offset_s, sum(o.measured for o in offsets)


def test_a_constant_offset_during_sweeps_is_recovered_within_50_ms() -> None:
    offset, measured = _final_offset(*_clip(True, 0.3))
    assert measured > 0
    assert offset == pytest.approx(0.3, abs=0.05)


def test_two_passes_re_time_a_file_from_its_first_frame_and_the_online_estimate_catches_up() -> None:
    frames, dets = _clip(True, 0.3)
    two = [o for _, o in retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings())]
    online = [o for _, o in retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings(two_pass=False))]
    assert all(o is not None and o.offset_s == pytest.approx(0.3, abs=0.05) for o in two)
    assert [o.measured for o in two if o] == [o.measured for o in online if o]  # measured: where a window was
    assert online[0] is not None and online[0].offset_s == ClockOffsetSettings().fallback_s  # nothing seen yet
    assert online[-1] is not None and online[-1].offset_s == pytest.approx(0.3, abs=0.05)


def test_no_offset_is_invented_on_a_hover() -> None:
    offset, measured = _final_offset(*_clip(False, 0.3))
    assert measured == 0
    assert offset == ClockOffsetSettings().fallback_s


def test_retimed_poses_carry_the_heading_at_frame_time_plus_the_offset() -> None:
    frames, dets = _clip(True, 0.3)
    track = HeadingTrack.from_frames(frames)
    out = retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings())
    for fr, off in out[-30:]:
        assert off is not None and fr.pose is not None and fr.pose_t == fr.t
        assert fr.pose.heading_deg == pytest.approx(track.at(fr.t + off.offset_s)[0], abs=1e-9)


@pytest.mark.parametrize("field,value", [("search_s", 0.0), ("fallback_s", 2.0), ("lags_s", ()),
                                          ("min_contrast", 1.5)])
def test_bad_settings_name_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        ClockOffsetSettings(**{field: value})  # type: ignore[arg-type]


def _hill_clip(offset_s: float) -> tuple[list[Frame], dict[int, tuple], Terrain]:
    """_clip's sweeps over ground that rises 12 m per 100 m towards the north-east, the objects standing on it."""
    axis = np.arange(-150.0, 151.0, 1.0)
    east_g, north_g = np.meshgrid(axis, axis[::-1])
    heights = 200.0 + 0.12 * (east_g + north_g) / math.sqrt(2.0)
    terrain = Terrain(ElevationGrid.from_local(heights, 0.0, 0.0, west_m=-150.0, north_m=150.0, cell_m=1.0), 200.0)
    frames, _ = _clip(True, offset_s)
    rng = np.random.default_rng(0)
    ang = rng.uniform(-20.0, 75.0, 40)
    rng_m = rng.uniform(40.0, 70.0, 40)
    east, north = rng_m * np.sin(np.radians(ang)), rng_m * np.cos(np.radians(ang))
    dets = {}
    for i, frame in enumerate(frames):
        true_pose = Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, _heading(frame.t, True) % 360.0)
        uv, valid = local_to_pixel(east, north, CAMERA, true_pose, terrain=terrain)
        inside = valid & (uv[:, 0] > 20) & (uv[:, 0] < CAMERA.width - 20) & (uv[:, 1] > 20) & (uv[:, 1] < CAMERA.height)
        uv = uv[inside]
        boxes = np.column_stack([uv[:, 0] - 8, uv[:, 1] - 24, uv[:, 0] + 8, uv[:, 1]]).astype(np.float32)
        dets[i] = (boxes, np.full(len(boxes), 0.9, np.float32), np.zeros(len(boxes), np.int64))
    return frames, dets, terrain


def test_over_a_terrain_the_detections_are_put_on_it() -> None:
    # the points the estimate compares lie where the objects stand on the slope, not where flat ground puts them
    frames, dets, terrain = _hill_clip(0.0)
    frame = frames[0]
    frame = Frame(frame.image, Pose(0.0, 0.0, HEIGHT_M, PITCH_DEG, _heading(frame.t, True) % 360.0), frame.t,
                  frame.camera, frame.pose_t)
    settings = ClockOffsetSettings()
    on_slope = frame_points(frame, *dets[0], settings, terrain)
    flat = frame_points(frame, *dets[0], settings)
    assert len(on_slope) == len(flat) >= 5
    rng = np.random.default_rng(0)  # the objects of _hill_clip
    ang, rng_m = rng.uniform(-20.0, 75.0, 40), rng.uniform(40.0, 70.0, 40)
    objects = np.column_stack([rng_m * np.sin(np.radians(ang)), rng_m * np.cos(np.radians(ang))])
    nearest = np.min(np.hypot(*(on_slope[:, None, :] - objects[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert nearest.max() < 0.5
    assert np.hypot(*(flat - on_slope).T).max() > 3.0  # flat earth: metres beyond them up the slope


def test_over_a_terrain_the_offset_is_recovered_with_the_detections_on_it() -> None:
    frames, dets, terrain = _hill_clip(0.3)
    out = retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings(), terrain_for=lambda _: terrain)
    offsets = [o for _, o in out if o is not None]
    assert sum(o.measured for o in offsets) > 0
    assert offsets[-1].offset_s == pytest.approx(0.3, abs=0.05)
    flat = [o for _, o in retime_frames(frames, lambda f: dets[f.image.id], ClockOffsetSettings()) if o is not None]
    assert abs(offsets[-1].offset_s - 0.3) <= abs(flat[-1].offset_s - 0.3) + 0.01

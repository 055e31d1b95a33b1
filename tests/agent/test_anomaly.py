"""Anomaly heatmap methods, the ground layer and regions of interest (agent.anomaly), on small synthetic frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.anomaly import ANOMALY_CLASS, AnomalyConfig, AnomalyDetector, AnomalyMap, AnomalyMapConfig, extract_rois
from agent.anomaly.methods import FrameDifference, normalise_robust
from agent.anomaly.registry import make_method
from shared.geo import Camera, Pose, metres_per_pixel

CAM = Camera(width=640, height=360, fx=450.0, fy=450.0, cx=320.0, cy=180.0)
POSE = Pose(lat=47.6, lon=9.3, height_m=40.0, pitch_deg=50.0, heading_deg=30.0)


def _sea(seed: int = 0, shape: tuple[int, int] = (360, 640)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.array([120, 110, 40], np.float32)  # teal water, BGR
    return np.clip(base + rng.normal(0, 4, (*shape, 3)), 0, 255).astype(np.uint8)


def _with_blob(image: np.ndarray, row: int, col: int) -> np.ndarray:
    out = image.copy()
    out[row - 3:row + 3, col - 3:col + 3] = (20, 40, 230)  # a red life jacket
    return out


@pytest.mark.parametrize("name", ["mean", "median", "autoencoder"])
def test_spatial_methods_score_a_small_object_highest(name):
    frame = _with_blob(_sea(), 200, 300)
    heat = make_method(name, work_width=320).heatmap(frame)
    assert heat.dtype == np.float32 and heat.shape == (180, 320)
    assert 0.0 <= heat.min() and heat.max() <= 1.0
    assert heat[100, 150] == heat.max() > 0.5
    top = np.argsort(heat.ravel())[-9:]  # the nine hottest pixels are the object's
    rows, cols = np.unravel_index(top, heat.shape)
    assert np.abs(rows - 100).max() <= 6 and np.abs(cols - 150).max() <= 6  # (the mean filter's halo)


def test_strong_responses_keep_their_order_in_the_heat():
    # a swimmer (z 12) and a whitecap (z 40) above the old clip at z 8 must not tie, nor reach past 1
    rng = np.random.default_rng(0)
    residual = rng.normal(10.0, 1.0, (64, 64)).astype(np.float32)
    residual[5, 5], residual[9, 9], residual[20, 20] = 10.0 + 4.0, 10.0 + 12.0, 10.0 + 40.0
    heat = normalise_robust(residual, 8.0)
    assert 0.0 < heat[5, 5] < heat[9, 9] < heat[20, 20] <= 1.0
    assert heat.min() == 0.0 and heat.dtype == np.float32


def test_unknown_method_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown anomaly method 'nope'; valid: autoencoder, diff, mean, median, mog2"):
        make_method("nope")


def test_frame_difference_undoes_the_camera_motion_given_by_telemetry():
    """The second frame is the first moved 8 px right with a new object: the homographies (pixel -> world)
    say so, and the difference lights up the object only, not the shifted texture."""
    rng = np.random.default_rng(1)
    texture = (rng.random((360, 660, 3)) * 255).astype(np.uint8)
    first, second = texture[:, 8:648].copy(), _with_blob(texture[:, 0:640], 180, 320)
    g1 = np.eye(3)
    g2 = np.array([[1.0, 0, -8.0], [0, 1.0, 0], [0, 0, 1.0]])  # pixel u of frame 2 shows world u - 8
    method = FrameDifference(work_width=640, register="telemetry")
    assert method.heatmap(first, g1).max() == 0.0  # nothing to compare with yet
    heat = method.heatmap(second, g2)
    assert heat[175:186, 315:326].max() == pytest.approx(1.0)
    heat[170:191, 310:331] = 0
    assert heat.max() < 0.3
    unregistered = FrameDifference(work_width=640, register="telemetry")
    unregistered.heatmap(first, g1)
    # without undoing the motion the whole texture differs and the object drowns in it
    assert unregistered.heatmap(second, g1)[175:186, 315:326].max() < 0.5


def test_mog2_flags_what_appears_in_a_still_scene():
    method = make_method("mog2", work_width=320)
    for seed in range(20):
        method.heatmap(_sea(seed))
    heat = method.heatmap(_with_blob(_sea(99), 100, 100))
    assert heat[50, 50] > 0.3 and heat[150, 250] < 0.1


def _blobs(points: list[tuple[int, int]]) -> np.ndarray:
    heat = np.zeros((180, 320), np.float32)
    for r, c in points:
        heat[r - 2:r + 3, c - 2:c + 3] = 1.0
    return heat


@settings(max_examples=15, deadline=None)
@given(height=st.floats(15, 100), pitch=st.floats(30, 90), heading=st.floats(0, 360),
       row=st.integers(110, 170), col=st.integers(20, 300))
def test_heat_put_on_the_ground_comes_back_at_the_same_pixel(height, pitch, heading, row, col):
    pose = Pose(lat=47.6, lon=9.3, height_m=height, pitch_deg=pitch, heading_deg=heading)
    # the window reaches the whole range (the default 300 m window's edge is 150 m away: a blob beyond it, e.g. 174 m
    # off at height 98 m, pitch 30 deg, row 110, col 20, is not stored and cannot come back)
    layer = AnomalyMap(AnomalyMapConfig(max_range_m=400.0, window_m=800.0))
    for i in range(6):
        layer.update(_blobs([(row, col)]), CAM, pose, i / 30)
    back = layer.image_scores(CAM, pose, (180, 320))
    peak = np.unravel_index(np.argmax(back), back.shape)
    # a cell holds the mean heat of its ground: at 15 m a 5-pixel blob is a third of the box around a rotated
    # cell's footprint, and 6 frames are 0.17 s of the 0.1 s prior's pull towards 0
    assert back.max() > 0.1
    # the layer's resolution is a grid cell: allow half a cell (in working pixels) besides 2 pixels
    cell_px = layer.grid.cell_size_m(47.6) / metres_per_pixel([[2 * col + 1, 2 * row + 1]], CAM, pose)[0] / 2
    tol = 2 + 0.5 * float(cell_px)
    assert abs(peak[0] - row) <= tol and abs(peak[1] - col) <= tol


def test_the_layer_forgets_what_is_no_longer_seen():
    layer = AnomalyMap(AnomalyMapConfig(half_life_s=0.5))
    for i in range(10):
        layer.update(_blobs([(140, 160)]), CAM, POSE, i / 30)
    assert layer.image_scores(CAM, POSE, (180, 320)).max() > 0.5
    away = Pose(lat=47.6, lon=9.3, height_m=40.0, pitch_deg=50.0, heading_deg=210.0)  # looking the other way
    for i in range(10, 100):
        layer.update(np.zeros((180, 320), np.float32), CAM, away, i / 30)  # 3 s = 6 half-lives
    assert layer.image_scores(CAM, POSE, (180, 320)).max() < 0.05


def test_a_steady_object_outscores_flicker_in_the_layer():
    """An object seen in every frame beats glints of equal strength that land elsewhere each frame."""
    rng = np.random.default_rng(3)
    layer = AnomalyMap()
    for i in range(30):
        glints = [(int(rng.integers(100, 175)), int(rng.integers(10, 310))) for _ in range(5)]
        layer.update(_blobs([(150, 160), *glints]), CAM, POSE, i / 30)
    back = layer.image_scores(CAM, POSE, (180, 320))
    peak = np.unravel_index(np.argmax(back), back.shape)
    assert abs(peak[0] - 150) <= 2 and abs(peak[1] - 160) <= 2
    back[145:156, 155:166] = 0
    assert back.max() < 0.5


def test_a_cell_holds_the_mean_heat_of_its_ground():
    """Near rows (a cell covers many pixels): a one-pixel glint counts by its share of the cell, a blob that
    covers the cell keeps its heat. Far rows (a pixel is taller than a cell on the ground): a 3-pixel object comes
    back about 3 rows tall, not stretched to the near rows' cell size (a uniform downscale of the whole band by
    the near rows' pixels per cell stretched it over 8 rows, and a glint kept 0.22 of its heat)."""
    pose = Pose(lat=47.6, lon=9.3, height_m=20.0, pitch_deg=30.0, heading_deg=0.0)
    layer = AnomalyMap(AnomalyMapConfig(max_range_m=200.0))
    heat = np.zeros((180, 320), np.float32)
    heat[172, 100] = 1.0  # glint, near
    heat[166:179, 200:213] = 1.0  # blob of about a cell and more, near
    heat[101:104, 150:153] = 1.0  # small object, far
    for i in range(30):
        layer.update(heat, CAM, pose, i / 30)
    back = layer.image_scores(CAM, pose, (180, 320))
    assert back[172, 206] > 0.6
    assert back[166:179, 94:107].max() < 0.2
    far = back[96:110, 140:165]
    assert far.max() > 0.3
    rows = np.flatnonzero(far.max(axis=1) >= 0.5 * far.max())
    assert rows.size <= 4 and abs(96 + rows.mean() - 102) <= 1


def test_the_layer_is_put_on_the_heat_scale_before_it_is_added():
    """An averaged layer has less noise than a frame: a steady object at 0.4 over water at 0.05 +- 0.01 (robust
    standard deviation) is 35 of them above it, and boosts its pixel as much as a heat of tanh(35 / 8) would,
    beating a glint the frame alone scores higher but the layer hardly keeps. The raw layer (z_max None) adds
    0.4."""
    from agent.anomaly.detector import combine_scores

    rng = np.random.default_rng(1)
    heat = (rng.random((90, 160)) * 0.3).astype(np.float32)
    layer = (0.05 + rng.normal(0, 0.01, (90, 160))).astype(np.float32)
    heat[60, 40], layer[60, 40] = 0.8, 0.4  # steady object
    heat[70, 120], layer[70, 120] = 0.95, 0.1  # glint
    scores = combine_scores(heat, layer, 20, 1.0)
    assert scores[:20].max() == 0.0
    assert scores[60, 40] > scores[70, 120]
    assert scores[60, 40] == pytest.approx((0.8 + np.tanh((0.4 - 0.05) / 0.01 / 8)) / 2, abs=0.03)
    raw = combine_scores(heat, layer, 20, 1.0, None)
    assert raw[60, 40] == pytest.approx(0.6) and raw[70, 120] == pytest.approx(0.525)
    mog2 = AnomalyDetector(AnomalyConfig(method="mog2"))
    assert mog2._layer_z_max() is None  # a foreground probability is not a z-score: its layer stays raw


def test_the_layer_boost_uses_its_own_z_scale_not_the_heats():
    """The boost's scale is AnomalyConfig.layer_z_max (6 by default, below the heat's 8: a faint steady object a
    few robust deviations above the water is raised more); MOG2's layer stays raw; bad values are refused."""
    default = AnomalyDetector(AnomalyConfig(method="median"))
    assert default.method.z_max == 8.0 and default._layer_z_max() == 6.0
    assert AnomalyDetector(AnomalyConfig(method="median", layer_z_max=3.0))._layer_z_max() == 3.0
    assert AnomalyDetector(AnomalyConfig(method="mog2", layer_z_max=3.0))._layer_z_max() is None
    assert AnomalyConfig().memory_weight == 1.5 and AnomalyMapConfig().half_life_s == 0.75
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="layer_z_max"):
            AnomalyConfig(layer_z_max=bad)
    with pytest.raises(ValueError, match="memory_weight"):
        AnomalyConfig(memory_weight=-0.5)


def test_the_min_rule_keeps_what_the_frame_and_the_layer_agree_on():
    """combine="min": a pixel scores min(heat, tanh(z_layer / 8)) = tanh(min(z_heat, z_layer) / 8). A steady object
    (in the frame and in the layer) keeps its heat; a glint of this frame alone (the layer hardly keeps it) and a
    ghost the layer keeps where the frame sees nothing are each capped by the other; nothing scores above its heat
    and the rows above the cut score 0. The raw layer (z_max None, MOG2) is taken as it is."""
    from agent.anomaly.detector import agree_scores

    rng = np.random.default_rng(1)
    heat = (rng.random((90, 160)) * 0.3).astype(np.float32)
    layer = (0.05 + rng.normal(0, 0.01, (90, 160))).astype(np.float32)
    heat[60, 40], layer[60, 40] = 0.8, 0.4  # steady object: 35 robust deviations above the layer's water
    heat[70, 120], layer[70, 120] = 0.95, 0.06  # glint: ~1 robust deviation in the layer
    heat[30, 80], layer[30, 80] = 0.05, 0.4  # ghost: the layer keeps it, this frame does not see it
    heat[10, 10], layer[10, 10] = 0.9, 0.4  # above the cut
    scores = agree_scores(heat, layer, 20)
    assert scores.dtype == np.float32 and scores.shape == heat.shape
    assert scores[:20].max() == 0.0
    assert np.all(scores[20:] <= heat[20:])
    assert scores[60, 40] == pytest.approx(0.8)  # tanh(35 / 8) ~ 1 > 0.8: the frame's heat is what both agree on
    assert scores[70, 120] < 0.2 and scores[30, 80] == pytest.approx(0.05)
    assert scores[60, 40] > 3 * max(scores[70, 120], scores[30, 80])
    band = np.zeros(heat.shape, bool)
    band[20:] = True
    assert np.allclose(scores, np.where(band, np.minimum(heat, normalise_robust(layer, 8.0, band)), 0.0))
    raw = agree_scores(heat, layer, 20, None)
    assert raw[60, 40] == pytest.approx(0.4) and raw[70, 120] == pytest.approx(0.06) and raw[:20].max() == 0.0


def test_the_detector_combines_heat_and_layer_by_the_configured_rule():
    """The default rule is "min" on the method's own z scale (MOG2: the raw layer); "sum" is the weighted boost of
    before; an unknown rule is refused, naming the valid ones."""
    from agent.anomaly.detector import COMBINE_RULES, agree_scores, combine_scores

    assert AnomalyConfig().combine == "min" and COMBINE_RULES == ("min", "sum")
    with pytest.raises(ValueError, match="combine must be one of min, sum, got 'max'"):
        AnomalyConfig(combine="max")
    assert AnomalyDetector(AnomalyConfig(method="median"))._heat_z_max() == 8.0
    assert AnomalyDetector(AnomalyConfig(method="mog2"))._heat_z_max() is None
    frames = [_with_blob(_sea(i), 300, 200) for i in range(3)]
    outs = {}
    for rule in COMBINE_RULES:
        det = AnomalyDetector(AnomalyConfig(method="median", combine=rule, method_options={"work_width": 320}))
        for i, frame in enumerate(frames):
            outs[rule] = det.process(frame, POSE, i / 10, CAM)
    first = int(np.ceil(outs["min"].cut_row * outs["min"].heat.shape[0] / CAM.height))
    for rule, expected in (("min", agree_scores(outs["min"].heat, outs["min"].layer, first, 8.0)),
                           ("sum", combine_scores(outs["sum"].heat, outs["sum"].layer, first, 1.5, 6.0))):
        out = outs[rule]
        assert out.layer is not None
        np.testing.assert_allclose(out.scores, expected, atol=1e-6)
        assert out.scores[150, 100] > 0.5  # the blob (300, 200 full resolution) is in the frame and stayed put
    alone = AnomalyDetector(AnomalyConfig(method="median", memory_weight=None, method_options={"work_width": 320}))
    out = alone.process(frames[0], POSE, 0.0, CAM)
    assert out.layer is not None and np.array_equal(out.scores, out.layer)  # None: the layer alone, either rule


def test_layer_tiles_hold_the_heat_on_the_shared_grid():
    layer = AnomalyMap()
    assert layer.tiles() == [] and layer.classes == []
    for i in range(5):
        layer.update(_blobs([(150, 160)]), CAM, POSE, i / 30)
    tiles = layer.tiles()
    assert layer.classes == [ANOMALY_CLASS]
    assert tiles and all(t.shape == (256, 256) and t.dtype == np.float32 for _, _, t in tiles)
    assert max(float(t.max()) for _, _, t in tiles) > 0.3
    assert len(layer.tiles(min_value=0.3)) < len(tiles)
    assert layer.tiles("person") == []


def test_regions_of_interest_are_components_with_their_peaks():
    scores = np.zeros((90, 160), np.float32)
    scores[10:14, 20:25] = 0.6
    scores[50:60, 100:104] = 0.9
    scores[80, 150] = 0.2  # below the threshold
    boxes, peaks = extract_rois(scores, 0.3, dilate_px=0, full_size=(640, 360))
    assert peaks.tolist() == pytest.approx([0.9, 0.6])
    assert boxes.tolist() == [[400.0, 200.0, 416.0, 240.0], [80.0, 40.0, 100.0, 56.0]]
    assert extract_rois(np.zeros((9, 9), np.float32), 0.3)[0].shape == (0, 4)


def test_detector_cuts_the_sky_and_rejects_a_frame_of_another_size():
    pose = Pose(lat=47.6, lon=9.3, height_m=40.0, pitch_deg=10.0, heading_deg=0.0)  # horizon in the image
    frame = _sea()
    frame[:40] = (255, 255, 255)  # bright sky edge
    for use_memory in (False, True):
        det = AnomalyDetector(AnomalyConfig(method="mean", use_memory=use_memory, method_options={"work_width": 320}))
        out = det.process(frame, pose, 0.0, CAM)
        assert out.cut_row > 40
        assert out.scores[: out.cut_row // 2].max() == 0.0
    with pytest.raises(ValueError, match="frame is 320x180 but the camera is 640x360"):
        det.process(frame[:180, :320], pose, 0.1, CAM)


def _ground_frames(poses: list[Pose], cam: Camera) -> list[np.ndarray]:
    """Frames of a textured flat ground (0.05 m texels around the first pose) seen with the given true poses."""
    from shared.geo import ground_to_image_homography, latlon_to_local

    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur((rng.random((1600, 1600, 3)) * 255).astype(np.uint8), (0, 0), 2.0)
    texel_to_metres = np.array([[0.05, 0, -40.0], [0, -0.05, 40.0], [0, 0, 1.0]])  # north up
    frames = []
    for pose in poses:
        east, north = latlon_to_local(pose.lat, pose.lon, poses[0].lat, poses[0].lon)
        to_pose = np.array([[1.0, 0, -float(east)], [0, 1.0, -float(north)], [0, 0, 1.0]])
        m = ground_to_image_homography(cam, pose) @ to_pose @ texel_to_metres
        frames.append(cv2.warpPerspective(texture, m, (cam.width, cam.height), flags=cv2.INTER_LINEAR))
    return frames


def test_registration_places_frames_more_consistently_than_noisy_telemetry():
    """True poses turn 0.2 deg a frame; the telemetry adds 0.5 deg heading and 0.3 deg pitch jitter. A ground point
    the registration projects lands nearer its true pixel than with the telemetry alone."""
    from agent.anomaly.registration import GroundRegistration
    from shared.geo import ground_to_image_homography

    cam = Camera(width=320, height=180, fx=225.0, fy=225.0, cx=160.0, cy=90.0)
    truth = [Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=60.0, heading_deg=0.2 * i) for i in range(25)]
    rng = np.random.default_rng(7)
    noisy = [Pose(lat=p.lat, lon=p.lon, height_m=p.height_m, pitch_deg=p.pitch_deg + rng.normal(0, 0.3),
                  heading_deg=p.heading_deg + rng.normal(0, 0.5)) for p in truth]
    reg = GroundRegistration(ecc_width=320)
    err_reg, err_tel = [], []
    ground = np.array([[[0.0, 15.0], [3.0, 20.0], [-4.0, 12.0]]])  # metres east/north of the start
    for frame, p_true, p_tel in zip(_ground_frames(truth, cam), truth, noisy, strict=True):
        g = reg.update(frame, cam, p_tel, 0)
        want = cv2.perspectiveTransform(ground, ground_to_image_homography(cam, p_true))[0]
        err_reg.append(np.abs(cv2.perspectiveTransform(ground, g)[0] - want).max())
        err_tel.append(np.abs(cv2.perspectiveTransform(ground, ground_to_image_homography(cam, p_tel))[0] - want).max())
    assert reg.failures == 0
    # the frame-to-frame jitter is what smears the layer: compare the change of the error between frames
    assert np.abs(np.diff(err_reg)).mean() < 0.3 * np.abs(np.diff(err_tel)).mean()
    # the absolute error keeps the noise of the first frames the registration started from: over other noise
    # draws it is ~0.9 of the telemetry's with or without the drift estimate, while the jitter above is 0.07-0.10
    # of the telemetry's (0.10-0.74 before the image-motion start and the drift estimate)
    assert np.mean(err_reg) < 0.75 * np.mean(err_tel)


def test_registration_follows_a_fast_turn_under_sample_and_hold_telemetry():
    """A 75 deg/s heading sweep with 10 Hz sample-and-hold telemetry (its relative motion is 0, 0, then three
    frames' turn): started from the telemetry's motion ECC lost the frames and the placement drifted 57 pixels
    (a 320-pixel frame); started from the previous frame's image motion when that aligns better, it stays
    within the 11 pixels the telemetry itself is off."""
    from agent.anomaly.registration import GroundRegistration
    from shared.geo import ground_to_image_homography

    cam = Camera(width=320, height=180, fx=225.0, fy=225.0, cx=160.0, cy=90.0)
    heading = np.cumsum([0.0] * 10 + [2.5] * 25 + [0.0] * 10)
    truth = [Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=60.0, heading_deg=float(h)) for h in heading]
    telemetry = [truth[3 * (i // 3)] for i in range(len(truth))]
    reg = GroundRegistration(ecc_width=320)
    ground = np.array([[[0.0, 15.0], [3.0, 20.0], [-4.0, 12.0]]])
    errors = []
    for i, (frame, p_true, p_tel) in enumerate(zip(_ground_frames(truth, cam), truth, telemetry, strict=True)):
        g = reg.update(frame, cam, p_tel, 0, i / 30)
        want = cv2.perspectiveTransform(ground, ground_to_image_homography(cam, p_true))[0]
        errors.append(np.abs(cv2.perspectiveTransform(ground, g)[0] - want).max())
    assert max(errors) < 8.0


def test_registration_pulls_less_towards_late_telemetry_while_the_view_sweeps():
    """A 75 deg/s sweep seen with 10 Hz sample-and-hold telemetry that is also two frames late: its placement is
    off by the turn of up to four frames. Pulled towards it at the full 5 % a frame, the placement drifted 15
    pixels (a 320-pixel frame) and moved 9 pixels within half a second; weighted by the share of the telemetry's
    error that is not its timing it stays within 3."""
    from agent.anomaly.registration import GroundRegistration
    from shared.geo import ground_to_image_homography

    cam = Camera(width=320, height=180, fx=225.0, fy=225.0, cx=160.0, cy=90.0)
    heading = np.cumsum([0.0] * 10 + [2.5] * 30 + [0.0] * 10)
    truth = [Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=60.0, heading_deg=float(h)) for h in heading]
    telemetry = [truth[max(3 * (i // 3) - 2, 0)] for i in range(len(truth))]
    ground = np.array([[[0.0, 15.0], [3.0, 20.0], [-4.0, 12.0]]])
    frames = _ground_frames(truth, cam)
    worst = {}
    for noise in (0.5, None):
        reg = GroundRegistration(ecc_width=320, telemetry_noise_m=noise)
        errors = []
        for i, (frame, p_true, p_tel) in enumerate(zip(frames, truth, telemetry, strict=True)):
            g = reg.update(frame, cam, p_tel, 0, i / 30)
            want = cv2.perspectiveTransform(ground, ground_to_image_homography(cam, p_true))[0]
            errors.append(np.abs(cv2.perspectiveTransform(ground, g)[0] - want).max())
        worst[noise] = max(errors)
        if noise is not None:
            assert reg.telemetry_interval_s == pytest.approx(0.1, abs=0.02)  # measured from the fresh samples
    assert worst[0.5] < 3.0 < 10.0 < worst[None]


def test_registration_takes_the_drift_of_the_water_out():
    """A still camera over water whose texture drifts at 1.7 m/s, telemetry exact: the images follow the water,
    the pull holds them back; without a drift estimate the placement settled 7 pixels off (a 320-pixel frame),
    with it the drift is estimated and the placement is within 2 pixels after 3 s."""
    from agent.anomaly.registration import GroundRegistration
    from shared.geo import ground_to_image_homography

    cam = Camera(width=320, height=180, fx=225.0, fy=225.0, cx=160.0, cy=90.0)
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur((rng.random((1600, 1600, 3)) * 255).astype(np.uint8), (0, 0), 2.0)
    pose = Pose(lat=47.6, lon=9.3, height_m=30.0, pitch_deg=60.0, heading_deg=20.0)
    velocity = np.array([1.2, -1.2])
    reg = GroundRegistration(ecc_width=320)
    ground = np.array([[[0.0, 15.0], [3.0, 20.0], [-4.0, 12.0]]])
    want = cv2.perspectiveTransform(ground, ground_to_image_homography(cam, pose))[0]
    errors = []
    for i in range(120):
        d = velocity * i / 30
        texel_to_metres = np.array([[0.05, 0, -40.0 + d[0]], [0, -0.05, 40.0 + d[1]], [0, 0, 1.0]])
        frame = cv2.warpPerspective(texture, ground_to_image_homography(cam, pose) @ texel_to_metres,
                                    (cam.width, cam.height))
        g = reg.update(frame, cam, pose, 0, i / 30)
        errors.append(np.abs(cv2.perspectiveTransform(ground, g)[0] - want).max())
    assert np.mean(errors[-30:]) < 2.0
    assert np.linalg.norm(reg.drift_mps - velocity) < 0.3 * np.linalg.norm(velocity)


def test_a_full_resolution_4k_heatmap_keeps_a_small_object():
    """The 4K path (resampled to 4 pixels a cell, then averaged over each cell's footprint) keeps a 12-pixel
    object's heat as well as the working-size heatmap of the same frame does. The object is 0.2 m across, a
    sixth of the box around a 0.4 m cell's footprint there, so both keep the same small share of its heat."""
    cam = Camera(width=3840, height=2160, fx=2700.0, fy=2700.0, cx=1920.0, cy=1080.0)
    heat = np.zeros((2160, 3840), np.float32)
    heat[1794:1806, 2394:2406] = 1.0
    small = cv2.resize(heat, (640, 360), interpolation=cv2.INTER_AREA)
    small /= small.max()
    peaks = []
    for h in (heat, small):
        layer = AnomalyMap()
        for i in range(5):
            layer.update(h, cam, POSE, i / 30)
        back = layer.image_scores(cam, POSE, (360, 640))
        peak = np.unravel_index(np.argmax(back), back.shape)
        assert abs(peak[0] - 300) <= 2 and abs(peak[1] - 400) <= 2
        peaks.append(back.max())
    assert peaks[0] >= 0.9 * peaks[1] > 0.03


def test_image_registration_goes_on_while_the_lens_zooms():
    """A zoom gives every frame a new camera (agent.field_of_view); the registration compared cameras and was off
    for the whole zoom. Only the frame size matters: the focal length is in the telemetry homographies."""
    import cv2

    from agent.anomaly.registration import GroundRegistration
    from agent.field_of_view import FieldOfView

    cam = Camera(width=640, height=360, fx=500.0, fy=500.0, cx=320.0, cy=180.0)
    img = cv2.GaussianBlur((np.random.default_rng(0).random((360, 640, 3)) * 255).astype(np.uint8), (7, 7), 2)
    pose = Pose(lat=48.5, lon=9.0, height_m=50.0, pitch_deg=70.0, heading_deg=0.0)
    ts = np.arange(0.0, 10.01, 0.1)
    zoom = FieldOfView(ts, 65.0 - 3.5 * ts, cam)  # 65 -> 30 deg over 10 s
    for cameras in ([cam] * 3, [zoom.camera_at(t) for t in (5.0, 5.033, 5.067)]):
        reg, used = GroundRegistration(), []
        for k, camera in enumerate(cameras):
            reg.update(img, camera, pose, row0=0, t=k / 30)
            used.append(reg._motion_prev is not None)
        assert used == [False, True, True]
    refit = Camera(width=320, height=180, fx=250.0, fy=250.0, cx=160.0, cy=90.0)  # another frame size: starts over
    reg = GroundRegistration()
    reg.update(img, cam, pose, row0=0, t=0.0)
    reg.update(cv2.resize(img, (320, 180)), refit, pose, row0=0, t=1 / 30)
    assert reg._motion_prev is None

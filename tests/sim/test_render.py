"""Rendering of simulated datasets: determinism, objects where the annotations are, sky above the horizon,
files OpenCV reads back (JPEG, MP4), telemetry that the readers parse and that matches the meta, clear errors."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.geo import Camera, Pose, horizon_row, latlon_to_local, local_to_latlon, local_to_pixel
from shared.telemetry import read_csv, read_srt
from sim.dataset import write_dataset
from sim.groundtruth import project_objects
from sim.render import RenderOptions, SimulatedDataset, WorldRenderer, exposure_for, render_dataset, sprites
from sim.render.effects import ExposureDrift, haze_rows, motion_blur, tone
from sim.render.geometry import first_ground_row, project_enu, sun_position
from sim.render.scene import CONTINUE_S, _continued
from sim.render.telemetry_files import format_srt, frame_records
from sim.render.texture import NoiseBank, TexelGrid, make_ground, world_noise
from sim.scenarios import get_scenario
from sim.world import CLASS_BOX_M
from uavmm.cli import main

SIZE = (640, 360)
FRAMES = 24
OPTIONS = RenderOptions(max_texture_px=1024)


def simulate(tmp_path_factory: pytest.TempPathFactory, scenario: str, seed: int = 0, frames: int = FRAMES,
             size: tuple[int, int] = SIZE) -> Path:
    out = tmp_path_factory.mktemp(f"render-{scenario}-{seed}") / "data"
    write_dataset(dataclasses.replace(get_scenario(scenario), image_size=size), out, seed=seed, frames=frames,
                  progress=False)
    return out


@pytest.fixture(scope="module")
def coop(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """The coop scenario (one world, two UAVs) rendered to images and videos."""
    data = simulate(tmp_path_factory, "coop")
    return data, render_dataset(data, images=True, video=True, options=OPTIONS, progress=False)


@pytest.fixture(scope="module")
def sea(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sea scenario (three worlds, ~1 % frames without meta), not rendered."""
    return simulate(tmp_path_factory, "sea", seed=2, frames=60, size=(320, 180))


def annotations_by_image(data: Path) -> dict[int, list[dict]]:
    coco = json.loads((data / "images.json").read_text())
    out: dict[int, list[dict]] = {int(im["id"]): [] for im in coco["images"]}
    for a in coco["annotations"]:
        out[int(a["image_id"])].append(a)
    return out


# ---------------------------------------------------------------------------------------------- determinism

def test_the_same_seed_gives_the_same_files_and_another_seed_other_pixels(tmp_path_factory):
    runs = [simulate(tmp_path_factory, "coop", seed=s, frames=4) for s in (0, 0, 1)]
    for data in runs:
        render_dataset(data, images=True, video=False, options=OPTIONS, progress=False)
    names = [im["file_name"] for im in json.loads((runs[0] / "images.json").read_text())["images"]]
    assert len(names) == 8
    for name in names:
        assert (runs[0] / name).read_bytes() == (runs[1] / name).read_bytes()
        a = cv2.imread(str(runs[0] / name)).astype(int)
        c = cv2.imread(str(runs[2] / name)).astype(int)
        assert np.abs(a - c).mean() > 5.0  # another world, other flights


def test_rendering_a_frame_twice_gives_identical_pixels(coop):
    data, _ = coop
    ds = SimulatedDataset(data)
    video = ds.videos[0]
    frame = list(ds.frames(video))[5]
    first = WorldRenderer(ds, ds.worlds[video.group], OPTIONS).render(frame, exposure_for(ds, video))
    second = WorldRenderer(ds, ds.worlds[video.group], OPTIONS).render(frame, exposure_for(ds, video))
    assert first.shape == (SIZE[1], SIZE[0], 3) and first.dtype == np.uint8
    assert np.array_equal(first, second)


# ---------------------------------------------------------------------------------------------- objects

def _mark_near(mask: np.ndarray, box: tuple[float, float, float, float]) -> None:
    """Set mask True around an xyxy box, one box size on each side (shadows reach about one body length)."""
    x0, y0, x1, y1 = box
    pad_x, pad_y = int(x1 - x0) + 3, int(y1 - y0) + 3
    mask[max(int(y0) - pad_y, 0):int(math.ceil(y1)) + pad_y, max(int(x0) - pad_x, 0):int(math.ceil(x1)) + pad_x] = True


def test_objects_are_drawn_inside_their_ground_truth_boxes(coop):
    """Pixels inside each annotated box differ from the same frame drawn without the tracked objects, and what
    changes lies next to some object's box (its shadow included): annotated ones, and those the simulator
    leaves unannotated (under 4 px, cut by the border, behind a tree), boxed here by `sim.groundtruth`."""
    data, _ = coop
    ds = SimulatedDataset(data)
    annotations = annotations_by_image(data)
    checked = 0
    for video in ds.videos:
        renderer = WorldRenderer(ds, ds.worlds[video.group], OPTIONS)
        world = ds.worlds[video.group]
        for frame in list(ds.frames(video))[::6]:
            if frame.blurred:
                continue
            drawn = renderer.render(frame).astype(int)
            empty = renderer.render(dataclasses.replace(frame, objects=())).astype(int)
            changed = np.abs(drawn - empty).max(axis=2) > 12
            explained = np.zeros_like(changed)
            for a in annotations[frame.image_id]:
                x, y, w, h = a["bbox"]
                if w >= 4 and h >= 6:
                    inside = changed[int(y):int(math.ceil(y + h)), int(x):int(math.ceil(x + w))]
                    assert inside.mean() >= 0.2, (frame.image_id, a["track_id"], a["bbox"])
                    checked += 1
                _mark_near(explained, (x, y, x + w, y + h))
            objs = [o for o in frame.objects if o.known]
            lat, lon = local_to_latlon(np.array([o.east_m for o in objs]), np.array([o.north_m for o in objs]),
                                       world.origin_lat, world.origin_lon)
            boxes = project_objects(lat, lon, np.array([o.yaw_deg for o in objs]), CLASS_BOX_M["person"],
                                    renderer.camera, frame.pose)
            for box, valid in zip(boxes.boxes_xyxy, boxes.valid, strict=True):
                if valid:
                    _mark_near(explained, tuple(box))
            assert changed.sum() > 0
            assert (changed & ~explained).sum() <= 0.02 * changed.sum(), frame.image_id
    assert checked >= 20


@settings(max_examples=60, deadline=None)
@given(height=st.floats(10.0, 100.0), pitch=st.floats(17.0, 90.0), heading=st.floats(0.0, 360.0),
       yaw=st.floats(0.0, 360.0), along=st.floats(-0.3, 0.3), across=st.floats(-0.3, 0.3))
def test_a_person_sprite_fills_most_of_its_ground_truth_box_and_stays_inside(height, pitch, heading, yaw, along,
                                                                              across):
    """A person is drawn at its metric size: the sprite's box lies inside the simulator's box of the projected
    0.5 x 0.3 x 1.7 m volume and fills most of it."""
    cam = Camera.from_preset("dji-mavic2-pro", 1920, 1080)
    pose = Pose(48.5, 9.0, height, pitch, heading)
    h = math.radians(heading)
    forward = height / math.tan(math.radians(max(pitch, 20.0))) * (1.0 + along)
    east = forward * math.sin(h) + across * height * math.cos(h)
    north = forward * math.cos(h) - across * height * math.sin(h)
    lat, lon = local_to_latlon(east, north, pose.lat, pose.lon)
    truth = project_objects(np.array([lat]), np.array([lon]), np.array([yaw]), CLASS_BOX_M["person"], cam, pose)
    proj = sprites.project_placed(sprites.Placed(sprites.person(np.random.default_rng(0)), east, north, yaw), cam,
                                  pose, (0.0, 0.0), None)
    assert proj is not None and truth.valid[0]
    bx0, by0, bx1, by1 = truth.boxes_xyxy[0]
    sx0, sy0, sx1, sy1 = proj.box
    assert bx0 - 0.5 <= sx0 and sx1 <= bx1 + 0.5 and by0 - 0.5 <= sy0 and sy1 <= by1 + 0.5
    assert sx1 - sx0 >= 0.6 * (bx1 - bx0) and sy1 - sy0 >= 0.7 * (by1 - by0)


@pytest.mark.parametrize("gap_px", [1.0, 1.7, 3.0])  # nearer, anti-aliasing reaches the edge pixel
def test_a_sprite_just_outside_the_left_or_top_border_draws_nothing_and_does_not_fail(gap_px):
    """Regression: a sprite ending within 2 px left of (or above) the image broke the texture lookup."""
    cam = Camera.from_preset("dji-mavic2-pro", 320, 180)
    pose = Pose(48.5, 9.0, 20.0, 45.0, 0.0)
    placed = sprites.Placed(sprites.person(np.random.default_rng(0)), 0.0, 20.0, 0.0)
    proj = sprites.project_placed(placed, cam, pose, (0.0, 0.0), None)
    assert proj is not None
    for axis in (0, 1):
        shift = np.zeros(2, np.int32)
        shift[axis] = -int(round((proj.box[2 + axis] + gap_px) * 16))
        moved = dataclasses.replace(
            proj, sides=[p + shift for p in proj.sides], tops=[p + shift for p in proj.tops],
            box=tuple(v + shift[i % 2] / 16 for i, v in enumerate(proj.box)),
            reach=tuple(v + shift[i % 2] / 16 for i, v in enumerate(proj.reach)))
        frame = np.full((180, 320, 3), 90, np.uint8)
        assert sprites.draw_placed(frame, placed, moved, 0.0) is False
        assert (frame == 90).all()


def test_an_object_grazing_the_camera_plane_is_skipped_without_overflow_warnings():
    """Regression: a tree top a hair below a nadir camera projected ~1e8 px out and overflowed int32."""
    import warnings

    cam = Camera.from_preset("dji-mavic2-pro", 3840, 2160)
    pose = Pose(48.5, 9.0, 10.0, 90.0, 0.0)
    tree = sprites.Placed(sprites.tree(np.random.default_rng(0), 3.0, 10.0 - 2e-6), 0.0, 0.0, 0.0)
    person = sprites.Placed(sprites.person(np.random.default_rng(1)), 0.0, 2.0, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        projections = sprites.project_many([tree, person], cam, pose, (0.0, 0.0), np.array([0.3, 0.4]))
    assert projections[0] is None and projections[1] is not None


def test_each_object_keeps_its_look_so_appearance_from_pixels_tells_them_apart(coop):
    """Colour histograms of the rendered boxes (the agent's re-ID descriptor) are closer for one object across
    frames than between objects."""
    from agent.tracking.appearance import hsv_histogram_descriptors

    data, _ = coop
    coco = json.loads((data / "images.json").read_text())
    images = {im["id"]: im for im in coco["images"]}
    by_track: dict[int, list[np.ndarray]] = {}
    for image_id, anns in annotations_by_image(data).items():
        big = [a for a in anns if a["bbox"][2] >= 5 and a["bbox"][3] >= 10]
        if not big:
            continue
        pixels = cv2.imread(str(data / images[image_id]["file_name"]))
        boxes = np.array([[a["bbox"][0], a["bbox"][1], a["bbox"][0] + a["bbox"][2], a["bbox"][1] + a["bbox"][3]]
                          for a in big])
        for a, d in zip(big, hsv_histogram_descriptors(pixels, boxes), strict=True):
            if np.isfinite(d).all():
                by_track.setdefault(a["track_id"], []).append(d)
    tracks = [t for t, ds in by_track.items() if len(ds) >= 3]
    assert len(tracks) >= 5
    same, other = [], []
    for i, t in enumerate(tracks):
        d = np.array(by_track[t])
        sim = d @ d.T
        same.append(sim[np.triu_indices(len(d), 1)].mean())
        for u in tracks[i + 1:]:
            other.append((d @ np.array(by_track[u]).T).mean())
    assert np.mean(same) > 0.85
    assert np.mean(same) > np.mean(other) + 0.3


# ---------------------------------------------------------------------------------------------- sky, haze, blur

def test_the_sky_fills_the_rows_above_the_horizon_and_the_ground_the_rows_below(coop):
    data, _ = coop
    ds = SimulatedDataset(data)
    video = ds.videos[0]
    renderer = WorldRenderer(ds, ds.worlds[video.group], dataclasses.replace(OPTIONS, sensor_noise_std=0.0))
    frame = list(ds.frames(video))[0]
    pose = dataclasses.replace(frame.pose, pitch_deg=8.0)
    image = renderer.render(dataclasses.replace(frame, pose=pose, objects=(), blurred=False)).astype(float)
    row = horizon_row(renderer.camera, pose)
    assert 40 < row < SIZE[1] - 40
    sky = image[: int(math.floor(row - 0.5))]
    ground = image[int(math.ceil(row + 0.5)) + 4:]
    assert sky.std(axis=1).max() < 1.0  # one colour per row: nothing but sky up there
    assert (sky[..., 0] > sky[..., 2]).all()  # blue above red
    assert sky[0, :, 0].mean() - sky[0, :, 2].mean() > sky[-1, :, 0].mean() - sky[-1, :, 2].mean()  # bluer upwards
    assert ground.std(axis=1).mean() > 3.0 * max(sky.std(axis=1).mean(), 0.5)  # textured ground
    assert ground[..., 1].mean() > ground[..., 0].mean()  # a green meadow
    assert first_ground_row(renderer.camera, pose) == int(math.floor(row - 0.5)) + 1


@settings(max_examples=100, deadline=None)
@given(height=st.floats(2.0, 500.0), pitch=st.floats(0.0, 90.0), heading=st.floats(0.0, 360.0))
def test_first_ground_row_is_the_first_row_whose_centres_are_below_the_horizon(height, pitch, heading):
    cam = Camera.from_preset("dji-mavic2-pro", 640, 360)
    pose = Pose(48.5, 9.0, height, pitch, heading)
    row = first_ground_row(cam, pose)
    horizon = horizon_row(cam, pose)
    assert 0 <= row <= cam.height
    if row < cam.height:
        assert row + 0.5 > horizon
    if row > 0:
        assert row - 0.5 <= horizon


@settings(max_examples=100, deadline=None)
@given(height=st.floats(5.0, 120.0), pitch=st.floats(17.0, 90.0), heading=st.floats(0.0, 360.0),
       u=st.floats(0.0, 640.0), v=st.floats(0.6, 1.0))
def test_project_enu_agrees_with_shared_geo_on_the_ground(height, pitch, heading, u, v):
    cam = Camera.from_preset("dji-mavic2-pro", 640, 360)
    pose = Pose(48.5, 9.0, height, pitch, heading)
    from shared.geo import pixel_to_local

    east, north, ok = pixel_to_local(np.array([[u, v * cam.height]]), cam, pose)
    if not ok[0]:
        return
    expected, valid = local_to_pixel(east, north, cam, pose)
    got, ok3 = project_enu(np.array([[east[0], north[0], 0.0]]), cam, pose)
    assert valid[0] and ok3[0]
    assert np.allclose(got, expected, atol=1e-6)


def test_haze_is_zero_in_the_sky_and_grows_towards_the_horizon(coop):
    data, _ = coop
    ds = SimulatedDataset(data)
    renderer = WorldRenderer(ds, ds.worlds[0], OPTIONS)
    pose = Pose(48.53, 9.06, 30.0, 10.0, 0.0)
    first = first_ground_row(renderer.camera, pose)
    alpha = haze_rows(renderer.camera, pose, renderer.atmosphere, first)
    assert first > 0 and (alpha[:first] == 0).all()
    below = alpha[first:]
    assert (np.diff(below) <= 1e-12).all() and 0.0 < below[-1] < below[0] < 1.0


def test_tone_pulls_hazy_rows_towards_the_haze_colour():
    frame = np.zeros((4, 8, 3), np.uint8)
    tone(frame, np.array([0.0, 0.0, 0.5, 1.0]), (200.0, 210.0, 220.0), np.ones(3))
    assert (frame[0] == 0).all() and (frame[1] == 0).all()
    assert np.allclose(frame[2, 0], (100, 105, 110), atol=2)
    assert (frame[3, 0] > frame[2, 0]).all()


def test_fast_turns_blur_the_frame_along_the_image_rows(coop):
    data, _ = coop
    ds = SimulatedDataset(data)
    video = ds.videos[1]
    renderer = WorldRenderer(ds, ds.worlds[video.group], dataclasses.replace(OPTIONS, sensor_noise_std=0.0))
    frame = dataclasses.replace(list(ds.frames(video))[3], blurred=False)
    sharp = renderer.render(frame).astype(np.float32)
    smeared = renderer.render(dataclasses.replace(frame, blurred=True, heading_rate_deg_s=80.0)).astype(np.float32)
    dx = lambda im: np.abs(np.diff(im, axis=1)).mean()  # noqa: E731
    dy = lambda im: np.abs(np.diff(im, axis=0)).mean()  # noqa: E731
    assert dx(smeared) < 0.6 * dx(sharp)
    assert dx(smeared) / dy(smeared) < 0.7 * dx(sharp) / dy(sharp)  # a yaw turn smears sideways


@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 45.0, 90.0, 135.0, 170.0])
def test_motion_blur_smears_a_point_into_a_centred_line_of_its_length_and_direction(angle_deg):
    image = np.zeros((101, 161, 3), np.uint8)
    image[50, 80] = 255
    smear = motion_blur(image, 21, angle_deg)[..., 0].astype(float)
    ys, xs = np.nonzero(smear > 2)
    weight = smear[ys, xs]
    assert np.average(xs, weights=weight) == pytest.approx(80.0, abs=0.5)
    assert np.average(ys, weights=weight) == pytest.approx(50.0, abs=0.5)
    values, vectors = np.linalg.eigh(np.cov(np.vstack([xs, ys]), aweights=weight))
    direction = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1])) % 180.0
    assert min(abs(direction - angle_deg), 180.0 - abs(direction - angle_deg)) < 2.0  # 45: down and to the right
    assert 2.0 * math.sqrt(3.0 * values[1]) == pytest.approx(21.0, abs=1.5)  # a uniform segment's length


def test_exposure_drift_is_deterministic_slow_and_bounded():
    a = ExposureDrift(900, 30.0, np.random.default_rng(5))
    b = ExposureDrift(900, 30.0, np.random.default_rng(5))
    gains = np.array([a.channel_gains(i, 0.0) for i in range(900)])
    assert np.array_equal(gains, np.array([b.channel_gains(i, 0.0) for i in range(900)]))
    assert 0.6 < gains.min() and gains.max() < 1.6 and gains.std() > 0.01
    assert np.abs(np.diff(gains, axis=0)).max() < 0.02  # slow: no flicker between frames
    assert (a.channel_gains(0, 1.0) < a.channel_gains(0, 0.0)).all()  # a sky-filled frame is exposed darker


def test_sun_position_follows_the_solar_geometry():
    # 2023-06-01 10:00 UTC at 47.6 N, 9.3 E: solar time 10:39, hour angle -20.2 deg, declination 22.0 deg give
    # elevation asin(sin 47.6 sin 22.0 + cos 47.6 cos 22.0 cos 20.2) = 59.7 deg and azimuth 140.6 deg
    az, el = sun_position(47.6, 9.3, 1685613600.0)
    assert az == pytest.approx(140.6, abs=1.0) and el == pytest.approx(59.7, abs=1.0)
    # at solar noon the sun is due south, 90 - latitude + declination high; on the equinox, 90 - latitude
    noon_utc = 1685613600.0 + 2 * 3600 - 9.3 * 240 - 2.3 * 60  # 12:00 solar time, equation of time +2.3 min
    az, el = sun_position(47.6, 9.3, noon_utc)
    assert az == pytest.approx(180.0, abs=1.0) and el == pytest.approx(90.0 - 47.6 + 22.0, abs=0.5)
    az, el = sun_position(0.0, 0.0, 1679313600.0 + 7 * 60)  # 2023-03-20 12:07 UTC, the equinox at Greenwich
    assert el == pytest.approx(90.0, abs=1.0)


# ---------------------------------------------------------------------------------------------- ground

def test_ground_noise_is_anchored_to_the_world_so_textures_agree_where_they_overlap():
    bank = NoiseBank(np.random.default_rng(3))
    a = world_noise(TexelGrid((120, 120), 0.1, 0.0, 10.0), 0.8, bank.table("x"))
    b = world_noise(TexelGrid((60, 60), 0.1, 2.0, 7.0), 0.8, bank.table("x"))  # 20 columns east, 30 rows south
    assert np.allclose(a[30:90, 20:80], b, atol=1e-4)
    assert a.std() > 0.2


def test_make_ground_rejects_an_unknown_kind_and_a_bad_resolution():
    bank, rng = NoiseBank(np.random.default_rng(0)), np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown ground kind 'lava'; valid: meadow, sea"):
        make_ground("lava", (0.0, 0.0, 10.0, 10.0), 0.1, bank, rng)
    with pytest.raises(ValueError, match="resolution must be > 0"):
        make_ground("sea", (0.0, 0.0, 10.0, 10.0), 0.0, bank, rng)


def test_sea_ground_has_waves_and_glint_potential_meadow_none():
    bank, rng = NoiseBank(np.random.default_rng(0)), np.random.default_rng(0)
    sea_ground = make_ground("sea", (0.0, 0.0, 40.0, 40.0), 0.05, bank, rng).levels[0]
    meadow = make_ground("meadow", (0.0, 0.0, 40.0, 40.0), 0.05, bank, rng).levels[0]
    assert sea_ground[..., 3].max() > 100 and (meadow[..., 3] == 0).all()
    assert sea_ground[..., 0].mean() > sea_ground[..., 2].mean()  # blue water
    assert meadow[..., 1].mean() > meadow[..., 0].mean()  # green grass


# ---------------------------------------------------------------------------------------------- scene

def test_positions_continue_at_most_a_second_beyond_the_sightings():
    table = np.array([[10.0, 0.0, 0.0], [11.0, 0.0, 1.0], [12.0, 0.0, 2.0]])  # north 1 m a frame
    fps = 30.0
    east, north, ok = _continued(table, 15, CONTINUE_S * fps, 7.5)
    assert ok and east == pytest.approx(0.0) and north == pytest.approx(5.0)
    east, north, ok = _continued(table, 5, CONTINUE_S * fps, 7.5)
    assert ok and north == pytest.approx(-5.0)
    assert not _continued(table, 12 + 31, CONTINUE_S * fps, 7.5)[2]
    gap = np.array([[0.0, 0.0, 0.0], [20.0, 4.0, 0.0]])  # 20 frames apart: interpolated
    east, _, ok = _continued(gap, 5, CONTINUE_S * fps, 7.5)
    assert ok and east == pytest.approx(1.0)


def test_known_positions_are_the_annotated_ones(coop):
    data, _ = coop
    ds = SimulatedDataset(data)
    world = ds.worlds[0]
    annotations = annotations_by_image(data)
    video = ds.videos[1]
    frame = list(ds.frames(video))[7]
    by_track = {o.track_id: o for o in frame.objects}
    assert annotations[frame.image_id]
    for a in annotations[frame.image_id]:
        obj = by_track[a["track_id"]]
        east, north = latlon_to_local(a["lat"], a["lon"], world.origin_lat, world.origin_lon)
        assert obj.known and obj.east_m == pytest.approx(float(east), abs=1e-3)
        assert obj.north_m == pytest.approx(float(north), abs=1e-3)


# ---------------------------------------------------------------------------------------------- files

def test_images_are_written_where_images_json_says_and_read_back_with_opencv(coop):
    data, summary = coop
    coco = json.loads((data / "images.json").read_text())
    assert summary["images"] == len(coco["images"]) == 2 * FRAMES
    for im in coco["images"]:
        pixels = cv2.imread(str(data / im["file_name"]))
        assert pixels is not None and pixels.shape == (im["height"], im["width"], 3)
    ds = SimulatedDataset(data)
    video = ds.videos[0]
    frame = list(ds.frames(video))[2]
    drawn = WorldRenderer(ds, ds.worlds[video.group], OPTIONS).render(frame, exposure_for(ds, video))
    read = cv2.imread(str(data / frame.file_name))
    assert np.abs(drawn.astype(int) - read.astype(int)).mean() < 4.0  # JPEG at quality 90
    report = json.loads((data / "render.json").read_text())
    assert report["summary"]["frames"] == 2 * FRAMES and report["worlds"][0]["kind"] == "meadow"
    assert {s["kind"] for s in report["worlds"][0]["scenery"]} == {"car"}


def test_each_mp4_decodes_with_opencv_to_all_its_frames(coop):
    data, summary = coop
    assert len(summary["videos"]) == 2
    for path in summary["videos"]:
        capture = cv2.VideoCapture(path)
        assert capture.isOpened()
        assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
        count = 0
        while True:
            ok, pixels = capture.read()
            if not ok:
                break
            assert pixels.shape == (SIZE[1], SIZE[0], 3)
            count += 1
        capture.release()
        assert count == FRAMES


def test_srt_and_csv_parse_and_match_the_images_meta(coop):
    data, summary = coop
    ds = SimulatedDataset(data)
    for video in ds.videos:
        frames = list(ds.frames(video))
        srt = read_srt(data / f"{video.name}.srt")
        table = read_csv(data / f"{video.name}.csv")
        assert len(srt) == len(table) == len(frames)
        for frame, a, b in zip(frames, srt, table, strict=True):
            assert a.t == pytest.approx(frame.t, abs=1e-3) and b.t == pytest.approx(frame.t, abs=1e-3)
            meta = frame.meta
            assert meta is not None  # coop has no dropouts
            assert a.lat == pytest.approx(meta["gps_latitude"], abs=6e-7)
            assert a.lon == pytest.approx(meta["gps_longitude"], abs=6e-7)
            assert b.lat == pytest.approx(meta["gps_latitude"], abs=1e-9)
            assert b.lon == pytest.approx(meta["gps_longitude"], abs=1e-9)
            for rec, tol in ((a, 0.051), (b, 1e-6)):
                assert rec.height_m == pytest.approx(meta["altitude"], abs=tol)
                assert rec.pitch_deg == pytest.approx(meta["gimbal_pitch"], abs=tol)
                turn = (rec.heading_deg - meta["gimbal_heading"] + 180.0) % 360.0 - 180.0
                assert abs(turn) <= tol
    assert sorted(summary["telemetry"]) == sorted(str(data / f"{v.name}.{ext}") for v in ds.videos
                                                  for ext in ("srt", "csv"))


def test_frames_without_meta_repeat_the_previous_telemetry(sea):
    ds = SimulatedDataset(sea)
    frames = [(f.frame_index, f.t, f.meta) for v in ds.videos for f in ds.frames(v) if v.id == 1]
    metas = [m for _, _, m in frames]
    first, later = next(m for m in metas if m is not None), [m for m in metas if m is not None][1]
    synthetic = [(0, 10.0, None), (1, 10.1, first), (2, 10.2, None), (3, 10.3, later)]
    records = frame_records(synthetic)
    assert [r.t for r in records] == [10.0, 10.1, 10.2, 10.3] and [r.frame for r in records] == [0, 1, 2, 3]
    assert records[0].lat == records[1].lat == records[2].lat == pytest.approx(first["gps_latitude"])
    assert records[3].lat == pytest.approx(later["gps_latitude"])
    with pytest.raises(ValueError, match="no frame of the video has telemetry"):
        frame_records([(0, 1.0, None)])
    with pytest.raises(ValueError, match="fps must be > 0"):
        format_srt(records, 0.0)


def test_the_rendered_video_and_srt_play_through_the_agents_video_source(coop, tmp_path):
    """`VideoSource` (what `uavmm agent --video` reads) decodes the MP4, gives every frame a pose from the SRT
    close to the image's meta, and hands the pixels on for appearance descriptors."""
    pytest.importorskip("onnx")
    from agent.sources import VideoSource
    from tests.agent.test_sources import _write_model

    data, _ = coop
    ds = SimulatedDataset(data)
    video = ds.videos[1]
    source = VideoSource(data / f"{video.name}.mp4", data / f"{video.name}.srt", _write_model(tmp_path / "m.onnx"),
                         data / "camera.json")
    frames = list(source.frames())
    expected = list(ds.frames(video))
    assert len(frames) == FRAMES
    assert (source.camera.width, source.camera.height) == SIZE
    for got, want in zip(frames, expected, strict=True):
        assert got.pose is not None and got.image is not None and got.image.shape == (SIZE[1], SIZE[0], 3)
        assert got.pose.lat == pytest.approx(want.meta["gps_latitude"], abs=1e-6)
        assert got.pose.heading_deg == pytest.approx(want.meta["gimbal_heading"], abs=0.06)
        assert got.t == pytest.approx(want.t, abs=1e-3)
        jpeg = cv2.imread(str(data / want.file_name)).astype(int)
        assert np.abs(got.image.astype(int) - jpeg).mean() < 8.0  # the same picture, two codecs


# ---------------------------------------------------------------------------------------------- errors

def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err, err


def test_render_errors_are_one_clear_line_and_exit_2(coop, tmp_path, capsys):
    data, _ = coop
    _one_line_error(capsys, ["render", str(tmp_path / "missing")], f"dataset directory {tmp_path / 'missing'} "
                                                                    "does not exist")
    plain = tmp_path / "plain"
    plain.mkdir()
    _one_line_error(capsys, ["render", str(plain)], "is not a dataset directory: images.json is missing")
    (plain / "images.json").write_text((data / "images.json").read_text())
    _one_line_error(capsys, ["render", str(plain)], "is not a simulated dataset: camera.json, truth.json missing")
    shutil.copy(data / "camera.json", plain / "camera.json")
    (plain / "truth.json").write_text("{not json")
    _one_line_error(capsys, ["render", str(plain)], "truth.json is not valid JSON")
    shutil.copy(data / "truth.json", plain / "truth.json")
    coco = json.loads((data / "images.json").read_text())
    for a in coco["annotations"]:
        del a["lat"]
    (plain / "images.json").write_text(json.dumps(coco))
    _one_line_error(capsys, ["render", str(plain)], "annotation(s) have no true 'lat'/'lon'")
    _one_line_error(capsys, ["render", str(data), "--no-images"], "--no-images writes nothing without --video")
    _one_line_error(capsys, ["render", str(data), "--jpeg-quality", "0"], "--jpeg-quality must be in 1..100")
    _one_line_error(capsys, ["render", str(data), "--max-texture-px", "10"], "max_texture_px=10 must be")
    _one_line_error(capsys, ["sim", "coop", "--out", str(tmp_path / "o"), "--image-size", "641x360", "--render"],
                    "--image-size needs even numbers")
    _one_line_error(capsys, ["sim", "coop", "--out", str(tmp_path / "o"), "--image-size", "big", "--render"],
                    "--image-size must look like 1920x1080")
    assert not (tmp_path / "o").exists()  # refused before simulating


def test_uavmm_sim_render_video_writes_the_dataset_the_frames_and_the_videos(tmp_path, capsys):
    out = tmp_path / "grass"
    assert main(["sim", "grass", "--out", str(out), "--frames", "3", "--image-size", "320x180", "--render", "--video",
                 "--no-images", "--max-texture-px", "512", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "rendered" in printed and "4 videos" in printed and "0 images" in printed
    names = [v["name"] for v in json.loads((out / "images.json").read_text())["videos"]]
    for name in names:
        assert (out / f"{name}.mp4").is_file() and (out / f"{name}.srt").is_file() and (out / f"{name}.csv").is_file()
        assert not (out / name).exists()  # --no-images
    assert json.loads((out / "camera.json").read_text())["width"] == 320
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no temporary files left


def test_the_render_benchmark_measures_drawing_and_a_plain_warp_per_frame(coop):
    from benchmarks import load_benchmark
    from benchmarks.bench_render import _draw_and_warp_s

    assert "frames/s" in load_benchmark("render").DESCRIPTION
    data, _ = coop
    draw, warp, setup_s, fps, worlds = _draw_and_warp_s(data)
    assert len(draw) == len(warp) == 2 * FRAMES and worlds == 1 and fps == 30.0
    assert min(draw) > 0 and min(warp) > 0 and setup_s > 0
    assert np.median(draw) > np.median(warp)  # the plain warp is the floor

"""`--dem` on the commands that georeference: `uavmm boost` and `uavmm track` on a tiny dataset over a slope."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from agent.dem import write_npz
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_local, latlon_to_pixel, local_to_latlon
from shared.telemetry import Telemetry, to_seadronessee_meta
from shared.terrain import ElevationGrid, Terrain
from uavmm.cli import main

CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
LAT, LON = 47.6, 9.3
TAKEOFF_M = 300.0
PERSON_EN = (2.0, 30.0)  # metres east, north of the UAV, where the meadow has risen 6 m


def slope_grid(rise_per_m: float = 0.2) -> ElevationGrid:
    """A DEM rising northward by rise_per_m metres per metre, TAKEOFF_M under the UAV (1 m cells, +-100 m)."""
    north = np.arange(100, -101, -1, dtype=float)
    heights = TAKEOFF_M + rise_per_m * np.repeat(north[:, None], 201, axis=1)
    return ElevationGrid.from_local(heights, LAT, LON, west_m=-100.0, north_m=100.0, cell_m=1.0)


def make_dataset(tmp_path, frames=20):
    """One person standing on the slope in front of a hovering UAV: per frame a cluster of candidates whose
    bottom edge is at the person's feet (projected with the terrain)."""
    rng = np.random.default_rng(0)
    terrain = Terrain(slope_grid(), TAKEOFF_M)
    images, cands = [], []
    obj_lat, obj_lon = local_to_latlon(np.array([PERSON_EN[0]]), np.array([PERSON_EN[1]]), LAT, LON)
    pose = Pose(lat=LAT, lon=LON, height_m=25.0, pitch_deg=50.0, heading_deg=0.0)
    (u, v), = latlon_to_pixel(obj_lat, obj_lon, CAM, pose, terrain=terrain)[0]
    for k in range(frames):
        tel = Telemetry(t=1.7e9 + k / 30, lat=LAT, lon=LON, height_m=25.0, pitch_deg=50.0, heading_deg=0.0)
        meta = to_seadronessee_meta(tel)
        images.append({"id": k + 1, "file_name": f"{k:05d}.jpg", "width": 1920, "height": 1080, "video_id": 1,
                       "frame_index": k, "date_time": meta["date_time"], "meta": meta})
        for _ in range(6):
            du, dh = rng.normal(0, 1.0, 2)
            cands.append({"image_id": k + 1, "category_id": 1, "bbox": [u - 12 + du, v - 60 - dh, 24, 60 + dh],
                          "score": float(np.clip(0.8 + rng.normal(0, 0.05), 0.01, 1))})
    coco = {"images": images, "annotations": [], "categories": [{"id": 1, "name": "person"}],
            "videos": [{"id": 1, "name": "v1"}]}
    (tmp_path / "images.json").write_text(json.dumps(coco))
    (tmp_path / "pre_nms.json").write_text(json.dumps(cands))
    (tmp_path / "camera.json").write_text(json.dumps(CAM.to_dict()))
    write_npz(tmp_path / "dem.npz", slope_grid())
    write_npz(tmp_path / "flat.npz", slope_grid(0.0))
    return tmp_path, (float(obj_lat[0]), float(obj_lon[0]))


def files(d, out):
    return ["--frames", str(d / "images.json"), "--candidates", str(d / "pre_nms.json"), "--camera",
            str(d / "camera.json"), "--out", str(d / out)]


def track_position_error_m(d, truth, *extra) -> float:
    assert main(["track", *files(d, "tracks.txt"), "--geojson", str(d / "tracks.geojson"), "--anchor", "bottom",
                 "--no-clock-offset", "--no-images", *extra]) == 0
    features = json.loads((d / "tracks.geojson").read_text())["features"]
    assert features
    coords = np.array([c for f in features for c in (f["geometry"]["coordinates"] if f["geometry"]["type"] ==
                                                     "LineString" else [f["geometry"]["coordinates"]])])
    east, north = latlon_to_local(coords[:, 1], coords[:, 0], *truth)
    return float(np.median(np.hypot(east, north)))


def test_track_with_the_dem_puts_the_person_on_the_slope(tmp_path):
    d, truth = make_dataset(tmp_path)
    flat_err = track_position_error_m(d, truth)
    dem_err = track_position_error_m(d, truth, "--dem", str(d / "dem.npz"), "--takeoff-elevation-m", str(TAKEOFF_M))
    first_pose_err = track_position_error_m(d, truth, "--dem", str(d / "dem.npz"))  # take-off under the first pose
    assert flat_err > 5.0  # over flat ground the feet's ray runs on ~9.5 m past them
    assert dem_err < 0.5 and first_pose_err < 0.5


def test_boost_with_a_dem_runs_and_a_flat_dem_changes_nothing(tmp_path):
    d, _ = make_dataset(tmp_path)
    assert main(["boost", *files(d, "plain.json")]) == 0
    assert main(["boost", *files(d, "flat.json"), "--dem", str(d / "flat.npz")]) == 0
    assert main(["boost", *files(d, "dem.json"), "--dem", str(d / "dem.npz")]) == 0
    plain, flat, dem = (json.loads((d / f).read_text()) for f in ("plain.json", "flat.json", "dem.json"))
    assert dem and len(flat) == len(plain)
    assert [r["bbox"] for r in flat] == [r["bbox"] for r in plain]
    np.testing.assert_allclose([r["score"] for r in flat], [r["score"] for r in plain], atol=1e-4)


def test_dem_flags_refuse_bad_input_in_one_line(tmp_path, capsys):
    d, _ = make_dataset(tmp_path, frames=2)
    assert main(["boost", *files(d, "r.json"), "--takeoff-elevation-m", "300"]) == 2
    assert "--takeoff-elevation-m needs --dem" in capsys.readouterr().err
    assert main(["boost", *files(d, "r.json"), "--dem", str(d / "nope.tif")]) == 2
    assert "nope.tif does not exist" in capsys.readouterr().err
    (d / "bad.npz").write_bytes(b"not a zip")
    assert main(["boost", *files(d, "r.json"), "--dem", str(d / "bad.npz")]) == 2
    assert "bad.npz" in capsys.readouterr().err


def test_the_pipeline_takes_the_takeoff_elevation_from_the_first_pose_of_each_video():
    terrain = Terrain(slope_grid())
    pipe = DetectionPipeline(CAM, {1: "person"}, PipelineConfig(terrain=terrain))
    first = Pose(lat=LAT, lon=LON, height_m=25.0, pitch_deg=50.0, heading_deg=0.0)
    later_lat, _ = local_to_latlon(0.0, 20.0, LAT, LON)  # 20 m north: the ground is 4 m higher
    later = Pose(lat=float(later_lat), lon=LON, height_m=25.0, pitch_deg=50.0, heading_deg=0.0)
    assert pipe.terrain_for(first).takeoff_elevation_m == pytest.approx(TAKEOFF_M)
    assert pipe.terrain_for(later).takeoff_elevation_m == pytest.approx(TAKEOFF_M)  # still the first pose's
    pipe.reset()
    assert pipe.terrain_for(later).takeoff_elevation_m == pytest.approx(TAKEOFF_M + 4.0)
    with pytest.raises(ValueError, match="terrain"):
        PipelineConfig(terrain="dem.tif")  # type: ignore[arg-type]


def test_the_pipeline_hands_the_tracker_each_points_effective_height():
    """Over a terrain FrameResult.view_height_m carries shared.terrain.effective_height_m of the kept boxes'
    ground points; the tracker's error models take it per point (flat ground: the pose's height)."""
    from agent.tracking.association import frame_detections
    from agent.tracking.config import TrackerConfig
    from agent.tracking.model import ground_measurement_cov

    pose = Pose(lat=LAT, lon=LON, height_m=25.0, pitch_deg=50.0, heading_deg=0.0)
    boxes = np.array([[940.0, 500.0, 964.0, 560.0], [300.0, 800.0, 324.0, 860.0]], dtype=np.float32)
    args = (boxes, np.array([0.9, 0.8], np.float32), np.ones(2, np.int64), pose, 0.0)
    flat = DetectionPipeline(CAM, {1: "person"}, PipelineConfig()).process(*args)
    assert flat.view_height_m is None
    sloped = DetectionPipeline(CAM, {1: "person"}, PipelineConfig(terrain=Terrain(slope_grid(), TAKEOFF_M)))
    result = sloped.process(*args)
    assert result.view_height_m is not None and len(result.view_height_m) == len(result)
    # the camera's distance from the terrain's tangent plane: for this 20 % slope 25 m below it, 25 / sqrt(1.04)
    np.testing.assert_allclose(result.view_height_m, 25.0 / math.sqrt(1.04))
    dets = frame_detections(result, TrackerConfig())
    np.testing.assert_array_equal(dets.view_h, result.view_height_m)
    kw = {"position_sigma_m": 0.5, "heading_sigma_deg": 1.0, "pitch_sigma_deg": 1.0, "height_sigma_m": 1.0,
          "pixel_sigma_px": 2.0}
    e, n = np.array([5.0, -20.0]), np.array([30.0, 40.0])
    per_point = ground_measurement_cov(e, n, np.array([10.0, 40.0]), 1400.0, **kw)
    for k, h in enumerate((10.0, 40.0)):
        np.testing.assert_allclose(per_point[k], ground_measurement_cov(e[k:k + 1], n[k:k + 1], h, 1400.0, **kw)[0])

"""`uavmm anomaly --dem` and `uavmm agent --anomaly --dem` on a tiny synthetic images dataset over a slope (the
renderer draws flat ground only and refuses a terrain dataset, so the test paints its own frames)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from agent.dem import write_npz
from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon
from shared.telemetry import Telemetry, to_seadronessee_meta
from shared.terrain import ElevationGrid, Terrain
from uavmm.cli import build_parser, main

CAM = Camera(width=640, height=360, fx=450.0, fy=450.0, cx=320.0, cy=180.0)
LAT, LON = 47.6, 9.3
TAKEOFF_M = 300.0
SPOT_EN = (2.0, 45.0)  # metres east, north of the take-off: the meadow has risen 13.5 m there
FRAMES = 24


def slope_grid(rise_per_m: float = 0.3) -> ElevationGrid:
    """A DEM rising northward by rise_per_m metres per metre, TAKEOFF_M at the take-off (1 m cells, +-150 m)."""
    north = np.arange(150, -151, -1, dtype=float)
    heights = TAKEOFF_M + rise_per_m * np.repeat(north[:, None], 301, axis=1)
    return ElevationGrid.from_local(heights, LAT, LON, west_m=-150.0, north_m=150.0, cell_m=1.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory):
    """A UAV flying north at 9 m/s, 30 m above the take-off, over a meadow (noise) with one red object on the slope
    ahead, drawn where the terrain puts it; images.json with SeaDronesSee meta, camera.json, dem.npz. Returns the
    folder and the object's pixel box (x0, y0, x1, y1) per image id."""
    d = tmp_path_factory.mktemp("anomaly-dem")
    rng = np.random.default_rng(0)
    terrain = Terrain(slope_grid(), TAKEOFF_M)
    lat, lon = local_to_latlon(np.array([SPOT_EN[0]]), np.array([SPOT_EN[1]]), LAT, LON)
    images, boxes = [], {}
    for k in range(FRAMES):
        plat, plon = local_to_latlon(0.0, 0.3 * k, LAT, LON)
        tel = Telemetry(t=1.7e9 + k / 30, lat=float(plat), lon=float(plon), height_m=30.0, pitch_deg=35.0,
                        heading_deg=0.0)
        pose = Pose(lat=float(plat), lon=float(plon), height_m=30.0, pitch_deg=35.0, heading_deg=0.0)
        (u, v), = latlon_to_pixel(lat, lon, CAM, pose, terrain=terrain)[0]
        frame = np.clip(np.array([60, 120, 70]) + rng.normal(0, 6, (360, 640, 3)), 0, 255).astype(np.uint8)
        cv2.circle(frame, (int(round(u)), int(round(v))), 4, (30, 30, 220), -1)
        cv2.imwrite(str(d / f"{k:05d}.png"), frame)
        boxes[k + 1] = (u - 5, v - 5, u + 5, v + 5)
        meta = to_seadronessee_meta(tel)
        images.append({"id": k + 1, "file_name": f"{k:05d}.png", "width": 640, "height": 360, "video_id": 1,
                       "frame_index": k, "date_time": meta["date_time"], "meta": meta})
    coco = {"images": images, "annotations": [], "categories": [{"id": 1, "name": "person"}],
            "videos": [{"id": 1, "name": "v1"}]}
    (d / "images.json").write_text(json.dumps(coco))
    (d / "camera.json").write_text(json.dumps(CAM.to_dict()))
    write_npz(d / "dem.npz", slope_grid())
    return d, boxes


def _hits(rois: list[dict], boxes: dict[int, tuple[float, float, float, float]]) -> int:
    """Frames whose best region of interest overlaps the object."""
    best: dict[int, dict] = {}
    for r in rois:
        if r["image_id"] not in best or r["score"] > best[r["image_id"]]["score"]:
            best[r["image_id"]] = r
    hits = 0
    for image_id, r in best.items():
        x, y, w, h = r["bbox"]
        x0, y0, x1, y1 = boxes[image_id]
        hits += x < x1 and x0 < x + w and y < y1 and y0 < y + h
    return hits


def test_anomaly_with_the_dem_finds_the_object_on_the_slope(dataset, tmp_path, capsys):
    d, boxes = dataset
    base = ["anomaly", "--frames", str(d / "images.json"), "--camera", str(d / "camera.json"), "--method", "median",
            "--quiet"]
    out = tmp_path / "dem.json"
    assert main([*base, "--out", str(out), "--dem", str(d / "dem.npz")]) == 0
    printed = capsys.readouterr().out
    assert f"for {FRAMES} frames" in printed and "memory map, terrain dem.npz" in printed
    rois = json.loads(out.read_text())
    assert {r["image_id"] for r in rois} <= set(boxes)
    assert _hits(rois, boxes) >= FRAMES - 1
    # the take-off given explicitly: the same regions (the first pose is over the take-off)
    given = tmp_path / "given.json"
    assert main([*base, "--out", str(given), "--dem", str(d / "dem.npz"), "--takeoff-elevation-m",
                 str(TAKEOFF_M)]) == 0
    assert json.loads(given.read_text()) == rois


def test_anomaly_dem_flags_refuse_bad_input_in_one_line(dataset, tmp_path, capsys):
    d, _ = dataset
    base = ["anomaly", "--frames", str(d / "images.json"), "--camera", str(d / "camera.json"), "--method", "mean",
            "--out", str(tmp_path / "r.json")]
    assert main([*base, "--takeoff-elevation-m", "300"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--takeoff-elevation-m needs --dem" in err and "\n" not in err
    assert main([*base, "--dem", str(d / "nope.npz")]) == 2
    assert "nope.npz does not exist" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


def test_agent_anomaly_takes_the_pipelines_dem(dataset):
    """`uavmm agent --anomaly METHOD --dem FILE`: the anomaly layer maps onto the same terrain as the detections."""
    from uavmm.cmd_agent import anomaly_from_args, pipeline_from_args

    d, _ = dataset
    args = build_parser().parse_args(["agent", "--uav-id", "uav1", "--dataset", str(d), "--anomaly", "median",
                                      "--dem", str(d / "dem.npz"), "--takeoff-elevation-m", str(TAKEOFF_M)])
    pipeline_config, _ = pipeline_from_args(args)
    detector = anomaly_from_args(args, pipeline_config.terrain)
    assert pipeline_config.terrain is not None and detector is not None
    assert detector.config.terrain is pipeline_config.terrain
    assert detector.config.terrain.takeoff_elevation_m == TAKEOFF_M
    plain = build_parser().parse_args(["agent", "--uav-id", "uav1", "--dataset", str(d), "--anomaly", "median"])
    assert anomaly_from_args(plain, pipeline_from_args(plain)[0].terrain).config.terrain is None

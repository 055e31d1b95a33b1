"""Dataset writer: SeaDronesSee/COCO layout that pycocotools loads, determinism, clear errors, atomic writes."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
from datetime import datetime
from pathlib import Path

import pytest
from pycocotools.coco import COCO

import sim.dataset as dataset_module
from shared.geo import Camera, Pose, latlon_to_pixel
from shared.telemetry import parse_datetime
from sim.dataset import DATASET_FILES, RENDER_FILES, write_dataset
from sim.domains import DOMAINS
from sim.noise import CLOCK_FIELDS
from tests.sim.conftest import SMALL_FRAMES, load

META_FIELDS = {"gps_latitude", "gps_latitude_ref", "gps_longitude", "gps_longitude_ref", "altitude", "gimbal_pitch",
               "compass_heading", "gimbal_heading", "speed", "xspeed", "yspeed", "zspeed", "date_time"}


def test_files_are_written(sea_dir: Path) -> None:
    assert sorted(p.name for p in sea_dir.iterdir()) == sorted(DATASET_FILES)


def test_images_json_layout(sea_dir: Path) -> None:
    coco = load(sea_dir, "images.json")
    assert {"images", "annotations", "categories", "videos"} <= set(coco)
    assert coco["categories"] == [{"id": 1, "name": "person", "supercategory": "person"},
                                  {"id": 2, "name": "swimmer", "supercategory": "swimmer"}]
    assert [v["uav"] for v in coco["videos"]] == ["uav1"] * 3
    assert len(coco["images"]) == 3 * SMALL_FRAMES
    n_null = 0
    for img in coco["images"]:
        assert set(img) == {"id", "file_name", "width", "height", "video_id", "frame_index", "date_time", "meta"}
        assert isinstance(img["id"], int) and isinstance(img["frame_index"], int)
        assert (img["width"], img["height"]) == (3840, 2160)
        assert datetime.fromisoformat(img["date_time"]).tzinfo is not None
        assert len(img["date_time"].split(".")[1]) == 4  # 3 digits of milliseconds and "Z"
        meta = img["meta"]
        if meta is None:
            n_null += 1
            continue
        assert set(meta) == META_FIELDS
        assert meta["gps_latitude_ref"] == "N" and meta["gps_longitude_ref"] == "E"
        assert 47.59 < meta["gps_latitude"] < 47.61 and 9.29 < meta["gps_longitude"] < 9.31
        assert 0.0 <= meta["gimbal_pitch"] <= 90.0
        for k in ("altitude", "compass_heading", "gimbal_heading", "speed", "xspeed", "yspeed", "zspeed"):
            assert isinstance(meta[k], float)
    assert n_null >= 1  # sea drops ~1 % of the meta
    for a in coco["annotations"]:
        assert set(a) == {"id", "image_id", "category_id", "bbox", "area", "iscrowd", "track_id", "lat", "lon"}
        assert a["category_id"] == 2 and a["iscrowd"] == 0 and len(a["bbox"]) == 4
        assert a["area"] == pytest.approx(a["bbox"][2] * a["bbox"][3], abs=0.01)
        assert isinstance(a["track_id"], int)


def test_default_noise_writes_the_old_layout_and_clocks(sea_dir: Path) -> None:
    """The clock fields are off by default: SeaDronesSee meta keys, UTC stamps with milliseconds, and
    truth.json without the clock fields (so datasets written before them stay byte-identical)."""
    coco = load(sea_dir, "images.json")
    for img in coco["images"]:
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", img["date_time"])
        if img["meta"] is not None:
            assert set(img["meta"]) == META_FIELDS
            assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", img["meta"]["date_time"])
    assert len({img["meta"]["date_time"][-5:] for img in coco["images"] if img["meta"]}) > 10  # not cut to seconds
    truth = load(sea_dir, "truth.json")
    for noise in (truth["noise"], truth["scenario"]["noise_base"]):
        assert not set(CLOCK_FIELDS) & set(noise) and "gps_bias_m" in noise


def test_clock_twins_simulate_the_same_data_on_different_clocks(tmp_path: Path) -> None:
    """sea-sds-clocks and its twin: same candidates, true poses and telemetry values; only the clocks
    and the meta's names differ (frames 2 h apart in local time, log stamps cut to whole seconds)."""
    for name in ("sea-sds-clocks", "sea-sds-clocks-agree"):
        write_dataset(DOMAINS[name].scenario(), tmp_path / name, seed=3, frames=45, progress=False)
    local, agree = tmp_path / "sea-sds-clocks", tmp_path / "sea-sds-clocks-agree"
    assert (local / "pre_nms.json").read_bytes() == (agree / "pre_nms.json").read_bytes()
    t_local, t_agree = load(local, "truth.json"), load(agree, "truth.json")
    assert t_local["poses"] == t_agree["poses"] and t_local["videos"][0]["telemetry_bias"] == \
        t_agree["videos"][0]["telemetry_bias"]
    assert t_local["noise"]["frame_clock_utc_offset_s"] == 7200.0 and "meta_layout" not in t_agree["noise"]
    c_local, c_agree = load(local, "images.json"), load(agree, "images.json")
    assert c_local["annotations"] == c_agree["annotations"]
    poses = {p["image_id"]: p for p in t_local["poses"]}
    n_meta = 0
    for a, b in zip(c_local["images"], c_agree["images"], strict=True):
        assert parse_datetime(a["date_time"]) - parse_datetime(b["date_time"]) == pytest.approx(7200.0, abs=6e-4)
        assert parse_datetime(b["date_time"]) == pytest.approx(poses[a["id"]]["t"], abs=1e-3)  # truth in UTC
        assert (a["meta"] is None) == (b["meta"] is None)
        if a["meta"] is None:
            continue
        n_meta += 1
        ma, mb = a["meta"], b["meta"]
        assert ma["latitude"] == mb["gps_latitude"] and ma["longitude"] == mb["gps_longitude"]
        assert ma["gimbal_heading(degrees)"] == mb["gimbal_heading"]
        assert ma["height_above_takeoff(meter)"] == mb["altitude"]
        assert parse_datetime(ma["datetime(utc)"]) == math.floor(parse_datetime(mb["date_time"]) + 1e-6)
    assert n_meta >= 80


def test_pycocotools_loads_ground_truth_and_candidates(sea_dir: Path) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO(str(sea_dir / "images.json"))
        dt = gt.loadRes(str(sea_dir / "pre_nms.json"))
    assert len(gt.getImgIds()) == 3 * SMALL_FRAMES
    assert len(dt.getAnnIds()) == len(load(sea_dir, "pre_nms.json"))
    cands = load(sea_dir, "pre_nms.json")
    cand = cands[0]
    # COCO result fields plus, on confident candidates, the optional appearance descriptor
    assert all(set(c) - {"embedding"} == {"image_id", "category_id", "bbox", "score"} for c in cands)
    with_emb = [c for c in cands if "embedding" in c]
    assert with_emb and all(c["score"] >= 0.25 and len(c["embedding"]) == 16 for c in with_emb)
    assert all(round(x, 2) == x for x in cand["bbox"]) and round(cand["score"], 4) == cand["score"]


def test_camera_and_truth_files(sea_dir: Path) -> None:
    cam = Camera.from_file(sea_dir / "camera.json")
    assert (cam.width, cam.height) == (3840, 2160)
    truth = load(sea_dir, "truth.json")
    assert truth["seed"] == 0 and truth["frames_per_video"] == SMALL_FRAMES
    assert truth["scenario"]["name"] == "sea" and truth["noise"]["gps_bias_m"] == 1.5
    assert len(truth["poses"]) == 3 * SMALL_FRAMES
    assert {"telemetry_bias", "blurred_frames", "frames_without_meta"} <= set(truth["videos"][0])
    # annotations agree with the true pose written beside them
    coco = load(sea_dir, "images.json")
    pose_by_image = {p["image_id"]: p for p in truth["poses"]}
    for a in coco["annotations"][:200]:
        p = pose_by_image[a["image_id"]]
        pose = Pose(p["lat"], p["lon"], p["height_m"], p["pitch_deg"], p["heading_deg"])
        uv, ok = latlon_to_pixel([a["lat"]], [a["lon"]], cam, pose)
        x, y, w, h = a["bbox"]
        u, v = uv[0]
        if 0 <= u <= 3840 and 0 <= v <= 2160:
            assert x - 0.02 <= u <= x + w + 0.02 and y - 0.02 <= v <= y + h + 0.02


def test_coop_truth_records_the_occlusion(tmp_path: Path) -> None:
    summary = write_dataset("coop", tmp_path / "coop", seed=0, frames=30, progress=False)
    assert summary["videos"] == 2 and summary["images"] == 60 and summary["occluded_objects"] >= 1
    truth = load(tmp_path / "coop", "truth.json")
    occ = [o for o in truth["occlusion"] if o["track_id"] == 1]
    assert occ and occ[0]["occluded_for"] == "uav1" and occ[0]["visible_for"] == "uav2"
    hidden = [b for b in truth["occluded_boxes"] if b["track_id"] == 1]
    assert len(hidden) == 30 and {b["uav"] for b in hidden} == {"uav1"}
    coco = load(tmp_path / "coop", "images.json")
    uav1_images = {i["id"] for i in coco["images"] if i["video_id"] == 1}
    assert not any(a["track_id"] == 1 and a["image_id"] in uav1_images for a in coco["annotations"])
    assert [v["uav"] for v in coco["videos"]] == ["uav1", "uav2"]
    times = {}
    for img in coco["images"]:
        times.setdefault(img["frame_index"], set()).add(img["date_time"])
    assert all(len(t) == 1 for t in times.values())  # one clock


def test_same_seed_writes_identical_files_other_seed_differs(tmp_path: Path) -> None:
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        write_dataset("grass", tmp_path / name, seed=seed, frames=10, progress=False)
    for f in DATASET_FILES:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert (tmp_path / "a" / "pre_nms.json").read_bytes() != (tmp_path / "c" / "pre_nms.json").read_bytes()
    assert (tmp_path / "a" / "images.json").read_bytes() != (tmp_path / "c" / "images.json").read_bytes()


def test_summary_counts(tmp_path: Path) -> None:
    s = write_dataset("reid", tmp_path / "r", seed=1, frames=20, progress=False)
    coco = load(tmp_path / "r", "images.json")
    assert s["images"] == len(coco["images"]) == 40
    assert s["annotations"] == len(coco["annotations"])
    assert s["candidates"] == len(load(tmp_path / "r", "pre_nms.json"))
    assert s["scenario"] == "reid" and s["seed"] == 1


def test_existing_dataset_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "d"
    write_dataset("sea", out, seed=0, frames=5, progress=False)
    write_dataset("sea", out, seed=0, frames=7, progress=False)
    assert len(load(out, "images.json")["images"]) == 21
    assert sorted(p.name for p in out.iterdir()) == sorted(DATASET_FILES)


def test_replacing_a_dataset_removes_an_earlier_renders_marks(tmp_path: Path) -> None:
    """Probe: write_dataset over a rendered folder left render.json, the mark of a complete render, describing the
    frames of the dataset it replaced (`sim.anomaly_eval` reuses a folder with render.json without drawing it)."""
    out = tmp_path / "d"
    write_dataset("sea", out, seed=0, frames=2, progress=False)
    for name in RENDER_FILES:
        (out / name).write_text("{}")
    write_dataset("sea", out, seed=1, frames=2, progress=False)
    assert sorted(p.name for p in out.iterdir()) == sorted(DATASET_FILES)


def test_progress_bar_stays_silent_without_a_terminal(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_dataset("sea", tmp_path / "p", seed=0, frames=3, progress=True)
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"scenario": "mars"}, "unknown scenario 'mars'; valid scenarios: coop, coop-slope, grass, hills, reid, sea"),
    ({"scenario": "sea", "seed": -3}, "seed must be a non-negative integer"),
    ({"scenario": "sea", "seed": "1"}, "seed must be a non-negative integer"),
    ({"scenario": "sea", "frames": 0}, "frames must be an integer >= 1"),
])
def test_bad_input_raises_value_error_and_writes_nothing(tmp_path: Path, kwargs: dict, match: str) -> None:
    out = tmp_path / "never"
    with pytest.raises(ValueError, match=match):
        write_dataset(out_dir=out, progress=False, **kwargs)
    assert not out.exists()


def test_unwritable_output_raises_os_error_naming_the_path(tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    out = blocker / "data"
    with pytest.raises(OSError, match=f"output directory {out} is not writable"):
        write_dataset("sea", out, frames=2, progress=False)
    with pytest.raises(OSError, match=f"output directory {blocker} is not writable"):
        write_dataset("sea", blocker, frames=2, progress=False)


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_directory_raises_os_error(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OSError, match="not writable"):
            write_dataset("sea", ro / "data", frames=2, progress=False)
    finally:
        ro.chmod(0o700)


def test_a_failure_midway_leaves_no_half_dataset(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "half"
    real_dumps = json.dumps
    calls = {"n": 0}

    def failing_dumps(obj, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # after images.json and camera.json were written to the temporary folder
            raise OSError("disk full")
        return real_dumps(obj, *args, **kwargs)

    monkeypatch.setattr(dataset_module.json, "dumps", failing_dumps)
    with pytest.raises(OSError, match="disk full"):
        write_dataset("sea", out, frames=3, progress=False)
    assert not out.exists()
    # an existing dataset survives a failed rewrite untouched
    monkeypatch.setattr(dataset_module.json, "dumps", real_dumps)
    write_dataset("sea", out, frames=2, progress=False)
    before = {f: (out / f).read_bytes() for f in DATASET_FILES}
    calls["n"] = 0
    monkeypatch.setattr(dataset_module.json, "dumps", failing_dumps)
    with pytest.raises(OSError, match="disk full"):
        write_dataset("sea", out, frames=3, progress=False)
    assert sorted(p.name for p in out.iterdir()) == sorted(DATASET_FILES)
    assert {f: (out / f).read_bytes() for f in DATASET_FILES} == before


def test_a_run_stopped_between_the_moves_leaves_no_images_json(tmp_path: Path, monkeypatch) -> None:
    """images.json marks a whole dataset for its readers (`uavmm eval`'s scenario cache reuses a folder holding it):
    it is moved in last, an earlier one removed first, so a run stopped after some moves leaves none."""
    out = tmp_path / "d"
    write_dataset("grass", out, frames=SMALL_FRAMES, progress=False)
    moved: list[str] = []
    real_replace = os.replace

    def stop_after_two(src, dst):
        if len(moved) == 2:
            raise KeyboardInterrupt  # as a SIGINT between two moves
        moved.append(Path(dst).name)
        real_replace(src, dst)

    monkeypatch.setattr(dataset_module.os, "replace", stop_after_two)
    with pytest.raises(KeyboardInterrupt):
        write_dataset("sea", out, frames=SMALL_FRAMES, progress=False)
    assert "images.json" not in moved and not (out / "images.json").exists()
    monkeypatch.setattr(dataset_module.os, "replace", real_replace)
    write_dataset("sea", out, frames=SMALL_FRAMES, progress=False)
    assert (out / "images.json").exists() and json.loads((out / "truth.json").read_text())["scenario"]["name"] == "sea"

"""`uavmm detect` on a rendered MP4 with its SRT and a real ONNX model (onnxruntime): every output loads in the
tool it is meant for (pycocotools, TrackEval, GDAL for GeoJSON, an XML parser for KML, OpenCV for the MP4)
(issue 18, acceptance)."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest

from uavmm.cli import main

pytestmark = pytest.mark.e2e
FRAMES = 24


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The coop scenario's second UAV (a line flight), 640x360, rendered to MP4 + SRT; an ONNX model."""
    pytest.importorskip("onnx")
    from tests.agent.test_detector import make_constant_model

    root = tmp_path_factory.mktemp("detect")
    out = root / "coop"
    assert main(["sim", "coop", "--out", str(out), "--frames", str(FRAMES), "--image-size", "640x360", "--video",
                 "--no-images", "--max-texture-px", "1024", "--quiet"]) == 0
    coco = json.loads((out / "images.json").read_text())
    video = coco["videos"][1]
    # v8 layout (1, 4 + C, N): two confident boxes (one with a weaker duplicate for NMS) in a 640 x 640 input
    raw = np.zeros((1, 4 + 2, 100), np.float32)
    raw[0, :4, 0], raw[0, 4, 0] = [320, 320, 20, 40], 0.9
    raw[0, :4, 1], raw[0, 4, 1] = [322, 321, 20, 40], 0.5
    raw[0, :4, 2], raw[0, 5, 2] = [200, 300, 24, 24], 0.8
    model = make_constant_model(root / "model.onnx", raw, metadata={"names": str({0: "person", 1: "swimmer"})})
    return {"dir": out, "name": video["name"], "video_id": video["id"], "coco": coco, "model": model}


def _detect(flight: dict, out: Path, *extra: str) -> int:
    d = flight["dir"]
    return main(["detect", str(d / f"{flight['name']}.mp4"), "--telemetry", str(d / f"{flight['name']}.srt"),
                 "--model", str(flight["model"]), "--camera", str(d / "camera.json"), "--out", str(out),
                 "--no-size-filter", *extra])  # the model's boxes are not sized like people at this height


def _trackeval_hota(truth_rows: list[str], tracks_file: Path, root: Path, frames: int) -> float:
    """HOTA of a MOTChallenge file read by TrackEval's own MOTChallenge loader."""
    trackeval = pytest.importorskip("trackeval")
    seq = "flight"
    gt_dir = root / "gt" / seq / "gt"
    gt_dir.mkdir(parents=True)
    (gt_dir / "gt.txt").write_text("".join(r + "\n" for r in truth_rows))
    (root / "gt" / seq / "seqinfo.ini").write_text(f"[Sequence]\nname={seq}\nseqLength={frames}\n")
    tr_dir = root / "trackers" / "uavmm" / "data"
    tr_dir.mkdir(parents=True)
    (tr_dir / f"{seq}.txt").write_text(tracks_file.read_text())
    config = {**trackeval.datasets.MotChallenge2DBox.get_default_dataset_config(),
              "GT_FOLDER": str(root / "gt"), "TRACKERS_FOLDER": str(root / "trackers"), "SKIP_SPLIT_FOL": True,
              "SEQ_INFO": {seq: frames}, "TRACKERS_TO_EVAL": ["uavmm"], "PRINT_CONFIG": False}
    evaluator = trackeval.Evaluator({**trackeval.Evaluator.get_default_eval_config(), "PRINT_RESULTS": False,
                                     "PRINT_CONFIG": False, "OUTPUT_SUMMARY": False, "OUTPUT_DETAILED": False,
                                     "PLOT_CURVES": False, "USE_PARALLEL": False, "TIME_PROGRESS": False})
    results, messages = evaluator.evaluate([trackeval.datasets.MotChallenge2DBox(config)],
                                           [trackeval.metrics.HOTA()])
    assert messages["MotChallenge2DBox"]["uavmm"] == "Success"
    return float(np.mean(results["MotChallenge2DBox"]["uavmm"][seq]["pedestrian"]["HOTA"]["HOTA"]))


def test_detect_writes_outputs_that_standard_tools_read(flight, tmp_path):
    out = tmp_path / "out" / "nested"  # created with its parents
    assert _detect(flight, out, "--render-video", "--quiet") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == FRAMES and summary["frames_without_pose"] == 0
    assert summary["detections"] == 2 * FRAMES  # the duplicate is suppressed, the two objects kept
    assert summary["tracks"] == 2

    # COCO: the results load against images.json in pycocotools and refer to its images
    from pycocotools.coco import COCO

    images = json.loads((out / "images.json").read_text())
    assert [im["frame_index"] for im in images["images"]] == list(range(FRAMES))
    assert all(im["meta"]["gps_latitude"] > 0 and im["meta"]["gimbal_pitch"] > 0 for im in images["images"])
    assert {c["name"] for c in images["categories"]} == {"person", "swimmer"}
    gt = COCO(str(out / "images.json"))
    dt = gt.loadRes(str(out / "detections.json"))
    assert len(dt.getAnnIds()) == 2 * FRAMES and set(dt.getImgIds()) == set(range(FRAMES))
    # the frames' meta is the SRT's telemetry (the sim's own meta for the same frames)
    truth = [im for im in flight["coco"]["images"] if im["video_id"] == flight["video_id"]]
    for ours, theirs in zip(images["images"], truth, strict=True):
        assert ours["meta"]["gps_latitude"] == pytest.approx(theirs["meta"]["gps_latitude"], abs=2e-5)
        assert ours["meta"]["altitude"] == pytest.approx(theirs["meta"]["altitude"], abs=0.2)

    # MOT: TrackEval's MOTChallenge loader reads it (ground truth: the simulator's annotations of this video)
    ids = {im["id"]: im["frame_index"] for im in truth}
    truth_rows = [f"{ids[a['image_id']] + 1},{a['track_id']},{','.join(f'{v:.2f}' for v in a['bbox'])},1,1,1"
                  for a in flight["coco"]["annotations"] if a["image_id"] in ids]
    hota = _trackeval_hota(truth_rows, out / "tracks.txt", tmp_path / "trackeval", FRAMES)
    assert 0.0 <= hota < 0.5  # a constant-output model does not find the people: scored, and low

    # GeoJSON: GDAL reads both layers; tracks are LineStrings in lon, lat order near the flight
    pyogrio = pytest.importorskip("pyogrio")
    lat0, lon0 = truth[0]["meta"]["gps_latitude"], truth[0]["meta"]["gps_longitude"]
    for name, kind in (("tracks.geojson", "LineString"), ("objects.geojson", "Point")):
        info = pyogrio.read_info(out / name)
        assert info["features"] == 2 and info["geometry_type"] == kind
        for feature in json.loads((out / name).read_text())["features"]:
            coords = np.array(feature["geometry"]["coordinates"]).reshape(-1, 2)
            assert np.allclose(coords[:, 0], lon0, atol=0.01) and np.allclose(coords[:, 1], lat0, atol=0.01)
            assert feature["properties"]["cls"] in {"person", "swimmer"}
            if name == "objects.geojson":  # UTC said, or a map reads it as its own local time
                props = feature["properties"]
                assert props["first_seen"].endswith("Z") and props["last_seen"].endswith("Z")
                last = datetime.fromisoformat(props["last_seen"][:-1]).replace(tzinfo=timezone.utc)  # 3.10: no "Z"
                assert last.timestamp() == pytest.approx(props["t"], abs=1e-3)

    # KML: parses, one Placemark per object and per track
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    root = ET.parse(out / "tracks.kml").getroot()
    folders = {f.findtext("k:name", namespaces=ns): f for f in root.iter("{http://www.opengis.net/kml/2.2}Folder")}
    assert set(folders) == {"objects", "tracks"}
    assert len(folders["tracks"].findall("k:Placemark/k:LineString", ns)) == 2
    assert len(folders["objects"].findall("k:Placemark/k:Point", ns)) == 2

    # MP4: OpenCV decodes every frame at the video's size
    capture = cv2.VideoCapture(str(out / "annotated.mp4"))
    decoded = 0
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        assert frame.shape == (360, 640, 3)
        decoded += 1
    capture.release()
    assert decoded == FRAMES
    assert not list(out.glob(".*tmp*"))  # no temporary files left


def test_detect_sliced_finds_the_model_box_in_each_tile(flight, tmp_path):
    assert _detect(flight, tmp_path, "--slices", "2x2", "--no-full-frame", "--max-frames", "5", "--quiet") == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 5
    # each tile's letterboxed input holds the model's two boxes, which land in the tile's own core
    assert summary["detections"] == 4 * 2 * 5


@pytest.mark.parametrize(("extra", "message"), [
    (("--providers", "NoSuchExecutionProvider"), "NoSuchExecutionProvider not available in this install; available:"),
    (("--slices", "2by2"), "--slices must look like 2x2"),
    (("--slice-overlap", "0.3"), "--slice-overlap and --no-full-frame need --slices"),
    (("--mavlink-system-id", "2"), "--mavlink-system-id applies to a MAVLink .tlog or a udp:HOST:PORT stream"),
])
def test_detect_refuses_bad_flags_in_one_line(flight, tmp_path, capsys, extra, message):
    assert _detect(flight, tmp_path / "o", *extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith("uavmm detect: error:")


def test_detect_refuses_an_out_that_is_a_file(flight, tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("")
    assert _detect(flight, blocker) == 2
    assert "exists and is not a directory" in capsys.readouterr().err


def test_detect_fits_a_camera_of_another_resolution_and_says_so(flight, tmp_path, caplog):
    camera = json.loads((flight["dir"] / "camera.json").read_text())
    double = {**camera, **{k: 2 * camera[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}}
    (tmp_path / "cam.json").write_text(json.dumps(double))
    d = flight["dir"]
    with caplog.at_level("WARNING", logger="agent.sources"):
        assert main(["detect", str(d / f"{flight['name']}.mp4"), "--telemetry", str(d / f"{flight['name']}.srt"),
                     "--model", str(flight["model"]), "--camera", str(tmp_path / "cam.json"), "--out",
                     str(tmp_path / "o"), "--no-size-filter", "--max-frames", "3", "--quiet"]) == 0
    assert any("is 1280x720 but the frames of" in r.getMessage() and "640x360" in r.getMessage()
               for r in caplog.records)
    # the same georeferencing as with the matching camera file
    assert main(["detect", str(d / f"{flight['name']}.mp4"), "--telemetry", str(d / f"{flight['name']}.srt"),
                 "--model", str(flight["model"]), "--camera", str(d / "camera.json"), "--out", str(tmp_path / "p"),
                 "--no-size-filter", "--max-frames", "3", "--quiet"]) == 0
    fitted = json.loads((tmp_path / "o" / "objects.geojson").read_text())["features"]
    matching = json.loads((tmp_path / "p" / "objects.geojson").read_text())["features"]
    assert np.allclose([f["geometry"]["coordinates"] for f in fitted],
                       [f["geometry"]["coordinates"] for f in matching], atol=1e-7)


def test_detect_refuses_a_model_with_nms_inside_in_one_line(flight, tmp_path, capsys):
    from tests.agent.test_detector import make_constant_model

    kept = np.zeros((1, 300, 6), np.float32)  # YOLO26's default export of a one-class model
    model = make_constant_model(tmp_path / "yolo26n.onnx", kept, metadata={"names": str({0: "person"}),
                                                                          "end2end": "True"})
    d = flight["dir"]
    assert main(["detect", str(d / f"{flight['name']}.mp4"), "--telemetry", str(d / f"{flight['name']}.srt"),
                 "--model", str(model), "--camera", str(d / "camera.json"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "yolo26n.onnx is an end-to-end export" in err[0] and "nms=False end2end=False" in err[0]
    assert not list((tmp_path / "o").glob("*"))  # nothing written


def test_detect_refuses_to_write_its_annotated_video_over_the_video_it_reads(flight, tmp_path, capsys):
    """Probe: `uavmm detect run/annotated.mp4 --out run --render-video` (a second pass over the first's video) wrote
    the new annotated video over the one it read (exit 0). Refused in one line naming both, before any work."""
    d = flight["dir"]
    run = tmp_path / "run"
    run.mkdir()
    video = run / "annotated.mp4"
    video.write_bytes((d / f"{flight['name']}.mp4").read_bytes())
    before = video.read_bytes()
    assert main(["detect", str(video), "--telemetry", str(d / f"{flight['name']}.srt"), "--model",
                 str(flight["model"]), "--camera", str(d / "camera.json"), "--out", str(run), "--no-size-filter",
                 "--render-video", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--out {video} is the VIDEO input {video}" in err[0]
    assert video.read_bytes() == before and sorted(p.name for p in run.iterdir()) == ["annotated.mp4"]
    assert _detect(flight, run, "--quiet") == 0  # without --render-video it writes no annotated.mp4: allowed
    assert video.read_bytes() == before and (run / "detections.json").is_file()

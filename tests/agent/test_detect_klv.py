"""`uavmm detect FLIGHT.ts --telemetry klv` end to end (issue 32): a transport stream written by FFmpeg's muxer
(PyAV) with MISB ST 0601 KLV beside the video, a real ONNX model run by onnxruntime, the memory map and the GPS
tracker; packets with a broken checksum are counted and skipped, never a crash."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from uavmm.cli import main

FRAMES = 30
T0 = 1_717_236_000.0


def _flight(tmp_path, broken: tuple[int, ...] = ()):
    pytest.importorskip("av")
    pytest.importorskip("onnx")
    from tests.agent.test_detector import make_constant_model
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    klv = []
    for i in range(FRAMES):
        p = bytearray(packet(T0 + 0.1 * i, {**FULL_FIELDS, "sensor_lat": 48.53 + 1e-6 * i}))
        if i in broken:
            p[-5] ^= 0xFF  # a value byte: the packet's checksum no longer holds
        klv.append(bytes(p))
    video = write_ts_with_pyav(tmp_path / "flight.ts", klv, fps=10, size=(320, 180))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    # v8 layout (1, 4 + C, N): one confident person box in the middle of the 640 x 640 input
    raw = np.zeros((1, 4 + 2, 100), np.float32)
    raw[0, :4, 0], raw[0, 4, 0] = [320, 320, 20, 40], 0.9
    model = make_constant_model(tmp_path / "model.onnx", raw, metadata={"names": str({0: "person", 1: "swimmer"})})
    return video, camera, model


def _detect(video, camera, model, out) -> int:
    return main(["detect", str(video), "--telemetry", "klv", "--model", str(model), "--camera", str(camera),
                 "--out", str(out), "--no-size-filter", "--quiet"])  # the model's box is not sized like a person


def test_detect_georeferences_and_tracks_a_transport_stream_by_its_klv(tmp_path):
    video, camera, model = _flight(tmp_path)
    out = tmp_path / "out"
    assert _detect(video, camera, model, out) == 0
    images = json.loads((out / "images.json").read_text())["images"]
    assert len(images) == FRAMES
    metas = [im.get("meta") or {} for im in images]
    assert all(m.get("gps_latitude") is not None for m in metas)  # every frame has the KLV's pose
    # frame i shows sample i (the KLV packets carry the frames' PTS): the sensor latitude steps by 1e-6 a frame
    assert [m["gps_latitude"] for m in metas[5:8]] == pytest.approx([48.53 + 1e-6 * i for i in (5, 6, 7)], abs=2e-7)
    # platform heading 350 + relative azimuth 20, sensor elevation -45: heading 10, pitch 45; height above the
    # frame centre's ground: 512 - 472 m (docs/agent.md, KLV metadata in the video)
    assert (metas[5]["gimbal_heading"], metas[5]["gimbal_pitch"], metas[5]["altitude"]) == pytest.approx(
        (10.0, 45.0, 40.0), abs=0.1)
    detections = json.loads((out / "detections.json").read_text())
    assert {d["image_id"] for d in detections} == {im["id"] for im in images}
    rows = [r.split(",") for r in (out / "tracks.txt").read_text().splitlines()]
    assert rows and len({r[1] for r in rows}) == 1  # one object, one track id
    track = json.loads((out / "tracks.geojson").read_text())["features"][0]["geometry"]
    assert track["type"] == "LineString"
    lon, lat = track["coordinates"][-1][:2]
    # the box in the image centre lies ~40 m ahead of the sensor (40 m up, 45 deg down), bearing 10 deg
    north, east = (lat - 48.53) * 111_320.0, (lon - 9.06) * 111_320.0 * np.cos(np.radians(48.53))
    assert 30.0 < np.hypot(east, north) < 50.0
    assert np.degrees(np.arctan2(east, north)) == pytest.approx(10.0, abs=2.0)


def test_detect_skips_klv_packets_whose_checksum_fails_and_says_so(tmp_path, caplog):
    video, camera, model = _flight(tmp_path, broken=(7, 19))
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING):
        assert _detect(video, camera, model, out) == 0
    assert any("checksum" in r.getMessage() and "2" in r.getMessage() for r in caplog.records)
    images = json.loads((out / "images.json").read_text())["images"]
    assert len(images) == FRAMES
    # the frames of the skipped packets take the poses between their neighbours' samples
    lat = [(im.get("meta") or {}).get("gps_latitude") for im in images]
    assert lat[7] == pytest.approx(48.53 + 7e-6, abs=2e-7) and lat[19] == pytest.approx(48.53 + 19e-6, abs=2e-7)


def test_detect_follows_a_zoom_lens_by_the_klv_field_of_view(tmp_path):
    """The gimbal zooms from 30 to 15 deg during the clip while the camera file's lens has 65.2: a box 80 px right
    of the image centre lies 10.7 deg right of the camera's heading at 30 deg and 5.3 at 15 deg (24.3 with the
    camera file's focal length). The track follows the zoom's bearing, frame by frame."""
    pytest.importorskip("av")
    pytest.importorskip("onnx")
    from shared.geo import Camera, Pose, pixel_to_local
    from tests.agent.test_detector import make_constant_model
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    hfovs = [30.0 - 15.0 * i / (FRAMES - 1) for i in range(FRAMES)]
    klv = [packet(T0 + 0.1 * i, {**FULL_FIELDS, "hfov_deg": h}) for i, h in enumerate(hfovs)]
    video = write_ts_with_pyav(tmp_path / "flight.ts", klv, fps=10, size=(320, 180))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    raw = np.zeros((1, 4 + 2, 100), np.float32)  # x 480 of the 640 input: x 240 of the 320 frame, 80 px right
    raw[0, :4, 0], raw[0, 4, 0] = [480, 320, 20, 40], 0.9
    model = make_constant_model(tmp_path / "model.onnx", raw, metadata={"names": str({0: "person", 1: "swimmer"})})
    out = tmp_path / "out"
    assert _detect(video, camera, model, out) == 0
    features = json.loads((out / "tracks.geojson").read_text())["features"]
    assert len(features) == 1  # one object, one track, though its ground point moves 4 m with the zoom
    coords = features[0]["geometry"]["coordinates"]

    def bearing(lon: float, lat: float) -> float:
        north, east = (lat - 48.53) * 111_320.0, (lon - 9.06) * 111_320.0 * np.cos(np.radians(48.53))
        return float(np.degrees(np.arctan2(east, north)))

    pose = Pose(lat=48.53, lon=9.06, height_m=40.0, pitch_deg=45.0, heading_deg=10.0)
    base = Camera(width=320, height=180, fx=250.0, fy=250.0, cx=160.0, cy=90.0)

    def expected(hfov: float) -> float:
        east, north, _ = pixel_to_local(np.array([[240.0, 100.0]]), base.with_hfov(hfov), pose)
        return float(np.degrees(np.arctan2(east[0], north[0])))

    assert expected(30.0) == pytest.approx(20.7, abs=0.3) and expected(15.0) == pytest.approx(15.3, abs=0.3)
    assert bearing(*coords[-1][:2]) == pytest.approx(expected(hfovs[-1]), abs=1.0)
    assert bearing(*coords[0][:2]) == pytest.approx(expected(hfovs[0]), abs=1.0)
    # the frames' fields of view are in detect's images.json (meta hfov_deg), so `uavmm track` on its outputs with
    # the same camera file puts the track where detect did
    metas = [im["meta"] for im in json.loads((out / "images.json").read_text())["images"]]
    assert [m["hfov_deg"] for m in metas] == pytest.approx(hfovs, abs=0.01)
    again = tmp_path / "again.geojson"
    assert main(["track", "--frames", str(out / "images.json"), "--candidates", str(out / "detections.json"),
                 "--camera", str(camera), "--out", str(tmp_path / "again.txt"), "--geojson", str(again),
                 "--no-size-filter", "--log-level", "ERROR"]) == 0
    redone = json.loads(again.read_text())["features"]
    assert len(redone) == 1
    assert bearing(*redone[0]["geometry"]["coordinates"][-1][:2]) == pytest.approx(expected(hfovs[-1]), abs=1.0)


def test_every_frame_of_a_zooming_flight_carries_its_field_of_view(tmp_path):
    """Frames at the camera file's own field of view were written without hfov_deg; read back as telemetry, they
    took their zoomed neighbours' (a frame at 65.2 deg read as 30)."""
    pytest.importorskip("av")
    pytest.importorskip("onnx")
    from shared.telemetry import read_telemetry
    from tests.agent.test_detector import make_constant_model
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    wide = 65.24  # the camera file's (fx 250 at 320 px)
    hfovs = [wide] * 10 + [wide - (wide - 30.0) * (i + 1) / (FRAMES - 10) for i in range(FRAMES - 10)]
    klv = [packet(T0 + 0.1 * i, {**FULL_FIELDS, "hfov_deg": h}) for i, h in enumerate(hfovs)]
    video = write_ts_with_pyav(tmp_path / "flight.ts", klv, fps=10, size=(320, 180))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    raw = np.zeros((1, 4 + 2, 100), np.float32)
    raw[0, :4, 0], raw[0, 4, 0] = [480, 320, 20, 40], 0.9
    model = make_constant_model(tmp_path / "model.onnx", raw, metadata={"names": str({0: "person", 1: "swimmer"})})
    out = tmp_path / "out"
    assert _detect(video, camera, model, out) == 0
    metas = [im["meta"] for im in json.loads((out / "images.json").read_text())["images"]]
    assert [m["hfov_deg"] for m in metas] == pytest.approx(hfovs, abs=0.01)
    back = read_telemetry(out / "images.json")
    assert [r.hfov_deg for r in back] == pytest.approx(hfovs, abs=0.01)

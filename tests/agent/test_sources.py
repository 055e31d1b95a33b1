"""Frame sources of the agent: dataset directories, video + telemetry + ONNX model, and their errors for
missing files and unknown names (the simulated source: tests/sim/test_source.py)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from agent.dataset_source import DatasetSource
from agent.sources import SourceFrame, VideoSource, pose_from_meta
from shared.geo import Camera
from sim.dataset import write_dataset
from sim.source import SimSource

FRAMES = 30


def check_source_frames(frames: list[SourceFrame], class_ids: set[int]) -> None:
    times = [f.t for f in frames]
    assert times == sorted(times)
    assert [f.index for f in frames] == list(range(len(frames)))
    for f in frames:
        assert f.boxes_xyxy.dtype == np.float32 and f.boxes_xyxy.shape == (len(f.scores), 4)
        assert f.scores.dtype == np.float32 and f.class_ids.dtype == np.int64
        assert np.all(f.boxes_xyxy[:, 2] > f.boxes_xyxy[:, 0]) and np.all(f.boxes_xyxy[:, 3] > f.boxes_xyxy[:, 1])
        assert set(np.unique(f.class_ids).tolist()) <= class_ids
        assert np.all((f.scores >= 0) & (f.scores <= 1))


@pytest.fixture(scope="module")
def coop_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("coop") / "data"
    write_dataset("coop", out, seed=1, frames=FRAMES, progress=False)
    return out


def test_dataset_source_plays_a_video_of_the_directory(coop_dir):
    source = DatasetSource(coop_dir, video_id=2)
    frames = list(source.frames())
    assert len(frames) == FRAMES
    check_source_frames(frames, set(source.class_names))
    assert source.camera == Camera.from_file(coop_dir / "camera.json")
    # the same candidates the simulator produced for that UAV
    sim_frames = list(SimSource("coop", seed=1, uav_index=1, frames=FRAMES).frames())
    for a, b in zip(frames, sim_frames, strict=True):
        np.testing.assert_allclose(a.boxes_xyxy, b.boxes_xyxy, atol=0.01)
        np.testing.assert_allclose(a.scores, b.scores, atol=1e-4)  # rounded in the file
        assert a.t == pytest.approx(b.t, abs=1e-3)
    assert DatasetSource(coop_dir).video_id == 1


def test_dataset_source_errors(coop_dir, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        DatasetSource(tmp_path / "missing")
    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "images.json").write_text((coop_dir / "images.json").read_text())
    with pytest.raises(ValueError, match="expected pre_nms.json or one detections"):
        DatasetSource(partial)
    (partial / "pre_nms.json").write_text((coop_dir / "pre_nms.json").read_text())
    with pytest.raises(ValueError, match="no camera.json"):
        DatasetSource(partial)
    # a real file as users have it: instances*.json, detections*.json and a camera preset
    real = tmp_path / "real"
    real.mkdir()
    (real / "instances_val.json").write_text((coop_dir / "images.json").read_text())
    (real / "detections_val.json").write_text((coop_dir / "pre_nms.json").read_text())
    source = DatasetSource(real, camera="dji-mavic2-pro")
    assert source.camera.preset == "dji-mavic2-pro" and len(list(source.frames())) > 0
    (real / "detections_other.json").write_text("[]")
    with pytest.raises(ValueError, match="detections_other.json, detections_val.json"):
        DatasetSource(real, camera="dji-mavic2-pro")
    with pytest.raises(ValueError, match=r"unknown video '9'; known ids: \[1, 2\]; names: "):
        DatasetSource(coop_dir, video_id=9)
    # by name, as `uavmm agent --video-id NAME` gives it
    names = {v["id"]: v["name"] for v in json.loads((coop_dir / "images.json").read_text())["videos"]}
    assert DatasetSource(coop_dir, video_id=names[2]).video_id == 2
    assert DatasetSource(coop_dir, video_id="2").video_id == 2


def test_pose_from_meta_reports_unusable_meta_instead_of_raising():
    assert pose_from_meta(None) == (None, None, None)
    pose, t, problem = pose_from_meta({"gps_latitude": 48.5, "gps_latitude_ref": "N"})
    assert pose is None and t is None and "gps_longitude" in problem


# ---- video + telemetry + ONNX model ----------------------------------------------------------------
def _write_video(path: Path, frames: int, size: tuple[int, int] = (320, 180), fps: float = 10.0) -> Path:
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for i in range(frames):
        image = np.full((size[1], size[0], 3), 40 + i, np.uint8)
        writer.write(image)
    writer.release()
    return path


def _write_model(path: Path) -> Path:
    pytest.importorskip("onnx")
    from tests.agent.test_detector import make_constant_model

    # v8 layout (1, 4 + C, N): one confident person box in the middle of a 640 x 640 input
    raw = np.zeros((1, 4 + 2, 100), np.float32)
    raw[0, :4, 0] = [320, 320, 60, 120]  # cx, cy, w, h
    raw[0, 4, 0] = 0.9
    return make_constant_model(path, raw, metadata={"names": str({0: "person", 1: "swimmer"})})


def test_video_source_detects_and_interpolates_telemetry(tmp_path):
    video = _write_video(tmp_path / "flight.avi", 12)
    telemetry = tmp_path / "flight.csv"
    rows = ["time_s,lat,lon,height_m,pitch_deg,heading_deg"]
    rows += [f"{100 + 0.5 * i},{48.53 + 1e-5 * i},9.06,30,90,{10 * i}" for i in range(4)]  # 0..1.5 s
    telemetry.write_text("\n".join(rows) + "\n")
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 640, "height": 360, "fx": 500.0}))
    source = VideoSource(video, telemetry, _write_model(tmp_path / "model.onnx"), camera, max_gap_s=0.2)
    assert source.class_names == {0: "person", 1: "swimmer"}
    assert (source.camera.width, source.camera.height, source.camera.fx) == (320, 180, 250.0)  # rescaled
    frames = list(source.frames())
    assert len(frames) == 12
    check_source_frames(frames, {0, 1})
    assert [f.t for f in frames] == pytest.approx([100 + i / 10 for i in range(12)])
    # 100.0 .. 101.5 s of telemetry, 0.2 s held beyond: frames at 101.8+ s have none
    assert [f.pose is not None for f in frames] == [f.t <= 101.7 + 1e-9 for f in frames]
    assert frames[5].pose.lat == pytest.approx(48.53 + 1e-5)  # t = 100.5 s: the second record
    assert frames[5].pose.heading_deg == pytest.approx(10.0)
    assert frames[2].pose_t == pytest.approx(100.2)
    assert all(len(f.scores) >= 1 and f.class_ids[0] == 0 for f in frames)
    # the box is in original-image pixels (letterbox undone)
    x1, y1, x2, y2 = frames[0].boxes_xyxy[0]
    assert (x1 + x2) / 2 == pytest.approx(160, abs=1) and (y1 + y2) / 2 == pytest.approx(90, abs=1)


def test_video_source_reads_the_vehicle_given_of_a_tlog_with_several(tmp_path, caplog):
    """QGroundControl logs every vehicle on its links in one .tlog: by default the one with the most positions
    is read (a warning names them all), --mavlink-system-id reads another; on other telemetry it is refused."""
    pytest.importorskip("pymavlink")
    from shared.telemetry import Telemetry
    from tests.shared.mavlink_writer import flight_packets, write_tlog

    t0 = 1_700_000_000.0
    ours = [Telemetry(t=t0 + 0.2 * i, lat=48.53 + 1e-5 * i, lon=9.06, height_m=30.0, pitch_deg=60.0,
                      heading_deg=10.0) for i in range(30)]
    other = [Telemetry(t=t0 + 0.2 * i, lat=48.55, lon=9.08 + 1e-5 * i, height_m=50.0, pitch_deg=45.0,
                       heading_deg=200.0) for i in range(20)]
    tlog = write_tlog(tmp_path / "qgc.tlog", sorted(flight_packets(ours) + flight_packets(other, system_id=2),
                                                    key=lambda tp: tp[0]))
    video = _write_video(tmp_path / "flight.avi", 12)
    model, camera = _write_model(tmp_path / "model.onnx"), "dji-mavic2-pro"
    with caplog.at_level(logging.WARNING):
        first = next(VideoSource(video, tlog, model, camera).frames())
    assert first.pose is not None and first.pose.lat == pytest.approx(48.53, abs=1e-6)
    assert "system 1 (30 positions)" in caplog.text and "system 2 (20 positions)" in caplog.text
    chosen = next(VideoSource(video, tlog, model, camera, system_id=2).frames())
    assert chosen.pose is not None and chosen.pose.lat == pytest.approx(48.55, abs=1e-6)
    assert chosen.pose.heading_deg == pytest.approx(200.0, abs=0.1)
    srt = tmp_path / "f.srt"
    srt.write_text("1\n00:00:00,000 --> 00:00:00,033\n2023-06-01 10:00:00.000\n[latitude: 48.53] "
                   "[longitude: 9.06] [rel_alt: 30.0 abs_alt: 400.0] [gb_yaw: 0.0 gb_pitch: -60.0 gb_roll: 0.0]\n")
    with pytest.raises(ValueError, match="--mavlink-system-id applies to a MAVLink .tlog"):
        VideoSource(video, srt, model, camera, system_id=2)


def _with_fov(packets, hfovs):
    """The packets with a CAMERA_FOV_STATUS (camera component 100) before each position, its hfov from hfovs."""
    from pymavlink.dialects.v20 import ardupilotmega

    camera = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=100)
    decoder = ardupilotmega.MAVLink(None)
    out, k = [], 0
    for t, p in packets:
        if decoder.decode(bytearray(p)).get_type() == "GLOBAL_POSITION_INT":
            fov = camera.camera_fov_status_encode(0, 0, 0, 0, 0, 0, 0, [1, 0, 0, 0], hfovs[k], hfovs[k] * 0.56)
            out.append((t, fov.pack(camera)))
            k += 1
        out.append((t, p))
    return out


@pytest.mark.parametrize("live", [False, True])
def test_a_mavlink_camera_that_zooms_gives_each_frame_its_field_of_view(tmp_path, caplog, live):
    """A gimbal camera zooming from 60 to 30 deg (CAMERA_FOV_STATUS): from a .tlog, and on a live link once the
    field of view has changed, each frame's camera has the field of view of its time; one warning says so."""
    pytest.importorskip("pymavlink")
    import threading

    from shared.telemetry import Telemetry
    from tests.netutil import free_udp_port
    from tests.shared.mavlink_writer import flight_packets, replay_udp, write_tlog

    t0 = 1_700_000_000.0
    flight = [Telemetry(t=t0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06, height_m=30.0, pitch_deg=60.0,
                        heading_deg=10.0) for i in range(14)]
    hfovs = [60.0 - 2.5 * i for i in range(14)]
    packets = _with_fov(flight_packets(flight), hfovs)
    video = _write_video(tmp_path / "flight.avi", 12)
    model, camera = _write_model(tmp_path / "model.onnx"), "dji-mavic2-pro"
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        if live:
            port = free_udp_port()
            thread = threading.Thread(target=replay_udp, args=(packets, port), kwargs={"rounds": 1}, daemon=True)
            thread.start()
            source = VideoSource(video, f"udp:127.0.0.1:{port}", model, camera, telemetry_offset_s=t0)
            thread.join(timeout=10.0)
        else:
            source = VideoSource(video, write_tlog(tmp_path / "zoom.tlog", packets), model, camera)
        try:
            frames = list(source.frames())
        finally:
            source.close()
    assert len(frames) == 12 and all(f.pose is not None for f in frames)
    said = [r.getMessage() for r in caplog.records if "field of view" in r.getMessage()]
    assert len(said) == 1 and "a zoom lens" in said[0]
    # frame i is at t0 + 0.1 i: the field of view of record i; the camera's principal point stays
    assert [round(f.camera.hfov_deg, 2) for f in frames[-4:]] == pytest.approx(hfovs[8:12], abs=0.01)
    assert all(f.camera.cx == frames[0].camera.cx for f in frames)


def test_an_srts_digital_zoom_that_changes_narrows_each_frames_camera(tmp_path):
    """A Mini 3's dzoom_ratio going from 1x to 2x mid-clip: each frame's focal length follows it (before, only a
    warning: a box off the image centre was put twice as far from the centre's ground point in the zoomed frames)."""
    video = _write_video(tmp_path / "flight.avi", 12)
    srt = tmp_path / "flight.srt"
    ratios = [10000] * 5 + [20000] * 5
    blocks = [f"{i + 1}\n00:00:00,{100 * i:03d} --> 00:00:00,{100 * i + 100:03d}\n2023-06-01 12:00:00.{100 * i:03d}\n"
              f"[focal_len : 240] [dzoom_ratio: {z}, delta:0],[latitude: {48.53 + 1e-5 * i:.6f}] [longitude: 9.06] "
              f"[rel_alt: 30.0 abs_alt: 400.0] [gb_yaw: 10.0 gb_pitch: -60.0 gb_roll: 0.0]\n\n"
              for i, z in enumerate(ratios)]
    srt.write_text("".join(blocks))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    frames = list(VideoSource(video, srt, _write_model(tmp_path / "model.onnx"), camera).frames())
    assert frames[0].camera.fx == pytest.approx(250.0, rel=1e-4)
    assert [f.camera.fx for f in frames[6:10]] == pytest.approx([500.0] * 4, rel=1e-4)
    assert all((f.camera.cx, f.camera.cy) == (160.0, 90.0) for f in frames)


def test_an_srts_local_dates_are_put_on_utc_with_the_offset_given(tmp_path):
    """DJI writes the drone's local time: --telemetry-utc-offset-h 2 (CEST) moves every frame's time 2 h back to
    UTC (a UNIX --telemetry-offset-s, and another UAV's UTC log, then meet it) and leaves the poses as they were."""
    video = _write_video(tmp_path / "flight.avi", 12)
    srt = tmp_path / "flight.srt"
    blocks = [f"{i + 1}\n00:00:00,{100 * i:03d} --> 00:00:00,{100 * i + 100:03d}\n2023-06-01 12:00:00.{100 * i:03d}\n"
              f"[latitude: {48.53 + 1e-5 * i:.6f}] [longitude: 9.06] [rel_alt: 30.0 abs_alt: 400.0] "
              f"[gb_yaw: 10.0 gb_pitch: -60.0 gb_roll: 0.0]\n\n" for i in range(10)]
    srt.write_text("".join(blocks))
    model = _write_model(tmp_path / "model.onnx")
    local = list(VideoSource(video, srt, model, "dji-mavic2-pro").frames())
    utc = list(VideoSource(video, srt, model, "dji-mavic2-pro", utc_offset_h=2.0).frames())
    assert local[0].t == pytest.approx(1685620800.0)  # 2023-06-01 12:00:00 read as UTC
    assert [b.t for b in utc] == pytest.approx([a.t - 7200.0 for a in local])
    assert [b.pose for b in utc] == [a.pose for a in local]
    csv = tmp_path / "flight.csv"
    csv.write_text("time_s,lat,lon,height_m,pitch_deg,heading_deg\n0,48.53,9.06,30,60,10\n1,48.53,9.06,30,60,10\n")
    with pytest.raises(ValueError, match="--telemetry-utc-offset-h applies to a DJI .srt"):
        VideoSource(video, csv, model, "dji-mavic2-pro", utc_offset_h=2.0)
    with pytest.raises(ValueError, match="must be hours within -14 .. 14"):
        VideoSource(video, srt, model, "dji-mavic2-pro", utc_offset_h=20.0)


def test_video_source_makes_a_preset_at_the_videos_size_without_a_warning(tmp_path, caplog):
    video = _write_video(tmp_path / "flight.avi", 2, size=(320, 240))  # 4:3 frames, a preset made at their size
    telemetry = tmp_path / "flight.csv"
    telemetry.write_text("time_s,lat,lon,height_m,pitch_deg,heading_deg\n0,48.53,9.06,30,90,0\n1,48.53,9.06,30,90,0\n")
    model = _write_model(tmp_path / "model.onnx")
    with caplog.at_level("WARNING", logger="agent.sources"):
        source = VideoSource(video, telemetry, model, "dji-mavic2-pro")
    assert source.camera == Camera.from_preset("dji-mavic2-pro", 320, 240)
    assert not [r for r in caplog.records if "camera" in r.getMessage()]
    source.close()
    (tmp_path / "cam.json").write_text(json.dumps({"width": 640, "height": 360, "fx": 500.0}))
    with pytest.raises(ValueError, match="the camera is 640x360 but the frames of .*flight.avi are 320x240 "
                                         r"\(another aspect ratio\)"):
        VideoSource(video, telemetry, model, tmp_path / "cam.json")


def test_video_source_errors_name_the_missing_file(tmp_path):
    video = _write_video(tmp_path / "v.avi", 2)
    model = _write_model(tmp_path / "m.onnx")
    tel = tmp_path / "t.csv"
    tel.write_text("time_s,lat,lon,height_m,pitch_deg,heading_deg\n0,48,9,30,60,0\n")
    cam = tmp_path / "c.json"
    cam.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    with pytest.raises(ValueError, match="telemetry file .*nope.srt does not exist"):
        VideoSource(video, tmp_path / "nope.srt", model, cam)
    with pytest.raises(ValueError, match="model file .*nope.onnx does not exist"):
        VideoSource(video, tel, tmp_path / "nope.onnx", cam)
    with pytest.raises(ValueError, match="video file .*nope.mp4 does not exist"):
        VideoSource(tmp_path / "nope.mp4", tel, model, cam)
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video")
    with pytest.raises(ValueError, match="cannot be opened"):
        VideoSource(bad, tel, model, cam)


def test_dataset_source_gives_the_telemetry_stamp_as_pose_time(coop_dir):
    # regression: the image time was passed as the pose time; the 10 Hz telemetry is older than the frame
    frames = [f for f in DatasetSource(coop_dir).frames() if f.pose is not None]
    ages = np.array([f.t - f.pose_t for f in frames])
    assert np.all(ages >= -1e-6) and np.all(ages < 0.2) and (ages > 0.01).sum() >= len(frames) // 3


def test_video_source_takes_the_klv_inside_a_transport_stream(tmp_path):
    pytest.importorskip("av")
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    t0 = 1_717_236_000.0
    klv = [packet(t0 + 0.1 * i, {**FULL_FIELDS, "sensor_lat": 48.53 + 1e-5 * i}) for i in range(12)]
    video = write_ts_with_pyav(tmp_path / "flight.ts", klv, fps=10, size=(320, 180), klv_delay_frames=2)
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    source = VideoSource(video, "klv", _write_model(tmp_path / "model.onnx"), camera, max_gap_s=0.15)
    # sample i is shown with frame i + 2: the video starts 0.2 s before the first sample, by the PTS
    assert source.telemetry_offset_s == pytest.approx(t0 - 0.2, abs=1e-3)
    frames = list(source.frames())
    assert len(frames) == 12
    assert [f.pose is not None for f in frames] == [False] + [True] * 11  # 0.2 s before the first sample: none
    pose = frames[5].pose
    assert pose.lat == pytest.approx(48.53 + 3e-5, abs=1e-7)
    assert (pose.pitch_deg, pose.heading_deg, pose.height_m) == pytest.approx((45.0, 10.0, 40.0), abs=0.31)
    avi = _write_video(tmp_path / "plain.avi", 2)
    with pytest.raises(ValueError, match=r"--telemetry klv reads the KLV metadata of an MPEG transport stream "
                                         r"\(\.ts, \.m2ts, \.mts\), not .*plain\.avi"):
        VideoSource(avi, "klv", tmp_path / "model.onnx", camera)


@pytest.mark.parametrize(("hfovs", "said"), [
    ((60.0, 60.0), None),
    ((8.0, 8.0), "constant over the flight, where the camera's is 65.2 deg"),
    ((60.0, 30.0), "changes during the flight (30.0 .. 60.0 deg, a zoom lens"),
])
def test_a_klv_field_of_view_is_applied_when_the_lens_zooms(tmp_path, caplog, hfovs, said):
    """A zooming ISR gimbal: the KLV says 8 deg where the camera file's lens has 65 (a box 100 px off centre put
    40 m out where it is 4 m). Constant, it is not applied (the camera file or the encoder is wrong, and nothing
    says which); changing in flight, each frame's camera follows it. A warning says which."""
    pytest.importorskip("av")
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    t0 = 1_717_236_000.0
    klv = [packet(t0 + 0.1 * i, {**FULL_FIELDS, "hfov_deg": hfovs[i * len(hfovs) // 6]}) for i in range(6)]
    video = write_ts_with_pyav(tmp_path / "flight.ts", klv, fps=10, size=(320, 180))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))  # 65.2 deg
    with caplog.at_level("WARNING", logger="agent.sources"):
        source = VideoSource(video, "klv", _write_model(tmp_path / "model.onnx"), camera)
    messages = [r.getMessage() for r in caplog.records if "field of view" in r.getMessage()]
    assert (len(messages) == 1 and said in messages[0]) if said else not messages
    frames = list(source.frames())
    assert len(frames) == 6
    fovs = [round(f.camera.hfov_deg, 1) for f in frames if f.pose is not None]
    if hfovs[0] != hfovs[1]:  # the frames show samples 0-2 at 60 deg, 3-5 at 30
        assert fovs[0] == 60.0 and fovs[-1] == 30.0 and len(fovs) >= 5
        assert all(f.camera.cx == 160.0 and f.camera.width == 320 for f in frames)
    else:
        assert set(fovs) == {65.2}


def test_klv_that_sends_angles_and_gives_no_pitch_says_why(tmp_path):
    """A nadir gimbal on a platform banked 3 deg looks past nadir (roll beyond 90) in every packet: the run was
    refused with "no gimbal pitch in any record", though tag 19 was in every packet."""
    pytest.importorskip("av")
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    t0 = 1_717_236_000.0
    fields = {**FULL_FIELDS, "platform_roll_deg": 3.0, "sensor_rel_elevation_deg": -90.0}
    video = write_ts_with_pyav(tmp_path / "flight.ts", [packet(t0 + 0.1 * i, fields) for i in range(6)], fps=10,
                               size=(320, 180))
    with pytest.raises(ValueError, match=r"no gimbal pitch in any of its 6 records \(6 with the camera above the "
                                         r"horizon or past nadir, 0 with the platform's attitude out of range\): "
                                         r"pass --pitch-deg DEG"):
        VideoSource(video, "klv", _write_model(tmp_path / "model.onnx"), "dji-mavic2-pro")


# ---- telemetry without a height: --height-m / --height-offset-m ------------------------------------
# Mavic 2 Pro firmware that logs the position and no altitude (issue 21), gimbal angles from the flags.
_SRT_NO_HEIGHT = "".join(
    f"{i + 1}\n00:00:{i // 10:02d},{i % 10 * 100:03d} --> 00:00:{(i + 1) // 10:02d},{(i + 1) % 10 * 100:03d}\n"
    f'<font size="36">SrtCnt : {i + 1}, DiffTime : 100ms\n2019-03-16 16:20:47,{i * 100:03d},000\n'
    f"[iso : 100] [shutter : 1/640.0] [fnum : 280] [ev : 0] [ct : 5500] [color_md : default] "
    f"[focal_len : 280] [latitude : {48.53 + 1e-5 * i:.6f}] [longtitude : 9.060000] </font>\n\n"
    for i in range(10)
)


def test_video_telemetry_without_height_asks_for_height_m_in_one_line(tmp_path):
    from agent.sources import load_video_telemetry

    srt = tmp_path / "DJI_0012.SRT"
    srt.write_text(_SRT_NO_HEIGHT)
    with pytest.raises(ValueError, match=r"DJI_0012\.SRT has no height above ground in 10 of 10 records: "
                                         r"pass --height-m METRES") as err:
        load_video_telemetry(srt)
    assert "\n" not in str(err.value)
    records = load_video_telemetry(srt, height_m=35.0)
    assert len(records) == 10 and records[0].height_m is None
    assert records[0].to_pose(90.0, 0.0, height_m=35.0).height_m == 35.0
    with pytest.raises(ValueError, match="--height-m -3.0 must be a height above the ground > 0 m"):
        load_video_telemetry(srt, height_m=-3.0)


def test_video_telemetry_above_sea_level_only_asks_for_height_offset_m(tmp_path):
    from agent.sources import load_video_telemetry

    srt = tmp_path / "mini3.srt"
    srt.write_text(_SRT_NO_HEIGHT.replace("[longtitude : 9.060000]", "[longitude : 9.06] [abs_alt: 452.5]"))
    with pytest.raises(ValueError, match=r"gives only altitude above sea level \(abs_alt\) in 10 of 10 records: "
                                         r"pass --height-offset-m=-\(ground elevation in metres\)"):
        load_video_telemetry(srt)
    records = load_video_telemetry(srt, height_offset_m=-412.5)
    assert [r.height_m for r in records] == pytest.approx([40.0] * 10)
    coco = tmp_path / "meta.json"
    coco.write_text("{}")
    with pytest.raises(ValueError, match="--height-offset-m applies to .srt and .csv telemetry"):
        load_video_telemetry(coco, height_offset_m=-10.0)


def test_video_source_georeferences_srt_without_height_with_height_m(tmp_path):
    video = _write_video(tmp_path / "flight.avi", 8)
    telemetry = tmp_path / "flight.srt"
    telemetry.write_text(_SRT_NO_HEIGHT)
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    source = VideoSource(video, telemetry, _write_model(tmp_path / "model.onnx"), camera, pitch_deg=60.0,
                         heading_deg=0.0, height_m=42.0)
    frames = list(source.frames())
    assert len(frames) == 8 and all(f.pose is not None for f in frames)
    assert {f.pose.height_m for f in frames} == {42.0}
    assert frames[3].pose.lat == pytest.approx(48.53 + 3e-5)


def test_agent_command_without_height_fails_with_one_clear_line(tmp_path, capsys):
    from uavmm.cli import main

    telemetry = tmp_path / "DJI_0012.SRT"
    telemetry.write_text(_SRT_NO_HEIGHT)
    for name in ("v.mp4", "m.onnx", "c.json"):  # the telemetry is read before these are opened
        (tmp_path / name).write_bytes(b"")
    code = main(["agent", "--uav-id", "uav1", "--video", str(tmp_path / "v.mp4"), "--telemetry", str(telemetry),
                 "--model", str(tmp_path / "m.onnx"), "--camera", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert code == 2
    lines = [line for line in err.splitlines() if "error" in line]
    assert lines == [f"uavmm agent: error: telemetry file {telemetry} has no height above ground in 10 of 10 "
                     "records: pass --height-m METRES (the flight's height above the ground)"]


def _srt_air2s(frames: int, *, gb_pitch: bool = True, gb_yaw: bool = True) -> str:
    """DJI Air 2S-style SRT blocks (rel_alt / abs_alt), with or without the gimbal's pitch and yaw."""
    blocks = []
    for i in range(frames):
        gimbal = (f" [gb_yaw: {173.3 + 0.1 * i:.1f}" if gb_yaw else "") + (" gb_pitch: -38.0" if gb_pitch else "") \
            + (" gb_roll: 0.0]" if gb_yaw or gb_pitch else "")
        blocks.append(f"{i + 1}\n00:00:{i // 10:02d},{i % 10 * 100:03d} --> 00:00:{(i + 1) // 10:02d},"
                      f"{(i + 1) % 10 * 100:03d}\n<font size=\"28\">FrameCnt: {i + 1}, DiffTime: 100ms\n"
                      f"2023-06-01 10:00:00.{i * 100:03d}\n[iso: 100] [latitude: {48.53 + 1e-5 * i:.6f}] "
                      f"[longitude: 9.060000] [rel_alt: 27.500 abs_alt: 412.500]{gimbal} </font>\n\n")
    return "".join(blocks)


def _video_source(tmp_path, srt_text: str, **kw) -> VideoSource:
    video = _write_video(tmp_path / "flight.avi", 8)
    telemetry = tmp_path / "DJI_0001.SRT"
    telemetry.write_text(srt_text)
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    return VideoSource(video, telemetry, _write_model(tmp_path / "model.onnx"), camera, **kw)


def test_video_source_without_gimbal_angles_asks_for_them_in_one_line(tmp_path):
    # an SRT whose drone does not log the gimbal (older firmware): position and height alone place no pixel
    with pytest.raises(ValueError, match=r"DJI_0001.SRT has no gimbal pitch in any of its 10 records: pass "
                                         r"--pitch-deg DEG"):
        _video_source(tmp_path, _srt_air2s(10, gb_pitch=False, gb_yaw=False))
    with pytest.raises(ValueError, match=r"has no gimbal heading in any of its 10 records: pass --heading-deg DEG"):
        _video_source(tmp_path, _srt_air2s(10, gb_pitch=False, gb_yaw=False), pitch_deg=38.0)
    frames = list(_video_source(tmp_path, _srt_air2s(10, gb_pitch=False, gb_yaw=False), pitch_deg=38.0,
                                heading_deg=173.0).frames())
    assert all(f.pose is not None for f in frames)
    assert {(f.pose.pitch_deg, f.pose.heading_deg) for f in frames} == {(38.0, 173.0)}


def test_gimbal_flags_fill_what_the_telemetry_lacks_and_never_replace_it(tmp_path, caplog):
    # gb_yaw logged, gb_pitch not: --pitch-deg supplies the pitch, the logged heading stays (the flags' help:
    # "fixed gimbal pitch if telemetry lacks it")
    frames = list(_video_source(tmp_path, _srt_air2s(10, gb_pitch=False), pitch_deg=38.0,
                                heading_deg=90.0).frames())
    assert all(f.pose is not None for f in frames)
    assert frames[3].pose.pitch_deg == 38.0
    assert frames[3].pose.heading_deg == pytest.approx(173.6, abs=0.01)
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        frames = list(_video_source(tmp_path, _srt_air2s(10), pitch_deg=60.0).frames())
    assert frames[3].pose.pitch_deg == pytest.approx(38.0)  # the file's -38 (DJI: negative down)
    assert any("every record has a gimbal pitch: --pitch-deg 60 is not used" in r.getMessage() for r in caplog.records)


def test_frames_without_a_pose_are_named_once_at_warning_level(tmp_path, caplog):
    # half the records lack the pitch (a gimbal that reported late): those frames have no pose, and the first is
    # named with its reason
    text = _srt_air2s(10)
    blocks = text.split("\n\n")
    text = "\n\n".join(b.replace(" gb_pitch: -38.0", "") if i < 5 else b for i, b in enumerate(blocks))
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        source = _video_source(tmp_path, text, max_gap_s=0.05)
        frames = list(source.frames())
    assert sum(f.pose is None for f in frames) >= 4 and source.problems >= 4
    named = [r.getMessage() for r in caplog.records if "no pose at" in r.getMessage()]
    assert len(named) == 1 and "telemetry has no gimbal pitch: pass --pitch-deg" in named[0]


def test_srt_blocks_without_a_fix_at_the_start_do_not_move_the_video_clock(tmp_path, caplog):
    # recording began before the GPS lock: the first three blocks are at 0, 0 and are skipped; the subtitle timing
    # of the first usable block still says where it sits in the video (0.3 s), so frame 5 shows block 5
    text = _srt_air2s(10)
    for i in range(3):
        text = text.replace(f"[latitude: {48.53 + 1e-5 * i:.6f}] [longitude: 9.060000]",
                            "[latitude: 0.000000] [longitude: 0.000000]", 1)
    with caplog.at_level(logging.INFO, logger="agent.sources"):
        source = _video_source(tmp_path, text)
    assert source.telemetry_offset_s == pytest.approx(utc_s("2023-06-01T10:00:00"), abs=1e-3)
    assert "(from the SRT's subtitle timing)" in caplog.text
    frames = list(source.frames())
    assert frames[5].pose is not None and frames[5].pose.lat == pytest.approx(48.53 + 5e-5, abs=1e-7)


def utc_s(text: str) -> float:
    from datetime import datetime, timezone

    return datetime.fromisoformat(text).replace(tzinfo=timezone.utc).timestamp()

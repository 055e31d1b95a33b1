"""`uavmm anomaly --video FLIGHT.ts --telemetry klv`: the MISB ST 0601 KLV inside a transport stream (written by
FFmpeg's muxer through PyAV), its PTS giving the telemetry time of video time 0, and --telemetry-offset-s."""

from __future__ import annotations

import json
import logging

import pytest

from agent.anomaly.frames import VideoFrames
from shared.geo import Camera
from uavmm.cli import main

T0 = 1_717_236_000.0
FRAMES = 12


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory):
    """A 10 fps MPEG-TS of 12 frames whose KLV sample i (sensor latitude 48.53 + 1e-5 i, 10 Hz) is shown with
    frame i + 2: the video starts 0.2 s before the first sample, by the PTS. Returns (video, camera file)."""
    pytest.importorskip("av")
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    d = tmp_path_factory.mktemp("anomaly-klv")
    klv = [packet(T0 + 0.1 * i, {**FULL_FIELDS, "sensor_lat": 48.53 + 1e-5 * i}) for i in range(FRAMES)]
    video = write_ts_with_pyav(d / "flight.ts", klv, fps=10, size=(320, 180), klv_delay_frames=2)
    camera = d / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    return video, camera


def test_video_frames_take_video_time_zero_from_the_klv_pts(flight):
    video, camera = flight
    cam = Camera.from_spec(camera)
    for telemetry in ("klv", "KLV", video):  # the word, or the transport stream named as the telemetry file
        source = VideoFrames(video, telemetry, cam)
        assert source.offset_s == pytest.approx(T0 - 0.2, abs=1e-3)
        frames = list(source)
        assert len(frames) == FRAMES and all(f.pose is not None for f in frames)
        assert frames[5].pose.lat == pytest.approx(48.53 + 3e-5, abs=1e-7)  # frame 5 shows sample 3
        assert frames[5].t == pytest.approx(T0 + 0.3, abs=1e-3)
        pose = frames[5].pose
        assert (pose.pitch_deg, pose.heading_deg, pose.height_m) == pytest.approx((45.0, 10.0, 40.0), abs=0.31)
    given = list(VideoFrames(video, "klv", cam, telemetry_offset_s=T0))
    assert given[5].pose.lat == pytest.approx(48.53 + 5e-5, abs=1e-7)  # --telemetry-offset-s overrides the PTS


def test_anomaly_reads_the_klv_inside_the_video(flight, tmp_path, capsys, caplog):
    video, camera = flight
    out = tmp_path / "rois.json"
    caplog.set_level(logging.INFO, logger="agent.sources")
    assert main(["anomaly", "--video", str(video), "--telemetry", "klv", "--camera", str(camera), "--out", str(out),
                 "--method", "mean", "--quiet"]) == 0
    assert f"video time 0 is telemetry time {T0 - 0.2:.3f} (from the KLV PTS)" in caplog.text
    assert f"for {FRAMES} frames" in capsys.readouterr().out
    assert {r["image_id"] for r in json.loads(out.read_text())} <= set(range(FRAMES))


def _error(capsys, args) -> str:
    assert main(["anomaly", *args, "--method", "mean", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    return err


def test_anomaly_klv_and_offset_errors_are_one_line(flight, tmp_path, capsys):
    video, camera = flight
    files = ["--camera", str(camera), "--out", str(tmp_path / "rois.json")]
    # an offset the telemetry does not cover: --telemetry-offset-s reaches the reader
    err = _error(capsys, ["--video", str(video), "--telemetry", "klv", "--telemetry-offset-s", str(T0 + 60), *files])
    assert "covers" in err and "flight.ts" in err
    avi = tmp_path / "clip.avi"
    avi.write_bytes(b"not a video")
    err = _error(capsys, ["--video", str(avi), "--telemetry", "klv", *files])
    assert "--telemetry klv reads the KLV metadata of an MPEG transport stream (.ts, .m2ts, .mts), not" in err
    images = tmp_path / "images.json"
    images.write_text(json.dumps({"images": [], "categories": []}))
    err = _error(capsys, ["--frames", str(images), "--telemetry-offset-s", "3", *files])
    assert "--telemetry-offset-s goes with --video" in err
    assert not (tmp_path / "rois.json").exists()


def test_video_without_gimbal_angles_warns_and_takes_them_from_the_flags(tmp_path, caplog, capsys):
    # an SRT whose drone logs no gimbal (older DJI firmware): the per-frame heatmap still runs, but no frame has a
    # pose until --pitch-deg / --heading-deg give the angles, which fill what records lack (as agent and detect)
    from tests.agent.test_sources import _srt_air2s, _write_video

    video = _write_video(tmp_path / "flight.avi", 8)
    srt = tmp_path / "DJI_0001.SRT"
    srt.write_text(_srt_air2s(10, gb_pitch=False, gb_yaw=False))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    cam = Camera.from_spec(camera)
    with caplog.at_level(logging.WARNING, logger="agent.anomaly.frames"):
        frames = list(VideoFrames(video, srt, cam))
    assert all(f.pose is None for f in frames)
    assert "has no gimbal pitch in any record: no frame has a pose (no ground layer); pass --pitch-deg" in caplog.text
    frames = list(VideoFrames(video, srt, cam, pitch_deg=60.0, heading_deg=173.0))
    assert all(f.pose is not None for f in frames)
    assert (frames[3].pose.pitch_deg, frames[3].pose.heading_deg) == (60.0, 173.0)
    # a logged heading is kept: the flag fills only the missing pitch
    srt.write_text(_srt_air2s(10, gb_pitch=False))
    frames = list(VideoFrames(video, srt, cam, pitch_deg=60.0, heading_deg=90.0))
    assert frames[3].pose.heading_deg == pytest.approx(173.6, abs=0.01)
    out = tmp_path / "rois.json"
    assert main(["anomaly", "--video", str(video), "--telemetry", str(srt), "--camera", str(camera), "--out", str(out),
                 "--method", "mean", "--quiet", "--pitch-deg", "60"]) == 0
    err = _error(capsys, ["--frames", str(tmp_path / "images.json"), "--pitch-deg", "60", "--camera", str(camera),
                          "--out", str(out)])
    assert "--pitch-deg goes with --video" in err
    err = _error(capsys, ["--frames", str(tmp_path / "images.json"), "--mavlink-system-id", "2", "--camera",
                          str(camera), "--out", str(out)])
    assert "--mavlink-system-id goes with --video" in err
    err = _error(capsys, ["--video", str(video), "--telemetry", str(srt), "--mavlink-system-id", "2", "--camera",
                          str(camera), "--out", str(out)])
    assert "--mavlink-system-id applies to a MAVLink .tlog" in err


def test_video_frames_follow_a_zoom_lens_by_the_klv_field_of_view(tmp_path):
    """The KLV's field of view goes from 40 to 20 deg in flight: each frame's camera has the field of view of the
    sample it shows (the camera file's 65.2 deg otherwise; the anomaly heatmap is put on the ground with it)."""
    pytest.importorskip("av")
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    klv = [packet(T0 + 0.1 * i, {**FULL_FIELDS, "hfov_deg": 40.0 - 2.0 * i}) for i in range(FRAMES)]
    video = write_ts_with_pyav(tmp_path / "zoom.ts", klv, fps=10, size=(320, 180))
    cam = Camera(width=320, height=180, fx=250.0, fy=250.0, cx=160.0, cy=90.0)
    frames = list(VideoFrames(video, "klv", cam))
    assert [round(f.camera.hfov_deg, 1) for f in frames] == pytest.approx([40.0 - 2.0 * i for i in range(FRAMES)],
                                                                           abs=0.01)
    assert all((f.camera.cx, f.camera.cy) == (160.0, 90.0) for f in frames)

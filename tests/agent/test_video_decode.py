"""Video frames with their own times (agent.video_decode): variable frame rates, dropped and damaged frames,
rotation metadata, and telemetry that does not belong to the video. Videos written by PyAV (FFmpeg's encoders),
read back by OpenCV as the agent and `uavmm detect` read them; each frame's barcode says which frame it is."""

from __future__ import annotations

import json
import logging
import struct
from datetime import datetime, timezone
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from agent.sources import VideoSource
from agent.video_decode import VideoReader
from tests.agent.test_sources import _write_model

av = pytest.importorskip("av")

W, H = 320, 180
BITS = 10
T0 = 1685613600.0  # 2023-06-01 10:00:00 UTC
LAT0, RATE = 48.53, 9e-5  # degrees north per second: ~10 m/s


def _image(k: int) -> np.ndarray:
    """Frame k: its index as a barcode of BITS black and white bars over the top third."""
    img = np.full((H, W, 3), 128, np.uint8)
    bar = W // BITS
    for b in range(BITS):
        img[: H // 3, b * bar:(b + 1) * bar] = 255 if (k >> b) & 1 else 0
    return img


def _index(img: np.ndarray) -> int:
    bar = img.shape[1] // BITS
    return sum(int(img[img.shape[0] // 6, b * bar + bar // 2].mean() > 128) << b for b in range(BITS))


def _write(path: Path, pts_s: list[float], codec: str = "libx264", **options: str) -> Path:
    """Frame k shows k and is presented at pts_s[k] seconds."""
    tb = Fraction(1, 90000)
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=30, options={"bf": "0", **options})
        stream.width, stream.height = W, H
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        stream.codec_context.time_base = tb
        stream.time_base = tb
        for k, p in enumerate(pts_s):
            frame = av.VideoFrame.from_ndarray(_image(k), format="rgb24")
            frame.pts, frame.time_base = int(round(p / tb)), tb
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def _srt(path: Path, pts_s: list[float]) -> Path:
    """A DJI SRT with a block per frame at its true time; latitude grows with time (RATE deg/s)."""
    blocks = []
    for i, p in enumerate(pts_s):
        end = pts_s[i + 1] if i + 1 < len(pts_s) else p + 1 / 30

        def stamp(s: float) -> str:
            ms = int(round(s * 1000))
            return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"

        d = datetime.fromtimestamp(T0 + p, timezone.utc)
        blocks.append(f"{i + 1}\n{stamp(p)} --> {stamp(end)}\n<font size=\"28\">FrameCnt: {i + 1}\n"
                      f"{d.strftime('%Y-%m-%d %H:%M:%S.')}{d.microsecond // 1000:03d}\n"
                      f"[latitude: {LAT0 + RATE * p:.7f}] [longitude: 9.060000] [rel_alt: 40.000 abs_alt: 452.000] "
                      f"[gb_yaw: 0.0 gb_pitch: -90.0 gb_roll: 0.0] </font>\n\n")
    path.write_text("".join(blocks))
    return path


def _camera(path: Path) -> Path:
    path.write_text(json.dumps({"width": W, "height": H, "fx": W * 0.8}))
    return path


def _pose_time(frame) -> float:
    return (frame.pose.lat - LAT0) / RATE


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return _write_model(tmp_path_factory.mktemp("model") / "model.onnx")


@pytest.mark.parametrize("container", ["mp4", "mkv"])
def test_frames_of_a_variable_rate_video_get_the_pose_of_their_own_time(tmp_path, model, container, caplog):
    """An encoder stall drops a second of frames and 5 % more are dropped at random; then a phone-like slowdown.
    A frame's index over the nominal rate was up to 0.6 s (MP4) or 1.5 s (MKV) from its own time, ~15 m of
    flight; now every frame takes the pose of its own time."""
    rng = np.random.default_rng(1)
    keep = np.ones(240, bool)
    keep[60:90] = False
    keep[rng.random(240) < 0.05] = False
    keep[0] = True
    pts = [float(k) / 30 for k in np.flatnonzero(keep)]
    pts += [pts[-1] + 0.05 * (i + 1) for i in range(40)]  # the last 2 s at 20 frames/s
    video = _write(tmp_path / f"vfr.{container}", pts)
    source = VideoSource(video, _srt(tmp_path / "vfr.srt", pts), model, _camera(tmp_path / "cam.json"))
    with caplog.at_level(logging.INFO, logger="agent.video_decode"):
        frames = list(source.frames())
    assert len(frames) == len(pts)
    for frame in frames:
        k = _index(frame.image)
        assert frame.t - T0 == pytest.approx(pts[k], abs=0.002)
        assert _pose_time(frame) == pytest.approx(pts[k], abs=0.002)
    # a frame's number: dropped frames leave theirs out (on the 30 frames/s grid: its time x 30), then one a frame
    numbers = [f.index for f in frames]
    assert numbers == sorted(set(numbers))
    assert [f.index for f in frames[:len(pts) - 40]] == [round(p * 30) for p in pts[:len(pts) - 40]]
    assert "frame number(s) have no frame" in caplog.text
    assert source.reader.report.untimed == 0


def test_a_steady_video_keeps_its_frame_grid(tmp_path, model):
    pts = [k / 30 for k in range(45)]
    video = _write(tmp_path / "cfr.mp4", pts, bf="2")  # B-frames: decode order is not presentation order
    reader = VideoReader(video)
    frames = list(reader.frames())
    assert [_index(f.image) for f in frames] == list(range(45))
    assert np.allclose([f.t for f in frames], pts, atol=1e-3)
    assert reader.report.max_off_grid_s < 1e-3 and reader.report.failed == 0


@pytest.mark.parametrize("codec,suffix,bframes", [("mjpeg", "avi", "0"), ("libx264", "mp4", "0"),
                                                  ("libx264", "mp4", "2"), ("libx264", "mkv", "0"),
                                                  ("libx264", "ts", "2")])
def test_a_damaged_frame_does_not_end_the_video_nor_shift_the_frames_after_it(tmp_path, model, codec, suffix,
                                                                             bframes, caplog):
    """A packet's bytes zeroed (a bad card sector, a lost datagram). Reading ended there, silently (40 of 90
    frames). Now the video goes on and the frames after keep their own times and numbers: some decoders drop the
    frame inside one read (a transport stream, B-frames), so the number follows the time, not the count of reads."""
    pts = [k / 30 for k in range(90)]
    clean = _write(tmp_path / f"clean.{suffix}", pts, codec, g="10", bf=bframes)
    data = bytearray(clean.read_bytes())
    with av.open(str(clean)) as container:
        packets = [(p.pos, p.size) for p in container.demux(container.streams.video[0]) if p.size and p.pos >= 0]
    pos, size = packets[40]
    data[pos + 8:pos + size] = bytes(size - 8)  # keep the first bytes (a header), zero the payload
    damaged = tmp_path / f"damaged.{suffix}"
    damaged.write_bytes(bytes(data))
    source = VideoSource(damaged, _srt(tmp_path / "c.srt", pts), model, _camera(tmp_path / "cam.json"))
    with caplog.at_level(logging.INFO, logger="agent.video_decode"):
        frames = list(source.frames())
    report = source.reader.report
    assert len(frames) >= 80
    assert [f.index for f in frames] == sorted({f.index for f in frames})
    for frame in frames:
        assert frame.t - T0 == pytest.approx(frame.index / 30, abs=0.002)  # the number follows the time
        assert _pose_time(frame) == pytest.approx(frame.index / 30, abs=0.002)
    # past the next key frame every image is the frame its number says (before it a decoder may conceal, and with
    # B-frames put a frame or two out of order: those are left out)
    assert all(_index(f.image) == f.index for f in frames if f.index >= 50)
    assert frames[-1].index == 89
    assert report.failed + report.skipped >= 1  # the damage is said
    if report.failed:
        assert "could not be decoded" in caplog.text
    if report.out_of_order:
        assert "came out of order" in caplog.text
    if report.skipped:
        assert "have no frame" in caplog.text


def test_rotation_metadata_is_not_applied(tmp_path, model, caplog):
    """A clip with a 90 deg display matrix (rotated in an editor): OpenCV turned its frames to 180x320 and the
    camera file of the drone (320x180) was refused. The frames are read as the sensor recorded them."""
    pts = [k / 30 for k in range(20)]
    data = bytearray(_write(tmp_path / "plain.mp4", pts).read_bytes())
    i = data.find(b"tkhd")
    version = data[i + 4]
    matrix = i + 4 + 4 + (8 if version == 0 else 16) + 4 + 4 + (4 if version == 0 else 8) + 8 + 8
    data[matrix:matrix + 36] = struct.pack(">9i", 0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30)
    rotated = tmp_path / "rot90.mp4"
    rotated.write_bytes(bytes(data))
    with caplog.at_level(logging.INFO, logger="agent.video_decode"):
        source = VideoSource(rotated, _srt(tmp_path / "r.srt", pts), model, _camera(tmp_path / "cam.json"))
        frames = list(source.frames())
    assert source.reader.rotation_deg in (90, 270)
    assert "rotation in its metadata" in caplog.text
    assert [f.image.shape[:2] for f in frames] == [(H, W)] * 20
    assert [_index(f.image) for f in frames] == list(range(20))


def test_telemetry_that_does_not_cover_the_video_or_runs_far_past_it_is_named(tmp_path, model, caplog):
    pts = [k / 30 for k in range(60)]
    video = _write(tmp_path / "clip.mp4", pts)
    camera = _camera(tmp_path / "cam.json")
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        VideoSource(video, _srt(tmp_path / "short.srt", pts[:15]), model, camera)
    assert "ends 0.5 s into the video but clip.mp4 lasts 2.0 s" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        VideoSource(video, _srt(tmp_path / "long.srt", [k / 30 for k in range(600)]), model, camera)
    assert "a clip cut from a longer recording?" in caplog.text and "long.srt runs 20.0 s" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="agent.sources"):
        VideoSource(video, _srt(tmp_path / "same.srt", pts), model, camera)
    assert caplog.text == ""


def test_frames_inside_a_gap_of_the_telemetry_get_no_pose(tmp_path, model):
    """A radio dropout of 1.4 s in the middle: frames more than max_gap_s from any record get no pose (they got
    one drawn straight across the gap); the frames near the gap's ends keep theirs."""
    pts = [k / 30 for k in range(90)]
    kept = [p for p in pts if not 0.9 < p < 2.3]
    video = _write(tmp_path / "gap.mp4", pts)
    source = VideoSource(video, _srt(tmp_path / "gap.srt", kept), model, _camera(tmp_path / "cam.json"),
                         max_gap_s=0.5)
    frames = list(source.frames())
    without = [f.index for f in frames if f.pose is None]
    assert without == [k for k in range(90) if 0.9 + 0.5 < k / 30 < 2.3 - 0.5 - 1e-9]


def test_a_raw_h264_stream_takes_its_rate_from_video_fps(tmp_path, model, caplog):
    """A raw .h264 stream (a Raspberry Pi camera, a DVR) has no frame times and FFmpeg guesses 25 frames/s: a 30
    frames/s recording drifted 20 % (frame 44 put at 1.76 s, 2.9 m of flight at 10 m/s, where it is at 1.47 s).
    --video-fps gives the rate; without it a warning names the flag."""
    pts = [k / 30 for k in range(45)]
    video = _write(tmp_path / "pi.h264", pts)
    with caplog.at_level(logging.WARNING, logger="agent.video_decode"):
        guessed = list(VideoReader(video).frames())
    assert [_index(f.image) for f in guessed] == list(range(45))
    assert np.allclose([f.t for f in guessed], [k / 25 for k in range(45)], atol=1e-9)
    assert "pi.h264 is a raw stream without frame times nor a stated rate" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        source = VideoSource(video, _srt(tmp_path / "pi.srt", pts), model, _camera(tmp_path / "camera.json"),
                             telemetry_offset_s=T0, video_fps=30.0)
        frames = list(source.frames())
    assert not [r for r in caplog.records if "raw stream" in r.getMessage()]
    assert [f.index for f in frames] == list(range(45))
    assert np.allclose([_pose_time(f) for f in frames], pts, atol=2e-3)  # each frame at its own time
    with pytest.raises(ValueError, match=r"--video-fps applies to a raw .* stream, which has no frame times; "
                                         r"cfr\.mp4 is a container with its own"):
        VideoReader(_write(tmp_path / "cfr.mp4", pts), fps=30.0)
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(ValueError, match="--video-fps"):
            VideoReader(video, fps=bad)


def test_video_fps_beside_a_container_is_refused_in_one_line_by_each_command(tmp_path, model, capsys):
    from uavmm.cli import main

    pts = [k / 30 for k in range(6)]
    video, srt = _write(tmp_path / "cfr.mp4", pts), _srt(tmp_path / "cfr.srt", pts)
    camera = _camera(tmp_path / "c.json")
    detect = ["detect", str(video), "--telemetry", str(srt), "--model", str(model), "--camera", str(camera), "--out",
              str(tmp_path / "out"), "--video-fps", "30"]
    anomaly = ["anomaly", "--video", str(video), "--telemetry", str(srt), "--camera", str(camera), "--out",
               str(tmp_path / "rois.json"), "--video-fps", "30"]
    for argv in (detect, anomaly):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--video-fps applies to a raw" in err[0] and "cfr.mp4 is a container" in err[0]


@pytest.mark.parametrize(("codec", "suffix", "damaged", "first"), [("mjpeg", "mkv", 10, 10), ("libx264", "mp4", 1, 10)])
def test_a_video_whose_first_frames_do_not_decode_keeps_every_frames_number(tmp_path, codec, suffix, damaged, first):
    """The first packets damaged (a bad card sector; for H.264 its first key frame, which takes the frames up to the
    next one with it): the first frame that decodes was numbered 0 and every later one shifted by as many (image ids
    and MOT frames of detect and agent --video), and anomaly --video refused a file with 10 such frames."""
    clean = _write(tmp_path / f"clean.{suffix}", [k / 30 for k in range(40)], codec, g="10")
    data = bytearray(clean.read_bytes())
    with av.open(str(clean)) as container:
        packets = [(p.pos, p.size) for p in container.demux(container.streams.video[0]) if p.size and p.pos >= 0]
    for pos, size in packets[:damaged]:
        data[pos + 8:pos + size] = bytes(size - 8)
    video = tmp_path / f"bad.{suffix}"
    video.write_bytes(bytes(data))
    reader = VideoReader(video)
    frames = list(reader.frames())
    assert frames[0].index == first and frames[0].t == pytest.approx(first / 30, abs=1e-3)
    assert all(f.index == _index(f.image) for f in frames)  # each frame's number is the one it shows
    assert reader.first_image() is not None

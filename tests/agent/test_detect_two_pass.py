"""`uavmm detect` reads a recording as a file (agent.offline.two_pass): the detector over the whole video, then the
clock offset, the view cuts and the adaptive stages on all of it, then memory map and tracker. End to end on a
real video (MJPG), a 1 Hz telemetry log and a real ONNX model run by onnxruntime (tests.agent.jump_flight)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.offline.two_pass import CandidateSpool
from agent.sources import pose_from_meta
from uavmm.cli import main

pytest.importorskip("onnx")

from tests.agent.jump_flight import JumpFlight, write_jump_flight  # noqa: E402  (needs onnx)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> JumpFlight:
    # seed 0: five objects a view; the views 90 deg apart, jumps at 2.5, 5.5 and 8.5 s, logged at whole seconds
    return write_jump_flight(tmp_path_factory.mktemp("jump-flight"), seed=0)


def _detect(flight: JumpFlight, out: Path, *extra: str) -> dict:
    assert main(["detect", str(flight.video), "--telemetry", str(flight.telemetry), "--model", str(flight.model),
                 "--camera", str(flight.camera), "--out", str(out), "--quiet", *extra]) == 0
    return json.loads((out / "summary.json").read_text())


def _heading_errors(flight: JumpFlight, out: Path) -> np.ndarray:
    """Per frame of images.json: |pose heading - true heading|, degrees (NaN without pose)."""
    errors = []
    for image in json.loads((out / "images.json").read_text())["images"]:
        pose, _, _ = pose_from_meta(image["meta"])
        truth = flight.headings[image["frame_index"]]
        errors.append(np.nan if pose is None else abs((pose.heading_deg - truth + 180.0) % 360.0 - 180.0))
    return np.array(errors)


def _track_ids(out: Path) -> set[int]:
    return {int(line.split(",")[1]) for line in (out / "tracks.txt").read_text().splitlines()}


def test_two_passes_put_the_view_jumps_a_one_hertz_log_smears_where_the_video_jumps(flight, tmp_path, capsys):
    two = _detect(flight, tmp_path / "two")
    printed = capsys.readouterr().out
    one = _detect(flight, tmp_path / "one", "--one-pass")
    assert two["two_pass"] is True and "one_pass_because" not in two
    assert one["two_pass"] is False and one["one_pass_because"] == "--one-pass"
    assert two["frames"] == one["frames"] == len(flight.headings)
    # one pass: the frames between a jump and the next sample get an interpolated heading up to 45 deg off
    one_err = _heading_errors(flight, tmp_path / "one")
    assert (one_err > 2.0).sum() >= 20
    # two passes: every frame's heading is the view it shows; the stage says it acted, the CLI prints it
    two_err = _heading_errors(flight, tmp_path / "two")
    assert not np.isnan(two_err).any() and two_err.max() <= 2.0
    assert two["stages"]["view cuts"]["acted"] == 1
    assert "view cuts: acted 1" in printed
    assert "clock offset" in two["stages"]
    # ten objects: the tracks keep to them; one pass splits them at every jump
    assert len(_track_ids(tmp_path / "two")) <= 12 < len(_track_ids(tmp_path / "one"))
    # the candidates' temporary file is gone: --out holds the outputs and nothing else
    written = {Path(f).name for f in two["files"].values()} | {"summary.json"}
    assert {p.name for p in (tmp_path / "two").iterdir()} == written


def _open_files_under(folder: Path) -> list[str]:
    """What this process holds open in folder (an unnamed temporary file shows as `folder/#123 (deleted)`)."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder) + os.sep):
            out.append(target)
    return out


def test_max_frames_stops_both_passes_and_the_spool_is_closed(flight, tmp_path):
    from agent.offline.run import DetectOptions, run_detect
    from agent.sources import VideoSource

    calls: list[tuple[int, int | None]] = []
    source = VideoSource(flight.video, flight.telemetry, flight.model, flight.camera)
    summary = run_detect(source, tmp_path / "out", options=DetectOptions(max_frames=17),
                         progress=lambda done, total: calls.append((done, total)))
    assert summary["frames"] == 17 and summary["two_pass"] is True
    # pass one read 17 frames (the detector ran on no more), pass two (announced with 0 done) ran on them
    assert [done for done, _ in calls] == [*range(1, 18), 0, *range(1, 18)]
    assert all(total == 17 for _, total in calls)
    images = json.loads((tmp_path / "out" / "images.json").read_text())["images"]
    assert [im["frame_index"] for im in images] == list(range(17))
    assert _open_files_under(tmp_path / "out") == []


def test_the_spool_is_closed_when_a_run_fails(flight, tmp_path):
    from agent.offline.run import run_detect
    from agent.sources import VideoSource

    def stop(done: int, total: int | None) -> None:
        if done == 5:
            raise KeyboardInterrupt

    source = VideoSource(flight.video, flight.telemetry, flight.model, flight.camera)
    with pytest.raises(KeyboardInterrupt):
        run_detect(source, tmp_path / "out", progress=stop)
    assert _open_files_under(tmp_path / "out") == []
    assert list((tmp_path / "out").iterdir()) == []  # no output file either


def test_a_no_fix_record_at_zero_zero_is_left_out_of_the_retimed_poses(tmp_path):
    # KLV keeps a packet whose sensor position is (0, 0), a logger's "no GPS fix": the interpolation of one pass
    # leaves it out, and so must the track the two passes re-time poses on
    pytest.importorskip("av")
    from tests.agent.test_detector import make_constant_model
    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts_with_pyav

    packets = [packet(1_717_236_000.0 + 0.1 * i, {**FULL_FIELDS, **({"sensor_lat": 0.0, "sensor_lon": 0.0}
                                                                     if i == 15 else {})}) for i in range(30)]
    video = write_ts_with_pyav(tmp_path / "flight.ts", packets, fps=10, size=(320, 180))
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 320, "height": 180, "fx": 250.0}))
    raw = np.zeros((1, 6, 100), np.float32)
    raw[0, :4, 0], raw[0, 4, 0] = [320, 320, 20, 40], 0.9
    model = make_constant_model(tmp_path / "model.onnx", raw, metadata={"names": str({0: "person", 1: "swimmer"})})
    assert main(["detect", str(video), "--telemetry", "klv", "--model", str(model), "--camera", str(camera),
                 "--out", str(tmp_path / "out"), "--no-size-filter", "--quiet"]) == 0
    metas = [im["meta"] for im in json.loads((tmp_path / "out" / "images.json").read_text())["images"]]
    assert len(metas) == 30 and all(m is not None for m in metas)
    assert [m["gps_latitude"] for m in metas] == pytest.approx([FULL_FIELDS["sensor_lat"]] * 30, abs=1e-4)


def test_a_flight_across_the_antimeridian_keeps_to_it(flight, tmp_path):
    rows = ["time_s,lat,lon,height_m,pitch_deg,heading_deg"]
    rows += [f"{t:.1f},-17.0,{179.9999 if t <= 5 else -179.9999},40,60,0" for t in range(14)]
    telemetry = tmp_path / "across.csv"
    telemetry.write_text("\n".join(rows) + "\n")
    assert main(["detect", str(flight.video), "--telemetry", str(telemetry), "--model", str(flight.model),
                 "--camera", str(flight.camera), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    images = json.loads((tmp_path / "out" / "images.json").read_text())["images"]
    lons = [pose_from_meta(im["meta"])[0].lon for im in images]
    assert len(lons) == len(flight.headings)
    assert all(abs(abs(lon) - 180.0) < 2e-4 for lon in lons), lons  # never the long way round through 0


def test_over_a_dem_the_clock_offset_puts_the_detections_on_the_terrain(flight, tmp_path, monkeypatch):
    import agent.file_frames as file_frames
    from agent.dem import write_npz
    from shared.geo import Pose
    from shared.terrain import ElevationGrid
    from tests.agent.jump_flight import LAT, LON

    north = np.arange(100, -101, -1, dtype=float)
    heights = 300.0 + 0.2 * np.repeat(north[:, None], 201, axis=1)  # a slope rising northward
    write_npz(tmp_path / "dem.npz", ElevationGrid.from_local(heights, LAT, LON, west_m=-100.0, north_m=100.0,
                                                            cell_m=1.0))
    given: list = []
    real = file_frames.retime_frames  # two passes run the dataset path's look-ahead (agent.file_frames)

    def retime_frames(*args, **kwargs):  # the real stage, its terrain argument kept
        given.append(kwargs.get("terrain_for"))
        return real(*args, **kwargs)

    monkeypatch.setattr(file_frames, "retime_frames", retime_frames)
    summary = _detect(flight, tmp_path / "out", "--dem", str(tmp_path / "dem.npz"), "--takeoff-elevation-m", "300")
    assert summary["two_pass"] is True and len(given) == 1 and given[0] is not None
    assert given[0](Pose(LAT, LON, 40.0, 60.0, 0.0)) is not None  # the DEM under the UAV, as the pipeline has it


def test_the_annotated_video_has_every_frame_decoded_again(flight, tmp_path):
    import cv2

    summary = _detect(flight, tmp_path / "out", "--render-video", "--max-frames", "30")
    capture = cv2.VideoCapture(summary["files"]["video"])
    try:
        frames = 0
        while capture.read()[0]:
            frames += 1
    finally:
        capture.release()
    assert frames == 30


boxes_st = st.integers(0, 12).flatmap(lambda n: st.tuples(
    st.lists(st.lists(st.floats(-1e4, 1e4, width=32), min_size=4, max_size=4), min_size=n, max_size=n),
    st.lists(st.floats(0.0, 1.0, width=32), min_size=n, max_size=n),
    st.lists(st.integers(-(2 ** 40), 2 ** 40), min_size=n, max_size=n)))


@settings(max_examples=40, deadline=None)
@given(st.lists(boxes_st, max_size=8))
def test_the_spool_gives_back_each_frames_candidates_exactly(tmp_path_factory, frames):
    spool = CandidateSpool(tmp_path_factory.mktemp("spool"))
    try:
        for boxes, scores, cids in frames:
            spool.add(np.array(boxes, np.float32).reshape(-1, 4), np.array(scores, np.float32), np.array(cids))
        assert len(spool) == len(frames)
        for i in reversed(range(len(frames))):  # any order
            boxes, scores, cids = spool.get(i)
            want_boxes, want_scores, want_cids = frames[i]
            assert boxes.dtype == np.float32 and scores.dtype == np.float32 and cids.dtype == np.int64
            np.testing.assert_array_equal(boxes, np.array(want_boxes, np.float32).reshape(-1, 4))
            np.testing.assert_array_equal(scores, np.array(want_scores, np.float32))
            np.testing.assert_array_equal(cids, np.array(want_cids, np.int64))
            boxes[:] = 0  # fresh arrays: writable, and the spool keeps its copy
        assert spool.nbytes == 28 * sum(len(f[1]) for f in frames)
    finally:
        spool.close()


def test_the_spool_refuses_candidates_that_disagree_in_length(tmp_path):
    spool = CandidateSpool(tmp_path)
    try:
        with pytest.raises(ValueError, match="3 boxes, 2 scores, 3 class ids"):
            spool.add(np.zeros((3, 4)), np.zeros(2), np.zeros(3))
        assert len(spool) == 0 and spool.nbytes == 0
        spool.add(np.zeros((1, 4)), np.ones(1), np.zeros(1))
        assert spool.get(0)[1].tolist() == [1.0]
    finally:
        spool.close()
    assert list(tmp_path.iterdir()) == []  # unnamed: nothing left behind


def test_dataset_files_make_the_output_a_dataset_that_track_reads_as_detect_tracked_it(flight, tmp_path):
    out = tmp_path / "out"
    summary = _detect(flight, out, "--dataset-files")
    assert {Path(summary["files"][k]).name for k in ("candidates", "camera")} == {"pre_nms.json", "camera.json"}
    candidates = json.loads((out / "pre_nms.json").read_text())
    images = json.loads((out / "images.json").read_text())["images"]
    assert len(candidates) == summary["candidates"]  # every pre-NMS candidate, not only the kept ones
    assert {c["image_id"] for c in candidates} <= {im["id"] for im in images}
    assert json.loads((out / "camera.json").read_text())["fx"] == pytest.approx(500.0)
    # the directory is a dataset: uavmm track reads it (no detector) and finds the objects detect found
    assert main(["track", "--frames", str(out / "images.json"), "--candidates", str(out / "pre_nms.json"),
                 "--camera", str(out / "camera.json"), "--out", str(tmp_path / "again.txt")]) == 0
    again = {int(line.split(",")[1]) for line in (tmp_path / "again.txt").read_text().splitlines()}
    assert len(again) <= 12 and abs(len(again) - len(_track_ids(out))) <= 2


def test_dataset_files_never_overwrite_an_input(flight, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    camera = out / "camera.json"
    camera.write_text(flight.camera.read_text())
    args = ["detect", str(flight.video), "--telemetry", str(flight.telemetry), "--model", str(flight.model),
            "--camera", str(camera), "--out", str(out), "--quiet"]
    assert main([*args, "--dataset-files"]) == 2
    assert "camera.json" in capsys.readouterr().err
    assert camera.read_text() == flight.camera.read_text()
    assert main([*args, "--max-frames", "3"]) == 0  # without the flag nothing writes camera.json


def test_the_progress_lines_name_each_pass(flight, tmp_path, capsys):
    args = ["detect", str(flight.video), "--telemetry", str(flight.telemetry), "--model", str(flight.model),
            "--camera", str(flight.camera), "--max-frames", "20"]
    assert main([*args, "--out", str(tmp_path / "two")]) == 0
    err = capsys.readouterr().err.splitlines()
    first = [line for line in err if "(pass 1: detector)" in line]
    second = [line for line in err if "(pass 2: memory map, tracker)" in line]
    assert first and second and err.index(first[-1]) < err.index(second[0])
    assert first[-1].split(")")[1].strip().startswith("20/20 frames") and "20/20 frames" in second[-1]
    assert main([*args, "--out", str(tmp_path / "one"), "--one-pass"]) == 0
    err = capsys.readouterr().err
    assert "20/20 frames" in err and "pass 1" not in err and "pass 2" not in err
    # a one-frame run: its count never goes back, the second pass is announced all the same
    assert main([*args[:-1], "1", "--out", str(tmp_path / "single")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line.split(" frames")[0] for line in err if "1/1" in line] == [
        f"detect {flight.video.name} (pass 1: detector) 1/1", f"detect {flight.video.name} (pass 2: memory map, "
        "tracker) 1/1"]


def test_a_spool_that_cannot_be_written_says_where_and_what_does_without(tmp_path):
    # a full disk, as a file-size limit in a child process (SIGXFSZ ignored: the write fails with EFBIG)
    import subprocess
    import sys

    script = f"""
import resource, signal, sys
import numpy as np
from agent.offline.two_pass import CandidateSpool
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
spool = CandidateSpool({str(tmp_path)!r})
try:
    for _ in range(100):
        spool.add(np.zeros((50, 4)), np.ones(50), np.zeros(50))
except OSError as exc:
    print("ERROR", len(spool), exc)
    print("READ", spool.get(0)[1][:2].tolist())
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0, done.stderr
    error = next(line for line in done.stdout.splitlines() if line.startswith("ERROR"))
    assert str(tmp_path) in error and "--one-pass" in error
    frames = int(error.split()[1])
    assert 0 < frames < 100  # the frames before the failure stay readable
    assert "READ [1.0, 1.0]" in done.stdout


@pytest.mark.parametrize("signum, code", [(15, 143), (2, 130)])
def test_sigterm_or_ctrl_c_mid_run_leaves_no_file_behind(tmp_path, signum, code):
    # kill, timeout and service managers send SIGTERM: it unwinds as Ctrl-C does (the streamed outputs' hidden
    # temporaries removed); before, a SIGTERM left .detections.json.<pid>.tmp and the others in --out
    import signal
    import subprocess
    import sys
    import time

    flight = write_jump_flight(tmp_path / "long", seconds=90.0, jumps=(20.0, 50.0))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "uavmm", "detect", str(flight.video), "--telemetry",
                             str(flight.telemetry), "--model", str(flight.model), "--camera", str(flight.camera),
                             "--out", str(out), "--render-video", "--dataset-files"],
                            cwd=Path(__file__).resolve().parents[2], stderr=subprocess.PIPE, text=True,
                            # SIGINT at its default: a suite run in the background (nohup ... &) ignores it, and
                            # Python then installs no KeyboardInterrupt for it
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert proc.stderr is not None
        for line in proc.stderr:  # pass two writes the outputs as it goes: stop it there
            if "(pass 2" in line:
                break
        time.sleep(0.5)
        written = [p.name for p in out.iterdir()]
        assert proc.poll() is None and any(name.startswith(".") for name in written), written
        proc.send_signal(signal.Signals(signum))
        assert proc.wait(timeout=60) == code
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert list(out.iterdir()) == []


def test_a_run_without_dataset_files_removes_an_earlier_runs(flight, tmp_path, caplog):
    # review finding: the earlier run's pre_nms.json stayed beside the new images.json, a dataset of two runs
    out = tmp_path / "out"
    _detect(flight, out, "--dataset-files")
    assert (out / "pre_nms.json").is_file() and (out / "camera.json").is_file()
    summary = _detect(flight, out, "--max-frames", "40")
    assert summary["removed_stale"] == ["pre_nms.json", "camera.json"]
    assert not (out / "pre_nms.json").exists() and not (out / "camera.json").exists()
    assert "removed pre_nms.json and camera.json of an earlier run" in caplog.text
    assert "removed_stale" not in _detect(flight, out, "--max-frames", "40")  # nothing left to remove

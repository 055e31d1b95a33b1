"""`uavmm anomaly` on a small rendered dataset and its video: COCO results per frame, and one-line errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from uavmm.cli import main

FRAMES = 45  # 1.5 s at 30 fps: one telemetry record (held 1 s) does not cover it


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory):
    """sea at 320x180, images + MP4 + SRT/CSV."""
    out = tmp_path_factory.mktemp("anomaly") / "sea"
    assert main(["sim", "sea", "--out", str(out), "--frames", str(FRAMES), "--image-size", "320x180", "--render",
                 "--video", "--max-texture-px", "1024", "--quiet"]) == 0
    return out


def _video(rendered, suffix: str) -> str:
    name = json.loads((rendered / "images.json").read_text())["videos"][0]["name"]
    return str(rendered / f"{name}.{suffix}")


@pytest.mark.parametrize("method,memory", [("median", True), ("diff", False), ("autoencoder", True)])
def test_anomaly_writes_coco_regions_for_the_dataset_frames(rendered, tmp_path, capsys, method, memory):
    out = tmp_path / "rois.json"
    args = ["anomaly", "--frames", str(rendered / "images.json"), "--camera", str(rendered / "camera.json"),
            "--out", str(out), "--method", method, "--quiet"] + ([] if memory else ["--no-memory"])
    assert main(args) == 0
    rois = json.loads(out.read_text())
    ids = {im["id"] for im in json.loads((rendered / "images.json").read_text())["images"]}
    assert rois and {r["image_id"] for r in rois} <= ids
    for r in rois:
        assert r["category_id"] == 1 and r["category"] == "anomaly" and 0 < r["score"] <= 1
        x, y, w, h = r["bbox"]
        assert 0 <= x and 0 <= y and w > 0 and h > 0 and x + w <= 320 and y + h <= 180
    assert f"for {3 * FRAMES} frames" in capsys.readouterr().out


def test_anomaly_reads_a_video_with_its_telemetry(rendered, tmp_path):
    out = tmp_path / "rois.json"
    assert main(["anomaly", "--video", _video(rendered, "mp4"), "--telemetry", _video(rendered, "srt"),
                 "--camera", str(rendered / "camera.json"), "--out", str(out), "--method", "mean", "--quiet"]) == 0
    rois = json.loads(out.read_text())
    assert {r["image_id"] for r in rois} <= set(range(FRAMES)) and rois


def _error(capsys, args) -> str:
    assert main([*args, "--method", "mean"] if "--method" not in args else args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    return err


def test_anomaly_bad_input_is_one_line_and_exit_2(rendered, tmp_path, capsys):
    cam, out = str(rendered / "camera.json"), str(tmp_path / "rois.json")
    video, srt = _video(rendered, "mp4"), _video(rendered, "srt")
    frames = ["--frames", str(rendered / "images.json")]
    err = _error(capsys, ["anomaly", *frames, "--camera", cam, "--out", out, "--method", "nope"])
    assert "unknown anomaly method 'nope'; valid: autoencoder, diff, mean, median, mog2" in err
    not_video = tmp_path / "clip.mp4"
    not_video.write_text("not a video")
    err = _error(capsys, ["anomaly", "--video", str(not_video), "--telemetry", srt, "--camera", cam, "--out", out])
    assert "cannot be read by OpenCV" in err
    short = tmp_path / "short.srt"
    blocks = _read(srt).strip().split("\n\n")
    short.write_text(blocks[0] + "\n\n")  # one record: does not cover the video
    err = _error(capsys, ["anomaly", "--video", video, "--telemetry", str(short), "--camera", cam, "--out", out])
    assert "covers" in err and "the video" in err
    wide = tmp_path / "camera.json"
    wide.write_text(json.dumps({"width": 400, "height": 300, "fx": 300.0, "fy": 300.0, "cx": 200.0, "cy": 150.0}))
    err = _error(capsys, ["anomaly", "--video", video, "--telemetry", srt, "--camera", str(wide), "--out", out])
    assert "another aspect ratio" in err
    err = _error(capsys, ["anomaly", "--video", video, "--camera", cam, "--out", out])
    assert "--video needs --telemetry" in err
    moved = tmp_path / "copy"
    moved.mkdir()
    shutil.copy(rendered / "images.json", moved / "images.json")  # without its image files
    err = _error(capsys, ["anomaly", "--frames", str(moved / "images.json"), "--camera", cam, "--out", out])
    assert "is missing or cannot be read" in err
    assert not (tmp_path / "rois.json").exists()


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


def test_the_protocol_gives_recall_per_rate_and_false_alarm_persistence(rendered):
    from agent.anomaly import AnomalyConfig
    from sim.anomaly_eval import RATES, evaluate_dataset, format_report, summarise

    run = evaluate_dataset(rendered, AnomalyConfig(method="mean"), every=5)
    assert run["objects"] > 0 and run["frames"] == 3 * FRAMES
    for mode in ("frame", "memory"):
        hits = run[mode]["hits"]
        assert len(hits) == len(RATES) and all(0 <= h <= run["objects"] for h in hits)
        assert hits == sorted(hits)  # flagging more never finds less
    classes = run["classes"]  # the swimmers and the rendered buoys/boats, each with its own recall
    assert "swimmer" in classes and set(classes) <= {"swimmer", "buoy", "boat"}
    assert sum(c["objects"] for c in classes.values()) == run["objects"]
    for mode in ("frame", "memory"):
        assert np.allclose(np.sum([c[mode]["hits"] for c in classes.values()], axis=0), run[mode]["hits"], atol=0.01)
    kept, transient = run["persistence"]["kept"], run["persistence"]["transient"]
    assert 0 <= kept <= 100 and 0 <= transient <= 100 and kept + transient <= 100
    summary = summarise([run])
    report = {"rates": list(RATES), "seeds": [0], "frames": FRAMES, "image_size": [320, 180],
              "results": {"sea": {"mean": {**summary, "objects": run["objects"]}}}}
    assert f"| mean | {summary['frame']['AR']} | {summary['memory']['AR']} |" in format_report(report)


def test_flags_that_do_not_apply_and_a_folder_as_out_are_refused_at_the_start(rendered, tmp_path, capsys):
    """Audit findings: `--height-m` beside `--frames` was silently ignored; `--out` naming a folder ran the whole
    video and failed at the end, leaving a temporary file."""
    cam = str(rendered / "camera.json")
    frames = ["--frames", str(rendered / "images.json")]
    err = _error(capsys, ["anomaly", *frames, "--camera", cam, "--out", str(tmp_path / "r.json"), "--height-m", "30"])
    assert "--height-m goes with --video" in err
    folder = tmp_path / "out"
    folder.mkdir()
    err = _error(capsys, ["anomaly", *frames, "--camera", cam, "--out", str(folder)])
    assert "is a directory" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and not any(folder.iterdir())


@pytest.mark.parametrize("signame, code", [("SIGINT", 130), ("SIGTERM", 143)])  # Ctrl-C; kill, timeout
def test_regions_are_written_as_they_come_and_ctrl_c_keeps_those_of_the_frames_done(rendered, tmp_path, signame, code):
    """Audit finding: every region was held to the end (an hour at 100 a frame: ~4 GiB), and Ctrl-C lost them all.
    The file is written as the frames come (the same bytes as the whole list dumped at once, checked on a full
    run) and an interrupted run puts what it has in place."""
    import os
    import signal
    import subprocess
    import sys
    import time

    whole = tmp_path / "whole.json"
    args = ["anomaly", "--frames", str(rendered / "images.json"), "--camera", str(rendered / "camera.json"),
            "--method", "mean", "--quiet"]
    assert main([*args, "--out", str(whole)]) == 0
    rois = json.loads(whole.read_text())
    assert rois and whole.read_text() == json.dumps(rois)
    # a slow run (many copies of the frames): interrupted once its first regions are on disk
    many = tmp_path / "many"
    many.mkdir()
    coco = json.loads((rendered / "images.json").read_text())
    for im in coco["images"]:
        (many / im["file_name"]).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(rendered / im["file_name"], many / im["file_name"])
    coco.pop("videos", None)  # 40 copies of each video, as videos of their own
    coco["images"] = [{**im, "id": k * 10_000 + im["id"], "video_id": k * 100 + im["video_id"]}
                      for k in range(40) for im in coco["images"]]
    (many / "images.json").write_text(json.dumps(coco))
    out = tmp_path / "partial.json"
    cmd = [sys.executable, "-m", "uavmm.cli", "anomaly", "--frames", str(many / "images.json"), "--camera",
           str(rendered / "camera.json"), "--method", "mean", "--out", str(out)]
    # SIGINT at its default in the child: a suite run in the background (nohup ... &) ignores it, and Python then
    # installs no KeyboardInterrupt for Ctrl-C
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    def spool_size() -> int:  # the results' hidden temporary beside the output (.partial.json.PID.tmp)
        sizes = [0]
        for path in tmp_path.glob(".partial.json.*.tmp"):
            try:
                sizes.append(path.stat().st_size)
            except FileNotFoundError:  # renamed into place meanwhile
                pass
        return max(sizes)

    deadline = time.monotonic() + 120
    while spool_size() <= 1000 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(getattr(signal, signame))
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    partial = json.loads(out.read_text())
    assert partial and "stopped: wrote" in err and not list(tmp_path.glob(".partial.json.*"))
    assert {r["image_id"] for r in partial} < {im["id"] for im in coco["images"]}


def test_progress_in_a_pipe_is_lines_not_carriage_returns(rendered, tmp_path, capsys):
    # the docs walk-through (1 Dec 2026): "\ranomaly: 50 frames\ranomaly: 100 frames..." on one line in a log file;
    # now as uavmm detect's progress: redrawn on a terminal only, lines elsewhere
    out = tmp_path / "rois.json"
    assert main(["anomaly", "--frames", str(rendered / "images.json"), "--camera", str(rendered / "camera.json"),
                 "--out", str(out), "--method", "median"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and "anomaly: 1 frames" in err

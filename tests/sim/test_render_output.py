"""`render_dataset`'s files under failure: written whole (a full disk, Ctrl-C), an earlier render's mark of
completeness gone before the first new frame, temporaries that are new names and only its own, an unwritable folder
or an oversized camera refused in one line before the drawing."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import sim.render.output as output_module
from sim.dataset import write_dataset
from sim.render import RenderOptions, WorldRenderer, render_dataset
from sim.scenarios import get_scenario

REPO = Path(__file__).resolve().parents[2]
OPTIONS = RenderOptions(max_texture_px=256)


def _dataset(tmp_path: Path, frames: int = 3, size: tuple[int, int] = (320, 180)) -> Path:
    out = tmp_path / "data"
    write_dataset(dataclasses.replace(get_scenario("grass"), image_size=size), out, frames=frames, progress=False)
    return out


def _full_disk(limit_bytes: int):
    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return limit


def test_a_full_disk_leaves_no_cut_image_and_no_mark_of_a_complete_render(tmp_path):
    """Probe: a re-render on a full disk left JPEGs cut at the limit under their final names, and the earlier
    render.json that marks a complete render."""
    data = _dataset(tmp_path)
    render_dataset(data, options=OPTIONS, progress=False)
    jpegs = sorted(data.rglob("*.jpg"))
    limit = min(p.stat().st_size for p in jpegs) // 2
    run = subprocess.run([sys.executable, "-m", "uavmm.cli", "render", str(data), "--quiet", "--max-texture-px", "256",
                          "--sensor-noise", "6"], cwd=REPO, capture_output=True, text=True, timeout=120,
                         preexec_fn=_full_disk(limit))
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line.startswith("uavmm render: error: cannot write image ") and ".tmp" not in line, line
    assert [p for p in jpegs if p.stat().st_size == limit] == []
    assert not (data / "render.json").exists() and not (data / "unannotated.json").exists()
    assert [p.name for p in data.rglob(".*")] == []  # no temporary left


def test_an_interrupted_render_does_not_look_complete_and_removes_only_its_own_temporaries(tmp_path, monkeypatch):
    """Probe: Ctrl-C during a re-render with other options left the earlier render.json over a mix of old and new
    frames; a failed render deleted every .*.tmp.mp4 in the folder, another writer's (`uavmm detect`) too."""
    data = _dataset(tmp_path)
    render_dataset(data, video=True, options=OPTIONS, progress=False)
    other = data / ".annotated.k3j2.tmp.mp4"
    other.write_bytes(b"another run's video")
    real_render, calls = WorldRenderer.render, {"n": 0}

    def interrupted(self, frame, drift=None):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real_render(self, frame, drift)

    monkeypatch.setattr(WorldRenderer, "render", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_dataset(data, video=True, options=dataclasses.replace(OPTIONS, sensor_noise_std=0.0), progress=False)
    assert not (data / "render.json").exists()
    assert other.read_bytes() == b"another run's video"
    assert sorted(p.name for p in data.iterdir() if p.name.startswith(".")) == [other.name]


def test_links_planted_at_temporary_names_are_not_written_through(tmp_path):
    """Probe: links at .<video>.tmp.mp4 and .render.json.tmp had the MP4 and render.json written into their
    targets (and the link moved to <video>.mp4)."""
    data = _dataset(tmp_path, frames=2, size=(64, 36))
    victims = {}
    for name in (".grass_01_orbit_uav1.tmp.mp4", ".render.json.tmp", f".render.json.{os.getpid()}.tmp"):
        victim = tmp_path / f"victim{len(victims)}"
        victim.write_text("precious")
        (data / name).symlink_to(victim)
        victims[name] = victim
    render_dataset(data, images=False, video=True, options=OPTIONS, progress=False)
    assert all(v.read_text() == "precious" for v in victims.values())
    assert not (data / "grass_01_orbit_uav1.mp4").is_symlink() and not (data / "render.json").is_symlink()


def test_an_unwritable_folder_is_one_line_before_the_ground_is_made(tmp_path):
    """Probe: a read-only dataset folder failed only after the ground set-up (6 s at 640x360, more at 4K), naming a
    temporary file (`.NAME.tmp.mp4`) the user never gave."""
    if os.geteuid() != 0 or subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode != 0:
        pytest.skip("needs root and unshare -m for a read-only mount")
    data = _dataset(tmp_path, frames=2, size=(64, 36))
    script = ('mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && '
              f'exec "{sys.executable}" -c "import sys, sim.render.renderer as r; '
              "r.WorldRenderer.__init__ = lambda *a, **k: sys.exit('ground set up'); "
              "from uavmm.cli import main; sys.exit(main(['render', sys.argv[1], '--video', '--quiet']))\" \"$1\"")
    run = subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", str(data)], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert line == f"uavmm render: error: cannot write in the dataset directory {data}: Read-only file system"


def test_a_camera_over_the_renderers_limit_is_refused_before_drawing(tmp_path):
    """Probe: a dataset simulated at 100000x100000 (possible without --render) made `uavmm render` end in a
    224 GiB MemoryError traceback, exit 1."""
    data = _dataset(tmp_path, frames=1, size=(100_000, 100_000))
    with pytest.raises(ValueError, match="the dataset's camera is 100000x100000: the renderer draws at most 8192"):
        render_dataset(data, options=OPTIONS, progress=False)


def test_images_are_written_whole_through_shared_files(tmp_path, monkeypatch):
    """Every image file is written whole (a new temporary renamed into place: a kill leaves no cut file under the
    image's name), never straight to its name."""
    data = _dataset(tmp_path, frames=1, size=(64, 36))
    written = []
    real = output_module.write_chunks_atomic
    monkeypatch.setattr(output_module, "write_chunks_atomic",
                        lambda path, chunks: (written.append(path), real(path, chunks)))
    summary = render_dataset(data, options=OPTIONS, progress=False)
    assert sum(p.suffix == ".jpg" for p in written) == summary["images"] == 4


@pytest.mark.parametrize("file_name", ["{tmp}/escaped.jpg", "../outside/victim.jpg", "v/../../victim.jpg"])
def test_an_image_file_name_leaving_the_dataset_directory_is_refused_before_drawing(tmp_path, file_name):
    """Probe: images.json's file_name "/tmp/hD/escaped.jpg" or "../outside/victim.jpg" had `uavmm render` write
    (over) files outside the dataset directory, exit 0."""
    data = _dataset(tmp_path, frames=1, size=(64, 36))
    file_name = file_name.format(tmp=tmp_path)
    coco = json.loads((data / "images.json").read_text())
    coco["images"][1]["file_name"] = file_name
    (data / "images.json").write_text(json.dumps(coco))
    with pytest.raises(ValueError, match=f"image 2's file_name '{re.escape(file_name)}' in images.json leaves the"):
        render_dataset(data, options=OPTIONS, progress=False)
    assert not (data / "grass_01_orbit_uav1").exists()  # refused before the first image


def test_videos_without_images_say_that_an_earlier_renders_frames_stay(tmp_path, caplog):
    """--video --no-images keeps the frames an earlier render drew (perhaps with other options; render.json then
    counts 0 images): said in a warning, the frames left as they are."""
    data = _dataset(tmp_path, frames=2)
    render_dataset(data, options=OPTIONS, progress=False)
    frames = sorted(p for p in data.rglob("*.jpg"))
    before = [p.read_bytes() for p in frames]
    with caplog.at_level(logging.WARNING, logger="sim.render.output"):
        render_dataset(data, images=False, video=True, options=OPTIONS, progress=False)
    assert any(f"holds {len(frames)} frames of an earlier render" in r.getMessage() for r in caplog.records)
    assert [p.read_bytes() for p in frames] == before
    caplog.clear()
    fresh = _dataset(tmp_path / "fresh", frames=2)
    with caplog.at_level(logging.WARNING, logger="sim.render.output"):
        render_dataset(fresh, images=False, video=True, options=OPTIONS, progress=False)
    assert not [r for r in caplog.records if "earlier render" in r.getMessage()]


def test_a_killed_renders_temporaries_are_removed_by_the_next_render_and_said_in_one_line(tmp_path):
    """Probe: a SIGKILL during `uavmm render --video` left `.<video>.mp4.PID.tmp.mp4` (the whole video so far) and
    `<video>/.000024.jpg.PID.tmp`; every later render left them there. Now the next render removes the temporaries
    of this dataset's files whose process is gone, says so in one line, and leaves a live render's and anyone
    else's."""
    data = _dataset(tmp_path, frames=2, size=(64, 36))
    video = json.loads((data / "images.json").read_text())["videos"][0]["name"]
    killed = subprocess.run([sys.executable, "-c", (
        "import os, signal, sys; from pathlib import Path; from shared.files import new_temporary\n"
        "data, video = Path(sys.argv[1]), sys.argv[2]\n"
        "for path, suffix in ((data / f'{video}.mp4', '.tmp.mp4'), (data / f'{video}.mp4', '.tmp.mp4'),\n"
        "                     (data / f'{video}.srt', '.tmp'), (data / 'render.json', '.tmp'),\n"
        "                     (data / video / '000000.jpg', '.tmp'), (data / 'annotated.mp4', '.tmp.mp4')):\n"
        "    path.parent.mkdir(exist_ok=True)\n"
        "    print(new_temporary(path, suffix=suffix)[0].relative_to(data), flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)"), str(data), video], cwd=REPO, capture_output=True, text=True,
        timeout=60)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    *ours, detects = killed.stdout.split()  # the last: another command's (uavmm detect's annotated video)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        kept = [data / detects, data / f".{video}.mp4.{live.pid}.tmp.mp4", data / "notes.mp4.7.tmp",
                data / f".{video}.mp4.0{live.pid}.tmp.mp4"]  # another's, a live render's, not hidden, zero-padded
        for path in kept[1:]:
            path.write_bytes(b"not the killed render's")
        run = subprocess.run([sys.executable, "-m", "uavmm.cli", "render", str(data), "--video", "--quiet",
                              "--max-texture-px", "256"], cwd=REPO, capture_output=True, text=True, timeout=120)
    finally:
        live.kill()
        live.wait()
    assert run.returncode == 0, run.stderr
    (line,) = run.stderr.strip().splitlines()
    assert f"removed {len(ours)} temporary file(s) of earlier renders in {data} that were killed" in line, line
    assert sum(name in line for name in ours) == 4 and line.endswith("and 1 more"), line  # the first four named
    assert not [name for name in ours if (data / name).exists()]
    assert all(path.exists() for path in kept)


@pytest.mark.parametrize("name", ["../outside", "sub/../../victim", "{tmp}/escaped", "a\\b", " "])
def test_a_video_name_that_is_not_a_plain_file_name_is_refused_before_drawing(tmp_path, name):
    """Probe: a video's name "../outside" in images.json had `uavmm render --video` write outside.mp4 (and its SRT /
    CSV) beside the dataset directory."""
    data = _dataset(tmp_path, frames=1, size=(64, 36))
    name = name.format(tmp=tmp_path)
    coco = json.loads((data / "images.json").read_text())
    coco["videos"][0]["name"] = name
    (data / "images.json").write_text(json.dumps(coco))
    with pytest.raises(ValueError, match=f"video 1's name {re.escape(repr(name))} in images.json is not a plain"):
        render_dataset(data, video=True, options=OPTIONS, progress=False)
    assert not list(tmp_path.rglob("*.mp4")) and not list(tmp_path.rglob("*.jpg"))


def test_an_interrupt_while_waiting_for_the_encoder_releases_the_video_only_after_its_last_write(tmp_path, monkeypatch):
    """Review finding: the render popped a frame's encoding off its queue before waiting for it, so an interrupt in
    that wait (Ctrl-C; SIGTERM since it unwinds the same way) left it out of the drain and released the video
    writer while the encoder thread was still writing to it: a segfault in 1 run of 5, its temporary left behind."""
    import threading
    import time
    import types

    import cv2

    data = _dataset(tmp_path, frames=12)
    events: list[str] = []

    class SlowWriter:  # OpenCV's writer, slowed down: the render's queue fills and it waits on the encoder
        def __init__(self, *args):
            self._writer = cv2.VideoWriter(*args)
            self.writing = False

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return self._writer.isOpened()

        def write(self, image):
            if not events:  # the first frame: the queue fills within a few frames, then the render waits on it
                events.append("writing")
                threading.Timer(0.9, lambda: signal.pthread_kill(main_id, signal.SIGUSR1)).start()
            self.writing = True
            time.sleep(0.3)
            self._writer.write(image)
            self.writing = False

        def release(self):
            events.append("release while writing" if self.writing else "release after the last write")
            self._writer.release()

    shim = types.SimpleNamespace(**{name: getattr(cv2, name) for name in dir(cv2) if not name.startswith("_")})
    shim.VideoWriter = type("VideoWriter", (), {"__new__": lambda cls, *a: SlowWriter(*a),
                                                "fourcc": staticmethod(cv2.VideoWriter.fourcc)})
    monkeypatch.setattr(output_module, "cv2", shim)

    def interrupt(_signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGUSR1, interrupt)  # a signal of our own: SIGINT may be ignored (nohup)
    main_id = threading.get_ident()
    try:
        with pytest.raises(KeyboardInterrupt):
            render_dataset(data, video=True, images=False, options=OPTIONS, progress=False)
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert events == ["writing", "release after the last write"]
    assert not [p.name for p in data.iterdir() if p.name.startswith(".")]

"""Render a simulated dataset directory to files: the images named in images.json, MP4 videos, telemetry.

`render_dataset(directory)` draws every frame (`sim.render.renderer.WorldRenderer`) and writes
- the image files under the dataset directory at each image's ``file_name`` (JPEG), unless ``images=False``;
- with ``video=True``, per video ``<name>.mp4`` (MPEG-4 Part 2, OpenCV's ``mp4v``, the scenario's fps) and its
  telemetry as ``<name>.srt`` (DJI style) and ``<name>.csv`` (`sim.render.telemetry_files`), so that
  ``uavmm agent --video <name>.mp4 --telemetry <name>.srt --camera camera.json --model M.onnx`` plays it;
- ``unannotated.json``: per image the boxes of the drawn objects images.json does not annotate (buoys and boats
  on the sea; rocks, trees and cars on the meadow): ``{"annotations": [{image_id, kind, bbox}]}``, bbox
  [x, y, w, h] pixels (the anomaly evaluation counts boats and buoys as anomalies, `sim.anomaly_eval`);
- ``render.json``: the options, each world's ground, sun, atmosphere and unannotated scenery (boats, cars),
  the files written and the measured speed. It is written last: its presence marks a complete render (an earlier
  render's render.json and unannotated.json are removed before the first frame is written, so a render that fails
  or is interrupted never leaves a folder that looks complete).

Every file is written whole (`shared.files`: a new hidden temporary beside it, renamed into place): a full disk,
an error or Ctrl-C never leaves a cut image or video under its final name, and the temporaries are new names (never
a file or a link already there, never another writer's). A render killed outright (SIGKILL) leaves its temporaries;
the next render in the folder removes those whose process is gone, and says so in one log line.

Encoding runs on a background thread (OpenCV releases the GIL) while the next frame is drawn.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import tempfile
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from shared.files import listed_names, new_temporary, stale_temporaries, sync_to_disk, write_chunks_atomic
from sim.dataset import RENDER_FILES, _Progress
from sim.render.renderer import RenderOptions, WorldRenderer, exposure_for
from sim.render.scene import SimulatedDataset
from sim.render.telemetry_files import format_csv, format_srt, frame_records
from sim.scenarios import MAX_IMAGE_SIDE_PX

logger = logging.getLogger(__name__)

#: Frames that may wait for the encoder thread before drawing pauses.
_MAX_PENDING = 4
#: FOURCC of the MP4 videos (MPEG-4 Part 2: encoded and decoded by OpenCV's bundled FFmpeg everywhere).
MP4_FOURCC = "mp4v"


def _check_quality(jpeg_quality: int) -> None:
    if isinstance(jpeg_quality, bool) or not isinstance(jpeg_quality, int) or not 1 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be an integer in 1..100, got {jpeg_quality!r}")


def _write_image(path: Path, image: np.ndarray, params: list[int]) -> None:
    """Encode (by ``path``'s suffix, JPEG without one) and write the file whole (`shared.files`)."""
    ok, data = cv2.imencode(path.suffix or ".jpg", image, params)
    if not ok:
        raise OSError(f"OpenCV cannot encode {path}")
    write_chunks_atomic(path, [data.tobytes()])


def _check_writable(out: Path) -> None:
    """OSError naming the folder when no file can be created in it (read-only, no permission): before the ground
    set-up, seconds to minutes a world, is spent. The probe is a new name, never a link planted there."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".uavmm-write-test-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OSError(f"cannot write in the dataset directory {out}: {exc.strerror or exc}") from None


def _check_file_names(dataset: SimulatedDataset) -> None:
    """ValueError naming the image when a ``file_name`` in images.json is missing, absolute or climbs out with
    ``..``: checked before the drawing, and no image is written outside the dataset directory."""
    for image_id, im in dataset.images.items():
        name = str(im.get("file_name") or "")
        if not name:
            raise ValueError(f"image {image_id} has no file_name in images.json")
        if PurePosixPath(name).is_absolute() or ".." in PurePosixPath(name).parts:
            raise ValueError(f"image {image_id}'s file_name {name!r} in images.json leaves the dataset directory "
                             f"{dataset.directory}: images are written inside it only")


def _check_video_names(dataset: SimulatedDataset) -> None:
    """ValueError naming the video when its name in images.json is not one plain file name (empty, a path with
    ``/`` or ``\\``, ``.`` or ``..``): the MP4 and its SRT / CSV telemetry are ``<name>.mp4`` etc. in the dataset
    directory, never elsewhere. Checked before the drawing."""
    for v in dataset.videos:
        if not v.name.strip() or "/" in v.name or "\\" in v.name or v.name in (".", ".."):
            raise ValueError(f"video {v.id}'s name {v.name!r} in images.json is not a plain file name: its MP4 and "
                             f"telemetry are written as <name>.mp4, .srt and .csv inside {dataset.directory} only")


def _remove_dead_renders_temporaries(dataset: SimulatedDataset) -> None:
    """Remove the temporaries of renders killed in this folder (SIGKILL, a power cut): `shared.files.new_temporary`
    names of this dataset's MP4s, telemetry, render files and images whose process is gone, which nobody else ever
    removes; a live render's (another process in the folder) and every other file stay. One log line says so."""
    out = dataset.directory
    stale = stale_temporaries(out, {f"{v.name}.mp4" for v in dataset.videos}, suffix=".tmp.mp4")
    stale += stale_temporaries(out, {f"{v.name}.{ext}" for v in dataset.videos for ext in ("srt", "csv")}
                               | set(RENDER_FILES))
    image_names: dict[Path, set[str]] = {}
    for im in dataset.images.values():
        name = PurePosixPath(str(im.get("file_name") or ""))
        if name.name and not name.is_absolute() and ".." not in name.parts:  # only names inside the folder
            image_names.setdefault(out / name.parent, set()).add(name.name)
    for folder, names in image_names.items():
        stale += stale_temporaries(folder, names)
    removed = []
    for path in stale:
        try:
            path.unlink()
        except FileNotFoundError:  # another render removed it first
            continue
        except OSError as exc:
            raise OSError(f"cannot remove {path}, a temporary of a killed render: {exc.strerror or exc}") from None
        removed.append(str(path.relative_to(out)))
    if removed:
        logger.warning("removed %d temporary file(s) of earlier renders in %s that were killed before they finished: "
                       "%s", len(removed), out, listed_names(removed))


def _forget_previous_render(out: Path) -> None:
    """Remove an earlier render's render.json (the mark of a complete render) and unannotated.json, so a render that
    fails or is interrupted does not leave old marks over a mix of old and new frames."""
    for name in reversed(RENDER_FILES):  # the mark first
        try:
            (out / name).unlink(missing_ok=True)
        except OSError as exc:
            raise OSError(f"cannot remove the earlier render's {out / name}: {exc.strerror or exc}") from None


def render_dataset(directory: str | Path, *, images: bool = True, video: bool = False,
                   options: RenderOptions | None = None, jpeg_quality: int = 90,
                   progress: bool = True) -> dict[str, Any]:
    """Render every frame of a simulated dataset directory.

    Parameters
    ----------
    directory : path
        Written by `uavmm sim` (images.json, camera.json, truth.json).
    images : bool
        Write each image at its ``file_name`` (folders are created; existing files are replaced, each file whole).
    video : bool
        Write ``<video name>.mp4``, ``.srt`` and ``.csv`` per video.
    options : RenderOptions, optional
    jpeg_quality : int
        1..100 for the image files.
    progress : bool
        A progress bar on stderr (only when stderr is a terminal).

    Returns
    -------
    dict
        Summary: ``directory, frames, images, videos (paths), telemetry (paths), width, height, worlds, seconds``
        (all), ``setup_s`` (generating the worlds' ground), ``frames_per_s`` (drawing and encoding after the
        set-up) and ``draw_frames_per_s`` (drawing alone).

    Raises
    ------
    ValueError
        Not a simulated dataset (one line, see `SimulatedDataset`), nothing to write, a bad option, a camera
        wider or higher than `sim.scenarios.MAX_IMAGE_SIDE_PX`.
    OSError
        The directory or a file cannot be written (the message names it; the directory is checked before any
        drawing). render.json and unannotated.json of an earlier render are gone then, the frames written so far
        are whole files.
    """
    if not images and not video:
        raise ValueError("nothing to render: ask for images, video or both")
    _check_quality(jpeg_quality)
    options = options if options is not None else RenderOptions()
    started = time.perf_counter()
    dataset = SimulatedDataset(directory)
    out = dataset.directory
    cam = dataset.camera
    if video and (cam.width % 2 or cam.height % 2):
        raise ValueError(f"MP4 needs an even image size, the dataset's camera is {cam.width}x{cam.height}")
    if max(cam.width, cam.height) > MAX_IMAGE_SIDE_PX:
        raise ValueError(f"the dataset's camera is {cam.width}x{cam.height}: the renderer draws at most "
                         f"{MAX_IMAGE_SIDE_PX} pixels a side")
    if images:
        _check_file_names(dataset)
    else:
        _warn_earlier_images(dataset)
    if video:
        _check_video_names(dataset)
    _check_writable(out)
    _remove_dead_renders_temporaries(dataset)
    _forget_previous_render(out)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    total = sum(len(v.image_ids) for v in dataset.videos)
    bar = _Progress(f"render {dataset.scenario}", total, progress)
    written_images, videos, telemetry, worlds = 0, [], [], []
    unannotated: list[dict[str, Any]] = []
    draw_s = setup_s = 0.0
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="uavmm-render-encode")
    pending: deque[Future] = deque()
    temporaries: list[Path] = []  # this render's MP4s being written: removed on failure, nobody else's
    done = 0
    try:
        for group in sorted(dataset.worlds):
            t_setup = time.perf_counter()
            renderer = WorldRenderer(dataset, dataset.worlds[group], options)
            setup_s += time.perf_counter() - t_setup
            worlds.append(renderer.describe())
            for v in renderer.videos:
                writer = None
                if video:
                    tmp_mp4, fd = new_temporary(out / f"{v.name}.mp4", suffix=".tmp.mp4")  # OpenCV opens it by name
                    os.close(fd)
                    temporaries.append(tmp_mp4)
                    writer = cv2.VideoWriter(str(tmp_mp4), cv2.VideoWriter.fourcc(*MP4_FOURCC), dataset.fps,
                                             (cam.width, cam.height))
                    if not writer.isOpened():
                        raise OSError(f"OpenCV cannot write an MP4 video at {out / f'{v.name}.mp4'}")
                drift = exposure_for(dataset, v)
                frame_meta = []
                try:
                    for frame in dataset.frames(v):
                        t0 = time.perf_counter()
                        image = renderer.render(frame, drift)
                        draw_s += time.perf_counter() - t0
                        frame_meta.append((frame.frame_index, frame.t, frame.meta))
                        unannotated.extend({"image_id": frame.image_id, "kind": kind, "bbox": box}
                                           for kind, box in renderer.unannotated_boxes(frame))
                        path = out / frame.file_name if images and frame.file_name else None
                        if images and path is None:
                            raise ValueError(f"image {frame.image_id} has no file_name in images.json")
                        pending.append(pool.submit(_encode, image, path, params, writer))
                        written_images += path is not None
                        while len(pending) > _MAX_PENDING:
                            # queued until done: an interrupt (Ctrl-C, SIGTERM) in result() leaves it to _drain,
                            # which waits for the encoder before the writer is released (popped first, a SIGTERM
                            # released it mid-write: a segfault, 1 run in 5)
                            pending[0].result()
                            pending.popleft()
                        done += 1
                        bar.update(done)
                    while pending:
                        pending[0].result()
                        pending.popleft()
                finally:
                    _drain(pending)  # the encoder thread must be done with the writer before it is released
                    if writer is not None:
                        writer.release()
                if video:
                    mp4 = out / f"{v.name}.mp4"
                    _flush_to_disk(tmp_mp4)
                    os.replace(tmp_mp4, mp4)
                    temporaries.remove(tmp_mp4)
                    videos.append(str(mp4))
                    records = frame_records(frame_meta)
                    srt, csv_path = out / f"{v.name}.srt", out / f"{v.name}.csv"
                    _write_text(srt, format_srt(records, dataset.fps))
                    _write_text(csv_path, format_csv(records, frame_meta[0][1]))
                    telemetry.extend([str(srt), str(csv_path)])
            del renderer
        bar.close()
    except BaseException:
        bar.close()
        pool.shutdown(wait=True)  # the encoder thread is done with the writer before its file goes
        for tmp in temporaries:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        pool.shutdown(wait=True)
    seconds = time.perf_counter() - started
    streaming_s = seconds - setup_s
    summary = {
        "directory": str(out), "frames": done, "images": written_images, "videos": videos, "telemetry": telemetry,
        "width": cam.width, "height": cam.height, "worlds": len(worlds), "seconds": round(seconds, 3),
        "setup_s": round(setup_s, 3),
        "frames_per_s": round(done / streaming_s, 2) if streaming_s > 0 else None,
        "draw_frames_per_s": round(done / draw_s, 2) if draw_s > 0 else None,
    }
    report = {"options": dataclasses.asdict(options), "jpeg_quality": jpeg_quality, "mp4_fourcc": MP4_FOURCC,
              "worlds": worlds, "summary": summary}
    _write_text(out / "unannotated.json", json.dumps({"annotations": unannotated}))
    _write_text(out / "render.json", json.dumps(report, indent=1))
    logger.info("rendered %s: %s", out, summary)
    return summary


def _drain(pending: deque[Future]) -> None:
    """Wait for every queued encoding (after an error: their own errors are secondary and dropped)."""
    while pending:
        future = pending.popleft()
        if not future.cancel():
            try:
                future.result()
            except Exception:  # noqa: BLE001 - the first error is already propagating
                logger.debug("encoding after an error failed too", exc_info=True)


def _encode(image: np.ndarray, path: Path | None, params: list[int], writer: cv2.VideoWriter | None) -> None:
    """Write one frame: the image file and/or the next video frame (runs on the encoder thread)."""
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            _write_image(path, image, params)
        except OSError as exc:
            raise OSError(f"cannot write image {path}: {exc.strerror or exc}") from exc
    if writer is not None:
        writer.write(image)


def _warn_earlier_images(dataset: SimulatedDataset) -> None:
    """A render without images (``--no-images``) leaves an earlier render's frames where they are: say so, since
    they may have been drawn with other options than the videos now are (render.json then counts 0 images)."""
    names = [str(im.get("file_name") or "") for im in dataset.images.values()]
    kept = sum(1 for name in names if name and not PurePosixPath(name).is_absolute()
               and ".." not in PurePosixPath(name).parts and (dataset.directory / name).is_file())
    if kept:
        logger.warning("%s holds %d frames of an earlier render: --no-images leaves them as they are (they may show "
                    "other render options than the new videos); render with images to redraw them", dataset.directory,
                    kept)


def _flush_to_disk(path: Path) -> None:
    """fsync a finished file before it is renamed into place (as `shared.files.PendingFile.commit` does)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        sync_to_disk(fd)
    finally:
        os.close(fd)


def _write_text(path: Path, text: str) -> None:
    """Write ``text`` whole (`shared.files`); OSError naming ``path``."""
    try:
        write_chunks_atomic(path, [text])
    except OSError as exc:
        raise OSError(f"cannot write {path}: {exc.strerror or exc}") from exc

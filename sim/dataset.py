"""Write a simulated scenario as a SeaDronesSee-compatible dataset (DESIGN.md 6).

Files: ``images.json`` (COCO ground truth with per-image SeaDronesSee ``meta`` from the noisy telemetry and
the true ``lat``/``lon`` of every annotation), ``camera.json``, ``pre_nms.json`` (all detector candidates)
and ``truth.json`` (true poses, scenario settings, realised telemetry biases, occlusion facts), and over a
terrain ``dem.npz`` (the terrain, `agent.dem`; truth.json's ``terrain`` gives the take-off's elevation). Files
are written to a temporary folder first and moved in only when everything succeeded; an earlier render's marks
(`RENDER_FILES`) go then, as they describe the frames of the dataset replaced.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from agent.dem import write_npz
from shared.files import listed_names
from sim.detector_emulator import EmulatorParams
from sim.noise import CLOCK_FIELDS, TelemetryNoise, format_time
from sim.scenarios import START_UNIX_S, Scenario
from sim.simulator import FrameSample, Simulation

logger = logging.getLogger(__name__)

DATASET_FILES = ("images.json", "camera.json", "pre_nms.json", "truth.json")
#: How the images.json `write_dataset` writes begins its info.description (`require_output_folder` replaces only such)
SIM_DESCRIPTION = "uav-memory-maps simulated scenario"
#: The terrain's DEM (agent.dem's .npz), written beside the dataset when the scenario has a terrain.
TERRAIN_DEM_FILE = "dem.npz"
#: What a render (`sim.render`) writes beside each video's image folder and <name>.mp4/.srt/.csv; render.json,
#: written last, marks a complete render.
RENDER_FILES = ("unannotated.json", "render.json")
#: Prefix of the temporary folder `write_dataset` writes in before moving the files in.
_TMP_PREFIX = ".sim-tmp-"


class _Progress:
    """A one-line progress bar on stderr, only when stderr is a terminal."""

    def __init__(self, label: str, total: int, enabled: bool) -> None:
        self.label, self.total = label, total
        self.enabled = enabled and sys.stderr.isatty()
        self._last = 0.0

    def update(self, done: int) -> None:
        now = time.monotonic()
        if not self.enabled or (now - self._last < 0.1 and done < self.total):
            return
        self._last = now
        width = 30
        filled = int(width * done / max(self.total, 1))
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] {done}/{self.total} frames")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            self.enabled = False
            sys.stderr.write("\n")
            sys.stderr.flush()


def _spec_dict(obj: Any) -> dict[str, Any]:
    d = dataclasses.asdict(obj)
    d["type"] = type(obj).__name__
    return d


def _emulator_dict(emulator: EmulatorParams) -> dict[str, Any]:
    """The emulator as truth.json writes it: the weakly seen objects' fields only when some are, so the datasets
    of scenarios without them stay byte-identical."""
    d = _spec_dict(emulator)
    if emulator.weak_fraction == 0.0:
        d.pop("weak_fraction")
        d.pop("weak_logit_drop")
    return d


def _noise_dict(noise: TelemetryNoise) -> dict[str, Any]:
    """The noise as truth.json writes it: the clock fields (`sim.noise.CLOCK_FIELDS`) only when they are not
    at their defaults, so the datasets of scenarios without them stay byte-identical."""
    d = _spec_dict(noise)
    default = TelemetryNoise()
    for name in CLOCK_FIELDS:
        if getattr(noise, name) == getattr(default, name):
            del d[name]
    return d


def existing_outputs(out: str | Path) -> tuple[list[str], list[str]]:
    """What a folder holds besides a dataset's own files (`DATASET_FILES`, `TERRAIN_DEM_FILE`): (render, other).

    render: an earlier render's outputs for the dataset there (`RENDER_FILES`, each video's image folder and
    ``<name>.mp4/.srt/.csv``, the video names read from its images.json); other: every other name, hidden ones
    too (an unreadable images.json names no video). Both sorted; ([], []) when the folder does not exist.
    """
    folder = Path(out)
    if not folder.is_dir():
        return [], []
    videos: set[str] = set()
    try:
        coco = json.loads((folder / "images.json").read_text())
        videos = {str(v["name"]) for v in coco.get("videos", [])}
        videos |= {str(im["file_name"]).split("/")[0] for im in coco.get("images", []) if "/" in str(im["file_name"])}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        pass
    rendered = set(RENDER_FILES) | videos | {f"{v}.{ext}" for v in videos for ext in ("mp4", "srt", "csv")}
    render: list[str] = []
    other: list[str] = []
    for name in sorted(p.name for p in folder.iterdir()):
        if name in DATASET_FILES or name == TERRAIN_DEM_FILE or name.startswith(_TMP_PREFIX):
            continue  # a dataset's own files, or a run's temporary folder (one killed left it; one running has it)
        (render if name in rendered else other).append(name)
    return render, other


def require_output_folder(out: str | Path) -> None:
    """ValueError (one line) when `out` is a file, or a folder that holds no uavmm sim dataset but other files (not
    hidden ones: .DS_Store, .gitkeep): another's files are not ours to mix with. A folder holding a dataset is
    replaced as always (boost's or track's outputs written beside it stay, as the README's commands do); an earlier
    render there loses its marks (`write_dataset` removes render.json / unannotated.json) and its frames are named
    in a warning: they no longer show the dataset. For callers that ask before the work (`uavmm sim`)."""
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"output directory {folder} is a file: give a folder (new, empty, or an earlier dataset's)")
    render, other = existing_outputs(folder)
    other = [name for name in other if not name.startswith(".")]

    images = folder / "images.json"
    if images.is_file() and not _written_by_sim(images):
        raise ValueError(f"output directory {folder} holds an images.json that is not a uavmm sim dataset's (its "
                         f"info.description does not start {SIM_DESCRIPTION!r}): it is not ours to replace; give a "
                         "new or empty folder")
    holds_dataset = any((folder / name).is_file() for name in DATASET_FILES)
    if other and not holds_dataset:
        raise ValueError(f"output directory {folder} holds files that are not a uavmm sim dataset "
                         f"({listed_names(other)}): give a new or empty folder")
    frames = [name for name in render if name not in RENDER_FILES]
    if frames:
        logger.warning("output directory %s holds an earlier render's frames (%s): they stay beside the new dataset "
                       "and no longer show it; render again (uavmm render) or remove them", folder,
                       listed_names(frames))


def _written_by_sim(images: Path) -> bool:
    """Whether an images.json is one `write_dataset` wrote (its info.description), not a user's own dataset."""
    try:
        with images.open(encoding="utf-8") as f:
            head = f.read(4096)  # "info" comes first in what write_dataset writes
    except (OSError, UnicodeDecodeError):
        return False
    return f'"description": "{SIM_DESCRIPTION}' in head


def _prepare_output(out: Path) -> tuple[bool, Path]:
    """Create `out` if needed and a temporary folder inside it; OSError naming the path if not writable."""
    created = not out.exists()
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"output directory {out} is not writable: it is a file, give a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=_TMP_PREFIX, dir=out))
    except OSError as exc:
        raise OSError(f"output directory {out} is not writable: {exc.strerror or exc}") from exc
    return created, tmp


def _candidate_lines(image_id: int, fs: FrameSample) -> list[str]:
    c = fs.candidates
    boxes = np.round(c.boxes_xywh, 2).tolist()
    scores = np.round(c.scores, 4).tolist()
    cats = c.category_ids.tolist()
    lines = [f'{{"image_id": {image_id}, "category_id": {k}, "bbox": [{b[0]}, {b[1]}, {b[2]}, {b[3]}], '
             f'"score": {s}' for b, s, k in zip(boxes, scores, cats, strict=True)]
    if c.embeddings is not None:  # optional appearance descriptor (docs/tracking.md), 3 decimals
        for i in np.flatnonzero(np.isfinite(c.embeddings).all(axis=1)).tolist():
            lines[i] += ', "embedding": [' + ", ".join(f"{v:.3f}" for v in c.embeddings[i].tolist()) + "]"
    return [line + "}" for line in lines]


def write_dataset(scenario: str | Scenario, out_dir: str | Path, *, seed: int = 0, frames: int | None = None,
                  noise_scale: float = 1.0, progress: bool = True) -> dict[str, Any]:
    """Simulate `scenario` and write its dataset to `out_dir`.

    Parameters
    ----------
    scenario : str or Scenario
        A name of `sim.scenarios.SCENARIOS` (or a Scenario, e.g. one with tuned emulator parameters).
    out_dir : str or Path
        Output folder, created if needed; existing dataset files in it are replaced, and an earlier render's
        render.json and unannotated.json removed (they described the frames of the dataset replaced).
    seed : int
        Non-negative seed.
    frames : int, optional
        Frames per video (default: the scenario's).
    noise_scale : float
        Telemetry noise multiplier (1 = realistic consumer drone, 2 = doubled).
    progress : bool
        Show a progress bar on stderr (only when stderr is a terminal).

    Returns
    -------
    dict
        Summary: ``scenario, seed, out_dir, videos, images, annotations, candidates,
        images_without_meta, blurred_images, occluded_objects, seconds``.

    Raises
    ------
    ValueError
        Unknown scenario (the message lists the valid ones), seed not a non-negative int, frames < 1.
    OSError
        `out_dir` cannot be created or written (the message names the path), or a file cannot be written (a
        full disk: the message names the file; what `out_dir` held is left as it was).
    """
    started = time.perf_counter()
    sim = Simulation(scenario, seed=seed, frames=frames, noise_scale=noise_scale)
    out = Path(out_dir)
    created, tmp = _prepare_output(out)
    bar = _Progress(f"sim {sim.scenario.name}", sim.n_frames_total, progress)
    try:
        images: list[dict[str, Any]] = []
        annotations: list[dict[str, Any]] = []
        poses: list[dict[str, Any]] = []
        occluded_boxes: list[dict[str, Any]] = []
        cand_lines: list[str] = []
        n_missing = n_blurred = 0
        for fs in sim.frames():
            video = sim.videos[fs.video_id - 1]
            images.append({
                "id": fs.image_id, "file_name": f"{video.name}/{fs.frame_index:06d}.jpg",
                "width": sim.camera.width, "height": sim.camera.height, "video_id": fs.video_id,
                "frame_index": fs.frame_index, "date_time": fs.date_time, "meta": fs.meta,
            })
            for o in fs.objects:
                if o.visible:
                    x, y, w, h = (round(v, 2) for v in o.bbox_xywh)  # type: ignore[union-attr]
                    annotations.append({
                        "id": len(annotations) + 1, "image_id": fs.image_id, "category_id": o.category_id,
                        "bbox": [x, y, w, h], "area": round(w * h, 2), "iscrowd": 0, "track_id": o.track_id,
                        "lat": round(o.lat, 9), "lon": round(o.lon, 9),
                    })
                elif o.in_view and o.occluded:
                    occluded_boxes.append({"image_id": fs.image_id, "video_id": fs.video_id, "uav": fs.uav,
                                           "track_id": o.track_id, "lat": round(o.lat, 9), "lon": round(o.lon, 9),
                                           "bbox": [round(v, 2) for v in o.bbox_xywh]})  # type: ignore[union-attr]
            p = fs.true_pose
            poses.append({"image_id": fs.image_id, "video_id": fs.video_id, "uav": fs.uav,
                          "frame_index": fs.frame_index, "t": round(fs.t, 6), "lat": p.lat, "lon": p.lon,
                          "height_m": p.height_m, "pitch_deg": p.pitch_deg, "heading_deg": p.heading_deg,
                          "blurred": fs.blurred})
            cand_lines.extend(_candidate_lines(fs.image_id, fs))
            n_missing += fs.meta is None
            n_blurred += fs.blurred
            bar.update(fs.image_id)
        bar.close()
        facts = sim.facts()
        sc = sim.scenario
        coco = {
            "info": {"description": f"{SIM_DESCRIPTION} {sc.name!r} (seed {sim.seed})",
                     "version": "1", "date_created": format_time(START_UNIX_S)},
            "images": images, "annotations": annotations, "categories": sim.categories,
            "videos": [{"id": v.id, "name": v.name, "uav": v.uav} for v in sim.videos],
        }
        truth = {
            "scenario": {
                "name": sc.name, "description": sc.description, "fps": sc.fps, "simultaneous": sc.simultaneous,
                "camera_preset": sc.camera_preset, "world": _spec_dict(sc.world),
                "flights": [_spec_dict(f) for f in sc.flights], "emulator": _emulator_dict(sc.emulator),
                "noise_base": _noise_dict(sc.noise),
                **({"sea_state": sc.sea_state.to_dict()} if sc.sea_state is not None else {}),
                **({"uav_settings": [dataclasses.asdict(u) for u in sc.uav_settings]} if sc.uav_settings else {}),
                **({"takeoff": sc.takeoff} if sc.takeoff != "origin" else {}),
            },
            "seed": sim.seed, "frames_per_video": sim.frames_per_video, "noise_scale": sim.noise_scale,
            "noise": _noise_dict(sim.noise),
            "videos": [{**dataclasses.asdict(v), **fv}
                       for v, fv in zip(sim.videos, _by_video(facts, sim), strict=True)],
            "occlusion": facts["occlusion"], "occluded_boxes": occluded_boxes,
            "trees": facts["trees"], "clutter": facts["clutter"], "poses": poses,
        }
        files = list(DATASET_FILES)
        if sim.terrain is not None:  # the DEM beside the dataset, for `--dem`; flat worlds write nothing more
            truth["scenario"]["terrain"] = _spec_dict(sim.terrain.spec)
            truth["terrain"] = facts["terrain"]
            with _naming(out / TERRAIN_DEM_FILE):
                write_npz(tmp / TERRAIN_DEM_FILE, sim.terrain.grid)
            files.append(TERRAIN_DEM_FILE)
        texts: list[tuple[str, Callable[[], str]]] = [  # made one at a time: pre_nms.json's text can be large
            ("images.json", lambda: json.dumps(coco)),
            ("camera.json", lambda: json.dumps(sim.camera.to_dict(), indent=2)),
            ("pre_nms.json", lambda: "[" + ",\n".join(cand_lines) + "]\n"),
            ("truth.json", lambda: json.dumps(truth))]
        for name, text in texts:
            with _naming(out / name):
                (tmp / name).write_text(text())
        for name in reversed(RENDER_FILES):  # the earlier render's marks first: they describe the old dataset
            with _naming(out / name):
                (out / name).unlink(missing_ok=True)
        # images.json last, and an earlier one gone first: a run stopped between the moves (SIGKILL, power) leaves
        # no images.json, which every reader takes for a whole dataset (`uavmm eval`'s cache, `uavmm render`)
        (out / "images.json").unlink(missing_ok=True)
        for name in sorted(files, key=lambda n: n == "images.json"):
            os.replace(tmp / name, out / name)
        if sim.terrain is None and (out / TERRAIN_DEM_FILE).exists():  # a terrain dataset's, written here before
            os.remove(out / TERRAIN_DEM_FILE)
    except BaseException:
        bar.close()
        shutil.rmtree(tmp, ignore_errors=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    summary = {
        "scenario": sim.scenario.name, "seed": sim.seed, "out_dir": str(out), "videos": len(sim.videos),
        "images": len(images), "annotations": len(annotations), "candidates": len(cand_lines),
        "images_without_meta": int(n_missing), "blurred_images": int(n_blurred),
        "occluded_objects": len(facts["occlusion"]), "seconds": round(time.perf_counter() - started, 3),
    }
    logger.info("wrote %s: %s", out, summary)
    return summary


@contextlib.contextmanager
def _naming(path: Path) -> Iterator[None]:
    """Re-raise an OSError as one naming ``path`` (the dataset's file, not the temporary being written)."""
    try:
        yield
    except OSError as exc:
        raise OSError(f"cannot write {path}: {exc.strerror or exc}") from None


def _by_video(facts: dict[str, Any], sim: Simulation) -> list[dict[str, Any]]:
    by_id = {f["video_id"]: f for f in facts["videos"]}
    return [{k: val for k, val in by_id[v.id].items() if k not in ("video_id", "name", "uav", "kind", "group")}
            for v in sim.videos]

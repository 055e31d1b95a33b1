"""`uavmm anomaly-train`: train the anomaly autoencoder on rendered sea frames and export it to ONNX.

Needs the optional ``train`` extra (PyTorch; ``pip install -e '.[train]'``); nothing else in the package
imports torch. The data are simulated and rendered here (`sim.dataset.write_dataset`, `sim.render`) from fixed
seeds that the evaluation does not use, with the settings the shipped model (`agent/anomaly/sea_autoencoder.onnx`;
docs/anomaly.md) was trained with. A run is the same for the same seed, scenes and PyTorch, but on 30 Nov 2026 the
default run (PyTorch 2.13.0 CPU) gave other weights than the shipped file (why was not established). The loss
ignores the annotated objects' boxes: the network learns to redraw water only.

Everything a run can be refused for (its values, the ONNX path, the work folder, a missing PyTorch) is checked
before the scenes are rendered; the model is written whole (`shared.files.write_atomic`), so an interrupted or
failed run leaves the file that was there, or none.
"""

from __future__ import annotations

import dataclasses
import io
import logging
import os
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from agent.anomaly.autoencoder import DEFAULT_MODEL, STRIDE
from agent.anomaly.methods import DEFAULT_WORK_WIDTH, to_work
from agent.dataset import Dataset, read_image
from shared.files import listed_names, same_file, write_atomic

log = logging.getLogger(__name__)

#: Seeds of the training scenes (the evaluation uses 0-99).
TRAIN_SEEDS = (100, 101)
CROP = 128
#: The install hint when PyTorch is missing (one line: the CLI prints it as the error).
TORCH_MISSING = "PyTorch is missing (the train extra): pip install -e '.[train]'"
#: The folders `render_training_scenes` makes in the work folder; nothing else may be there.
_SCENE_DIR = re.compile(r"sea_\d+x\d+_s\d+_f\d+")


def require_torch() -> None:
    """ImportError with the install hint (`TORCH_MISSING`) unless PyTorch can be imported."""
    try:
        import torch  # noqa: F401
    except ImportError:
        raise ImportError(TORCH_MISSING) from None


def check_paths(out: str | Path, work_dir: str | Path) -> None:
    """ValueError naming the path when the run would fail or do harm only after its work.

    out: the ONNX file: not a folder, its folder must exist, and not the model shipped in the package
    (`agent.anomaly.autoencoder.DEFAULT_MODEL`, by any spelling or link: every `uavmm anomaly` runs it; write
    elsewhere and copy it over deliberately). work_dir: absent, or a folder holding only the scene folders a
    run makes (``sea_WxH_sSEED_fFRAMES``), so scenes are never written into a folder of other files.
    """
    out, work_dir = Path(out), Path(work_dir)
    if out.is_dir():
        raise ValueError(f"{out} is a directory: give the ONNX file's path")
    if not out.parent.is_dir():
        raise ValueError(f"output directory {out.parent} does not exist (for {out})")
    if os.path.realpath(out) == os.path.realpath(DEFAULT_MODEL) or same_file(out, DEFAULT_MODEL):
        raise ValueError(f"{out} is the model shipped in the package ({DEFAULT_MODEL}): write the new model "
                         "elsewhere, compare it, then copy it over deliberately")
    if work_dir.exists() and not work_dir.is_dir():
        raise ValueError(f"work directory {work_dir} is not a directory")
    if work_dir.is_dir():
        other = sorted(p.name for p in work_dir.iterdir()
                       if not (_SCENE_DIR.fullmatch(p.name) and p.is_dir()) and not p.name.startswith("."))
        if other:
            raise ValueError(f"work directory {work_dir} holds other files ({listed_names(other, 5)}): give an "
                             "empty or new folder, or one an earlier anomaly-train run made")


def render_training_scenes(work_dir: Path, seeds: Sequence[int], frames: int,
                           image_size: tuple[int, int], progress: bool = False) -> list[Path]:
    """Simulate and render the sea scenario for each seed under work_dir (reused when already complete).

    progress: the simulator's and renderer's progress bars on stderr (only when it is a terminal)."""
    from sim.dataset import write_dataset
    from sim.render import RenderOptions, render_dataset
    from sim.scenarios import get_scenario

    scenario = dataclasses.replace(get_scenario("sea"), image_size=image_size)
    out = []
    for seed in seeds:
        d = work_dir / f"sea_{image_size[0]}x{image_size[1]}_s{seed}_f{frames}"
        if not (d / "render.json").is_file():
            log.info("rendering the training scene %s", d)
            write_dataset(scenario, d, seed=seed, frames=frames, progress=progress)
            # the frozen sea the shipped model was trained on (the autoencoder sees single frames, and a frame
            # of the moving sea has the same statistics: docs/anomaly.md)
            render_dataset(d, options=RenderOptions(sea_waves=False), progress=progress)
        out.append(d)
    return out


def load_frames(directories: Sequence[Path], work_width: int, every: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Working-size frames (N, h, w, 3) uint8 and loss masks (N, h, w) uint8 (0 on objects) of every
    ``every``-th frame."""
    images, masks = [], []
    for d in directories:
        ds = Dataset.load(d / "images.json")
        boxes: dict[int, list[list[float]]] = {}
        import json

        for a in json.loads((d / "images.json").read_text())["annotations"]:
            boxes.setdefault(int(a["image_id"]), []).append(a["bbox"])
        for k, image in enumerate(ds.images.values()):
            if k % every:
                continue
            pixels = read_image(d, image)
            if pixels is None:
                continue
            small = to_work(pixels, work_width)
            s = small.shape[1] / pixels.shape[1]
            mask = np.ones(small.shape[:2], np.uint8)
            for x, y, w, h in boxes.get(image.id, []):
                cv2.rectangle(mask, (int(x * s) - 3, int(y * s) - 3), (int((x + w) * s) + 3, int((y + h) * s) + 3),
                              0, -1)
            images.append(small)
            masks.append(mask)
    return np.stack(images), np.stack(masks)


def build_model() -> Any:
    """The autoencoder: three stride-2 convolutions down to 1/8, three transposed convolutions up (~40 k weights)."""
    import torch.nn as nn

    return nn.Sequential(
        nn.Conv2d(3, 16, 3, 2, 1), nn.ReLU(),
        nn.Conv2d(16, 32, 3, 2, 1), nn.ReLU(),
        nn.Conv2d(32, 32, 3, 2, 1), nn.ReLU(),
        nn.ConvTranspose2d(32, 32, 4, 2, 1), nn.ReLU(),
        nn.ConvTranspose2d(32, 16, 4, 2, 1), nn.ReLU(),
        nn.ConvTranspose2d(16, 3, 4, 2, 1), nn.Sigmoid(),
    )


def train_autoencoder(out: str | Path, *, work_dir: str | Path = "out/anomaly-train",
                      seeds: Sequence[int] = TRAIN_SEEDS,
                      frames: int = 120, image_size: tuple[int, int] = (1280, 720), steps: int = 1500,
                      batch: int = 16, lr: float = 2e-3, seed: int = 0, work_width: int = DEFAULT_WORK_WIDTH,
                      progress: bool = False, on_step: Callable[[int, int], None] | None = None
                      ) -> dict[str, Any]:
    """Render the training scenes, train, export ``out`` (ONNX opset 17, dynamic height and width), written whole.

    progress: the rendering's progress bars on stderr (on a terminal); on_step: called with (steps done, steps)
    after each optimiser step.
    Returns a summary: frames, steps, final masked L1 loss, seconds, the ONNX file's size in bytes.
    Before any work: ValueError for an empty ``seeds``, a negative seed, ``frames``, ``steps`` or ``batch`` < 1,
    ``lr`` <= 0 or a refused path (`check_paths`); ImportError (with the install hint) when PyTorch is missing.
    """
    seeds = [int(s) for s in seeds]
    if not seeds or min(seeds) < 0:
        raise ValueError(f"seeds must be one or more integers >= 0, got {seeds}")
    for name, value in (("frames", frames), ("steps", steps), ("batch", batch)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    if not lr > 0:
        raise ValueError(f"lr must be > 0, got {lr}")
    check_paths(out, work_dir)
    require_torch()
    import torch

    started = time.perf_counter()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    dirs = render_training_scenes(Path(work_dir), seeds, frames, image_size, progress)
    images, masks = load_frames(dirs, work_width)
    n, h, w = masks.shape
    if h < CROP or w < CROP:
        raise ValueError(f"working frames {w}x{h} are smaller than the {CROP}-pixel training crops")
    x_all = torch.from_numpy(images).permute(0, 3, 1, 2).float().div_(255.0)
    m_all = torch.from_numpy(masks).float()[:, None]
    model = build_model()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    loss_v = float("nan")
    for step in range(steps):
        idx = rng.integers(0, n, batch)
        ys = rng.integers(0, h - CROP + 1, batch)
        xs = rng.integers(0, w - CROP + 1, batch)
        xb = torch.stack([x_all[i, :, y:y + CROP, x:x + CROP] for i, y, x in zip(idx, ys, xs, strict=True)])
        mb = torch.stack([m_all[i, :, y:y + CROP, x:x + CROP] for i, y, x in zip(idx, ys, xs, strict=True)])
        loss = ((model(xb) - xb).abs() * mb).sum() / (mb.sum() * 3 + 1e-6)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        loss_v = float(loss.detach())  # float(loss) warns on every run (a tensor that requires grad)
        if step % 250 == 0:
            log.info("step %d/%d: masked L1 %.4f", step, steps, loss_v)
        if on_step is not None:
            on_step(step + 1, steps)
    model.eval()
    out = Path(out)
    dummy = torch.zeros(1, 3, (h // STRIDE) * STRIDE, (w // STRIDE) * STRIDE)
    onnx_bytes = io.BytesIO()  # exported in memory, then written whole: torch.onnx.export truncates its file first
    torch.onnx.export(model, dummy, onnx_bytes, dynamo=False, opset_version=17, input_names=["frames"],
                      output_names=["reconstruction"],
                      dynamic_axes={"frames": {2: "height", 3: "width"}, "reconstruction": {2: "height", 3: "width"}})

    def write(file: IO[bytes]) -> None:
        file.write(onnx_bytes.getvalue())

    write_atomic(out, write)
    return {"out": str(out), "frames": int(n), "steps": steps, "final_masked_l1": round(loss_v, 5),
            "seconds": round(time.perf_counter() - started, 1), "bytes": out.stat().st_size}

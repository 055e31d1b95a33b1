"""`uavmm anomaly-train`: train the anomaly autoencoder on rendered sea frames and export it to ONNX.

Needs the optional ``train`` extra (PyTorch; ``pip install -e '.[train]'``); nothing else in the package
imports torch. The data are simulated and rendered here (`sim.dataset.write_dataset`, `sim.render`) from fixed
seeds that the evaluation does not use, so one command reproduces the shipped model
(`agent/anomaly/sea_autoencoder.onnx`; docs/anomaly.md). The loss ignores the annotated objects' boxes: the
network learns to redraw water only.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from agent.anomaly.autoencoder import STRIDE
from agent.anomaly.methods import DEFAULT_WORK_WIDTH, to_work
from agent.dataset import Dataset, read_image

log = logging.getLogger(__name__)

#: Seeds of the training scenes (the evaluation uses 0-99).
TRAIN_SEEDS = (100, 101)
CROP = 128


def render_training_scenes(work_dir: Path, seeds: Sequence[int], frames: int,
                           image_size: tuple[int, int]) -> list[Path]:
    """Simulate and render the sea scenario for each seed under work_dir (reused when already complete)."""
    from sim.dataset import write_dataset
    from sim.render import RenderOptions, render_dataset
    from sim.scenarios import get_scenario

    scenario = dataclasses.replace(get_scenario("sea"), image_size=image_size)
    out = []
    for seed in seeds:
        d = work_dir / f"sea_{image_size[0]}x{image_size[1]}_s{seed}_f{frames}"
        if not (d / "render.json").is_file():
            write_dataset(scenario, d, seed=seed, frames=frames, progress=False)
            # the frozen sea the shipped model was trained on (the autoencoder sees single frames, and a frame
            # of the moving sea has the same statistics: docs/anomaly.md)
            render_dataset(d, options=RenderOptions(sea_waves=False), progress=False)
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
                      batch: int = 16, lr: float = 2e-3, seed: int = 0, work_width: int = DEFAULT_WORK_WIDTH
                      ) -> dict[str, Any]:
    """Render the training scenes, train, export ``out`` (ONNX opset 17, dynamic height and width).

    Returns a summary: frames, steps, final masked L1 loss, seconds, the ONNX file's size in bytes.
    ImportError (with the install hint) when PyTorch is missing.
    """
    try:
        import torch
    except ImportError:
        raise ImportError("uavmm anomaly-train needs PyTorch: pip install -e '.[train]'") from None
    started = time.perf_counter()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    dirs = render_training_scenes(Path(work_dir), seeds, frames, image_size)
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
        loss_v = float(loss)
        if step % 250 == 0:
            log.info("step %d/%d: masked L1 %.4f", step, steps, loss_v)
    model.eval()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 3, (h // STRIDE) * STRIDE, (w // STRIDE) * STRIDE)
    torch.onnx.export(model, dummy, str(out), dynamo=False, opset_version=17, input_names=["frames"],
                      output_names=["reconstruction"],
                      dynamic_axes={"frames": {2: "height", 3: "width"}, "reconstruction": {2: "height", 3: "width"}})
    return {"out": str(out), "frames": int(n), "steps": steps, "final_masked_l1": round(loss_v, 5),
            "seconds": round(time.perf_counter() - started, 1), "bytes": out.stat().st_size}

"""`uavmm eval --tasks anomaly`: the paper's anomaly protocol (section IV-C, Table III) on rendered datasets.

For each frame a method gives a score image (the per-frame heatmap, or the memory layer read back into the
frame); flagging its highest-scoring pixels until a fraction p of the image is flagged (the "broadcasting
rate": the share of the frame a UAV would transmit), an annotated object is found when one of its box's
pixels is flagged. Exactly that share is flagged for every score image: pixels tied at the threshold are drawn
at random (the expected hit counts), so a saturated heatmap is not judged at a larger share than a smooth one.
R@p is the share of objects found over all frames; AR averages R@p over `RATES`. Both modes use the same pixels
below the horizon cut, so the only difference is the ground aggregation. Objects wholly above the cut (beyond
``max_range_m`` or near the horizon) count as missed in both modes, as the paper counts recall over the data
set's objects; the report also gives AR and R@p over the objects in the mapped region alone (a part of the box
below the cut row), labelled as such.
The anomalies are everything on the water that is not water: the annotated swimmers and the boats and buoys
the renderer draws without annotating them (their boxes come from the render's ``unannotated.json``); recall
is also reported per class, so the swimmers' figure stays visible.
Parameters are chosen on tuning seeds and reported on held-out seeds (docs/anomaly.md).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agent.anomaly import AnomalyConfig, AnomalyDetector
from agent.dataset import Dataset, iter_video_frames, read_image
from shared.geo import Camera

#: Broadcasting rates (fraction of the image flagged) averaged into AR. Stricter than 1-20 %: on our rendered
#: scenes every method finds ~all objects once 1 % of the image is flagged.
RATES = (0.002, 0.005, 0.01, 0.02, 0.05)
#: Image size the evaluation renders its scenes at (objects of 4-20 pixels, like SeaDronesSee at 4K / 3).
EVAL_IMAGE_SIZE = (1280, 720)
MODES = ("frame", "memory")
#: Unannotated rendered objects (``unannotated.json`` kinds) that count as anomalies: not water, on the water.
ANOMALY_KINDS = ("boat", "buoy")


def anomaly_boxes(directory: Path, coco: dict[str, Any],
                  kinds: Sequence[str] = ANOMALY_KINDS) -> dict[int, list[tuple[str, list[float]]]]:
    """Per image id the (class, [x, y, w, h]) boxes of the anomalies: the annotations (class = their category's
    name) and the rendered unannotated objects of `kinds`.

    Raises ValueError when the rendered dataset has no unannotated.json (rendered before it existed: render
    it again).
    """
    names = {int(c["id"]): str(c["name"]) for c in coco.get("categories", [])}
    out: dict[int, list[tuple[str, list[float]]]] = {}
    for a in coco["annotations"]:
        out.setdefault(int(a["image_id"]), []).append((names.get(int(a["category_id"]), "object"), a["bbox"]))
    path = directory / "unannotated.json"
    if not path.is_file():
        raise ValueError(f"{directory}: unannotated.json is missing (render the dataset again: "
                         f"`uavmm render {directory}`)")
    for a in json.loads(path.read_text())["annotations"]:
        if a["kind"] in kinds:
            out.setdefault(int(a["image_id"]), []).append((str(a["kind"]), a["bbox"]))
    return out


def frame_hits(scores: NDArray[np.float32], boxes_xywh: NDArray[np.float64], full_size: tuple[int, int],
               rates: Sequence[float] = RATES) -> NDArray[np.float64]:
    """How likely each object is found at each broadcasting rate: (len(rates), N) float64 in [0, 1].

    scores: (h, w) score image at any scale of the frame (full_size = (width, height)); boxes_xywh (N, 4) in
    full-resolution pixels. At rate p exactly k = ceil(p h w) pixels are flagged, the highest first; pixels
    tied at the threshold score are drawn at random (zero scores never are), so every score image is judged
    at the same flagged share whatever its ties (a heatmap saturated over 1.3 % of the frame flagged all of
    that at the "0.2 %" rate when ties were all flagged). An object is found when a pixel of its box (grown to
    whole pixels of the score image) is flagged: 1 when its maximum is above the threshold, else the chance
    that the random draw of the tied pixels hits one of its own.
    """
    h, w = scores.shape
    out = np.zeros((len(rates), len(boxes_xywh)), dtype=np.float64)
    if len(boxes_xywh) == 0:
        return out
    desc = -np.sort(scores.ravel())[::-1]  # ascending negated scores, for searchsorted
    sx, sy = w / full_size[0], h / full_size[1]
    crops = []
    for x, y, bw, bh in boxes_xywh:
        c0, r0 = max(int(math.floor(x * sx)), 0), max(int(math.floor(y * sy)), 0)
        c1, r1 = min(int(math.ceil((x + bw) * sx)), w), min(int(math.ceil((y + bh) * sy)), h)
        crops.append(scores[r0:max(r1, r0 + 1), c0:max(c1, c0 + 1)] if c1 > c0 and r1 > r0
                     else np.zeros((1, 1), np.float32))
    peaks = np.array([float(c.max()) for c in crops])
    for j, p in enumerate(rates):
        k = min(max(int(math.ceil(p * h * w)), 1), desc.size)
        thr = float(-desc[k - 1])
        if thr <= 0.0:  # fewer than k positive pixels: all of them are flagged, nothing else
            out[j] = peaks > 0.0
            continue
        above = int(np.searchsorted(desc, -thr, side="left"))
        ties = int(np.searchsorted(desc, -thr, side="right")) - above
        drawn = k - above  # tied pixels flagged, drawn at random among the ties
        out[j] = peaks > thr
        for i in np.flatnonzero(peaks == thr):
            own = int((crops[i] == thr).sum())
            if ties - drawn < own:
                out[j, i] = 1.0
            else:  # 1 - P(no own pixel among the drawn) = 1 - C(ties - own, drawn) / C(ties, drawn)
                out[j, i] = 1.0 - math.exp(math.lgamma(ties - own + 1) - math.lgamma(ties - own - drawn + 1)
                                           - math.lgamma(ties + 1) + math.lgamma(ties - drawn + 1))
    return out


def persistence(heat: NDArray[np.float32], layer: NDArray[np.float32], boxes_xywh: NDArray[np.float64],
                full_size: tuple[int, int], rate: float = RATES[0], grow_px: int = 2
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How much of the frame's heat the ground layer keeps, at the frame's false alarms and at its objects.

    heat: the per-frame scores (cut), layer: the ground layer read back into the frame, same shape. Returns the
    ratios layer / heat at the ceil(rate h w) highest heat pixels that lie outside every object box (grown by
    grow_px score pixels), and at each object (layer maximum / heat maximum over its box). Aggregation can only
    demote false alarms whose ratio is below the objects': the transient ones.
    """
    h, w = heat.shape
    k = min(max(int(math.ceil(rate * h * w)), 1), heat.size)
    top = np.argpartition(heat.ravel(), heat.size - k)[heat.size - k:]
    top = top[heat.ravel()[top] > 0]
    inside = np.zeros((h, w), dtype=bool)
    sx, sy = w / full_size[0], h / full_size[1]
    objects = []
    for x, y, bw, bh in boxes_xywh:
        c0, r0 = max(int(math.floor(x * sx)), 0), max(int(math.floor(y * sy)), 0)
        c1, r1 = min(int(math.ceil((x + bw) * sx)), w), min(int(math.ceil((y + bh) * sy)), h)
        if c1 <= c0 or r1 <= r0:
            continue
        inside[max(r0 - grow_px, 0):r1 + grow_px, max(c0 - grow_px, 0):c1 + grow_px] = True
        peak = float(heat[r0:r1, c0:c1].max())
        if peak > 0:
            objects.append(float(layer[r0:r1, c0:c1].max()) / peak)
    alarms = top[~inside.ravel()[top]]
    return (layer.ravel()[alarms] / heat.ravel()[alarms]).astype(np.float64), np.asarray(objects, dtype=np.float64)


def evaluate_dataset(directory: str | Path, config: AnomalyConfig, *, rates: Sequence[float] = RATES,
                     every: int = 1) -> dict[str, Any]:
    """Run one method over every video of a rendered dataset; both modes from the same heatmaps.

    Returns ``{"objects": N, "frames": F, "fps": heatmap+map frames per second, "frame": {"hits": [per rate]},
    "memory": {...}, "classes": {class: {"objects": n, "frame": {"hits"}, "memory": {"hits"}}},
    "region": {"objects": n, "frame": {"hits"}, "memory": {"hits"}}, "persistence": {...}}`` where objects are the
    anomalies (`anomaly_boxes`), region the objects with a part of their box below the cut row, hits count found
    objects
    (expected counts: ties are drawn at random, `frame_hits`) and persistence (`persistence`,
    `persistence_summary`) tells how many of the per-frame false alarms the layer keeps as well as it keeps the
    objects; objects are scored on every ``every``-th frame (the heatmaps and the layer still see every frame).
    """
    directory = Path(directory)
    ds = Dataset.load(directory / "images.json")
    camera = Camera.from_file(directory / "camera.json")
    coco = json.loads((directory / "images.json").read_text())
    by_image = anomaly_boxes(directory, coco)
    hits = {m: np.zeros(len(rates), dtype=np.float64) for m in MODES}
    region_hits = {m: np.zeros(len(rates), dtype=np.float64) for m in MODES}
    classes: dict[str, dict[str, Any]] = {}
    objects = frames = region_objects = 0
    busy = 0.0
    detector = AnomalyDetector(config)
    alarm_ratios: list[NDArray[np.float64]] = []
    object_ratios: list[NDArray[np.float64]] = []
    for video_id in ds.videos:
        detector.reset()
        # the poses each frame carries, as the anomaly layer was measured with (docs/anomaly.md)
        for i, frame in enumerate(iter_video_frames(ds, camera, video_id, at_frame_time=False)):
            image = read_image(directory, frame.image)
            if image is None:
                raise ValueError(f"{directory}: image file of image {frame.image.id} is missing (render the dataset)")
            t0 = time.perf_counter()
            result = detector.process(image, frame.pose, frame.t, frame.camera)
            busy += time.perf_counter() - t0
            frames += 1
            boxes = by_image.get(frame.image.id)
            if not boxes or i % every:
                continue
            arr = np.asarray([b for _, b in boxes], dtype=np.float64)
            labels = np.array([c for c, _ in boxes])
            objects += len(arr)
            per_frame = result.heat.copy()
            per_frame[:int(math.ceil(result.cut_row * per_frame.shape[0] / camera.height))] = 0.0
            size = (frame.camera.width, frame.camera.height)
            memory = result.scores if frame.pose is not None else per_frame
            # in the mapped region: a part of the box lies below the cut row (full-resolution pixels)
            mapped = arr[:, 1] + arr[:, 3] > result.cut_row
            region_objects += int(mapped.sum())
            for mode, score in (("frame", per_frame), ("memory", memory)):
                found = frame_hits(score, arr, size, rates)
                hits[mode] += found.sum(axis=1)
                region_hits[mode] += found[:, mapped].sum(axis=1)
                for cls in np.unique(labels):
                    entry = classes.setdefault(str(cls), {"objects": 0, **{m: np.zeros(len(rates)) for m in MODES}})
                    entry[mode] += found[:, labels == cls].sum(axis=1)
            for cls in np.unique(labels):
                classes[str(cls)]["objects"] += int((labels == cls).sum())
            if result.layer is not None:
                a, o = persistence(per_frame, result.layer, arr, size, rates[0])
                alarm_ratios.append(a)
                object_ratios.append(o)
    return {"objects": objects, "frames": frames, "fps": round(frames / busy, 2) if busy > 0 else None,
            **{m: {"hits": [round(float(v), 3) for v in hits[m]]} for m in MODES},
            "classes": {c: {"objects": e["objects"], **{m: {"hits": [round(float(v), 3) for v in e[m]]} for m in MODES}}
                        for c, e in sorted(classes.items())},
            "region": {"objects": region_objects,
                       **{m: {"hits": [round(float(v), 3) for v in region_hits[m]]} for m in MODES}},
            "persistence": persistence_summary(np.concatenate(alarm_ratios or [np.zeros(0)]),
                                               np.concatenate(object_ratios or [np.zeros(0)]))}


def persistence_summary(alarm_ratios: NDArray[np.float64], object_ratios: NDArray[np.float64]) -> dict[str, Any]:
    """Shares (percent) of false-alarm pixels the layer keeps at least as well as the median object ("kept") and
    at less than half of that ("transient"), and the objects' median ratio; None without data."""
    if alarm_ratios.size == 0 or object_ratios.size == 0:
        return {"kept": None, "transient": None, "object_ratio": None}
    med = float(np.median(object_ratios))
    return {"kept": round(float(np.mean(alarm_ratios >= med)) * 100.0, 1),
            "transient": round(float(np.mean(alarm_ratios < 0.5 * med)) * 100.0, 1),
            "object_ratio": round(med, 2)}


def summarise(results: Sequence[dict[str, Any]], rates: Sequence[float] = RATES) -> dict[str, Any]:
    """Mean over datasets (seeds) of AR and R@5% per mode, in percent, with the per-seed values."""
    out: dict[str, Any] = {}
    i5 = list(rates).index(0.05) if 0.05 in rates else None
    for m in MODES:
        ars, r5s = [], []
        for r in results:
            rec = np.asarray(r[m]["hits"], dtype=np.float64) / max(r["objects"], 1) * 100.0
            ars.append(float(rec.mean()))
            if i5 is not None:
                r5s.append(float(rec[i5]))
        out[m] = {"AR": round(float(np.mean(ars)), 1), "R@5%": round(float(np.mean(r5s)), 1) if r5s else None,
                  "AR_per_seed": [round(a, 1) for a in ars], "R@5%_per_seed": [round(a, 1) for a in r5s]}
    out["gain"] = {"AR": round(out["memory"]["AR"] - out["frame"]["AR"], 1),
                   "R@5%": round((out["memory"]["R@5%"] or 0) - (out["frame"]["R@5%"] or 0), 1)}
    out["fps"] = round(float(np.mean([r["fps"] for r in results if r["fps"]])), 1)
    shares = {}
    for key in ("kept", "transient"):
        values = [r["persistence"][key] for r in results if r.get("persistence", {}).get(key) is not None]
        shares[key] = round(float(np.mean(values)), 1) if values else None
    out["false_alarms"] = shares
    per_class: dict[str, Any] = {}
    for cls in sorted({c for r in results for c in r.get("classes", {})}):
        n = sum(r["classes"][cls]["objects"] for r in results if cls in r.get("classes", {}))
        entry: dict[str, Any] = {"objects": n}
        for m in MODES:  # pooled over the seeds (a seed may have few boats in view)
            rec = sum(np.asarray(r["classes"][cls][m]["hits"], dtype=np.float64) for r in results
                      if cls in r.get("classes", {})) / max(n, 1) * 100.0
            entry[m] = {"AR": round(float(np.mean(rec)), 1),
                        "R@5%": round(float(rec[i5]), 1) if i5 is not None else None}
        per_class[cls] = entry
    out["classes"] = per_class
    if results and all("region" in r for r in results):
        region: dict[str, Any] = {"objects": sum(r["region"]["objects"] for r in results)}
        for m in MODES:  # mean over the seeds, as the headline figures
            recs = [np.asarray(r["region"][m]["hits"], dtype=np.float64) / max(r["region"]["objects"], 1) * 100.0
                    for r in results]
            region[m] = {"AR": round(float(np.mean([x.mean() for x in recs])), 1),
                         "R@5%": round(float(np.mean([x[i5] for x in recs])), 1) if i5 is not None else None}
        region["gain"] = {"AR": round(region["memory"]["AR"] - region["frame"]["AR"], 1),
                          "R@5%": round((region["memory"]["R@5%"] or 0) - (region["frame"]["R@5%"] or 0), 1)}
        out["region"] = region
    return out


Progress = Callable[[str], None]
#: Methods evaluated by default (all registered ones).
EVAL_METHODS = ("autoencoder", "diff", "mean", "median", "mog2")


def _dataset(data_dir: Path, scenario: str, seed: int, frames: int) -> Path:
    """The rendered dataset of a scenario and seed at EVAL_IMAGE_SIZE (simulated and drawn once, then reused)."""
    import dataclasses

    from sim.dataset import write_dataset
    from sim.render import render_dataset
    from sim.scenarios import get_scenario

    w, h = EVAL_IMAGE_SIZE
    d = data_dir / f"{scenario}_s{seed}_f{frames}_{w}x{h}"
    if not (d / "render.json").is_file() or not (d / "unannotated.json").is_file():
        write_dataset(dataclasses.replace(get_scenario(scenario), image_size=EVAL_IMAGE_SIZE), d, seed=seed,
                      frames=frames, progress=False)
        render_dataset(d, progress=False)
    return d


def run_anomaly_eval(scenarios: Sequence[str], seeds: Sequence[int], *, methods: Sequence[str] = EVAL_METHODS,
                     frames: int | None = None, out_dir: str | Path = "out/eval/anomaly",
                     progress: Progress | None = None, every: int = 3) -> dict[str, Any]:
    """Per scenario and method: AR and R@5 % per frame and with the memory map over the seeds (held out: the
    defaults were chosen on seed 0 of sea). Writes report.json and report.md to out_dir; returns the report."""
    from agent.anomaly import AnomalyConfig

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    frames = frames or 150
    table: dict[str, dict[str, Any]] = {}
    for scenario in scenarios:
        dirs = [_dataset(out / "data", scenario, seed, frames) for seed in seeds]
        for method in methods:
            if progress:
                progress(f"anomaly {scenario} {method}: seeds {list(seeds)}")
            runs = [evaluate_dataset(d, AnomalyConfig(method=method), every=every) for d in dirs]
            table.setdefault(scenario, {})[method] = {**summarise(runs), "objects": sum(r["objects"] for r in runs)}
    report = {"rates": list(RATES), "seeds": list(seeds), "frames": frames, "image_size": list(EVAL_IMAGE_SIZE),
              "results": table, "seconds": round(time.perf_counter() - started, 1)}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(format_report(report))
    return report


def format_report(report: dict[str, Any]) -> str:
    """The report as a Markdown table per scenario: per-frame beside memory map, AR and R@5 %, gains, FPS."""
    lines = [f"# Anomaly detection (paper IV-C): recall at broadcasting rates {[r * 100 for r in report['rates']]} %",
             f"seeds {report['seeds']}, {report['frames']} frames a video, {report['image_size'][0]}x"
             f"{report['image_size'][1]}", ""]
    for scenario, methods in report["results"].items():
        lines += [f"## {scenario}", "", "| method | AR frame | AR memory | gain | R@5% frame | R@5% memory | gain | "
                  "false alarms kept / transient (%) | FPS (heatmap + map) | objects |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in methods.items():
            fa = r.get("false_alarms") or {}
            lines.append(f"| {name} | {r['frame']['AR']} | {r['memory']['AR']} | {r['gain']['AR']:+} | "
                         f"{r['frame']['R@5%']} | {r['memory']['R@5%']} | {r['gain']['R@5%']:+} | "
                         f"{fa.get('kept')} / {fa.get('transient')} | {r['fps']} | {r['objects']} |")
        lines += ["", "AR and R@5 % in percent over all the anomalies in the frames (those wholly above the cut row "
                  "count as missed in both modes), mean over the seeds (per seed in report.json); exactly the share p "
                  "of each frame is flagged in both modes (ties drawn at random). False alarms kept / transient: of "
                  f"the per-frame heatmap's top {report['rates'][0] * 100:g} % pixels outside the objects, the share "
                  "the ground layer keeps at least as well as it keeps the median object / at less than half of that: "
                  "aggregation can only demote the transient ones.", ""]
        if all("region" in r for r in methods.values()):
            lines += ["Mapped region only (objects with a part of the box below the cut row; the table above counts "
                      "the objects above the cut as missed in both modes, as the paper counts recall over all "
                      "objects):",
                      "", "| method | AR frame | AR memory | gain | R@5% frame | R@5% memory | gain | objects |",
                      "|---|---|---|---|---|---|---|---|"]
            for name, r in methods.items():
                g = r["region"]
                lines.append(f"| {name} | {g['frame']['AR']} | {g['memory']['AR']} | {g['gain']['AR']:+} | "
                             f"{g['frame']['R@5%']} | {g['memory']['R@5%']} | {g['gain']['R@5%']:+} | {g['objects']} |")
            lines.append("")
        lines += ["Per class (pooled over the seeds), AR frame -> memory, R@5% frame -> memory:", ""]
        for name, r in methods.items():
            parts = [f"{c} ({e['objects']}) {e['frame']['AR']} -> {e['memory']['AR']}, "
                     f"{e['frame']['R@5%']} -> {e['memory']['R@5%']}" for c, e in r.get("classes", {}).items()]
            lines.append(f"- {name}: " + "; ".join(parts))
        lines.append("")
    return "\n".join(lines) + "\n"

"""`uavmm eval --domains`: detection and tracking over the evaluation domains (`sim.domains`), with the
tuning and held-out domains reported apart and the issue's acceptance bars checked on the held-out ones.

Per domain, seed and telemetry-noise scale a dataset is simulated once (cached under out/data, keyed by
the domain's definition), then scored like `sim.evaluate` (pycocotools AP50) for three variants: the
single-frame baseline, our memory map, and the paper's literal rule (sum stamping, c + p, r 6 m,
per-frame forgetting and gain); tracking (TrackEval HOTA, IDs) compares our GPS tracker with norfair
on the same detections at noise x1, beside the ground error of our tracker's reported positions
(`pos_err_m`, `pos_err_p90_m`; `sim.position_error`). Terrain domains add our variants with the dataset's DEM
and the same flights over flat ground (`sim.terrain_eval`).
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.memory_map import MemoryMapConfig
from agent.pipeline_config import PipelineConfig
from agent.tracking import TrackerConfig
from sim.domains import FAR_DOMAINS, Domain
from sim.evaluate import Variant, evaluate_detection, write_reports
from sim.position_error import format_metres, mean_known
from sim.terrain_eval import DEM_SUFFIX, TWIN, markdown_terrain, summarise_terrain, terrain_acceptance, terrain_of

BASELINE, OURS, PAPER = "baseline", "memory map", "paper rule"
NORFAIR, GPS = "norfair (pixel IoU)", "GPS tracker + memory map"
#: Ours without the appearance cue, beside GPS on the view-jump domains whose detections carry descriptors.
GPS_MOTION = "GPS tracker + memory map, motion only"
#: Bars of the view-jump (re-ID) domains: IDF1 at least this, and over norfair's by IDF1 / HOTA margins.
JUMPS_MIN_IDF1, JUMPS_IDF1_MARGIN, JUMPS_HOTA_MARGIN = 60.0, 25.0, 15.0
#: The paper's constants: forgetting phi = 0.9 and scale s per frame (s = 0.02: 0.6 per second at 30 fps).
PAPER_FORGET_PER_FRAME = 0.9
PAPER_GAIN_PER_FRAME = 0.02


def paper_rule_config() -> PipelineConfig:
    """The paper's rule as printed: every pre-NMS box adds s * c * Gaussian (r 6 m), phi per frame, c + p for
    every box (no fragment_iou), on the telemetry each frame carries (no interpolation at frame time,
    clock-offset estimate, dequantised GPS, score calibration or telemetry correction: those are ours; the
    telemetry's time zone is removed, without which no stamp means anything). The distance-size filter is the
    paper's too."""
    memory = MemoryMapConfig(radius_m=6.0, stamp="sum", forget_per_frame=PAPER_FORGET_PER_FRAME,
                             gain_per_frame=PAPER_GAIN_PER_FRAME)
    return PipelineConfig(memory=memory, boost_mode="add", boost_weight=1.0, estimate_clock_offset=False,
                          dequantize_telemetry=False, telemetry_at_frame_time=False, calibrate_scores=False,
                          correct_telemetry=False, fragment_iou=0.0)


def domain_detection_variants() -> list[Variant]:
    """Baseline (first: it sets the operating point), ours, the paper's rule."""
    base = PipelineConfig()
    return [Variant(BASELINE, dataclasses.replace(base, use_memory=False)), Variant(OURS, base),
            Variant(PAPER, paper_rule_config())]


#: Written last into a domain dataset's folder, which is then renamed into the cache whole: only an entry holding it
#: is reused (one a killed run left, or one from before 30 Nov 2026 when final_output rewrote pre_nms.json in place
#: after images.json had marked the entry complete, is built again).
COMPLETE_MARKER = "complete.json"


def ensure_domain_dataset(domain: Domain, seed: int, noise_scale: float, full: bool, cache_dir: Path) -> Path:
    """Path of the domain's dataset for (seed, noise, clip length), simulated once and reused.

    Built in a hidden folder beside the entry (``.NAME.partial-PID``) and renamed into place with `COMPLETE_MARKER`
    inside, so a run killed while building (SIGKILL, power) never leaves an entry the next run takes as complete;
    an entry without the marker is built again, and the partial folders of runs no longer alive are removed.
    """
    import os
    import shutil

    from shared.files import write_chunks_atomic
    from sim.dataset import write_dataset

    out = cache_dir / f"{domain.name}-{domain.tag}-s{seed}-n{noise_scale:g}{'-full' if full else ''}"
    if (out / COMPLETE_MARKER).is_file():
        return out
    cache_dir.mkdir(parents=True, exist_ok=True)
    _remove_dead_partials(cache_dir, out.name)
    tmp = cache_dir / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write_dataset(domain.scenario(), tmp, seed=seed, frames=domain.frames(full), noise_scale=noise_scale,
                      progress=False)
        if domain.final_score is not None:
            final_output(tmp / "pre_nms.json", domain.final_score)
        write_chunks_atomic(tmp / COMPLETE_MARKER, [json.dumps({"domain": domain.name, "tag": domain.tag,
                                                                "seed": seed, "noise_scale": noise_scale,
                                                                "full": full})])
        if (out / COMPLETE_MARKER).is_file():  # another run finished it meanwhile: its entry stays (it may be read)
            return out
        if out.exists():  # an incomplete entry (a killed run's, or an older version's): set aside, then dropped
            stale = cache_dir / f".{out.name}.stale-{os.getpid()}"
            shutil.rmtree(stale, ignore_errors=True)
            out.rename(stale)
            shutil.rmtree(stale, ignore_errors=True)
        try:
            tmp.rename(out)
        except OSError:
            if not (out / COMPLETE_MARKER).is_file():  # not another run's complete entry that won the race
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _remove_dead_partials(cache_dir: Path, name: str) -> None:
    """Remove ``.NAME.partial-PID`` folders whose process is gone (runs killed while building the entry)."""
    import shutil

    from shared.files import process_gone

    for path in cache_dir.glob(f".{name}.partial-*"):
        try:
            pid = int(path.name.rsplit("-", 1)[1])
        except ValueError:
            continue
        if process_gone(pid):  # not this run's, nor another user's (alive as far as we can tell)
            shutil.rmtree(path, ignore_errors=True)


def final_output(candidates_path: Path, min_score: float, *, iou: float = 0.5, max_per_image: int = 100) -> int:
    """Replace a candidates file by the detector's final output: per image, class-wise NMS at `iou` and
    scores >= min_score (at most max_per_image, highest first), as detectors ship their results. Returns the
    entries kept; the file is rewritten in place."""
    import numpy as np

    from agent.boxes import nms

    entries = json.loads(candidates_path.read_text())
    by_image: dict[int, list[dict[str, Any]]] = {}
    for e in entries:
        by_image.setdefault(int(e["image_id"]), []).append(e)
    kept: list[dict[str, Any]] = []
    for image_id in sorted(by_image):
        group = by_image[image_id]
        xywh = np.array([e["bbox"] for e in group], dtype=np.float64).reshape(-1, 4)
        boxes = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]])
        scores = np.array([e["score"] for e in group], dtype=np.float64)
        keep = nms(boxes, scores, np.array([e["category_id"] for e in group]), iou, 0.0, max_per_image)
        kept.extend(group[i] for i in keep.tolist() if scores[i] >= min_score)
    candidates_path.write_text(json.dumps(kept))
    return len(kept)


def run_domain_eval(domains: list[Domain], seeds: list[int], *, noise_scales: tuple[float, ...] = (1.0, 2.0),
                    tasks: tuple[str, ...] = ("detection", "tracking"), full: bool = False,
                    out_dir: Path = Path("out/eval-domains"),
                    progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Evaluate every domain x seed (x noise for detection); returns the report (also report.json/.md)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / "data"
    t0 = time.perf_counter()
    det_rows: list[dict[str, Any]] = []
    trk_rows: list[dict[str, Any]] = []
    jobs = [(d, seed, k) for d in domains for k in noise_scales for seed in seeds]
    for i, (domain, seed, noise) in enumerate(jobs):
        run_trk = "tracking" in tasks and noise == 1.0
        if "detection" not in tasks and not run_trk:
            continue
        if progress:
            progress(f"[{i + 1}/{len(jobs)}] {domain.name} seed={seed} noise x{noise:g}")
        data_dir = ensure_domain_dataset(domain, seed, noise, full, cache)
        base = {"domain": domain.name, "split": domain.split, "motion": domain.motion, "seed": seed,
                "noise_scale": noise}
        # a terrain domain: our variants again on its DEM, and (noise x1) on the same flights over flat ground
        terrain = terrain_of(data_dir) if domain.terrain is not None else None
        twin_dir = (ensure_domain_dataset(domain.flat_twin(), seed, noise, full, cache)
                    if terrain is not None and noise == 1.0 else None)
        if "detection" in tasks:
            variants = domain_detection_variants()
            if terrain is not None:
                variants += [Variant(v.name + DEM_SUFFIX, dataclasses.replace(v.config, terrain=terrain))
                             for v in variants if v.name in (BASELINE, OURS)]
            for name, m in evaluate_detection(data_dir, variants).items():
                det_rows.append({**base, "variant": name, **m})
            if twin_dir is not None:
                for name, m in evaluate_detection(twin_dir, variants[:2]).items():
                    det_rows.append({**base, "variant": TWIN + name, **m})
        if run_trk:
            from sim.track_eval import TrackingVariant, evaluate_tracking

            base_cfg = PipelineConfig()
            # norfair on the single-frame detections of the telemetry as stamped (it does not use poses)
            trk_variants = [TrackingVariant(NORFAIR, dataclasses.replace(base_cfg, use_memory=False,
                                                                         estimate_clock_offset=False), kind="pixel"),
                            TrackingVariant(GPS, base_cfg, kind="gps")]
            if domain.motion == "jumps" and domain.descriptors:
                # the same detections without their descriptors: what ours keeps on data that has none
                trk_variants.append(TrackingVariant(GPS_MOTION, base_cfg, kind="gps",
                                                    tracker=TrackerConfig(use_appearance=False)))
            if terrain is not None:
                trk_variants.append(TrackingVariant(GPS + DEM_SUFFIX, dataclasses.replace(base_cfg, terrain=terrain),
                                                    kind="gps"))
            for name, m in evaluate_tracking(data_dir, trk_variants, fps=domain.fps).items():
                trk_rows.append({**base, "variant": name, **m})
            if twin_dir is not None:
                for name, m in evaluate_tracking(twin_dir, trk_variants[1:2], fps=domain.fps).items():
                    trk_rows.append({**base, "variant": TWIN + name, **m})
    terrain_summary = summarise_terrain(det_rows, trk_rows, OURS, BASELINE, GPS)
    report = {"domains": [d.name for d in domains], "seeds": seeds, "noise_scales": list(noise_scales),
              "full": full, "detection_rows": det_rows, "tracking_rows": trk_rows,
              "detection": summarise_detection(det_rows), "tracking": summarise_tracking(trk_rows),
              "terrain": terrain_summary, "seconds": round(time.perf_counter() - t0, 1)}
    report["acceptance"] = acceptance(report) + terrain_acceptance(terrain_summary)
    write_reports(out_dir, report, markdown_domain_report(report))
    return report


def _mean(values: list[float]) -> float:
    return statistics.fmean(values) if values else float("nan")


def summarise_detection(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (domain, noise): mean AP50 over seeds of each variant, and the gains over the baseline."""
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["domain"], r["noise_scale"]), []).append(r)
    out = []
    for (domain, noise), rs in groups.items():
        ap = {v: _mean([r["AP50"] for r in rs if r["variant"] == v]) for v in (BASELINE, OURS, PAPER)}
        out.append({"domain": domain, "split": rs[0]["split"], "motion": rs[0]["motion"], "noise_scale": noise,
                    "seeds": len({r["seed"] for r in rs}), "AP50_baseline": ap[BASELINE], "AP50_ours": ap[OURS],
                    "AP50_paper": ap[PAPER], "gain_ours": ap[OURS] - ap[BASELINE],
                    "gain_paper": ap[PAPER] - ap[BASELINE],
                    "ms_ours": _mean([r["pipeline_ms_per_frame"] for r in rs if r["variant"] == OURS])})
    return out


def summarise_tracking(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per domain: mean HOTA, MOTA, IDF1 and summed IDs over seeds of norfair and ours, and the ground error
    of the reported positions (`pos_err_m` median, `pos_err_p90_m`; metres, mean over seeds of each seed's
    figure; None for norfair, which reports no ground positions, and where nothing matched); re-ID events
    kept / scored (summed over seeds) of each; where the motion-only variant ran (view-jump domains with
    descriptors), its figures as `*_motion`."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r["domain"], []).append(r)
    out = []
    for domain, rs in groups.items():
        row: dict[str, Any] = {"domain": domain, "split": rs[0]["split"], "motion": rs[0]["motion"],
                               "seeds": len({r["seed"] for r in rs})}
        for v, key in ((NORFAIR, "norfair"), (GPS, "ours"), (GPS_MOTION, "motion")):
            vr = [r for r in rs if r["variant"] == v]
            if not vr and key == "motion":
                continue
            for k in ("reid_kept", "reid_scored"):
                row[f"{k}_{key}"] = sum(r.get(k, 0) for r in vr)
            for m in ("HOTA", "MOTA", "IDF1"):
                row[f"{m}_{key}"] = _mean([r[m] for r in vr])
            row[f"IDs_{key}"] = sum(r["IDs"] for r in vr)
            for m in ("pos_err_m", "pos_err_p90_m"):
                row[f"{m}_{key}"] = mean_known([r.get(m) for r in vr])
        out.append(row)
    return out


def acceptance(report: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's bars on the held-out domains: [{criterion, value, bar, ok}]."""
    out: list[dict[str, Any]] = []
    # the far group's boxes all lie beyond the memory map's range: only its tracking bars apply
    det = [s for s in report["detection"] if s["split"] == "heldout" and s["domain"] not in FAR_DOMAINS]
    for noise, bar in ((1.0, 3.0), (2.0, 2.0)):
        rows = [s for s in det if s["noise_scale"] == noise]
        if not rows:
            continue
        gain = _mean([s["gain_ours"] for s in rows])
        worst = min(s["gain_ours"] for s in rows)
        paper = _mean([s["AP50_ours"] - s["AP50_paper"] for s in rows])
        out += [{"criterion": f"held-out mean AP50 gain over no-memory, noise x{noise:g}", "value": gain,
                 "bar": f">= +{bar:g}", "ok": gain >= bar},
                {"criterion": f"held-out worst domain AP50 gain, noise x{noise:g}", "value": worst, "bar": ">= 0",
                 "ok": worst >= 0},
                {"criterion": f"held-out mean AP50 ours - paper rule, noise x{noise:g}", "value": paper,
                 "bar": "> 0", "ok": paper > 0}]
    for s in report["tracking"]:
        if s["split"] != "heldout":
            continue
        if s["motion"] == "jumps":
            out += jumps_acceptance(s)
        elif s["motion"] == "gentle":
            out.append({"criterion": f"{s['domain']}: HOTA ours - norfair", "value": s["HOTA_ours"] - s["HOTA_norfair"],
                        "bar": ">= -1", "ok": s["HOTA_ours"] - s["HOTA_norfair"] >= -1})
            out.append({"criterion": f"{s['domain']}: IDs ours (norfair: bar)", "value": s["IDs_ours"],
                        "bar": f"<= {s['IDs_norfair']}", "ok": s["IDs_ours"] <= s["IDs_norfair"]})
        else:
            out.append({"criterion": f"{s['domain']}: HOTA ours - norfair", "value": s["HOTA_ours"] - s["HOTA_norfair"],
                        "bar": ">= +15", "ok": s["HOTA_ours"] - s["HOTA_norfair"] >= 15})
            out.append({"criterion": f"{s['domain']}: IDs ours (norfair: bar)", "value": s["IDs_ours"],
                        "bar": f"<= {0.8 * s['IDs_norfair']:g}", "ok": s["IDs_ours"] <= 0.8 * s["IDs_norfair"]})
    return out


def jumps_acceptance(s: dict[str, Any]) -> list[dict[str, Any]]:
    """The re-ID bars of a view-jump domain's tracking summary `s`: IDF1 ours >= JUMPS_MIN_IDF1 and >= norfair
    + JUMPS_IDF1_MARGIN, HOTA ours >= norfair + JUMPS_HOTA_MARGIN."""
    d_idf1, d_hota = s["IDF1_ours"] - s["IDF1_norfair"], s["HOTA_ours"] - s["HOTA_norfair"]
    return [{"criterion": f"{s['domain']}: IDF1 ours", "value": s["IDF1_ours"], "bar": f">= {JUMPS_MIN_IDF1:g}",
             "ok": s["IDF1_ours"] >= JUMPS_MIN_IDF1},
            {"criterion": f"{s['domain']}: IDF1 ours - norfair", "value": d_idf1, "bar": f">= +{JUMPS_IDF1_MARGIN:g}",
             "ok": d_idf1 >= JUMPS_IDF1_MARGIN},
            {"criterion": f"{s['domain']}: HOTA ours - norfair", "value": d_hota, "bar": f">= +{JUMPS_HOTA_MARGIN:g}",
             "ok": d_hota >= JUMPS_HOTA_MARGIN}]


def _markdown_jumps(summary: list[dict[str, Any]]) -> list[str]:
    """The view-jump domains: HOTA / IDF1 / IDs and re-ID kept of norfair, ours and ours on motion alone."""
    rows = [s for s in summary if s["motion"] == "jumps"]
    if not rows:
        return []
    lines = ["## Re-ID with view jumps: HOTA / IDF1 / IDs (sum) and returns that kept their id", "",
             "Motion only: ours without the appearance cue on the same detections (where they carry descriptors; "
             "on the other domains ours has none to use).", "",
             "| split | domain | norfair | ours | ours, motion only | re-ID kept ours | re-ID kept motion only |",
             "|---|---|---|---|---|---|---|"]

    def cell(s: dict[str, Any], key: str) -> str:
        return f"{s[f'HOTA_{key}']:.1f} / {s[f'IDF1_{key}']:.1f} / {s[f'IDs_{key}']}" if f"HOTA_{key}" in s else "-"

    def kept(s: dict[str, Any], key: str) -> str:
        return f"{s[f'reid_kept_{key}']}/{s[f'reid_scored_{key}']}" if f"reid_kept_{key}" in s else "-"

    for split in ("tune", "heldout"):
        for s in (s for s in rows if s["split"] == split):
            lines.append(f"| {split} | {s['domain']} | {cell(s, 'norfair')} | {cell(s, 'ours')} | "
                         f"{cell(s, 'motion')} | {kept(s, 'ours')} | {kept(s, 'motion')} |")
    return [*lines, ""]


def markdown_domain_report(report: dict[str, Any]) -> str:
    """The report as Markdown: detection and tracking per domain, tuning and held-out apart, acceptance."""
    lines = ["# uavmm eval --domains", "",
             f"Seeds {report['seeds']}; {'full-length' if report['full'] else 'short'} clips; mean over seeds. "
             "Parameters and design choices were made on the tuning domains; the held-out ones are only reported.",
             ""]
    if report["detection"]:
        lines += ["## Detection: AP50 (pycocotools)", "",
                  "| split | domain | noise | no memory | memory map | paper rule | gain | paper gain | ms/frame |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for split in ("tune", "heldout"):
            rows = sorted((s for s in report["detection"] if s["split"] == split),
                          key=lambda s: (s["noise_scale"], s["domain"]))
            for s in rows:
                lines.append(f"| {split} | {s['domain']} | x{s['noise_scale']:g} | {s['AP50_baseline']:.1f} | "
                             f"{s['AP50_ours']:.1f} | {s['AP50_paper']:.1f} | {s['gain_ours']:+.1f} | "
                             f"{s['gain_paper']:+.1f} | {s['ms_ours']:.2f} |")
            for noise in sorted({s["noise_scale"] for s in rows}):
                sel = [s for s in rows if s["noise_scale"] == noise]
                m = {k: _mean([s[k] for s in sel]) for k in ("AP50_baseline", "AP50_ours", "AP50_paper",
                                                              "gain_ours", "gain_paper")}
                lines.append(f"| {split} | **mean** | x{noise:g} | {m['AP50_baseline']:.1f} | {m['AP50_ours']:.1f} | "
                             f"{m['AP50_paper']:.1f} | {m['gain_ours']:+.1f} | {m['gain_paper']:+.1f} | |")
        lines.append("")
    if report["tracking"]:
        lines += ["## Tracking (noise x1): TrackEval HOTA, MOTA, IDF1 (mean), IDs (sum over seeds)", "",
                  "Pos err: metres between our reported track positions and the truth of the objects their boxes "
                  "match (IoU >= 0.5), median and 90th percentile (mean over seeds); norfair has no ground "
                  "positions.", "",
                  "| split | domain | flights | HOTA norfair | HOTA ours | MOTA norfair | MOTA ours | IDF1 norfair | "
                  "IDF1 ours | IDs norfair | IDs ours | pos err ours m | pos err p90 ours m |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for split in ("tune", "heldout"):
            for s in (s for s in report["tracking"] if s["split"] == split):
                lines.append(f"| {split} | {s['domain']} | {s['motion']} | {s['HOTA_norfair']:.1f} | "
                             f"{s['HOTA_ours']:.1f} | {s['MOTA_norfair']:.1f} | {s['MOTA_ours']:.1f} | "
                             f"{s['IDF1_norfair']:.1f} | {s['IDF1_ours']:.1f} | {s['IDs_norfair']} | {s['IDs_ours']} | "
                             f"{format_metres(s.get('pos_err_m_ours'))} | "
                             f"{format_metres(s.get('pos_err_p90_m_ours'))} |")
        lines.append("")
        lines += _markdown_jumps(report["tracking"])
    lines += markdown_terrain(report.get("terrain", []))
    if report.get("acceptance"):
        lines += ["## Acceptance (held-out domains)", "", "| criterion | value | bar | holds |", "|---|---|---|---|"]
        for a in report["acceptance"]:
            value = (f"{a['value']:.0f}" if "IDs" in a["criterion"] else
                     f"{a['value']:.1f}" if a["criterion"].endswith("IDF1 ours") else
                     f"{a['value']:+.2f}" if a["criterion"].endswith(", m") else f"{a['value']:+.1f}")
            lines.append(f"| {a['criterion']} | {value} | {a['bar']} | {'yes' if a['ok'] else 'NO'} |")
    lines.append(f"\n{report['seconds']} s")
    return "\n".join(lines) + "\n"

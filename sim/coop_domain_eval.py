"""`uavmm eval --tasks coop --domains ...`: the cooperative domains (`sim.coop_domains`), per UAV, from one run.

Each domain and seed is simulated once (cached by the domain's tag) and run by `sim.coop_eval.evaluate_coop`:
the single-frame detector (memory off), the UAV's own memory map, and the joint map the fusion server would
send it (boosting and joint detections, the agent's defaults), all on the wire's data path; the joint variant is
also tracked, and its tracks go through the fusion server's global tracker (`sim.cross_uav`: one object, one id
across UAVs, with and without re-association, against each UAV's ids kept apart). AP50 counts the
objects a UAV has in view, hidden ones included (does it report everything in its view?). Tuning and held-out
domains are reported apart; the acceptance rows are issue 30's: on every held-out domain the weaker UAV's joint
map gains >= JOINT_GAIN_BAR AP50 over its own map, and no other UAV loses more than STRONG_LOSS_BAR.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeFilter
from sim.coop_domains import CoopDomain
from sim.coop_report import CROSS_COLUMNS, CROSS_HEADER, cross_cells, settings_line

DETECTOR, OWN, JOINT = "baseline", "own memory map", "joint map + joint detections"
#: The variants run per domain (the joint map's boosting alone is left to `uavmm eval --tasks coop`).
VARIANTS = (DETECTOR, OWN, JOINT)
#: Issue 30's bars: the weaker UAV's joint map over its own map (AP50 points), the others' least change.
JOINT_GAIN_BAR, STRONG_LOSS_BAR = 5.0, -0.5
_METRICS = ("AP50", "AP50_hidden_ignored", "hidden_detected", "registration_offset_px", "registration_left_px")


def ensure_coop_domain_dataset(domain: CoopDomain, seed: int, noise_scale: float, cache_dir: Path) -> Path:
    """Path of the domain's dataset for (seed, noise), simulated once and reused."""
    from sim.dataset import write_dataset

    out = cache_dir / f"{domain.name}-{domain.tag}-s{seed}-n{noise_scale:g}"
    if not (out / "images.json").exists():
        write_dataset(domain.scenario(), out, seed=seed, frames=domain.frames(), noise_scale=noise_scale,
                      progress=False)
    return out


def summarise(rows: list[dict[str, Any]], domains: list[CoopDomain]) -> list[dict[str, Any]]:
    """Per domain and UAV: the mean over seeds of each variant's metrics, and the joint map's gain over the
    UAV's own map (`gain`, AP50 points)."""
    out = []
    for d in domains:
        for uav in dict.fromkeys(r["uav"] for r in rows if r["domain"] == d.name):
            row: dict[str, Any] = {"domain": d.name, "split": d.split, "uav": uav, "weaker": uav == d.weaker,
                                   "seeds": len({r["seed"] for r in rows if r["domain"] == d.name})}
            for variant in VARIANTS:
                rs = [r for r in rows if r["domain"] == d.name and r["uav"] == uav and r["variant"] == variant]
                for m in _METRICS:
                    values = [r[m] for r in rs if m in r and r[m] == r[m]]
                    row[f"{m}|{variant}"] = statistics.fmean(values) if values else float("nan")
            row["gain"] = row[f"AP50|{JOINT}"] - row[f"AP50|{OWN}"]
            out.append(row)
    return out


def summarise_cross(rows: list[dict[str, Any]], domains: list[CoopDomain]) -> list[dict[str, Any]]:
    """Per domain: the mean over seeds of the cross-UAV identity figures (`sim.cross_uav.CROSS_METRICS`) of the
    joint variant over flat ground (over a terrain `evaluate_coop` also runs it on the DEM: not mixed in)."""
    from sim.cross_uav import CROSS_METRICS

    out = []
    for d in domains:
        rs = [r for r in rows if r["domain"] == d.name and r.get("variant", JOINT) == JOINT]
        if rs:
            out.append({"domain": d.name, "split": d.split, "seeds": len(rs), **{
                m: statistics.fmean(v) if (v := [r[m] for r in rs if r[m] == r[m]]) else float("nan")
                for m in CROSS_METRICS}})
    return out


def acceptance(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Issue 30's rows on the held-out domains: the weaker UAV's gain >= JOINT_GAIN_BAR, the others' >=
    STRONG_LOSS_BAR."""
    out = []
    for s in summary:
        if s["split"] != "heldout":
            continue
        bar = JOINT_GAIN_BAR if s["weaker"] else STRONG_LOSS_BAR
        out.append({"criterion": f"{s['domain']} {s['uav']}{' (weaker)' if s['weaker'] else ''}: joint - own AP50",
                    "value": s["gain"], "bar": f">= {bar:+g}", "ok": s["gain"] >= bar})
    return out


def markdown(report: dict[str, Any]) -> str:
    """The report as Markdown: per split, domain and UAV the detector, own map and joint map; acceptance."""
    lines = ["# uavmm eval --tasks coop --domains", "",
             f"Seeds {report['seeds']}, noise x{report['noise_scale']:g}, mean over seeds. AP50 (pycocotools) on "
             "each UAV's frames with every object in its view as ground truth (hidden ones too); 'hidden det.' = "
             "share of the boxes of objects hidden from that UAV found with score >= 0.25. Own map: the UAV's "
             "memory map alone; joint: the joint map boosting and the joint detections, "
             "fused as the fusion server does at 5 Hz. (w) marks the weaker UAV. Registration: the median offset "
             "of the other UAVs' evidence in this UAV's image that the telemetry errors make (from the truth), "
             "and what the joint registration leaves of it (sim.coop_registration).", "", settings_line(report), ""]
    for split in ("tune", "heldout"):
        rows = [s for s in report["summary"] if s["split"] == split]
        if not rows:
            continue
        lines += [f"## {'Tuning' if split == 'tune' else 'Held-out'} domains", "",
                  "| domain | uav | detector | own map | joint | joint - own | hidden det. own / joint | "
                  "registration offset -> left |",
                  "|---|---|---|---|---|---|---|---|"]
        for s in rows:
            lines.append(f"| {s['domain']} | {s['uav']}{' (w)' if s['weaker'] else ''} | {s[f'AP50|{DETECTOR}']:.1f} | "
                         f"{s[f'AP50|{OWN}']:.1f} | {s[f'AP50|{JOINT}']:.1f} | "
                         f"{s['gain']:+.1f} | {_pct(s[f'hidden_detected|{OWN}'])} / "
                         f"{_pct(s[f'hidden_detected|{JOINT}'])} | {_px(s.get(f'registration_offset_px|{JOINT}'))} -> "
                         f"{_px(s.get(f'registration_left_px|{JOINT}'))} |")
        lines.append("")
    cross = report.get("cross_summary") or []
    if cross:
        lines += ["## One object, one id across UAVs (joint variant)", "",
                  "The joint variant's GPS tracks, as each agent publishes them at 5 Hz, through the fusion "
                  "server's global tracker on the frame clock (sim.cross_uav), scored as multi-camera tracking over "
                  "all UAVs: global ids / the first look's (no re-association) / each UAV's own ids kept apart.", "",
                  f"| split | domain | {CROSS_HEADER} |", "|---|---|" + "---|" * CROSS_COLUMNS]
        lines += [f"| {c['split']} | {c['domain']} | {cross_cells(c)} |" for c in cross]
        lines.append("")
    if report["acceptance"]:
        lines += ["## Acceptance (held-out domains)", "", "| criterion | value | bar | ok |", "|---|---|---|---|"]
        lines += [f"| {a['criterion']} | {a['value']:+.1f} | {a['bar']} | {'yes' if a['ok'] else 'NO'} |"
                  for a in report["acceptance"]]
        lines.append("")
    return "\n".join(lines)


def _px(value: float | None) -> str:
    return "-" if value is None or value != value else f"{value:.0f} px"


def _pct(value: float) -> str:
    return "-" if value != value else f"{value:.0f} %"


def run_coop_domain_eval(domains: list[CoopDomain], seeds: list[int], *, noise_scale: float = 1.0,
                         out_dir: Path = Path("out/eval-coop-domains"),
                         progress: Callable[[str], None] | None = None,
                         config: PipelineConfig | None = None,
                         size_filter: SizeFilter | None = None) -> dict[str, Any]:
    """Evaluate the coop domains over seeds; writes report.json and report.md to out_dir and returns the report.
    config: every variant's settings (`--config PARAMS.json`; default PipelineConfig()), its differences from
    the defaults in the report (config_overrides); size_filter: the fitted size filter such a parameters file
    carries (None: the built-in priors), in the report too."""
    from sim.coop_eval import evaluate_coop, settings_record

    if not domains or not seeds:
        raise ValueError("run_coop_domain_eval needs at least one domain and one seed")
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    cross_rows: list[dict[str, Any]] = []
    jobs = [(d, s) for d in domains for s in seeds]
    for i, (domain, seed) in enumerate(jobs):
        if progress:
            progress(f"[{i + 1}/{len(jobs)}] coop domain {domain.name} seed={seed}")
        data_dir = ensure_coop_domain_dataset(domain, seed, noise_scale, out_dir / "data")
        per_uav, _ = evaluate_coop(data_dir, config, variants=(DETECTOR, OWN), track=False, size_filter=size_filter)
        cross: list[dict[str, Any]] = []  # the joint variant is tracked: the fusion server's global ids over UAVs
        joint, _ = evaluate_coop(data_dir, config, variants=(JOINT,), size_filter=size_filter, cross_rows=cross)
        tag = {"domain": domain.name, "split": domain.split, "seed": seed}
        rows += [{**tag, **r} for r in per_uav + joint]
        cross_rows += [{**tag, **r} for r in cross]
    summary = summarise(rows, domains)
    report = {"domains": [d.name for d in domains], "seeds": seeds, "noise_scale": noise_scale,
              **settings_record(config, size_filter), "rows": rows,
              "summary": summary, "acceptance": acceptance(summary), "cross_rows": cross_rows,
              "cross_summary": summarise_cross(cross_rows, domains), "seconds": round(time.perf_counter() - t0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    (out_dir / "report.md").write_text(markdown(report))
    return report

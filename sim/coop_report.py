"""The Markdown report of `uavmm eval --tasks coop` (`sim.coop_eval.run_coop_eval`): per UAV the detection
figures of every variant, the joint map's peaks against the truth, and over a terrain flat earth against the DEM.
"""

from __future__ import annotations

import math
from typing import Any

from sim.coop_peaks import MATCH_GATE_M, PEAK_BAR_M, PEAK_MIN_SCORE
from sim.position_error import format_metres
from sim.terrain_eval import DEM_SUFFIX

__all__ = ["CROSS_COLUMNS", "CROSS_HEADER", "coop_markdown", "cross_cells", "settings_line"]

_SCENES = {
    "coop": "A tree line hides resting people (and passing walkers) from the far, oblique uav1 for the whole "
            "flight; uav2, closer, sees them.",
    "coop-slope": "Two UAVs on opposite sides of a slope (10 m per 100 m), each launched from its own side: uav1 "
                  "below looks up it, uav2 above looks down it; ten people stand on it, three walk. Flat earth "
                  "projects onto the plane of each UAV's own take-off; '+ DEM' georeferences on the dataset's "
                  "dem.npz with each UAV's take-off elevation (truth.json), as --dem does.",
}


def _pct(value: float) -> str:
    return "" if value != value else f"{value:.1f}"


def settings_line(report: dict[str, Any]) -> str:
    """The report.md line naming what --config changed (config_overrides, a fitted size filter)."""
    changed = [f"{k} = {v}" for k, v in (report.get("config_overrides") or {}).items()]
    if report.get("size_filter"):
        changed.append("a fitted size filter")
    return "Settings: " + (", ".join(changed) + " (--config), the rest the defaults." if changed
                           else "all the defaults.")


def coop_markdown(report: dict[str, Any]) -> str:
    """report.md of a `run_coop_eval` report dict (its summary, peak_summary and acceptance)."""
    lines = [f"# uavmm eval: cooperative detection ({', '.join(report['scenarios'])}, two UAVs)", "",
             f"Seeds {report['seeds']}, telemetry noise x{', x'.join(f'{n:g}' for n in report['noise_scales'])}, "
             "mean over seeds. " + " ".join(_SCENES.get(s, "") for s in report["scenarios"]), "",
             settings_line(report), "",
             "AP50 by pycocotools on each UAV's frames with the hidden people's boxes as ground truth "
             "(does the UAV report everything in its view?); 'hidden ignored': their boxes are COCO crowd "
             "(ignore) regions; 'hidden as FP': left out, so detecting them counts as a false positive; "
             "'hidden detected' = share of their boxes found with score >= 0.25; 'hidden "
             "tracked' = share matched (IoU >= 0.5) by the box of a confirmed GPS-tracker track matched in "
             "that frame; HOTA (TrackEval, hidden people as distractors), id switches and the median ground error "
             "of the reported track positions ('track err m') of the GPS tracker on each variant's detections. "
             "Joint map: the fusion server's JointMap (mean rule; a UAV covers the cells of its camera "
             "footprints of the last 2 s) over both UAVs' tiles as the agent encodes them, at 5 Hz; "
             "'joint detections': the peaks of the other UAV's evidence in view that no detection explains "
             "promote a weak real candidate or carry this UAV's last sighting of the object "
             "(agent.joint_detections).", "",
             "| scenario | noise | uav | variant | AP50 | AP50 hidden ignored | AP50 hidden as FP | "
             "hidden detected % | hidden tracked % | HOTA | IDs | track err m |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["summary"]:
        lines.append(f"| {s['scenario']} | x{s['noise_scale']:g} | {s['uav']} | {s['variant']} | {s['AP50']:.1f} | "
                     f"{s['AP50_hidden_ignored']:.1f} | {s['AP50_hidden_as_fp']:.1f} | {_pct(s['hidden_detected'])} | "
                     f"{_pct(s['hidden_tracked'])} | {_pct(s.get('HOTA', math.nan))} | "
                     f"{_pct(s.get('IDs', math.nan))} | {format_metres(s.get('pos_err_m'))} |")
    lines += ["", "## Joint-map peaks against the truth", "",
              f"Once a second (after 3 s) the joint map's object candidates as the REST API's /v1/objects finds them "
              f"(fusion_server.peaks, min_score {PEAK_MIN_SCORE:g}), matched one to one (Hungarian, within "
              f"{MATCH_GATE_M:g} m) to the true positions of the people who stand still for the whole flight and "
              "whom a UAV sees then, in the run of the default variant (joint detections add boxes, not "
              "evidence: the joint map of 'joint map boosting' is the same). Error: ground distance of the "
              "matched peaks, median and 90th percentile (mean over seeds; a person whose peak lies beyond the "
              f"gate counts as without one); 'with a peak' / 'within {PEAK_BAR_M:g} m': share of those people "
              "matched / matched that close; 'extra': peaks left over per sample (clutter, walkers, a person "
              "split in two). Rows per UAV count the people that UAV sees at the sample; 'both': those either sees.",
              "", f"| scenario | noise | variant | uav | standing people | peak err m | peak err p90 m | "
              f"with a peak % | within {PEAK_BAR_M:g} m % | extra peaks |", "|---|---|---|---|---|---|---|---|---|---|"]
    for p in report["peak_summary"]:
        lines.append(f"| {p['scenario']} | x{p['noise_scale']:g} | {p['variant']} | {p.get('uav', 'both')} | "
                     f"{p['standing_objects']:.0f} | "
                     f"{format_metres(p['peak_err_m'])} | {format_metres(p['peak_err_p90_m'])} | "
                     f"{_pct(p['objects_with_peak'])} | {_pct(p['objects_within_bar'])} | "
                     f"{_pct(p['extra_peaks'])} |")
    lines += _cross_lines(report)
    lines += _terrain_lines(report)
    return "\n".join(lines) + "\n"


#: The cross-UAV identity columns (`cross_cells`), shared with the coop domains' report.
CROSS_HEADER = "IDF1 | HOTA | IDs | objects on 2+ UAVs | one id %"
CROSS_COLUMNS = 5


def cross_cells(c: dict[str, Any]) -> str:
    """The CROSS_HEADER cells of a `sim.cross_uav.cross_uav_metrics` row: global / first look / apart."""
    triples = " | ".join(f"{c[m]:.1f} / {c[m + '_first_look']:.1f} / {c[m + '_separate']:.1f}"
                         for m in ("IDF1", "HOTA", "IDs"))
    return f"{triples} | {c['shared_objects']:.1f} | {_pct(c['same_id'])} / {_pct(c['same_id_first_look'])}"


def _cross_lines(report: dict[str, Any]) -> list[str]:
    """The fusion server's global ids over all UAVs (sim.cross_uav) per variant, against the UAVs' own ids."""
    rows = []
    for c in report.get("cross_summary", []):
        rows.append(f"| {c['scenario']} | x{c['noise_scale']:g} | {c['variant']} | {cross_cells(c)} |")
    if not rows:
        return []
    return ["", "## One object, one id across UAVs (the fusion server's global tracks)", "",
            "Every UAV's GPS-tracker tracks as its agent publishes them (5 Hz) go through the fusion server's "
            "global tracker (fusion_server.global_tracks, `uavmm fusion`'s defaults) on the frame clock. Scored "
            "as multi-camera tracking: the UAVs' sequences end to end, one ground-truth id per object over all "
            "UAVs (TrackEval; hidden people as distractors); each figure with the global ids / with the first "
            "look's (the same messages through a tracker without re-association, --track-reassociate-m 0) / with "
            "each UAV's own ids kept apart (UAVs that do not share tracks). 'objects on 2+ UAVs': objects more "
            "than one UAV tracks; 'one id %': of those, the share whose most frequent id is the same on every "
            "UAV (global / first look).", "",
            f"| scenario | noise | variant | {CROSS_HEADER} |", "|---|---|---|" + "---|" * CROSS_COLUMNS, *rows]


def _terrain_lines(report: dict[str, Any]) -> list[str]:
    """Flat earth beside the DEM per UAV (own map, joint map + joint detections: AP50, HOTA, the tracks' and the
    joint map's peaks' ground error) and the bars."""
    by = {(s["scenario"], s["noise_scale"], s["uav"], s["variant"]): s for s in report["summary"]}
    peaks = {(p["scenario"], p["noise_scale"], p.get("uav", "both"), p["variant"]): p for p in report["peak_summary"]}
    own, joint = "own memory map", "joint map + joint detections"
    rows = []
    for scenario, noise, uav, variant in by:
        if variant != own + DEM_SUFFIX:
            continue
        cells = []
        for metric, fmt in (("AP50", _pct), ("HOTA", _pct), ("pos_err_m", format_metres)):
            for name in (own, joint):
                pair = [by.get((scenario, noise, uav, name + suffix)) for suffix in ("", DEM_SUFFIX)]
                cells.append(" / ".join("" if r is None else fmt(r.get(metric, math.nan)) for r in pair))
        pk = [peaks.get((scenario, noise, uav, joint + suffix)) for suffix in ("", DEM_SUFFIX)]
        for key in ("peak_err_m", "peak_err_p90_m"):
            cells.append(" / ".join("" if p is None else format_metres(p[key]) for p in pk))
        rows.append(f"| {scenario} | x{noise:g} | {uav} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    lines = ["", "## Terrain: flat earth vs --dem (flat / DEM)", "",
             "| scenario | noise | uav | AP50 own map | AP50 joint + det. | HOTA own map | HOTA joint + det. | "
             "track err m own map | track err m joint + det. | joint-map peak err m | peak err p90 m |",
             "|---|---|---|---|---|---|---|---|---|---|---|", *rows]
    if report.get("acceptance"):
        lines += ["", "| bar | value | needed | ok |", "|---|---|---|---|"]
        lines += [f"| {a['criterion']} | {a['value']:.2f} | {a['bar']} | {'yes' if a['ok'] else 'NO'} |"
                  for a in report["acceptance"]]
    return lines

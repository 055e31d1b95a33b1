"""Flat earth against the DEM on the terrain domains of `uavmm eval --domains` (`sim.domains`, terrain set).

On a terrain domain our variants run twice on the same dataset, georeferencing over flat ground at the take-off's
height and on the dataset's DEM (dem.npz, the take-off's elevation from truth.json, as `--dem FILE
--takeoff-elevation-m` does), and once more on the same flights over flat ground (`Domain.flat_twin`). The
summary per domain gives AP50, HOTA and the ground error of the reported track positions of each; the bars:
with the DEM, AP50 and HOTA not below flat earth, and the median ground error within 0.3 m of the flat twin's.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

from agent.dem import load_terrain
from shared.terrain import Terrain
from sim.position_error import format_metres, mean_known

__all__ = ["DEM_SUFFIX", "POS_ERR_BAR_M", "TWIN", "markdown_terrain", "summarise_terrain", "terrain_acceptance",
           "terrain_of"]

#: Appended to a variant's name when it runs with the DEM.
DEM_SUFFIX = " + DEM"
#: The flat twin's rows carry this variant prefix.
TWIN = "flat twin: "
#: Median ground error with the DEM may exceed the flat twin's by at most this (metres).
POS_ERR_BAR_M = 0.3


def terrain_of(data_dir: Path, video_id: int | None = None) -> Terrain:
    """The dataset's DEM with the take-off's elevation from its truth.json (what the operator knows).

    video_id: the video whose take-off counts, where the UAVs take off apart (a scenario's takeoff "start":
    truth.json's videos[i].takeoff_elevation_m); otherwise, and by default, the scene's (terrain's) take-off.
    """
    truth = json.loads((data_dir / "truth.json").read_text())
    elevation = float(truth["terrain"]["takeoff_elevation_m"])
    for video in truth.get("videos", []):
        if video_id is not None and video.get("id") == video_id and "takeoff_elevation_m" in video:
            elevation = float(video["takeoff_elevation_m"])
    return load_terrain(data_dir / truth["terrain"]["dem"], elevation)


def _mean(values: list[float]) -> float:
    return statistics.fmean(values) if values else float("nan")


def summarise_terrain(det_rows: list[dict[str, Any]], trk_rows: list[dict[str, Any]], ours: str,
                      baseline: str, gps: str) -> list[dict[str, Any]]:
    """Per terrain domain (rows whose variants include a DEM one), means over seeds at noise x1: AP50 of the
    baseline and ours over flat earth, with the DEM and on the flat twin; HOTA and pos_err_m (median ground
    error, mean over seeds) of our GPS tracker likewise."""
    out = []
    domains = sorted({r["domain"] for r in det_rows + trk_rows if r["variant"].endswith(DEM_SUFFIX)})
    for domain in domains:
        det = [r for r in det_rows if r["domain"] == domain and r["noise_scale"] == 1.0]
        trk = [r for r in trk_rows if r["domain"] == domain]
        row: dict[str, Any] = {"domain": domain, "seeds": len({r["seed"] for r in det + trk})}
        for key, name in (("baseline", baseline), ("ours", ours)):
            for tag, variant in (("flat", name), ("dem", name + DEM_SUFFIX), ("twin", TWIN + name)):
                row[f"AP50_{key}_{tag}"] = _mean([r["AP50"] for r in det if r["variant"] == variant])
        for tag, variant in (("flat", gps), ("dem", gps + DEM_SUFFIX), ("twin", TWIN + gps)):
            vr = [r for r in trk if r["variant"] == variant]
            row[f"HOTA_{tag}"] = _mean([r["HOTA"] for r in vr])
            row[f"pos_err_m_{tag}"] = mean_known([r.get("pos_err_m") for r in vr])
            row[f"pos_err_p90_m_{tag}"] = mean_known([r.get("pos_err_p90_m") for r in vr])
        out.append(row)
    return out


def terrain_acceptance(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The terrain bars per domain: [{criterion, value, bar, ok}] (a bar without figures is left out)."""
    out: list[dict[str, Any]] = []
    for s in summary:
        d = s["domain"]
        gain = s["AP50_ours_dem"] - s["AP50_ours_flat"]
        if gain == gain:  # not NaN
            out.append({"criterion": f"{d}: AP50 with DEM - flat earth", "value": gain, "bar": ">= 0",
                        "ok": gain >= 0})
        hota = s["HOTA_dem"] - s["HOTA_flat"]
        if hota == hota:
            out.append({"criterion": f"{d}: HOTA with DEM - flat earth", "value": hota, "bar": ">= 0",
                        "ok": hota >= 0})
        if s["pos_err_m_dem"] is not None and s["pos_err_m_twin"] is not None:
            excess = s["pos_err_m_dem"] - s["pos_err_m_twin"]
            out.append({"criterion": f"{d}: pos err with DEM - flat-ground twin, m", "value": excess,
                        "bar": f"<= {POS_ERR_BAR_M:g}", "ok": excess <= POS_ERR_BAR_M})
    return out


def markdown_terrain(summary: list[dict[str, Any]]) -> list[str]:
    """The table of `summarise_terrain` as Markdown lines (none without terrain domains)."""
    if not summary:
        return []
    lines = ["## Terrain: flat earth vs --dem (noise x1, mean over seeds)", "",
             "The same dataset georeferenced over flat ground at the take-off's height and on its DEM; the flat twin "
             "flies the same flights over flat ground. Pos err: median ground error of our reported track positions.",
             "", "| domain | AP50 no memory flat / DEM | AP50 ours flat / DEM / twin | HOTA flat / DEM / twin | "
             "pos err m flat / DEM / twin | pos err p90 m flat / DEM / twin |", "|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(
            f"| {s['domain']} | {s['AP50_baseline_flat']:.1f} / {s['AP50_baseline_dem']:.1f} | "
            f"{s['AP50_ours_flat']:.1f} / {s['AP50_ours_dem']:.1f} / {s['AP50_ours_twin']:.1f} | "
            f"{s['HOTA_flat']:.1f} / {s['HOTA_dem']:.1f} / {s['HOTA_twin']:.1f} | "
            + " / ".join(format_metres(s[f"pos_err_m_{t}"]) for t in ("flat", "dem", "twin")) + " | "
            + " / ".join(format_metres(s[f"pos_err_p90_m_{t}"]) for t in ("flat", "dem", "twin")) + " |")
    return lines + [""]

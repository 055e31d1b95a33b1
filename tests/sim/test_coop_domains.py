"""Cooperative domains: per-UAV telemetry, detector and frame rate in one simulation, the domain grid, its
evaluation report and `uavmm eval --tasks coop --domains`."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from agent.params_file import make_params
from agent.pipeline_config import PipelineConfig
from agent.size_filter import SizeBand, SizeFilter
from sim.coop_domain_eval import JOINT, OWN, acceptance, markdown, run_coop_domain_eval, summarise, summarise_cross
from sim.coop_domains import (
    COOP_DOMAINS,
    HELDOUT_COOP_DOMAINS,
    TUNING_COOP_DOMAINS,
    CoopDomain,
    coop_domain_table,
    get_coop_domain,
    resolve_coop_domains,
)
from sim.dataset import write_dataset
from sim.scenarios import UavSetting, get_scenario
from sim.simulator import Simulation
from uavmm.cli import main
from uavmm.eval_domains import coop_noise_scale, coop_params


def _coop(**settings) -> object:
    return dataclasses.replace(get_scenario("coop"), uav_settings=tuple(settings.values()), default_frames=60)


def test_the_grid_has_six_or_more_domains_split_into_tuning_and_held_out():
    assert len(COOP_DOMAINS) >= 6 and len(TUNING_COOP_DOMAINS) >= 2 and len(HELDOUT_COOP_DOMAINS) >= 4
    assert set(TUNING_COOP_DOMAINS).isdisjoint(HELDOUT_COOP_DOMAINS)
    for d in COOP_DOMAINS.values():
        sc = d.scenario()
        assert sc.simultaneous and sc.name == d.name and len({f.uav for f in sc.flights}) >= 2
    # the ways they differ: biases per UAV, frame rates, who sees what
    steps = {u.frame_step for d in COOP_DOMAINS.values() for u in d.uavs}
    assert steps >= {1, 2, 3}
    assert any(u.emulator.get("weak_fraction", 0) > 0 for d in COOP_DOMAINS.values() for u in d.uavs)
    assert any(len(d.flights) == 3 for d in COOP_DOMAINS.values())
    assert resolve_coop_domains(["tune", "coop-trees"]) == [get_coop_domain(n) for n in TUNING_COOP_DOMAINS]
    table = coop_domain_table()
    assert all(f"| {name} |" in table for name in COOP_DOMAINS)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"uav": ""}, "non-empty"),
    ({"uav": "a", "frame_step": 0}, "frame_step"),
    ({"uav": "a", "frame_step": True}, "frame_step"),
    ({"uav": "a", "noise": {"gps_bias": 1.0}}, "unknown noise field"),
    ({"uav": "a", "emulator": {"weak_fraction": 1.5}}, "probability"),
])
def test_bad_uav_settings_are_refused_naming_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        UavSetting(**kwargs)


def test_a_setting_for_a_uav_the_scenario_does_not_fly_is_refused():
    with pytest.raises(ValueError, match="uav_settings"):
        _coop(a=UavSetting("uav9"))
    with pytest.raises(ValueError, match="uav_settings"):
        _coop(a=UavSetting("uav1"), b=UavSetting("uav1"))
    with pytest.raises(ValueError, match="weaker"):
        dataclasses.replace(get_coop_domain("coop-trees"), weaker="uav7")
    with pytest.raises(ValueError, match="unknown coop domain"):
        get_coop_domain("coop-nowhere")


def test_each_uav_gets_its_own_noise_detector_and_frame_rate():
    plain = Simulation(_coop(), 3, frames=60)
    sc = _coop(a=UavSetting("uav1", noise={"gps_bias_m": 0.0, "heading_bias_deg": 0.0, "height_bias_m": 0.0}),
               b=UavSetting("uav2", emulator={"score_logit_shift": 2.0}, frame_step=3))
    sim = Simulation(sc, 3, frames=60)
    assert sim.noise_for("uav1").gps_bias_m == 0.0 and sim.noise_for("uav2") == plain.noise
    frames = list(sim.frames())
    plain_frames = list(plain.frames())
    by_uav = {u: [f for f in frames if f.uav == u] for u in ("uav1", "uav2")}
    assert len(by_uav["uav1"]) == 60 and len(by_uav["uav2"]) == 20 == sim.frames_of(sim.videos[1])
    assert sim.n_frames_total == 80
    # uav2 films every third frame of the clock, with consecutive frame indices 1/10 s apart
    assert [f.frame_index for f in by_uav["uav2"][:3]] == [0, 1, 2]
    assert by_uav["uav2"][1].t - by_uav["uav2"][0].t == pytest.approx(0.1)
    bias = {v["uav"]: v["telemetry_bias"] for v in sim.facts()["videos"]}
    assert bias["uav1"] == {"east_m": 0.0, "north_m": 0.0, "heading_deg": 0.0, "pitch_deg": bias["uav1"]["pitch_deg"],
                            "height_m": 0.0}
    assert abs(bias["uav2"]["heading_deg"]) > 0
    # the more confident detector of uav2 scores its best boxes higher than the same UAV without the setting
    top = np.mean([f.candidates.scores.max() for f in by_uav["uav2"] if len(f.candidates.scores)])
    top_plain = np.mean([f.candidates.scores.max() for f in plain_frames[1::2][::3] if len(f.candidates.scores)])
    assert top > top_plain + 0.05


def test_weakly_seen_objects_score_lower_in_that_uav_only_and_are_listed(tmp_path):
    sc = _coop(a=UavSetting("uav2", emulator={"weak_fraction": 0.5, "weak_logit_drop": 6.0}))
    sim = Simulation(sc, 1, frames=45)
    frames = list(sim.frames())
    weak = {v["uav"]: v.get("weak_track_ids") for v in sim.facts()["videos"]}
    assert weak["uav1"] is None and len(weak["uav2"]) == round(0.5 * sim._objects_per_world)
    plain = list(Simulation(_coop(), 1, frames=45).frames())
    # the same frames without the setting: uav1's do not change, uav2's weak objects' best scores fall
    for f, g in zip(frames, plain, strict=True):
        if f.uav == "uav1":
            assert np.array_equal(f.candidates.scores, g.candidates.scores)
    weak_set = set(weak["uav2"])
    weak_now, weak_before = _best_scores(frames, "uav2", weak_set), _best_scores(plain, "uav2", weak_set)
    assert len(weak_now) > 20 and np.mean(weak_now) < np.mean(weak_before) - 0.2
    summary = write_dataset(sc, tmp_path / "d", seed=1, frames=45)
    truth = json.loads((tmp_path / "d" / "truth.json").read_text())
    assert "weak_fraction" not in truth["scenario"]["emulator"]  # the scenario-wide emulator has none
    assert truth["scenario"]["uav_settings"][0]["uav"] == "uav2"
    assert [v.get("weak_track_ids") for v in truth["videos"]] == [None, weak["uav2"]]
    assert summary["images"] == 90


def _best_scores(frames, uav: str, track_ids: set[int]) -> list[float]:
    """The best candidate score (IoU >= 0.5, else 0) of each visible object of `track_ids` in `uav`'s frames."""
    out = []
    for f in frames:
        if f.uav != uav:
            continue
        boxes = f.candidates.boxes_xywh
        for o in f.objects:
            if not (o.visible and o.track_id in track_ids):
                continue
            x, y, w, h = o.bbox_xywh
            iw = np.clip(np.minimum(x + w, boxes[:, 0] + boxes[:, 2]) - np.maximum(x, boxes[:, 0]), 0, None)
            ih = np.clip(np.minimum(y + h, boxes[:, 1] + boxes[:, 3]) - np.maximum(y, boxes[:, 1]), 0, None)
            inter = iw * ih
            iou = inter / (w * h + boxes[:, 2] * boxes[:, 3] - inter)
            out.append(float(f.candidates.scores[iou >= 0.5].max(initial=0.0)))
    return out


def test_scenarios_without_settings_write_the_same_truth_as_before(tmp_path):
    write_dataset("coop", tmp_path / "d", seed=0, frames=5)
    truth = json.loads((tmp_path / "d" / "truth.json").read_text())
    assert "uav_settings" not in truth["scenario"] and "weak_fraction" not in truth["scenario"]["emulator"]
    assert all("weak_track_ids" not in v for v in truth["videos"])


def _rows() -> list[dict]:
    rows = []
    for seed, (own1, joint1, own2, joint2) in enumerate(((60.0, 68.0, 80.0, 80.2), (62.0, 66.0, 81.0, 80.0))):
        for uav, own, joint in (("uav1", own1, joint1), ("uav2", own2, joint2)):
            for variant, ap in (("baseline", own - 5), (OWN, own), ("joint map boosting", joint - 1), (JOINT, joint)):
                rows.append({"domain": "coop-glare-east", "split": "heldout", "seed": seed, "uav": uav,
                             "variant": variant, "AP50": ap, "AP50_hidden_ignored": ap,
                             "hidden_detected": float("nan")})
    return rows


def test_the_summary_asks_the_gain_of_the_weaker_uav_and_no_loss_of_the_other():
    summary = summarise(_rows(), [get_coop_domain("coop-glare-east")])
    by = {s["uav"]: s for s in summary}
    assert by["uav1"]["weaker"] and not by["uav2"]["weaker"]
    assert by["uav1"]["gain"] == pytest.approx(6.0) and by["uav2"]["gain"] == pytest.approx(-0.4)
    assert math.isnan(by["uav1"][f"hidden_detected|{OWN}"])
    rows = acceptance(summary)
    assert [(r["value"], r["ok"]) for r in rows] == [(pytest.approx(6.0), True), (pytest.approx(-0.4), True)]
    worse = summarise([{**r, "AP50": r["AP50"] - 2.0} if r["uav"] == "uav1" and r["variant"] == JOINT else r
                       for r in _rows()], [get_coop_domain("coop-glare-east")])
    assert [r["ok"] for r in acceptance(worse)] == [False, True]
    text = markdown({"seeds": [0, 1], "noise_scale": 1.0, "summary": summary, "acceptance": rows})
    assert "| coop-glare-east | uav1 (w) | 56.0 | 61.0 | 67.0 | +6.0 | - / - |" in text


def test_a_small_domain_runs_end_to_end_from_the_cli(tmp_path, capsys):
    # one tuning domain cut to 1.5 s: every UAV reported with the detector, its own map and the joint map
    small = dataclasses.replace(get_coop_domain("coop-trees"), clip_s=1.5)
    report = run_coop_domain_eval([small], [0], out_dir=tmp_path / "eval")
    assert {s["uav"] for s in report["summary"]} == {"uav1", "uav2"}
    assert all(0.0 <= s[f"AP50|{JOINT}"] <= 100.0 for s in report["summary"])
    # the joint registration against the truth, for the joint map's variant only
    assert all(s[f"registration_offset_px|{JOINT}"] > 0 and s[f"registration_left_px|{JOINT}"] >= 0
               for s in report["summary"])
    assert all(math.isnan(s[f"registration_offset_px|{OWN}"]) for s in report["summary"])
    text = (tmp_path / "eval" / "report.md").read_text()
    assert text.startswith("# uavmm eval --tasks coop --domains") and " px -> " in text
    assert report["acceptance"] == []  # a tuning domain: no held-out rows
    # the joint variant is tracked, and its tracks go through the fusion server's global tracker
    (cross,) = report["cross_summary"]
    assert cross["domain"] == "coop-trees" and cross["seeds"] == 1
    assert all(0.0 <= cross[m] <= 100.0 for m in ("IDF1", "IDF1_first_look", "IDF1_separate"))
    assert "## One object, one id across UAVs (joint variant)" in text
    assert main(["eval", "--tasks", "coop", "--domains", "coop-nowhere", "--out", str(tmp_path / "x")]) == 2
    assert "unknown coop domain" in capsys.readouterr().err
    assert main(["eval", "--tasks", "coop,tracking", "--domains", "tune", "--out", str(tmp_path / "x")]) == 2
    assert "coop runs alone" in capsys.readouterr().err
    assert main(["eval", "--tasks", "coop", "--domains", "tune", "--noise-scales", "1,2", "--out",
                 str(tmp_path / "x")]) == 2
    assert "one noise scale" in capsys.readouterr().err
    assert main(["eval", "--tasks", "coop", "--list-domains"]) == 0
    assert "| coop-glare-east | heldout |" in capsys.readouterr().out
    # --config reaches the domains' runs (it was ignored there until 28 Nov 2026); a bad one is named first
    bad = tmp_path / "bad.json"
    bad.write_text('{"fragment_iou": 1.5}')
    assert main(["eval", "--tasks", "coop", "--domains", "tune", "--config", str(bad), "--out",
                 str(tmp_path / "x")]) == 2
    assert "fragment_iou" in capsys.readouterr().err
    paper_boost = run_coop_domain_eval([small], [0], out_dir=tmp_path / "eval0",
                                       config=PipelineConfig(fragment_iou=0.0))
    assert paper_boost["config_overrides"] == {"fragment_iou": 0.0} and report["config_overrides"] == {}
    assert paper_boost["size_filter"] is None  # a plain config carries no fitted filter
    assert "Settings: fragment_iou = 0.0 (--config)" in (tmp_path / "eval0" / "report.md").read_text()
    own = {s["uav"]: s[f"AP50|{OWN}"] for s in report["summary"]}
    assert {s["uav"]: s[f"AP50|{OWN}"] for s in paper_boost["summary"]} != own
    # and a `uavmm tune` parameters file's fitted size filter with it (dropped until 28 Nov 2026): here one that
    # takes every object for 100 m across (the size check widens it to the confident boxes, SizeFilterCheck, but
    # the filter still changes what the single-frame detector keeps)
    builtin = SizeFilter.builtin()
    absurd = SizeFilter({name: SizeBand(b.depression_deg, tuple(math.log(100.0) for _ in b.mean_log_m),
                                        tuple(0.05 for _ in b.std_log)) for name, b in builtin.bands.items()})
    params = tmp_path / "params.json"
    params.write_text(json.dumps(make_params({"fragment_iou": 0.0}, absurd, {"by": "test"})))
    config, size_filter = coop_params(params)
    assert config == PipelineConfig(fragment_iou=0.0) and size_filter == absurd
    assert coop_params(None) == (None, None)
    fitted = run_coop_domain_eval([small], [0], out_dir=tmp_path / "eval1", config=config, size_filter=size_filter)
    assert fitted["size_filter"] == absurd.to_dict() and report["size_filter"] is None
    priors = {s["uav"]: s["AP50|baseline"] for s in paper_boost["summary"]}
    assert all(s["AP50|baseline"] != pytest.approx(priors[s["uav"]], abs=0.05) for s in fitted["summary"])


def test_the_coop_noise_scale_defaults_to_one():
    # `uavmm eval --tasks coop --domains all` without --noise-scales crashed on None before 28 Nov 2026
    assert coop_noise_scale(None) == 1.0 and coop_noise_scale("0.5") == 0.5
    with pytest.raises(ValueError, match="one noise scale"):
        coop_noise_scale("1,2")
    with pytest.raises(ValueError, match=">= 0"):
        coop_noise_scale("-1")


def test_coop_domain_is_a_dataclass_of_its_own():
    d = get_coop_domain("coop-sea-rates")
    assert isinstance(d, CoopDomain) and d.frames() == 360 and d.weaker == "uav1"
    assert d.tag == dataclasses.replace(d).tag != dataclasses.replace(d, clip_s=10.0).tag


def test_the_cross_uav_summary_is_the_flat_joint_variants_not_mixed_with_its_dem_run():
    """Over a terrain evaluate_coop also tracks the joint variant on the DEM: its cross rows were averaged in."""
    from sim.coop_domains import get_coop_domain
    from sim.cross_uav import CROSS_METRICS

    domain = get_coop_domain("coop-glare")
    rows = [{"domain": domain.name, "seed": 0, "variant": JOINT, **dict.fromkeys(CROSS_METRICS, 80.0)},
            {"domain": domain.name, "seed": 0, "variant": JOINT + " + DEM", **dict.fromkeys(CROSS_METRICS, 40.0)},
            {"domain": domain.name, "seed": 1, "variant": JOINT, **dict.fromkeys(CROSS_METRICS, 90.0)}]
    (row,) = summarise_cross(rows, [domain])
    assert row["seeds"] == 2 and row["IDF1"] == 85.0 and row["same_id"] == 85.0

"""Evaluation domains: every domain builds a valid scenario, the split is disjoint, the telemetry defects
do what they say, and `uavmm eval --domains` runs a grid and reports the held-out split apart."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.dataset import Dataset, VideoTelemetry, iter_video_frames
from shared.geo import Camera, latlon_to_local
from sim.dataset import write_dataset
from sim.domain_eval import run_domain_eval
from sim.domains import DOMAINS, HELDOUT_DOMAINS, TUNING_DOMAINS, Domain, domain_table, get_domain, resolve_domains
from sim.flight import KeyframeFlight
from sim.noise import TelemetryNoise, TelemetryStream

REPO = Path(__file__).resolve().parents[2]


def test_every_domain_builds_and_the_split_is_disjoint() -> None:
    assert TUNING_DOMAINS and HELDOUT_DOMAINS and not set(TUNING_DOMAINS) & set(HELDOUT_DOMAINS)
    assert {d.motion for d in DOMAINS.values() if d.split == "heldout"} == {"gentle", "sweeps", "jumps"}
    # view-jump (re-ID) domains on both sides of the split, with and without appearance descriptors
    for split in ("tune", "heldout"):
        jumps = [d for d in DOMAINS.values() if d.split == split and d.motion == "jumps"]
        assert {d.descriptors for d in jumps} == {True, False} and len({d.fps for d in jumps}) >= 2
    assert {d.fps for d in DOMAINS.values()} >= {24.0, 30.0, 60.0}
    assert {d.camera for d in DOMAINS.values()} >= {"4k", "1080p-wide", "4k-tele"}
    for d in DOMAINS.values():
        sc = d.scenario()
        assert sc.name == d.name and sc.fps == d.fps and sc.default_frames == d.frames()
        assert d.frames(full=True) == pytest.approx(5 * d.frames(), abs=1)
    assert [d.name for d in resolve_domains(["heldout", HELDOUT_DOMAINS[0]])] == list(HELDOUT_DOMAINS)
    assert "| domain | split |" in domain_table()
    with pytest.raises(ValueError, match="unknown domain 'nope'"):
        get_domain("nope")
    with pytest.raises(ValueError, match="camera"):
        dataclasses.replace(DOMAINS[TUNING_DOMAINS[0]], camera="8k")


def test_the_clock_domains_are_held_out_twins_that_differ_in_their_clocks_alone() -> None:
    local, agree = DOMAINS["sea-sds-clocks"], DOMAINS["sea-sds-clocks-agree"]
    assert local.split == agree.split == "heldout" and local.motion == agree.motion == "gentle"
    assert "reference twin" in agree.description
    assert dataclasses.replace(agree, name=local.name, description=local.description, noise=local.noise) == local
    a, b = local.scenario().noise, agree.scenario().noise
    assert (a.meta_layout, a.stamp_resolution_s, a.frame_clock_utc_offset_s) == ("flight_log", 1.0, 7200.0)
    assert (b.meta_layout, b.stamp_resolution_s, b.frame_clock_utc_offset_s) == ("seadronessee", 0.0, 0.0)
    assert dataclasses.replace(a, meta_layout=b.meta_layout, stamp_resolution_s=0.0, frame_clock_utc_offset_s=0.0) == b
    assert a.telemetry_hz == 10.0 and 0.0 <= a.time_offset_s <= 0.1
    assert local.fps == 30.0 and local.camera == "4k"
    # the camera pans like a pilot: 5-15 deg/s at its peak, not the sweeps' 40-100
    rates = []
    for k, spec in enumerate(local.flights):
        flight = spec.build(np.random.default_rng(k), local.clip_s)
        rates += [abs(flight.state(t).heading_rate_deg_s) for t in np.arange(0.0, local.clip_s, 0.1)]
    assert 4.0 < max(rates) <= 15.5


def test_the_agent_reads_the_sds_clocks_domain_onto_the_frame_clock(tmp_path: Path) -> None:
    """Every frame with meta gets a pose; the clock stage finds the +2 h zone (frame - stamp) and the
    whole-second stamps; the frames' times are local (UTC + 2 h)."""
    out = tmp_path / "sds"
    write_dataset(DOMAINS["sea-sds-clocks"].scenario(), out, seed=1, frames=90, progress=False)
    coco = json.loads((out / "images.json").read_text())
    dataset = Dataset.from_dict(coco)
    camera = Camera.from_file(out / "camera.json")
    truth_t = {p["image_id"]: p["t"] for p in json.loads((out / "truth.json").read_text())["poses"]}
    assert len(dataset.videos) == 2
    for video_id in dataset.videos:
        report, problems = VideoTelemetry(), []
        frames = list(iter_video_frames(dataset, camera, video_id, fps=30.0, problems=problems, report=report))
        assert len(frames) == 90
        assert all(f.pose is not None for f in frames if f.image.meta is not None)
        assert all(p.reason == "no meta" for p in problems)
        assert sum(f.pose is not None for f in frames) >= 85
        assert report.clock.zone_offset_s == 7200.0 and report.clock.whole_seconds and report.clock.stamps_used
        assert 0.0 < report.clock.residual_s < 1.2  # latency and the whole-second cut, left to the next stage
        assert report.clock.samples > 20  # 10 Hz samples recognised under the shared whole-second stamps
        assert all(f.t - truth_t[f.image.id] == pytest.approx(7200.0, abs=1e-5) for f in frames)


def _metas(noise: TelemetryNoise, frames: int, fps: float = 30.0) -> list[dict]:
    flight = KeyframeFlight([0.0], [10.0], [-20.0], [40.0], [45.0], [30.0])
    stream = TelemetryStream(noise, flight, np.random.default_rng(3), 48.53, 9.06, 1685613600.0)
    return [stream.meta(f / fps)[0] for f in range(frames)]


def test_gps_decimals_and_altitude_steps_round_the_log() -> None:
    for meta in _metas(TelemetryNoise(gps_decimals=4, altitude_step_m=0.5), 20):
        assert round(meta["gps_latitude"], 4) == meta["gps_latitude"]
        assert round(meta["gps_longitude"], 4) == meta["gps_longitude"]
        assert math.isclose(meta["altitude"] / 0.5, round(meta["altitude"] / 0.5), abs_tol=1e-6)


def test_white_jitter_at_the_frame_rate_changes_every_frame() -> None:
    base = TelemetryNoise(telemetry_hz=30.0, gps_bias_m=0, gps_jitter_m=0, heading_jitter_deg=0, heading_bias_deg=0)
    quiet = _metas(base, 30)
    noisy = _metas(dataclasses.replace(base, white_heading_deg=1.0, white_gps_m=1.0), 30)
    d_heading = np.diff([m["gimbal_heading"] for m in noisy])
    assert np.count_nonzero(np.abs(d_heading) > 1e-3) >= 28 and 0.5 < np.std(d_heading) < 3.0
    assert np.ptp([m["gimbal_heading"] for m in quiet]) < 1e-6
    e, n = latlon_to_local(np.array([m["gps_latitude"] for m in noisy]), np.array([m["gps_longitude"] for m in noisy]),
                           48.53, 9.06)
    assert 0.3 < float(np.std(np.diff(e))) < 3.0


def test_defects_off_leave_the_telemetry_as_it_was() -> None:
    a = _metas(TelemetryNoise(), 40)
    b = _metas(TelemetryNoise(white_gps_m=0.0, gps_decimals=0, time_offset_drift=0.0), 40)
    assert a == b


def test_a_drifting_offset_grows_with_time() -> None:
    flight = KeyframeFlight([0.0], [0.0], [0.0], [40.0], [45.0], [0.0])
    stream = TelemetryStream(TelemetryNoise(time_offset_s=0.1, time_offset_drift=0.02), flight,
                             np.random.default_rng(0), 48.53, 9.06, 0.0)
    assert stream.offset_s(0.0) == pytest.approx(0.1) and stream.offset_s(10.0) == pytest.approx(0.3)


def test_domain_eval_reports_tuning_and_heldout_apart(tmp_path: Path) -> None:
    tiny = [dataclasses.replace(DOMAINS[TUNING_DOMAINS[0]], clip_s=0.7),
            dataclasses.replace(DOMAINS[HELDOUT_DOMAINS[0]], clip_s=0.7)]
    report = run_domain_eval(tiny, [0], noise_scales=(1.0,), tasks=("detection",), out_dir=tmp_path)
    assert {s["split"] for s in report["detection"]} == {"tune", "heldout"}
    row = report["detection"][0]
    assert {"AP50_baseline", "AP50_ours", "AP50_paper", "gain_ours"} <= set(row)
    assert any("held-out" in a["criterion"] for a in report["acceptance"])
    md = (tmp_path / "report.md").read_text()
    assert "| heldout |" in md and "paper rule" in md
    assert json.loads((tmp_path / "report.json").read_text())["domains"] == [d.name for d in tiny]


def test_domain_eval_tracking_reports_the_position_error_of_ours_beside_hota(tmp_path: Path) -> None:
    tiny = [dataclasses.replace(DOMAINS["sea-sds-clocks"], clip_s=2.0)]
    report = run_domain_eval(tiny, [0], noise_scales=(1.0,), tasks=("tracking",), out_dir=tmp_path)
    rows = {r["variant"]: r for r in report["tracking_rows"]}
    assert rows["norfair (pixel IoU)"]["pos_err_m"] is None and rows["norfair (pixel IoU)"]["pos_err_n"] is None
    ours = rows["GPS tracker + memory map"]
    assert ours["pos_err_n"] > 50 and 0.0 < ours["pos_err_m"] <= ours["pos_err_p90_m"] < 15.0
    (s,) = report["tracking"]
    assert s["pos_err_m_ours"] == pytest.approx(ours["pos_err_m"]) and s["pos_err_m_norfair"] is None
    assert {"HOTA_ours", "HOTA_norfair", "IDs_ours", "IDs_norfair", "pos_err_p90_m_ours"} <= set(s)
    md = (tmp_path / "report.md").read_text()
    assert "| IDs norfair | IDs ours | pos err ours m | pos err p90 ours m |" in md
    line = next(x for x in md.splitlines() if x.startswith("| heldout | sea-sds-clocks |"))
    assert line.endswith(f"| {ours['pos_err_m']:.2f} | {ours['pos_err_p90_m']:.2f} |")
    saved = json.loads((tmp_path / "report.json").read_text())
    assert saved["tracking"][0]["pos_err_m_ours"] == pytest.approx(ours["pos_err_m"])


def test_cli_lists_domains_and_refuses_unknown_ones() -> None:
    proc = subprocess.run([sys.executable, "-m", "uavmm", "eval", "--list-domains"], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and all(name in proc.stdout for name in DOMAINS)
    proc = subprocess.run([sys.executable, "-m", "uavmm", "eval", "--domains", "nope"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "unknown domain 'nope'" in proc.stderr
    assert isinstance(DOMAINS[TUNING_DOMAINS[0]], Domain)


def test_final_output_domains_give_the_detectors_post_nms_thresholded_results(tmp_path: Path) -> None:
    from agent.boxes import box_iou
    from sim.domain_eval import ensure_domain_dataset

    domain = get_domain("sea-sds-final")
    assert domain.split == "heldout" and domain.fps == 2.0 and domain.final_score == 0.25
    assert DOMAINS["sea-jitter"].tag == "fbcdf83b"  # domains without the field keep their cached datasets
    data = ensure_domain_dataset(domain, 0, 1.0, False, tmp_path)
    entries = json.loads((data / "pre_nms.json").read_text())
    assert entries and min(e["score"] for e in entries) >= 0.25
    by_key: dict[tuple[int, int], list[list[float]]] = {}
    for e in entries:
        x, y, w, h = e["bbox"]
        by_key.setdefault((e["image_id"], e["category_id"]), []).append([x, y, x + w, y + h])
    for boxes in by_key.values():  # NMS at 0.5: no two kept boxes of a class overlap that much
        b = np.array(boxes)
        iou = box_iou(b, b)
        np.fill_diagonal(iou, 0.0)
        assert iou.max(initial=0.0) <= 0.5 + 1e-6
    with pytest.raises(ValueError, match="final_score"):
        dataclasses.replace(domain, final_score=1.5)


def test_view_jump_domains_report_norfair_ours_and_ours_on_motion_alone_with_the_reid_bars(tmp_path: Path) -> None:
    from sim.domain_eval import GPS_MOTION, JUMPS_HOTA_MARGIN, JUMPS_IDF1_MARGIN, JUMPS_MIN_IDF1, jumps_acceptance

    tiny = [dataclasses.replace(DOMAINS["sea-jumps-desc"], clip_s=4.0)]
    assert tiny[0].split == "heldout" and tiny[0].motion == "jumps" and tiny[0].descriptors
    report = run_domain_eval(tiny, [0], noise_scales=(1.0,), tasks=("tracking",), out_dir=tmp_path)
    variants = {r["variant"] for r in report["tracking_rows"]}
    assert variants == {"norfair (pixel IoU)", "GPS tracker + memory map", GPS_MOTION}
    (s,) = report["tracking"]
    assert {"HOTA_motion", "IDF1_motion", "IDs_motion", "reid_kept_ours", "reid_scored_ours"} <= set(s)
    assert 0 <= s["reid_kept_ours"] <= s["reid_scored_ours"]
    rows = [a for a in report["acceptance"] if a["criterion"].startswith("sea-jumps-desc:")]
    bars = [f">= {JUMPS_MIN_IDF1:g}", f">= +{JUMPS_IDF1_MARGIN:g}", f">= +{JUMPS_HOTA_MARGIN:g}"]
    assert [a["bar"] for a in rows] == bars
    assert rows[0]["ok"] == (s["IDF1_ours"] >= 60.0)
    assert rows[1]["value"] == pytest.approx(s["IDF1_ours"] - s["IDF1_norfair"])
    md = (tmp_path / "report.md").read_text()
    assert "## Re-ID with view jumps" in md
    assert any(line.startswith("| heldout | sea-jumps-desc |") and line.count("/") >= 8 for line in md.splitlines())
    # the bars themselves: a domain just past them holds, one just short fails each in turn
    past = {"domain": "d", "IDF1_ours": 61.0, "IDF1_norfair": 35.0, "HOTA_ours": 40.0, "HOTA_norfair": 24.0}
    assert all(a["ok"] for a in jumps_acceptance(past))
    assert [a["ok"] for a in jumps_acceptance({**past, "IDF1_ours": 59.9, "IDF1_norfair": 20.0})] == [False, True, True]
    assert [a["ok"] for a in jumps_acceptance({**past, "IDF1_norfair": 36.5})] == [True, False, True]
    assert [a["ok"] for a in jumps_acceptance({**past, "HOTA_norfair": 25.5})] == [True, True, False]


def test_a_domain_without_descriptors_writes_the_same_boxes_without_embeddings(tmp_path: Path) -> None:
    with_desc = dataclasses.replace(DOMAINS["grass-jumps-desc-wide"], clip_s=0.5)
    without = dataclasses.replace(with_desc, descriptors=False)
    assert with_desc.tag != without.tag
    assert without.changes()["descriptors"] == "none" and "descriptors" not in with_desc.changes()
    a, b = tmp_path / "a", tmp_path / "b"
    write_dataset(with_desc.scenario(), a, seed=0, frames=with_desc.frames(), progress=False)
    write_dataset(without.scenario(), b, seed=0, frames=without.frames(), progress=False)
    pa, pb = json.loads((a / "pre_nms.json").read_text()), json.loads((b / "pre_nms.json").read_text())
    assert any("embedding" in c for c in pa) and not any("embedding" in c for c in pb)
    assert len(pa) > 0 and [c["bbox"] for c in pa] == [c["bbox"] for c in pb]


def test_the_far_group_flies_below_the_usual_pitch_floor_apart_from_the_grid() -> None:
    from sim.domains import FAR_DOMAINS, HELDOUT_DOMAINS, resolve_domains
    from sim.flight import MIN_PITCH_DEG, HoverSweepsSpec

    far = resolve_domains(["far"])
    assert [d.name for d in far] == list(FAR_DOMAINS) == ["sea-far-tele", "sea-farther-tele", "grass-far-tele",
                                                             "grass-farther-tele", "grass-trees-far-tele"]
    assert not set(FAR_DOMAINS) & {d.name for d in resolve_domains(["all"])}
    assert {d.split for d in far} == {"tune", "heldout"} and "grass-far-tele" not in HELDOUT_DOMAINS
    assert all(f.pitch_deg[0] < MIN_PITCH_DEG and f.min_pitch_deg == 3.0 for d in far for f in d.flights)
    with pytest.raises(ValueError, match="pitch_deg"):
        HoverSweepsSpec(pitch_deg=(5.0, 9.0))  # the usual floor still holds
    with pytest.raises(ValueError, match="min_pitch_deg"):
        HoverSweepsSpec(pitch_deg=(2.0, 9.0), min_pitch_deg=2.0)

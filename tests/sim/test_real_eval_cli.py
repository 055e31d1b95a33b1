"""`uavmm eval --real` on a small COCO file with meta and its detector's candidates (a simulated flight written in the
real layout's place): the per-class report, and `--dem` (DESIGN 5: on every command that georeferences)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agent.dem import write_npz
from shared.terrain import ElevationGrid
from sim.dataset import write_dataset
from uavmm.cli import main


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("real") / "data"
    write_dataset("reid", out, seed=3, frames=30, progress=False)
    return out


def _eval(d: Path, out: Path, *extra: str) -> dict:
    assert main(["eval", "--real", str(d / "images.json"), "--detections", str(d / "pre_nms.json"), "--camera",
                 str(d / "camera.json"), "--out", str(out), *extra]) == 0
    return json.loads((out / "real" / "report.json").read_text())


def _dem(path: Path, elevation: float) -> Path:
    write_npz(path, ElevationGrid(np.full((3, 3), elevation), lat0_deg=48.54, lon0_deg=9.05, lat_step_deg=-0.01,
                                  lon_step_deg=0.01))
    return path


def test_eval_real_takes_a_dem_and_a_flat_one_changes_nothing(data, tmp_path):
    flat = _eval(data, tmp_path / "flat")
    assert [row["class"] for row in flat["rows"]] == ["all", "person"]
    on_dem = _eval(data, tmp_path / "dem", "--dem", str(_dem(tmp_path / "flat.npz", 120.0)),
                   "--takeoff-elevation-m", "120")
    for a, b in zip(on_dem["rows"], flat["rows"], strict=True):  # the ray meets a flat DEM by iteration: AR
        assert {k: v for k, v in a.items() if "AR" not in k} == {k: v for k, v in b.items() if "AR" not in k}
        assert [a[k] for k in a if "AR" in k] == pytest.approx([b[k] for k in b if "AR" in k], abs=0.1)
    # ground 25 m above the take-off point under the whole flight: every box lands elsewhere, the figures move
    raised = _eval(data, tmp_path / "raised", "--dem", str(_dem(tmp_path / "raised.npz", 145.0)),
                   "--takeoff-elevation-m", "120")
    assert raised["rows"] != flat["rows"]


@pytest.mark.parametrize("flag", [["--dem", "x.npz"], ["--takeoff-elevation-m", "120"]])
def test_terrain_flags_without_real_are_refused(capsys, flag):
    assert main(["eval", *flag, "--list-domains"]) == 2
    assert "--dem and --takeoff-elevation-m go with --real" in capsys.readouterr().err


def test_ids_and_scores_written_as_text_are_scored_as_numbers(data, tmp_path):
    """Results with "image_id": "3464", "category_id": "1", "score": "0.58": the pipeline variants read them, the
    detector's own row was scored raw (0 AP50 beside the variants', a gain of +88; or a pycocotools traceback)."""
    plain = _eval(data, tmp_path / "plain")
    results = json.loads((data / "pre_nms.json").read_text())
    as_text = [{**r, "image_id": str(r["image_id"]), "category_id": str(r["category_id"]), "score": str(r["score"])}
               for r in results]
    (tmp_path / "text.json").write_text(json.dumps(as_text))
    assert main(["eval", "--real", str(data / "images.json"), "--detections", str(tmp_path / "text.json"),
                 "--camera", str(data / "camera.json"), "--out", str(tmp_path / "text")]) == 0
    text = json.loads((tmp_path / "text" / "real" / "report.json").read_text())
    assert [r["AP50 detector"] for r in text["rows"]] == [r["AP50 detector"] for r in plain["rows"]]


def _eval_with(data: Path, tmp_path: Path, name: str, results: list) -> tuple[int, Path]:
    (tmp_path / f"{name}.json").write_text(json.dumps(results))
    code = main(["eval", "--real", str(data / "images.json"), "--detections", str(tmp_path / f"{name}.json"),
                 "--camera", str(data / "camera.json"), "--out", str(tmp_path / name)])
    return code, tmp_path / name / "real" / "report.json"


def test_boxes_the_pipeline_skips_are_skipped_for_the_detector_too(data, tmp_path):
    # probe: zero-size and non-finite boxes were scored as the detector's false positives, never as the variants'
    plain = _eval(data, tmp_path / "plain")
    results = json.loads((data / "pre_nms.json").read_text())
    junk = [{**r, "bbox": [r["bbox"][0], r["bbox"][1], 0.0, r["bbox"][3]], "score": 0.99} for r in results[:40]]
    code, report = _eval_with(data, tmp_path, "junk", results + junk)
    assert code == 0
    got = json.loads(report.read_text())
    assert got["rows"] == plain["rows"]
    assert got["skipped_detections"] == {"non_positive_size": 40}
    assert "non_positive_size 40" in (report.parent / "report.md").read_text()


@pytest.mark.parametrize(("scale", "hint"), [(100.0, "percentages? divide them by 100"), (None, "boosted scores")])
def test_scores_outside_zero_one_are_refused_naming_them(data, tmp_path, capsys, scale, hint):
    # probe: 611 boosted scores above 1 read as boat 86.2 (detector) -> 27.4 (memory off), gain -21; percentages
    # gave every variant 0.0
    results = json.loads((data / "pre_nms.json").read_text())
    if scale is None:  # a boosted output: some scores above 1
        changed = [{**r, "score": r["score"] * 1.6} for r in results]
    else:
        changed = [{**r, "score": r["score"] * scale} for r in results]
    bad = sum(not 0 <= r["score"] <= 1 for r in changed)
    code, report = _eval_with(data, tmp_path, f"scores{scale}", changed)
    err = capsys.readouterr().err
    assert code == 2 and not report.exists()
    assert f"{bad} of the detections have a score outside [0, 1]" in err and hint in err


def test_a_nan_score_is_skipped_in_every_column_not_refused(data, tmp_path):
    # probe (review): one NaN among 2,522 scores refused the whole file ("outside [0, 1]: e.g. nan"); the loader skips
    # NaN scores (detectors emit them), so the detector's column does too, and the count is said under the table
    plain = _eval(data, tmp_path / "plain")
    results = json.loads((data / "pre_nms.json").read_text())
    with_nan = results + [{**results[0], "score": float("nan")}]
    (tmp_path / "nan.json").write_text(json.dumps(with_nan))  # NaN as JSON's NaN token, as Python writes it
    code, report = _eval_with(data, tmp_path, "nan", with_nan)
    assert code == 0
    got = json.loads(report.read_text())
    assert got["rows"] == plain["rows"] and got["skipped_detections"] == {"score_out_of_range": 1}


def test_a_bad_score_on_a_box_skipped_anyway_does_not_refuse_the_file(data, tmp_path):
    # probe (second review): a zero-width box scored 1.5 beside a NaN score refused the file, though every column
    # skips that box for its size
    plain = _eval(data, tmp_path / "plain")
    results = json.loads((data / "pre_nms.json").read_text())
    r = results[0]
    extra = [{**r, "bbox": [r["bbox"][0], r["bbox"][1], 0.0, r["bbox"][3]], "score": 1.5},
             {**r, "score": float("nan")}, {**r, "score": float("inf")}]
    code, report = _eval_with(data, tmp_path, "mixed", results + extra)
    assert code == 0
    got = json.loads(report.read_text())
    assert got["rows"] == plain["rows"]
    assert got["skipped_detections"] == {"non_positive_size": 1, "score_out_of_range": 2}

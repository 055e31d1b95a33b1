"""`uavmm tune`: PARAMS.json from an annotated set, read back by boost/track, and its bad-input errors."""

from __future__ import annotations

import json

import pytest

from agent.boost import load_params
from agent.params_file import PARAMS_FORMAT
from agent.pipeline_config import PipelineConfig
from agent.tune import SEARCH_SPACE, tune
from tests.agent.test_boost_cli import make_dataset, run_boost
from uavmm.cli import main


def _two_videos(d):
    """make_dataset's flight twice, as videos 1 and 2 (ids of the second shifted)."""
    coco = json.loads((d / "images.json").read_text())
    cands = json.loads((d / "pre_nms.json").read_text())
    n = len(coco["images"])
    coco["images"] += [{**im, "id": im["id"] + n, "video_id": 2} for im in coco["images"]]
    coco["annotations"] += [{**a, "id": a["id"] + n, "image_id": a["image_id"] + n} for a in coco["annotations"]]
    coco["videos"].append({"id": 2, "name": "v2"})
    cands += [{**c, "image_id": c["image_id"] + n} for c in cands]
    (d / "images.json").write_text(json.dumps(coco))
    (d / "pre_nms.json").write_text(json.dumps(cands))
    return d


def run_tune(d, *extra):
    return main(["tune", "--frames", str(d / "images.json"), "--candidates", str(d / "pre_nms.json"),
                 "--camera", str(d / "camera.json"), "--out", str(d / "params.json"), "--quiet", *extra])


def test_tune_writes_params_that_boost_reads(tmp_path, capsys):
    d = make_dataset(tmp_path)
    assert run_tune(d, "--no-holdout") == 0
    out = capsys.readouterr().out
    assert "AP50: no memory" in out and "wrote" in out
    params = json.loads((d / "params.json").read_text())
    assert params["format"] == PARAMS_FORMAT and params["version"] == 1
    report = params["tuned_on"]
    # the search never ends below where it started, and memory beats the single-frame baseline here
    assert report["AP50_tuned"] >= report["AP50_start"] > report["AP50_no_memory"]
    assert set(params["pipeline"]["memory"]) | set(params["pipeline"]) - {"memory"} == {n for n, _ in SEARCH_SPACE}
    config, size_filter = load_params(d / "params.json")
    assert config.memory.gain_per_s == params["pipeline"]["memory"]["gain_per_s"]
    assert config.boost_weight == params["pipeline"]["boost_weight"]
    assert (size_filter is None) == (params["size_filter"] is None)
    assert run_boost(d, "--config", str(d / "params.json")) == 0
    assert json.loads((d / "results.json").read_text())


def test_tune_reports_a_held_out_video_when_there_are_two(tmp_path):
    d = _two_videos(make_dataset(tmp_path, frames=20))
    result = tune(d / "images.json", d / "pre_nms.json", d / "camera.json", passes=1)
    holdout = result.report["holdout"]
    assert holdout["tuned_on_videos"] == [1] and holdout["scored_on_videos"] == [2]
    assert 0.0 <= holdout["AP50_no_memory"] <= 100.0 and 0.0 <= holdout["AP50_tuned"] <= 100.0
    assert result.report["videos"] == 2 and result.report["images_scored"] == 40


def test_a_min_gain_out_of_reach_keeps_the_defaults(tmp_path):
    d = make_dataset(tmp_path, frames=20)
    result = tune(d / "images.json", d / "pre_nms.json", d / "camera.json", min_gain=101.0, holdout=False)
    assert result.report["steps"] == [] and result.report["AP50_tuned"] == result.report["AP50_start"]
    defaults = PipelineConfig()
    assert result.report["settings"] == {
        "memory": {"gain_per_s": defaults.memory.gain_per_s, "half_life_s": defaults.memory.half_life_s,
                   "radius_m": defaults.memory.radius_m},
        "boost_weight": defaults.boost_weight}


@pytest.mark.parametrize(("change", "message"), [
    ("no_meta", "no frame has usable meta"),
    ("no_annotations", "no 'annotations': tuning needs ground-truth boxes"),
])
def test_tune_refuses_data_it_cannot_tune_on(tmp_path, capsys, change, message):
    d = make_dataset(tmp_path, frames=10, with_meta=change != "no_meta")
    if change == "no_annotations":
        coco = json.loads((d / "images.json").read_text())
        coco["annotations"] = []
        (d / "images.json").write_text(json.dumps(coco))
    assert run_tune(d) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (d / "params.json").exists()


def test_tune_names_a_missing_output_directory(tmp_path, capsys):
    d = make_dataset(tmp_path, frames=10)
    assert main(["tune", "--frames", str(d / "images.json"), "--candidates", str(d / "pre_nms.json"),
                 "--camera", str(d / "camera.json"), "--out", str(d / "nope" / "params.json")]) == 2
    assert "output directory" in capsys.readouterr().err


@pytest.mark.parametrize(("content", "message"), [
    ({"format": PARAMS_FORMAT, "version": 9, "pipeline": {}}, "unsupported uavmm-params version 9"),
    ({"format": PARAMS_FORMAT, "version": 1, "pipeline": [], "size_filter": None}, "'pipeline' must be an object"),
    ({"format": PARAMS_FORMAT, "version": 1, "pipeline": {"nosuch": 1}}, "unknown setting 'nosuch'"),
    ({"format": PARAMS_FORMAT, "version": 1, "pipeline": {}, "extra": 1}, "unknown keys ['extra']"),
    ({"format": PARAMS_FORMAT, "version": 1, "pipeline": {}, "size_filter": {"format": "x"}}, "not a size-filter"),
])
def test_a_bad_params_file_is_one_clear_line(tmp_path, capsys, content, message):
    d = make_dataset(tmp_path, frames=5)
    (d / "bad.json").write_text(json.dumps(content))
    assert run_boost(d, "--config", str(d / "bad.json")) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.json" in err and "Traceback" not in err


def test_params_go_through_a_new_temporary_never_through_a_planted_link(tmp_path):
    """`uavmm tune` wrote ``PARAMS.json.tmp`` with a plain open() and renamed it: a link left at that name got the
    parameters (the file it points to overwritten) and PARAMS.json became the link; two runs shared the name."""
    import os

    d = make_dataset(tmp_path, frames=10)
    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    for name in ("params.json.tmp", f".params.json.{os.getpid()}.tmp"):
        (d / name).symlink_to(outside)
    assert run_tune(d, "--no-holdout", "--no-size-filter-fit") == 0
    assert outside.read_text() == "precious\n" and not (d / "params.json").is_symlink()
    assert json.loads((d / "params.json").read_text())["format"] == PARAMS_FORMAT
    assert not [p.name for p in d.iterdir() if p.name.endswith(".tmp") and not p.is_symlink()]

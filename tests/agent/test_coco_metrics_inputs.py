"""agent.coco_metrics on what real ground-truth files carry: ids written as text, malformed boxes, category names
that clash. Compared with pycocotools run directly where it reads the file right."""

from __future__ import annotations

import contextlib
import copy
import io
import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.coco_metrics import coco_detection_metrics, per_class_metrics


def _gt(categories=({"id": 1, "name": "swimmer"}, {"id": 2, "name": "boat"})) -> dict:
    boxes = {1: [[10, 10, 20, 20], [100, 100, 30, 20]], 2: [[50, 50, 40, 40]], 3: [[5, 60, 10, 12]]}
    annotations, k = [], 1
    for image_id, bs in boxes.items():
        for b in bs:
            annotations.append({"id": k, "image_id": image_id, "category_id": 1 + (k % 2 == 0), "bbox": b})
            k += 1
    return {"images": [{"id": i, "width": 640, "height": 480} for i in (1, 2, 3)], "annotations": annotations,
            "categories": list(categories)}


def _results(gt: dict) -> list[dict]:
    out = []
    for a in gt["annotations"]:
        x, y, w, h = a["bbox"]
        out.append({"image_id": a["image_id"], "category_id": a["category_id"], "bbox": [x + 1, y, w, h], "score": 0.9})
        out.append({"image_id": a["image_id"], "category_id": a["category_id"], "bbox": [x + 200, y, w, h],
                    "score": 0.95})  # a confident false positive beside each
    return out


def _pycocotools_ap50(gt: dict, res: list[dict]) -> float:
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO()
        coco.dataset = {**gt, "annotations": [{**a, "iscrowd": 0, "area": a["bbox"][2] * a["bbox"][3]}
                                              for a in gt["annotations"]]}
        coco.createIndex()
        ev = COCOeval(coco, coco.loadRes(copy.deepcopy(res)), "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return float(ev.stats[1])


def test_the_reference_figures_agree_on_a_plain_file():
    gt = _gt()
    assert coco_detection_metrics(gt, _results(gt))["AP50"] == pytest.approx(_pycocotools_ap50(gt, _results(gt)))
    assert per_class_metrics(gt, _results(gt))["all"]["AP50"] == pytest.approx(_pycocotools_ap50(gt, _results(gt)))


@given(as_text=st.sampled_from(["image_id", "category_id", "both"]), as_float=st.booleans())
@settings(max_examples=12, deadline=None)
def test_ids_written_as_text_or_floats_score_as_the_numbers(as_text, as_float):
    # probe: annotations with "image_id": "3464" scored 0.0 in every cell with "boxes 2778" (pycocotools matched none)
    gt = _gt()
    plain = per_class_metrics(gt, _results(gt))
    odd = copy.deepcopy(gt)
    for a in odd["annotations"]:
        for key in (["image_id", "category_id"] if as_text == "both" else [as_text]):
            a[key] = f"{a[key]}" if not as_float else float(a[key])
    assert per_class_metrics(odd, _results(gt)) == plain
    assert coco_detection_metrics(odd, _results(gt)) == coco_detection_metrics(gt, _results(gt))


@pytest.mark.parametrize(("change", "message"), [
    ({"bbox": [1, 2, -5, 4]}, "bbox [1, 2, -5, 4] is not [x, y, w, h]"),
    ({"bbox": [1, 2, 3]}, "bbox [1, 2, 3] is not"),
    ({"bbox": None}, "bbox None is not"),
    ({"bbox": [1, 2, "x", 4]}, "is not [x, y, w, h]"),
    ({"bbox": [1, 2, float("nan"), 4]}, "is not [x, y, w, h]"),
    ({"image_id": "3464.jpg"}, "image_id '3464.jpg' is not an integer"),
    ({"category_id": 1.5}, "category_id 1.5 is not an integer"),
    ({"category_id": 7}, "category_id 7 is not in 'categories'"),
])
def test_a_malformed_annotation_is_refused_naming_it(change, message):
    # probe: a missing or short bbox was a pycocotools traceback, a negative width a box silently dropped (all 50.0
    # against pycocotools' 100.0)
    gt = _gt()
    gt["annotations"][2].update(change)
    for metric in (per_class_metrics, coco_detection_metrics):
        with pytest.raises(ValueError, match="annotation 2 ") as info:
            metric(gt, _results(_gt()))
        assert message in str(info.value)


def test_a_malformed_annotation_through_the_cli_is_one_line_and_exit_2(tmp_path, capsys):
    from sim.dataset import write_dataset
    from uavmm.cli import main

    data = tmp_path / "data"
    write_dataset("reid", data, seed=1, frames=6, progress=False)
    coco = json.loads((data / "images.json").read_text())
    coco["annotations"][0]["bbox"] = [1.0, 2.0, 3.0]
    (data / "images.json").write_text(json.dumps(coco))
    code = main(["eval", "--real", str(data / "images.json"), "--detections", str(data / "pre_nms.json"),
                 "--camera", str(data / "camera.json"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "annotation 0" in err and "Traceback" not in err


def test_categories_that_share_a_name_or_are_named_all_keep_their_own_rows():
    # probe: a category named "all" overwrote the overall row (100.0 against pycocotools' 66.7); two named alike
    # merged into one row
    gt = _gt(({"id": 1, "name": "all"}, {"id": 2, "name": "boat"}, {"id": 3, "name": "boat"}))
    gt["annotations"][0]["category_id"] = 3
    rows = per_class_metrics(gt, _results(gt))
    assert set(rows) == {"all", "all (1)", "boat (2)", "boat (3)"}
    assert rows["all"]["AP50"] == pytest.approx(_pycocotools_ap50(gt, _results(gt)))
    assert sum(rows[k]["gt"] for k in rows if k != "all") == rows["all"]["gt"] == len(gt["annotations"])


def test_ids_written_as_long_text_keep_every_digit():
    # probe (review): "9007199254740993" went through float and lost its last digit: the box matched no image
    gt = _gt()
    big = 2**53 + 1
    gt["images"].append({"id": big, "width": 640, "height": 480})
    gt["annotations"].append({"id": 99, "image_id": str(big), "category_id": 1, "bbox": [1, 1, 10, 10]})
    res = _results(_gt()) + [{"image_id": big, "category_id": 1, "bbox": [1, 1, 10, 10], "score": 0.99}]
    rows = per_class_metrics(gt, res)
    assert rows["swimmer"]["gt"] == 3.0 and rows["all"]["gt"] == 5.0

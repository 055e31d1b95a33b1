"""Tests of the ONNX YOLO detector backend: decoding both layouts, letterbox un-mapping, names, errors.

The models are built here with onnx.helper and return known constant raw outputs (plus 0 x the sum
of the input, so the input is used), so every expected box and score is computed by hand.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from agent.detector import DETECTOR_BACKENDS, Detections, OnnxYoloDetector, make_detector  # noqa: E402
from agent.letterbox import LetterboxTransform, letterbox  # noqa: E402
from agent.yolo_format import load_class_names  # noqa: E402

N_CANDIDATES = 100  # >> 4 + C so that layout="auto" can tell the layouts apart
NUM_CLASSES = 3


def make_constant_model(
    path: Path,
    raw: np.ndarray,
    *,
    input_shape: list = (1, 3, 640, 640),  # type: ignore[assignment]
    dynamic_output: bool = False,
    metadata: dict[str, str] | None = None,
) -> Path:
    """ONNX model whose output0 is ``raw`` + 0 * sum(images).

    With ``dynamic_output`` the sum is taken per batch item, so output0's first dim is the symbolic
    batch dim of the input (onnxruntime then cannot know the output shape before a run).
    """
    if dynamic_output:
        nodes = [
            helper.make_node("ReduceSum", ["images", "axes"], ["per_item"], keepdims=0),
            helper.make_node("Unsqueeze", ["per_item", "unsqueeze_axes"], ["total"]),
        ]
        output_shape = ["batch", *raw.shape[1:]]
    else:
        nodes = [helper.make_node("ReduceSum", ["images"], ["total"], keepdims=0)]
        output_shape = list(raw.shape)
    nodes += [
        helper.make_node("Mul", ["total", "zero"], ["nothing"]),
        helper.make_node("Add", ["raw", "nothing"], ["output0"]),
    ]
    graph = helper.make_graph(
        nodes,
        "constant",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, output_shape)],
        initializer=[
            numpy_helper.from_array(raw.astype(np.float32), "raw"),
            numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
            numpy_helper.from_array(np.array([1, 2, 3], np.int64), "axes"),
            numpy_helper.from_array(np.array([1, 2], np.int64), "unsqueeze_axes"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if metadata:
        helper.set_model_props(model, metadata)
    onnx.save(model, str(path))
    return path


def v8_raw(boxes_cxcywh: np.ndarray, class_probs: np.ndarray, n: int = N_CANDIDATES) -> np.ndarray:
    """[1, 4 + C, n] with the given candidates first, zero-score filler after."""
    k, c = class_probs.shape
    raw = np.zeros((1, 4 + c, n), np.float32)
    raw[0, :4, :] = np.array([320, 320, 10, 10], np.float32)[:, None]
    raw[0, :4, :k] = boxes_cxcywh.T
    raw[0, 4:, :k] = class_probs.T
    return raw


def v5_raw(
    boxes_cxcywh: np.ndarray, objectness: np.ndarray, class_probs: np.ndarray, n: int = N_CANDIDATES
) -> np.ndarray:
    """[1, n, 5 + C] with the given candidates first, zero-score filler after."""
    k, c = class_probs.shape
    raw = np.zeros((1, n, 5 + c), np.float32)
    raw[0, :, :4] = [320, 320, 10, 10]
    raw[0, :k, :4] = boxes_cxcywh
    raw[0, :k, 4] = objectness
    raw[0, :k, 5:] = class_probs
    return raw


def image(width: int, height: int) -> np.ndarray:
    return np.zeros((height, width, 3), np.uint8)


# Candidates in 640 x 640 input pixels (cx, cy, w, h) and their class probabilities.
BOXES_IN = np.array(
    [
        [320.0, 320.0, 100.0, 50.0],  # centre of the input
        [100.0, 200.0, 40.0, 80.0],
        [600.0, 450.0, 60.0, 20.0],
        [50.0, 30.0, 20.0, 20.0],  # inside the top padding band for a 1280x720 image
    ],
    np.float32,
)
PROBS = np.array(
    [
        [0.9, 0.05, 0.0],
        [0.1, 0.2, 0.6],
        [0.005, 0.008, 0.002],  # below 0.01
        [0.5, 0.0, 0.0],
    ],
    np.float32,
)


def xyxy(boxes_cxcywh: np.ndarray) -> np.ndarray:
    cx, cy, w, h = boxes_cxcywh.T
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)


# ---------------------------------------------------------------------------------------------
# Decoding and un-letterboxing
# ---------------------------------------------------------------------------------------------


def test_v8_boxes_are_unmapped_through_the_letterbox_of_a_landscape_image(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    detector = OnnxYoloDetector(path)
    dets = detector(image(1280, 720))
    assert detector.layout == "v8"
    # 1280x720 -> gain 0.5 -> 640x360 content, 140 px of padding above and below.
    expected = xyxy(BOXES_IN[:2])
    expected[:, [1, 3]] -= 140
    expected /= 0.5
    assert len(dets) == 2  # candidate 2 below threshold, candidate 3 entirely in the padding
    np.testing.assert_allclose(dets.boxes_xyxy, expected, atol=1e-3)
    np.testing.assert_allclose(dets.scores, [0.9, 0.6], rtol=1e-6)
    np.testing.assert_array_equal(dets.class_ids, [0, 2])
    assert dets.boxes_xyxy.dtype == np.float32 and dets.scores.dtype == np.float32
    assert dets.class_ids.dtype == np.int32


def test_v8_boxes_are_unmapped_through_the_letterbox_of_a_portrait_image(tmp_path):
    boxes_in = BOXES_IN[:, [1, 0, 3, 2]]  # the landscape candidates transposed
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(boxes_in, PROBS))
    dets = OnnxYoloDetector(path)(image(720, 1280))
    # 720x1280 -> gain 0.5 -> 360x640 content, 140 px of padding left and right.
    expected = xyxy(boxes_in[:2])
    expected[:, [0, 2]] -= 140
    expected /= 0.5
    np.testing.assert_allclose(dets.boxes_xyxy, expected, atol=1e-3)
    np.testing.assert_allclose(dets.scores, [0.9, 0.6], rtol=1e-6)
    np.testing.assert_array_equal(dets.class_ids, [0, 2])


def test_box_partly_in_the_padding_is_clipped_at_the_image_edge(tmp_path):
    boxes_in = np.array([[150.0, 320.0, 40.0, 40.0]], np.float32)  # x 130..170, pad_left 140
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(boxes_in, PROBS[:1]))
    dets = OnnxYoloDetector(path)(image(720, 1280))
    np.testing.assert_allclose(dets.boxes_xyxy, [[0.0, 600.0, 60.0, 680.0]], atol=1e-3)


def test_boxes_are_clipped_to_the_image(tmp_path):
    boxes = np.array([[5.0, 320.0, 30.0, 30.0], [630.0, 320.0, 40.0, 700.0]], np.float32)
    probs = np.array([[0.5, 0, 0], [0.5, 0, 0]], np.float32)
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(boxes, probs))
    dets = OnnxYoloDetector(path)(image(640, 640))
    np.testing.assert_allclose(dets.boxes_xyxy, [[0, 305, 20, 335], [610, 0, 640, 640]], atol=1e-3)


def test_v5_score_is_objectness_times_class_probability(tmp_path):
    objectness = np.array([0.5, 0.9, 1.0, 0.02], np.float32)
    path = make_constant_model(tmp_path / "v5.onnx", v5_raw(BOXES_IN, objectness, PROBS))
    detector = OnnxYoloDetector(path)
    dets = detector(image(1280, 720))
    assert detector.layout == "v5"
    expected = xyxy(BOXES_IN[:2])
    expected[:, [1, 3]] -= 140
    expected /= 0.5
    np.testing.assert_allclose(dets.boxes_xyxy, expected, atol=1e-3)
    np.testing.assert_allclose(dets.scores, [0.5 * 0.9, 0.9 * 0.6], rtol=1e-6)
    np.testing.assert_array_equal(dets.class_ids, [0, 2])


def test_low_objectness_removes_a_candidate_with_a_high_class_probability(tmp_path):
    objectness = np.array([0.01, 0.0, 0.0, 0.0], np.float32)  # 0.01 * 0.9 < 0.01
    path = make_constant_model(tmp_path / "v5.onnx", v5_raw(BOXES_IN, objectness, PROBS))
    assert len(OnnxYoloDetector(path)(image(640, 640))) == 0


def test_threshold_keeps_scores_at_or_above_it(tmp_path):
    probs = np.array([[0.25, 0, 0], [0.2499, 0, 0], [0.5, 0, 0]], np.float32)
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN[:3], probs))
    dets = OnnxYoloDetector(path, conf_threshold=0.25)(image(640, 640))
    np.testing.assert_allclose(dets.scores, [0.25, 0.5])


def test_default_threshold_returns_low_confidence_candidates(tmp_path):
    probs = np.array([[0.011, 0, 0], [0.0099, 0, 0], [0.02, 0.03, 0]], np.float32)
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN[:3], probs))
    dets = OnnxYoloDetector(path)(image(640, 640))
    np.testing.assert_allclose(dets.scores, [0.011, 0.03], rtol=1e-6)
    np.testing.assert_array_equal(dets.class_ids, [0, 1])


@pytest.mark.parametrize("layout", ["v8", "v5"])
def test_multi_label_returns_every_pair_above_threshold(tmp_path, layout):
    probs = np.array([[0.9, 0.3, 0.0], [0.0, 0.005, 0.6]], np.float32)
    if layout == "v8":
        raw = v8_raw(BOXES_IN[:2], probs)
    else:
        raw = v5_raw(BOXES_IN[:2], np.ones(2, np.float32), probs)
    path = make_constant_model(tmp_path / "m.onnx", raw)
    dets = OnnxYoloDetector(path, multi_label=True)(image(640, 640))
    np.testing.assert_array_equal(dets.class_ids, [0, 1, 2])
    np.testing.assert_allclose(dets.scores, [0.9, 0.3, 0.6], rtol=1e-6)
    boxes = xyxy(BOXES_IN[[0, 0, 1]])
    np.testing.assert_allclose(dets.boxes_xyxy, boxes, atol=1e-3)


@pytest.mark.parametrize("layout", ["v8", "v5"])
def test_max_candidates_keeps_the_highest_scores_in_candidate_order(tmp_path, layout):
    rng = np.random.default_rng(0)
    n = 50
    scores = rng.permutation(np.linspace(0.02, 0.9, n)).astype(np.float32)
    probs = np.zeros((n, NUM_CLASSES), np.float32)
    probs[:, 1] = scores
    boxes = np.tile([[320.0, 320.0, 10.0, 10.0]], (n, 1)).astype(np.float32)
    boxes[:, 0] = np.arange(n) * 10 + 20  # tells candidates apart
    if layout == "v8":
        raw = v8_raw(boxes, probs, n=200)
    else:
        raw = v5_raw(boxes, np.ones(n, np.float32), probs, n=200)
    path = make_constant_model(tmp_path / "m.onnx", raw)
    dets = OnnxYoloDetector(path, max_candidates=10)(image(640, 640))
    top10 = np.sort(np.argsort(scores)[-10:])
    assert len(dets) == 10
    np.testing.assert_allclose(dets.scores, scores[top10])
    np.testing.assert_allclose((dets.boxes_xyxy[:, 0] + dets.boxes_xyxy[:, 2]) / 2, boxes[top10, 0], atol=1e-3)


def test_no_candidate_above_threshold_gives_empty_detections(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN[:1], np.zeros((1, 3), np.float32)))
    dets = OnnxYoloDetector(path)(image(320, 240))
    assert len(dets) == 0
    assert dets.boxes_xyxy.shape == (0, 4) and dets.scores.shape == (0,) and dets.class_ids.shape == (0,)


def test_non_square_static_input_size_is_read_from_the_model(tmp_path):
    # 384 x 640 input (h, w): a 1280x720 image -> gain 0.5 -> 640x360, 12 px padding top and bottom.
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN[:1], PROBS[:1]), input_shape=[1, 3, 384, 640])
    detector = OnnxYoloDetector(path)
    assert detector.input_size == (384, 640)
    dets = detector(image(1280, 720))
    expected = xyxy(BOXES_IN[:1])
    expected[:, [1, 3]] -= 12
    np.testing.assert_allclose(dets.boxes_xyxy, expected / 0.5, atol=1e-3)


def test_dynamic_input_defaults_to_640_and_accepts_an_input_size(tmp_path):
    raw = v8_raw(BOXES_IN[:1], PROBS[:1])
    path = make_constant_model(
        tmp_path / "v8.onnx", raw, input_shape=["batch", 3, "height", "width"], dynamic_output=True
    )
    detector = OnnxYoloDetector(path)
    assert detector.input_size == (640, 640)
    assert detector.layout is None  # symbolic output shape: decided at the first run
    assert detector.class_names == ["class0", "class1", "class2"]  # runs one inference
    assert detector.layout == "v8"
    blob, _ = OnnxYoloDetector(path, input_size=320).preprocess(image(1280, 720))
    assert blob.shape == (1, 3, 320, 320)


def test_rect_pads_only_to_the_stride(tmp_path):
    raw = v8_raw(BOXES_IN[:1], PROBS[:1])
    path = make_constant_model(tmp_path / "v8.onnx", raw, input_shape=[1, 3, "height", "width"])
    detector = OnnxYoloDetector(path, rect=True)
    blob, transform = detector.preprocess(image(1280, 720))
    assert blob.shape == (1, 3, 384, 640)  # 360 -> next multiple of 32
    assert (transform.pad_left, transform.pad_top) == (0, 12)
    dets = detector(image(1280, 720))
    expected = xyxy(BOXES_IN[:1])
    expected[:, [1, 3]] -= 12
    np.testing.assert_allclose(dets.boxes_xyxy, expected / 0.5, atol=1e-3)


def test_rect_with_a_static_model_is_rejected(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    with pytest.raises(ValueError, match="rect"):
        OnnxYoloDetector(path, rect=True)


def test_preprocess_makes_rgb_nchw_in_0_1_with_grey_padding(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    img = np.zeros((720, 1280, 3), np.uint8)
    img[..., 0] = 255  # pure blue in BGR
    blob, transform = OnnxYoloDetector(path).preprocess(img)
    assert blob.shape == (1, 3, 640, 640) and blob.dtype == np.float32
    np.testing.assert_allclose(blob[0, :, 320, 320], [0.0, 0.0, 1.0])  # R, G, B
    np.testing.assert_allclose(blob[0, :, 10, 320], [114 / 255] * 3)  # padding band
    assert transform == LetterboxTransform(0.5, 0.5, 0, 140, 1280, 720)


# ---------------------------------------------------------------------------------------------
# Letterbox geometry
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "width,height", [(1280, 720), (720, 1280), (1000, 333), (333, 1000), (640, 640), (64, 48), (1281, 721)]
)
def test_letterbox_places_content_where_the_transform_says(width, height):
    img = np.zeros((height, width, 3), np.uint8)
    x1, y1, x2, y2 = width // 4, height // 3, width // 2, (2 * height) // 3
    img[y1:y2, x1:x2] = 255
    padded, t = letterbox(img, (640, 640))
    assert padded.shape == (640, 640, 3)
    ys, xs = np.nonzero(padded[..., 0] > 127)  # the 50 % level of a blurred (upscaled) edge
    found = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)
    mapped = np.array([x1 * t.scale_x + t.pad_left, y1 * t.scale_y + t.pad_top,
                       x2 * t.scale_x + t.pad_left, y2 * t.scale_y + t.pad_top])  # fmt: skip
    np.testing.assert_allclose(found, mapped, atol=1.0)
    # padding is grey 114 and centred (the odd pixel goes to the bottom/right)
    content_w, content_h = round(width * t.scale_x), round(height * t.scale_y)
    assert 0 <= (640 - content_w) - 2 * t.pad_left <= 1
    assert 0 <= (640 - content_h) - 2 * t.pad_top <= 1
    if t.pad_top:
        assert (padded[: t.pad_top] == 114).all()
    if t.pad_left:
        assert (padded[:, : t.pad_left] == 114).all()


def test_letterbox_of_an_extreme_aspect_ratio_keeps_one_pixel_row():
    padded, t = letterbox(np.full((1, 5000, 3), 255, np.uint8), (640, 640))
    assert padded.shape == (640, 640, 3)
    assert t.scale_y == 1.0 and t.pad_top == 319
    assert (padded[319] == 255).all() and (padded[318] == 114).all()


@settings(max_examples=200, deadline=None)
@given(
    width=st.integers(1, 4000),
    height=st.integers(1, 4000),
    frac=st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4),
)
def test_unmap_inverts_the_letterbox_mapping(width, height, frac):
    gain = min(640 / height, 640 / width)
    new_w, new_h = max(round(width * gain), 1), max(round(height * gain), 1)
    t = LetterboxTransform(new_w / width, new_h / height, (640 - new_w) // 2, (640 - new_h) // 2, width, height)
    u = sorted([frac[0] * width, frac[1] * width])
    v = sorted([frac[2] * height, frac[3] * height])
    box = np.array([[u[0], v[0], u[1], v[1]]])
    forward = box * [t.scale_x, t.scale_y, t.scale_x, t.scale_y] + [t.pad_left, t.pad_top, t.pad_left, t.pad_top]
    back = t.unmap_boxes(forward)
    np.testing.assert_allclose(back, box, atol=1e-3 * max(width, height))


# ---------------------------------------------------------------------------------------------
# Class names
# ---------------------------------------------------------------------------------------------


def test_class_names_come_from_ultralytics_metadata(tmp_path):
    metadata = {"names": "{0: 'person', 1: 'boat', 2: 'buoy'}", "stride": "32"}
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS), metadata=metadata)
    assert OnnxYoloDetector(path).class_names == ["person", "boat", "buoy"]


def test_malicious_names_metadata_is_not_evaluated(tmp_path, caplog):
    metadata = {"names": "__import__('os').system('echo pwned')"}
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS), metadata=metadata)
    assert OnnxYoloDetector(path).class_names == ["class0", "class1", "class2"]
    assert "unparseable" in caplog.text


def test_class_names_argument_overrides_metadata(tmp_path):
    metadata = {"names": "{0: 'person', 1: 'boat', 2: 'buoy'}"}
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS), metadata=metadata)
    assert OnnxYoloDetector(path, class_names=["a", "b", "c"]).class_names == ["a", "b", "c"]
    assert OnnxYoloDetector(path, class_names={0: "x", 2: "z"}).class_names == ["x", "class1", "z"]


@pytest.mark.parametrize(
    "filename,content",
    [
        ("names.txt", "swimmer\nboat\n\nbuoy\n"),
        ("names.json", json.dumps(["swimmer", "boat", "buoy"])),
        ("names.json", json.dumps({"0": "swimmer", "1": "boat", "2": "buoy"})),
    ],
)
def test_class_names_from_a_file(tmp_path, filename, content):
    names_path = tmp_path / filename
    names_path.write_text(content)
    assert load_class_names(names_path) == ["swimmer", "boat", "buoy"]
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    assert OnnxYoloDetector(path, class_names=str(names_path)).class_names == ["swimmer", "boat", "buoy"]


def test_default_class_names_without_metadata(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    assert OnnxYoloDetector(path).class_names == ["class0", "class1", "class2"]


def test_class_count_mismatch_is_an_error(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    with pytest.raises(ValueError, match="4 names"):
        OnnxYoloDetector(path, class_names=["a", "b", "c", "d"], layout="v8")


# ---------------------------------------------------------------------------------------------
# Layout detection
# ---------------------------------------------------------------------------------------------


def test_auto_layout_uses_the_class_count_for_small_v5_outputs(tmp_path):
    # 6 candidates x (5 + 3): by shape alone this looks like v8 with 2 classes.
    raw = v5_raw(BOXES_IN, np.ones(4, np.float32), PROBS, n=6)
    path = make_constant_model(tmp_path / "v5.onnx", raw)
    assert OnnxYoloDetector(path).layout == "v8"  # the documented shape heuristic
    by_names = OnnxYoloDetector(path, class_names=["a", "b", "c"])
    explicit = OnnxYoloDetector(path, layout="v5")
    for detector in (by_names, explicit):
        assert detector.layout == "v5"
        np.testing.assert_array_equal(detector(image(640, 640)).class_ids, [0, 2, 0])


def test_explicit_layout_that_does_not_fit_is_an_error(tmp_path):
    raw = np.zeros((1, 100, 4), np.float32)
    path = make_constant_model(tmp_path / "m.onnx", raw)
    with pytest.raises(ValueError, match=r"\[1, 100, 4\].*v5"):
        OnnxYoloDetector(path, layout="v5")


@pytest.mark.parametrize(("metadata", "reason"), [
    ({"names": "{0: 'person'}", "end2end": "True"}, "is an end-to-end export"),
    ({"names": "{0: 'person'}", "args": "{'batch': 1, 'half': False, 'nms': True}"}, "was exported with nms=True"),
    ({"names": "{0: 'person'}"}, "looks like the kept boxes of an export with NMS inside"),  # shape alone
])
def test_a_model_with_nms_inside_is_refused_with_the_export_recipe(tmp_path, metadata, reason):
    # YOLO26's default export, or any ultralytics export with nms=True: [1, 300, 6] = x1, y1, x2, y2, score, class.
    # A one-class model's output is 6 wide like a raw YOLOv5 head: it used to be decoded as one, silently wrong.
    kept = np.zeros((1, 300, 6), np.float32)
    kept[0, 0] = [100, 100, 140, 180, 0.9, 0]
    path = make_constant_model(tmp_path / "e2e.onnx", kept, metadata=metadata)
    with pytest.raises(ValueError, match=reason) as info:
        OnnxYoloDetector(path)
    assert "nms=False end2end=False" in str(info.value) and "docs/detect.md" in str(info.value)
    if "end2end" not in metadata and "args" not in metadata:
        assert OnnxYoloDetector(path, layout="v5").layout == "v5"  # an explicit layout is believed


def test_raw_exports_with_false_flags_and_raw_v5_heads_load(tmp_path):
    raw = v8_raw(BOXES_IN, PROBS)
    path = make_constant_model(tmp_path / "v8.onnx", raw, metadata={"end2end": "False", "args": "{'nms': False}"})
    assert OnnxYoloDetector(path).layout == "v8"
    one_class = v5_raw(BOXES_IN, np.ones(4, np.float32), PROBS[:, :1], n=1008)  # a 1-class v5 head at 128 px
    path = make_constant_model(tmp_path / "v5.onnx", one_class, metadata={"names": "{0: 'person'}"})
    assert OnnxYoloDetector(path).layout == "v5"


@pytest.mark.parametrize("shape", [(1, 84), (2, 84, 8400), (1, 4, 4), (1, 84, 8400, 1)])
def test_unsupported_output_shape_names_the_shape_and_the_layouts(tmp_path, shape):
    path = make_constant_model(tmp_path / "m.onnx", np.zeros(shape, np.float32))
    with pytest.raises(ValueError) as info:
        OnnxYoloDetector(path)
    message = str(info.value)
    assert str(list(shape)) in message and "[1, N, 5 + C]" in message and "[1, 4 + C, N]" in message


# ---------------------------------------------------------------------------------------------
# Errors and registry
# ---------------------------------------------------------------------------------------------


def test_missing_model_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.onnx"):
        OnnxYoloDetector(tmp_path / "nope.onnx")


@pytest.mark.parametrize(
    "bad,error",
    [
        (np.zeros((720, 1280, 3), np.float32), TypeError),
        (np.zeros((720, 1280), np.uint8), ValueError),
        (np.zeros((720, 1280, 4), np.uint8), ValueError),
        (np.zeros((0, 1280, 3), np.uint8), ValueError),
        ([[0, 0, 0]], TypeError),
    ],
)
def test_wrong_image_dtype_or_shape(tmp_path, bad, error):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    with pytest.raises(error, match="image"):
        OnnxYoloDetector(path)(bad)


def test_bad_arguments(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    with pytest.raises(ValueError, match="layout"):
        OnnxYoloDetector(path, layout="v9")
    with pytest.raises(ValueError, match="conf_threshold"):
        OnnxYoloDetector(path, conf_threshold=1.5)
    with pytest.raises(ValueError, match="max_candidates"):
        OnnxYoloDetector(path, max_candidates=0)
    with pytest.raises(ValueError, match="static input size"):
        OnnxYoloDetector(path, input_size=320)


def test_registry_makes_detectors_and_rejects_unknown_names(tmp_path):
    path = make_constant_model(tmp_path / "v8.onnx", v8_raw(BOXES_IN, PROBS))
    assert DETECTOR_BACKENDS["onnx-yolo"] is OnnxYoloDetector
    assert isinstance(make_detector("onnx-yolo", model_path=path), OnnxYoloDetector)
    with pytest.raises(ValueError, match="onnx-yolo") as info:
        make_detector("tensorrt", model_path=path)
    assert "tensorrt" in str(info.value)


# ---------------------------------------------------------------------------------------------
# Detections value object
# ---------------------------------------------------------------------------------------------


def test_detections_concat_select_and_empty():
    a = Detections(np.array([[0, 0, 1, 1]]), np.array([0.5]), np.array([1]))
    b = Detections(np.array([[1, 1, 2, 2], [2, 2, 3, 3]]), np.array([0.2, 0.9]), np.array([0, 2]))
    both = Detections.concat([a, b])
    assert len(both) == 3
    assert both.boxes_xyxy.dtype == np.float32 and both.class_ids.dtype == np.int32
    np.testing.assert_allclose(both.scores, [0.5, 0.2, 0.9])
    high = both.select(both.scores > 0.3)
    np.testing.assert_array_equal(high.class_ids, [1, 2])
    np.testing.assert_array_equal(both.select(np.array([2, 0])).class_ids, [2, 1])
    assert len(Detections.empty()) == 0 and len(Detections.concat([])) == 0
    assert len(Detections.concat([Detections.empty(), a])) == 1


def test_detections_validate_shapes():
    with pytest.raises(ValueError, match="boxes_xyxy"):
        Detections(np.zeros((2, 3)), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="scores"):
        Detections(np.zeros((2, 4)), np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="class_ids"):
        Detections(np.zeros((2, 4)), np.zeros(2), np.zeros(1))
    with pytest.raises(ValueError, match="mask"):
        Detections(np.zeros((2, 4)), np.zeros(2), np.zeros(2)).select(np.array([True]))


# ---------------------------------------------------------------------------------------------
# Benchmark models
# ---------------------------------------------------------------------------------------------


def test_yolov8n_like_model_runs_with_the_v8_layout(tmp_path):
    from benchmarks.yolo_model import build_yolov8n_like_onnx

    built = build_yolov8n_like_onnx(tmp_path / "v8n.onnx", input_size=320)
    assert built.output_shape == (1, 84, 1600 + 400 + 100)
    assert 3.0e6 < built.num_params < 3.3e6  # YOLOv8n: 3.15 M
    assert 2.0 < built.gflops < 2.4  # 8.7 GFLOPs at 640 scales as size^2
    detector = OnnxYoloDetector(built.path, conf_threshold=0.0)
    assert detector.layout == "v8" and detector.input_size == (320, 320)
    assert detector.class_names[:2] == ["person", "bicycle"]
    raw = detector.infer(detector.preprocess(image(1280, 720))[0])
    assert raw.shape == (1, 84, 2100) and np.isfinite(raw).all()
    assert ((raw[0, 4:] >= 0) & (raw[0, 4:] <= 1)).all()
    assert (raw[0, 2:4] > 0).all()
    rng = np.random.default_rng(0)
    frame = np.kron(rng.integers(0, 256, (45, 80, 3), dtype=np.uint8), np.ones((16, 16, 1), np.uint8))
    dets = detector(frame)  # threshold 0: every candidate whose box overlaps the image
    assert 1000 < len(dets) <= 2100
    assert (dets.boxes_xyxy[:, [0, 2]] <= 1280).all() and (dets.boxes_xyxy[:, [1, 3]] <= 720).all()


def test_yolov5_like_model_runs_with_the_v5_layout(tmp_path):
    from benchmarks.yolo_model import build_yolov5_like_onnx

    built = build_yolov5_like_onnx(tmp_path / "v5.onnx", input_size=160, num_classes=5)
    assert built.output_shape == (1, 3 * (400 + 100 + 25), 10)
    detector = OnnxYoloDetector(built.path)
    assert detector.layout == "v5" and len(detector.class_names) == 5
    raw = detector.infer(detector.preprocess(image(200, 100))[0])
    assert raw.shape == built.output_shape and np.isfinite(raw).all()
    assert ((raw[0, :, 4:] >= 0) & (raw[0, :, 4:] <= 1)).all()


def test_providers_by_alias_and_an_unavailable_one_named_with_the_available():
    from agent.detector import resolve_providers

    assert resolve_providers(["cpu"], ["CPUExecutionProvider"]) == ["CPUExecutionProvider"]
    assert resolve_providers(["CUDA", "cpu"], ["CUDAExecutionProvider", "CPUExecutionProvider"]) == [
        "CUDAExecutionProvider", "CPUExecutionProvider"]
    with pytest.raises(ValueError, match="TensorrtExecutionProvider not available in this install; "
                                         "available: CPUExecutionProvider"):
        resolve_providers(["tensorrt", "cpu"], ["CPUExecutionProvider"])
    with pytest.raises(ValueError, match="no onnxruntime execution provider given"):
        resolve_providers([" "], ["CPUExecutionProvider"])


@pytest.mark.parametrize("content", [b"not an onnx model", b"", b'{"images": []}'])
def test_a_file_that_is_no_onnx_model_is_a_value_error_naming_it(tmp_path, content):
    # the contract audit (1 Dec 2026): onnxruntime's InvalidProtobuf went up as a traceback, exit 1, from uavmm detect
    # and uavmm agent --video (README: exit 2 and one line naming the bad file)
    bad = tmp_path / "model.onnx"
    bad.write_bytes(content)
    with pytest.raises(ValueError, match=r"model .*model\.onnx: onnxruntime cannot load it as an ONNX model"):
        OnnxYoloDetector(bad)

"""ONNX exports as users bring them (agent.detector, agent.slicing, agent.yolo_format): YOLOv9's two heads, a
dynamic export's size, inputs the detector cannot feed refused at load, a BOM in a class-names file, tiles without
overlap beside the full frame. Each failed before (a helper's audit with proof scripts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from agent.detector import OnnxYoloDetector  # noqa: E402
from agent.slicing import SlicedDetector, SliceGrid  # noqa: E402
from agent.yolo_format import load_class_names  # noqa: E402
from tests.agent.test_detector import v8_raw  # noqa: E402


def _model(path: Path, raws: list[np.ndarray], *, input_shape: list | None = None, input_type: int = TensorProto.FLOAT,
           extra_input: bool = False, metadata: dict[str, str] | None = None) -> Path:
    """Outputs output0, output1, ... = raws[k] + 0 * sum(the image cast to float)."""
    shape = input_shape or [1, 3, 640, 640]
    nodes = [helper.make_node("Cast", ["images"], ["as_float"], to=TensorProto.FLOAT),
             helper.make_node("ReduceSum", ["as_float"], ["total"], keepdims=0),
             helper.make_node("Mul", ["total", "zero"], ["nothing"])]
    outputs, inits = [], [numpy_helper.from_array(np.array(0.0, np.float32), "zero")]
    for k, raw in enumerate(raws):
        nodes.append(helper.make_node("Add", [f"raw{k}", "nothing"], [f"output{k}"]))
        outputs.append(helper.make_tensor_value_info(f"output{k}", TensorProto.FLOAT, list(raw.shape)))
        inits.append(numpy_helper.from_array(raw.astype(np.float32), f"raw{k}"))
    inputs = [helper.make_tensor_value_info("images", input_type, shape)]
    if extra_input:
        inputs.append(helper.make_tensor_value_info("orig_target_sizes", TensorProto.INT64, [1, 2]))
    model = helper.make_model(helper.make_graph(nodes, "m", inputs, outputs, initializer=inits),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, metadata or {"names": "{0: 'person', 1: 'boat'}"})
    onnx.save(model, str(path))
    return path


def test_yolov9s_main_head_is_used_not_its_auxiliary_one(tmp_path):
    """WongKinYiu/yolov9's export keeps both heads, auxiliary first, of one shape; the first was read silently."""
    aux = v8_raw(np.array([[320, 320, 40, 40]], np.float32), np.array([[0.30, 0.0]], np.float32))
    main = v8_raw(np.array([[100, 180, 40, 40]], np.float32), np.array([[0.0, 0.90]], np.float32))
    detector = OnnxYoloDetector(_model(tmp_path / "yolov9-c.onnx", [aux, main]), conf_threshold=0.25)
    found = detector(np.zeros((640, 640, 3), np.uint8))
    assert [detector.class_names[c] for c in found.class_ids] == ["boat"]
    assert found.boxes_xyxy.tolist() == [[80.0, 160.0, 120.0, 200.0]]


def test_a_dynamic_export_runs_at_the_size_it_was_exported_at(tmp_path):
    raw = v8_raw(np.array([[320, 320, 40, 40]], np.float32), np.array([[0.9, 0.0]], np.float32))
    path = _model(tmp_path / "dyn.onnx", [raw], input_shape=[1, 3, "h", "w"],
                  metadata={"names": "{0: 'person', 1: 'boat'}", "imgsz": "[1280, 1280]"})
    assert OnnxYoloDetector(path).input_size == (1280, 1280)  # was 640, whatever the export said
    assert OnnxYoloDetector(path, input_size=960).input_size == (960, 960)  # asked for: as asked
    plain = _model(tmp_path / "plain.onnx", [raw], input_shape=[1, 3, "h", "w"])
    assert OnnxYoloDetector(plain).input_size == (640, 640)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"input_type": TensorProto.UINT8}, r"input 'images' is tensor\(uint8\): the detector feeds float32 or float16"),
    ({"extra_input": True}, r"takes 2 inputs \(images, orig_target_sizes\): the detector feeds one image tensor"),
    ({"input_shape": ["n", "h", "w", 3]}, r"has shape \['n', 'h', 'w', 3\]: expected \[1, 3, H, W\]"),
])
def test_inputs_the_detector_cannot_feed_are_refused_at_load(tmp_path, kwargs, message):
    """They loaded, and the first frame ended in onnxruntime's INVALID_ARGUMENT traceback."""
    raw = v8_raw(np.array([[320, 320, 40, 40]], np.float32), np.array([[0.9, 0.0]], np.float32))
    with pytest.raises(ValueError, match=message):
        OnnxYoloDetector(_model(tmp_path / "m.onnx", [raw], **kwargs))


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16"])
def test_a_class_names_file_saved_with_a_bom_reads_its_first_name_clean(tmp_path, encoding):
    """Notepad's "UTF-8 with BOM" made class 0 '\\ufeffswimmer', which no size prior, tracker setting or map knew."""
    path = tmp_path / "names.txt"
    path.write_text("swimmer\nboat\n", encoding=encoding)
    assert load_class_names(path) == ["swimmer", "boat"]


def test_tiles_without_overlap_beside_the_full_frame_are_refused():
    """A tile keeps the boxes no larger than the overlap when the full frame runs too: at 0, none (5x the cost for
    the full frame's candidates alone)."""
    with pytest.raises(ValueError, match="--slice-overlap 0 beside the full frame keeps no tile's candidate"):
        SlicedDetector(lambda image: None, SliceGrid(2, 2, 0.0))  # type: ignore[arg-type,return-value]
    SlicedDetector(lambda image: None, SliceGrid(2, 2, 0.0), full_frame=False)  # type: ignore[arg-type,return-value]
    SlicedDetector(lambda image: None, SliceGrid(1, 1, 0.0))  # type: ignore[arg-type,return-value]

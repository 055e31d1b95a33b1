"""Randomly-weighted YOLO-shaped ONNX models built with ``onnx.helper`` (no torch, no downloads).

The benchmarks measure the memory map's overhead as a ratio to a realistic detector inference time
measured in the same run; these builders give a network with YOLOv8n's architecture and cost.

The v8 builder follows ultralytics' ``yolov8n.yaml`` (width 0.25, depth 0.33) layer for layer, with
batch norm folded into the convolutions as in an exported model: a strided 3x3 conv backbone with C2f
blocks and SPPF, a PAN neck, and a decoupled Detect head (box branch with DFL over 16 bins, class
branch with sigmoid) whose output is ``[1, 4 + C, A]`` (cx, cy, w, h in input pixels, then class
probabilities) with ``A = 8400`` anchors at 640 x 640 (strides 8, 16, 32: 80x80 + 40x40 + 20x20).
At 640 x 640 and 80 classes it has ~3.16 M parameters and ~8.7 GFLOPs (2 x multiply-adds of the
convolutions), the figures ultralytics reports for YOLOv8n.

The v5 builder reuses the backbone and neck with a YOLOv5-style anchor head: output ``[1, N, 5 + C]``
(cx, cy, w, h in input pixels, objectness, class probabilities), ``N = 3 x (80x80 + 40x40 + 20x20)``.
Both write ultralytics-style metadata (``names``, ``stride``, ``imgsz``) into the model.

The weights are random but calibrated layer by layer (LSUV, like folding batch norm statistics) on
a smooth random image, so that activations neither vanish nor explode: boxes vary in position and
size (DFL distances are bounded by 15 strides) and a few percent of the anchors score above 0.01,
a realistic pre-NMS load. Building takes ~1 s at 320 and ~3 s at 640 (needs ``onnx`` and
``onnxruntime``).

Usage::

    stats = build_yolov8n_like_onnx("yolov8n_like.onnx")   # 640 x 640, 80 classes
    print(stats.num_params, stats.gflops)
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

__all__ = [
    "BuiltModel",
    "COCO_CLASS_NAMES",
    "build_yolov5_like_onnx",
    "build_yolov8n_like_onnx",
]

OPSET = 17
STRIDES = (8, 16, 32)
#: YOLOv5s anchors (pixels) per stride level.
V5_ANCHORS = (
    ((10, 13), (16, 30), (33, 23)),
    ((30, 61), (62, 45), (59, 119)),
    ((116, 90), (156, 198), (373, 326)),
)
REG_MAX = 16
#: Class (and v5 objectness) logit bias and spread of the random heads, chosen so that a smooth
#: random image yields a realistic pre-NMS load: at 640, 5-10 % of the anchors score above 0.01.
CLS_LOGIT_BIAS = -8.0
OBJ_LOGIT_BIAS = -3.0
CLS_LOGIT_STD = 1.0

COCO_CLASS_NAMES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant", "bed",
    "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone", "microwave",
    "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors", "teddy bear",
    "hair drier", "toothbrush",
)  # fmt: skip


@dataclass(frozen=True, slots=True)
class BuiltModel:
    """What a builder wrote.

    Attributes
    ----------
    path : str
        The ONNX file.
    input_size : int
        Square input side in pixels; the input is ``images`` float32 ``[1, 3, S, S]``, RGB in 0..1.
    output_shape : tuple of int
        Shape of the single output ``output0``.
    num_params : int
        Number of weights and biases (constants of the decoding excluded).
    gflops : float
        2 x multiply-adds of the convolutions for one image, in 1e9 (the ultralytics convention).
    """

    path: str
    input_size: int
    output_shape: tuple[int, ...]
    num_params: int
    gflops: float


@dataclass(frozen=True, slots=True)
class _ConvRecord:
    """A convolution whose weights the calibration rescales."""

    weight: str
    bias: str
    output: str  # pre-activation output
    target_std: float


class _GraphBuilder:
    """Accumulates ONNX nodes and constants, counting parameters and conv multiply-adds."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.nodes: list[onnx.NodeProto] = []
        self.arrays: dict[str, np.ndarray] = {}
        self.convs: list[_ConvRecord] = []
        self.num_params = 0
        self.macs = 0
        self._count = 0

    def name(self, prefix: str) -> str:
        self._count += 1
        return f"{prefix}_{self._count}"

    def const(self, array: np.ndarray, prefix: str = "c", *, is_param: bool = False) -> str:
        name = self.name(prefix)
        self.arrays[name] = np.ascontiguousarray(array)
        if is_param:
            self.num_params += int(array.size)
        return name

    def op(self, op_type: str, inputs: Sequence[str], **attrs) -> str:
        """Add a node with one output; returns the output's name."""
        return self.op_outputs(op_type, inputs, 1, **attrs)[0]

    def op_outputs(self, op_type: str, inputs: Sequence[str], n_out: int, **attrs) -> list[str]:
        """Add a node with n_out outputs; returns their names."""
        outs = [self.name(op_type.lower()) for _ in range(n_out)]
        self.nodes.append(helper.make_node(op_type, list(inputs), outs, name=self.name(op_type), **attrs))
        return outs

    def make_model(
        self,
        output: str,
        input_size: int,
        output_shape: Sequence[int],
        *,
        weights_as_inputs: bool = False,
        extra_outputs: Sequence[str] = (),
    ) -> onnx.ModelProto:
        """The ONNX model; for calibration the conv weights can be graph inputs and more outputs exposed."""
        weight_names = {n for c in self.convs for n in (c.weight, c.bias)} if weights_as_inputs else set()
        inputs = [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, input_size, input_size])]
        inputs += [
            helper.make_tensor_value_info(n, TensorProto.FLOAT, list(self.arrays[n].shape))
            for n in sorted(weight_names)
        ]
        outputs = [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output_shape))]
        outputs += [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in extra_outputs]
        graph = helper.make_graph(
            [*self.nodes, helper.make_node("Identity", [output], ["output0"], name="output")],
            "yolo_like",
            inputs,
            outputs,
            initializer=[numpy_helper.from_array(a, n) for n, a in self.arrays.items() if n not in weight_names],
        )
        model = helper.make_model(
            graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="uavmm.benchmarks"
        )
        model.ir_version = 8  # readable by onnxruntime >= 1.14
        return model


@dataclass(frozen=True, slots=True)
class _Feature:
    """A tensor name with its channel count and spatial side (square inputs only)."""

    name: str
    channels: int
    side: int


def _conv2d(
    g: _GraphBuilder,
    x: _Feature,
    c_out: int,
    k: int,
    s: int = 1,
    *,
    act: bool = True,
    bias: float | np.ndarray = 0.0,
    target_std: float = 1.0,
) -> _Feature:
    """Conv (BN folded, so with bias) + optional SiLU written as ``x * sigmoid(x)``.

    Weights are drawn N(0, 1 / fan_in); :func:`_calibrate` later rescales them so that the
    pre-activation (minus bias) has standard deviation ``target_std``.
    """
    fan_in = x.channels * k * k
    w = (g.rng.standard_normal((c_out, x.channels, k, k)) / np.sqrt(fan_in)).astype(np.float32)
    b = np.broadcast_to(np.asarray(bias, dtype=np.float32), (c_out,)).copy()
    w_name, b_name = g.const(w, "w", is_param=True), g.const(b, "b", is_param=True)
    pad = k // 2
    y = g.op("Conv", [x.name, w_name, b_name], kernel_shape=[k, k], strides=[s, s], pads=[pad] * 4)
    g.convs.append(_ConvRecord(w_name, b_name, y, target_std))
    side = (x.side + 2 * pad - k) // s + 1
    g.macs += c_out * x.channels * k * k * side * side
    if act:
        y = g.op("Mul", [y, g.op("Sigmoid", [y])])
    return _Feature(y, c_out, side)


def _concat(g: _GraphBuilder, feats: Sequence[_Feature]) -> _Feature:
    name = g.op("Concat", [f.name for f in feats], axis=1)
    return _Feature(name, sum(f.channels for f in feats), feats[0].side)


def _c2f(g: _GraphBuilder, x: _Feature, c_out: int, n: int, shortcut: bool) -> _Feature:
    """Ultralytics C2f: 1x1 conv, split in two, n bottlenecks of two 3x3 convs, concat all, 1x1 conv."""
    c = c_out // 2
    y = _conv2d(g, x, 2 * c, 1)
    split = g.const(np.array([c, c], dtype=np.int64), "split")
    a, b = g.op_outputs("Split", [y.name, split], 2, axis=1)
    parts = [_Feature(a, c, y.side), _Feature(b, c, y.side)]
    for _ in range(n):
        prev = parts[-1]
        h = _conv2d(g, _conv2d(g, prev, c, 3), c, 3)
        if shortcut:
            h = _Feature(g.op("Add", [prev.name, h.name]), c, h.side)
        parts.append(h)
    return _conv2d(g, _concat(g, parts), c_out, 1)


def _sppf(g: _GraphBuilder, x: _Feature, c_out: int) -> _Feature:
    """Ultralytics SPPF: 1x1 conv, three chained 5x5 max-pools, concat, 1x1 conv."""
    y = _conv2d(g, x, x.channels // 2, 1)
    pools = [y]
    for _ in range(3):
        name = g.op("MaxPool", [pools[-1].name], kernel_shape=[5, 5], strides=[1, 1], pads=[2, 2, 2, 2])
        pools.append(_Feature(name, y.channels, y.side))
    return _conv2d(g, _concat(g, pools), c_out, 1)


def _upsample2(g: _GraphBuilder, x: _Feature) -> _Feature:
    scales = g.const(np.array([1.0, 1.0, 2.0, 2.0], dtype=np.float32), "scales")
    name = g.op("Resize", [x.name, "", scales], mode="nearest")
    return _Feature(name, x.channels, x.side * 2)


def _backbone_and_neck(g: _GraphBuilder, image: _Feature) -> list[_Feature]:
    """YOLOv8n backbone + PAN neck; returns the P3, P4, P5 features (64, 128, 256 channels)."""
    x = _conv2d(g, image, 16, 3, 2)  # P1/2
    x = _conv2d(g, x, 32, 3, 2)  # P2/4
    x = _c2f(g, x, 32, 1, True)
    x = _conv2d(g, x, 64, 3, 2)  # P3/8
    p3 = _c2f(g, x, 64, 2, True)
    x = _conv2d(g, p3, 128, 3, 2)  # P4/16
    p4 = _c2f(g, x, 128, 2, True)
    x = _conv2d(g, p4, 256, 3, 2)  # P5/32
    x = _c2f(g, x, 256, 1, True)
    p5 = _sppf(g, x, 256)
    # top-down
    n4 = _c2f(g, _concat(g, [_upsample2(g, p5), p4]), 128, 1, False)
    o3 = _c2f(g, _concat(g, [_upsample2(g, n4), p3]), 64, 1, False)
    # bottom-up
    o4 = _c2f(g, _concat(g, [_conv2d(g, o3, 64, 3, 2), n4]), 128, 1, False)
    o5 = _c2f(g, _concat(g, [_conv2d(g, o4, 128, 3, 2), p5]), 256, 1, False)
    return [o3, o4, o5]


def _flatten_hw(g: _GraphBuilder, x: _Feature) -> str:
    """(1, C, H, W) -> (1, C, H*W)."""
    shape = g.const(np.array([1, x.channels, x.side * x.side], dtype=np.int64), "shape")
    return g.op("Reshape", [x.name, shape])


def _anchor_grid(sides: Sequence[int], strides: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres (1, 2, A) in grid units and per-anchor stride (1, 1, A), levels concatenated."""
    centres, stride_rows = [], []
    for side, stride in zip(sides, strides, strict=True):
        sy, sx = np.meshgrid(np.arange(side) + 0.5, np.arange(side) + 0.5, indexing="ij")
        centres.append(np.stack([sx.ravel(), sy.ravel()]))
        stride_rows.append(np.full(side * side, stride))
    return (
        np.concatenate(centres, axis=1)[None].astype(np.float32),
        np.concatenate(stride_rows)[None, None].astype(np.float32),
    )


def _v8_head(g: _GraphBuilder, feats: Sequence[_Feature], num_classes: int) -> str:
    """Ultralytics Detect head with DFL and dist2bbox; returns the name of the (1, 4 + C, A) output."""
    c2 = max(16, feats[0].channels // 4, REG_MAX * 4)
    c3 = max(feats[0].channels, min(num_classes, 100))
    box_parts, cls_parts = [], []
    for f in feats:
        # DFL logits spread enough that box sizes vary from candidate to candidate.
        box_map = _conv2d(g, _conv2d(g, _conv2d(g, f, c2, 3), c2, 3), 4 * REG_MAX, 1, act=False, target_std=2.0)
        cls_map = _conv2d(
            g, _conv2d(g, _conv2d(g, f, c3, 3), c3, 3), num_classes, 1,
            act=False, bias=CLS_LOGIT_BIAS, target_std=CLS_LOGIT_STD,
        )  # fmt: skip
        box_parts.append(_flatten_hw(g, box_map))
        cls_parts.append(_flatten_hw(g, cls_map))
    box = g.op("Concat", box_parts, axis=2)  # (1, 64, A)
    cls = g.op("Concat", cls_parts, axis=2)  # (1, C, A)
    num_anchors = sum(f.side * f.side for f in feats)
    # DFL: softmax over the 16 bins of each side, expected bin index = distance in grid units.
    dist = g.op("Reshape", [box, g.const(np.array([1, 4, REG_MAX, num_anchors], dtype=np.int64), "shape")])
    dist = g.op("Softmax", [dist], axis=2)
    bins = g.const(np.arange(REG_MAX, dtype=np.float32).reshape(1, 1, REG_MAX, 1), "bins")
    dist = g.op(
        "ReduceSum",
        [g.op("Mul", [dist, bins]), g.const(np.array([2], dtype=np.int64), "axes")],
        keepdims=0,
    )  # (1, 4, A): left, top, right, bottom
    lt, rb = g.op_outputs("Split", [dist, g.const(np.array([2, 2], dtype=np.int64), "split")], 2, axis=1)
    centres, strides = _anchor_grid([f.side for f in feats], STRIDES)
    half = g.const(np.array(0.5, dtype=np.float32), "half")
    cxy = g.op("Add", [g.const(centres, "anchors"), g.op("Mul", [g.op("Sub", [rb, lt]), half])])
    wh = g.op("Add", [lt, rb])
    stride_c = g.const(strides, "strides")
    xywh = g.op("Mul", [g.op("Concat", [cxy, wh], axis=1), stride_c])
    return g.op("Concat", [xywh, g.op("Sigmoid", [cls])], axis=1)


def _v5_head(g: _GraphBuilder, feats: Sequence[_Feature], num_classes: int) -> str:
    """YOLOv5 Detect head; returns the name of the (1, N, 5 + C) output, N = 3 * sum(H * W)."""
    no = 5 + num_classes
    parts = []
    for f, stride, anchors in zip(feats, STRIDES, V5_ANCHORS, strict=True):
        bias = np.zeros((3, no), dtype=np.float32)
        bias[:, 4] = OBJ_LOGIT_BIAS
        bias[:, 5:] = CLS_LOGIT_BIAS
        conv = _conv2d(g, f, 3 * no, 1, act=False, bias=bias.ravel(), target_std=CLS_LOGIT_STD)
        hw = f.side * f.side
        # (1, 3*no, H, W) -> (1, 3, no, HW) -> (1, 3, HW, no)
        y = g.op("Reshape", [conv.name, g.const(np.array([1, 3, no, hw], dtype=np.int64), "shape")])
        y = g.op("Sigmoid", [g.op("Transpose", [y], perm=[0, 1, 3, 2])])
        xy, wh, rest = g.op_outputs(
            "Split", [y, g.const(np.array([2, 2, no - 4], dtype=np.int64), "split")], 3, axis=3
        )
        gy, gx = np.meshgrid(np.arange(f.side), np.arange(f.side), indexing="ij")
        grid = (np.stack([gx.ravel(), gy.ravel()], axis=1) - 0.5).astype(np.float32)[None, None]  # (1,1,HW,2)
        two = g.const(np.array(2.0, dtype=np.float32), "two")
        xy = g.op(
            "Mul",
            [g.op("Add", [g.op("Mul", [xy, two]), g.const(grid, "grid")]),
             g.const(np.array(float(stride), dtype=np.float32), "stride")],
        )  # fmt: skip
        anchor_wh = np.asarray(anchors, dtype=np.float32).reshape(1, 3, 1, 2)
        wh2 = g.op("Mul", [wh, two])
        wh = g.op("Mul", [g.op("Mul", [wh2, wh2]), g.const(anchor_wh, "anchor_wh")])
        y = g.op("Concat", [xy, wh, rest], axis=3)
        parts.append(g.op("Reshape", [y, g.const(np.array([1, 3 * hw, no], dtype=np.int64), "shape")]))
    return g.op("Concat", parts, axis=1)


def _smooth_noise(size: int, rng: np.random.Generator) -> np.ndarray:
    """(1, 3, size, size) float32 image in 0..1: blocky low-frequency colour plus pixel noise."""
    coarse = rng.random((3, size // 16, size // 16))
    image = np.kron(coarse, np.ones((16, 16))) * 0.8 + rng.random((3, size, size)) * 0.2
    return image[None].astype(np.float32)


def _calibrate(g: _GraphBuilder, output: str, input_size: int, output_shape: Sequence[int], seed: int) -> None:
    """Rescale every conv, in graph order (LSUV), as batch norm folding would.

    The weights are scaled so that the layer's pre-activation has standard deviation ``target_std``
    on a smooth random image of the model's input size and the bias is set so that its mean is the
    bias the layer was built with (0 for hidden layers, the logit priors for the heads). A random
    network's activations otherwise vanish with depth, leaving constant boxes and scores. The
    weights are graph inputs here, so one onnxruntime session serves all the updates.
    """
    import onnxruntime as ort  # only needed while building

    model = g.make_model(
        output, input_size, output_shape, weights_as_inputs=True, extra_outputs=[c.output for c in g.convs]
    )
    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    feeds = {"images": _smooth_noise(input_size, np.random.default_rng(seed + 1))}
    feeds |= {name: g.arrays[name] for c in g.convs for name in (c.weight, c.bias)}
    for conv in g.convs:
        target_bias = g.arrays[conv.bias]
        linear = session.run([conv.output], feeds)[0][0] - target_bias[:, None, None]  # (C, H, W)
        scale = conv.target_std / max(float(linear.std()), 1e-6)
        g.arrays[conv.weight] = (g.arrays[conv.weight] * scale).astype(np.float32)
        g.arrays[conv.bias] = (target_bias - float(linear.mean()) * scale).astype(np.float32)
        feeds[conv.weight], feeds[conv.bias] = g.arrays[conv.weight], g.arrays[conv.bias]


def _make_graph(input_size: int, num_classes: int, seed: int, head: str) -> tuple[_GraphBuilder, str, tuple]:
    g = _GraphBuilder(seed)
    feats = _backbone_and_neck(g, _Feature("images", 3, input_size))
    if head == "v8":
        out = _v8_head(g, feats, num_classes)
        out_shape = (1, 4 + num_classes, sum(f.side * f.side for f in feats))
    else:
        out = _v5_head(g, feats, num_classes)
        out_shape = (1, 3 * sum(f.side * f.side for f in feats), 5 + num_classes)
    return g, out, out_shape


def _build(path: str | os.PathLike[str], input_size: int, num_classes: int, seed: int, head: str) -> BuiltModel:
    if input_size <= 0 or input_size % 32:
        raise ValueError(f"input_size must be a positive multiple of 32, got {input_size}")
    if num_classes < 1:
        raise ValueError(f"num_classes must be >= 1, got {num_classes}")
    g, out, out_shape = _make_graph(input_size, num_classes, seed, head)
    _calibrate(g, out, input_size, out_shape, seed)
    model = g.make_model(out, input_size, out_shape)
    names = {i: (COCO_CLASS_NAMES[i] if i < len(COCO_CLASS_NAMES) else f"class{i}") for i in range(num_classes)}
    helper.set_model_props(
        model,
        {
            "names": repr(names),
            "stride": str(max(STRIDES)),
            "imgsz": repr([input_size, input_size]),
            "description": f"random-weight YOLO{head}-like model (uavmm benchmarks)",
        },
    )
    onnx.checker.check_model(model)
    onnx.save(model, os.fspath(path))
    return BuiltModel(
        path=os.fspath(path),
        input_size=input_size,
        output_shape=out_shape,
        num_params=g.num_params,
        gflops=2.0 * g.macs / 1e9,
    )


def build_yolov8n_like_onnx(
    path: str | os.PathLike[str], input_size: int = 640, num_classes: int = 80, seed: int = 0
) -> BuiltModel:
    """Write a random-weight ONNX model with YOLOv8n's architecture, cost and output layout.

    Parameters
    ----------
    path : str or PathLike
        Where to write the ``.onnx`` file (overwritten).
    input_size : int
        Square input side in pixels, a multiple of 32. The input is ``images``, float32
        ``[1, 3, input_size, input_size]``.
    num_classes : int
        C, the number of classes; names are COCO's (then ``classK``) in the ``names`` metadata.
    seed : int
        Seed of the random weights (the file is deterministic for a given seed).

    Returns
    -------
    BuiltModel
        Output ``output0`` float32 ``[1, 4 + C, A]``, ``A = (S/8)^2 + (S/16)^2 + (S/32)^2``
        (8400 at 640): rows cx, cy, w, h in input pixels, then C sigmoid class probabilities.
        At 640 and 80 classes: ~3.16 M parameters, ~8.7 GFLOPs.
    """
    return _build(path, input_size, num_classes, seed, "v8")


def build_yolov5_like_onnx(
    path: str | os.PathLike[str], input_size: int = 640, num_classes: int = 80, seed: int = 0
) -> BuiltModel:
    """Write a random-weight ONNX model with a YOLOv5-style anchor head (``[1, N, 5 + C]`` output).

    The backbone and neck are those of :func:`build_yolov8n_like_onnx`; the head is YOLOv5's
    (3 anchors per cell and level, sigmoid, ``xy = (2 s - 0.5 + grid) * stride``,
    ``wh = (2 s)^2 * anchor``). Meant for tests at small sizes (e.g. 160 or 320).

    Parameters
    ----------
    path : str or PathLike
        Where to write the ``.onnx`` file (overwritten).
    input_size : int
        Square input side in pixels, a multiple of 32.
    num_classes : int
        C, the number of classes.
    seed : int
        Seed of the random weights.

    Returns
    -------
    BuiltModel
        Output ``output0`` float32 ``[1, N, 5 + C]`` with ``N = 3 A`` (25200 at 640): columns cx, cy,
        w, h in input pixels, objectness, then C class probabilities.
    """
    return _build(path, input_size, num_classes, seed, "v5")

"""Detector backends: YOLO-family ONNX models run with onnxruntime, returning pre-NMS candidates.

The memory map needs every candidate box above a low confidence threshold (not the NMS survivors),
so the detector decodes the raw head output and leaves NMS to a later stage. The output layouts the
backend understands and their decoding are described in `agent.yolo_format`; the letterbox in
`agent.letterbox`.

Usage::

    detector = make_detector("onnx-yolo", model_path="yolov8n.onnx", conf_threshold=0.01)
    detections = detector(frame_bgr)          # Detections: boxes_xyxy, scores, class_ids
    names = detector.class_names
"""

from __future__ import annotations

import ast
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.letterbox import PAD_VALUE, LetterboxTransform, letterbox
from agent.yolo_format import (
    LAYOUTS,
    RAW_EXPORT_HINT,
    check_layout,
    decode_raw_output,
    detect_layout,
    kept_boxes_shape,
    names_from_metadata,
    nms_inside,
    resolve_class_names,
)

__all__ = [
    "DETECTOR_BACKENDS",
    "PROVIDER_ALIASES",
    "Detections",
    "OnnxYoloDetector",
    "make_detector",
    "resolve_providers",
]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# Detections
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class Detections:
    """Detection candidates of one image.

    Attributes
    ----------
    boxes_xyxy : np.ndarray
        (N, 4) float32 boxes ``x1, y1, x2, y2`` in original-image pixels (u right, v down, origin
        at the top-left corner of the top-left pixel).
    scores : np.ndarray
        (N,) float32 confidences in 0..1.
    class_ids : np.ndarray
        (N,) int32 class indices into the detector's ``class_names``.

    Inputs are converted to these dtypes; mismatched lengths or shapes raise ``ValueError``.
    Equality is identity (arrays do not compare to a single bool).
    """

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    class_ids: np.ndarray

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes_xyxy, dtype=np.float32)
        scores = np.asarray(self.scores, dtype=np.float32)
        class_ids = np.asarray(self.class_ids, dtype=np.int32)
        if boxes.size == 0 and boxes.ndim != 2:
            boxes = boxes.reshape(0, 4)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"boxes_xyxy must have shape (N, 4), got {boxes.shape}")
        n = boxes.shape[0]
        if scores.shape != (n,):
            raise ValueError(f"scores must have shape ({n},) to match boxes_xyxy, got {scores.shape}")
        if class_ids.shape != (n,):
            raise ValueError(f"class_ids must have shape ({n},) to match boxes_xyxy, got {class_ids.shape}")
        object.__setattr__(self, "boxes_xyxy", boxes)
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "class_ids", class_ids)

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def __repr__(self) -> str:
        return f"Detections(n={len(self)})"

    @classmethod
    def empty(cls) -> Detections:
        """No detections: shapes (0, 4), (0,), (0,)."""
        return cls(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32))

    @classmethod
    def concat(cls, parts: Sequence[Detections]) -> Detections:
        """Concatenate several ``Detections`` in order (an empty sequence gives :meth:`empty`)."""
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.boxes_xyxy for p in parts]),
            np.concatenate([p.scores for p in parts]),
            np.concatenate([p.class_ids for p in parts]),
        )

    def select(self, mask_or_indices: np.ndarray) -> Detections:
        """Subset by a (N,) bool mask or an integer index array (order of the indices kept)."""
        sel = np.asarray(mask_or_indices)
        if sel.dtype == bool and sel.shape != (len(self),):
            raise ValueError(f"boolean mask must have shape ({len(self)},), got {sel.shape}")
        return Detections(self.boxes_xyxy[sel], self.scores[sel], self.class_ids[sel])


# --------------------------------------------------------------------------------------------------
# Detector
# --------------------------------------------------------------------------------------------------


#: Short names accepted for onnxruntime execution providers (``--providers cuda,cpu``).
PROVIDER_ALIASES = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "trt": "TensorrtExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "dml": "DmlExecutionProvider",
    "rocm": "ROCMExecutionProvider",
}


def resolve_providers(providers: Sequence[str], available: Sequence[str] | None = None) -> list[str]:
    """onnxruntime execution providers by full name or short alias (`PROVIDER_ALIASES`), checked.

    available: the providers this onnxruntime build offers (default ``onnxruntime.get_available_providers()``).
    onnxruntime itself only warns and falls back to the CPU for a provider it lacks; a user who asked for
    CUDA should know. Raises ValueError naming the unknown ones and listing the available ones, or for an
    empty list.
    """
    if available is None:
        import onnxruntime as ort

        available = ort.get_available_providers()
    names = [PROVIDER_ALIASES.get(p.strip().lower(), p.strip()) for p in providers if p.strip()]
    if not names:
        raise ValueError(f"no onnxruntime execution provider given; available: {', '.join(available)}")
    unknown = [n for n in names if n not in available]
    if unknown:
        raise ValueError(f"onnxruntime execution provider(s) {', '.join(unknown)} not available in this install; "
                         f"available: {', '.join(available)}")
    return list(dict.fromkeys(names))


def _imgsz(metadata: Mapping[str, str]) -> tuple[int, int] | None:
    """The (h, w) an ultralytics export was made at (its ``imgsz`` metadata, ``[1280, 1280]`` or ``640``), if
    readable and a multiple of 32 from 32 to 8192; else None."""
    try:
        value = ast.literal_eval(metadata.get("imgsz", "None"))
    except (ValueError, SyntaxError, TypeError):
        return None
    if isinstance(value, int):
        value = [value, value]
    if not (isinstance(value, (list, tuple)) and len(value) == 2 and all(isinstance(v, int) for v in value)):
        return None
    h, w = value
    return (h, w) if all(32 <= v <= 8192 and v % 32 == 0 for v in (h, w)) else None


def _static_dim(dim: Any) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


def _as_hw(size: int | Sequence[int]) -> tuple[int, int]:
    hw = [int(size)] * 2 if isinstance(size, int | np.integer) else [int(s) for s in size]
    if len(hw) != 2 or min(hw) <= 0:
        raise ValueError(f"input_size must be a positive int or (height, width), got {size!r}")
    return hw[0], hw[1]


class OnnxYoloDetector:
    """YOLO-family ONNX model (raw, pre-NMS output) run with onnxruntime; returns all candidates.

    Parameters
    ----------
    model_path : str or PathLike
        ONNX file with one image input ``[1, 3, H, W]`` (float32 or float16, RGB in 0..1) whose
        first output is a raw head output in one of the layouts of `agent.yolo_format`.
    class_names : sequence of str, {index: name} mapping, path, or None
        Overrides the model's ``names`` metadata; a ``str``/path is read with
        :func:`load_class_names`. Default: the metadata, else ``class0, class1, ...``.
    input_size : int or (height, width), optional
        Network input size in pixels. Default: the model's static input size, else 640. Must
        agree with a static input size.
    conf_threshold : float
        Keep candidates with score >= this (0..1; low on purpose: the memory map re-scores them).
    max_candidates : int
        Keep at most this many candidates per image, the highest-scoring.
    intra_op_threads, inter_op_threads : int
        onnxruntime thread pools.
    providers : sequence of str
        onnxruntime execution providers, in order of preference (full names or the aliases of
        `resolve_providers`); ValueError listing the available ones for one this install lacks.
    layout : {"auto", "v5", "v8"}
        Output layout; "auto" decides from the output shape (`agent.yolo_format`).
    multi_label : bool
        Return every (box, class) pair above the threshold instead of the best class per box.
    rect : bool
        Minimal stride-aligned padding instead of padding to ``input_size`` (models with dynamic
        height/width only); the stride is the model's ``stride`` metadata, else 32.

    Raises
    ------
    FileNotFoundError
        The model file does not exist.
    ValueError
        Bad arguments, an input that is not ``[1, 3, H, W]``, an output shape that fits no layout,
        or class names that disagree with the model's number of classes.
    """

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        class_names: Sequence[str] | Mapping[int, str] | str | os.PathLike[str] | None = None,
        input_size: int | Sequence[int] | None = None,
        conf_threshold: float = 0.01,
        max_candidates: int = 30000,
        intra_op_threads: int = 2,
        inter_op_threads: int = 1,
        providers: Sequence[str] = ("CPUExecutionProvider",),
        layout: str = "auto",
        multi_label: bool = False,
        rect: bool = False,
    ) -> None:
        import onnxruntime as ort  # heavy import kept out of module import time

        self.model_path = Path(model_path)
        if not self.model_path.is_file():
            raise FileNotFoundError(f"ONNX model not found: {self.model_path}")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if not 0.0 <= conf_threshold <= 1.0:
            raise ValueError(f"conf_threshold must be in 0..1, got {conf_threshold}")
        if max_candidates < 1:
            raise ValueError(f"max_candidates must be >= 1, got {max_candidates}")
        self.conf_threshold = float(conf_threshold)
        self.max_candidates = int(max_candidates)
        self.multi_label = bool(multi_label)

        options = ort.SessionOptions()
        options.intra_op_num_threads = int(intra_op_threads)
        options.inter_op_num_threads = int(inter_op_threads)
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.providers = resolve_providers(providers, ort.get_available_providers())
        try:
            self._session = ort.InferenceSession(str(self.model_path), options, providers=self.providers)
        except Exception as exc:  # onnxruntime's own types (InvalidProtobuf, Fail, ...) for a file it cannot load
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"model {self.model_path}: onnxruntime cannot load it as an ONNX model ({first[:200]}): "
                             "give a YOLO export (.onnx)") from None

        inputs = self._session.get_inputs()
        model_input = inputs[0]
        shape = list(model_input.shape)
        name = self.model_path.name
        if len(inputs) > 1:  # RT-DETR / D-FINE exports also take the original image size: not a YOLO head
            raise ValueError(f"model {name} takes {len(inputs)} inputs ({', '.join(i.name for i in inputs)}): the "
                             f"detector feeds one image tensor [1, 3, H, W]; {RAW_EXPORT_HINT}")
        if len(shape) != 4 or _static_dim(shape[1]) not in (3, None) or _static_dim(shape[0]) not in (1, None) \
                or (_static_dim(shape[1]) is None and _static_dim(shape[3]) == 3):  # [N, H, W, 3]: channels last
            raise ValueError(f"model input {model_input.name!r} has shape {shape}: expected [1, 3, H, W]")
        if model_input.type not in ("tensor(float)", "tensor(float16)"):
            raise ValueError(f"model {name} input {model_input.name!r} is {model_input.type}: the detector feeds "
                             "float32 or float16 RGB in 0..1 (a YOLO export)")
        self._input_name = model_input.name
        self._input_dtype = np.float16 if model_input.type == "tensor(float16)" else np.float32
        static_hw = (_static_dim(shape[2]), _static_dim(shape[3]))
        self._dynamic_input = None in static_hw
        metadata = dict(self._session.get_modelmeta().custom_metadata_map)
        if input_size is None and self._dynamic_input:
            # a dynamic export carries the size it was trained and exported at (ultralytics' imgsz): 640 otherwise
            input_size = _imgsz(metadata) or (640, 640)
            if input_size != (640, 640):
                logger.info("model %s: dynamic input, run at its export size %s (metadata imgsz)", name, input_size)
        if input_size is None:
            assert static_hw[0] is not None and static_hw[1] is not None  # a dynamic input has a size by now
            self.input_size = (static_hw[0], static_hw[1])
        else:
            self.input_size = _as_hw(input_size)
            if not self._dynamic_input and self.input_size != static_hw:
                raise ValueError(
                    f"input_size {self.input_size} disagrees with the model's static input size {static_hw}"
                )
        if rect and not self._dynamic_input:
            raise ValueError("rect=True needs a model with dynamic input height/width")
        self.rect = bool(rect)

        try:
            self.stride = max(int(ast.literal_eval(metadata.get("stride", "32"))), 1)
        except (ValueError, SyntaxError, TypeError):
            self.stride = 32
        user_names = resolve_class_names(class_names)
        self._names_from_user = user_names is not None
        self._names = user_names if user_names is not None else names_from_metadata(metadata)

        reason = nms_inside(metadata, [o.name for o in self._session.get_outputs()])
        if reason is not None:
            raise ValueError(f"model {self.model_path.name} {reason}; {RAW_EXPORT_HINT}")

        self._requested_layout = layout
        self._layout: str | None = None
        self._num_classes: int | None = None
        self._resolved_shape: tuple[int, ...] | None = None
        outputs = self._session.get_outputs()
        # YOLOv9's own export keeps both heads, the auxiliary one first and the main one last, of one shape (its
        # detect_dual.py uses the last): of several outputs shaped like the first, the last; else the first
        same = [o for o in outputs if list(o.shape) == list(outputs[0].shape)]
        self._output_name = same[-1].name
        if len(same) > 1:
            logger.info("model %s: %d outputs of shape %s (YOLOv9's auxiliary and main heads): using the last, %r",
                        name, len(same), list(outputs[0].shape), self._output_name)
        output_shape = tuple(same[-1].shape)
        if all(_static_dim(d) is not None for d in output_shape):
            self._resolve_output(output_shape)  # fail fast on unsupported static shapes
        logger.info(
            "loaded %s: input %s %s, layout %s, %s classes",
            self.model_path.name,
            self._input_name,
            self.input_size,
            self._layout or "(decided at first run)",
            self._num_classes if self._num_classes is not None else "?",
        )

    # ---- properties ------------------------------------------------------------------------------

    @property
    def class_names(self) -> list[str]:
        """Class names indexed by ``Detections.class_ids`` (a copy).

        If the model's output shape is symbolic and no names were given, the first access runs
        one inference on a blank image to learn the number of classes.
        """
        if self._num_classes is None and self._names is None:
            self(np.full((*self.input_size, 3), PAD_VALUE, np.uint8))
        if self._names is None:
            assert self._num_classes is not None
            return [f"class{i}" for i in range(self._num_classes)]
        return list(self._names)

    @property
    def layout(self) -> str | None:
        """"v5" or "v8" (None until the first run for a model with a symbolic output shape)."""
        return self._layout

    # ---- pipeline --------------------------------------------------------------------------------

    def preprocess(self, image_bgr: np.ndarray) -> tuple[np.ndarray, LetterboxTransform]:
        """Letterbox and convert a BGR image to the network input.

        Parameters
        ----------
        image_bgr : np.ndarray
            (H, W, 3) uint8 BGR image.

        Returns
        -------
        blob : np.ndarray
            (1, 3, h, w) float32 (or float16) RGB in 0..1, NCHW.
        transform : LetterboxTransform

        Raises
        ------
        TypeError
            Not a numpy array, or dtype other than uint8.
        ValueError
            Shape other than (H, W, 3) with H, W >= 1.
        """
        if not isinstance(image_bgr, np.ndarray):
            raise TypeError(f"image must be a numpy array, got {type(image_bgr).__name__}")
        if image_bgr.dtype != np.uint8:
            raise TypeError(f"image must be uint8 (H, W, 3) BGR, got dtype {image_bgr.dtype}")
        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or min(image_bgr.shape[:2]) < 1:
            raise ValueError(f"image must have shape (H, W, 3) BGR, got {image_bgr.shape}")
        padded, transform = letterbox(image_bgr, self.input_size, stride=self.stride, auto=self.rect)
        blob = np.empty((1, 3, *padded.shape[:2]), dtype=self._input_dtype)
        # BGR -> RGB, HWC -> CHW and /255 in one pass into the output buffer.
        np.multiply(padded[..., ::-1].transpose(2, 0, 1), np.float32(1 / 255), out=blob[0], casting="unsafe")
        return blob, transform

    def infer(self, blob: np.ndarray) -> np.ndarray:
        """Run the network: (1, 3, h, w) input -> its raw head output as float32 (the first output; of several
        shaped like it, the last: YOLOv9's main head)."""
        return np.asarray(self._session.run([self._output_name], {self._input_name: blob})[0], dtype=np.float32)

    def decode(self, raw: np.ndarray, transform: LetterboxTransform) -> Detections:
        """Raw output -> :class:`Detections` in original-image pixels (threshold, top-k, un-letterbox).

        Boxes that end up with zero area after clipping to the image (entirely in the padding or
        outside the image) are dropped.
        """
        layout = self._resolve_output(tuple(raw.shape))
        boxes, scores, class_ids = decode_raw_output(
            raw, layout, self.conf_threshold, multi_label=self.multi_label, max_candidates=self.max_candidates
        )
        boxes = transform.unmap_boxes(boxes)
        inside = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        if not inside.all():
            boxes, scores, class_ids = boxes[inside], scores[inside], class_ids[inside]
        return Detections(boxes, scores, class_ids)

    def __call__(self, image_bgr: np.ndarray) -> Detections:
        """Detect in one image.

        Parameters
        ----------
        image_bgr : np.ndarray
            (H, W, 3) uint8 BGR image (OpenCV's order).

        Returns
        -------
        Detections
            All candidates with score >= ``conf_threshold`` (at most ``max_candidates``), boxes
            in original-image pixels clipped to the image, in the model's candidate order. No NMS.
        """
        blob, transform = self.preprocess(image_bgr)
        return self.decode(self.infer(blob), transform)

    # ---- helpers ---------------------------------------------------------------------------------

    def _resolve_output(self, shape: tuple[int, ...]) -> str:
        """Decide (once) and validate the layout for an output shape; checks the class count."""
        if shape == self._resolved_shape:
            return self._layout  # type: ignore[return-value]
        names_count = len(self._names) if self._names is not None else None
        if self._requested_layout == "auto":
            layout = detect_layout(shape, names_count)
            if layout == "v5" and kept_boxes_shape(shape):  # a 1-class model's [1, 300, 6] fits v5 by its width
                raise ValueError(f"model {self.model_path.name} output {list(shape)} looks like the kept boxes of an "
                                 f"export with NMS inside (x1, y1, x2, y2, score, class), not a raw YOLOv5 head "
                                 f"(pass layout='v5' if it is one); {RAW_EXPORT_HINT}")
        else:
            layout = self._requested_layout
        num_classes = check_layout(shape, layout)
        if names_count is not None and names_count != num_classes:
            source = "class_names" if self._names_from_user else "the model's 'names' metadata"
            raise ValueError(
                f"{source} has {names_count} names but the model output {list(shape)} "
                f"(layout {layout!r}) has {num_classes} classes"
            )
        self._layout, self._num_classes, self._resolved_shape = layout, num_classes, shape
        return layout


# --------------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------------

DETECTOR_BACKENDS: dict[str, Callable[..., Callable[[np.ndarray], Detections]]] = {
    "onnx-yolo": OnnxYoloDetector,
}


def make_detector(name: str, **kwargs: Any) -> Callable[[np.ndarray], Detections]:
    """Create a detector backend by registry name (see ``DETECTOR_BACKENDS``).

    Raises ``ValueError`` listing the valid names for an unknown ``name``.
    """
    try:
        backend = DETECTOR_BACKENDS[name]
    except KeyError:
        valid = ", ".join(sorted(DETECTOR_BACKENDS))
        raise ValueError(f"unknown detector backend {name!r}; valid names: {valid}") from None
    return backend(**kwargs)

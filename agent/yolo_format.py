"""What a YOLO-family ONNX export's raw output and metadata mean: the output layouts, decoding the head
output into candidates (no NMS), and class names (model metadata or a names file).

Supported raw output layouts (the first model output, batch 1):

``"v5"``: ``[1, N, 5 + C]``
    YOLOv5/v7 exports: per candidate cx, cy, w, h (input pixels), objectness, C class
    probabilities; score = objectness x class probability.
``"v8"``: ``[1, 4 + C, N]``
    YOLOv8/v11 (ultralytics) exports: per candidate (column) cx, cy, w, h, C class probabilities;
    no objectness.

``layout="auto"`` decides from the output shape ``[1, A, B]``: when the number of classes C is known
(``class_names`` argument or the model's ``names`` metadata) it picks ``"v8"`` if ``A == 4 + C`` and
``"v5"`` if ``B == 5 + C``; otherwise ``"v8"`` if ``4 < A < B`` (a YOLOv8 head has far fewer channels
than candidates, e.g. 84 x 8400) and ``"v5"`` if ``A > B > 5`` (e.g. 25200 x 85). Pass
``layout="v5"`` or ``"v8"`` when a model breaks that rule (e.g. fewer candidates than channels).
"""

from __future__ import annotations

import ast
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["LAYOUTS", "RAW_EXPORT_HINT", "check_layout", "decode_raw_output", "detect_layout", "load_class_names",
           "kept_boxes_shape", "names_from_metadata", "nms_inside", "resolve_class_names"]

logger = logging.getLogger(__name__)

LAYOUTS = ("auto", "v5", "v8")
#: What to do about a model with NMS inside (docs/detect.md has the whole recipe).
RAW_EXPORT_HINT = ("the memory map needs the raw candidates before NMS: export the model without it "
                   "(yolo export model=M.pt format=onnx nms=False end2end=False; docs/detect.md, "
                   "'Raw candidates from ultralytics')")
#: Output names of exports with an NMS operator or plugin at the end (TensorRT EfficientNMS, ONNX NMS).
_NMS_OUTPUT_NAMES = {"num_dets", "det_boxes", "det_scores", "det_classes", "num_detections", "detection_boxes",
                     "detection_scores", "detection_classes", "selected_indices"}
#: An ultralytics end-to-end or NMS export is [1, max_det, 6] (x1, y1, x2, y2, score, class), max_det 300 by
#: default; a raw YOLOv5 head has thousands of candidates (25200 at 640, 1008 even at 128).
_KEPT_BOXES_MAX = 1000


def nms_inside(metadata: Mapping[str, str], output_names: Sequence[str]) -> str | None:
    """Why a model's output is already NMS-filtered (ultralytics metadata, NMS output names), or None.

    Reads ultralytics' ``end2end`` and ``args`` (``nms=True``) metadata as literals (never evaluated).
    """
    if str(metadata.get("end2end", "")).strip().lower() == "true":
        return "is an end-to-end export (ultralytics metadata end2end=True: its output holds the kept boxes only)"
    try:
        args = ast.literal_eval(metadata.get("args", "{}"))
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        args = {}
    if isinstance(args, dict) and args.get("nms") is True:
        return "was exported with nms=True (ultralytics metadata: its output holds the kept boxes only)"
    named = sorted(_NMS_OUTPUT_NAMES & {str(n).lower() for n in output_names})
    if named:
        return f"has NMS outputs ({', '.join(named)}): only the kept boxes come out"
    return None


def kept_boxes_shape(shape: tuple[int, ...]) -> bool:
    """True for an output shaped like kept boxes, [1, K, 6] with K <= 1000, rather than a raw 1-class v5 head."""
    return len(shape) == 3 and shape[0] == 1 and shape[2] == 6 and shape[1] <= _KEPT_BOXES_MAX


# --------------------------------------------------------------------------------------------------
# Class names
# --------------------------------------------------------------------------------------------------


def _names_from_mapping(mapping: Mapping[Any, Any]) -> list[str]:
    """{0: 'person', '1': 'car'} -> ['person', 'car']; missing indices become 'classK'."""
    by_index = {int(k): str(v) for k, v in mapping.items()}
    if not by_index:
        return []
    if min(by_index) < 0:
        raise ValueError(f"class indices must be >= 0, got {min(by_index)}")
    return [by_index.get(i, f"class{i}") for i in range(max(by_index) + 1)]


def load_class_names(path: str | os.PathLike[str]) -> list[str]:
    """Read class names from a file.

    ``.json``: a list of names or an ``{index: name}`` object. Anything else: a text file with one
    name per line (surrounding whitespace stripped, blank lines skipped), as ``coco.names``.
    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` for unusable content.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"class names file not found: {path}")
    from shared.telemetry.text import read_text  # UTF-8 with or without a BOM (Notepad), UTF-16 with one

    text = read_text(path)
    if path.suffix.lower() == ".json":
        content = json.loads(text)
        if isinstance(content, dict):
            return _names_from_mapping(content)
        if isinstance(content, list) and all(isinstance(n, str) for n in content):
            return list(content)
        raise ValueError(f"{path}: expected a JSON list of names or an {{index: name}} object")
    return [line.strip() for line in text.splitlines() if line.strip()]


def names_from_metadata(metadata: Mapping[str, str]) -> list[str] | None:
    """Class names from ultralytics' ``names`` custom metadata (a Python dict literal), if valid."""
    raw = metadata.get("names")
    if raw is None:
        return None
    try:
        value = ast.literal_eval(raw)  # literals only: never evaluates code
        if isinstance(value, dict):
            return _names_from_mapping(value)
        if isinstance(value, list | tuple) and all(isinstance(n, str) for n in value):
            return list(value)
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        pass
    logger.warning("ignoring unparseable 'names' metadata in the model: %.80r", raw)
    return None


def resolve_class_names(arg: Sequence[str] | Mapping[int, str] | str | os.PathLike[str] | None) -> list[str] | None:
    """Class names given as a list, an {index: name} mapping or a names file (`load_class_names`); None: None."""
    if arg is None:
        return None
    if isinstance(arg, str | os.PathLike):
        return load_class_names(arg)
    if isinstance(arg, Mapping):
        return _names_from_mapping(arg)
    return [str(n) for n in arg]


# --------------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------------


def detect_layout(shape: tuple[int, ...], num_classes: int | None) -> str:
    """Choose "v5" or "v8" for a raw output shape (see the module docstring); ValueError if neither."""
    expected = "[1, N, 5 + C] (YOLOv5/v7, layout='v5') or [1, 4 + C, N] (YOLOv8/v11, layout='v8')"
    if len(shape) != 3 or shape[0] != 1:
        raise ValueError(f"unsupported model output shape {list(shape)}: expected {expected}")
    a, b = shape[1], shape[2]
    if num_classes is not None:
        v8, v5 = a == 4 + num_classes, b == 5 + num_classes
        if v8 and not v5:
            return "v8"
        if v5 and not v8:
            return "v5"
        if not (v8 or v5):
            raise ValueError(
                f"unsupported model output shape {list(shape)} for {num_classes} classes: expected {expected}"
            )
    if 4 < a < b:
        return "v8"
    if a > b > 5:
        return "v5"
    raise ValueError(
        f"cannot tell the layout of model output shape {list(shape)}: expected {expected}; "
        "pass layout='v5' or layout='v8'"
    )


def check_layout(shape: tuple[int, ...], layout: str) -> int:
    """Validate a shape against an explicit layout; returns the number of classes C."""
    expected = "[1, N, 5 + C]" if layout == "v5" else "[1, 4 + C, N]"
    ok = len(shape) == 3 and shape[0] == 1 and (shape[2] > 5 if layout == "v5" else shape[1] > 4)
    if not ok:
        raise ValueError(f"model output shape {list(shape)} does not fit layout={layout!r}: expected {expected}")
    return shape[2] - 5 if layout == "v5" else shape[1] - 4


def _top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Ascending indices of the k largest scores (all indices if there are at most k)."""
    if scores.shape[0] <= k:
        return np.arange(scores.shape[0])
    return np.sort(np.argpartition(scores, scores.shape[0] - k)[-k:])


def decode_raw_output(
    raw: np.ndarray,
    layout: str,
    conf_threshold: float,
    *,
    multi_label: bool = False,
    max_candidates: int = 30000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode a raw YOLO head output into candidates in input pixels (no NMS).

    Parameters
    ----------
    raw : np.ndarray
        ``[1, N, 5 + C]`` (``layout="v5"``) or ``[1, 4 + C, N]`` (``layout="v8"``), float; boxes
        cx, cy, w, h in input pixels, probabilities in 0..1.
    layout : {"v5", "v8"}
    conf_threshold : float
        Keep pairs with score >= this (v5 score = objectness x class probability).
    multi_label : bool
        False: one pair per candidate, its best class. True: every (candidate, class) pair above
        the threshold.
    max_candidates : int
        Keep at most this many pairs, the highest-scoring (``np.argpartition``, no full sort).

    Returns
    -------
    boxes_xyxy : (M, 4) float32 in input pixels
    scores : (M,) float32
    class_ids : (M,) int32
        In candidate order (then class order with ``multi_label``).
    """
    out = raw[0]
    if layout == "v8":
        cls = out[4:]  # (C, N)
        best = cls.max(axis=0)
        keep = np.flatnonzero(best >= conf_threshold)
        cls_kept = cls[:, keep].T  # (K, C)
        boxes_cxcywh = out[:4, keep].T
    else:
        # score = obj * cls; with obj >= 0, the best class is argmax(cls) and best = obj * max(cls).
        obj = out[:, 4]
        best = obj * out[:, 5:].max(axis=1)
        keep = np.flatnonzero(best >= conf_threshold)
        cls_kept = out[keep, 5:] * obj[keep, None]
        boxes_cxcywh = out[keep, :4]
    if multi_label:
        rows, class_ids = np.nonzero(cls_kept >= conf_threshold)  # row-major: candidate, then class
        scores = cls_kept[rows, class_ids]
    else:
        rows = np.arange(keep.shape[0])
        class_ids = cls_kept.argmax(axis=1) if cls_kept.shape[0] else np.zeros(0, np.intp)
        scores = best[keep]
    if scores.shape[0] > max_candidates:
        top = _top_k(scores, max_candidates)
        rows, class_ids, scores = rows[top], class_ids[top], scores[top]
    cxcywh = boxes_cxcywh[rows].astype(np.float32, copy=False)
    half_wh = cxcywh[:, 2:4] * 0.5
    boxes = np.concatenate([cxcywh[:, :2] - half_wh, cxcywh[:, :2] + half_wh], axis=1)
    return boxes, scores.astype(np.float32, copy=False), class_ids.astype(np.int32, copy=False)

"""A recorded flight for `uavmm detect`: a hovering UAV whose gimbal jumps between two views, a video of white
squares on dark ground (the objects) seen from the true poses, a 1 Hz telemetry log that stamps the jumps a
second apart, and a real ONNX model (run by onnxruntime) that finds bright squares."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon

LAT, LON = 48.53, 9.06
HEIGHT_M, PITCH_DEG = 40.0, 60.0
WIDTH, HEIGHT, FX = 640, 360, 500.0
FPS = 10.0
SQUARE_PX = 24


def make_blob_model(path: Path, size: int = 320, cell: int = 12, stride: int = 3) -> Path:
    """A YOLOv8-layout model (output (1, 4 + 2, N), classes person and swimmer) that scores every cell x cell
    window of its input on a stride grid by how bright it is, (mean - 0.5) * 2.5 clipped to 0..1 (the letterbox's
    grey pads score 0), where its mean is a local maximum of the grid (one box an object, as a trained detector
    has after NMS); box = the window."""
    g = (size - cell) // stride + 1
    n = g * g
    gy, gx = np.mgrid[0:g, 0:g]
    boxes = np.stack([gx.ravel() * stride + cell / 2, gy.ravel() * stride + cell / 2,
                      np.full(n, cell), np.full(n, cell)]).astype(np.float32)[None]  # (1, 4, N)
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["grey"], axes=[1], keepdims=1),
        helper.make_node("AveragePool", ["grey"], ["pooled"], kernel_shape=[cell, cell], strides=[stride, stride]),
        helper.make_node("MaxPool", ["pooled"], ["around"], kernel_shape=[3, 3], strides=[1, 1], pads=[1, 1, 1, 1]),
        helper.make_node("Equal", ["pooled", "around"], ["peak"]),
        helper.make_node("Cast", ["peak"], ["is_peak"], to=TensorProto.FLOAT),
        helper.make_node("Sub", ["pooled", "half"], ["centred"]),
        helper.make_node("Mul", ["centred", "gain"], ["scaled"]),
        helper.make_node("Clip", ["scaled", "lo", "hi"], ["clipped"]),
        helper.make_node("Mul", ["clipped", "is_peak"], ["score"]),
        helper.make_node("Reshape", ["score", "flat"], ["scores"]),
        helper.make_node("Concat", ["boxes", "scores", "none"], ["output0"], axis=1),
    ]
    graph = helper.make_graph(
        nodes, "blobs",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, size, size])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 6, n])],
        initializer=[
            numpy_helper.from_array(boxes, "boxes"),
            numpy_helper.from_array(np.zeros((1, 1, n), np.float32), "none"),
            numpy_helper.from_array(np.array(0.5, np.float32), "half"),
            numpy_helper.from_array(np.array(2.5, np.float32), "gain"),
            numpy_helper.from_array(np.array(0.0, np.float32), "lo"),
            numpy_helper.from_array(np.array(1.0, np.float32), "hi"),
            numpy_helper.from_array(np.array([1, 1, n], np.int64), "flat"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    helper.set_model_props(model, {"names": str({0: "person", 1: "swimmer"})})
    onnx.save(model, str(path))
    return path


@dataclass(frozen=True)
class JumpFlight:
    video: Path
    telemetry: Path
    camera: Path
    model: Path
    #: the true heading of each frame (degrees)
    headings: np.ndarray
    #: objects' (lat, lon)
    objects: np.ndarray


def true_heading(t: float, jumps: tuple[float, ...], views: tuple[float, float]) -> float:
    return views[sum(t >= j for j in jumps) % 2]


def write_jump_flight(folder: Path, *, seconds: float = 12.0, jumps: tuple[float, ...] = (2.5, 5.5, 8.5),
                      views: tuple[float, float] = (0.0, 90.0), seed: int = 0) -> JumpFlight:
    """The flight in folder: flight.avi (MJPG), flight.csv (1 Hz, whole seconds), camera.json, blobs.onnx."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    camera = Camera(width=WIDTH, height=HEIGHT, fx=FX, fy=FX, cx=WIDTH / 2, cy=HEIGHT / 2)
    # five objects in each view, 14-34 m out, within 18 deg of its centre
    bearing = np.concatenate([rng.uniform(-18, 18, 5) + v for v in views])
    dist = rng.uniform(14.0, 34.0, len(bearing))
    east, north = dist * np.sin(np.radians(bearing)), dist * np.cos(np.radians(bearing))
    lat, lon = local_to_latlon(east, north, LAT, LON)
    n_frames = int(round(seconds * FPS))
    writer = cv2.VideoWriter(str(folder / "flight.avi"), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    assert writer.isOpened()
    headings = np.array([true_heading(i / FPS, jumps, views) for i in range(n_frames)])
    half = SQUARE_PX // 2
    for heading in headings:
        image = np.full((HEIGHT, WIDTH, 3), 30, np.uint8)
        uv, valid = latlon_to_pixel(lat, lon, camera, Pose(LAT, LON, HEIGHT_M, PITCH_DEG, float(heading)))
        for (u, v), ok in zip(uv, valid, strict=True):
            if ok and 0 <= u < WIDTH and 0 <= v < HEIGHT:
                cv2.rectangle(image, (int(u) - half, int(v) - half), (int(u) + half, int(v) + half),
                              (255, 255, 255), -1)
        writer.write(image)
    writer.release()
    rows = ["time_s,lat,lon,height_m,pitch_deg,heading_deg"]
    rows += [f"{t:.1f},{LAT},{LON},{HEIGHT_M},{PITCH_DEG},{true_heading(t, jumps, views)}"
             for t in np.arange(0.0, seconds + 1.0, 1.0)]
    (folder / "flight.csv").write_text("\n".join(rows) + "\n")
    (folder / "camera.json").write_text(json.dumps({"width": WIDTH, "height": HEIGHT, "fx": FX}))
    return JumpFlight(folder / "flight.avi", folder / "flight.csv", folder / "camera.json",
                      make_blob_model(folder / "blobs.onnx"), headings, np.stack([lat, lon], axis=1))

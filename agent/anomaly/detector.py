"""Anomaly detection per frame: heatmap method -> (optionally) the ground memory layer -> regions of interest.

`AnomalyDetector.process(image, pose, t, camera)` runs the chosen heatmap method, cuts the pixels above the
horizon and beyond the range limit, adds the heatmap to the anomaly layer (`agent.anomaly.ground`) and reads
the layer back into the frame; with ``use_memory=False`` the frame's own heatmap is used (the per-frame
baseline). Regions of interest are the connected components of the score image above a threshold, as image
boxes with the component's peak score.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from agent.anomaly.ground import AnomalyMap, AnomalyMapConfig, cut_row
from agent.anomaly.methods import DEFAULT_Z_MAX, AnomalyMethod, normalise_robust
from agent.anomaly.registration import GroundRegistration
from agent.anomaly.registry import DEFAULT_METHOD, make_method
from agent.dem import takeoff_terrain
from shared.geo import Camera, Pose, image_to_ground_homography, latlon_to_local
from shared.terrain import Terrain
from shared.tiles import TileGrid

#: Robust z-score scale of the layer's boost (`AnomalyConfig.layer_z_max`, the "sum" rule), chosen on the tuning
#: seeds 0 and 1 of sea and sea-hard (docs/anomaly.md).
LAYER_Z_MAX = 6.0
#: How the ground layer enters a frame's scores (`AnomalyConfig.combine`): "min" (`agree_scores`), "sum"
#: (`combine_scores`).
COMBINE_RULES = ("min", "sum")


@dataclass(frozen=True, slots=True)
class AnomalyConfig:
    """What `AnomalyDetector` runs.

    method: a heatmap method name (`agent.anomaly.methods.ANOMALY_METHODS`); method_options its keyword options.
    use_memory: aggregate on the ground (True) or use each frame's heatmap alone (the baseline).
    map: the anomaly layer's parameters.
    roi_threshold: score a pixel needs to belong to a region of interest.
    max_rois: regions kept per frame (highest peaks first).
    roi_dilate_px: regions closer than this (working pixels) merge.
    combine: how the layer read back into the frame enters its scores (`COMBINE_RULES`):
        "min" (default since 26 Nov 2026, `agree_scores`): scores = min(heat, layer), both on the heat's own
        scale, i.e. tanh(min(z_frame, z_layer) / z_max): a pixel scores as far as both this frame and the ground
        memory put it above their own noise. A glint or a whitecap of this frame alone (the layer does not keep
        it) and a ghost the layer keeps where the frame sees nothing (misregistration, an object that left) are
        both capped by the other; an object that is in the frame and stayed put keeps its heat. Chosen on the
        tuning seeds 0 and 1 of sea and sea-hard over "sum" (every method's AR and R@5% gain rose there;
        docs/anomaly.md, "Min rule"); it has no parameter: memory_weight and layer_z_max do not enter it.
        "sum" (`combine_scores`, the rule before): (heat + w * boost) / (1 + w), boost on layer_z_max's scale.
    memory_weight: the "sum" rule's weight w, as the memory map boosts detections (c + w p): the frame keeps its
        own sharp peaks and what persisted on the ground is raised. 1.5 since 26 Nov 2026 (1 before). None, with
        either rule: the layer alone (the paper's "replace the 2D heat map").
    normalise_layer: before it is combined, the layer read back into the frame is put on the heat's own scale: its
        robust z-score over the mapped band (median and MAD of this frame's layer), mapped by tanh(z / z_max) as
        the method maps its residuals (`agent.anomaly.methods.normalise_robust`; z_max is the method's own for
        "min" and layer_z_max for "sum"; methods whose heat is not such a z-score, MOG2's foreground probability,
        keep the raw layer, already on their heat's scale). Averaging over frames shrinks the layer's noise (the
        water) more than a steady object's heat; measured against its own noise, the steady object stands out as
        far as it does in the average, not at the heat's scale. False: the raw layer (mean heat), as before
        26 Nov 2026.
    layer_z_max: the z-score scale of the "sum" rule's boost. Smaller than the heat's own (8): a faint object the
        layer keeps a few robust deviations above the water is raised more, the strongest ones saturate sooner.
        LAYER_Z_MAX since 26 Nov 2026 (the method's z_max, 8, before).
    register: place the frames on the ground with `GroundRegistration` (telemetry made consistent by image
        alignment) instead of the telemetry alone.
    terrain: the ground's DEM (`--dem`): heat is mapped onto its surface, cells it hides are not seen, and the cut
        row is the first image row that shows a mapped cell (`agent.anomaly.terrain_view`); None: flat ground.
        Without a take-off elevation, each video takes the DEM's height under its first pose
        (`agent.dem.takeoff_terrain`, as the detection pipeline does).
    """

    method: str = DEFAULT_METHOD
    method_options: dict[str, Any] = field(default_factory=dict)
    use_memory: bool = True
    map: AnomalyMapConfig = field(default_factory=AnomalyMapConfig)
    combine: str = "min"
    roi_threshold: float = 0.3
    max_rois: int = 100
    roi_dilate_px: int = 2
    memory_weight: float | None = 1.5
    normalise_layer: bool = True
    layer_z_max: float = LAYER_Z_MAX
    register: bool = True
    terrain: Terrain | None = None

    def __post_init__(self) -> None:
        if self.combine not in COMBINE_RULES:
            raise ValueError(f"AnomalyConfig.combine must be one of {', '.join(COMBINE_RULES)}, got {self.combine!r}")
        if not (math.isfinite(self.roi_threshold) and 0 < self.roi_threshold < 1):
            raise ValueError(f"AnomalyConfig.roi_threshold must be in (0, 1), got {self.roi_threshold!r}")
        if self.max_rois < 1:
            raise ValueError(f"AnomalyConfig.max_rois must be >= 1, got {self.max_rois!r}")
        if self.roi_dilate_px < 0:
            raise ValueError(f"AnomalyConfig.roi_dilate_px must be >= 0, got {self.roi_dilate_px!r}")
        if not (isinstance(self.layer_z_max, int | float) and math.isfinite(self.layer_z_max) and self.layer_z_max > 0):
            raise ValueError(f"AnomalyConfig.layer_z_max must be a finite number > 0, got {self.layer_z_max!r}")
        if self.memory_weight is not None and not (math.isfinite(self.memory_weight) and self.memory_weight >= 0):
            raise ValueError(f"AnomalyConfig.memory_weight must be None or a finite number >= 0, "
                             f"got {self.memory_weight!r}")
        if self.terrain is not None and not isinstance(self.terrain, Terrain):
            raise ValueError(f"AnomalyConfig.terrain must be a shared.terrain.Terrain or None, "
                             f"got {type(self.terrain).__name__}")


@dataclass(frozen=True, slots=True)
class AnomalyFrame:
    """One frame's outcome.

    scores: (h, w) float32 in [0, 1] at the method's working scale: the per-frame heatmap (baseline) or the
        memory layer seen from the frame, 0 above the cut row.
    boxes_xyxy: (N, 4) float32 regions of interest in full-resolution pixels; roi_scores (N,) their peaks.
    heat: the method's own heatmap of the frame (before the cut).
    cut_row: first full-resolution row mapped to the ground (0 without a pose in baseline mode).
    layer: the ground layer read back into the frame (the heat's shape), None when the layer was not used.
    """

    scores: NDArray[np.float32]
    boxes_xyxy: NDArray[np.float32]
    roi_scores: NDArray[np.float32]
    heat: NDArray[np.float32]
    cut_row: int
    layer: NDArray[np.float32] | None = None


def extract_rois(scores: NDArray[np.float32], threshold: float, *, max_rois: int = 100, dilate_px: int = 2,
                 full_size: tuple[int, int] | None = None) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Regions of interest of a score image: connected components (8-neighbour) of ``scores >= threshold``
    (dilated by dilate_px so near pixels merge), highest peak first.

    scores: (h, w) float32. full_size: (width, height) of the frame the boxes are for (default the score
    image's). Returns boxes (N, 4) float32 xyxy in that frame's pixels and their peak scores (N,) float32.
    """
    mask = (scores >= threshold).astype(np.uint8)
    if dilate_px > 0 and mask.any():
        mask = np.asarray(cv2.dilate(mask, np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)), dtype=np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32)
    peaks = np.asarray(ndimage.maximum(scores, labels, np.arange(1, n)), dtype=np.float32)
    order = np.argsort(-peaks, kind="stable")[:max_rois]
    st = stats[1:][order].astype(np.float32)
    boxes = np.column_stack([st[:, 0], st[:, 1], st[:, 0] + st[:, 2], st[:, 1] + st[:, 3]])
    if full_size is not None:
        boxes *= np.array([full_size[0] / scores.shape[1], full_size[1] / scores.shape[0]] * 2, dtype=np.float32)
    return boxes.astype(np.float32), peaks[order]


def _layer_boost(layer: NDArray[np.float32], first: int, z_max: float | None) -> NDArray[np.float32]:
    """The layer on the heat's scale: its robust z-score over the rows from first on, mapped by tanh(z / z_max)
    (`normalise_robust`); the layer as it is when z_max is None or no row is mapped."""
    if z_max is None or first >= layer.shape[0]:
        return layer
    band = np.zeros(layer.shape, dtype=bool)
    band[first:] = True
    return normalise_robust(layer, z_max, band)


def combine_scores(heat: NDArray[np.float32], layer: NDArray[np.float32], first_row: int, weight: float,
                   z_max: float | None = DEFAULT_Z_MAX) -> NDArray[np.float32]:
    """A frame's scores from its heat and the ground layer read back into it: (heat + w * boost) / (1 + w).

    heat, layer: (h, w) float32 in [0, 1], same shape; rows above first_row (the cut) score 0. boost is the
    layer's robust z-score over the rows from first_row on, mapped by tanh(z / z_max) as the heat was
    (`normalise_robust`), or the layer as it is when z_max is None. Returns (h, w) float32 in [0, 1].
    """
    first = min(max(int(first_row), 0), heat.shape[0])
    cut = heat.copy()
    cut[:first] = 0.0
    boost = _layer_boost(layer, first, z_max)
    w = np.float32(weight)
    return ((cut + w * boost) / (1 + w)).astype(np.float32, copy=False)


def agree_scores(heat: NDArray[np.float32], layer: NDArray[np.float32], first_row: int,
                 z_max: float | None = DEFAULT_Z_MAX) -> NDArray[np.float32]:
    """A frame's scores as far as its heat and the ground layer read back into it agree: min(heat, boost).

    heat, layer: (h, w) float32 in [0, 1], same shape; rows above first_row (the cut) score 0. boost is the
    layer's robust z-score over the rows from first_row on, mapped by tanh(z / z_max) (`normalise_robust`), with
    z_max the scale of the heat's own z-scores, so the result is tanh(min(z_heat, z_layer) / z_max); z_max None:
    the layer as it is (a heat that is not a z-score, on the layer's scale already). Returns (h, w) float32 in
    [0, 1], never above the heat.
    """
    first = min(max(int(first_row), 0), heat.shape[0])
    out = np.minimum(heat, _layer_boost(layer, first, z_max)).astype(np.float32, copy=False)
    out[:first] = 0.0
    return out


class AnomalyDetector:
    """Heatmaps, the ground layer and regions of interest for a sequence of frames (one video).

    Parameters
    ----------
    config : AnomalyConfig, optional
    method : AnomalyMethod, optional
        A ready method (default: built from config.method and config.method_options).
    grid : TileGrid, optional
        The shared tile grid of the anomaly layer.
    """

    def __init__(self, config: AnomalyConfig | None = None, method: AnomalyMethod | None = None,
                 grid: TileGrid | None = None) -> None:
        self.config = config or AnomalyConfig()
        self.method = method if method is not None else make_method(self.config.method, **self.config.method_options)
        self.map = AnomalyMap(self.config.map, grid)
        self.registration = GroundRegistration() if self.config.register else None
        self._ref: tuple[float, float] | None = None
        self._terrain: Terrain | None = None

    def reset(self) -> None:
        """A new video: forget the previous frames and the layer (and the take-off elevation taken from the DEM)."""
        self.method.reset()
        self.map.reset()
        if self.registration is not None:
            self.registration.reset()
        self._ref = None
        self._terrain = None

    def terrain_for(self, pose: Pose) -> Terrain | None:
        """The terrain of this video (None: flat ground): the configured one, its take-off elevation taken from the
        DEM under the video's first pose when it has none (`agent.dem.takeoff_terrain`)."""
        if self.config.terrain is None:
            return None
        if self._terrain is None:
            self._terrain = takeoff_terrain(self.config.terrain, pose)
        return self._terrain

    def image_to_world(self, camera: Camera, pose: Pose) -> NDArray[np.float64]:
        """(3, 3) homography from full-resolution pixels to metres east/north of the sequence's first pose."""
        if self._ref is None:
            self._ref = (pose.lat, pose.lon)
        east, north = latlon_to_local(pose.lat, pose.lon, *self._ref)
        shift = np.array([[1.0, 0.0, float(east)], [0.0, 1.0, float(north)], [0.0, 0.0, 1.0]])
        return shift @ image_to_ground_homography(camera, pose)

    def _layer_z_max(self) -> float | None:
        """The z-score scale of the layer's boost (`AnomalyConfig.layer_z_max`) for a method whose heat is a robust
        z-score (it has a z_max), or None for one whose heat is not (MOG2's foreground probability: its layer is
        already on the heat's scale)."""
        return self.config.layer_z_max if self._heat_z_max() is not None else None

    def _heat_z_max(self) -> float | None:
        """The z-score scale of the method's own heat (its z_max), or None for a heat that is not a robust z-score
        (MOG2): the scale the "min" rule puts the layer on."""
        z_max = getattr(self.method, "z_max", None)
        return float(z_max) if isinstance(z_max, int | float) and z_max > 0 else None

    def process(self, image: NDArray[np.uint8], pose: Pose | None, t: float, camera: Camera) -> AnomalyFrame:
        """One frame: (H, W, 3) uint8 BGR with its pose (None: no ground help) at time t (s)."""
        if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
            raise ValueError(f"frame is {image.shape[1]}x{image.shape[0]} but the camera is "
                             f"{camera.width}x{camera.height}")
        g = self.image_to_world(camera, pose) if pose is not None else None
        heat = self.method.heatmap(image, g)
        cfg = self.config
        row = 0
        layer = None
        terrain = None
        if pose is not None:
            row = cut_row(camera, pose, cfg.map.max_range_m, cfg.map.horizon_margin_deg)
            terrain = self.terrain_for(pose)
        if pose is not None and cfg.use_memory:
            g = None
            if self.registration is not None:  # on flat homographies over a terrain too (registration.py says why)
                g = self.registration.to_pose_local(self.registration.update(image, camera, pose, row, t), pose)
            self.map.update(heat, camera, pose, t, g, terrain)
            scores = layer = self.map.image_scores(camera, pose, heat.shape, g, terrain)
        if terrain is not None:  # the first row that shows a mapped cell of the terrain
            assert pose is not None
            row = self.map.terrain_cut_row(camera, pose, terrain, g if cfg.use_memory else None)
        first = min(heat.shape[0], int(math.ceil(row * heat.shape[0] / camera.height)))  # the cut in heat rows
        if layer is not None:
            if cfg.memory_weight is None:
                pass  # the layer alone
            elif cfg.combine == "min":
                scores = agree_scores(heat, layer, first, self._heat_z_max() if cfg.normalise_layer else None)
            else:
                scores = combine_scores(heat, layer, first, cfg.memory_weight,
                                        self._layer_z_max() if cfg.normalise_layer else None)
        else:
            scores = heat.copy()
            scores[:first] = 0.0
        boxes, peaks = extract_rois(scores, cfg.roi_threshold, max_rois=cfg.max_rois, dilate_px=cfg.roi_dilate_px,
                                    full_size=(camera.width, camera.height))
        return AnomalyFrame(scores, boxes, peaks, heat, row, layer)

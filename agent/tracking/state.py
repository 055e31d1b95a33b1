"""What the tracker holds between frames, as tables of columns (struct of arrays): the active tracks, the
re-ID memory of lost ones, and one frame's detections as the stages see them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from agent.tracking.config import TrackerConfig
from agent.tracking.image_motion import ImageMotion
from agent.tracking.model import FloatArray, MotionModels

__all__ = ["ACTIVE_FIELDS", "LOST_FIELDS", "EvidenceFn", "FrameDetections", "Table", "TrackState"]

#: Evidence lookup for re-ID: (class id, lat (N,), lon (N,)) -> (N,) memory-map values in [0, 1].
EvidenceFn = Callable[[int, FloatArray, FloatArray], NDArray[np.floating]]


ACTIVE_FIELDS = {
    "id": ((), np.int64), "cls": ((), np.int64), "x": ((4,), np.float64), "P": ((4, 4), np.float64),
    "box": ((4,), np.float64), "score": ((), np.float64), "hits": ((), np.int64), "support": ((), np.int64),
    "t_hit": ((), np.float64), "t_born": ((), np.float64), "t_shadow": ((), np.float64),
    "confirmed": ((), np.bool_), "matched": ((), np.bool_), "reid": ((), np.bool_), "strong": ((), np.bool_),
    "R_last": ((2, 2), np.float64), "quality": ((), np.float64),
    "heading_hit": ((), np.float64), "pending": ((), np.bool_), "probation": ((), np.bool_),
    # shown: the id has been reported (or came from the memory); det_row: this frame's detection, -1 none
    "shown": ((), np.bool_), "det_row": ((), np.int64),
    # vel_img: image velocity of the box centre, px/s (NaN: unknown)
    "vel_img": ((2,), np.float64),
    # loose: the ground position comes from loose far points only (agent.tracking.far_points)
    "loose": ((), np.bool_),
    # img_offset: the image's common offset (px) in the frame the track was last matched in (image_motion)
    "img_offset": ((2,), np.float64),
}
LOST_FIELDS = {
    "id": ((), np.int64), "cls": ((), np.int64), "pos": ((2,), np.float64), "vel": ((2,), np.float64),
    "Ppos": ((2, 2), np.float64), "box": ((4,), np.float64), "score": ((), np.float64),
    "hits": ((), np.int64), "support": ((), np.int64), "t_hit": ((), np.float64), "quality": ((), np.float64),
    "claimed": ((), np.bool_),
}


class Table:
    """Columns of equal length, filtered and appended as a whole."""

    def __init__(self, fields: dict[str, tuple[tuple[int, ...], type]]) -> None:
        self.fields = dict(fields)
        self.cols: dict[str, np.ndarray] = {k: np.zeros((0, *shape), dtype) for k, (shape, dtype) in fields.items()}

    def add_float_column(self, name: str, shape: tuple[int, ...]) -> None:
        """A new float64 column, NaN in the existing rows and in appended rows that do not give it."""
        self.fields[name] = (shape, np.float64)
        self.cols[name] = np.full((len(self), *shape), np.nan)

    def __len__(self) -> int:
        return len(self.cols["id"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.cols[name]

    def keep(self, mask: NDArray[np.bool_]) -> None:
        self.cols = {k: v[mask] for k, v in self.cols.items()}

    def append(self, **cols: np.ndarray) -> None:
        n = len(np.asarray(cols["id"]).reshape(-1))
        for k, (shape, dtype) in self.fields.items():
            new = np.asarray(cols[k], dtype=dtype).reshape(n, *shape) if k in cols else np.full((n, *shape), np.nan)
            self.cols[k] = np.concatenate([self.cols[k], new])


@dataclass
class FrameDetections:
    """One frame's detections as the stages use them (rows of the FrameResult; `association.frame_detections`).

    boxes (N, 4) pixels; scores (N,) boosted, raw (N,) the detector's; entry (N,): the score births and
    re-identifications are judged by; score_cost (N,) -score_weight * ln(raw); cls (N,); lat, lon (N,)
    degrees; used (N,): taken (or set aside) in this frame; z (N, 2) local ground points, metres, with
    covariances R (N, 2, 2); geo (N,): has a ground point; emb (N, D) unit descriptors or None; view_h (N,)
    over a terrain: the flat-ground height with each ground point's along-ray error (FrameResult.view_height_m;
    NaN: the pose's), None over flat ground; alt_latlon (N, 2) a second ground point where the box's ray passes an
    edge of the terrain (FrameResult.alt_latlon) and alt (N, 2) the step from z to it, metres (NaN rows: none),
    None without.
    """

    boxes: FloatArray
    scores: FloatArray
    raw: FloatArray
    entry: FloatArray  # the score births and re-identifications are judged by
    score_cost: FloatArray  # -score_weight * ln(raw): a better box wins among near ones
    cls: NDArray[np.int64]
    lat: FloatArray
    lon: FloatArray
    used: NDArray[np.bool_]
    z: FloatArray
    R: FloatArray
    geo: NDArray[np.bool_]
    emb: FloatArray | None = None  # (n, D) unit appearance descriptors, NaN rows: none
    view_h: FloatArray | None = None  # (n,) over a terrain: the flat-ground height of each point's error model
    alt_latlon: FloatArray | None = None  # (n, 2) a second ground point (lat, lon) past a terrain edge
    alt: FloatArray | None = None  # (n, 2) z's step to the other point, metres (set with z; swapped with it)
    loose: NDArray[np.bool_] | None = None  # (n,) ground points beyond the image reach: births, image association
    unplaced: NDArray[np.bool_] | None = None  # (n,) those beyond the far reach as well: no position reported


@dataclass
class TrackState:
    """Everything the stages (association, re-ID, lifecycle) read and change.

    active: tracks being followed (ACTIVE_FIELDS); lost: the re-ID memory (LOST_FIELDS); next_id: id
    of the next new track; origin: (lat, lon) of the local east/north frame, None before the first pose;
    heading_now: gimbal heading of the last frame with a pose, degrees (image cue); n_return_shifts: frames whose
    returning points were shifted onto the lost tracks (reid.return_offset); n_reidentified:
    re-identifications so far; image_steady: the frame's image registration paired its boxes with the
    tracks' expected ones (the image gate applies).
    """

    config: TrackerConfig
    motion: MotionModels
    evidence_at: EvidenceFn | None
    next_id: int
    active: Table = field(default_factory=lambda: Table(ACTIVE_FIELDS))
    lost: Table = field(default_factory=lambda: Table(LOST_FIELDS))
    origin: tuple[float, float] | None = None
    heading_now: float = 0.0
    n_reidentified: int = 0
    n_return_shifts: int = 0
    #: this frame's image agreed with the tracks' expected boxes (the image registration found it)
    image_steady: bool = False
    #: (id, id) -> frames with a detection whose two ground points past a terrain edge fell in the two tracks' gates
    #: while not both took a detection (-1: both did once, two objects); this frame's pairs in edge_twins_now
    edge_twins: dict[tuple[int, int], int] = field(default_factory=dict)
    edge_twins_now: set[tuple[int, int]] = field(default_factory=set)
    #: the image's common motion as the far tracks show it (TrackerConfig.far_shift_radius)
    image_motion: ImageMotion = field(default_factory=ImageMotion)

    def ensure_descriptor_columns(self, dim: int) -> None:
        """Descriptor columns ("emb", (dim,)) in the track tables, added at the first descriptor."""
        if "emb" not in self.active.cols:
            self.active.add_float_column("emb", (dim,))
            self.lost.add_float_column("emb", (dim,))
        elif self.active.fields["emb"][0] != (dim,):
            raise ValueError(f"appearance descriptors changed length: {self.active.fields['emb'][0][0]} -> {dim}")

"""GPS-space multi-object tracker with long-term re-identification (PAPER.md 3, DESIGN.md 1).

Tracks live on the ground in local east/north metres, so they survive turns, blur and looking away.
Arrays in, arrays out: no I/O (files and datasets are handled by `agent.tracking_io`).

Per frame with a pose (docs/tracking.md has the details and the measured effect of each step):

1. every active track is predicted with a constant-velocity Kalman filter (x, y, vx, vy);
2. detections get ground points (turned about the UAV by the heading change the telemetry has
   not reported yet) and covariances from the viewing geometry: a heading error moves a point
   sideways by range * d_theta, a pitch error along the ray by slant^2 / h * d_beta;
3. leftovers of NMS (boxes overlapping a stronger one, or much weaker ones at the same ground spot)
   are set aside: the memory map boosts every box around a remembered object;
4. detections are assigned to tracks of their class with `scipy.optimize.linear_sum_assignment`
   on the negative log-likelihood of the ground distance (Mahalanobis gate), the detector's
   confidence and, while the camera is steady, the image overlap with the track's last box;
   confirmed tracks first, then tentative ones, then weak detections to confirmed tracks;
5. free detections are matched to lost tracks remembered for `reid_horizon_s` (predicted with a
   damped, capped velocity; the gate grows with the time lost): a match gives the old id back; so
   does a young track whose id is not being reported when its detection matches a lost track;
6. the rest start tentative tracks, confirmed after `confirm_hits` convincing detections; tracks
   following one object are merged; unmatched ones coast, then are lost (confirmed) or deleted.

Frames without a pose coast every track and match detections by image IoU with each track's last box.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from agent.boxes import box_iou
from agent.frame_result import FrameResult
from shared.geo import Camera, Pose, latlon_to_local, local_to_latlon, local_to_pixel

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
#: Cost given to gated-out pairs before the assignment (finite: linear_sum_assignment rejects inf rows).
_GATED_COST = 1e9
#: Up to this many rows x columns an assignment is solved as one dense problem.
_DENSE_CELLS = 2500
#: Evidence lookup for re-ID: (class id, lat (N,), lon (N,)) -> (N,) memory-map values in [0, 1].
EvidenceFn = Callable[[int, FloatArray, FloatArray], NDArray[np.floating]]


# ---------------------------------------------------------------------------------------------
# Configuration and outputs
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class ClassMotion:
    """How objects of one class move.

    Attributes
    ----------
    accel_sigma_mps2 : float
        White-acceleration process noise of the Kalman filter, m/s^2.
    max_speed_mps : float
        Speed cap of the filter's velocity and of a lost track's predicted motion, m/s.
    reid_spread_mps : float
        Growth of a lost track's position uncertainty (1 sigma) per second lost, m/s.
    persistence_s : float
        How long the class keeps its velocity (time constant of the exponential damping of a lost
        track's velocity), s: the predicted displacement after dt is v * tau * (1 - exp(-dt / tau)).
        Walkers keep their direction for several seconds; swimmers drift with the current.
    """

    accel_sigma_mps2: float = 1.0
    max_speed_mps: float = 3.0
    reid_spread_mps: float = 0.6
    persistence_s: float = 3.0

    def __post_init__(self) -> None:
        for name in ("accel_sigma_mps2", "max_speed_mps", "reid_spread_mps", "persistence_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"ClassMotion.{name}={value!r} must be a finite number > 0")


#: Built-in motion per class name: people walk (1.2-1.5 m/s, sudden turns), swimmers drift slowly.
DEFAULT_CLASS_MOTION: tuple[tuple[str, ClassMotion], ...] = (
    ("person", ClassMotion(accel_sigma_mps2=1.0, max_speed_mps=3.0, reid_spread_mps=1.0, persistence_s=1.5)),
    ("swimmer", ClassMotion(accel_sigma_mps2=0.3, max_speed_mps=1.5, reid_spread_mps=0.25, persistence_s=20.0)),
    ("boat", ClassMotion(accel_sigma_mps2=1.5, max_speed_mps=15.0, reid_spread_mps=2.0, persistence_s=10.0)),
)


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    """Tracker parameters, in metres, seconds and degrees (frame-rate independent).

    Defaults: the best measured on the simulator (docs/tracking.md). "Boosted" scores are the
    pipeline's (c + memory, may exceed 1), "raw" ones the detector's own (`FrameResult.raw_scores`).

    Track life
    ----------
    match_score : float
        Boosted score from which a detection is associated first (to every active track).
    low_score : float
        Weaker detections down to this boosted score may still update a confirmed track left over
        (a blurred or partly hidden object); they never start or revive tracks.
    birth_score, reid_score : float
        Score from which a free detection starts a tentative track, or revives a lost one.
    birth_on_raw : bool
        Judge birth_score and reid_score on the raw score: the memory map lifts every box near a
        remembered spot (persistent clutter too) to about 1 + c, so a new or returning track should
        rest on a convincing detection; boosted scores then keep it.
    confirm_hits, confirm_score : int, float
        A tentative track is confirmed after confirm_hits matches with a raw score >= confirm_score,
        within confirm_window_s of its birth (else deleted).
    confirm_window_s, tentative_coast_s, max_coast_s : float
        Seconds: see confirm_hits; a tentative track unmatched for tentative_coast_s is deleted; a
        confirmed one unmatched for max_coast_s is lost (goes to the re-ID memory).
    exit_margin_px, exit_coast_s : float
        A confirmed track whose last box came within exit_margin_px pixels of the image border and
        that has then been unmatched for more than exit_coast_s seconds (0: one frame) has left the
        view: it goes to the re-ID memory at once instead of coasting for max_coast_s. A coasting
        track of an object that left used to take a neighbour's detection near the border while the
        gimbal turned faster than the telemetry showed (an exit swap); a negative margin disables it.

    Association
    -----------
    gate_chi2, max_gate_m : float
        Mahalanobis gate (squared; 9.21 = 99 % for 2 dof) and hard cap (metres) of track-detection
        pairs.
    score_weight : float
        Weight of -ln(raw score) in the pair cost (the negative log-likelihood of the ground
        distance): among detections near a track, the detector's best box wins, not a leftover.
    pair_max_cost : float or None
        A pair costing more (d2 + ln(|S| / |R|) + score and image terms) is not worth making: a track
        and a detection may both stay unassigned, so the assignment does not trade one good pair for
        two poor ones (None: as many pairs as the gate allows, like plain linear_sum_assignment).
    image_weight, image_max_age_s, image_max_turn_deg : float
        Image cue: a track matched within image_max_age_s (s) while the gimbal turned by at most
        image_max_turn_deg (deg) adds image_weight * (1 - IoU of its last box) to each pair cost (0.5
        * image_weight for other tracks): with a steady camera, pixels separate close objects better
        than ground points carrying the pose noise.
    iou_threshold : float
        Minimum image IoU with a track's last box for detections without ground position (frames
        without pose, boxes beyond the georeferencing range).

    Ground error of a detection (1 sigma)
    -------------------------------------
    position_sigma_m : float
        Isotropic (GPS jitter, box anchor), metres.
    heading_sigma_deg, pitch_sigma_deg, height_sigma_m, pixel_sigma_px : float
        Frame-to-frame telemetry errors and the anchor pixel's error: sideways range * d_theta, along
        the ray slant^2 / h * d_beta and range / h * dh, a pixel slant / f (times slant / h along).
    max_measurement_sigma_m : float
        Cap of the sideways and along-ray errors (far pixels near the horizon), metres.
    telemetry_latency_s, max_heading_correction_deg : float
        How much older the telemetry is than its stamp (s): while the gimbal turns, ground points are
        turned about the UAV by rate * (frame time - pose time + latency), at most this many degrees.
    timing_sigma_s : float
        Timing error left after that (s): the heading and pitch errors grow by turn rate * it.

    Duplicates (boosting lifts the whole cluster of boxes around a remembered object)
    --------------------------------------------------------------------------------
    duplicate_iou, duplicate_ioa : float
        A box overlapping a stronger one of its class by this IoU, or covering this fraction of the
        smaller box, is not used.
    duplicate_raw_ratio, duplicate_chi2 : float
        Nor is one within duplicate_chi2 (squared Mahalanobis, both ground errors) of another with
        a raw score below duplicate_raw_ratio times the other's (part boxes, shifted boxes).
    birth_suppress_iou, birth_suppress_chi2 : float
        A free detection overlapping a box taken in this frame by this IoU, or within this squared
        Mahalanobis distance of any active track of its class, starts no track.
    merge_chi2, merge_max_m, merge_after_s : float
        Two confirmed tracks of a class within merge_chi2 (track and measurement errors) and
        merge_max_m metres for merge_after_s seconds, never both taking a convincing detection in one
        frame, follow one object: the one with fewer hits is dropped.

    Re-identification
    -----------------
    reid_horizon_s : float
        How long a lost track is remembered, s.
    reid_gate_chi2 : float
        Mahalanobis gate of lost track-detection pairs; the lost track is predicted with its class's
        damped velocity (`ClassMotion`) and its uncertainty grows by reid_spread_mps per second.
    reid_delay_s : float
        0: a free detection is matched against the lost tracks at once. > 0: a new track is followed
        this long first, then all such tracks are matched in one assignment on filtered positions
        (and reported only after that).
    reid_min_evidence : float
        With an evidence function (`GpsTracker(evidence_at=...)`), a lost track is revived only
        where the memory map holds at least this much (0 = do not ask).
    reid_unreported_s : float
        A track born less than this many seconds ago whose id is not being reported (never yet, see
        `GpsTracker.report`, or no longer: its quality fell below report_quality) still competes
        for the lost tracks' ids whenever it takes a detection good enough to revive one: a
        returning object's first boxes, partly out of view or a false positive next to it, start a
        new track that then takes the object's good detections before they can revive its old
        track. It takes the old id on probation, like a revival; a track whose id was reported only
        for a lost track its detection looks more like than like the track itself (0: off).

    Appearance (optional: used when the detections carry descriptors, `FrameResult.embeddings`)
    ----------
    use_appearance : bool
        Use the descriptors at all (False: motion only, as without them).
    appearance_ema : float
        A track's descriptor is an exponential moving average of its detections' unit descriptors
        (weight of the past, per matched detection; FairMOT/BoT-SORT use 0.9).
    reid_appearance_weight, reid_appearance_gate : float
        Re-ID pair cost += weight * cosine distance (0 = same look, 1 = unrelated); a pair farther
        than the gate in cosine distance is not made (pairs where either side has no descriptor are
        judged on motion alone).
    appearance_weight : float
        Frame-to-frame association pair cost += weight * cosine distance (a secondary cue; ground
        distance leads).

    Reporting
    ---------
    quality_rate, report_quality : float
        A track's quality is a running mean of the raw scores of its detections, with zeros for
        frames where it is in view and not detected (weight quality_rate per frame); it is reported
        (`GpsTracker.report`) only while quality >= report_quality: persistent clutter and objects
        behind foliage are followed but not reported.

    Other
    -----
    reanchor_m : float
        Move the local origin to the UAV when it is farther than this from it, metres.
    class_motion : tuple of (class name, ClassMotion)
        Motion per class name; default_motion for other classes.
    default_motion : ClassMotion
    """

    match_score: float = 0.4
    low_score: float = 0.15
    birth_score: float = 0.5
    reid_score: float = 0.5
    birth_on_raw: bool = True
    confirm_hits: int = 3
    confirm_score: float = 0.2
    confirm_window_s: float = 0.5
    tentative_coast_s: float = 0.25
    max_coast_s: float = 1.0
    exit_margin_px: float = 4.0
    exit_coast_s: float = 0.0
    gate_chi2: float = 9.21
    max_gate_m: float = 40.0
    score_weight: float = 1.0
    pair_max_cost: float | None = 17.0
    image_weight: float = 8.0
    image_max_age_s: float = 0.2
    image_max_turn_deg: float = 1.0
    iou_threshold: float = 0.2
    position_sigma_m: float = 0.5
    heading_sigma_deg: float = 1.0
    pitch_sigma_deg: float = 0.5
    height_sigma_m: float = 0.3
    pixel_sigma_px: float = 4.0
    max_measurement_sigma_m: float = 30.0
    telemetry_latency_s: float = 0.05
    max_heading_correction_deg: float = 30.0
    timing_sigma_s: float = 0.05
    duplicate_iou: float = 0.25
    duplicate_ioa: float = 0.5
    duplicate_raw_ratio: float = 0.5
    duplicate_chi2: float = 4.0
    birth_suppress_iou: float = 0.1
    birth_suppress_chi2: float = 4.0
    merge_chi2: float = 9.21
    merge_max_m: float = 10.0
    merge_after_s: float = 0.5
    reid_horizon_s: float = 30.0
    reid_gate_chi2: float = 9.21
    reid_delay_s: float = 0.0
    reid_min_evidence: float = 0.0
    reid_unreported_s: float = 3.0
    use_appearance: bool = True
    appearance_ema: float = 0.9
    reid_appearance_weight: float = 10.0
    reid_appearance_gate: float = 0.5
    appearance_weight: float = 2.0
    quality_rate: float = 0.1
    report_quality: float = 0.4
    reanchor_m: float = 2000.0
    class_motion: tuple[tuple[str, ClassMotion], ...] = DEFAULT_CLASS_MOTION
    default_motion: ClassMotion = field(default_factory=lambda: ClassMotion(2.0, 10.0, 1.0))

    def __post_init__(self) -> None:
        positive = {"confirm_window_s", "tentative_coast_s", "max_coast_s", "gate_chi2", "max_gate_m",
                    "position_sigma_m", "max_measurement_sigma_m", "merge_chi2", "merge_max_m", "reid_gate_chi2",
                    "reanchor_m"}
        unit = {"duplicate_iou", "duplicate_ioa", "birth_suppress_iou", "iou_threshold", "quality_rate"}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("birth_on_raw", "use_appearance", "confirm_hits", "class_motion", "default_motion",
                          "pair_max_cost", "exit_margin_px"):
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"TrackerConfig.{f.name} must be a finite number, got {value!r}")
            if f.name in unit and not 0.0 < value <= 1.0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be in (0, 1]")
            if f.name in positive and value <= 0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be > 0")
            if value < 0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be >= 0")
        if self.pair_max_cost is not None and not (isinstance(self.pair_max_cost, (int, float))
                                                   and math.isfinite(self.pair_max_cost) and self.pair_max_cost > 0):
            raise ValueError(f"TrackerConfig.pair_max_cost={self.pair_max_cost!r} must be None or a number > 0")
        if not isinstance(self.exit_margin_px, (int, float)) or not math.isfinite(self.exit_margin_px):
            raise ValueError(f"TrackerConfig.exit_margin_px must be a finite number (< 0: off), "
                             f"got {self.exit_margin_px!r}")
        for name in ("birth_on_raw", "use_appearance"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"TrackerConfig.{name} must be a bool, got {getattr(self, name)!r}")
        if not self.appearance_ema < 1.0:
            raise ValueError(f"TrackerConfig.appearance_ema={self.appearance_ema!r} must be in [0, 1)")
        if isinstance(self.confirm_hits, bool) or not isinstance(self.confirm_hits, int) or self.confirm_hits < 1:
            raise ValueError(f"TrackerConfig.confirm_hits={self.confirm_hits!r} must be an integer >= 1")
        if self.low_score > self.match_score:
            raise ValueError(f"TrackerConfig.low_score={self.low_score!r} must be <= match_score={self.match_score!r}")
        for entry in self.class_motion:
            if (not isinstance(entry, tuple) or len(entry) != 2 or not isinstance(entry[0], str)
                    or not isinstance(entry[1], ClassMotion)):
                raise ValueError(f"TrackerConfig.class_motion entries must be (name, ClassMotion), got {entry!r}")
        if not isinstance(self.default_motion, ClassMotion):
            raise ValueError(f"TrackerConfig.default_motion must be a ClassMotion, got {self.default_motion!r}")

    def motion_for(self, class_name: str | None) -> ClassMotion:
        """The motion model of a class name (`default_motion` when it has none)."""
        for name, motion in self.class_motion:
            if name == class_name:
                return motion
        return self.default_motion


@dataclass(frozen=True, slots=True)
class TrackOutput:
    """One track's state after a frame.

    Attributes
    ----------
    id : int
        Track id, unique per tracker, starting at 1; a re-identified object gets its old id back.
    cls : int
        Class (category) id.
    box_xyxy : tuple of 4 float
        Image box, pixels: the detection matched in this frame, else the last matched one.
    lat, lon : float
        Filtered ground position, degrees.
    vel_en : tuple of 2 float
        Filtered ground velocity (east, north), m/s.
    score : float
        Boosted confidence of the last matched detection.
    confirmed : bool
        Confirmed (matched in `confirm_hits` frames, or re-identified).
    matched : bool
        A detection was assigned to this track in this frame.
    hits : int
        Frames matched so far.
    time_since_update_s : float
        Seconds since the last matched detection (0 when matched).
    reidentified : bool
        The track was revived from the re-ID memory in this frame.
    quality : float
        Running mean of the detector's own confidence (raw score) over the matched detections.
    """

    id: int
    cls: int
    box_xyxy: tuple[float, float, float, float]
    lat: float
    lon: float
    vel_en: tuple[float, float]
    score: float
    confirmed: bool
    matched: bool
    hits: int = 0
    time_since_update_s: float = 0.0
    reidentified: bool = False
    quality: float = 0.0


# ---------------------------------------------------------------------------------------------
# Geometry of a detection's ground error
# ---------------------------------------------------------------------------------------------

def ground_measurement_cov(
    rel_east_m: FloatArray, rel_north_m: FloatArray, height_m: float, focal_px: float, *,
    position_sigma_m: float, heading_sigma_deg: float, pitch_sigma_deg: float, height_sigma_m: float,
    pixel_sigma_px: float, max_sigma_m: float = math.inf,
) -> FloatArray:
    """Covariance of georeferenced ground points from the telemetry and pixel errors.

    Parameters
    ----------
    rel_east_m, rel_north_m : (N,) float
        Ground points relative to the point below the UAV, metres.
    height_m : float
        UAV height above the ground, metres (> 0).
    focal_px : float
        Focal length, pixels.
    position_sigma_m : float
        Isotropic error (GPS, anchor), metres.
    heading_sigma_deg, pitch_sigma_deg : float
        Heading and pitch errors, degrees: sideways error range * d_theta, along the ray
        slant^2 / h * d_beta.
    height_sigma_m : float
        Height error, metres: along the ray range / h * dh.
    pixel_sigma_px : float
        Pixel error of the anchor point: slant / f sideways, slant^2 / (h f) along the ray.
    max_sigma_m : float
        Cap of the sideways and along-ray standard deviations, metres.

    Returns
    -------
    (N, 2, 2) float64
        East/north covariance, square metres. A point right below the UAV uses north as its ray.
    """
    e = np.asarray(rel_east_m, dtype=np.float64).reshape(-1)
    n = np.asarray(rel_north_m, dtype=np.float64).reshape(-1)
    r = np.hypot(e, n)
    slant2 = r * r + height_m * height_m
    d_theta = math.radians(heading_sigma_deg)
    d_beta = math.radians(pitch_sigma_deg)
    px = pixel_sigma_px / focal_px
    side_var = (r * d_theta) ** 2 + slant2 * px * px
    along_var = (slant2 / height_m * d_beta) ** 2 + (r / height_m * height_sigma_m) ** 2 \
        + (slant2 / height_m * px) ** 2
    cap = max_sigma_m * max_sigma_m
    side_var = np.minimum(side_var, cap)
    along_var = np.minimum(along_var, cap)
    safe = r > 1e-9
    ue = np.where(safe, e / np.where(safe, r, 1.0), 0.0)
    un = np.where(safe, n / np.where(safe, r, 1.0), 1.0)
    cov = np.empty((len(e), 2, 2))
    pos_var = position_sigma_m * position_sigma_m
    cov[:, 0, 0] = pos_var + along_var * ue * ue + side_var * un * un
    cov[:, 1, 1] = pos_var + along_var * un * un + side_var * ue * ue
    cov[:, 0, 1] = cov[:, 1, 0] = (along_var - side_var) * ue * un
    return cov


def at_image_border(boxes_xyxy: NDArray, width_px: float, height_px: float, margin_px: float) -> NDArray[np.bool_]:
    """(N, 4) xyxy pixel boxes -> (N,) bool: the box comes within margin_px of an image border
    (an object partly out of view, about to leave or just entering). NaN boxes: False."""
    b = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        return (b[:, 0] <= margin_px) | (b[:, 1] <= margin_px) | (b[:, 2] >= width_px - margin_px) \
            | (b[:, 3] >= height_px - margin_px)


def mahalanobis2_and_logdet(diff: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Squared Mahalanobis distance and log-determinant for 2-D residuals.

    diff: (..., 2) residuals; cov: (..., 2, 2) symmetric positive definite covariances (broadcast).
    Returns d2 (...,) and logdet (...,) float64.
    """
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    det = np.maximum(a * d - b * b, 1e-12)
    x, y = diff[..., 0], diff[..., 1]
    return (d * x * x - 2.0 * b * x * y + a * y * y) / det, np.log(det)


def duplicate_mask(boxes_xyxy: NDArray, scores: NDArray, class_ids: NDArray, iou: float,
                   ioa: float) -> NDArray[np.bool_]:
    """Which detections duplicate a higher-scoring one of the same class in the image.

    boxes_xyxy (N, 4) pixels, scores (N,), class_ids (N,). A box is a duplicate when its IoU with a
    stronger box (not itself a duplicate) is >= iou, or their intersection covers >= ioa of the
    smaller of the two. Returns (N,) bool, True for duplicates (greedy, strongest first).
    """
    n = len(scores)
    dup = np.zeros(n, dtype=bool)
    if n < 2:
        return dup
    order = np.argsort(-np.asarray(scores), kind="stable")
    b = np.asarray(boxes_xyxy, dtype=np.float64)[order]
    c = np.asarray(class_ids)[order]
    centre = 0.5 * (b[:, :2] + b[:, 2:])
    half_diag = 0.5 * np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    i, j = near_pairs(centre, half_diag, centre, half_diag)
    keep = (i > j) & (c[i] == c[j])  # i weaker than j (later in score order)
    i, j = i[keep], j[keep]
    if not len(i):
        return dup
    inter = np.clip(np.minimum(b[i, 2], b[j, 2]) - np.maximum(b[i, 0], b[j, 0]), 0.0, None) \
        * np.clip(np.minimum(b[i, 3], b[j, 3]) - np.maximum(b[i, 1], b[j, 1]), 0.0, None)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area[i] + area[j] - inter
    overlap = (inter > 0) & ((inter >= iou * union) | (inter >= ioa * np.minimum(area[i], area[j])))
    i, j = i[overlap], j[overlap]
    stronger: dict[int, list[int]] = {}
    for a_, b_ in zip(i.tolist(), j.tolist(), strict=True):
        stronger.setdefault(a_, []).append(b_)
    dup_sorted = np.zeros(n, dtype=bool)
    for k in sorted(stronger):
        # duplicates of duplicates are judged against the kept boxes only
        if not dup_sorted[stronger[k]].all():
            dup_sorted[k] = True
    dup[order] = dup_sorted
    return dup


def ground_duplicates(z: FloatArray, R: FloatArray, raw: FloatArray, class_ids: NDArray, candidates: NDArray[np.bool_],
                      chi2: float, raw_ratio: float) -> NDArray[np.bool_]:
    """Detections that duplicate a much more confident one of their class on the ground.

    z (N, 2) ground points, metres; R (N, 2, 2) their covariances; raw (N,) detector confidences;
    candidates (N,) bool: the rows to consider. Row j is a duplicate of row i when both are
    candidates of one class, (z_j - z_i) is within `chi2` (squared Mahalanobis, R_i + R_j) and
    raw_j < raw_ratio * raw_i. Returns (N,) bool.
    """
    out = np.zeros(len(raw), dtype=bool)
    idx = np.flatnonzero(candidates)
    if len(idx) < 2:
        return out
    radius = math.sqrt(chi2) * sigma_max(R[idx])
    i, j = near_pairs(z[idx], radius, z[idx], radius)
    i, j = idx[i], idx[j]
    keep = (raw[i] < raw_ratio * raw[j]) & (class_ids[i] == class_ids[j])
    i, j = i[keep], j[keep]
    d2, _ = mahalanobis2_and_logdet(z[i] - z[j], R[i] + R[j])
    out[i[d2 <= chi2]] = True
    return out


def sigma_max(cov: FloatArray) -> FloatArray:
    """(N, 2, 2) covariances -> (N,) square root of the largest eigenvalue (the longest 1-sigma axis)."""
    a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    return np.sqrt(np.maximum(0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0))


def near_pairs(a_xy: FloatArray, a_radius: FloatArray, b_xy: FloatArray,
               b_radius: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs (i, j) with |a_i - b_j| <= a_radius_i + b_radius_j, found with a k-d tree.

    a_xy (A, 2), a_radius (A,), b_xy (B, 2), b_radius (B,), any consistent unit. Returns (K,) int64
    arrays i, j (every pair, i ascending); rows with NaN coordinates never pair.
    """
    empty = np.zeros(0, np.int64)
    a_ok = np.flatnonzero(np.isfinite(a_xy).all(axis=1))
    b_ok = np.flatnonzero(np.isfinite(b_xy).all(axis=1))
    if not len(a_ok) or not len(b_ok):
        return empty, empty
    reach = float(np.max(np.asarray(a_radius)[a_ok])) + float(np.max(np.asarray(b_radius)[b_ok]))
    found = cKDTree(a_xy[a_ok]).sparse_distance_matrix(cKDTree(b_xy[b_ok]), reach, output_type="ndarray")
    if not len(found):
        return empty, empty
    i, j = a_ok[found["i"]], b_ok[found["j"]]
    keep = np.hypot(*(a_xy[i] - b_xy[j]).T) <= np.asarray(a_radius)[i] + np.asarray(b_radius)[j]
    i, j = i[keep], j[keep]
    order = np.lexsort((j, i))
    return i[order].astype(np.int64), j[order].astype(np.int64)


def sparse_assignment(rows: NDArray[np.int64], cols: NDArray[np.int64], cost: FloatArray, *,
                      unassigned_cost: float | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Optimal assignment over the allowed pairs (rows[k], cols[k]) with costs cost[k].

    Without unassigned_cost: minimises the total cost among the assignments of largest size, like
    linear_sum_assignment on the dense matrix with the other pairs gated out. With it, a row and a
    column may also stay unassigned, which together cost unassigned_cost: pairs costing more are
    never used, and two cheap pairs are not traded for one good and one poor pair. Each connected
    group of rows and columns is solved on its own (far-apart tracks never compete). Returns the
    assigned (rows, cols).
    """
    empty = np.zeros(0, np.int64)
    if unassigned_cost is not None:
        keep = cost < unassigned_cost
        rows, cols, cost = rows[keep], cols[keep], cost[keep] - unassigned_cost
    if not len(rows):
        return empty, empty
    r_ids, r_inv = np.unique(rows, return_inverse=True)
    c_ids, c_inv = np.unique(cols, return_inverse=True)
    n_r = len(r_ids)
    if n_r * len(c_ids) <= _DENSE_CELLS:  # small: one dense problem is cheaper than finding the groups
        r, c = _dense_assignment(r_inv, c_inv, cost, n_r, len(c_ids), unassigned_cost is not None)
        return r_ids[r].astype(np.int64), c_ids[c].astype(np.int64)
    graph = coo_matrix((np.ones(len(rows)), (r_inv, c_inv + n_r)), shape=(n_r + len(c_ids),) * 2)
    _, labels = connected_components(graph, directed=False)
    lab = labels[r_inv]
    n_labels = int(labels.max()) + 1
    rows_per = np.bincount(np.unique(lab * n_r + r_inv) // n_r, minlength=n_labels)
    cols_per = np.bincount(np.unique(lab * len(c_ids) + c_inv) // len(c_ids), minlength=n_labels)
    # One row or one column in the group (most groups): its cheapest pair is the optimum.
    star = (rows_per[lab] == 1) | (cols_per[lab] == 1)
    out_r, out_c = [], []
    s_idx = np.flatnonzero(star)
    if len(s_idx):
        order = s_idx[np.lexsort((cost[s_idx], lab[s_idx]))]
        first = np.ones(len(order), dtype=bool)
        first[1:] = lab[order][1:] != lab[order][:-1]
        out_r.append(rows[order[first]])
        out_c.append(cols[order[first]])
    multi = np.flatnonzero(~star)
    if len(multi):
        order = multi[np.argsort(lab[multi], kind="stable")]
        bounds = np.flatnonzero(np.diff(lab[order])) + 1
        for group in np.split(order, bounds):
            gr, gr_inv = np.unique(r_inv[group], return_inverse=True)
            gc, gc_inv = np.unique(c_inv[group], return_inverse=True)
            r, c = _dense_assignment(gr_inv, gc_inv, cost[group], len(gr), len(gc), unassigned_cost is not None)
            out_r.append(r_ids[gr[r]])
            out_c.append(c_ids[gc[c]])
    return np.concatenate(out_r).astype(np.int64), np.concatenate(out_c).astype(np.int64)


def _dense_assignment(r: NDArray[np.int64], c: NDArray[np.int64], cost: FloatArray, n_rows: int, n_cols: int,
                      optional: bool) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """linear_sum_assignment of pairs (r, c) with costs in an (n_rows, n_cols) problem; with optional,
    dummy rows and columns at cost 0 let every row and column stay unassigned (costs are < 0 then)."""
    if optional:
        dense = np.zeros((n_rows + n_cols, n_cols + n_rows))
        dense[:n_rows, :n_cols] = _GATED_COST
    else:
        dense = np.full((n_rows, n_cols), _GATED_COST)
    dense[r, c] = cost
    allowed = np.zeros(dense.shape, dtype=bool)
    allowed[r, c] = True
    rr, cc = linear_sum_assignment(dense)
    ok = allowed[rr, cc]
    return rr[ok], cc[ok]


def gated_assignment(cost: FloatArray, allowed: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Optimal assignment (linear_sum_assignment) restricted to allowed pairs.

    cost: (R, C) float; allowed: (R, C) bool. Returns row and column indices (K,) of the assigned
    allowed pairs, minimising the total cost of those; empty when nothing is allowed.
    """
    rows_any = allowed.any(axis=1)
    cols_any = allowed.any(axis=0)
    if not rows_any.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ri = np.flatnonzero(rows_any)
    ci = np.flatnonzero(cols_any)
    sub_allowed = allowed[np.ix_(ri, ci)]
    sub = np.where(sub_allowed, cost[np.ix_(ri, ci)], _GATED_COST)
    r, c = linear_sum_assignment(sub)
    ok = sub_allowed[r, c]
    return ri[r[ok]].astype(np.int64), ci[c[ok]].astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Track tables (struct of arrays)
# ---------------------------------------------------------------------------------------------

_ACTIVE_FIELDS = {
    "id": ((), np.int64), "cls": ((), np.int64), "x": ((4,), np.float64), "P": ((4, 4), np.float64),
    "box": ((4,), np.float64), "score": ((), np.float64), "hits": ((), np.int64), "support": ((), np.int64),
    "t_hit": ((), np.float64), "t_born": ((), np.float64), "t_shadow": ((), np.float64),
    "confirmed": ((), np.bool_), "matched": ((), np.bool_), "reid": ((), np.bool_), "strong": ((), np.bool_),
    "R_last": ((2, 2), np.float64), "quality": ((), np.float64),
    "heading_hit": ((), np.float64), "pending": ((), np.bool_), "probation": ((), np.bool_),
    # shown: the id has been reported (or came from the memory); det_row: this frame's detection, -1 none
    "shown": ((), np.bool_), "det_row": ((), np.int64),
}
_LOST_FIELDS = {
    "id": ((), np.int64), "cls": ((), np.int64), "pos": ((2,), np.float64), "vel": ((2,), np.float64),
    "Ppos": ((2, 2), np.float64), "box": ((4,), np.float64), "score": ((), np.float64),
    "hits": ((), np.int64), "support": ((), np.int64), "t_hit": ((), np.float64), "quality": ((), np.float64),
    "claimed": ((), np.bool_),
}


class _Table:
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


# ---------------------------------------------------------------------------------------------
# The tracker
# ---------------------------------------------------------------------------------------------

@dataclass
class _Detections:
    """One frame's detections as the stages use them (rows of the FrameResult)."""

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

    @classmethod
    def from_result(cls, result: FrameResult, config: TrackerConfig) -> _Detections:
        boxes = np.asarray(result.boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        scores = np.asarray(result.scores, dtype=np.float64).reshape(-1)
        raw = np.asarray(result.raw_scores, dtype=np.float64).reshape(-1)
        class_ids = np.asarray(result.class_ids, dtype=np.int64).reshape(-1)
        n = len(scores)
        if not (len(boxes) == len(raw) == len(class_ids) == n):
            raise ValueError(f"FrameResult arrays differ in length: boxes {len(boxes)}, scores {n}, "
                             f"raw_scores {len(raw)}, class_ids {len(class_ids)}")
        return cls(
            boxes=boxes, scores=scores, raw=raw, entry=raw if config.birth_on_raw else scores,
            score_cost=-config.score_weight * np.log(np.clip(raw, 1e-3, None)), cls=class_ids,
            lat=np.asarray(result.lat, dtype=np.float64).reshape(-1),
            lon=np.asarray(result.lon, dtype=np.float64).reshape(-1),
            used=duplicate_mask(boxes, scores, class_ids, config.duplicate_iou, config.duplicate_ioa),
            z=np.full((n, 2), np.nan), R=np.zeros((n, 2, 2)), geo=np.zeros(n, dtype=bool),
            emb=_unit_rows(result.embeddings, n) if config.use_appearance and result.embeddings is not None else None)


class GpsTracker:
    """Multi-object tracker on the ground plane with long-term re-identification.

    Parameters
    ----------
    config : TrackerConfig, optional
    class_names : dict, optional
        Class id -> name, to look up each class's motion model (`TrackerConfig.class_motion`).
    evidence_at : callable, optional
        (class id, lat (N,), lon (N,)) -> (N,) memory-map evidence; with
        `TrackerConfig.reid_min_evidence` > 0 a re-identification needs that much evidence.
    first_id : int
        Id of the first new track (1, as MOTChallenge counts); the live agent starts each run elsewhere
        so ids stay unique across restarts (`agent.node.run_first_track_id`).

    Use one tracker per video; `update` must be called with non-decreasing times.
    """

    def __init__(self, config: TrackerConfig | None = None, class_names: dict[int, str] | None = None,
                 *, evidence_at: EvidenceFn | None = None, first_id: int = 1) -> None:
        if isinstance(first_id, bool) or not isinstance(first_id, int) or not 0 <= first_id < 2**62:
            raise ValueError(f"first_id must be an int in 0..2**62-1, got {first_id!r}")
        self.config = config or TrackerConfig()
        self.class_names = dict(class_names or {})
        self.evidence_at = evidence_at
        self._active = _Table(_ACTIVE_FIELDS)
        self._lost = _Table(_LOST_FIELDS)
        self._next_id = first_id
        self._t: float | None = None
        self._origin: tuple[float, float] | None = None
        self._motion_cache: dict[int, ClassMotion] = {}
        # Turn-rate estimate from pose changes (telemetry often arrives at a lower rate than frames).
        self._pose_ref: Pose | None = None
        self._t_pose_ref = 0.0
        self._t_frame_ref = 0.0
        self._pose_interval_s = 0.0
        self._heading_rate_deg_s = 0.0
        self._pitch_rate_deg_s = 0.0
        self.n_reidentified = 0
        self._heading_now = 0.0  # heading of the last frame with a pose (image cue)

    # ----------------------------------------------------------------------------- views
    @property
    def origin(self) -> tuple[float, float] | None:
        """(lat, lon) degrees of the local east/north frame, None before the first pose."""
        return self._origin

    @property
    def tracks(self) -> list[TrackOutput]:
        """Active tracks (tentative and confirmed, matched or coasting) after the last update."""
        return self._outputs()

    @property
    def lost_tracks(self) -> list[TrackOutput]:
        """Tracks in the re-ID memory: last filtered position and velocity, time lost so far."""
        lost = self._lost
        if not len(lost) or self._origin is None:
            return []
        lat, lon = local_to_latlon(lost["pos"][:, 0], lost["pos"][:, 1], *self._origin)
        now = self._t if self._t is not None else 0.0
        return [
            TrackOutput(int(lost["id"][i]), int(lost["cls"][i]), _box_tuple(lost["box"][i]), float(lat[i]),
                        float(lon[i]), (float(lost["vel"][i, 0]), float(lost["vel"][i, 1])),
                        float(lost["score"][i]), True, False, int(lost["hits"][i]),
                        float(now - lost["t_hit"][i]), False, float(lost["quality"][i]))
            for i in range(len(lost)) if not lost["claimed"][i]  # claimed: on probation among the active
        ]

    def report(self, tracks: list[TrackOutput]) -> list[TrackOutput]:
        """The tracks to report for a frame (MOT rows): confirmed, matched in this frame, and with a
        `quality` of at least `TrackerConfig.report_quality`."""
        q = self.config.report_quality
        return [tr for tr in tracks if tr.confirmed and tr.matched and tr.quality >= q]

    # ----------------------------------------------------------------------------- update
    def update(self, result: FrameResult, pose: Pose | None, t: float, camera: Camera, *,
               pose_t: float | None = None) -> list[TrackOutput]:
        """Advance to time t and associate one frame's detections.

        Parameters
        ----------
        result : FrameResult
            The pipeline's detections of the frame (boxes, boosted scores, classes, lat/lon, NaN
            where not georeferenced).
        pose : Pose or None
            The frame's camera pose; None without metadata: tracks coast and detections are matched
            by image IoU with each track's last box (no ground positions, no new tracks).
        t : float
            Frame time, seconds; earlier than the previous frame is treated as the same time.
        camera : Camera
            The camera (its focal length scales the pixel error on the ground).
        pose_t : float, optional
            Time the pose was measured (the telemetry's stamp), seconds; default t. While the gimbal
            turns, detections are rotated about the UAV by turn rate * (t - pose_t +
            `telemetry_latency_s`): the heading the frame was really taken at.

        Returns
        -------
        list of TrackOutput
            Every active track (tentative and confirmed, matched or coasting).
        """
        if not math.isfinite(t):
            raise ValueError(f"t must be finite seconds, got {t!r}")
        dt = 0.0 if self._t is None else t - self._t
        if dt < 0:
            log.debug("time went back by %.3f s; treating the frame as simultaneous", -dt)
            dt = 0.0
            t = self._t if self._t is not None else t
        self._t = t
        act = self._active
        act.cols["matched"][:] = False
        act.cols["reid"][:] = False
        act.cols["strong"][:] = False
        act.cols["det_row"][:] = -1
        self._predict(dt)

        dets = _Detections.from_result(result, self.config)
        if dets.emb is not None:
            self._ensure_emb(dets.emb.shape[1])
        if pose is None:
            self._associate_iou(dets, t, np.ones(len(dets.scores), dtype=bool))
        else:
            pose_t = t if pose_t is None or not math.isfinite(pose_t) else pose_t
            self._update_rates(pose, pose_t, t)
            self._heading_now = pose.heading_deg
            self._maybe_reanchor(pose)
            self._frame_with_pose(dets, pose, t, camera, staleness_s=max(t - pose_t, 0.0))
            self._merge_duplicates(t)
            self._decay_unseen_quality(pose, camera)

        self._settle_probation()
        self._retire(t, camera)
        act = self._active
        act.cols["shown"] |= act["confirmed"] & act["matched"] & (act["quality"] >= self.config.report_quality)
        return self._outputs()

    # ----------------------------------------------------------------------------- stages
    def _frame_with_pose(self, dets: _Detections, pose: Pose, t: float, camera: Camera,
                         staleness_s: float) -> None:
        cfg = self.config
        assert self._origin is not None
        geo = np.isfinite(dets.lat) & np.isfinite(dets.lon)
        dets.geo = geo
        if geo.any():
            e, n = latlon_to_local(dets.lat[geo], dets.lon[geo], *self._origin)
            uav_e, uav_n = (float(v) for v in latlon_to_local(pose.lat, pose.lon, *self._origin))
            rel_e, rel_n = e - uav_e, n - uav_n
            # The telemetry's heading is older than the frame: turn the ground points about the UAV
            # by the heading change since (a flat-ground projection rotates with the heading).
            delta_deg = self._heading_rate_deg_s * (staleness_s + cfg.telemetry_latency_s)
            delta = math.radians(max(-cfg.max_heading_correction_deg, min(cfg.max_heading_correction_deg, delta_deg)))
            if delta:
                c, s = math.cos(delta), math.sin(delta)
                rel_e, rel_n = rel_e * c + rel_n * s, -rel_e * s + rel_n * c
            dets.z[geo, 0], dets.z[geo, 1] = rel_e + uav_e, rel_n + uav_n
            rate = abs(self._heading_rate_deg_s)
            heading_sd = math.hypot(cfg.heading_sigma_deg, rate * cfg.timing_sigma_s)
            pitch_sd = math.hypot(cfg.pitch_sigma_deg, abs(self._pitch_rate_deg_s) * cfg.timing_sigma_s)
            dets.R[geo] = ground_measurement_cov(
                rel_e, rel_n, pose.height_m, math.sqrt(camera.fx * camera.fy),
                position_sigma_m=cfg.position_sigma_m, heading_sigma_deg=heading_sd, pitch_sigma_deg=pitch_sd,
                height_sigma_m=cfg.height_sigma_m, pixel_sigma_px=cfg.pixel_sigma_px,
                max_sigma_m=cfg.max_measurement_sigma_m)

        if cfg.duplicate_raw_ratio > 0 and geo.sum() > 1:
            dets.used |= ground_duplicates(dets.z, dets.R, dets.raw, dets.cls, geo & ~dets.used,
                                           cfg.duplicate_chi2, cfg.duplicate_raw_ratio)

        # 1. strong detections, confirmed tracks first (they own their object), then tentative ones;
        # 2. weak detections to confirmed tracks left over.
        confirmed = self._active["confirmed"].copy()
        strong = geo & ~dets.used & (dets.scores >= cfg.match_score)
        self._associate_ground(dets, strong, t, confirmed)
        strong &= ~dets.used
        self._associate_ground(dets, strong, t, ~confirmed)
        weak = geo & ~dets.used & (dets.scores >= cfg.low_score)
        if weak.any():
            self._associate_ground(dets, weak, t, confirmed)
        # Detections the pipeline could not georeference (beyond its range) still follow by IoU.
        far = ~geo & ~dets.used & (dets.scores >= cfg.match_score)
        if far.any():
            self._associate_iou(dets, t, far)
        # 3. re-identification from the lost-track memory (at once, or deferred: _resolve_pending).
        # Free detections and young tracks whose id nobody has seen yet compete for the lost ids.
        cand = geo & ~dets.used & (dets.entry >= cfg.reid_score)
        young = self._unreported(dets, t)
        if cfg.reid_delay_s <= 0 and (cand.any() or len(young)) and len(self._lost):
            if self.evidence_at is not None and cfg.reid_min_evidence > 0:
                young_rows = np.zeros(len(cand), dtype=bool)
                young_rows[self._active["det_row"][young]] = True
                ok = self._evidence_ok(cand | young_rows, dets.cls, dets.lat, dets.lon)
                cand &= ok
                young = young[ok[self._active["det_row"][young]]]
            self._reidentify(dets, cand, t, young)
        # 4. births.
        cand = geo & ~dets.used & (dets.entry >= cfg.birth_score)
        if cand.any():
            self._birth(dets, cand, t)
        if cfg.reid_delay_s > 0:
            self._resolve_pending(t)

    def _ensure_emb(self, dim: int) -> None:
        """Descriptor columns ("emb", (dim,)) in the track tables, added at the first descriptor."""
        if "emb" not in self._active.cols:
            self._active.add_float_column("emb", (dim,))
            self._lost.add_float_column("emb", (dim,))
        elif self._active.fields["emb"][0] != (dim,):
            raise ValueError(f"appearance descriptors changed length: {self._active.fields['emb'][0][0]} -> {dim}")

    @staticmethod
    def _emb_cost(track_emb: FloatArray, det_emb: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Cosine distance of paired rows and whether both have a descriptor (else the distance is 0)."""
        d = cosine_distance(track_emb, det_emb)
        known = np.isfinite(d)
        return np.where(known, d, 0.0), known

    def _ema(self, old: FloatArray, new: FloatArray) -> FloatArray:
        """Per-row moving average of unit descriptors (either side NaN: the other one)."""
        a = self.config.appearance_ema
        old_ok = np.isfinite(old).all(axis=-1, keepdims=True)
        new_ok = np.isfinite(new).all(axis=-1, keepdims=True)
        mix = a * np.where(old_ok, old, 0.0) + (1.0 - a) * np.where(new_ok, new, 0.0)
        mix = np.where(old_ok & ~new_ok, old, np.where(~old_ok & new_ok, new, mix))
        norm = np.linalg.norm(mix, axis=-1, keepdims=True)
        return np.where(old_ok | new_ok, mix / np.maximum(norm, 1e-12), np.nan)

    def _associate_ground(self, dets: _Detections, det_mask: NDArray[np.bool_], t: float,
                          track_mask: NDArray[np.bool_]) -> None:
        cfg = self.config
        act = self._active
        track_mask = track_mask & ~act["matched"]
        if not len(act) or not track_mask.any() or not det_mask.any():
            return
        ti = np.flatnonzero(track_mask)
        di = np.flatnonzero(det_mask)
        # Candidate pairs within the gate's longest axis (and the hard cap) only: large scenes stay sparse.
        gate = math.sqrt(cfg.gate_chi2)
        t_rad = np.minimum(gate * sigma_max(act["P"][ti, :2, :2]), cfg.max_gate_m)
        d_rad = np.minimum(gate * sigma_max(dets.R[di]), cfg.max_gate_m)
        pi, pj = near_pairs(act["x"][ti, :2], t_rad, dets.z[di], d_rad)
        tr, dt_ = ti[pi], di[pj]
        keep = act["cls"][tr] == dets.cls[dt_]
        tr, dt_ = tr[keep], dt_[keep]
        diff = dets.z[dt_] - act["x"][tr, :2]
        d2, logdet = mahalanobis2_and_logdet(diff, act["P"][tr, :2, :2] + dets.R[dt_])
        keep = (d2 <= cfg.gate_chi2) & (np.hypot(diff[:, 0], diff[:, 1]) <= cfg.max_gate_m)
        tr, dt_, d2, logdet = tr[keep], dt_[keep], d2[keep], logdet[keep]
        # Negative log-likelihood: distance, the track's own uncertainty (relative to the detection's,
        # so uncertain tracks pay for their wide gates), the detector's confidence, the image overlap.
        _, logdet_r = mahalanobis2_and_logdet(diff[keep], dets.R[dt_])
        cost = d2 + (logdet - logdet_r) + dets.score_cost[dt_]
        if cfg.image_weight > 0:
            cost += cfg.image_weight * self._image_cost(tr, dets.boxes[dt_], t)
        if cfg.appearance_weight > 0 and dets.emb is not None and len(tr):
            app, _ = self._emb_cost(act["emb"][tr], dets.emb[dt_])
            cost += cfg.appearance_weight * app
        r, c = sparse_assignment(tr, dt_, cost, unassigned_cost=cfg.pair_max_cost)
        if len(r):
            self._kf_update(r, dets.z[c], dets.R[c])
            self._mark_hit(r, dets, c, t)

    def _image_cost(self, ti: NDArray[np.int64], boxes: FloatArray, t: float) -> FloatArray:
        """(K,) 1 - IoU of track ti[k]'s last box with boxes[k] where the image still shows the track
        where it was (matched within image_max_age_s, heading turned by at most image_max_turn_deg
        since); 0.5 elsewhere (no image evidence either way)."""
        cfg = self.config
        act = self._active
        cost = np.full(len(ti), 0.5)
        turned = np.abs((self._heading_now - act["heading_hit"][ti] + 180.0) % 360.0 - 180.0)
        fresh = (t - act["t_hit"][ti] <= cfg.image_max_age_s) & (turned <= cfg.image_max_turn_deg)
        if fresh.any():
            a, b = act["box"][ti[fresh]], boxes[fresh]
            inter = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0.0, None) \
                * np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0.0, None)
            union = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]) + (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) - inter
            cost[fresh] = 1.0 - np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
        return cost

    def _associate_iou(self, dets: _Detections, t: float, det_mask: NDArray[np.bool_]) -> None:
        """Match detections to tracks by IoU with each track's last box; the ground state only coasts."""
        act = self._active
        det_mask = det_mask & ~dets.used & (dets.scores >= self.config.low_score)
        track_mask = ~act["matched"]
        if not len(act) or not det_mask.any() or not track_mask.any():
            return
        ti = np.flatnonzero(track_mask)
        di = np.flatnonzero(det_mask)
        iou = box_iou(act["box"][ti], dets.boxes[di])
        allowed = (iou >= self.config.iou_threshold) & (act["cls"][ti][:, None] == dets.cls[di][None, :])
        r, c = gated_assignment(-iou, allowed)
        if len(r):
            self._mark_hit(ti[r], dets, di[c], t)

    def _lost_match(self, z: FloatArray, R: FloatArray, cls: NDArray[np.int64], t: float,
                    emb: FloatArray | None = None) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
        """Cost (d2 + logdet, + the appearance term) and gate of every lost track against ground points
        z (K, 2) with covariances R (K, 2, 2) and descriptors emb (K, D) at time t; also the lost
        tracks' times lost (L,)."""
        cfg = self.config
        lost = self._lost
        lost_for = np.maximum(t - lost["t_hit"], 0.0)
        speed_cap, spread, tau = self._class_arrays(lost["cls"])
        vel = lost["vel"]
        speed = np.hypot(vel[:, 0], vel[:, 1])
        vel = vel * np.minimum(1.0, speed_cap / np.maximum(speed, 1e-9))[:, None]
        pred = lost["pos"] + vel * (tau * (1.0 - np.exp(-lost_for / tau)))[:, None]
        cov = lost["Ppos"] + ((spread * lost_for) ** 2)[:, None, None] * np.eye(2)
        S = cov[:, None] + R[None, :]
        diff = z[None, :, :] - pred[:, None, :]
        d2, logdet = mahalanobis2_and_logdet(diff, S)
        dist = np.hypot(diff[..., 0], diff[..., 1])
        # However uncertain the telemetry, the object cannot have gone farther than its speed allows.
        meas_sd = np.sqrt(np.maximum(R[:, 0, 0] + R[:, 1, 1], 0.0))
        reach = (speed_cap * lost_for + 3.0 * np.sqrt(np.trace(lost["Ppos"], axis1=1, axis2=2)))[:, None]
        allowed = (d2 <= cfg.reid_gate_chi2) & (dist <= reach + 3.0 * meas_sd[None, :])
        allowed &= (lost["cls"][:, None] == cls[None, :]) & ~lost["claimed"][:, None]
        cost = d2 + logdet
        if emb is not None and "emb" in lost.cols:
            app, known = self._emb_cost(lost["emb"][:, None, :], emb[None, :, :])
            cost = cost + cfg.reid_appearance_weight * app
            allowed &= ~known | (app <= cfg.reid_appearance_gate)
        return cost, allowed, lost_for

    def _resolve_pending(self, t: float) -> None:
        """Deferred re-identification: new tracks that have been followed for `reid_delay_s` take
        the id of the lost track they match best. All pending tracks enter one optimal assignment
        (an object that came into view a little later may be the better match), but only those old
        enough are decided."""
        cfg = self.config
        act = self._active
        pend = act["pending"]
        if not pend.any():
            return
        ready = pend & (t - act["t_born"] >= cfg.reid_delay_s)
        if not len(self._lost):
            self._settle(ready)
            return
        if not ready.any():
            return
        ki = np.flatnonzero(pend)
        cost, allowed, lost_for = self._lost_match(act["x"][ki, :2], act["P"][ki, :2, :2], act["cls"][ki], t,
                                                   act["emb"][ki] if "emb" in act.cols else None)
        if self.evidence_at is not None and cfg.reid_min_evidence > 0 and self._origin is not None:
            lat, lon = local_to_latlon(act["x"][ki, 0], act["x"][ki, 1], *self._origin)
            allowed &= self._evidence_ok(np.ones(len(ki), dtype=bool), act["cls"][ki], lat, lon)[None, :]
        r, c = gated_assignment(cost, allowed)
        now = ready[ki[c]]
        r, k = r[now], ki[c[now]]
        if len(r):
            lost = self._lost
            act.cols["id"][k] = lost["id"][r]
            act.cols["hits"][k] += lost["hits"][r]
            act.cols["support"][k] += lost["support"][r]
            act.cols["confirmed"][k] = True
            act.cols["reid"][k] = True
            act.cols["pending"][k] = False
            keep = np.ones(len(lost), dtype=bool)
            keep[r] = False
            lost.keep(keep)
            self.n_reidentified += len(r)
            log.debug("re-identified %d track(s) after %s s", len(r), np.round(lost_for[r], 2).tolist())
        self._settle(act["pending"] & ready)

    def _settle(self, mask: NDArray[np.bool_]) -> None:
        """Pending tracks that matched no lost track become ordinary new tracks."""
        act = self._active
        act.cols["pending"][mask] = False
        act.cols["confirmed"][mask] = act["support"][mask] >= self.config.confirm_hits

    def _unreported(self, dets: _Detections, t: float) -> NDArray[np.int64]:
        """Indices of active tracks that may still take a lost track's id (`reid_unreported_s`): born
        within that time, id never reported or not reported now (quality below report_quality), not
        pending or on probation, and holding in this frame a georeferenced detection with entry score
        >= reid_score (its row: the "det_row" column)."""
        cfg = self.config
        act = self._active
        if cfg.reid_unreported_s <= 0 or not len(act) or not len(self._lost):
            return np.zeros(0, np.int64)
        row = act["det_row"]
        ok = act["matched"] & (row >= 0) & ~act["probation"] & ~act["pending"] \
            & (t - act["t_born"] <= cfg.reid_unreported_s)
        ok &= ~act["shown"] | (act["quality"] < cfg.report_quality)
        k = np.flatnonzero(ok)
        r = row[k]
        return k[dets.geo[r] & (dets.entry[r] >= cfg.reid_score)]

    def _reidentify(self, dets: _Detections, det_mask: NDArray[np.bool_], t: float,
                    young: NDArray[np.int64] | None = None) -> None:
        """Revive lost tracks on free detections (det_mask) and hand lost ids to young unreported
        tracks (active indices `young`, judged on their detection of this frame), in one assignment."""
        cfg = self.config
        lost = self._lost
        di = np.flatnonzero(det_mask)
        young = np.zeros(0, np.int64) if young is None else young
        cand = np.concatenate([di, self._active["det_row"][young]])
        cost, allowed, lost_for = self._lost_match(dets.z[cand], dets.R[cand], dets.cls[cand], t,
                                                   None if dets.emb is None else dets.emb[cand])
        shown = self._active["shown"][young]
        if shown.any():
            # A young track whose id was reported (now below report_quality) gives it up only for a lost
            # track that its detection looks more like than like the track itself (both descriptors known).
            if dets.emb is None or "emb" not in lost.cols:
                allowed[:, len(di):] &= ~shown[None, :]
            else:
                own = cosine_distance(self._active["emb"][young], dets.emb[cand[len(di):]])
                app = cosine_distance(lost["emb"][:, None, :], dets.emb[cand[len(di):]][None, :, :])
                with np.errstate(invalid="ignore"):
                    allowed[:, len(di):] &= ~shown[None, :] | (app < own[None, :])
        r, c = gated_assignment(cost + dets.score_cost[cand][None, :], allowed)
        adopt = c >= len(di)
        if adopt.any():
            self._adopt(young[c[adopt] - len(di)], r[adopt], dets, t)
        r, c = r[~adopt], c[~adopt]
        if not len(r):
            return
        rows = di[c]
        n = len(r)
        x = np.zeros((n, 4))
        x[:, :2] = dets.z[rows]
        P = np.zeros((n, 4, 4))
        P[:, :2, :2] = dets.R[rows]
        P[:, 2:, 2:] = self._initial_velocity_cov(lost["cls"][r])
        # Provisional: the revived track must be confirmed like a new one (confirm_hits convincing
        # detections within confirm_window_s); until then the memory entry stays, claimed, and comes
        # back unchanged if the track dies (a false positive must not take, or move, an object's id).
        strong = dets.raw[rows] >= cfg.confirm_score
        extra: dict[str, FloatArray] = {}
        if "emb" in lost.cols:
            extra["emb"] = lost["emb"][r] if dets.emb is None else self._ema(lost["emb"][r], dets.emb[rows])
        self._active.append(id=lost["id"][r], cls=lost["cls"][r], x=x, P=P, box=dets.boxes[rows],
                            score=dets.scores[rows], hits=lost["hits"][r] + 1, support=strong.astype(np.int64),
                            t_hit=np.full(n, t), t_born=np.full(n, t), t_shadow=np.full(n, np.nan),
                            confirmed=strong & (cfg.confirm_hits <= 1), matched=np.ones(n, bool),
                            reid=np.zeros(n, bool), strong=strong, R_last=dets.R[rows],
                            quality=lost["quality"][r], heading_hit=np.full(n, self._heading_now),
                            pending=np.zeros(n, bool), probation=np.ones(n, bool), shown=np.ones(n, bool),
                            det_row=rows, **extra)
        lost.cols["claimed"][r] = True
        dets.used[rows] = True
        log.debug("revived %d track(s) on probation after %s s", n, np.round(lost_for[r], 2).tolist())

    def _adopt(self, k: NDArray[np.int64], r: NDArray[np.int64], dets: _Detections, t: float) -> None:
        """Young unreported tracks k take the ids of lost tracks r: on probation like a revival (the
        confirmation starts again from this frame's detection; the memory entry stays, claimed)."""
        cfg = self.config
        act, lost = self._active, self._lost
        rows = act["det_row"][k]
        strong = dets.raw[rows] >= cfg.confirm_score
        log.debug("young track(s) %s take lost id(s) %s on probation", act["id"][k].tolist(), lost["id"][r].tolist())
        act.cols["id"][k] = lost["id"][r]
        act.cols["hits"][k] += lost["hits"][r]
        act.cols["support"][k] = strong
        act.cols["confirmed"][k] = strong & (cfg.confirm_hits <= 1)
        act.cols["probation"][k] = True
        act.cols["shown"][k] = True
        act.cols["t_born"][k] = t
        act.cols["t_shadow"][k] = np.nan
        act.cols["quality"][k] = lost["quality"][r]
        if "emb" in lost.cols:
            act.cols["emb"][k] = lost["emb"][r] if dets.emb is None else self._ema(lost["emb"][r], dets.emb[rows])
        lost.cols["claimed"][r] = True

    def _settle_probation(self) -> None:
        """Revived tracks that are now confirmed keep their old id for good: their memory entries
        are dropped and their support carried over."""
        act = self._active
        done = act["probation"] & act["confirmed"]
        if not done.any():
            return
        lost = self._lost
        k = np.flatnonzero(done)
        act.cols["probation"][k] = False
        act.cols["reid"][k] = True
        entry = lost["claimed"] & np.isin(lost["id"], act["id"][k])
        if entry.any():
            support = dict(zip(lost["id"][entry].tolist(), lost["support"][entry].tolist(), strict=True))
            act.cols["support"][k] += np.array([support.get(i, 0) for i in act["id"][k].tolist()], dtype=np.int64)
            lost.keep(~entry)
        self.n_reidentified += len(k)
        log.debug("re-identified track(s) %s", act["id"][k].tolist())

    def _birth(self, dets: _Detections, det_mask: NDArray[np.bool_], t: float) -> None:
        cfg = self.config
        act = self._active
        order = np.flatnonzero(det_mask)
        order = order[np.argsort(-dets.entry[order], kind="stable")]
        # Not next to a track of the class (on the ground), nor overlapping a box taken in this frame:
        # such detections are leftovers around an object the tracker already follows.
        free = np.ones(len(order), dtype=bool)
        if len(act):
            gate = math.sqrt(cfg.birth_suppress_chi2)
            ti, oj = near_pairs(act["x"][:, :2], gate * sigma_max(act["P"][:, :2, :2]), dets.z[order],
                                gate * sigma_max(dets.R[order]))
            same = act["cls"][ti] == dets.cls[order[oj]]
            ti, oj = ti[same], oj[same]
            dj = order[oj]
            d2, _ = mahalanobis2_and_logdet(dets.z[dj] - act["x"][ti, :2], act["P"][ti, :2, :2] + dets.R[dj])
            free[oj[d2 <= cfg.birth_suppress_chi2]] = False
            taken = act["matched"]
            if taken.any():
                iou = box_iou(act["box"][taken], dets.boxes[order])
                same = act["cls"][taken][:, None] == dets.cls[order][None, :]
                free &= ~((iou >= cfg.birth_suppress_iou) & same).any(axis=0)
        born: list[int] = []
        for j in order[free]:  # strongest first; each newborn suppresses the weaker ones around it
            if born:
                b = np.asarray(born)
                same = dets.cls[b] == dets.cls[j]
                if same.any():
                    if box_iou(dets.boxes[j][None], dets.boxes[b[same]]).max() >= cfg.birth_suppress_iou:
                        continue
                    near = b[same]
                    d2, _ = mahalanobis2_and_logdet(dets.z[j][None] - dets.z[near], dets.R[near] + dets.R[j][None])
                    if d2.min() <= cfg.birth_suppress_chi2:
                        continue
            born.append(int(j))
        if not born:
            return
        b = np.asarray(born, dtype=np.int64)
        n = len(b)
        x = np.zeros((n, 4))
        x[:, :2] = dets.z[b]
        P = np.zeros((n, 4, 4))
        P[:, :2, :2] = dets.R[b]
        P[:, 2:, 2:] = self._initial_velocity_cov(dets.cls[b])
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        # With lost tracks of its class around, a new track may turn out to be an old one.
        pending = np.zeros(n, dtype=bool)
        if cfg.reid_delay_s > 0 and len(self._lost):
            pending = np.isin(dets.cls[b], self._lost["cls"])
        act.append(id=ids, cls=dets.cls[b], x=x, P=P, box=dets.boxes[b], score=dets.scores[b],
                   hits=np.ones(n, np.int64), support=np.ones(n, np.int64), t_hit=np.full(n, t),
                   t_born=np.full(n, t), t_shadow=np.full(n, np.nan), confirmed=~pending & (cfg.confirm_hits <= 1),
                   matched=np.ones(n, bool), reid=np.zeros(n, bool), strong=dets.raw[b] >= cfg.confirm_score,
                   R_last=dets.R[b], quality=dets.raw[b], heading_hit=np.full(n, self._heading_now),
                   pending=pending, probation=np.zeros(n, bool), shown=np.zeros(n, bool), det_row=b,
                   **({} if dets.emb is None else {"emb": dets.emb[b]}))
        dets.used[b] = True

    def _decay_unseen_quality(self, pose: Pose, camera: Camera) -> None:
        """A track in view without a detection counts as a zero in its quality: persistent clutter
        that the detector reports in part of the frames, or weakly, falls below report_quality."""
        act = self._active
        miss = np.flatnonzero(~act["matched"])
        if not len(miss) or self._origin is None:
            return
        uav_e, uav_n = (float(v) for v in latlon_to_local(pose.lat, pose.lon, *self._origin))
        uv, ok = local_to_pixel(act["x"][miss, 0] - uav_e, act["x"][miss, 1] - uav_n, camera, pose)
        m = 0.05 * camera.width
        inside = ok & (uv[:, 0] >= m) & (uv[:, 0] <= camera.width - m) & (uv[:, 1] >= m) \
            & (uv[:, 1] <= camera.height - m)
        act.cols["quality"][miss[inside]] *= 1.0 - self.config.quality_rate

    def _merge_duplicates(self, t: float) -> None:
        """Two confirmed tracks on one object (they share its detections, taking turns): after
        `merge_after_s` of being within `merge_chi2` of a track with more hits, a track is dropped."""
        cfg = self.config
        act = self._active
        conf = np.flatnonzero(act["confirmed"])
        shadowed = np.zeros(len(act), dtype=bool)
        if len(conf) >= 2:
            pos = act["x"][conf, :2]
            pairs = cKDTree(pos).query_pairs(cfg.merge_max_m, output_type="ndarray")
            if len(pairs):
                i, j = conf[pairs[:, 0]], conf[pairs[:, 1]]
                same = act["cls"][i] == act["cls"][j]
                # Two convincing detections in one frame: two objects, whatever their distance.
                same &= ~(act["strong"][i] & act["strong"][j])
                # Taking turns needs a turn: two tracks coasting side by side (out of view, their
                # covariances growing) are no evidence of a duplicate.
                same &= act["matched"][i] | act["matched"][j]
                i, j = i[same], j[same]
                diff = act["x"][i, :2] - act["x"][j, :2]
                # Tracks that take turns on one object's detections differ by about a measurement error.
                S = act["P"][i, :2, :2] + act["P"][j, :2, :2] + 0.5 * (act["R_last"][i] + act["R_last"][j])
                d2, _ = mahalanobis2_and_logdet(diff, S)
                close = d2 <= cfg.merge_chi2
                i, j = i[close], j[close]
                # the track with fewer hits (ties: the newer id) is the duplicate
                j_weaker = (act["hits"][j] < act["hits"][i]) | ((act["hits"][j] == act["hits"][i])
                                                                 & (act["id"][j] > act["id"][i]))
                shadowed[np.where(j_weaker, j, i)] = True
        t_shadow = act.cols["t_shadow"]
        t_shadow[~shadowed] = np.nan
        t_shadow[shadowed & np.isnan(t_shadow)] = t
        merged = shadowed & (t - t_shadow >= cfg.merge_after_s)
        if merged.any():
            log.debug("merged duplicate track(s) %s", act["id"][merged].tolist())
            act.keep(~merged)

    def _retire(self, t: float, camera: Camera | None = None) -> None:
        """Tentative tracks unmatched too long die; confirmed ones go to the re-ID memory, at once
        when their object left the view through the image border (`exit_margin_px`)."""
        cfg = self.config
        act = self._active
        if len(act):
            idle = t - act["t_hit"]
            conf = act["confirmed"]
            drop = (conf & (idle > cfg.max_coast_s)) | (~conf & (idle > cfg.tentative_coast_s))
            if camera is not None and cfg.exit_margin_px >= 0:
                drop |= conf & (idle > cfg.exit_coast_s) & at_image_border(
                    act["box"], camera.width, camera.height, cfg.exit_margin_px)
            # A tentative track not confirmed soon lives on boosted leftovers around some object.
            drop |= ~conf & (t - act["t_born"] > cfg.confirm_window_s + cfg.reid_delay_s)
            to_lost = drop & conf
            if to_lost.any() and cfg.reid_horizon_s > 0:
                self._lost.append(id=act["id"][to_lost], cls=act["cls"][to_lost], pos=act["x"][to_lost][:, :2],
                                  vel=act["x"][to_lost][:, 2:], Ppos=act["P"][to_lost][:, :2, :2],
                                  box=act["box"][to_lost], score=act["score"][to_lost], hits=act["hits"][to_lost],
                                  support=act["support"][to_lost], t_hit=act["t_hit"][to_lost],
                                  quality=act["quality"][to_lost], claimed=np.zeros(int(to_lost.sum()), bool),
                                  **({"emb": act["emb"][to_lost]} if "emb" in act.cols else {}))
            failed = drop & act["probation"]
            if failed.any() and len(self._lost):
                # A revival that was not confirmed: the object's memory entry is free again, unchanged.
                self._lost.cols["claimed"][np.isin(self._lost["id"], act["id"][failed])] = False
            if drop.any():
                act.keep(~drop)
        if len(self._lost):
            self._lost.keep(t - self._lost["t_hit"] <= cfg.reid_horizon_s)

    # ----------------------------------------------------------------------------- filter
    def _predict(self, dt: float) -> None:
        act = self._active
        if not len(act) or dt <= 0:
            return
        accel, _ = self._accel_and_cap(act["cls"])
        x = act["x"]
        x[:, :2] += dt * x[:, 2:]
        P = act["P"]
        # P <- F P F^T with F = [[I, dt I], [0, I]], written blockwise.
        pxx, pxv, pvv = P[:, :2, :2], P[:, :2, 2:], P[:, 2:, 2:]
        new_xx = pxx + dt * (pxv + pxv.transpose(0, 2, 1)) + dt * dt * pvv
        new_xv = pxv + dt * pvv
        q = accel * accel
        eye = np.eye(2)
        P[:, :2, :2] = new_xx + (q * dt**4 / 4.0)[:, None, None] * eye
        P[:, :2, 2:] = new_xv + (q * dt**3 / 2.0)[:, None, None] * eye
        P[:, 2:, :2] = P[:, :2, 2:].transpose(0, 2, 1)
        P[:, 2:, 2:] = pvv + (q * dt * dt)[:, None, None] * eye

    def _kf_update(self, ti: NDArray[np.int64], z: FloatArray, R: FloatArray) -> None:
        act = self._active
        x = act["x"][ti]
        P = act["P"][ti]
        S = P[:, :2, :2] + R
        a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        det = np.maximum(a * d - b * b, 1e-12)
        S_inv = np.empty_like(S)
        S_inv[:, 0, 0], S_inv[:, 1, 1] = d / det, a / det
        S_inv[:, 0, 1] = S_inv[:, 1, 0] = -b / det
        K = P[:, :, :2] @ S_inv  # (n, 4, 2)
        y = z - x[:, :2]
        x = x + np.einsum("nij,nj->ni", K, y)
        P = P - K @ P[:, :2, :]
        P = 0.5 * (P + P.transpose(0, 2, 1))
        _, speed_cap = self._accel_and_cap(act["cls"][ti])
        speed = np.hypot(x[:, 2], x[:, 3])
        x[:, 2:] *= np.minimum(1.0, speed_cap / np.maximum(speed, 1e-9))[:, None]
        act.cols["x"][ti] = x
        act.cols["P"][ti] = P

    def _mark_hit(self, ti: NDArray[np.int64], dets: _Detections, di: NDArray[np.int64], t: float) -> None:
        act = self._active
        act.cols["box"][ti] = dets.boxes[di]
        act.cols["score"][ti] = dets.scores[di]
        act.cols["hits"][ti] += 1
        # Only convincing detections confirm a track: boosted leftovers around an object do not.
        strong = dets.raw[di] >= self.config.confirm_score
        act.cols["quality"][ti] += self.config.quality_rate * (dets.raw[di] - act["quality"][ti])
        act.cols["support"][ti] += strong
        act.cols["strong"][ti] = strong
        if dets.geo[di].all():
            act.cols["R_last"][ti] = dets.R[di]
        act.cols["t_hit"][ti] = t
        act.cols["heading_hit"][ti] = self._heading_now
        if dets.emb is not None:
            act.cols["emb"][ti] = self._ema(act["emb"][ti], dets.emb[di])
        act.cols["matched"][ti] = True
        act.cols["det_row"][ti] = di
        act.cols["confirmed"][ti] |= (act["support"][ti] >= self.config.confirm_hits) & ~act["pending"][ti]
        dets.used[di] = True

    # ----------------------------------------------------------------------------- helpers
    def _motion(self, cid: int) -> ClassMotion:
        m = self._motion_cache.get(cid)
        if m is None:
            m = self.config.motion_for(self.class_names.get(cid))
            self._motion_cache[cid] = m
        return m

    def _accel_and_cap(self, cls: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        accel = np.empty(len(cls))
        cap = np.empty(len(cls))
        for cid in np.unique(cls):
            m = self._motion(int(cid))
            sel = cls == cid
            accel[sel], cap[sel] = m.accel_sigma_mps2, m.max_speed_mps
        return accel, cap

    def _class_arrays(self, cls: NDArray[np.int64]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Speed cap, re-ID spread and persistence per row."""
        out = np.empty((3, len(cls)))
        for cid in np.unique(cls):
            m = self._motion(int(cid))
            out[:, cls == cid] = np.array([[m.max_speed_mps], [m.reid_spread_mps], [m.persistence_s]])
        return out[0], out[1], out[2]

    def _initial_velocity_cov(self, cls: NDArray[np.int64]) -> FloatArray:
        _, cap = self._accel_and_cap(cls)
        return ((cap / 2.0) ** 2)[:, None, None] * np.eye(2)

    def _evidence_ok(self, cand: NDArray[np.bool_], cls: NDArray[np.int64], lat: FloatArray,
                     lon: FloatArray) -> NDArray[np.bool_]:
        assert self.evidence_at is not None
        ok = np.zeros(len(cand), dtype=bool)
        for cid in np.unique(cls[cand]):
            sel = cand & (cls == cid)
            values = np.asarray(self.evidence_at(int(cid), lat[sel], lon[sel]), dtype=np.float64)
            ok[sel] = values >= self.config.reid_min_evidence
        return ok

    def _update_rates(self, pose: Pose, pose_t: float, t: float) -> None:
        """Signed gimbal turn rates (deg/s) from successive distinct poses (telemetry is often
        sample-and-hold at a lower rate than the frames)."""
        ref = self._pose_ref
        if ref is None:
            self._pose_ref, self._t_pose_ref, self._t_frame_ref = pose, pose_t, t
            return
        changed = pose.heading_deg != ref.heading_deg or pose.pitch_deg != ref.pitch_deg
        if changed:
            interval = pose_t - self._t_pose_ref
            if interval <= 1e-3:  # no usable pose clock: the frames' one
                interval = max(t - self._t_frame_ref, 1e-3)
            d_heading = (pose.heading_deg - ref.heading_deg + 180.0) % 360.0 - 180.0
            self._heading_rate_deg_s = d_heading / interval
            self._pitch_rate_deg_s = (pose.pitch_deg - ref.pitch_deg) / interval
            self._pose_interval_s = interval
            self._pose_ref, self._t_pose_ref, self._t_frame_ref = pose, pose_t, t
        elif t - self._t_frame_ref > max(0.25, 2.0 * self._pose_interval_s):
            # No new telemetry for a while: the gimbal holds still.
            self._heading_rate_deg_s = self._pitch_rate_deg_s = 0.0

    def _maybe_reanchor(self, pose: Pose) -> None:
        if self._origin is None:
            self._origin = (pose.lat, pose.lon)
            return
        e, n = latlon_to_local(pose.lat, pose.lon, *self._origin)
        if math.hypot(float(e), float(n)) <= self.config.reanchor_m:
            return
        old, new = self._origin, (pose.lat, pose.lon)
        for table, key in ((self._active, "x"), (self._lost, "pos")):
            if len(table):
                pos = table.cols[key]
                lat, lon = local_to_latlon(pos[:, 0], pos[:, 1], *old)
                pos[:, 0], pos[:, 1] = latlon_to_local(lat, lon, *new)
        self._origin = new
        log.debug("re-anchored the local frame at %.6f, %.6f", *new)

    def _outputs(self) -> list[TrackOutput]:
        act = self._active
        n = len(act)
        if not n:
            return []
        if self._origin is not None:
            lat, lon = local_to_latlon(act["x"][:, 0], act["x"][:, 1], *self._origin)
        else:
            lat = lon = np.full(n, np.nan)
        now = self._t if self._t is not None else 0.0
        # Python scalars column by column: building 1,000 outputs stays ~1 ms.
        cols = zip(act["id"].tolist(), act["cls"].tolist(), map(tuple, act["box"].tolist()), lat.tolist(),
                   lon.tolist(), map(tuple, act["x"][:, 2:].tolist()), act["score"].tolist(),
                   act["confirmed"].tolist(), act["matched"].tolist(), act["hits"].tolist(),
                   (now - act["t_hit"]).tolist(), act["reid"].tolist(), act["quality"].tolist(), strict=True)
        return [TrackOutput(*c) for c in cols]


def _unit_rows(emb: NDArray, n: int) -> FloatArray | None:
    """(n, D) descriptors scaled to unit length; rows that are not finite or zero become NaN."""
    e = np.asarray(emb, dtype=np.float64).reshape(n, -1)
    if not e.shape[1]:
        return None
    norm = np.linalg.norm(e, axis=1, keepdims=True)
    ok = np.isfinite(norm) & (norm > 1e-12)
    return np.where(ok, e / np.where(ok, norm, 1.0), np.nan)


def cosine_distance(a: FloatArray, b: FloatArray) -> FloatArray:
    """1 - cosine similarity of unit rows a (..., D) and b (..., D) (broadcast); NaN where either is NaN."""
    return 1.0 - np.einsum("...d,...d->...", a, b)


def _box_tuple(box: NDArray) -> tuple[float, float, float, float]:
    return (float(box[0]), float(box[1]), float(box[2]), float(box[3]))

"""Detector emulator: pre-NMS candidate boxes with the statistics of real aerial detectors (PAPER.md 2).

Real single-frame detectors find almost every object before NMS (recall 97-99 %) as a dense cluster of
low-confidence boxes, but after NMS and a score threshold only 86-88 % survive, because an object's
confidence fluctuates from frame to frame. This module reproduces that, deterministically per seed.

Model, per frame of one UAV (every knob is a field of `EmulatorParams`; defaults in brackets, scenarios
override some of them in `sim.scenarios`):

Objects (visible targets).
- Best-box logit = ``logit_at_32px`` [2.0] + ``logit_per_octave`` [0.9] * clip(log2(size_px / 32),
  ``octave_clip`` [(-3, 1.5)]) + d + e, where size_px = sqrt(w * h) of the true box, d is a per-object
  difficulty that varies slowly (AR(1), std ``difficulty_std`` [1.0], correlation time
  ``difficulty_corr_s`` [2 s]) and e is independent per-frame noise (std ``frame_noise_std`` [1.6]).
- Missed before NMS entirely with probability ``miss_rate`` [0.012], or ``small_miss_rate`` [0.06] when
  size_px < ``small_px`` [10 px].
- A cluster of n boxes, n in ``cluster_boxes`` [(5, 30)] growing with size_px (times U(0.7, 1.3)); box
  scores are best * U^``cluster_score_decay`` [2.5] (the first box is the best one). The cluster is displaced
  by a shared localisation error of ``box_bias_frac`` [0.09] of the box size (centre and log-size), and each
  box jitters around it by ``box_jitter_frac`` [0.05] of the size (times 1 + ``jitter_growth`` [0.6] *
  (1 - relative score)) plus ``box_jitter_px`` [0.3 px].
- With probability ``duplicate_box_rate`` [0.08] one extra part box (the upper half of a person, a shifted
  swimmer) scoring best * U(``duplicate_score_range``) [(0.1, 0.5)]: it survives NMS as a false positive.
Occluded objects (behind a tree; not annotated): the same cluster with the logit lowered by
``occluded_logit_drop`` [4.0] (foliage lets a weak signal through).
Weakly seen objects: a share ``weak_fraction`` [0] of the objects (drawn per UAV by the simulator: glare on the
water, a shadow, thin foliage this UAV looks through) score with the logit lowered by ``weak_logit_drop`` [3.0]
in every frame this detector sees them.
Clutter (persistent false positives at fixed world spots: rocks, buoys): detected in a frame with
probability ``clutter_detect_prob`` [0.6], logit lowered by ``clutter_logit_drop`` [2.5].
Background false positives: Poisson(``fp_per_frame`` [20]) spots, uniform in the image below the horizon
row + ``fp_horizon_margin_frac`` [0.03] of the height; each a mini cluster of 1 + Poisson(``fp_cluster_mean``
- 1) [2.0] boxes. Best logit ~ N(``fp_logit_mean`` [-3.2], ``fp_logit_std`` [1.3]), except for a fraction
``fp_confusing_frac`` [0.15] of confusing spots (glare, wave crests, bushes) with logit ~
N(``fp_confusing_logit``) [(0.3, 1.5)] (mean, std). Box size = the class's expected size at that pixel
(from `shared.geo.metres_per_pixel`) times lognormal(``fp_size_log_std`` [0.35]), except for a fraction
``fp_implausible_frac`` [0.35] whose size is multiplied by a factor in ``fp_implausible_small``
[(0.08, 0.3)] or ``fp_implausible_big`` [(3, 10)]: far too small or big for the class at that range (what
a distance-size filter removes).
Blur: a frame is blurred when the gimbal turns faster than ``blur_heading_rate_deg_s`` [30 deg/s] or at
random with probability ``blur_random_rate`` [0.03]; then every score is multiplied by one factor from
U(``blur_score_factor``) [(0.1, 0.3)] and all jitter by ``blur_jitter_mult`` [1.5].
Score regime: every score is finally mapped through logit -> ``score_logit_scale`` [1] * logit +
``score_logit_shift`` [0] (an over-confident detector: scale > 1 or shift > 0; under-confident: below);
the identity draws nothing and changes nothing.
Finally boxes are clipped to the image; boxes under 1 px or scoring below ``score_threshold`` [0.02] are
dropped. Candidates of the class's category only (no class confusion).

Appearance descriptors (what a re-ID head such as DeepSORT's or JDE's, or a colour histogram of the box
crop, gives per box; optional, off when ``appearance_dim`` [16] is 0). Every target key (object or
clutter) has a fixed unit vector (`object_appearance`): one of ``appearance_groups`` [6] look-alike groups
(clothing colours; swimmers: caps) plus an individual part of relative length ``appearance_spread`` [0.6]
(cosine ~0.74 between two members of a group, ~0 across groups). A candidate's descriptor is its target's
vector plus isotropic noise of relative length ``appearance_noise`` [0.45] * clip(32 / size_px, 0.5, 4)
(small boxes carry few pixels), times ``appearance_blur_mult`` [2] in blurred frames and 1.5 for part
boxes, renormalised. Background false positives look like a random group (a bush may resemble a green
jacket) with noise 1. Only candidates scoring at least ``appearance_min_score`` [0.25] carry one (the
others never start or revive a track; this keeps pre_nms.json small). The noise is drawn from a
generator of its own, so the boxes and scores are the same with and without descriptors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from shared.geo import Camera, Pose, horizon_row, metres_per_pixel

#: Target kinds passed to `DetectorEmulator.detect`.
KIND_OBJECT, KIND_OCCLUDED, KIND_CLUTTER = 0, 1, 2


@dataclass(frozen=True, slots=True)
class EmulatorParams:
    """Knobs of the detector emulator; see the module docstring for their meaning and defaults."""

    score_threshold: float = 0.02
    logit_at_32px: float = 2.0
    logit_per_octave: float = 0.9
    octave_clip: tuple[float, float] = (-3.0, 1.5)
    difficulty_std: float = 1.0
    difficulty_corr_s: float = 2.0
    frame_noise_std: float = 1.6
    miss_rate: float = 0.012
    small_px: float = 10.0
    small_miss_rate: float = 0.06
    cluster_boxes: tuple[int, int] = (5, 30)
    cluster_score_decay: float = 2.5
    box_jitter_frac: float = 0.05
    jitter_growth: float = 0.6
    box_jitter_px: float = 0.3
    box_bias_frac: float = 0.09
    duplicate_box_rate: float = 0.08
    duplicate_score_range: tuple[float, float] = (0.1, 0.5)
    occluded_logit_drop: float = 4.0
    clutter_detect_prob: float = 0.6
    clutter_logit_drop: float = 2.5
    fp_per_frame: float = 20.0
    fp_horizon_margin_frac: float = 0.03
    fp_cluster_mean: float = 2.0
    fp_logit_mean: float = -3.2
    fp_logit_std: float = 1.3
    fp_confusing_frac: float = 0.15
    fp_confusing_logit: tuple[float, float] = (0.3, 1.5)
    fp_size_log_std: float = 0.35
    fp_implausible_frac: float = 0.35
    fp_implausible_small: tuple[float, float] = (0.08, 0.3)
    fp_implausible_big: tuple[float, float] = (3.0, 10.0)
    blur_heading_rate_deg_s: float = 30.0
    blur_random_rate: float = 0.03
    blur_score_factor: tuple[float, float] = (0.1, 0.3)
    blur_jitter_mult: float = 1.5
    appearance_dim: int = 16
    appearance_groups: int = 6
    appearance_spread: float = 0.6
    appearance_noise: float = 0.45
    appearance_blur_mult: float = 2.0
    appearance_min_score: float = 0.25
    score_logit_scale: float = 1.0
    score_logit_shift: float = 0.0
    weak_fraction: float = 0.0
    weak_logit_drop: float = 3.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise ValueError(f"EmulatorParams.{f.name}={value!r} must be finite numbers")
        if not 0.0 < self.score_threshold < 1.0:
            raise ValueError(f"EmulatorParams.score_threshold={self.score_threshold!r} must be in (0, 1)")
        lo, hi = self.cluster_boxes
        if not 1 <= lo <= hi:
            raise ValueError(f"EmulatorParams.cluster_boxes={self.cluster_boxes!r} must satisfy 1 <= low <= high")
        for name in ("miss_rate", "small_miss_rate", "duplicate_box_rate", "clutter_detect_prob",
                     "fp_implausible_frac", "blur_random_rate", "fp_confusing_frac", "weak_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"EmulatorParams.{name}={getattr(self, name)!r} must be a probability")
        if self.difficulty_corr_s <= 0 or self.fp_per_frame < 0:
            raise ValueError("EmulatorParams.difficulty_corr_s must be > 0 and fp_per_frame >= 0")
        if self.score_logit_scale <= 0:
            raise ValueError(f"EmulatorParams.score_logit_scale={self.score_logit_scale!r} must be > 0")
        for name in ("appearance_dim", "appearance_groups"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if name == "appearance_dim" else 1):
                raise ValueError(f"EmulatorParams.{name}={value!r} must be an integer >= "
                                 f"{0 if name == 'appearance_dim' else 1}")
        for name in ("appearance_spread", "appearance_noise", "appearance_blur_mult", "appearance_min_score"):
            if getattr(self, name) < 0:
                raise ValueError(f"EmulatorParams.{name}={getattr(self, name)!r} must be >= 0")


@dataclass(frozen=True, slots=True)
class Candidates:
    """Pre-NMS candidates of one frame.

    Attributes
    ----------
    boxes_xywh : (N, 4) float64
        COCO boxes [x, y, w, h] in pixels, inside the image.
    scores : (N,) float64
        Confidences in [score_threshold, 1).
    category_ids : (N,) int64
        COCO category ids.
    embeddings : (N, D) float32 or None
        Unit appearance descriptors, NaN rows for candidates without one; None when the emulator has
        no appearance model.
    """

    boxes_xywh: np.ndarray
    scores: np.ndarray
    category_ids: np.ndarray
    embeddings: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.scores)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def object_appearance(n_keys: int, params: EmulatorParams, rng: np.random.Generator) -> np.ndarray:
    """Fixed appearance vectors of a world's targets: (n_keys, appearance_dim) float64 unit rows.

    Each key belongs to one of `appearance_groups` look-alike groups (a random unit centre) and adds an
    individual random direction of relative length `appearance_spread`. Deterministic given rng.
    """
    d = params.appearance_dim
    centres = _unit(rng.standard_normal((params.appearance_groups, d)))
    group = rng.integers(0, params.appearance_groups, n_keys)
    own = _unit(rng.standard_normal((n_keys, d)))
    return _unit(centres[group] + params.appearance_spread * own)


class DetectorEmulator:
    """Stateful candidate generator of one UAV's detector.

    Parameters
    ----------
    params : EmulatorParams
    camera : shared.geo.Camera
    rng : numpy.random.Generator
        Private generator (the emulator is deterministic given it and the call sequence).
    n_keys : int
        Number of target keys (objects and clutter of the world) whose difficulty state is tracked.
    box_m : (width_m, depth_m, height_m)
        The class's 3-D size, used for the expected size of background false positives.
    fp_category_id : int
        Category id given to background false positives.
    """

    def __init__(self, params: EmulatorParams, camera: Camera, rng: np.random.Generator, n_keys: int,
                 box_m: tuple[float, float, float], fp_category_id: int, *,
                 appearance: np.ndarray | None = None, appearance_rng: np.random.Generator | None = None,
                 weak: np.ndarray | None = None) -> None:
        self.params, self.camera, self._rng = params, camera, rng
        if weak is not None:
            weak = np.asarray(weak, dtype=bool)
            if weak.shape != (n_keys,):
                raise ValueError(f"weak must be a ({n_keys},) mask of the weakly seen targets, got {weak.shape}")
        #: (n_keys,) bool: the targets this detector sees weakly (logit - weak_logit_drop), None = none
        self.weak = weak
        self._difficulty = np.zeros(n_keys)
        self._last_t = np.full(n_keys, -np.inf)
        self.box_m = box_m
        self.fp_category_id = int(fp_category_id)
        if appearance is not None:
            appearance = np.asarray(appearance, dtype=np.float64)
            if appearance.ndim != 2 or len(appearance) != n_keys or appearance_rng is None:
                raise ValueError("appearance must be (n_keys, D) and needs appearance_rng")
        self.appearance = appearance
        self._app_rng = appearance_rng
        # Look-alike group centres for background false positives.
        self._fp_looks = None if appearance is None else _unit(appearance_rng.standard_normal(  # type: ignore[union-attr]
            (params.appearance_groups, appearance.shape[1])))

    def _descriptors(self, vectors: np.ndarray, size_px: np.ndarray, noise_mult: np.ndarray,
                     blurred: bool) -> np.ndarray:
        """Noisy unit descriptors of (K, D) true vectors seen in boxes of size_px (K,)."""
        p = self.params
        sigma = p.appearance_noise * np.clip(32.0 / np.maximum(size_px, 1e-6), 0.5, 4.0) * noise_mult
        if blurred:
            sigma = sigma * p.appearance_blur_mult
        noise = _unit(self._app_rng.standard_normal(vectors.shape))  # type: ignore[union-attr]
        return _unit(vectors + sigma[:, None] * noise)

    def is_blurred(self, heading_rate_deg_s: float) -> bool:
        """Draw whether the next frame is blurred (consumes one random number)."""
        p = self.params
        random_blur = self._rng.uniform() < p.blur_random_rate
        return bool(random_blur or abs(heading_rate_deg_s) > p.blur_heading_rate_deg_s)

    def _update_difficulty(self, keys: np.ndarray, t_s: float) -> np.ndarray:
        p = self.params
        dt = t_s - self._last_t[keys]
        a = np.exp(-dt / p.difficulty_corr_s)  # 0 for keys never seen (dt = inf)
        self._difficulty[keys] = a * self._difficulty[keys] + np.sqrt(1.0 - a * a) * self._rng.normal(
            0.0, p.difficulty_std, len(keys))
        self._last_t[keys] = t_s
        return self._difficulty[keys]

    def _clusters(self, boxes_xyxy: np.ndarray, best: np.ndarray, n_boxes: np.ndarray,
                  jitter_mult: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Expand M (box, best score, count) into jittered boxes; returns xyxy (K, 4), scores (K,), owner (K,).

        The whole cluster is first displaced by a shared localisation error (`box_bias_frac`), then each box
        jitters around it (`box_jitter_frac`, more for low-ranked boxes, plus `box_jitter_px`).
        """
        p, rng = self.params, self._rng
        m = len(best)
        bw, bh = boxes_xyxy[:, 2] - boxes_xyxy[:, 0], boxes_xyxy[:, 3] - boxes_xyxy[:, 1]
        zb = rng.standard_normal((m, 4)) * p.box_bias_frac * jitter_mult
        bcx = 0.5 * (boxes_xyxy[:, 0] + boxes_xyxy[:, 2]) + zb[:, 0] * bw
        bcy = 0.5 * (boxes_xyxy[:, 1] + boxes_xyxy[:, 3]) + zb[:, 1] * bh
        bw, bh = bw * np.exp(zb[:, 2]), bh * np.exp(zb[:, 3])
        boxes_xyxy = np.column_stack([bcx - 0.5 * bw, bcy - 0.5 * bh, bcx + 0.5 * bw, bcy + 0.5 * bh])
        owner = np.repeat(np.arange(len(best)), n_boxes)
        k = len(owner)
        first = np.zeros(k, dtype=bool)
        starts = np.cumsum(n_boxes) - n_boxes
        first[starts[n_boxes > 0]] = True
        ratio = np.where(first, 1.0, rng.uniform(size=k) ** p.cluster_score_decay)
        jit = p.box_jitter_frac * (1.0 + p.jitter_growth * (1.0 - ratio)) * jitter_mult
        b = boxes_xyxy[owner]
        w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
        z = rng.standard_normal((k, 4))
        px = p.box_jitter_px * jitter_mult
        cx = 0.5 * (b[:, 0] + b[:, 2]) + z[:, 0] * (jit * w + px)
        cy = 0.5 * (b[:, 1] + b[:, 3]) + z[:, 1] * (jit * h + px)
        w2 = np.maximum(w * np.exp(z[:, 2] * jit) + rng.normal(0.0, px, k), 1.0)
        h2 = np.maximum(h * np.exp(z[:, 3] * jit) + rng.normal(0.0, px, k), 1.0)
        out = np.column_stack([cx - 0.5 * w2, cy - 0.5 * h2, cx + 0.5 * w2, cy + 0.5 * h2])
        return out, best[owner] * ratio, owner

    def _background(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Background false-positive spots: (F, 4) xyxy boxes and (F,) best scores."""
        p, rng, cam = self.params, self._rng, self.camera
        top = max(horizon_row(cam, pose) + p.fp_horizon_margin_frac * cam.height, 0.0)
        n = int(rng.poisson(p.fp_per_frame))
        if n == 0 or top >= cam.height - 2.0:
            return np.zeros((0, 4)), np.zeros(0)
        uv = np.column_stack([rng.uniform(0.0, cam.width, n), rng.uniform(top, cam.height, n)])
        mpp = metres_per_pixel(uv, cam, pose)
        ok = np.isfinite(mpp)
        uv, mpp = uv[ok], mpp[ok]
        n = len(uv)
        # Depression of each pixel's ray (for the class's apparent height vs. width).
        dep = np.radians(pose.pitch_deg) + np.arctan((uv[:, 1] - cam.cy) / cam.fy)
        width_m, depth_m, height_m = self.box_m
        apparent_h_m = height_m * np.cos(dep) + depth_m * np.abs(np.sin(dep))
        scale = np.exp(rng.normal(0.0, p.fp_size_log_std, n))
        odd = rng.uniform(size=n) < p.fp_implausible_frac
        big = rng.uniform(size=n) < 0.5
        factor = np.where(big, rng.uniform(*p.fp_implausible_big, n), rng.uniform(*p.fp_implausible_small, n))
        scale = np.where(odd, scale * factor, scale)
        w = width_m / mpp * scale
        h = apparent_h_m / mpp * scale * np.exp(rng.normal(0.0, 0.2, n))
        boxes = np.column_stack([uv[:, 0] - 0.5 * w, uv[:, 1] - 0.5 * h, uv[:, 0] + 0.5 * w, uv[:, 1] + 0.5 * h])
        confusing = rng.uniform(size=n) < p.fp_confusing_frac
        logit = np.where(confusing, rng.normal(p.fp_confusing_logit[0], p.fp_confusing_logit[1], n),
                         rng.normal(p.fp_logit_mean, p.fp_logit_std, n))
        return boxes, _sigmoid(logit)

    def detect(self, boxes_xyxy: np.ndarray, keys: np.ndarray, kinds: np.ndarray, category_ids: np.ndarray,
               pose: Pose, t_s: float, blurred: bool) -> Candidates:
        """Candidates of one frame.

        Parameters
        ----------
        boxes_xyxy : (M, 4) float
            True (clipped) boxes of the targets in view: objects, occluded objects and clutter.
        keys : (M,) int
            Target keys in [0, n_keys) (difficulty state).
        kinds : (M,) int
            KIND_OBJECT, KIND_OCCLUDED or KIND_CLUTTER.
        category_ids : (M,) int
            Category of each target.
        pose : shared.geo.Pose
            TRUE pose of the camera (for background false positives).
        t_s : float
            Frame time in seconds (any clock that increases; drives the AR(1) difficulty).
        blurred : bool
            Whether this frame is blurred (see `is_blurred`).

        Returns
        -------
        Candidates
        """
        p, rng, cam = self.params, self._rng, self.camera
        m = len(keys)
        boxes_xyxy = np.asarray(boxes_xyxy, dtype=np.float64).reshape(m, 4)
        keys = np.asarray(keys, dtype=np.int64)
        kinds = np.asarray(kinds)
        category_ids = np.asarray(category_ids, dtype=np.int64)
        jitter_mult = p.blur_jitter_mult if blurred else 1.0

        w = boxes_xyxy[:, 2] - boxes_xyxy[:, 0]
        h = boxes_xyxy[:, 3] - boxes_xyxy[:, 1]
        size_px = np.sqrt(np.maximum(w * h, 1e-6))
        octave = np.clip(np.log2(size_px / 32.0), *p.octave_clip)
        logit = p.logit_at_32px + p.logit_per_octave * octave + self._update_difficulty(keys, t_s)
        logit = logit + rng.normal(0.0, p.frame_noise_std, m)
        logit = logit - np.where(kinds == KIND_OCCLUDED, p.occluded_logit_drop, 0.0)
        logit = logit - np.where(kinds == KIND_CLUTTER, p.clutter_logit_drop, 0.0)
        if self.weak is not None:
            logit = logit - np.where(self.weak[keys] & (kinds != KIND_CLUTTER), p.weak_logit_drop, 0.0)
        miss_p = np.where(size_px < p.small_px, p.small_miss_rate, p.miss_rate)
        miss_p = np.where(kinds == KIND_CLUTTER, 1.0 - p.clutter_detect_prob, miss_p)
        present = rng.uniform(size=m) >= miss_p
        lo, hi = p.cluster_boxes
        frac = np.clip(np.log2(size_px / 8.0) / 4.0, 0.0, 1.0)
        n_boxes = np.clip(np.round((lo + (hi - lo) * frac) * rng.uniform(0.7, 1.3, m)), lo, hi).astype(np.int64)
        n_boxes = np.where(present, n_boxes, 0)
        best = _sigmoid(logit)
        obj_boxes, obj_scores, owner = self._clusters(boxes_xyxy, best, n_boxes, jitter_mult)
        obj_cats = category_ids[owner]

        # Part boxes that NMS does not merge with the object's box.
        dup = present & (kinds != KIND_CLUTTER) & (rng.uniform(size=m) < p.duplicate_box_rate)
        d = boxes_xyxy[dup]
        dw, dh = d[:, 2] - d[:, 0], d[:, 3] - d[:, 1]
        tall = dh > 1.3 * dw
        shift = rng.choice([-1.0, 1.0], len(d)) * 0.7 * dw
        dup_boxes = np.where(tall[:, None],
                             np.column_stack([d[:, 0], d[:, 1], d[:, 2], d[:, 1] + 0.45 * dh]),
                             np.column_stack([d[:, 0] + shift, d[:, 1], d[:, 2] + shift, d[:, 3]]))
        dup_scores = best[dup] * rng.uniform(*p.duplicate_score_range, len(d))

        fp_spots, fp_best = self._background(pose)
        fp_n = 1 + rng.poisson(max(p.fp_cluster_mean - 1.0, 0.0), len(fp_best))
        fp_boxes, fp_scores, fp_owner = self._clusters(fp_spots, fp_best, fp_n, jitter_mult)

        boxes = np.vstack([obj_boxes, dup_boxes, fp_boxes])
        scores = np.concatenate([obj_scores, dup_scores, fp_scores])
        cats = np.concatenate([obj_cats, category_ids[dup], np.full(len(fp_scores), self.fp_category_id)])
        if blurred:
            scores = scores * rng.uniform(*p.blur_score_factor)
        if p.score_logit_scale != 1.0 or p.score_logit_shift != 0.0:
            logit = np.log(np.clip(scores, 1e-9, 1 - 1e-9) / np.clip(1.0 - scores, 1e-9, None))
            scores = _sigmoid(p.score_logit_scale * logit + p.score_logit_shift)
        boxes[:, 0::2] = np.clip(boxes[:, 0::2], 0.0, float(cam.width))
        boxes[:, 1::2] = np.clip(boxes[:, 1::2], 0.0, float(cam.height))
        bw, bh = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
        keep = (scores >= p.score_threshold) & (bw >= 1.0) & (bh >= 1.0)
        xywh = np.column_stack([boxes[keep, 0], boxes[keep, 1], bw[keep], bh[keep]])
        embeddings = None
        if self.appearance is not None:
            n_obj, n_dup = len(obj_boxes), len(dup_boxes)
            fp_size = np.sqrt(np.maximum((fp_spots[:, 2] - fp_spots[:, 0]) * (fp_spots[:, 3] - fp_spots[:, 1]), 1e-6))
            fp_vec = self._fp_looks[self._app_rng.integers(0, len(self._fp_looks), len(fp_spots))]  # type: ignore
            vectors = np.vstack([self.appearance[keys[owner]], self.appearance[keys[dup]], fp_vec[fp_owner]])
            size = np.concatenate([size_px[owner], size_px[dup], fp_size[fp_owner]])
            mult = np.concatenate([np.ones(n_obj), np.full(n_dup, 1.5),
                                   np.full(len(fp_owner), 1.0 / max(p.appearance_noise, 1e-6))])
            # FP noise is 1 (relative length) whatever the box size.
            mult[n_obj + n_dup:] /= np.clip(32.0 / np.maximum(size[n_obj + n_dup:], 1e-6), 0.5, 4.0)
            carry = keep & (scores >= p.appearance_min_score)
            embeddings = np.full((len(scores), vectors.shape[1]), np.nan, dtype=np.float32)
            if carry.any():
                embeddings[carry] = self._descriptors(vectors[carry], size[carry], mult[carry], blurred)
            embeddings = embeddings[keep]
        return Candidates(xywh, np.minimum(scores[keep], 0.9999), cats[keep].astype(np.int64), embeddings)

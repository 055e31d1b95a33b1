"""The sea in motion: travelling waves, twinkling glint facets, transient whitecaps and glint sparkles.

A real sea is not fixed in the world. Its crests travel (deep water: phase speed sqrt(g lambda / 2 pi), about
1.8 m/s for 2 m waves), the short waves riding on them travel slower (about 0.9 m/s at 0.5 m) and tilt the
long waves' facets towards the sun and away again, so a glint facet lives a fraction of a second; breaking
crests flash white for a moment and the sun's glitter twinkles from frame to frame.

`WaveDrift` moves the ground texture (colour, crests, glint potential) with the long waves' phase speed
towards the wind direction and the texture's facets channel with the short waves' speed: the glint
(potential x facets) changes where the two patterns slide over each other, about 0.9 m/s, i.e. a 0.4 m
facet lives ~0.4 s. The drift is a function of the world time alone, so every UAV sees the same sea.
`SeaEvents` draws transient whitecaps and sparkles on top of the warped texture.

Events live in world space-time: time is cut into buckets of `BUCKET_S`; bucket k's events (positions over
the ground texture's extent, start times within the bucket, lifetimes, sizes) come from a generator seeded by
(seed, world group, role, k), so every frame, video and UAV of a seed sees the same whitecap at the same place
and moment, and rendering a frame twice gives identical pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from shared.geo import Camera, Pose
from sim.render.geometry import project_enu

#: Length of a time bucket of events, seconds.
BUCKET_S = 0.1
#: Phase speeds (m/s) of the long waves (~2 m: the texture's colour, crests, glint potential) and of the short
#: waves that tilt its facets (~0.5 m), deep water.
LONG_WAVE_MPS, SHORT_WAVE_MPS = 1.8, 0.9
#: The drift wraps after the long waves have travelled this far (the near texture is grown upwind by as much
#: as the world's videos need, at most this): a sea shown for longer jumps back once per wrap (67 s).
MAX_DRIFT_M = 120.0
#: Outline points of a projected event disc.
_N_OUTLINE = 10
_CIRCLE = np.column_stack([np.cos(np.linspace(0, 2 * math.pi, _N_OUTLINE, endpoint=False)),
                           np.sin(np.linspace(0, 2 * math.pi, _N_OUTLINE, endpoint=False))])
_SHIFT = 4


@dataclass(frozen=True, slots=True)
class WaveDrift:
    """How far the sea's texture has travelled at a world time (seconds since the world's first frame).

    wind_deg: where the waves travel towards, degrees clockwise from north.
    """

    wind_deg: float
    long_mps: float = LONG_WAVE_MPS
    short_mps: float = SHORT_WAVE_MPS
    max_drift_m: float = MAX_DRIFT_M

    @property
    def period_s(self) -> float:
        """Seconds after which the drift wraps."""
        return self.max_drift_m / self.long_mps

    def offset_en(self, t_s: float, speed_mps: float) -> tuple[float, float]:
        """(east, north) metres the pattern moving at speed_mps has travelled at t_s (wrapped, >= 0 along)."""
        d = speed_mps * (t_s % self.period_s)
        a = math.radians(self.wind_deg)
        return d * math.sin(a), d * math.cos(a)

    def moved(self, texel_to_world: np.ndarray, t_s: float, speed_mps: float) -> np.ndarray:
        """(3, 3) texel -> world affine of a texture carried by the waves moving at speed_mps."""
        de, dn = self.offset_en(t_s, speed_mps)
        return np.array([[1.0, 0.0, de], [0.0, 1.0, dn], [0.0, 0.0, 1.0]]) @ np.asarray(texel_to_world, np.float64)

    def grow(self, extent_m: tuple[float, float, float, float],
             times_s: np.ndarray) -> tuple[float, float, float, float]:
        """extent_m grown upwind so the texture still covers it at every time in times_s (the ground at world
        point p shows the texel at p - offset)."""
        reach = self.long_mps * float(np.max(np.asarray(times_s) % self.period_s, initial=0.0))
        a = math.radians(self.wind_deg)
        de, dn = reach * math.sin(a), reach * math.cos(a)
        e0, n0, e1, n1 = extent_m
        return e0 - max(de, 0.0), n0 - max(dn, 0.0), e1 - min(de, 0.0), n1 - min(dn, 0.0)


@dataclass(frozen=True, slots=True)
class EventKind:
    """One kind of transient event.

    rate_per_m2_s: events per square metre of sea per second; life_s: (min, max) lifetime; radius_m: (min, max);
    bgr: colour; opacity: (min, max) peak opacity; in_glint: drawn only where the sun glint is (scaled by it).
    """

    rate_per_m2_s: float
    life_s: tuple[float, float]
    radius_m: tuple[float, float]
    bgr: tuple[float, float, float]
    opacity: tuple[float, float]
    in_glint: bool = False


#: Breaking crests: ~0.2 % of the sea white at any moment, 0.25-0.8 m, 0.2-0.7 s.
WHITECAPS = EventKind(0.006, (0.2, 0.7), (0.25, 0.8), (228.0, 232.0, 228.0), (0.45, 0.9))
#: Glitter: facets mirroring the sun for one or two frames, only inside the glint patch.
SPARKLES = EventKind(0.08, (0.03, 0.12), (0.05, 0.15), (255.0, 255.0, 255.0), (0.7, 1.0), in_glint=True)

#: Residual foam: the patches a broken crest leaves behind, fading over seconds (rate set by `SeaState.foam_rate`).
FOAM = EventKind(1.0, (1.5, 4.0), (0.15, 0.45), (220.0, 226.0, 222.0), (0.3, 0.7))


class SeaEvents:
    """The transient events of one world (deterministic for its seed and group)."""

    def __init__(self, seed: int, group: int, role: int, extent_m: tuple[float, float, float, float],
                 kinds: tuple[EventKind, ...] = (WHITECAPS, SPARKLES)) -> None:
        self.seed, self.group, self.role = int(seed), int(group), int(role)
        self.extent_m = extent_m
        self.kinds = kinds
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def _bucket(self, kind_index: int, k: int) -> np.ndarray:
        """(N, 6) events of one bucket: east, north, start s, life s, radius m, peak opacity."""
        key = (kind_index, k)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        kind = self.kinds[kind_index]
        e0, n0, e1, n1 = self.extent_m
        rng = np.random.default_rng([self.seed, self.group, self.role, kind_index, k & 0x7FFFFFFF])
        n = int(rng.poisson(kind.rate_per_m2_s * (e1 - e0) * (n1 - n0) * BUCKET_S))
        ev = np.column_stack([rng.uniform(e0, e1, n), rng.uniform(n0, n1, n), (k + rng.uniform(0, 1, n)) * BUCKET_S,
                              rng.uniform(*kind.life_s, n), rng.uniform(*kind.radius_m, n),
                              rng.uniform(*kind.opacity, n)])
        if len(self._cache) > 4096:
            self._cache.clear()
        self._cache[key] = ev
        return ev

    def active(self, kind_index: int, t_s: float) -> np.ndarray:
        """(M, 6) events alive at t_s, the last column their opacity now (a sine envelope over the life)."""
        kind = self.kinds[kind_index]
        k1 = math.floor(t_s / BUCKET_S)
        k0 = math.floor((t_s - kind.life_s[1]) / BUCKET_S)
        ev = np.vstack([self._bucket(kind_index, k) for k in range(k0, k1 + 1)])
        age = t_s - ev[:, 2]
        alive = (age >= 0) & (age < ev[:, 3])
        ev = ev[alive].copy()
        ev[:, 5] *= np.sin(math.pi * (age[alive] / ev[:, 3]))
        return ev

    def draw(self, image: np.ndarray, camera: Camera, pose: Pose, uav_en: tuple[float, float], t_s: float,
             first_row: int, glint: tuple[np.ndarray, tuple[int, int, int, int]] | None) -> int:
        """Draw the events alive at t_s into image (in place, below first_row); returns how many were drawn."""
        h, w = image.shape[:2]
        drawn = 0
        for i, kind in enumerate(self.kinds):
            if kind.in_glint and glint is None:
                continue
            ev = self.active(i, t_s)
            if not len(ev):
                continue
            rel = ev[:, :2] - np.asarray(uav_en)[None, :]
            centre, ok = project_enu(np.column_stack([rel, np.zeros(len(ev))]), camera, pose)
            inside = ok & (centre[:, 0] > -20) & (centre[:, 0] < w + 20) & (centre[:, 1] > first_row) \
                & (centre[:, 1] < h + 20)
            if kind.in_glint and glint is not None:
                x0, y0, x1, y1 = glint[1]
                inside &= (centre[:, 0] >= x0) & (centre[:, 0] < x1) & (centre[:, 1] >= y0) & (centre[:, 1] < y1)
            idx = np.flatnonzero(inside)
            if not len(idx):
                continue
            ring = (rel[idx, None, :] + ev[idx, None, 4:5] * _CIRCLE[None]).reshape(-1, 2)
            uv, ok_r = project_enu(np.column_stack([ring, np.zeros(len(ring))]), camera, pose)
            uv = uv.reshape(len(idx), _N_OUTLINE, 2)
            ok_all = np.asarray(np.asarray(ok_r).reshape(len(idx), _N_OUTLINE).all(axis=1))
            colour = np.array(kind.bgr, np.float32)
            for j, e in enumerate(idx):
                if not ok_all[j]:
                    continue
                opacity = float(ev[e, 5])
                if kind.in_glint and glint is not None:
                    weights, (gx0, gy0, _, _) = glint
                    cu, cv_ = int(centre[e, 0]) - gx0, int(centre[e, 1]) - gy0
                    opacity *= min(1.0, 3.0 * float(weights[min(max(cv_, 0), weights.shape[0] - 1),
                                                            min(max(cu, 0), weights.shape[1] - 1)]))
                if opacity < 0.03:
                    continue
                drawn += _blend_disc(image, uv[j], colour, opacity, first_row)
        return drawn


def _blend_disc(image: np.ndarray, poly: np.ndarray, colour: np.ndarray, opacity: float, first_row: int) -> int:
    """Alpha-blend a filled polygon (at least one pixel) of `colour` into image; returns 1 if drawn."""
    h, w = image.shape[:2]
    span = poly.max(axis=0) - poly.min(axis=0)
    sigma = 0.25 * float(span.min())  # foam fades out towards its edge
    pad = int(math.ceil(2.5 * sigma)) + 1 if sigma >= 0.7 else 1
    x0 = max(int(math.floor(poly[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(poly[:, 1].min())) - pad, first_row, 0)
    x1 = min(int(math.ceil(poly[:, 0].max())) + pad + 1, w)
    y1 = min(int(math.ceil(poly[:, 1].max())) + pad + 1, h)
    if x1 <= x0 or y1 <= y0:
        return 0
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    pts = np.round((poly - np.array([x0, y0])) * (1 << _SHIFT)).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_AA, _SHIFT)
    if not mask.any():  # smaller than a pixel: light the pixel under its centre, by its area
        cx, cy = poly.mean(axis=0) - np.array([x0, y0])
        iy, ix = min(max(int(cy), 0), mask.shape[0] - 1), min(max(int(cx), 0), mask.shape[1] - 1)
        mask[iy, ix] = 255
        opacity *= 0.5
    a = mask.astype(np.float32) * (opacity / 255.0)
    if sigma >= 0.7:
        a = np.asarray(cv2.GaussianBlur(a, (0, 0), sigma), dtype=np.float32)
    roi = image[y0:y1, x0:x1].astype(np.float32)
    roi += a[..., None] * (colour[None, None, :] - roi)
    image[y0:y1, x0:x1] = np.clip(roi, 0, 255).astype(np.uint8)
    return 1

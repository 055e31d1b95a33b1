"""Light and camera effects: sky, haze with range, sun glint on water, motion blur, exposure and colour drift, noise.

Per-pixel quantities that vary slowly over the image (haze, glint strength) are computed on a coarse grid
and resized with OpenCV; whole-frame operations are single OpenCV calls (blur, LUT, addWeighted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from shared.geo import Camera, Pose
from sim.render.geometry import pixel_rays_grid, slant_range_grid, sun_vector

#: Grid step (pixels) of the coarse haze and glint maps.
COARSE_STEP_PX = 16


@dataclass(frozen=True, slots=True)
class Atmosphere:
    """Light of one world.

    Attributes
    ----------
    zenith_bgr, horizon_bgr : tuple of 3 float
        Sky colours at the zenith and at the horizon (also the haze colour).
    visibility_m : float
        Meteorological visibility: haze opacity 1 - exp(-3.912 * range / visibility).
    sun_azimuth_deg, sun_elevation_deg : float
    shadow_darkness : float
        Share of the light a shadow removes (0..1).
    glint_strength : float
        Peak sun glint added on water (0..255 per unit glint potential).
    glint_width_deg : float
        Angular spread of the glint around the mirror direction (wave slopes).
    """

    zenith_bgr: tuple[float, float, float]
    horizon_bgr: tuple[float, float, float]
    visibility_m: float
    sun_azimuth_deg: float
    sun_elevation_deg: float
    shadow_darkness: float
    glint_strength: float
    glint_width_deg: float


def make_atmosphere(kind: str, sun_azimuth_deg: float, sun_elevation_deg: float,
                    rng: np.random.Generator) -> Atmosphere:
    """A clear-to-hazy summer day (visibility 4-15 km) with the given sun; shadows fade as the sun sinks."""
    zenith = (float(rng.uniform(190, 215)), float(rng.uniform(135, 160)), float(rng.uniform(80, 105)))
    horizon = (float(rng.uniform(225, 240)), float(rng.uniform(215, 228)), float(rng.uniform(200, 215)))
    darkness = 0.55 * min(max(sun_elevation_deg / 25.0, 0.0), 1.0)
    return Atmosphere(zenith, horizon, float(rng.uniform(4000.0, 15000.0)), sun_azimuth_deg, sun_elevation_deg,
                      darkness, 230.0 if kind == "sea" else 0.0, float(rng.uniform(9.0, 14.0)))


def ray_elevations_deg(camera: Camera, pose: Pose, rows: np.ndarray) -> np.ndarray:
    """(R,) elevation (deg above the horizontal) of the ray through each row's centre at column cx."""
    up = pixel_rays_grid(camera, pose, np.array([camera.cx]), np.asarray(rows, np.float64) + 0.5)[:, 0, 2]
    return np.degrees(np.arcsin(np.clip(up, -1.0, 1.0)))


def fill_sky(frame: np.ndarray, first_ground_row: int, camera: Camera, pose: Pose, atm: Atmosphere) -> None:
    """Paint rows above `first_ground_row` with the sky gradient (horizon haze to zenith blue), in place."""
    if first_ground_row <= 0:
        return
    elev = np.maximum(ray_elevations_deg(camera, pose, np.arange(first_ground_row)), 0.0)
    t = np.clip(elev / 30.0, 0.0, 1.0) ** 0.6
    horizon, zenith = np.asarray(atm.horizon_bgr)[None, :], np.asarray(atm.zenith_bgr)[None, :]
    colours = horizon * (1.0 - t[:, None]) + zenith * t[:, None]
    frame[:first_ground_row] = np.clip(colours, 0, 255).astype(np.uint8)[:, None, :]


def _coarse_axes(camera: Camera, first_row: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    us = np.arange(0, camera.width + step, step, dtype=np.float64)
    vs = np.arange(first_row, camera.height + step, step, dtype=np.float64)
    return us, vs


def haze_rows(camera: Camera, pose: Pose, atm: Atmosphere, first_ground_row: int, columns: int = 9) -> np.ndarray:
    """(H,) haze opacity of each image row: 1 - exp(-3.912 * slant range / visibility), 0 for sky rows.

    The range is the ground's along each row, averaged over `columns` columns (with roll 0 a row's range
    varies only by the lateral angle: up to ~20 % more at the image corners of a 70 deg lens). Objects take
    the haze of the ground behind them.
    """
    h = camera.height
    alpha = np.zeros(h, np.float64)
    if first_ground_row >= h:
        return alpha
    us = np.linspace(0.5, camera.width - 0.5, columns)
    rows = np.arange(first_ground_row, h, dtype=np.float64) + 0.5
    rng_m = slant_range_grid(camera, pose, us, rows)
    a = 1.0 - np.exp(-3.912 * rng_m / atm.visibility_m)
    alpha[first_ground_row:] = np.where(np.isfinite(a), a, 1.0).mean(axis=1)
    return alpha


def tone(frame: np.ndarray, haze_alpha: np.ndarray, haze_bgr: tuple[float, float, float],
         gains_bgr: np.ndarray, *, levels: int = 256) -> None:
    """Haze, exposure and white balance in one pass, in place: per band of rows one look-up table.

    Each pixel x becomes T(x (1 - a) + haze a) with a the row's haze opacity (`haze_rows`, quantised to
    1/`levels`, so rows with the same value share a band) and T the per-channel gain with a soft shoulder
    (`exposure_curve`). One `cv2.LUT` per band: the cost of one pass over the frame.
    """
    q = np.round(np.asarray(haze_alpha) * levels).astype(np.int64)
    cuts = np.flatnonzero(np.diff(q)) + 1
    starts, ends = np.r_[0, cuts], np.r_[cuts, len(q)]
    a = q[starts].astype(np.float64) / levels  # (B,)
    x = np.arange(256, dtype=np.float64)
    mixed = x[None, :, None] * (1.0 - a[:, None, None]) + np.asarray(haze_bgr)[None, None, :] * a[:, None, None]
    luts = exposure_curve(mixed / 255.0 * np.asarray(gains_bgr)[None, None, :])  # (B, 256, 3) uint8
    for b, (r0, r1) in enumerate(zip(starts, ends, strict=True)):
        band = frame[r0:r1]
        cv2.LUT(band, luts[b].reshape(1, 256, 3), dst=band)


def exposure_curve(y: np.ndarray) -> np.ndarray:
    """Linear light (1 = white) to uint8 with a soft shoulder above 0.85 instead of hard clipping."""
    knee = 0.85
    out = np.array(y, dtype=np.float64)
    over = out > knee
    out[over] = knee + (1.0 - knee) * (1.0 - np.exp(-(out[over] - knee) / (1.0 - knee)))
    return np.clip(np.round(255.0 * out), 0, 255).astype(np.uint8)


def glint_map(camera: Camera, pose: Pose, atm: Atmosphere, first_ground_row: int,
              step: int = COARSE_STEP_PX) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
    """Strength of the sun's mirror image on the water per pixel, (rows, cols) float32 over a rectangle.

    The weight is exp(-angle^2 / (2 width^2)) between the sun and the view ray reflected by a flat surface.
    Returns (weights, (x0, y0, x1, y1)) for the rectangle where it exceeds 1 %, or None.
    """
    if atm.glint_strength <= 0.0 or atm.sun_elevation_deg <= 0.0 or first_ground_row >= camera.height:
        return None
    us, vs = _coarse_axes(camera, first_ground_row, step)
    rays = pixel_rays_grid(camera, pose, us, vs)
    mirrored = rays * np.array([1.0, 1.0, -1.0])
    cos_a = np.clip(mirrored @ sun_vector(atm.sun_azimuth_deg, atm.sun_elevation_deg), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos_a))
    weight = np.exp(-0.5 * (angle / atm.glint_width_deg) ** 2) * (rays[..., 2] < 0)
    rows, cols = np.nonzero(weight > 0.01)
    if not len(rows):
        return None
    r0, r1 = rows.min(), rows.max() + 1
    c0, c1 = cols.min(), cols.max() + 1
    sub = weight[r0:r1 + 1, c0:c1 + 1].astype(np.float32)
    x0, y0 = int(c0 * step), first_ground_row + int(r0 * step)
    x1, y1 = min(int(c1 * step), camera.width), min(first_ground_row + int(r1 * step), camera.height)
    if x1 <= x0 or y1 <= y0:
        return None
    full = cv2.resize(sub, ((sub.shape[1] - 1) * step + 1, (sub.shape[0] - 1) * step + 1),
                      interpolation=cv2.INTER_LINEAR)[: y1 - y0, : x1 - x0]
    return full, (x0, y0, x1, y1)


#: Share of the glint strength spread evenly over the glint patch (the glitter's haze between facets).
GLINT_SHEEN = 0.25


def add_glint(frame: np.ndarray, potential: np.ndarray, weights: np.ndarray, rect: tuple[int, int, int, int],
              strength: float) -> None:
    """frame[rect] += strength * weights * (potential / 255 + GLINT_SHEEN) on every channel (saturating).

    potential: the warped texture's A channel (wave facets that mirror the sun), (H, W) uint8 aligned with
    frame; in place.
    """
    x0, y0, x1, y1 = rect
    add = (weights * (strength / 255.0)) * (potential[y0:y1, x0:x1].astype(np.float32) + 255.0 * GLINT_SHEEN)
    add8 = np.clip(add, 0, 255).astype(np.uint8)
    roi = frame[y0:y1, x0:x1]
    roi[:] = cv2.add(roi, cv2.merge([add8, add8, add8]))


def motion_blur(frame: np.ndarray, length_px: float, angle_deg: float) -> np.ndarray:
    """The frame smeared along a line of `length_px` at `angle_deg` (0 = along the rows, 90 = down the columns;
    image coordinates, so 45 runs down and to the right).

    Axis-aligned smears are one box filter. Other directions rotate the frame onto the rows (on a canvas that
    holds all of it), box-filter, and rotate back: three cheap passes instead of a large 2-D kernel, which
    OpenCV would filter through a DFT (~100 ms at 1080p).
    """
    n = int(round(length_px))
    if n < 2:
        return frame
    a = math.radians(angle_deg) % math.pi
    if min(a, math.pi - a) < math.radians(3.0):
        return cv2.blur(frame, (n, 1))
    if abs(a - math.pi / 2.0) < math.radians(3.0):
        return cv2.blur(frame, (1, n))
    h, w = frame.shape[:2]
    c, s = abs(math.cos(a)), abs(math.sin(a))
    cw, ch = int(math.ceil(w * c + h * s)) + 2 * n, int(math.ceil(w * s + h * c)) + 2 * n
    # getRotationMatrix2D turns the picture by +angle anticlockwise on screen, taking direction `a` onto the rows
    m = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), math.degrees(a), 1.0)
    m[0, 2] += (cw - w) / 2.0
    m[1, 2] += (ch - h) / 2.0
    turned = cv2.warpAffine(frame, m, (cw, ch), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    turned = cv2.blur(turned, (n, 1))
    return cv2.warpAffine(turned, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


class ExposureDrift:
    """Slow exposure and white-balance drift of one video, and the camera's reaction to the sky.

    Log gain: AR(1) with std `gain_std` and correlation time `gain_corr_s`; per-channel white balance: AR(1)
    with std `wb_std` over `wb_corr_s`; both drawn at knots every `KNOT_S` seconds and interpolated linearly
    to the frames (auto exposure and white balance move smoothly; they do not flicker frame to frame). Auto
    exposure darkens frames by up to 20 % as the bright sky fills them. Deterministic for the generator;
    `channel_gains` feeds `tone`.
    """

    KNOT_S = 0.5

    def __init__(self, n_frames: int, fps: float, rng: np.random.Generator, *, gain_std: float = 0.08,
                 gain_corr_s: float = 4.0, wb_std: float = 0.025, wb_corr_s: float = 10.0) -> None:
        knots = int(math.ceil(max(n_frames, 1) / fps / self.KNOT_S)) + 2
        t_knot = np.arange(knots) * self.KNOT_S
        t = np.arange(max(n_frames, 1)) / fps
        gain = _ar1(knots, 1.0 / self.KNOT_S, gain_corr_s, gain_std, 1, rng)
        wb = _ar1(knots, 1.0 / self.KNOT_S, wb_corr_s, wb_std, 3, rng)
        self.gain = np.interp(t, t_knot, gain[:, 0])
        self.wb = np.column_stack([np.interp(t, t_knot, wb[:, c]) for c in range(3)])
        self.n_frames = max(n_frames, 1)

    def channel_gains(self, frame_index: int, sky_fraction: float) -> np.ndarray:
        """(3,) B, G, R multipliers of a frame."""
        f = min(max(frame_index, 0), self.n_frames - 1)
        return np.exp(self.gain[f] + self.wb[f]) / (1.0 + 0.25 * min(max(sky_fraction, 0.0), 1.0))


def _ar1(n: int, fps: float, corr_s: float, std: float, dims: int, rng: np.random.Generator) -> np.ndarray:
    a = math.exp(-1.0 / (fps * corr_s))
    z = rng.standard_normal((max(n, 1), dims))
    out = np.empty_like(z)
    out[0] = z[0] * std
    b = math.sqrt(1.0 - a * a) * std
    for i in range(1, len(z)):
        out[i] = a * out[i - 1] + b * z[i]
    return out


class SensorNoise:
    """Zero-mean sensor noise added to every frame: one random tile, sliced at a random offset per frame."""

    MARGIN = 64

    def __init__(self, width: int, height: int, std: float, rng: np.random.Generator) -> None:
        self.std = float(std)
        tile = rng.normal(16.0, std, (height + self.MARGIN, width + self.MARGIN, 3))
        self.tile = np.clip(np.round(tile), 0, 255).astype(np.uint8)

    def apply(self, frame: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """frame + noise (saturating); the offset comes from rng."""
        if self.std <= 0:
            return frame
        h, w = frame.shape[:2]
        dy, dx = (int(v) for v in rng.integers(0, self.MARGIN, 2))
        return cv2.addWeighted(frame, 1.0, self.tile[dy:dy + h, dx:dx + w], 1.0, -16.0)

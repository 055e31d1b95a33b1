"""Procedural ground textures in world coordinates: sea with waves, meadow with soil and roads; baked tree shadows.

A `GroundTexture` is made once per world: a BGRA image of the ground around the flights at one resolution
(metres per texel) plus its mip levels. Colour is in B, G, R; A holds the sun-glint potential of water
(sparse wave facets, 0 on land). A detailed sea also has a `facets` channel: the short waves' tilt that turns
those facets towards the sun or away (mean 1), which the renderer moves at another speed than the long waves
(`sim.render.renderer`), so the glint twinkles. Features are sized in metres, so a texture looks the same at
any resolution. Deterministic for a generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

#: Mip levels kept (each half the resolution of the one before).
MIP_LEVELS = 6
#: The facets channel stores the glint factor times this (factor 0..2.55 in uint8).
FACET_SCALE = 100.0
#: Feature sizes (metres) of the short waves' facets (capillary and short gravity waves).
FACET_SCALES_M = (0.8, 0.4)


@dataclass(frozen=True, slots=True)
class Road:
    """A road as a polyline in world east/north metres, its width and surface ("asphalt" or "dirt")."""

    points_en: tuple[tuple[float, float], ...]
    width_m: float
    surface: str


@dataclass(frozen=True, slots=True)
class GroundTexture:
    """The ground of one world.

    Attributes
    ----------
    levels : tuple of (H, W, 4) uint8
        BGRA mip levels; level 0 has `res_m` metres per texel, level k has res_m * 2**k.
    res_m : float
        Metres per texel of level 0.
    east0_m, north0_m : float
        World east/north of the centre of level 0's texel (0, 0) (the north-west corner; rows go south).
    kind : str
        "sea" or "meadow".
    roads : tuple of Road
    facets : tuple of (H, W) uint8
        Detailed sea only (else empty): per mip level, the short waves' glint factor times `FACET_SCALE`
        (mean ~1: multiplies A where the renderer draws the glint).
    wind_deg : float or None
        Sea only: the direction the waves travel towards, degrees clockwise from north.
    """

    levels: tuple[np.ndarray, ...]
    res_m: float
    east0_m: float
    north0_m: float
    kind: str
    roads: tuple[Road, ...] = ()
    facets: tuple[np.ndarray, ...] = ()
    wind_deg: float | None = None

    def texel_to_world(self, level: int = 0) -> NDArray[np.float64]:
        """(3, 3) affine from a texel index (column, row) of `level` to world east/north metres.

        cv2.pyrDown puts output texel i over input texel 2 i, so level k's texel i is level 0's texel 2**k i.
        """
        s = self.res_m * 2.0 ** level
        return np.array([[s, 0.0, self.east0_m], [0.0, -s, self.north0_m], [0.0, 0.0, 1.0]])

    def world_to_texel(self, east_m: NDArray, north_m: NDArray) -> tuple[NDArray, NDArray]:
        """World east/north metres -> level-0 texel (column, row) coordinates (float)."""
        return (np.asarray(east_m) - self.east0_m) / self.res_m, (self.north0_m - np.asarray(north_m)) / self.res_m

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(east_min, north_min, east_max, north_max) covered by level 0, metres."""
        h, w = self.levels[0].shape[:2]
        return (self.east0_m, self.north0_m - (h - 1) * self.res_m, self.east0_m + (w - 1) * self.res_m,
                self.north0_m)


# --------------------------------------------------------------------------------------------- noise

#: Side of the random lattice tables: a noise octave of scale s repeats every NOISE_PERIOD * s metres.
NOISE_PERIOD = 512


class NoiseBank:
    """Random lattice tables, one per named noise field, drawn once per world from `rng`.

    Noise sampled through `world_noise` is anchored to world coordinates: two textures of one world at any
    extent and resolution show the same patterns (the near and the far ground join without a seam). A table
    depends only on the bank's seed and its name, so threads may share a bank (a race draws the same table).
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self._seed = int(rng.integers(0, 2**62))
        self._tables: dict[str, np.ndarray] = {}

    def table(self, name: str) -> np.ndarray:
        """(NOISE_PERIOD, NOISE_PERIOD) float32 standard normal values for the field `name`."""
        if name not in self._tables:
            rng = np.random.default_rng([self._seed, *name.encode()])
            self._tables[name] = rng.standard_normal((NOISE_PERIOD, NOISE_PERIOD)).astype(np.float32)
        return self._tables[name]


@dataclass(frozen=True, slots=True)
class TexelGrid:
    """The texels of a texture: shape (rows, columns), metres per texel, world east/north of texel (0, 0)."""

    shape: tuple[int, int]
    res_m: float
    east0_m: float
    north0_m: float


def world_noise(grid: TexelGrid, scale_m: float, table: np.ndarray) -> np.ndarray:
    """(H, W) float32 smooth noise with features of `scale_m` metres at the texels of `grid`, std ~0.5.

    Lattice values at world multiples of `scale_m` (from `table`, repeating every NOISE_PERIOD cells) are
    interpolated bicubically by one cv2.warpAffine from texel to lattice coordinates. Zero for octaves finer
    than a texel (they would only alias).
    """
    h, w = grid.shape
    if scale_m < grid.res_m:
        return np.zeros((h, w), np.float32)
    k = grid.res_m / scale_m
    gx0 = grid.east0_m / scale_m  # lattice x grows east, lattice y grows south (like texel rows)
    gy0 = -grid.north0_m / scale_m
    i0, j0 = int(math.floor(gx0)) - 2, int(math.floor(gy0)) - 2
    gw, gh = int(math.ceil(w * k)) + 5, int(math.ceil(h * k)) + 5
    period = table.shape[0]
    cells = table[np.ix_((j0 + np.arange(gh)) % period, (i0 + np.arange(gw)) % period)]
    to_lattice = np.array([[k, 0.0, gx0 - i0], [0.0, k, gy0 - j0]])
    out = cv2.warpAffine(cells, to_lattice, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REFLECT)
    return out * np.float32(0.5)


def fractal_noise(grid: TexelGrid, scales_m: tuple[float, ...], bank: NoiseBank, name: str,
                  weights: tuple[float, ...] | None = None) -> np.ndarray:
    """(H, W) float32 weighted sum of `world_noise` octaves (weights default to sqrt(scale)), std ~0.5
    when every octave is resolved; octaves finer than a texel drop out (as a mip level averages them)."""
    ws = weights if weights is not None else tuple(math.sqrt(s) for s in scales_m)
    total = np.zeros(grid.shape, np.float32)
    for i, (s, wgt) in enumerate(zip(scales_m, ws, strict=True)):
        if s >= grid.res_m:
            total += np.float32(wgt) * world_noise(grid, s, bank.table(f"{name}/{i}"))
    return total / np.float32(math.sqrt(sum(w * w for w in ws)))


def _channels(base: np.ndarray, terms: list[tuple[np.ndarray, np.ndarray]],
              gain: np.ndarray | None) -> list[np.ndarray]:
    """Per channel c: (base[c] + sum(colour[c] * field)) * gain, as three (H, W) float32 planes (one plane at
    a time, in place: a texture has tens of millions of texels). `terms` must not be empty."""
    planes = []
    for c in range(3):
        plane = np.full(terms[0][1].shape, np.float32(base[c]), np.float32)
        for colour, field in terms:
            plane += np.float32(colour[c]) * field
        if gain is not None:
            plane *= gain
        planes.append(plane)
    return planes


def _blend_where(planes: list[np.ndarray], colour: np.ndarray, weight: np.ndarray,
                 colour_gain: np.ndarray | None = None) -> None:
    """planes += (colour * colour_gain - planes) * weight, only at texels with weight > 0 (in place)."""
    idx = np.flatnonzero(weight.ravel() > 0)
    if not len(idx):
        return
    wgt = weight.ravel()[idx]
    g = colour_gain.ravel()[idx] if colour_gain is not None else np.float32(1.0)
    for c, plane in enumerate(planes):
        flat = plane.reshape(-1)
        flat[idx] += (np.float32(colour[c]) * g - flat[idx]) * wgt


def _to_bgra(planes: list[np.ndarray], alpha: np.ndarray | None = None) -> np.ndarray:
    h, w = planes[0].shape
    out = np.zeros((h, w, 4), np.uint8)
    for c, plane in enumerate(planes):
        np.clip(plane, 0, 255, out=plane)
        out[..., c] = plane
    if alpha is not None:
        out[..., 3] = alpha
    return out


# --------------------------------------------------------------------------------------------- sea

def _wave_tile(tile: int, res_m: float, wind_deg: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A periodic (tile, tile) patch of wave height and of its slope towards the wind, both std ~1.

    Sinusoids with wave numbers on the tile's lattice (so the patch repeats seamlessly), wavelengths 0.35-6 m
    within +-25 deg (1 sigma) of the wind, amplitude ~ wavelength^0.8 (a short-crested wind sea).
    """
    y, x = np.mgrid[0:tile, 0:tile].astype(np.float32)
    height = np.zeros((tile, tile), np.float32)
    slope = np.zeros((tile, tile), np.float32)
    period_m = tile * res_m
    for _ in range(24):
        lam = float(np.exp(rng.uniform(math.log(max(0.35, 2.5 * res_m)), math.log(6.0))))
        direction = math.radians(wind_deg + rng.normal(0.0, 25.0))
        cycles = period_m / lam
        m = int(round(cycles * math.sin(direction)))
        n = int(round(cycles * math.cos(direction)))
        if m == 0 and n == 0:
            continue
        amp = lam ** 0.8
        phase = rng.uniform(0.0, 2.0 * math.pi)
        arg = (2.0 * math.pi / tile) * (m * x - n * y) + phase  # rows go south
        height += np.float32(amp) * np.sin(arg)
        slope += np.float32(amp * 2.0 * math.pi / lam) * np.cos(arg)
    height /= max(float(height.std()), 1e-6)
    slope /= max(float(slope.std()), 1e-6)
    return height, slope


def _sea(grid: TexelGrid, bank: NoiseBank, rng: np.random.Generator, detail: bool,
         wind_deg: float | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """(BGRA level 0, facets level 0 or None, wind direction deg)."""
    h, w = grid.shape
    deep = np.array([92.0, 78.0, 34.0], np.float32)  # BGR: Lake Constance teal
    shallow = np.array([112.0, 104.0, 60.0], np.float32)
    tint = np.clip(0.5 + fractal_noise(grid, (90.0, 30.0), bank, "sea/tint"), 0.0, 1.0)
    if wind_deg is None:
        wind_deg = float(rng.uniform(0.0, 360.0))
    if not (detail and grid.res_m < 1.0):
        return _to_bgra(_channels(deep, [(shallow - deep, tint)], None)), None, wind_deg
    tile = int(min(512, max(64, 2 ** round(math.log2(max(8.0 / grid.res_m, 64))))))
    wave_h, wave_s = _wave_tile(tile, grid.res_m, wind_deg, rng)
    reps = (h // tile + 1, w // tile + 1)
    groups = 1.0 + 0.45 * fractal_noise(grid, (30.0, 9.0), bank, "sea/groups")  # breaks the repetition
    fine = fractal_noise(grid, (1.2, 0.4), bank, "sea/fine")
    height = np.tile(wave_h, reps)[:h, :w] * groups + 0.35 * fine
    slope = np.tile(wave_s, reps)[:h, :w] * groups + 0.5 * fine
    del groups
    planes = _channels(deep, [(shallow - deep, tint)], 1.0 + 0.10 * height + 0.12 * slope)
    crest = np.clip((height - 2.6) * 1.6, 0.0, 1.0) * np.clip(0.5 + fine, 0.0, 1.0)
    _blend_where(planes, np.array([225.0, 228.0, 225.0], np.float32), 0.7 * crest)  # whitecaps
    glint = np.clip((slope - 0.6) / 1.6, 0.0, 1.0) ** 2 * np.clip(0.6 + fine, 0.0, 1.5)
    del fine, height, slope
    facet = fractal_noise(grid, FACET_SCALES_M, bank, "sea/facets")  # std ~0.5 where resolved
    facets = np.clip(FACET_SCALE * (1.0 + 1.6 * facet), 0, 255).astype(np.uint8)
    return _to_bgra(planes, np.clip(255.0 * glint, 0, 255).astype(np.uint8)), facets, wind_deg


# --------------------------------------------------------------------------------------------- meadow

def _meadow(grid: TexelGrid, bank: NoiseBank, rng: np.random.Generator, detail: bool) -> np.ndarray:
    h, w = grid.shape
    base = np.array([52.0, 128.0, 84.0], np.float32)  # BGR meadow green
    dry = np.array([62.0, 148.0, 138.0], np.float32)
    lush = np.array([40.0, 98.0, 52.0], np.float32)
    patches = fractal_noise(grid, (40.0, 14.0, 5.0), bank, "meadow/patches")
    blades = fractal_noise(grid, (0.6, 0.25, 0.1), bank, "meadow/blades", weights=(0.6, 0.8, 1.0))
    planes = _channels(base, [(dry - base, np.clip(patches, 0.0, 1.0)), (lush - base, np.clip(-patches, 0.0, 1.0))],
                       1.0 + 0.22 * blades)
    del patches
    soil_field = fractal_noise(grid, (18.0, 6.0, 1.5), bank, "meadow/soil", weights=(1.0, 0.6, 0.3))
    soil_t = np.clip((soil_field - 0.7) * 4.0, 0.0, 1.0)
    _blend_where(planes, np.array([70.0, 98.0, 122.0], np.float32), 0.85 * soil_t, 1.0 + 0.25 * blades)
    if detail and grid.res_m <= 0.1:  # sparse white and yellow flowers, a few centimetres each: 0.2 % of texels
        flowers = rng.integers(0, h * w, int(rng.poisson(0.002 * h * w)))
        yellow = rng.uniform(size=len(flowers)) < 0.5
        for c, (y_c, w_c) in enumerate(((60.0, 225.0), (210.0, 230.0), (230.0, 230.0))):
            planes[c].reshape(-1)[flowers] = np.where(yellow, y_c, w_c)
    return _to_bgra(planes)


def meadow_roads(extent_m: tuple[float, float, float, float], rng: np.random.Generator) -> tuple[Road, ...]:
    """A gently curved asphalt road and a dirt track across the scene, clear of its centre.

    The road passes 30-60 m from the world origin, the track 12-30 m on the other side; both run straight
    across `extent_m` (give the largest texture's) with a slow sideways wander (metres).
    """
    e0, n0, e1, n1 = extent_m
    half = 0.75 * math.hypot(e1 - e0, n1 - n0)
    roads = []
    for offset_range, width, surface in (((30.0, 60.0), 6.0, "asphalt"), ((12.0, 30.0), 3.0, "dirt")):
        heading = math.radians(rng.uniform(0.0, 180.0))
        along = np.array([math.sin(heading), math.cos(heading)])
        across = np.array([along[1], -along[0]])
        side = 1.0 if surface == "asphalt" else -1.0
        offset = side * rng.uniform(*offset_range)
        s = np.linspace(-half, half, 256)
        wander = 4.0 * np.sin(s / rng.uniform(40.0, 80.0) + rng.uniform(0.0, 2.0 * math.pi))
        pts = (offset + wander)[:, None] * across[None, :] + s[:, None] * along[None, :]
        roads.append(Road(tuple((float(a), float(b)) for a, b in pts), width, surface))
    return tuple(roads)


def _stroke(tex: GroundTexture, shape: tuple[int, int], points_en: np.ndarray, width_m: float) -> np.ndarray:
    """(H, W) float32 coverage 0..1 of a polyline `width_m` wide; strokes thinner than a texel are drawn one
    texel wide with their share of it (a 0.15 m line on a 1 m texel darkens 15 %, it is not 1 m wide)."""
    col, row = tex.world_to_texel(points_en[:, 0], points_en[:, 1])
    poly = np.round(np.column_stack([col, row]) * 16).astype(np.int32).reshape(-1, 1, 2)
    width_px = width_m / tex.res_m
    mask = np.zeros(shape, np.uint8)
    cv2.polylines(mask, [poly], False, 255, max(1, int(round(width_px))), cv2.LINE_AA, shift=4)
    return mask.astype(np.float32) * np.float32(min(1.0, width_px) / 255.0)


def _paint(img: np.ndarray, colour: np.ndarray, coverage: np.ndarray, gain: np.ndarray | None = None) -> None:
    """img[..., :3] += (colour * gain - img) * coverage where coverage > 0 (in place)."""
    idx = np.flatnonzero(coverage.ravel() > 0)
    if not len(idx):
        return
    flat = img.reshape(-1, img.shape[2])
    cur = flat[idx, :3].astype(np.float32)
    g = gain.ravel()[idx, None] if gain is not None else np.float32(1.0)
    cur += (colour[None, :] * g - cur) * coverage.ravel()[idx, None]
    flat[idx, :3] = np.clip(cur, 0, 255).astype(np.uint8)


def _draw_roads(img: np.ndarray, tex: GroundTexture, roads: tuple[Road, ...], bank: NoiseBank) -> None:
    """Asphalt with white edge lines, dirt tracks with a grass strip between the ruts; in place."""
    h, w = img.shape[:2]
    grain = fractal_noise(TexelGrid((h, w), tex.res_m, tex.east0_m, tex.north0_m), (2.0, 0.3), bank, "road/grain")
    for road in roads:
        pts = np.array(road.points_en)
        if road.surface == "asphalt":
            _paint(img, np.array([84.0, 86.0, 90.0], np.float32), _stroke(tex, (h, w), pts, road.width_m),
                   1.0 + 0.12 * grain)
            for edge in (-1.0, 1.0):  # white edge lines 0.15 m wide, 0.3 m inside the edges
                line = _offset_polyline(pts, edge * (road.width_m / 2.0 - 0.3))
                _paint(img, np.array([215.0, 218.0, 220.0], np.float32), _stroke(tex, (h, w), line, 0.15))
        else:
            _paint(img, np.array([118.0, 146.0, 165.0], np.float32), _stroke(tex, (h, w), pts, road.width_m),
                   1.0 + 0.2 * grain)
            _paint(img, np.array([55.0, 120.0, 90.0], np.float32), 0.6 * _stroke(tex, (h, w), pts, 0.5),
                   1.0 + 0.2 * grain)


def _offset_polyline(pts: np.ndarray, offset_m: float) -> np.ndarray:
    """(N, 2) polyline moved sideways by offset_m (to the right of its direction)."""
    d = np.gradient(pts, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    right = np.column_stack([d[:, 1], -d[:, 0]])
    return pts + offset_m * right


# --------------------------------------------------------------------------------------------- shadows

def bake_shadows(tex: GroundTexture, footprints_en: list[np.ndarray], heights_m: list[float],
                 sun_azimuth_deg: float, sun_elevation_deg: float, darkness: float = 0.5) -> None:
    """Darken level 0 where static objects (trees) shade the ground; in place, before `with_mips`.

    footprints_en: per object an (P, 2) world east/north outline on the ground; heights_m: their heights.
    The shadow is the convex hull of the outline and the outline moved away from the sun by
    height / tan(elevation), softened by a 0.3 m blur.
    """
    if sun_elevation_deg <= 1.0 or not footprints_en:
        return
    img = tex.levels[0]
    h, w = img.shape[:2]
    length = 1.0 / math.tan(math.radians(sun_elevation_deg))
    away = -np.array([math.sin(math.radians(sun_azimuth_deg)), math.cos(math.radians(sun_azimuth_deg))])
    mask = np.zeros((h, w), np.uint8)
    for outline, height in zip(footprints_en, heights_m, strict=True):
        pts = np.vstack([outline, outline + away * height * length])
        col, row = tex.world_to_texel(pts[:, 0], pts[:, 1])
        hull = cv2.convexHull(np.round(np.column_stack([col, row]) * 16).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 255, cv2.LINE_AA, shift=4)
    sigma = max(0.3 / tex.res_m, 0.5)
    soft = cv2.GaussianBlur(mask, (0, 0), sigma)
    idx = np.flatnonzero(soft.ravel())
    flat = img.reshape(-1, 4)
    factor = 1.0 - darkness * soft.ravel()[idx, None].astype(np.float32) / 255.0
    flat[idx, :3] = np.clip(flat[idx, :3] * factor, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------- entry

def make_ground(kind: str, extent_m: tuple[float, float, float, float], res_m: float, bank: NoiseBank,
                rng: np.random.Generator, *, roads: tuple[Road, ...] = (), detail: bool = True,
                wind_deg: float | None = None) -> GroundTexture:
    """Level 0 of the ground over `extent_m` = (east_min, north_min, east_max, north_max) at `res_m` metres per
    texel (call `with_mips` after any baking).

    kind "sea": water with colour drift and (with `detail`) a short-crested wind sea, whitecaps and glint
    potential in A. "meadow": grass with dry and lush patches, soil, (with `detail`) flowers, and the roads.
    Patterns come from `bank` (world-anchored: textures of one world agree where they overlap); `rng` draws
    what is only in detailed textures (flowers, the waves) and the sea's wind direction unless `wind_deg`
    (degrees clockwise from north, where the waves travel) is given.
    """
    if kind not in ("sea", "meadow"):
        raise ValueError(f"unknown ground kind {kind!r}; valid: meadow, sea")
    if not (math.isfinite(res_m) and res_m > 0):
        raise ValueError(f"ground resolution must be > 0 metres per texel, got {res_m!r}")
    e0, n0, e1, n1 = extent_m
    w = int(math.ceil((e1 - e0) / res_m)) + 1
    h = int(math.ceil((n1 - n0) / res_m)) + 1
    if w < 2 or h < 2:
        raise ValueError(f"ground extent {extent_m} is empty at {res_m} m per texel")
    grid = TexelGrid((h, w), res_m, e0, n1)
    facets: tuple[np.ndarray, ...] = ()
    wind: float | None = None
    if kind == "sea":
        img, facet0, wind = _sea(grid, bank, rng, detail, wind_deg)
        facets = (facet0,) if facet0 is not None else ()
    else:
        img = _meadow(grid, bank, rng, detail)
    tex = GroundTexture((img,), res_m, e0, n1, kind, roads, facets, wind)
    if roads:
        _draw_roads(img, tex, roads, bank)
    return tex


def with_mips(tex: GroundTexture, levels: int = MIP_LEVELS) -> GroundTexture:
    """The texture with its mip levels (cv2.pyrDown of level 0, up to `levels` levels, at least 8 texels);
    the facets channel gets the same levels."""
    mips = [tex.levels[0]]
    while len(mips) < levels and min(mips[-1].shape[:2]) >= 16:
        mips.append(cv2.pyrDown(mips[-1]))
    facets = list(tex.facets[:1])
    while facets and len(facets) < len(mips):
        facets.append(cv2.pyrDown(facets[-1]))
    return GroundTexture(tuple(mips), tex.res_m, tex.east0_m, tex.north0_m, tex.kind, tex.roads, tuple(facets),
                         tex.wind_deg)

"""Objects as textured sprites of their metric size: people, swimmers, buoys, rocks, trees, boats, cars.

Each object is a stack of vertical prisms (`Part`: a ground outline in the object's own frame, a bottom and a
top height, a colour). A prism's image is the convex hull of its projected bottom and top outlines (exact for
convex prisms); its top face is drawn lighter (lit from above). Shadows are the prisms' outlines cast on the
ground away from the sun. Colours and a fine texture are fixed per object (`appearance_rng`), so an object
looks the same in every frame and to every UAV: re-identification from pixels has something to use.

Sizes follow `sim.world.CLASS_BOX_M`: a person fills 0.5 x 0.3 x 1.7 m, a swimmer's head and shoulders
0.5 x 0.5 x 0.3 m (a faint submerged body and foam ring reach beyond it, as in real footage).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared.geo import Camera, Pose
from sim.render.geometry import project_enu

#: Sub-pixel bits of the polygon fills.
_SHIFT = 4
#: Parts thinner than this (metres) are drawn by their top face alone.
FLAT_M = 0.05

# Clothing and gear colours (BGR), drawn per object.
_SHIRTS = ((40, 40, 200), (170, 80, 30), (40, 200, 230), (60, 160, 60), (30, 120, 240), (140, 50, 120),
           (230, 230, 230), (35, 35, 35), (120, 120, 120), (170, 120, 240), (200, 180, 60), (100, 40, 20))
_TROUSERS = ((130, 80, 50), (40, 40, 40), (110, 160, 180), (100, 100, 100), (60, 60, 120))
_SKIN = ((120, 150, 200), (100, 130, 180), (70, 95, 140), (50, 70, 100))
_HAIR = ((30, 30, 30), (40, 60, 90), (80, 150, 200), (20, 40, 60))
_CAPS = ((0, 120, 255), (0, 220, 255), (30, 30, 220), (235, 235, 235), (200, 90, 20), (180, 100, 255), (40, 200, 40))
_SUITS = ((30, 30, 30), (90, 40, 20), (40, 40, 170), (0, 110, 240))
_BUOYS = ((0, 100, 250), (20, 30, 210), (0, 210, 250))
_HULLS = ((235, 235, 235), (150, 60, 20), (40, 40, 190), (210, 210, 200))
_CARS = ((225, 225, 225), (40, 40, 40), (150, 150, 150), (30, 30, 170), (140, 70, 20), (70, 110, 60))


@dataclass(frozen=True, slots=True)
class Part:
    """One vertical prism of an object.

    outline: (P, 2) convex ground outline in the object frame, metres (right, forward); z0_m, z1_m: bottom and
    top heights above the ground; side_bgr, top_bgr: colours of the walls and the top face (0..255);
    alpha: opacity (foam and submerged parts are partly transparent); casts_shadow: whether it shades the ground.
    """

    outline: np.ndarray
    z0_m: float
    z1_m: float
    side_bgr: tuple[float, float, float]
    top_bgr: tuple[float, float, float]
    alpha: float = 1.0
    casts_shadow: bool = True


@dataclass(frozen=True, slots=True)
class Model:
    """An object's shape and look: parts bottom to top, texture contrast, and a fine texture patch.

    radius_m and height_m (derived) bound the object: a vertical cylinder around its centre, for culling.
    """

    parts: tuple[Part, ...]
    texture: np.ndarray  # (h, w) float32 around 0, resized over the object's image
    texture_contrast: float
    radius_m: float = field(init=False)
    height_m: float = field(init=False)
    points: np.ndarray = field(init=False, repr=False)  # (M, 3) right, forward, z: each part at z0 then z1
    shadow_points: np.ndarray = field(init=False, repr=False)  # (S, 3) the casting parts, at z0 then z1

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError("a sprite Model needs at least one Part")
        put = object.__setattr__
        put(self, "radius_m", max(float(np.hypot(*p.outline.T).max()) for p in self.parts))
        put(self, "height_m", max(p.z1_m for p in self.parts))
        put(self, "points", np.vstack([_levels(p.outline, p.z0_m, p.z1_m) for p in self.parts]))
        casting = [_levels(p.outline, p.z0_m, p.z1_m) for p in self.parts if p.casts_shadow]
        put(self, "shadow_points", np.vstack(casting) if casting else np.zeros((0, 3)))


def _levels(outline: np.ndarray, z0: float, z1: float) -> np.ndarray:
    """(2P, 3) an outline at two heights."""
    p = len(outline)
    return np.column_stack([np.vstack([outline, outline]), np.r_[np.full(p, z0), np.full(p, z1)]])


@dataclass(frozen=True, slots=True)
class Placed:
    """A model at a world position: east/north metres (world frame), yaw (deg from north)."""

    model: Model
    east_m: float
    north_m: float
    yaw_deg: float
    border_only: bool = False  # draw only when cut by the image border (continued positions; scene.py)


def ellipse(width_m: float, depth_m: float, n: int = 12, forward_m: float = 0.0, power: float = 2.0) -> np.ndarray:
    """(n, 2) outline of an ellipse across (`width_m`) and along (`depth_m`) the object's heading.

    power > 2 gives a superellipse |x/a|^p + |y/b|^p = 1, squarer (shoulders, hips); it stays convex.
    """
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    e = 2.0 / power
    return np.column_stack([0.5 * width_m * np.sign(c) * np.abs(c) ** e,
                            forward_m + 0.5 * depth_m * np.sign(s) * np.abs(s) ** e])


def _shade(bgr: tuple[int, ...], k: float) -> tuple[float, float, float]:
    return (min(bgr[0] * k, 255.0), min(bgr[1] * k, 255.0), min(bgr[2] * k, 255.0))


#: The sea's mean colour (BGR, `sim.render.texture`), which water on a swimmer pulls colours towards.
_WATER = (100.0, 90.0, 45.0)


def _washed(bgr: tuple[float, float, float], k: float) -> tuple[int, int, int]:
    """A colour pulled a fraction k towards the water's (desaturated and darkened by a film of water)."""
    return (int(round(bgr[0] + k * (_WATER[0] - bgr[0]))), int(round(bgr[1] + k * (_WATER[1] - bgr[1]))),
            int(round(bgr[2] + k * (_WATER[2] - bgr[2]))))


def appearance_rng(seed: int, key: int, kind: str) -> np.random.Generator:
    """The generator of an object's look: the same for a (seed, key, kind) in every frame and video."""
    return np.random.default_rng([int(seed), int(key) & 0x7FFFFFFF, sum(kind.encode()) + 1009])


def _texture(rng: np.random.Generator, size: int = 24, blur: float = 1.0) -> np.ndarray:
    t = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), blur)
    return t / max(float(t.std()), 1e-6)


def _pick(rng: np.random.Generator, palette: tuple[tuple[int, int, int], ...]) -> tuple[int, int, int]:
    return palette[int(rng.integers(len(palette)))]


def person(rng: np.random.Generator) -> Model:
    """Legs, torso and head filling 0.5 x 0.3 x 1.7 m; shirt, trousers, skin and hair drawn from rng."""
    shirt, trousers, skin, hair = _pick(rng, _SHIRTS), _pick(rng, _TROUSERS), _pick(rng, _SKIN), _pick(rng, _HAIR)
    parts = (
        Part(ellipse(0.36, 0.22, 16, power=3.0), 0.0, 0.85, _shade(trousers, 0.8), _shade(trousers, 1.0)),
        Part(ellipse(0.50, 0.30, 16, power=4.0), 0.85, 1.48, _shade(shirt, 0.82), _shade(shirt, 1.05)),
        Part(ellipse(0.20, 0.23, 10), 1.48, 1.70, _shade(skin, 0.85), _shade(hair, 1.0)),
    )
    return Model(parts, _texture(rng), 0.12)


def swimmer(rng: np.random.Generator) -> Model:
    """Foam ring, faint submerged body, shoulders at the surface and a capped head (0.5 x 0.5 x 0.3 m)."""
    cap, suit, skin = _pick(rng, _CAPS), _pick(rng, _SUITS), _pick(rng, _SKIN)
    vest = rng.uniform() < 0.3
    shoulders = (0, 140, 250) if vest else suit
    # partly submerged: the water film and spray wash the colours towards the sea's, by a per-swimmer amount
    wash = float(rng.uniform(0.3, 0.75))
    cap, shoulders = _washed(cap, wash), _washed(shoulders, min(0.9, wash + 0.15))
    above = float(rng.uniform(0.45, 0.9))  # how much of the shoulders shows through the water
    parts = (
        Part(ellipse(0.95, 1.1, 14), 0.0, 0.02, (215, 220, 220), (225, 230, 230), alpha=0.25, casts_shadow=False),
        Part(ellipse(0.42, 1.1, 12, forward_m=-0.45), 0.0, 0.01, _shade(suit, 0.7), _shade(suit, 0.8), alpha=0.2,
             casts_shadow=False),
        Part(ellipse(0.5, 0.26), 0.0, 0.12, _shade(shoulders, 0.8), _shade(shoulders, 1.0), alpha=above,
             casts_shadow=False),
        Part(ellipse(0.2, 0.23, 10, forward_m=0.08), 0.05, 0.30, _shade(_washed(skin, wash), 0.85),
             _shade(cap, 1.0)),
    )
    return Model(parts, _texture(rng), 0.1)


def submerged(model: Model, k: float) -> Model:
    """A swimmer `model` with its body, shoulders and head a further share k (0..1) towards the water's colour
    and the shoulders k less opaque (rougher water: spray, a film of water, more of the body under the
    surface); the foam ring (the first part) is kept. k = 0 returns the model itself."""
    if k <= 0.0:
        return model
    parts = [model.parts[0]]
    for i, p in enumerate(model.parts[1:], start=1):
        alpha = p.alpha * (1.0 - k) if i == 2 else p.alpha
        parts.append(dataclasses.replace(p, side_bgr=_washed(p.side_bgr, k), top_bgr=_washed(p.top_bgr, k),
                                         alpha=alpha))
    return Model(tuple(parts), model.texture, model.texture_contrast)


def buoy(rng: np.random.Generator) -> Model:
    """A 0.45 m mooring buoy with a foam ring at the waterline."""
    colour = _pick(rng, _BUOYS)
    parts = (
        Part(ellipse(0.7, 0.7, 14), 0.0, 0.02, (215, 220, 220), (225, 230, 230), alpha=0.3, casts_shadow=False),
        Part(ellipse(0.45, 0.45, 14), 0.0, 0.32, _shade(colour, 0.75), _shade(colour, 1.0)),
        Part(ellipse(0.3, 0.3, 12), 0.32, 0.45, _shade(colour, 0.85), _shade(colour, 1.1)),
    )
    return Model(parts, _texture(rng), 0.08)


def rock(rng: np.random.Generator) -> Model:
    """A grey boulder 0.5-0.9 m across, 0.25-0.5 m high (an irregular convex outline)."""
    size = rng.uniform(0.5, 0.9)
    a = np.sort(rng.uniform(0.0, 2.0 * math.pi, 9))
    r = size / 2.0 * rng.uniform(0.7, 1.0, 9)
    outline = np.column_stack([r * np.cos(a), r * np.sin(a)])
    grey = tuple(int(v) for v in np.clip(rng.normal(118.0, 12.0) + rng.normal(0.0, 5.0, 3), 60, 200))
    height = rng.uniform(0.25, 0.5)
    parts = (Part(outline, 0.0, height * 0.6, _shade(grey, 0.7), _shade(grey, 0.9)),
             Part(outline * 0.7, height * 0.6, height, _shade(grey, 0.85), _shade(grey, 1.1)))
    return Model(parts, _texture(rng, blur=0.8), 0.18)


def tree(rng: np.random.Generator, radius_m: float, height_m: float) -> Model:
    """The simulator's tree: a dense foliage cylinder from the ground to its height (it occludes exactly the
    lines of sight `sim.world.World.occluded` says), shaded round and darker below, with a blotchy leaf texture.
    No per-frame shadow: trees stand still, their shadows are baked into the ground texture."""
    n = 20
    circum = radius_m / math.cos(math.pi / n)  # circumscribed polygon: covers the cylinder
    green = (int(rng.integers(30, 45)), int(rng.integers(80, 105)), int(rng.integers(40, 60)))
    parts = (Part(ellipse(2 * circum, 2 * circum, n), 0.0, height_m, _shade(green, 0.8), _shade(green, 1.15),
                  casts_shadow=False),)
    size = 48
    leaves = _texture(rng, size=size, blur=1.2)
    x = np.linspace(-1.0, 1.0, size, dtype=np.float32)
    rounding = -1.6 * x[None, :] ** 2  # darker towards the silhouette's sides
    below = -1.2 * np.linspace(0.0, 1.0, size, dtype=np.float32)[:, None] ** 2  # and towards the ground
    return Model(parts, leaves + rounding + below, 0.3)


def boat(rng: np.random.Generator) -> Model:
    """A 5.5 x 2.1 m motor boat: pointed hull 0.9 m high and a cabin."""
    hull = _pick(rng, _HULLS)
    outline = np.array([[-1.05, -2.75], [1.05, -2.75], [1.05, 1.2], [0.5, 2.45], [0.0, 2.75], [-0.5, 2.45],
                        [-1.05, 1.2]])
    parts = (
        Part(ellipse(3.2, 8.0, 16, forward_m=-1.5), 0.0, 0.02, (215, 220, 220), (225, 230, 230), alpha=0.3,
             casts_shadow=False),
        Part(outline, 0.0, 0.9, _shade(hull, 0.8), _shade((225, 225, 220), 1.0)),
        Part(np.array([[-0.8, -1.6], [0.8, -1.6], [0.8, 0.4], [-0.8, 0.4]]), 0.9, 1.9, (170, 170, 165),
             (235, 235, 235)),
    )
    return Model(parts, _texture(rng), 0.05)


def car(rng: np.random.Generator) -> Model:
    """A 4.4 x 1.8 x 1.45 m car: body and a darker glazed cabin."""
    paint = _pick(rng, _CARS)
    body = np.array([[-0.9, -2.2], [0.9, -2.2], [0.9, 2.0], [0.7, 2.2], [-0.7, 2.2], [-0.9, 2.0]])
    cabin = np.array([[-0.78, -1.3], [0.78, -1.3], [0.72, 0.7], [-0.72, 0.7]])
    parts = (Part(body, 0.15, 0.95, _shade(paint, 0.75), _shade(paint, 1.0)),
             Part(cabin, 0.95, 1.45, (60, 55, 50), _shade(paint, 0.95)))
    return Model(parts, _texture(rng), 0.05)


# --------------------------------------------------------------------------------------------- drawing

@dataclass
class Projection:
    """Image geometry of one placed model: per part the side hull and top polygon (fixed point), the shadows,
    and the sprite's (`box`) and sprite-plus-shadow's (`reach`) xyxy pixel extents."""

    sides: list[np.ndarray]
    tops: list[np.ndarray]
    shadows: list[np.ndarray]
    box: tuple[float, float, float, float]
    reach: tuple[float, float, float, float]


def project_many(placed: list[Placed], camera: Camera, pose: Pose, uav_en: tuple[float, float],
                 shadow_away_en: np.ndarray | None) -> list[Projection | None]:
    """The image geometry of placed models (None for one with a point behind the camera), in one projection.

    uav_en: the UAV's world east/north; shadow_away_en: (2,) metres the shadow of a point 1 m high is cast on
    the ground (away from the sun), None for no shadows.
    """
    if not placed:
        return []
    blocks, z_parts, offsets = [], [], [0]
    for p in placed:
        yaw = math.radians(p.yaw_deg)
        c, s_ = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, s_], [-s_, c]])  # (right, forward) -> (east, north): right = (c, -s), fwd = (s, c)
        centre = np.array([p.east_m - uav_en[0], p.north_m - uav_en[1]])
        sprite = p.model.points
        blocks.append(sprite[:, :2] @ rot.T + centre)
        z_parts.append(sprite[:, 2])
        count = len(sprite)
        shadow = p.model.shadow_points
        if shadow_away_en is not None and len(shadow):
            blocks.append(shadow[:, :2] @ rot.T + centre + shadow[:, 2:3] * shadow_away_en[None, :])
            z_parts.append(np.zeros(len(shadow)))
            count += len(shadow)
        offsets.append(offsets[-1] + count)
    en = np.vstack(blocks)
    uv, ok = project_enu(np.column_stack([en, np.concatenate(z_parts)]), camera, pose)
    # points just in front of the camera plane project very far out: clip before the fixed-point cast
    fixed = np.round(np.clip(np.nan_to_num(uv), -1e7, 1e7) * (1 << _SHIFT)).astype(np.int32)
    out: list[Projection | None] = []
    for k, p in enumerate(placed):
        a, b = offsets[k], offsets[k + 1]
        obj_uv = uv[a:b]
        if not ok[a:b].all() or np.abs(obj_uv).max() > 1e6:  # behind the camera, or too close to draw
            out.append(None)
            continue
        obj_fixed = fixed[a:b]
        sides, tops, shadows = [], [], []
        i = 0
        for part in p.model.parts:
            n = len(part.outline)
            block = obj_fixed[i:i + 2 * n]
            sides.append(cv2.convexHull(block))
            tops.append(block[n:].reshape(-1, 1, 2))
            i += 2 * n
        n_sprite = i
        if b - a > n_sprite:
            for part in p.model.parts:
                if part.casts_shadow:
                    n = len(part.outline)
                    shadows.append(cv2.convexHull(obj_fixed[i:i + 2 * n]))
                    i += 2 * n
        s_uv = obj_uv[:n_sprite]
        box = (float(s_uv[:, 0].min()), float(s_uv[:, 1].min()), float(s_uv[:, 0].max()), float(s_uv[:, 1].max()))
        reach = (float(obj_uv[:, 0].min()), float(obj_uv[:, 1].min()), float(obj_uv[:, 0].max()),
                 float(obj_uv[:, 1].max()))
        out.append(Projection(sides, tops, shadows, box, reach))
    return out


def project_placed(placed: Placed, camera: Camera, pose: Pose, uav_en: tuple[float, float],
                   shadow_away_en: np.ndarray | None) -> Projection | None:
    """The image geometry of one placed model, or None when any of its points is behind the camera
    (`project_many` for one)."""
    return project_many([placed], camera, pose, uav_en, shadow_away_en)[0]


def _rect(poly: np.ndarray, w: int, h: int) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (x0, y0, x1, y1) of a fixed-point polygon, clipped to the frame, or None if empty."""
    x0 = max(int(poly[..., 0].min()) >> _SHIFT, 0)
    y0 = max(int(poly[..., 1].min()) >> _SHIFT, 0)
    x1 = min((int(poly[..., 0].max()) >> _SHIFT) + 2, w)
    y1 = min((int(poly[..., 1].max()) >> _SHIFT) + 2, h)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _poly_mask(poly: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = rect
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, poly - np.array([x0 << _SHIFT, y0 << _SHIFT], np.int32), 255, cv2.LINE_AA, _SHIFT)
    return mask


def draw_placed(frame: np.ndarray, placed: Placed, proj: Projection, shadow_darkness: float) -> bool:
    """Draw a projected model into `frame` (H, W, 3) uint8 in place: shadow, parts bottom to top, texture.

    Opaque parts are filled straight into the frame (anti-aliased OpenCV fills); translucent ones (foam,
    submerged bodies) are blended over their own rectangle; the object's fine texture then modulates the
    pixels it covers. Only the rectangles of the polygons are touched. Returns whether anything was drawn.
    """
    h, w = frame.shape[:2]
    if shadow_darkness > 0:
        for poly in proj.shadows:
            rect = _rect(poly, w, h)
            if rect is None:
                continue
            x0, y0, x1, y1 = rect
            factor = 255 - (_poly_mask(poly, rect).astype(np.float32) * shadow_darkness).astype(np.uint8)
            roi = frame[y0:y1, x0:x1]
            roi[:] = cv2.multiply(roi, cv2.merge([factor, factor, factor]), scale=1.0 / 255.0)
    box = _rect(np.array([[proj.box[0], proj.box[1]], [proj.box[2], proj.box[3]]]) * (1 << _SHIFT), w, h)
    if box is None:
        return False
    bx0, by0, bx1, by1 = box
    # the fine texture, stretched over the sprite's box and cut to its part inside the frame
    left, top = int(math.floor(proj.box[0])), int(math.floor(proj.box[1]))
    full_w = max(int(math.ceil(proj.box[2])) - left, 1)
    full_h = max(int(math.ceil(proj.box[3])) - top, 1)
    tex_full = cv2.resize(placed.model.texture, (full_w, full_h), interpolation=cv2.INTER_LINEAR)
    tex = tex_full[np.ix_(np.clip(np.arange(by0, by1) - top, 0, full_h - 1),
                          np.clip(np.arange(bx0, bx1) - left, 0, full_w - 1))]
    cover = np.zeros((by1 - by0, bx1 - bx0), np.uint8)
    offset = np.array([bx0 << _SHIFT, by0 << _SHIFT], np.int32)
    for part, side, top_poly in zip(placed.model.parts, proj.sides, proj.tops, strict=True):
        # a flat part (foam, a submerged body) has no walls to see: its top is all of it
        faces = ((top_poly, part.top_bgr),) if part.z1_m - part.z0_m < FLAT_M else ((side, part.side_bgr),
                                                                                      (top_poly, part.top_bgr))
        for poly, colour in faces:
            if part.alpha >= 1.0:
                cv2.fillConvexPoly(frame, poly, colour, cv2.LINE_AA, _SHIFT)
                cv2.fillConvexPoly(cover, poly - offset, 255, cv2.LINE_AA, _SHIFT)
                continue
            rect = _rect(poly, w, h)
            if rect is None:
                continue
            x0, y0, x1, y1 = rect
            # translucent parts (foam, a submerged body) are patchy: their opacity follows the texture
            patch = tex_full[np.ix_(np.clip(np.arange(y0, y1) - top, 0, full_h - 1),
                                    np.clip(np.arange(x0, x1) - left, 0, full_w - 1))]
            mask = _poly_mask(poly, rect).astype(np.float32) * (part.alpha / 255.0)
            mask *= np.clip(1.0 + 1.2 * patch, 0.0, 2.0)
            roi = frame[y0:y1, x0:x1]
            region = roi.astype(np.float32)
            region += (np.asarray(colour, np.float32)[None, None, :] - region) * np.minimum(mask, 1.0)[..., None]
            roi[:] = region.astype(np.uint8)
    if not cover.any():
        return False
    detail = np.clip(128.0 + 128.0 * placed.model.texture_contrast * tex * (cover.astype(np.float32) / 255.0),
                     0, 255).astype(np.uint8)
    roi = frame[by0:by1, bx0:bx1]
    roi[:] = cv2.multiply(roi, cv2.merge([detail, detail, detail]), scale=1.0 / 128.0)
    return True

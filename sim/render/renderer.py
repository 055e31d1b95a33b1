"""Compose one frame of a simulated world: ground warp, sky, glint, shadows and sprites, haze, blur, exposure, noise.

`WorldRenderer` is built once per world (group of videos): it sizes and generates the ground texture around the
flights, lays out the static scene (trees, clutter, roads, boats and cars) and keeps each tracked object's
model. `render(frame, drift)` then draws a `sim.render.scene.SceneFrame` with its TRUE pose:

1. ground: one `cv2.warpPerspective` of the texture per band of rows, each band from the mip level that
   matches its ground sampling (no aliasing far away, full detail near); rows above the horizon are sky;
   on the sea the texture travels with the waves and its facets with the short waves (`sea_motion.WaveDrift`);
2. sun glint on water around the sun's mirror image (the texture's A channel holds the wave facets, the facets
   channel whether the short waves tilt them towards the sun now);
3. objects far to near: shadow, then the textured prisms (`sim.render.sprites`);
4. haze with range, motion blur on the frames the simulator marks blurred, exposure/white-balance drift and
   sensor noise.

Deterministic for the dataset's seed: every generator is seeded from (seed, group or video, frame, role).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared.geo import Camera, Pose, footprint_local, pixel_slant_range_m
from sim.render import effects, sprites
from sim.render.effects import Atmosphere, ExposureDrift, SensorNoise
from sim.render.geometry import (
    check_renderable,
    first_ground_row,
    pixel_rays_grid,
    sun_position,
    texture_to_image_homography,
    uav_world_en,
)
from sim.render.scene import SceneFrame, SceneVideo, SceneWorld, SimulatedDataset
from sim.render.sea_motion import FOAM, SPARKLES, WHITECAPS, EventKind, SeaEvents, WaveDrift
from sim.render.sprites import Model, Placed
from sim.render.texture import (
    FACET_SCALE,
    GroundTexture,
    NoiseBank,
    Road,
    bake_shadows,
    make_ground,
    meadow_roads,
    with_mips,
)
from sim.sea_state import CALM, SeaState

logger = logging.getLogger(__name__)

# roles of the generators derived from the seed (apart from the simulator's own)
ROLE_GROUND, ROLE_ATMOSPHERE, ROLE_SCENERY, ROLE_FRAME, ROLE_EXPOSURE, ROLE_NOISE = 101, 102, 103, 104, 105, 106
ROLE_SEA_EVENTS, ROLE_WAVES = 107, 108
#: Exposure time that turns the gimbal's yaw rate into blur length (1/50 s).
EXPOSURE_S = 0.02
#: Side of the far ground (metres) drawn beyond the near texture, and its texels a side.
FAR_GROUND_M, FAR_TEXTURE_PX = 1600.0, 4096
#: Rows (share of the image height) over which the far ground fades into the near one.
FADE_FRACTION = 0.06


@dataclass(frozen=True, slots=True)
class RenderOptions:
    """Knobs of the renderer.

    Attributes
    ----------
    max_texture_px : int
        Longest side of the ground texture (level 0); the resolution coarsens to fit the flights' ground.
    ground_range_m : float
        The texture covers the ground within this horizontal distance of every camera position (farther
        ground repeats the texture mirrored, under the haze).
    ground_res_m : float or None
        Metres per texel; None = the finest ground sampling the cameras see (5th percentile), within the cap.
    scenery : bool
        Add boats (sea) and cars on the roads (meadow): not annotated, listed in render.json.
    sensor_noise_std : float
        Standard deviation of the sensor noise, grey levels (0 = none).
    sea_events : bool
        Transient whitecaps and glint sparkles on the sea (`sim.render.sea_motion`): clutter that moves.
    sea_waves : bool
        The sea's texture travels with the waves and its glint facets twinkle (`sea_motion.WaveDrift`);
        False keeps it fixed in the world (the renderer before 25 Nov 2026).
    """

    max_texture_px: int = 4096
    ground_range_m: float = 150.0
    ground_res_m: float | None = None
    scenery: bool = True
    sensor_noise_std: float = 2.0
    sea_events: bool = True
    sea_waves: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.max_texture_px, bool) or not isinstance(self.max_texture_px, int) \
                or not 64 <= self.max_texture_px <= 16384:
            raise ValueError(f"RenderOptions.max_texture_px={self.max_texture_px!r} must be an integer in 64..16384")
        if not (math.isfinite(self.ground_range_m) and self.ground_range_m > 0):
            raise ValueError(f"RenderOptions.ground_range_m={self.ground_range_m!r} must be > 0")
        if self.ground_res_m is not None and not (math.isfinite(self.ground_res_m) and self.ground_res_m > 0):
            raise ValueError(f"RenderOptions.ground_res_m={self.ground_res_m!r} must be > 0 or None")
        if not (math.isfinite(self.sensor_noise_std) and self.sensor_noise_std >= 0):
            raise ValueError(f"RenderOptions.sensor_noise_std={self.sensor_noise_std!r} must be >= 0")


@dataclass(frozen=True, slots=True)
class Scenery:
    """An object that is not annotated: a boat or car, parked or moving (world metres, m/s, seconds since t0).

    Moving along `path_en` (an (N, 2) polyline) at `speed_mps` from arc length `s0_m`, back and forth.
    """

    kind: str
    model: Model
    east_m: float
    north_m: float
    yaw_deg: float
    speed_mps: float = 0.0
    path_en: np.ndarray | None = None
    s0_m: float = 0.0

    def at(self, t_s: float) -> Placed:
        """The object placed at t_s seconds after the world's first frame."""
        if self.path_en is None or self.speed_mps == 0.0:
            return Placed(self.model, self.east_m, self.north_m, self.yaw_deg)
        seg = np.diff(self.path_en, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        total = float(lengths.sum())
        s = (self.s0_m + self.speed_mps * t_s) % (2.0 * total)
        backwards = s > total
        s = 2.0 * total - s if backwards else s
        k = min(int(np.searchsorted(np.cumsum(lengths), s)), len(lengths) - 1)
        s_k = s - (float(np.cumsum(lengths)[k - 1]) if k else 0.0)
        p = self.path_en[k] + seg[k] * (s_k / max(lengths[k], 1e-9))
        d = -seg[k] if backwards else seg[k]
        return Placed(self.model, float(p[0]), float(p[1]), math.degrees(math.atan2(d[0], d[1])) % 360.0)

    def describe(self) -> dict:
        """JSON description for render.json."""
        out = {"kind": self.kind, "east_m": round(self.east_m, 3), "north_m": round(self.north_m, 3),
               "yaw_deg": round(self.yaw_deg, 2), "speed_mps": round(self.speed_mps, 3)}
        if self.path_en is not None:
            out["path_en"] = np.round(self.path_en, 2).tolist()
            out["s0_m"] = round(self.s0_m, 3)
        return out


@dataclass
class WorldRenderer:
    """Renders the frames of the videos of one world.

    Parameters
    ----------
    dataset : SimulatedDataset
    world : SceneWorld
    options : RenderOptions
    """

    dataset: SimulatedDataset
    world: SceneWorld
    options: RenderOptions = field(default_factory=RenderOptions)

    def __post_init__(self) -> None:
        ds, world = self.dataset, self.world
        self.camera: Camera = ds.camera
        check_renderable(self.camera)
        self.seed = ds.seed
        self.videos: list[SceneVideo] = [v for v in ds.videos if v.group == world.group]
        self.t0 = ds.time_of(self.videos[0].image_ids[0])
        az, el = sun_position(world.origin_lat, world.origin_lon, self.t0)
        self.atmosphere: Atmosphere = effects.make_atmosphere(world.kind, az, el, self._rng(ROLE_ATMOSPHERE))
        self.sea_state: SeaState = ds.sea_state if world.kind == "sea" else CALM
        if not self.sea_state.calm:  # the calm sea keeps exactly the atmosphere it always had
            self.atmosphere = dataclasses.replace(
                self.atmosphere, glint_strength=self.atmosphere.glint_strength * self.sea_state.glint_gain,
                visibility_m=self.atmosphere.visibility_m * self.sea_state.visibility_scale)
        wind_deg = float(self._rng(ROLE_WAVES).uniform(0.0, 360.0))
        self.drift: WaveDrift | None = (WaveDrift(wind_deg) if world.kind == "sea" and self.options.sea_waves
                                        else None)
        extent, res = self._ground_extent()
        far_extent, far_res = self._far_extent(extent, res)
        rng = self._rng(ROLE_GROUND)
        bank = NoiseBank(rng)
        roads: tuple[Road, ...] = meadow_roads(far_extent, rng) if world.kind == "meadow" else ()
        trees = [sprites.ellipse(2 * t.radius_m, 2 * t.radius_m, 20) + np.array([t.east_m, t.north_m])
                 for t in world.trees]

        def ground(ext: tuple[float, float, float, float], r: float, detail: bool, key: int) -> GroundTexture:
            # a frozen sea draws its wind from the texture's generator, as before the waves moved (same pixels)
            g = make_ground(world.kind, ext, r, bank, self._rng(ROLE_GROUND, key), roads=roads, detail=detail,
                            wind_deg=wind_deg if self.drift is not None else None)
            bake_shadows(g, trees, [t.height_m for t in world.trees], az, el, self.atmosphere.shadow_darkness)
            return with_mips(g)

        # the two textures on two threads (numpy and OpenCV release the GIL); each has its own generator
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="uavmm-render-ground") as pool:
            near = pool.submit(ground, extent, res, True, 0)
            far = pool.submit(ground, far_extent, far_res, False, 1)
            self.ground: GroundTexture = near.result()
            self.far_ground: GroundTexture = far.result()
        self.static: list[Placed] = []
        for i, t in enumerate(world.trees):
            model = sprites.tree(sprites.appearance_rng(self.seed, 10_000 + 100 * world.group + i, "tree"),
                                 t.radius_m, t.height_m)
            self.static.append(Placed(model, t.east_m, t.north_m, 0.0))
        self.static_kinds: list[str] = ["tree"] * len(self.static)
        clutter_model = sprites.buoy if world.kind == "sea" else sprites.rock
        for i, (e, n) in enumerate(world.clutter_en):
            arng = sprites.appearance_rng(self.seed, 20_000 + 100 * world.group + i, "clutter")
            self.static.append(Placed(clutter_model(arng), float(e), float(n), float(arng.uniform(0, 360))))
            self.static_kinds.append("buoy" if world.kind == "sea" else "rock")
        self.scenery: list[Scenery] = self._scenery(roads) if self.options.scenery else []
        self._models: dict[int, Model] = {}
        self.noise = (SensorNoise(self.camera.width, self.camera.height, self.options.sensor_noise_std,
                                  self._rng(ROLE_NOISE)) if self.options.sensor_noise_std > 0 else None)
        st = self.sea_state
        kinds: tuple[EventKind, ...] = (
            dataclasses.replace(WHITECAPS, rate_per_m2_s=WHITECAPS.rate_per_m2_s * st.whitecap_rate),
            dataclasses.replace(SPARKLES, rate_per_m2_s=SPARKLES.rate_per_m2_s * st.sparkle_rate))
        if st.foam_rate > 0:  # (a calm sea keeps its two kinds and their generators)
            kinds += (dataclasses.replace(FOAM, rate_per_m2_s=st.foam_rate),)
        self.sea_events = (SeaEvents(self.seed, world.group, ROLE_SEA_EVENTS, self.ground.extent_m, kinds)
                           if world.kind == "sea" and self.options.sea_events else None)
        self._buffer = np.empty((self.camera.height, self.camera.width, 4), np.uint8)
        logger.info("world %d (%s): ground %dx%d texels at %.3f m (far %.2f m), sun az %.0f el %.0f deg, %d trees, "
                    "%d scenery", world.group, world.kind, self.ground.levels[0].shape[1],
                    self.ground.levels[0].shape[0], res, far_res, az, el, len(world.trees), len(self.scenery))

    def _rng(self, role: int, *keys: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.world.group, role, *keys])

    # ------------------------------------------------------------------ set-up

    def _ground_extent(self) -> tuple[tuple[float, float, float, float], float]:
        """Extent (east_min, north_min, east_max, north_max) and metres per texel of the ground texture."""
        cam, ds, o = self.camera, self.dataset, self.options
        pts, gsd = [], []
        bottom = np.array([[cam.cx, cam.height - 0.5]])
        for video in self.videos:
            for image_id in video.image_ids:  # every frame: a frame left out could switch to the far ground
                pose = ds.pose(image_id)
                e, n = uav_world_en(pose, self.world.origin_lat, self.world.origin_lon)
                fp = footprint_local(cam, pose, max_range_m=o.ground_range_m, samples_per_edge=8)
                pts.append(fp + np.array([e, n]))
                slant = float(pixel_slant_range_m(bottom, cam, pose)[0])
                if math.isfinite(slant):
                    gsd.append(slant / cam.fx)
        allp = np.vstack(pts)
        margin = 10.0
        extent = (float(allp[:, 0].min() - margin), float(allp[:, 1].min() - margin),
                  float(allp[:, 0].max() + margin), float(allp[:, 1].max() + margin))
        if self.drift is not None:  # the waves carry the texture downwind: more of it upwind
            times = np.array([ds.time_of(i) - self.t0 for v in self.videos for i in v.image_ids])
            extent = self.drift.grow(extent, times)
        side = max(extent[2] - extent[0], extent[3] - extent[1])
        finest = float(np.percentile(gsd, 5)) if gsd else 0.05
        res = o.ground_res_m if o.ground_res_m is not None else finest
        return extent, max(res, side / (o.max_texture_px - 1), 0.005)

    def _far_extent(self, near: tuple[float, float, float, float],
                    near_res: float) -> tuple[tuple[float, float, float, float], float]:
        """The far ground: FAR_GROUND_M square around the near ground's centre, at most FAR_TEXTURE_PX (and
        max_texture_px) texels a side, at least 4 near texels per texel."""
        ce, cn = 0.5 * (near[0] + near[2]), 0.5 * (near[1] + near[3])
        half = 0.5 * max(FAR_GROUND_M, near[2] - near[0], near[3] - near[1])
        side_px = min(FAR_TEXTURE_PX, self.options.max_texture_px)
        res = max(2.0 * half / (side_px - 1), 4.0 * near_res)
        return (ce - half, cn - half, ce + half, cn + half), res

    def _scenery(self, roads: tuple[Road, ...]) -> list[Scenery]:
        """Boats on the sea, cars on the meadow's asphalt road: one parked, one moving."""
        rng = self._rng(ROLE_SCENERY)
        out: list[Scenery] = []
        kind = self.world.kind
        if kind == "sea":
            r, a = rng.uniform(45.0, 80.0), rng.uniform(0.0, 2.0 * math.pi)
            out.append(Scenery("boat", sprites.boat(sprites.appearance_rng(self.seed, 30_001, "boat")),
                               r * math.sin(a), r * math.cos(a), float(rng.uniform(0.0, 360.0))))
            heading = rng.uniform(0.0, 2.0 * math.pi)
            along = np.array([math.sin(heading), math.cos(heading)])
            across = np.array([along[1], -along[0]])
            offset = rng.choice([-1.0, 1.0]) * rng.uniform(50.0, 80.0)
            path = np.array([offset * across - 400.0 * along, offset * across + 400.0 * along])
            out.append(Scenery("boat", sprites.boat(sprites.appearance_rng(self.seed, 30_002, "boat")),
                               float(path[0, 0]), float(path[0, 1]), math.degrees(heading) % 360.0,
                               speed_mps=float(rng.uniform(2.0, 4.0)), path_en=path,
                               s0_m=float(400.0 - rng.uniform(20.0, 60.0))))
        else:
            asphalt = [r for r in roads if r.surface == "asphalt"]
            if asphalt:
                path = np.array(asphalt[0].points_en)
                mid = len(path) // 2 + int(rng.integers(-6, 6))
                d = path[mid + 1] - path[mid]
                yaw = math.degrees(math.atan2(d[0], d[1])) % 360.0
                side = np.array([d[1], -d[0]]) / max(float(np.hypot(d[0], d[1])), 1e-9)
                park = path[mid] + side * (asphalt[0].width_m / 2.0 - 1.1)
                out.append(Scenery("car", sprites.car(sprites.appearance_rng(self.seed, 30_003, "car")),
                                   float(park[0]), float(park[1]), yaw))
                lane = path - side * 1.5
                seg = np.hypot(*np.diff(lane, axis=0).T).sum()
                out.append(Scenery("car", sprites.car(sprites.appearance_rng(self.seed, 30_004, "car")),
                                   float(lane[0, 0]), float(lane[0, 1]), yaw, speed_mps=float(rng.uniform(8.0, 12.0)),
                                   path_en=lane, s0_m=float(rng.uniform(0.3, 0.7) * seg)))
        return out

    def describe(self) -> dict:
        """The world's look for render.json: ground texture, sun, atmosphere, roads, scenery."""
        g, a = self.ground, self.atmosphere

        def texture(t: GroundTexture) -> dict:
            h, w = t.levels[0].shape[:2]
            return {"texels": [w, h], "res_m": round(t.res_m, 4), "extent_m": [round(v, 2) for v in t.extent_m],
                    "mip_levels": len(t.levels)}

        return {
            "group": self.world.group, "kind": self.world.kind,
            "ground": texture(g), "far_ground": texture(self.far_ground),
            "sun": {"azimuth_deg": round(a.sun_azimuth_deg, 2), "elevation_deg": round(a.sun_elevation_deg, 2)},
            "visibility_m": round(a.visibility_m, 1), "shadow_darkness": round(a.shadow_darkness, 3),
            "roads": [{"surface": r.surface, "width_m": r.width_m, "points_en": [list(p) for p in r.points_en]}
                      for r in g.roads],
            "scenery": [s.describe() for s in self.scenery],
            "waves": None if self.drift is None else {
                "towards_deg": round(self.drift.wind_deg, 2), "long_mps": self.drift.long_mps,
                "short_mps": self.drift.short_mps, "wrap_s": round(self.drift.period_s, 1)},
            **({} if self.sea_state.calm else {"sea_state": self.sea_state.to_dict()}),
        }

    def model_of(self, track_id: int, cls: str) -> Model:
        """The fixed model (shape, colours, texture) of a tracked object."""
        model = self._models.get(track_id)
        if model is None:
            arng = sprites.appearance_rng(self.seed, track_id, cls)
            model = (sprites.submerged(sprites.swimmer(arng), self.sea_state.swimmer_wash) if cls == "swimmer"
                     else sprites.person(arng))
            self._models[track_id] = model
        return model

    # ------------------------------------------------------------------ per frame

    def ground_bands(self, pose: Pose, first_row: int,
                     t_s: float = 0.0) -> tuple[list[tuple[int, int, GroundTexture, int]], int]:
        """(row0, row1, texture, level) bands of the ground rows, top to bottom, and the first near row.

        Rows whose ground (at the left, centre and right columns) lies inside the near texture use it, the
        rows above the far one; within each, the mip level whose texel matches the rows' ground sampling
        (the geometric mean of the along- and across-range pixel footprints). t_s: seconds since the world's
        first frame (the near texture has travelled with the waves).
        """
        cam = self.camera
        rows = np.arange(first_row, cam.height, dtype=np.float64)
        if not len(rows):
            return [], cam.height
        uav_en = uav_world_en(pose, self.world.origin_lat, self.world.origin_lon)
        rays = pixel_rays_grid(cam, pose, np.array([0.5, cam.cx, cam.width - 0.5]), np.r_[rows + 0.5, rows[-1] + 1.5])
        up = rays[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(up < -1e-9, pose.height_m / -up, np.inf)
            east = uav_en[0] + rays[..., 0] * t
            north = uav_en[1] + rays[..., 1] * t
            ground = np.hypot(rays[:, 1, 0], rays[:, 1, 1]) * t[:, 1]
            along = np.abs(np.diff(ground))
            across = np.sqrt(pose.height_m ** 2 + ground[:-1] ** 2) / cam.fx
            footprint = np.sqrt(along * across)
        e0, n0, e1, n1 = self.ground.extent_m
        if self.drift is not None:
            de, dn = self.drift.offset_en(t_s, self.drift.long_mps)
            e0, n0, e1, n1 = e0 + de, n0 + dn, e1 + de, n1 + dn
        pad = 2.0 * self.ground.res_m
        inside = np.asarray(((east >= e0 + pad) & (east <= e1 - pad) & (north >= n0 + pad) & (north <= n1 - pad)
                             ).all(axis=1))
        outside = np.flatnonzero(~inside[:-1])
        split = int(outside[-1]) + 1 if len(outside) else 0  # rows below the last outside row are all near
        bands: list[tuple[int, int, GroundTexture, int]] = []
        for lo, hi, tex in ((0, split, self.far_ground), (split, len(rows), self.ground)):
            if hi <= lo:
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                texel = footprint[lo:hi] / tex.res_m
                level = np.where(np.isfinite(texel), np.floor(np.log2(np.maximum(texel, 1.0))), len(tex.levels) - 1)
            level = np.clip(level, 0, len(tex.levels) - 1).astype(int)
            cuts = np.flatnonzero(np.diff(level)) + 1
            for s0, s1 in zip(np.r_[0, cuts], np.r_[cuts, len(level)], strict=True):
                bands.append((first_row + lo + int(s0), first_row + lo + int(s1), tex, int(level[s0])))
        return bands, first_row + split

    def render(self, frame: SceneFrame, drift: ExposureDrift | None = None) -> np.ndarray:
        """The (H, W, 3) uint8 BGR image of a frame."""
        cam, pose = self.camera, frame.pose
        check_renderable(cam, pose)
        atm = self.atmosphere
        uav_en = uav_world_en(pose, self.world.origin_lat, self.world.origin_lon)
        first = first_ground_row(cam, pose)
        buf = self._buffer
        t_rel = frame.t - self.t0
        bands, split = self.ground_bands(pose, first, t_rel)
        for r0, r1, tex, level in bands:
            m = texture_to_image_homography(cam, pose, uav_en, self._texel_to_world(tex, level, t_rel), r0)
            cv2.warpPerspective(tex.levels[level], m, (cam.width, r1 - r0), dst=buf[r0:r1],
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        self._fade_to_near(bands, split, first, pose, uav_en, t_rel)
        image = cv2.cvtColor(buf, cv2.COLOR_BGRA2BGR)
        effects.fill_sky(image, first, cam, pose, atm)
        if self.world.kind == "sea":
            glint = effects.glint_map(cam, pose, atm, first)
            if glint is not None:
                self._twinkle(bands, glint[1], pose, uav_en, t_rel)
                effects.add_glint(image, buf[..., 3], glint[0], glint[1], atm.glint_strength)
            if self.sea_events is not None:
                self.sea_events.draw(image, cam, pose, uav_en, t_rel, first, glint)
        self._draw_objects(image, frame, uav_en)
        gains = drift.channel_gains(frame.frame_index, first / cam.height) if drift is not None else np.ones(3)
        effects.tone(image, effects.haze_rows(cam, pose, atm, first), atm.horizon_bgr, gains)
        rng = np.random.default_rng([self.seed, frame.video_id, frame.frame_index, ROLE_FRAME])
        if frame.blurred:
            image = self._blur(image, frame, rng)
        if self.sea_state.blur_mrad > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.sea_state.blur_mrad * 1e-3 * cam.fx)
        if self.noise is not None:
            image = self.noise.apply(image, rng)
        return image

    def _texel_to_world(self, tex: GroundTexture, level: int, t_s: float, facets: bool = False) -> np.ndarray:
        """Texel -> world affine of a texture level at t_s: carried by the long waves (its facets channel by
        the short waves) on a moving sea, fixed otherwise."""
        if self.drift is None:
            return tex.texel_to_world(level)
        return self.drift.moved(tex.texel_to_world(level), t_s,
                                self.drift.short_mps if facets else self.drift.long_mps)

    def _twinkle(self, bands: list[tuple[int, int, GroundTexture, int]], rect: tuple[int, int, int, int],
                 pose: Pose, uav_en: tuple[float, float], t_s: float) -> None:
        """Multiply the glint potential (A of the buffer) inside rect by the near texture's facets channel as
        the short waves carry it now (in place): where the two patterns slide over each other, facets turn
        towards the sun and away. Rows of the far ground keep their potential."""
        if self.drift is None or not self.ground.facets:
            return
        x0, y0, x1, y1 = rect
        factor = np.full((y1 - y0, x1 - x0), int(FACET_SCALE), np.uint8)
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        for r0, r1, tex, level in bands:
            a, b = max(r0, y0), min(r1, y1)
            if tex is not self.ground or b <= a:
                continue
            m = shift @ texture_to_image_homography(self.camera, pose, uav_en,
                                                    self._texel_to_world(tex, level, t_s, facets=True), a)
            cv2.warpPerspective(tex.facets[level], m, (x1 - x0, b - a), dst=factor[a - y0:b - y0],
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        alpha = np.ascontiguousarray(self._buffer[y0:y1, x0:x1, 3])
        self._buffer[y0:y1, x0:x1, 3] = cv2.multiply(alpha, factor, scale=1.0 / FACET_SCALE)

    def _fade_to_near(self, bands: list[tuple[int, int, GroundTexture, int]], split: int, first: int, pose: Pose,
                      uav_en: tuple[float, float], t_s: float = 0.0) -> None:
        """Cross-fade the last far rows above `split` into the near ground (no seam between the two)."""
        cam = self.camera
        fade0 = max(first, split - max(2, int(FADE_FRACTION * cam.height)))
        near = [b for b in bands if b[2] is self.ground]
        if not near or split <= fade0 or split >= cam.height:
            return
        level = near[0][3]
        m = texture_to_image_homography(cam, pose, uav_en, self._texel_to_world(self.ground, level, t_s), fade0)
        near_rows = cv2.warpPerspective(self.ground.levels[level], m, (cam.width, split - fade0),
                                        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
        ramp = ((np.arange(split - fade0, dtype=np.float32) + 0.5) / (split - fade0))[:, None]
        w_near = np.ascontiguousarray(np.broadcast_to(ramp, (split - fade0, cam.width)))
        band = self._buffer[fade0:split]
        band[:] = cv2.blendLinear(band, near_rows, np.ascontiguousarray(1.0 - w_near), w_near)

    def _blur(self, image: np.ndarray, frame: SceneFrame, rng: np.random.Generator) -> np.ndarray:
        """Smear along the image x axis by yaw rate x fx x exposure for fast turns, else a random shake."""
        cam = self.camera
        rate = abs(frame.heading_rate_deg_s)
        if rate >= self.dataset.blur_heading_rate_deg_s:
            length = math.radians(rate) * cam.fx * EXPOSURE_S
            angle = 0.0
        else:
            length = rng.uniform(0.01, 0.025) * cam.width  # a shake: the emulator's blurred frames lose most score
            angle = float(rng.uniform(0.0, 180.0))
        return effects.motion_blur(image, min(max(length, 2.0), 0.05 * cam.width), angle)

    def placed_objects(self, frame: SceneFrame) -> list[Placed]:
        """Everything standing on the ground in a frame: trees, clutter, scenery and the tracked objects."""
        t_rel = frame.t - self.t0
        placed = list(self.static)
        placed.extend(s.at(t_rel) for s in self.scenery)
        placed.extend(Placed(self.model_of(o.track_id, o.cls), o.east_m, o.north_m, o.yaw_deg, border_only=not o.known)
                      for o in frame.objects)
        return placed

    def unannotated_boxes(self, frame: SceneFrame, min_inside: float = 0.5) -> list[tuple[str, list[float]]]:
        """(kind, [x, y, w, h]) image boxes of the drawn objects that images.json does not annotate: buoys and
        boats on the sea; rocks, trees and cars on the meadow. Like the annotations, a box is cut to the image
        and kept when at least `min_inside` of it is inside (and it is at least a pixel a side)."""
        cam, pose = self.camera, frame.pose
        uav_en = uav_world_en(pose, self.world.origin_lat, self.world.origin_lon)
        t_rel = frame.t - self.t0
        placed = list(self.static) + [s.at(t_rel) for s in self.scenery]
        kinds = self.static_kinds + [s.kind for s in self.scenery]
        if not placed:
            return []
        in_view = np.flatnonzero(self._cull(placed, pose, uav_en, 0.0))
        out = []
        for i, proj in zip(in_view, sprites.project_many([placed[i] for i in in_view], cam, pose, uav_en, None),
                           strict=True):
            if proj is None:
                continue
            bx0, by0, bx1, by1 = proj.box
            cx0, cy0 = max(bx0, 0.0), max(by0, 0.0)
            cx1, cy1 = min(bx1, float(cam.width)), min(by1, float(cam.height))
            full = max(bx1 - bx0, 1e-9) * max(by1 - by0, 1e-9)
            if cx1 - cx0 < 1.0 or cy1 - cy0 < 1.0 or (cx1 - cx0) * (cy1 - cy0) < min_inside * full:
                continue
            out.append((kinds[int(i)], [round(cx0, 2), round(cy0, 2), round(cx1 - cx0, 2), round(cy1 - cy0, 2)]))
        return out

    def _cull(self, placed: list[Placed], pose: Pose, uav_en: tuple[float, float],
              shadow_m_per_m: float) -> np.ndarray:
        """(N,) bool: whether each object (a cylinder of its radius and height, widened by its longest shadow)
        may reach into the image; one vectorised projection instead of drawing everything."""
        cam = self.camera
        n = len(placed)
        centre = np.array([[p.east_m - uav_en[0], p.north_m - uav_en[1]] for p in placed]).reshape(n, 2)
        radius = np.array([p.model.radius_m + p.model.height_m * shadow_m_per_m for p in placed])
        height = np.array([p.model.height_m for p in placed])
        pts = np.vstack([np.column_stack([centre, np.zeros(n)]), np.column_stack([centre, height])])
        cam_xyz = (pts - pose.camera_position_enu[None, :]) @ pose.R_world_from_cam
        z = cam_xyz[:, 2]
        near = np.minimum(z[:n], z[n:])
        keep = np.ones(n, bool)
        ok = near > radius + 1e-3  # every point of the object is in front of the camera: test its box
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * cam_xyz[:, 0] / z + cam.cx
            v = cam.fy * cam_xyz[:, 1] / z + cam.cy
            r_px = (radius * max(cam.fx, cam.fy)) / np.maximum(near - radius, 1e-3) + 2.0
        u0, u1 = np.minimum(u[:n], u[n:]) - r_px, np.maximum(u[:n], u[n:]) + r_px
        v0, v1 = np.minimum(v[:n], v[n:]) - r_px, np.maximum(v[:n], v[n:]) + r_px
        outside = (u1 < 0) | (v1 < 0) | (u0 > cam.width) | (v0 > cam.height)
        keep[ok] = ~outside[ok]
        keep[z.reshape(2, n).max(axis=0) <= 0] = False  # wholly behind the camera
        return keep

    def _draw_objects(self, image: np.ndarray, frame: SceneFrame, uav_en: tuple[float, float]) -> int:
        """Shadows and sprites far to near; returns how many were drawn."""
        cam, pose, atm = self.camera, frame.pose, self.atmosphere
        placed = self.placed_objects(frame)
        if not placed:
            return 0
        dist = np.array([math.hypot(p.east_m - uav_en[0], p.north_m - uav_en[1]) for p in placed])
        away = None
        if atm.sun_elevation_deg > 1.0 and atm.shadow_darkness > 0:
            az = math.radians(atm.sun_azimuth_deg)
            away = -np.array([math.sin(az), math.cos(az)]) / math.tan(math.radians(atm.sun_elevation_deg))
        drawn = 0
        w, h = cam.width, cam.height
        shadow_m = 0.0 if away is None else float(np.hypot(*away))
        in_view = self._cull(placed, pose, uav_en, shadow_m)
        order = [int(i) for i in np.argsort(-dist, kind="stable") if in_view[int(i)]]
        projections = sprites.project_many([placed[i] for i in order], cam, pose, uav_en, away)
        for i, proj in zip(order, projections, strict=True):
            p = placed[i]
            if proj is None:
                continue
            x0, y0, x1, y1 = proj.reach
            if x1 < 0 or y1 < 0 or x0 > w or y0 > h:
                continue
            if p.border_only:
                bx0, by0, bx1, by1 = proj.box
                if bx0 >= 0 and by0 >= 0 and bx1 <= w and by1 <= h:
                    continue  # a continued position inside the image: the simulator did not see it there
            drawn += sprites.draw_placed(image, p, proj, atm.shadow_darkness)
        return drawn


def exposure_for(dataset: SimulatedDataset, video: SceneVideo) -> ExposureDrift:
    """The exposure drift of one video (deterministic for the dataset's seed and the video id)."""
    rng = np.random.default_rng([dataset.seed, video.id, ROLE_EXPOSURE])
    return ExposureDrift(len(video.image_ids), dataset.fps, rng)

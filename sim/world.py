"""The simulated ground truth world: ground at a real lat/lon with moving objects, trees and clutter.

People walk (POG-like), swimmers drift in a common current (SeaDronesSee-like); trees are vertical cylinders
that occlude lines of sight; clutter objects are fixed rocks/buoys that look like the class to a detector.

Positions are kept in local east/north metres around the world origin (`WorldParams.origin_lat/lon`) and
converted with `shared.geo.local_to_latlon`. The world advances in fixed steps (`World.step`), driven by its
own seeded generator, so a run is reproducible for a seed. The ground is flat unless the scenario gives a
terrain (`sim.terrain`), which objects and trees then stand on (`occluded`'s ground_m, tree_ground_m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.geo import local_to_latlon

#: Class names and their fixed COCO category ids (the same in every scenario).
CATEGORY_IDS: dict[str, int] = {"person": 1, "swimmer": 2}

#: 3-D box of each class in metres: (width across the heading, depth along it, height above the ground).
CLASS_BOX_M: dict[str, tuple[float, float, float]] = {
    "person": (0.5, 0.3, 1.7),
    "swimmer": (0.5, 0.5, 0.3),
}


@dataclass(frozen=True, slots=True)
class Tree:
    """A tree as a vertical cylinder: centre east/north (m, world-local), radius (m) and height (m)."""

    east_m: float
    north_m: float
    radius_m: float
    height_m: float


@dataclass(frozen=True, slots=True)
class WorldParams:
    """Everything that defines a world; ranges are (low, high) tuples sampled per world.

    Attributes
    ----------
    origin_lat, origin_lon : float
        WGS84 degrees of the local frame's origin (the centre of the scene).
    cls : str
        Class of every moving object: "person" (walking) or "swimmer" (drifting).
    n_objects : int
        Number of moving objects.
    spawn_radius_m : float
        Objects start uniformly in a disc of this radius around the origin.
    boundary_radius_m : float
        People turn back towards the origin when they walk beyond this radius (soft boundary).
    walk_speed_mps : tuple
        Preferred walking speed per person, m/s.
    turn_noise_deg_per_sqrt_s : float
        Heading random walk of walkers, degrees per sqrt(second).
    sharp_turn_rate_hz : float
        Rate of sudden turns by +-(45..135) degrees per walker.
    pause_rate_hz, pause_duration_s : float, tuple
        Rate at which a walker stops and how long the stop lasts (s).
    current_speed_mps : tuple
        Speed of the common surface current (swimmers), m/s; its direction is uniform.
    swim_speed_std_mps, swim_corr_s : float
        Own random motion of each swimmer: AR(1) velocity std (m/s) and correlation time (s).
    n_trees : int
        Random trees in the spawn disc (plus `fixed_trees`).
    tree_radius_m, tree_height_m : tuple
        Ranges of random trees.
    fixed_trees : tuple of Tree
        Trees at designed positions (e.g. the coop scenario's occluder).
    n_clutter : int
        Persistent clutter objects (rocks, buoys) that a detector mistakes for the class.
    clutter_radius_m : float
        Clutter lies uniformly in a disc of this radius.
    fixed_objects : tuple of (east_m, north_m, stationary)
        Objects at designed start positions, prepended to the random ones; stationary ones never move.
    """

    origin_lat: float
    origin_lon: float
    cls: str = "person"
    n_objects: int = 15
    spawn_radius_m: float = 40.0
    boundary_radius_m: float = 50.0
    walk_speed_mps: tuple[float, float] = (1.2, 1.5)
    turn_noise_deg_per_sqrt_s: float = 25.0
    sharp_turn_rate_hz: float = 0.05
    pause_rate_hz: float = 0.03
    pause_duration_s: tuple[float, float] = (2.0, 8.0)
    current_speed_mps: tuple[float, float] = (0.1, 0.4)
    swim_speed_std_mps: float = 0.05
    swim_corr_s: float = 5.0
    n_trees: int = 0
    tree_radius_m: tuple[float, float] = (1.5, 3.5)
    tree_height_m: tuple[float, float] = (6.0, 15.0)
    fixed_trees: tuple[Tree, ...] = ()
    n_clutter: int = 3
    clutter_radius_m: float = 40.0
    fixed_objects: tuple[tuple[float, float, bool], ...] = ()

    def __post_init__(self) -> None:
        if self.cls not in CLASS_BOX_M:
            raise ValueError(f"WorldParams.cls={self.cls!r} is not one of {sorted(CLASS_BOX_M)}")
        if not -90.0 <= self.origin_lat <= 90.0 or not -180.0 <= self.origin_lon <= 180.0:
            raise ValueError(f"WorldParams origin ({self.origin_lat}, {self.origin_lon}) is not a valid lat/lon")
        if self.n_objects < 0 or self.n_trees < 0 or self.n_clutter < 0:
            raise ValueError("WorldParams counts (n_objects, n_trees, n_clutter) must be >= 0")


class World:
    """State of one simulated world; advance it with `step`.

    Attributes (arrays over objects, shape (N,)): `track_ids` int, `east_m`, `north_m` float metres
    (world-local), `yaw_deg` (direction the object faces, clockwise from north), `stationary` bool.
    `trees` lists the occluders; `clutter_east_m`, `clutter_north_m` (C,) the clutter spots.
    """

    def __init__(self, params: WorldParams, rng: np.random.Generator, *, first_track_id: int = 1) -> None:
        self.params = params
        self.cls = params.cls
        self.category_id = CATEGORY_IDS[params.cls]
        self.box_m = CLASS_BOX_M[params.cls]
        self._rng = rng
        self.t_s = 0.0

        fixed = np.array([[e, n] for e, n, _ in params.fixed_objects], dtype=np.float64).reshape(-1, 2)
        n_rand = params.n_objects
        r = params.spawn_radius_m * np.sqrt(rng.uniform(0.0, 1.0, n_rand))
        a = rng.uniform(0.0, 2.0 * math.pi, n_rand)
        pos = np.vstack([fixed, np.column_stack([r * np.sin(a), r * np.cos(a)])])
        n = len(pos)
        self.n = n
        self.track_ids = np.arange(first_track_id, first_track_id + n, dtype=np.int64)
        self.east_m = pos[:, 0].copy()
        self.north_m = pos[:, 1].copy()
        self.stationary = np.array([s for _, _, s in params.fixed_objects] + [False] * n_rand, dtype=bool)
        self.yaw_deg = rng.uniform(0.0, 360.0, n)

        # walkers
        self._speed_pref = rng.uniform(*params.walk_speed_mps, n)
        self._pause_left_s = np.zeros(n)
        # swimmers
        c_speed = rng.uniform(*params.current_speed_mps)
        c_dir = math.radians(rng.uniform(0.0, 360.0))
        self.current_en_mps = np.array([c_speed * math.sin(c_dir), c_speed * math.cos(c_dir)])
        self._swim_vel = rng.normal(0.0, params.swim_speed_std_mps, (n, 2))

        trees = list(params.fixed_trees)
        tr = params.spawn_radius_m * np.sqrt(rng.uniform(0.0, 1.0, params.n_trees))
        ta = rng.uniform(0.0, 2.0 * math.pi, params.n_trees)
        radii = rng.uniform(*params.tree_radius_m, params.n_trees)
        heights = rng.uniform(*params.tree_height_m, params.n_trees)
        for i in range(params.n_trees):
            trees.append(Tree(float(tr[i] * math.sin(ta[i])), float(tr[i] * math.cos(ta[i])),
                              float(radii[i]), float(heights[i])))
        self.trees: tuple[Tree, ...] = tuple(trees)

        cr = params.clutter_radius_m * np.sqrt(rng.uniform(0.0, 1.0, params.n_clutter))
        ca = rng.uniform(0.0, 2.0 * math.pi, params.n_clutter)
        self.clutter_east_m = cr * np.sin(ca)
        self.clutter_north_m = cr * np.cos(ca)
        self.clutter_yaw_deg = rng.uniform(0.0, 360.0, params.n_clutter)

    # ------------------------------------------------------------------ motion

    def step(self, dt_s: float) -> None:
        """Advance every object by dt_s seconds (people walk, swimmers drift)."""
        if self.n:
            if self.cls == "swimmer":
                self._step_swimmers(dt_s)
            else:
                self._step_walkers(dt_s)
        self.t_s += dt_s

    def _step_walkers(self, dt_s: float) -> None:
        p, rng, n = self.params, self._rng, self.n
        yaw = self.yaw_deg + rng.normal(0.0, p.turn_noise_deg_per_sqrt_s * math.sqrt(dt_s), n)
        sharp = rng.uniform(size=n) < p.sharp_turn_rate_hz * dt_s
        yaw = np.where(sharp, yaw + rng.choice([-1.0, 1.0], n) * rng.uniform(45.0, 135.0, n), yaw)
        # Soft boundary: beyond the radius, turn towards the origin at up to 90 deg/s.
        dist = np.hypot(self.east_m, self.north_m)
        home = np.degrees(np.arctan2(-self.east_m, -self.north_m))
        err = (home - yaw + 180.0) % 360.0 - 180.0
        outside = dist > p.boundary_radius_m
        yaw = np.where(outside, yaw + np.clip(err, -90.0 * dt_s, 90.0 * dt_s), yaw)

        self._pause_left_s = np.maximum(self._pause_left_s - dt_s, 0.0)
        start_pause = (self._pause_left_s <= 0.0) & (rng.uniform(size=n) < p.pause_rate_hz * dt_s) & ~outside
        self._pause_left_s = np.where(start_pause, rng.uniform(*p.pause_duration_s, n), self._pause_left_s)
        moving = (self._pause_left_s <= 0.0) & ~self.stationary
        self.yaw_deg = np.where(self.stationary, self.yaw_deg, yaw % 360.0)
        step = np.where(moving, self._speed_pref * dt_s, 0.0)
        rad = np.radians(self.yaw_deg)
        self.east_m = self.east_m + step * np.sin(rad)
        self.north_m = self.north_m + step * np.cos(rad)

    def _step_swimmers(self, dt_s: float) -> None:
        p = self.params
        a = math.exp(-dt_s / p.swim_corr_s)
        self._swim_vel = a * self._swim_vel + math.sqrt(1.0 - a * a) * self._rng.normal(
            0.0, p.swim_speed_std_mps, (self.n, 2))
        vel = np.where(self.stationary[:, None], 0.0, self.current_en_mps[None, :] + self._swim_vel)
        self.east_m = self.east_m + vel[:, 0] * dt_s
        self.north_m = self.north_m + vel[:, 1] * dt_s
        self.yaw_deg = np.where(self.stationary, self.yaw_deg,
                                (self.yaw_deg + self._rng.normal(0.0, 5.0 * math.sqrt(dt_s), self.n)) % 360.0)

    # ------------------------------------------------------------------ queries

    def latlon(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,) lat, lon degrees of the objects' ground centres."""
        return local_to_latlon(self.east_m, self.north_m, self.params.origin_lat, self.params.origin_lon)

    def clutter_latlon(self) -> tuple[np.ndarray, np.ndarray]:
        """(C,) lat, lon degrees of the clutter spots."""
        return local_to_latlon(self.clutter_east_m, self.clutter_north_m,
                               self.params.origin_lat, self.params.origin_lon)

    def occluded(self, cam_east_m: float, cam_north_m: float, cam_height_m: float,
                 east_m: np.ndarray, north_m: np.ndarray, centre_height_m: float, *,
                 ground_m: np.ndarray | None = None, tree_ground_m: np.ndarray | None = None) -> np.ndarray:
        """Whether the line of sight from the camera to each point passes through a tree.

        Parameters
        ----------
        cam_east_m, cam_north_m, cam_height_m : float
            Camera position in world-local metres.
        east_m, north_m : (N,) float
            Target ground positions (world-local metres).
        centre_height_m : float
            Height of the target point above the ground (the object's centre), m.
        ground_m, tree_ground_m : (N,) and (T,) float, optional
            Over a terrain: the ground's height under each target and under each tree (`trees` order), m in
            the frame of cam_height_m; None: flat ground at 0.

        Returns
        -------
        (N,) bool
            True where the segment camera -> target meets a tree cylinder (ground to tree height).
        """
        n = len(east_m)
        out = np.zeros(n, dtype=bool)
        if not self.trees or n == 0:
            return out
        tx = np.array([t.east_m for t in self.trees])[None, :]
        ty = np.array([t.north_m for t in self.trees])[None, :]
        tr = np.array([t.radius_m for t in self.trees])[None, :]
        th = np.array([t.height_m for t in self.trees])[None, :]
        # Segment P(s) = C + s (O - C), s in [0, 1]; horizontal distance to the axis <= r is a quadratic in s.
        dx = (east_m - cam_east_m)[:, None]
        dy = (north_m - cam_north_m)[:, None]
        fx = cam_east_m - tx
        fy = cam_north_m - ty
        qa = dx * dx + dy * dy
        qb = 2.0 * (fx * dx + fy * dy)
        qc = fx * fx + fy * fy - tr * tr
        disc = qb * qb - 4.0 * qa * qc
        with np.errstate(invalid="ignore", divide="ignore"):
            sq = np.sqrt(np.maximum(disc, 0.0))
            s0 = np.clip((-qb - sq) / (2.0 * qa), 0.0, 1.0)
            s1 = np.clip((-qb + sq) / (2.0 * qa), 0.0, 1.0)
        # Height along the segment decreases with s; inside the cylinder over [s0, s1] the lowest point is at s1.
        if ground_m is None:
            z_at_s1 = cam_height_m + s1 * (centre_height_m - cam_height_m)
        else:  # over a terrain: the target and the trees stand on their own ground
            z_at_s1 = cam_height_m + s1 * (ground_m[:, None] + centre_height_m - cam_height_m)
            th = th + (np.zeros(len(self.trees)) if tree_ground_m is None else tree_ground_m)[None, :]
        hit = (disc > 0.0) & (qa > 0.0) & (s1 > s0) & (z_at_s1 <= th)
        out = hit.any(axis=1)
        return out

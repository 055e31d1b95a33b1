"""Simulated terrain under the grass world: hills, a slope or a step (a river bank), as a DEM around the scene.

`TerrainSpec` is what a scenario (or an evaluation domain) sets; `SimTerrain` is one realisation of it, drawn
from a seeded generator of its own (so the world, flights, telemetry and detector draw the same numbers with and
without a terrain: the same flights over another ground). The DEM is the truth: a `shared.terrain` grid whose
bilinear surface the objects and trees stand on and the simulator projects with; the dataset writer saves it
as dem.npz beside the dataset. The UAVs take off at the scene's origin: their heights count from its
elevation (`SimTerrain.takeoff_elevation_m`), as DJI's rel_alt and SeaDronesSee's altitude do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.terrain import ElevationGrid, Terrain

__all__ = ["TERRAIN_KINDS", "SimTerrain", "TerrainSpec"]

TERRAIN_KINDS = ("hills", "slope", "step")


@dataclass(frozen=True, slots=True)
class TerrainSpec:
    """The ground of a world that is not flat.

    Attributes
    ----------
    kind : str
        "hills" (Gaussian hills and hollows), "slope" (a plane), "step" (a bank between two levels).
    relief_m : float
        hills: from the lowest hollow to the highest top; slope: the rise over 100 m; step: its height.
    extent_m, cell_m : float
        The DEM: a square of extent_m around the origin, samples every cell_m metres.
    base_elevation_m : float
        Elevation of the flat part under the hills (the datum's heights, as a DEM's above sea level).
    n_hills : int
        hills: how many, centres within `spread_m` of the origin.
    hill_sigma_m : (float, float)
        hills: range of their widths (standard deviation, metres).
    spread_m : float
        hills: their centres lie within this radius; step: its line passes within a tenth of it.
    step_width_m : float
        step: the width over which the bank rises (metres, 10-90 %).
    aspect_deg : float or None
        slope, step: the bearing the ground rises towards (degrees clockwise from north); None (the default)
        draws it per seed. A scenario that places its UAVs by the slope (`coop-slope`: one below, one above)
        fixes it.
    """

    kind: str
    relief_m: float = 8.0
    extent_m: float = 500.0
    cell_m: float = 1.0
    base_elevation_m: float = 420.0
    n_hills: int = 8
    hill_sigma_m: tuple[float, float] = (15.0, 35.0)
    spread_m: float = 50.0
    step_width_m: float = 3.0
    aspect_deg: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in TERRAIN_KINDS:
            raise ValueError(f"TerrainSpec.kind={self.kind!r} is not one of {', '.join(TERRAIN_KINDS)}")
        for name in ("relief_m", "extent_m", "cell_m", "spread_m", "step_width_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0) or (name in ("extent_m", "cell_m") and value <= 0):
                raise ValueError(f"TerrainSpec.{name}={value!r} must be a finite number > 0 (>= 0 for relief)")
        if self.extent_m / self.cell_m > 4000:
            raise ValueError(f"TerrainSpec: {self.extent_m} m at {self.cell_m} m is over 4,000 cells across")
        if self.aspect_deg is not None and not (isinstance(self.aspect_deg, (int, float))
                                                and math.isfinite(self.aspect_deg)):
            raise ValueError(f"TerrainSpec.aspect_deg={self.aspect_deg!r} must be a finite bearing in degrees or None")
        lo, hi = self.hill_sigma_m
        if not 0 < lo <= hi:
            raise ValueError(f"TerrainSpec.hill_sigma_m={self.hill_sigma_m!r} must be 0 < low <= high")

    def build(self, rng: np.random.Generator, origin_lat: float, origin_lon: float) -> SimTerrain:
        """One realisation around the world's origin (lat/lon degrees)."""
        half = 0.5 * self.extent_m
        n = int(round(self.extent_m / self.cell_m)) + 1
        axis = np.linspace(-half, half, n)
        east, north = np.meshgrid(axis, axis[::-1])  # row 0 is the northern edge
        heights = self.base_elevation_m + self._relief(rng, east, north)
        grid = ElevationGrid.from_local(heights, origin_lat, origin_lon, west_m=-half, north_m=half,
                                        cell_m=self.cell_m)
        return SimTerrain(self, grid, float(grid.at_grid((n - 1) / 2, (n - 1) / 2)))

    def _relief(self, rng: np.random.Generator, east: NDArray, north: NDArray) -> NDArray:
        if self.kind == "slope":
            aspect = self._aspect_rad(rng)
            return self.relief_m / 100.0 * (east * math.sin(aspect) + north * math.cos(aspect))
        if self.kind == "step":
            aspect = self._aspect_rad(rng)
            offset = rng.uniform(-0.1, 0.1) * self.spread_m
            across = east * math.sin(aspect) + north * math.cos(aspect) - offset
            # tanh(1.1) = 0.8: the bank rises 10..90 % over step_width_m
            return self.relief_m * 0.5 * (1.0 + np.tanh(2.2 * across / max(self.step_width_m, 1e-9)))
        z = np.zeros_like(east)
        for _ in range(self.n_hills):
            r = self.spread_m * math.sqrt(rng.uniform())
            a = rng.uniform(0.0, 2.0 * math.pi)
            sigma = rng.uniform(*self.hill_sigma_m)
            height = self.relief_m * rng.uniform(0.4, 1.0) * (1.0 if rng.uniform() < 0.7 else -0.5)
            z += height * np.exp(-((east - r * math.sin(a)) ** 2 + (north - r * math.cos(a)) ** 2) / (2 * sigma**2))
        span = float(np.ptp(z))  # overlapping hills add up: the relief is the whole terrain's
        return z * (self.relief_m / span) if span > 0 else z

    def _aspect_rad(self, rng: np.random.Generator) -> float:
        """The bearing the ground rises towards, radians: drawn (always, so a fixed aspect leaves the other draws
        where they were) and replaced by aspect_deg when that is set."""
        drawn = rng.uniform(0.0, 2.0 * math.pi)
        return drawn if self.aspect_deg is None else math.radians(self.aspect_deg)


@dataclass(frozen=True, slots=True, eq=False)
class SimTerrain:
    """A realised terrain: its spec, the DEM grid (the truth) and the elevation of the take-off at the origin."""

    spec: TerrainSpec
    grid: ElevationGrid
    takeoff_elevation_m: float

    @property
    def terrain(self) -> Terrain:
        """For `shared.geo`'s terrain=: heights above the take-off at the origin."""
        return Terrain(self.grid, self.takeoff_elevation_m)

    def up_world_m(self, east_m: ArrayLike, north_m: ArrayLike) -> NDArray[np.float64]:
        """Ground height above the take-off at world-local east/north metres (NaN off the DEM)."""
        half, cell = 0.5 * self.spec.extent_m, self.spec.cell_m
        e = np.asarray(east_m, dtype=np.float64)
        n = np.asarray(north_m, dtype=np.float64)
        return self.grid.at_grid((e + half) / cell, (half - n) / cell) - self.takeoff_elevation_m

    def facts(self) -> dict[str, float | str]:
        """What truth.json records of it."""
        low, high = float(np.nanmin(self.grid.heights_m)), float(np.nanmax(self.grid.heights_m))
        return {"kind": self.spec.kind, "takeoff_elevation_m": round(self.takeoff_elevation_m, 4),
                "min_elevation_m": round(low, 3), "max_elevation_m": round(high, 3), "dem": "dem.npz"}

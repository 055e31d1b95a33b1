"""DEM files into `shared.terrain` (the `--dem FILE` of the commands that georeference): GeoTIFF and any raster
GDAL opens (through rasterio, the `dem` extra), SRTM .hgt tiles and our .npz (pure numpy).

`read_dem(path)` dispatches by extension; `load_terrain(path, takeoff_elevation_m)` makes the Terrain.
Errors are ValueErrors naming the file.
"""

from __future__ import annotations

import logging
import math
import re
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from agent.stage_report import StageReport
from shared.geo import Pose
from shared.terrain import ElevationGrid, Terrain

__all__ = ["DEM_SUFFIXES", "DemCoverage", "NPZ_FORMAT", "load_terrain", "read_dem", "read_hgt", "read_npz",
           "read_raster", "takeoff_terrain", "write_npz"]

#: Extensions read without rasterio; anything else goes to rasterio (GeoTIFF .tif/.tiff, .vrt, .img, ...).
DEM_SUFFIXES = (".hgt", ".npz")
NPZ_FORMAT = "uavmm-dem"
#: SRTM's void value.
HGT_VOID = -32768
log = logging.getLogger(__name__)
_HGT_NAME = re.compile(r"^([NS])(\d{2})([EW])(\d{3})$", re.IGNORECASE)
_RASTERIO_MISSING = ("reading {path} needs rasterio (GeoTIFF and the other GDAL rasters): "
                     "pip install 'uav-memory-maps[dem]' (or give an SRTM .hgt or a .npz DEM)")


def read_dem(path: str | Path) -> ElevationGrid:
    """The DEM in `path`: .hgt (SRTM), .npz (write_npz), else a raster through rasterio (GeoTIFF, ...)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"DEM file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".hgt":
        return read_hgt(path)
    if suffix == ".npz":
        return read_npz(path)
    return read_raster(path)


def load_terrain(path: str | Path, takeoff_elevation_m: float | None = None) -> Terrain:
    """Terrain of the DEM in `path` with the take-off's elevation (None: decided later, see
    `shared.terrain.Terrain`); logs the grid it read (INFO)."""
    grid = read_dem(path)
    log.info("DEM %s: %s", path, grid)
    return Terrain(grid, takeoff_elevation_m)


def takeoff_terrain(terrain: Terrain, pose: Pose) -> Terrain:
    """The terrain a video is georeferenced on, given its first pose: a terrain without a take-off elevation takes
    the DEM's height under that pose (telemetry heights are above take-off, and a video starts over the take-off's
    ground unless --takeoff-elevation-m says otherwise); one with it, or a pose off the DEM, is returned as it is
    (off the DEM, heights count from the ground below the UAV, frame by frame; logged)."""
    if terrain.takeoff_elevation_m is not None:
        return terrain
    elevation = float(terrain.height_at(pose.lat, pose.lon))
    if math.isfinite(elevation):
        log.info("terrain: take-off elevation %.1f m (the DEM under the video's first pose)", elevation)
        return terrain.with_takeoff_elevation(elevation)
    log.warning("terrain: the video's first pose (%.6f, %.6f) is off the DEM: heights are taken above the DEM under "
                "the UAV, frame by frame", pose.lat, pose.lon)
    return terrain


class DemCoverage:
    """Whether the DEM lies under the flight: counted per frame with a pose (the UAV's position on the grid or off
    it). A DEM of another place gives the boxes no ground point (no memory map, no size filter: the detector's
    boxes as they are), and a run finished without a word; now one warning when the UAV is off the DEM in each of
    the first `WARN_AFTER` frames, and the stage report says in how many frames it was over it."""

    WARN_AFTER = 10

    def __init__(self) -> None:
        self.on = self.off = 0
        self._warned = False

    def observe(self, terrain: Terrain | None, pose: Pose | None) -> None:
        """Count one frame (`DetectionPipeline.process` calls it once a frame; without a terrain or a pose: nothing)."""
        if terrain is None or pose is None:
            return
        if math.isfinite(float(terrain.height_at(pose.lat, pose.lon))):
            self.on += 1
            return
        self.off += 1
        if not self._warned and self.on == 0 and self.off >= self.WARN_AFTER:
            self._warned = True
            lat0, lat1, lon0, lon1 = terrain.grid.bounds()
            log.warning("terrain: the UAV is off the DEM in each of the first %d frames (at %.6f, %.6f; the DEM spans "
                        "lat %.6f .. %.6f, lon %.6f .. %.6f): boxes seen off it get no ground point (no memory map, "
                        "no size filter for them); is it this flight's DEM?", self.off, pose.lat, pose.lon, lat0, lat1,
                        lon0, lon1)

    def report(self) -> StageReport:
        """The run's terrain stage: acted where the UAV was over the DEM."""
        why = f"UAV over the DEM in {self.on} of {self.on + self.off} frames"
        return StageReport("terrain", self.on > 0, why if self.on else why + " (another place's DEM?)")


def read_hgt(path: str | Path) -> ElevationGrid:
    """An SRTM tile: big-endian int16, 1201 x 1201 (3 arc-seconds) or 3601 x 3601 (1 arc-second) samples, named
    after its south-west corner (N47E009.hgt: 47..48 N, 9..10 E); row 0 is the northern edge, samples on the
    whole-degree lines. Voids (-32768) become NaN."""
    path = Path(path)
    match = _HGT_NAME.match(path.name.split(".")[0])
    if match is None:
        raise ValueError(f"SRTM file {path}: the name must give the tile's south-west corner like N47E009.hgt")
    ns, lat, ew, lon = match.groups()
    south = int(lat) * (1 if ns.upper() == "N" else -1)
    west = int(lon) * (1 if ew.upper() == "E" else -1)
    raw = np.fromfile(path, dtype=">i2")
    side = math.isqrt(len(raw))
    if side * side != len(raw) or side not in (1201, 3601):
        raise ValueError(f"SRTM file {path}: {len(raw)} samples, not 1201 x 1201 or 3601 x 3601")
    heights = raw.reshape(side, side).astype(np.float64)
    heights[raw.reshape(side, side) == HGT_VOID] = np.nan
    step = 1.0 / (side - 1)
    try:
        return ElevationGrid(heights, lat0_deg=south + 1.0, lon0_deg=float(west), lat_step_deg=-step,
                             lon_step_deg=step)
    except ValueError as exc:
        raise ValueError(f"SRTM file {path}: {exc}") from None


def write_npz(path: str | Path, grid: ElevationGrid) -> None:
    """The grid as .npz: heights_m (float32 when that keeps every height to the millimetre, else float64),
    lat0_deg, lon0_deg, lat_step_deg, lon_step_deg and format "uavmm-dem", version 1."""
    heights = grid.heights_m
    small = heights.astype(np.float32)
    exact = np.allclose(small, heights, atol=5e-4, equal_nan=True)
    np.savez_compressed(Path(path), heights_m=small if exact else heights, lat0_deg=grid.lat0_deg,
                        lon0_deg=grid.lon0_deg, lat_step_deg=grid.lat_step_deg, lon_step_deg=grid.lon_step_deg,
                        format=NPZ_FORMAT, version=1)


#: What zipfile, zlib and numpy's .npy header parser raise on a damaged archive, besides OSError and ValueError
#: (zipfile's NotImplementedError: an entry asking for a newer zip version or an unknown compression).
_DAMAGED_ZIP = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, tokenize.TokenError, SyntaxError)


def read_npz(path: str | Path) -> ElevationGrid:
    """A DEM written by write_npz."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            if f.read(4) != b"PK\x03\x04":  # numpy took any other bytes for a pickle and said so, confusingly
                raise ValueError(f"not a .npz archive (a zip; {NPZ_FORMAT} writes one)")
        with np.load(path, allow_pickle=False) as data:
            if str(data.get("format", "")) != NPZ_FORMAT:
                raise ValueError(f"not a {NPZ_FORMAT} file (no format field)")
            fields = {k: data[k] for k in ("heights_m", "lat0_deg", "lon0_deg", "lat_step_deg", "lon_step_deg")}
    except KeyError as exc:
        raise ValueError(f"DEM file {path}: missing field {exc}") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"DEM file {path}: {exc}") from None
    except _DAMAGED_ZIP as exc:  # a damaged archive: zipfile, zlib and numpy's header parser raise their own
        raise ValueError(f"DEM file {path}: a damaged .npz archive ({type(exc).__name__}: {exc})") from None
    try:
        return ElevationGrid(np.asarray(fields["heights_m"], dtype=np.float64),
                             **{k: float(v) for k, v in fields.items() if k != "heights_m"})
    except (TypeError, ValueError) as exc:
        raise ValueError(f"DEM file {path}: {exc}") from None


def read_raster(path: str | Path, band: int = 1) -> ElevationGrid:
    """One band of a raster GDAL opens (GeoTIFF, VRT, ...), in metres. A geographic, north-up raster is taken
    as it is; any other CRS (UTM, national grids) or a rotated one is resampled (bilinear) onto a lat/lon grid
    of about the same resolution, since the terrain is looked up by lat/lon. nodata and masked samples
    become NaN; a band's scale and offset are applied."""
    path = Path(path)
    try:
        import rasterio
        from rasterio.warp import Resampling, calculate_default_transform, reproject
    except ImportError:
        raise ValueError(_RASTERIO_MISSING.format(path=path)) from None
    try:
        with rasterio.open(path) as ds:
            if ds.crs is None:
                raise ValueError("the raster has no coordinate reference system")
            if not 1 <= band <= ds.count:
                raise ValueError(f"band {band} does not exist (the raster has {ds.count})")
            data = ds.read(band, masked=True).astype(np.float64)
            heights = np.ma.filled(data, np.nan) * ds.scales[band - 1] + ds.offsets[band - 1]
            transform, crs = ds.transform, ds.crs
            if not crs.is_geographic or transform.b != 0 or transform.d != 0:
                dst_crs = "EPSG:4326"
                dst_transform, width, height = calculate_default_transform(crs, dst_crs, ds.width, ds.height,
                                                                           *ds.bounds)
                out = np.full((height, width), np.nan)
                reproject(heights, out, src_transform=transform, src_crs=crs, src_nodata=np.nan,
                          dst_transform=dst_transform, dst_crs=dst_crs, dst_nodata=np.nan,
                          resampling=Resampling.bilinear)
                heights, transform = out, dst_transform
    except rasterio.errors.RasterioError as exc:
        raise ValueError(f"DEM file {path}: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"DEM file {path}: {exc}") from None
    if transform.a < 0:  # columns east to west: flip them
        heights = heights[:, ::-1]
        transform = transform @ rasterio.Affine.translation(heights.shape[1], 0) @ rasterio.Affine.scale(-1, 1)
    try:
        # sample points at the pixels' centres (GDAL's transform gives the corners)
        return ElevationGrid(heights, lat0_deg=transform.f + transform.e / 2, lon0_deg=transform.c + transform.a / 2,
                             lat_step_deg=transform.e, lon_step_deg=transform.a)
    except ValueError as exc:
        raise ValueError(f"DEM file {path}: {exc}") from None

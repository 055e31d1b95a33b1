"""DEM files (agent.dem): GeoTIFF through rasterio (geographic and projected), SRTM .hgt tiles, our .npz."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent.dem import HGT_VOID, load_terrain, read_dem, read_hgt, read_npz, write_npz
from shared.terrain import ElevationGrid

rasterio = pytest.importorskip("rasterio")


def origin(west, north, dx, dy):
    """GDAL's transform of a north-up raster (rasterio.transform.from_origin, without its deprecated `*`)."""
    return rasterio.Affine.translation(west, north) @ rasterio.Affine.scale(dx, -dy)


def write_geotiff(path, heights, transform, crs, nodata=None):
    with rasterio.open(path, "w", driver="GTiff", height=heights.shape[0], width=heights.shape[1], count=1,
                       dtype="float32", crs=crs, transform=transform, nodata=nodata) as ds:
        ds.write(heights.astype(np.float32), 1)


def test_a_geographic_geotiff_is_read_at_its_pixel_centres_with_nodata_as_nan(tmp_path):
    heights = np.arange(12, dtype=float).reshape(3, 4) * 10.0
    heights[2, 3] = -9999.0
    path = tmp_path / "dem.tif"
    write_geotiff(path, heights, origin(9.0, 47.003, 0.001, 0.001), "EPSG:4326",
                  nodata=-9999.0)
    grid = read_dem(path)
    assert grid.shape == (3, 4)
    assert grid.height_at(47.0025, 9.0005) == pytest.approx(0.0)  # centre of the north-west pixel
    assert grid.height_at(47.0015, 9.0025) == pytest.approx(60.0)  # row 1, column 2
    assert grid.height_at(47.0020, 9.0010) == pytest.approx(np.mean([0.0, 10.0, 40.0, 50.0]))  # between four
    assert np.isnan(grid.height_at(47.0005, 9.0035))  # the nodata pixel
    assert np.isnan(grid.height_at(47.0028, 9.0005))  # north of the first row of centres


def test_a_projected_geotiff_is_resampled_to_lat_lon(tmp_path):
    from rasterio.warp import transform as warp

    # UTM 32N around (47.67 N, 9.27 E), 2 m pixels, a plane rising 0.1 m per metre east and 0.05 north
    x0, y0 = warp("EPSG:4326", "EPSG:32632", [9.26], [47.675])
    xs = x0[0] + 2.0 * (np.arange(400) + 0.5)
    ys = y0[0] - 2.0 * (np.arange(400) + 0.5)
    xx, yy = np.meshgrid(xs, ys)
    plane = 400.0 + 0.1 * (xx - x0[0]) + 0.05 * (yy - y0[0])
    path = tmp_path / "utm.tif"
    write_geotiff(path, plane, origin(x0[0], y0[0], 2.0, 2.0), "EPSG:32632")
    grid = read_dem(path)
    lats = np.array([47.670, 47.672, 47.668])
    lons = np.array([9.265, 9.270, 9.268])
    ux, uy = warp("EPSG:4326", "EPSG:32632", lons.tolist(), lats.tolist())
    expected = 400.0 + 0.1 * (np.array(ux) - x0[0]) + 0.05 * (np.array(uy) - y0[0])
    np.testing.assert_allclose(grid.height_at(lats, lons), expected, atol=0.05)


def test_srtm_tiles_by_name_with_voids(tmp_path):
    side = 1201
    tile = np.zeros((side, side), dtype=">i2")
    tile[0, 0] = 500  # north-west corner: 48 N, 9 E
    tile[side - 1, side - 1] = 300  # south-east corner: 47 N, 10 E
    tile[600, 600] = HGT_VOID
    path = tmp_path / "N47E009.hgt"
    tile.tofile(path)
    grid = read_hgt(path)
    assert grid.height_at(48.0, 9.0) == pytest.approx(500.0)
    assert grid.height_at(47.0, 10.0) == pytest.approx(300.0)
    assert np.isnan(grid.height_at(47.5, 9.5))
    assert grid.bounds() == pytest.approx((47.0, 48.0, 9.0, 10.0))
    south_west = tmp_path / "s12w077.hgt"
    np.zeros((side, side), dtype=">i2").tofile(south_west)
    assert read_dem(south_west).bounds() == pytest.approx((-12.0, -11.0, -77.0, -76.0))


@pytest.mark.parametrize(("name", "size", "match"), [
    ("N47E009.hgt", 1000, "1201 x 1201"),
    ("tile.hgt", 1201 * 1201, "N47E009"),
])
def test_bad_srtm_files_are_refused_naming_the_file(tmp_path, name, size, match):
    path = tmp_path / name
    np.zeros(size, dtype=">i2").tofile(path)
    with pytest.raises(ValueError, match=match) as info:
        read_dem(path)
    assert name in str(info.value)


def test_npz_round_trip_and_bad_files(tmp_path):
    grid = ElevationGrid(np.array([[1.25, 2.5], [np.nan, 4.0]]), lat0_deg=47.001, lon0_deg=9.0,
                         lat_step_deg=-0.001, lon_step_deg=0.001)
    path = tmp_path / "dem.npz"
    write_npz(path, grid)
    back = read_npz(path)
    np.testing.assert_array_equal(back.heights_m, grid.heights_m)
    assert (back.lat0_deg, back.lon0_deg, back.lat_step_deg, back.lon_step_deg) == (47.001, 9.0, -0.001, 0.001)
    np.savez(tmp_path / "other.npz", heights=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="other.npz"):
        read_dem(tmp_path / "other.npz")
    with pytest.raises(ValueError, match="does not exist"):
        read_dem(tmp_path / "missing.tif")
    (tmp_path / "junk.tif").write_text("not a raster")
    with pytest.raises(ValueError, match="junk.tif"):
        read_dem(tmp_path / "junk.tif")
    # text named .npz: numpy's "pickled (object) data ... allow_pickle" message (the contract audit, 1 Dec 2026)
    (tmp_path / "junk.npz").write_text("garbage\n")
    with pytest.raises(ValueError, match=r"DEM file .*junk\.npz: not a \.npz archive"):
        read_dem(tmp_path / "junk.npz")


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=4), st.integers(0, 16))
def test_a_damaged_npz_is_a_grid_or_a_value_error_naming_the_file(tmp_path, flips, cut_16ths):
    """Fuzzing (1 Dec 2026): bytes flipped or cut in a written .npz raised zipfile.BadZipFile, zlib.error, EOFError,
    NotImplementedError ("zip file version") or tokenize.TokenError (numpy's header parser): tracebacks from the
    CLI's --dem; now ValueError naming the file."""
    path = tmp_path / "dem.npz"
    write_npz(path, ElevationGrid(np.arange(12.0).reshape(3, 4), lat0_deg=47.001, lon0_deg=9.0,
                                  lat_step_deg=-0.001, lon_step_deg=0.001))
    data = bytearray(path.read_bytes())
    for at, value in flips:
        data[at % len(data)] = value
    path.write_bytes(bytes(data[:len(data) * cut_16ths // 16]))
    try:
        read_npz(path)
    except ValueError as exc:
        assert "dem.npz" in str(exc)


def test_load_terrain_carries_the_takeoff_elevation(tmp_path):
    path = tmp_path / "dem.npz"
    write_npz(path, ElevationGrid(np.full((2, 2), 100.0), lat0_deg=47.001, lon0_deg=9.0, lat_step_deg=-0.001,
                                  lon_step_deg=0.001))
    terrain = load_terrain(path, 95.0)
    assert terrain.takeoff_elevation_m == 95.0 and terrain.grid.shape == (2, 2)
    assert load_terrain(path).takeoff_elevation_m is None


@pytest.mark.parametrize(("telemetry", "given", "expected"), [
    ("flight.klv", {}, (0.0, 0.0)),                           # both unset: MSL altitudes on the DEM's datum
    ("klv", {}, (0.0, 0.0)),                                  # the KLV inside the video
    ("hae.klv", {}, (None, None)),                            # ellipsoid heights only: metres off the geoid, left
    ("flight.klv", {"height_m": 40.0}, (None, None)),         # --height-m: above the take-off, as given
    ("flight.klv", {"takeoff_elevation_m": 0.0}, (None, 0.0)),  # one alone: a warning
    ("flight.srt", {}, (None, None)),                         # not KLV: heights above take-off, as always
])
def test_klv_heights_on_a_dem_are_altitudes_above_sea_level(tmp_path, caplog, telemetry, given, expected):
    """ST 0601's heights without an offset are above the frame centre's ground; the DEM counted them from the
    take-off elevation under the first pose (13.7 m off on a 20 % slope in a probe)."""
    import argparse

    from tests.shared.klv_writer import FULL_FIELDS, packet, write_ts
    from uavmm.cli import terrain_from_args

    path = tmp_path / "dem.npz"
    write_npz(path, ElevationGrid(np.full((2, 2), 100.0), lat0_deg=47.001, lon0_deg=9.0, lat_step_deg=-0.001,
                                  lon_step_deg=0.001))
    t0 = 1_717_236_000.0
    (tmp_path / "flight.klv").write_bytes(b"".join(packet(t0 + 0.1 * i, FULL_FIELDS) for i in range(3)))
    hae = {k: v for k, v in FULL_FIELDS.items() if k not in ("sensor_alt_msl_m", "frame_center_elevation_m")}
    (tmp_path / "hae.klv").write_bytes(b"".join(packet(t0 + 0.1 * i, {**hae, "sensor_hae_m": 560.0,
                                                                      "frame_center_hae_m": 520.0}) for i in range(3)))
    (tmp_path / "video.ts").write_bytes(write_ts([(90_000 + 9_000 * i, packet(t0 + 0.1 * i, FULL_FIELDS))
                                                  for i in range(3)], video_pts=[90_000]))
    args = argparse.Namespace(**{"dem": path, "takeoff_elevation_m": None, "height_offset_m": None, "height_m": None,
                                 "video": tmp_path / "video.ts",
                                 "telemetry": telemetry if telemetry == "klv" else tmp_path / telemetry, **given})
    with caplog.at_level("INFO", logger="uavmm"):
        terrain = terrain_from_args(args)
    assert (args.height_offset_m, args.takeoff_elevation_m) == expected
    assert terrain.takeoff_elevation_m == expected[1]
    assert ("--takeoff-elevation-m alone" in caplog.text) == ("takeoff_elevation_m" in given)


def test_a_npz_needing_a_newer_zip_version_is_a_value_error_naming_the_file(tmp_path):
    """zipfile raises NotImplementedError ("zip file version") for an entry that asks for a newer extractor: read_npz
    turns it into a ValueError naming the file (the fuzzing's reproducer, made deterministic)."""
    path = tmp_path / "dem.npz"
    write_npz(path, ElevationGrid(np.arange(12.0).reshape(3, 4), lat0_deg=47.001, lon0_deg=9.0,
                                  lat_step_deg=-0.001, lon_step_deg=0.001))
    data = bytearray(path.read_bytes())
    central = data.find(b"PK\x01\x02")  # the first central directory entry; its "version needed" at offset 6
    assert central > 0
    data[central + 6:central + 8] = (99).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"dem\.npz: a damaged \.npz archive \(NotImplementedError"):
        read_npz(path)

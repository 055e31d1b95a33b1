"""The anomaly layer on a terrain (`--dem`): heat mapped onto the DEM's surface, cells hidden by the terrain left
out, a flat DEM giving the flat layer (agent.anomaly.ground, agent.anomaly.terrain_view)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agent.anomaly import AnomalyConfig, AnomalyDetector, AnomalyMap, AnomalyMapConfig
from agent.anomaly.ground import footprint_means, spread_footprints
from agent.anomaly.terrain_view import TerrainCells, terrain_cut_row, terrain_view
from shared.geo import Camera, Pose, ground_to_image_homography, latlon_to_local, local_to_latlon, local_to_pixel
from shared.terrain import ElevationGrid, Terrain

CAM = Camera(width=640, height=360, fx=450.0, fy=450.0, cx=320.0, cy=180.0)
LAT, LON = 47.6, 9.3
TAKEOFF_M = 300.0
HEAT = (180, 320)


def _grid(heights_of) -> ElevationGrid:
    """A 1 m DEM of +-150 m about (LAT, LON); heights_of(east, north) in metres above the take-off."""
    axis = np.arange(-150.0, 151.0)
    east, north = np.meshgrid(axis, axis[::-1])
    return ElevationGrid.from_local(TAKEOFF_M + heights_of(east, north), LAT, LON, west_m=-150.0, north_m=150.0,
                                    cell_m=1.0)


SLOPE = Terrain(_grid(lambda e, n: 0.3 * n), TAKEOFF_M)  # rises 0.3 m per metre northward
FLAT = Terrain(_grid(lambda e, n: 0.0 * n), TAKEOFF_M)
#: A ridge 8 m high across the view, 40 m north of the UAV (Gaussian profile, 4 m wide).
RIDGE = Terrain(_grid(lambda e, n: 8.0 * np.exp(-((n - 40.0) ** 2) / (2 * 4.0**2))), TAKEOFF_M)


def _pose(north_m: float = 0.0, height_m: float = 30.0, pitch_deg: float = 35.0, heading_deg: float = 0.0) -> Pose:
    lat, lon = local_to_latlon(0.0, north_m, LAT, LON)
    return Pose(lat=float(lat), lon=float(lon), height_m=height_m, pitch_deg=pitch_deg, heading_deg=heading_deg)


def _blob_at(east_m: float, north_m: float, pose: Pose, terrain: Terrain | None, sigma_px: float = 1.5
             ) -> np.ndarray:
    """A heatmap (HEAT, working scale = half the camera's) with a Gaussian hot spot where the ground point (east,
    north of LAT, LON; on the terrain's surface) appears."""
    lat, lon = local_to_latlon(east_m, north_m, LAT, LON)
    e, n = latlon_to_local(lat, lon, pose.lat, pose.lon)
    (u, v), = local_to_pixel(np.atleast_1d(e), np.atleast_1d(n), CAM, pose, terrain=terrain)[0] / 2
    yy, xx = np.mgrid[0:HEAT[0], 0:HEAT[1]]
    return np.exp(-((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2) / (2 * sigma_px**2)).astype(np.float32)


def _peak_ground(layer: AnomalyMap) -> tuple[float, float]:
    """East, north (m from LAT, LON) of the layer's hottest cell's centre."""
    values = layer.layer()
    assert values is not None
    r, c = np.unravel_index(np.argmax(values), values.shape)
    gx0, gy0 = layer.origin
    lat, lon = layer.grid.cell_to_latlon(gx0 + c + 0.5, gy0 + r + 0.5)
    e, n = latlon_to_local(lat, lon, LAT, LON)
    return float(e), float(n)


def _hot_north_extent_m(layer: AnomalyMap) -> float:
    """North-south extent (m) of the layer's cells at half its peak or more."""
    values = layer.layer()
    assert values is not None
    rows, cols = np.nonzero(values >= 0.5 * values.max())
    gx0, gy0 = layer.origin
    _, north = latlon_to_local(*layer.grid.cell_to_latlon(gx0 + cols + 0.5, gy0 + rows + 0.5), LAT, LON)
    return float(np.ptp(north))


def test_a_hot_spot_on_a_slope_lands_on_its_cell_with_the_terrain_and_far_beyond_it_without():
    """A spot 40 m ahead on a slope that has risen 12 m there, seen from 30 m above the take-off: the flat model
    runs its ray on to the take-off's level, dz / tan(depression) = 12 m / tan(24.2 deg) = 26.7 m too far (22.6 m
    after 30 frames of a UAV flying north at 9 m/s); on the terrain it is the spot's own cell. As the UAV flies, the
    flat model's point moves along the line of sight, and the flat layer smears the spot over metres."""
    spot = (3.0, 40.0)
    layers = {name: AnomalyMap(AnomalyMapConfig(max_range_m=200.0)) for name in ("terrain", "flat")}
    for i in range(30):
        pose = _pose(north_m=0.3 * i)
        heat = _blob_at(*spot, pose, SLOPE)  # what the camera sees: the spot where it is, on the slope
        layers["terrain"].update(heat, CAM, pose, i / 30, terrain=SLOPE)
        layers["flat"].update(heat, CAM, pose, i / 30)
    errors = {k: float(np.hypot(*np.subtract(_peak_ground(m), spot))) for k, m in layers.items()}
    assert errors["terrain"] <= 0.3  # within its 0.4 m cell (the centre is at most 0.28 m from any point of it)
    assert 20.0 < errors["flat"] < 27.0
    peak = {k: float(np.max(m.layer())) for k, m in layers.items()}
    assert peak["terrain"] > 1.5 * peak["flat"]  # measured 0.63 and 0.33
    assert _hot_north_extent_m(layers["terrain"]) <= 0.8 and _hot_north_extent_m(layers["flat"]) > 3.0  # 0.4, 5.2


def test_heat_on_the_terrain_comes_back_at_the_same_pixel():
    pose = _pose(height_m=25.0, pitch_deg=40.0, heading_deg=20.0)
    layer = AnomalyMap()
    heat = _blob_at(-4.0, 30.0, pose, SLOPE)
    for i in range(6):
        layer.update(heat, CAM, pose, i / 30, terrain=SLOPE)
    back = layer.image_scores(CAM, pose, HEAT, terrain=SLOPE)
    assert back.shape == HEAT and back.dtype == np.float32
    want = np.unravel_index(np.argmax(heat), HEAT)
    got = np.unravel_index(np.argmax(back), HEAT)
    assert abs(got[0] - want[0]) <= 1 and abs(got[1] - want[1]) <= 1


@pytest.mark.parametrize("pitch,heading", [(35.0, 20.0), (70.0, 200.0), (20.0, 100.0)])
def test_a_flat_dem_gives_the_flat_layer(pitch, heading):
    """A DEM at the take-off's elevation everywhere: the same cells are seen (but for the footprint's outline) and
    hold the same mean heat; the read-back differs by the footprint box spread instead of bilinear sampling."""
    rng = np.random.default_rng(0)
    heat = cv2.GaussianBlur(rng.random(HEAT).astype(np.float32), (0, 0), 2.0)
    heat = (heat - heat.min()) / np.ptp(heat)
    pose = _pose(height_m=30.0 if pitch < 60 else 50.0, pitch_deg=pitch, heading_deg=heading)
    out = {}
    for name, terrain in (("flat", None), ("dem", FLAT)):
        layer = AnomalyMap(AnomalyMapConfig(max_range_m=100.0))
        assert layer.update(heat, CAM, pose, 0.0, terrain=terrain)
        seen, _ = layer._sums.stored("anomaly_seen")
        out[name] = (layer.layer(), seen > 0, layer.image_scores(CAM, pose, HEAT, terrain=terrain))
    (flat, seen_flat, back_flat), (dem, seen_dem, back_dem) = out["flat"], out["dem"]
    assert (seen_flat ^ seen_dem).sum() <= 0.015 * seen_flat.sum()
    both = seen_flat & seen_dem
    inner = cv2.erode(both.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.abs(flat - dem)[both].mean() < 0.003 and np.abs(flat - dem)[inner].max() < 0.03
    mapped = back_flat > 0
    assert np.abs(back_flat - back_dem)[mapped].mean() < 0.006
    assert np.percentile(np.abs(back_flat - back_dem)[mapped], 99) < 0.05


def _candidates_and_truth(terrain: Terrain, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The window cells of a frame (a view without the viewshed), the view's seen cells on the same block, and
    which of them exact ray casting (`Terrain.intersect_rays` aimed at each cell's centre) sees."""
    import agent.anomaly.terrain_view as tv

    layer = AnomalyMap()
    layer._sums.advance(0.0, pose.lat, pose.lon)
    a = layer._cell_to_local(pose)
    cells = TerrainCells(terrain.grid)
    args = (CAM, pose, terrain, cells, a, layer.size_cells, 0.4, 120.0, 3.0)
    view = terrain_view(*args)
    hidden_by_terrain = tv.hidden_by_terrain
    try:
        tv.hidden_by_terrain = lambda east, *rest: np.zeros(len(east), bool)
        everything = terrain_view(*args)
    finally:
        tv.hidden_by_terrain = hidden_by_terrain
    assert view is not None and everything is not None
    c0, r0, c1, r1 = everything.block
    seen = np.zeros_like(everything.valid)
    vc0, vr0, vc1, vr1 = view.block
    seen[vr0 - r0:vr1 - r0, vc0 - c0:vc1 - c0] = view.valid
    cc, rr = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
    east, north = a[0, 0] * cc + a[0, 1] * rr + a[0, 2], a[1, 0] * cc + a[1, 1] * rr + a[1, 2]
    rel = np.stack([east.ravel(), north.ravel(), terrain.up_m(east, north, pose).ravel() - pose.height_m], 1)
    dist = np.linalg.norm(rel, axis=1)
    he, hn, hu, hit = terrain.intersect_rays(rel / dist[:, None], pose)
    to_hit = np.sqrt(he**2 + hn**2 + (hu - pose.height_m) ** 2)
    truth = (hit & (to_hit > dist - 0.02 - 1e-3 * dist)).reshape(cc.shape)
    return everything.valid, seen, truth


def test_cells_behind_a_ridge_are_not_seen():
    """From 15 m above the take-off, a ridge 8 m high 40 m ahead hides the ground behind it; the viewshed agrees
    with exact ray casting on all but the hidden region's edge cells."""
    pose = _pose(height_m=15.0, pitch_deg=20.0)
    candidates, seen, truth = _candidates_and_truth(RIDGE, pose)
    hidden = candidates & ~truth
    assert hidden.sum() > 2000  # the ridge hides a lot
    assert not (seen & hidden & ~cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)).any()
    disagree = (seen != truth) & candidates
    assert disagree.sum() <= 0.005 * candidates.sum()
    assert (seen & ~truth).sum() <= 0.02 * hidden.sum()  # missed hidden cells: at its edges
    # without the ridge every one of them is seen
    flat_candidates, flat_seen, _ = _candidates_and_truth(FLAT, pose)
    assert (flat_seen == flat_candidates).all()


def test_heat_on_the_ridge_stays_on_the_ridge():
    """A hot spot on the ridge's crest: the ground behind it along the same rays is hidden and gets nothing."""
    pose = _pose(height_m=15.0, pitch_deg=20.0)
    layer = AnomalyMap()
    layer.update(_blob_at(0.0, 40.0, pose, RIDGE), CAM, pose, 0.0, terrain=RIDGE)
    e, n = _peak_ground(layer)
    assert abs(e) < 0.5 and abs(n - 40.0) < 1.0
    values = layer.layer()
    assert values is not None
    gx0, gy0 = layer.origin
    east, north = latlon_to_local(*layer.grid.cell_to_latlon(gx0 + np.arange(values.shape[1]) + 0.5,
                                                             gy0 + np.full(values.shape[1], values.shape[0] // 2)
                                                             + 0.5), LAT, LON)
    # cells on the ground 45-60 m ahead (behind the crest along the spot's rays) stay cold
    _, layer_north = latlon_to_local(*layer.grid.cell_to_latlon(np.full(values.shape[0], gx0 + 0.5),
                                                                gy0 + np.arange(values.shape[0]) + 0.5), LAT, LON)
    col = int(np.argmin(np.abs(east)))
    behind = (layer_north > 45.0) & (layer_north < 60.0)
    assert values[behind, col - 2:col + 3].max() < 0.05 * values.max()


def test_the_projection_is_local_to_pixel_on_the_terrain_and_takes_the_registration_as_an_image_correction():
    pose = _pose(height_m=20.0, pitch_deg=30.0, heading_deg=15.0)
    layer = AnomalyMap()
    layer._sums.advance(0.0, pose.lat, pose.lon)
    a = layer._cell_to_local(pose)
    cells = TerrainCells(RIDGE.grid)
    view = terrain_view(CAM, pose, RIDGE, cells, a, layer.size_cells, 0.4, 120.0, 3.0)
    assert view is not None
    c0, r0, c1, r1 = view.block
    cc, rr = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
    east = (a[0, 0] * cc + a[0, 1] * rr + a[0, 2])[view.valid]
    north = (a[1, 0] * cc + a[1, 1] * rr + a[1, 2])[view.valid]
    uv, ok = local_to_pixel(east, north, CAM, pose, terrain=RIDGE)
    assert ok.all() and np.abs(view.uv - uv).max() < 0.01
    assert view.cut_row == int(np.floor(uv[:, 1].min()))
    # the registration's placement as the pose's own homography changes nothing; a shifted one shifts the cells
    same = terrain_view(CAM, pose, RIDGE, cells, a, layer.size_cells, 0.4, 120.0, 3.0,
                        ground_to_image_homography(CAM, pose))
    assert same is not None and np.abs(same.uv - view.uv).max() < 0.01
    shift = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])
    moved = terrain_view(CAM, pose, RIDGE, cells, a, layer.size_cells, 0.4, 120.0, 3.0,
                         shift @ ground_to_image_homography(CAM, pose))
    assert moved is not None
    # the cells seen in both views moved by (3, -2) pixels
    mc0, mr0, _, _ = moved.block
    before = {(i + r0, j + c0): k for k, (i, j) in enumerate(zip(*np.nonzero(view.valid), strict=True))}
    pairs = [(before[(i + mr0, j + mc0)], k) for k, (i, j) in enumerate(zip(*np.nonzero(moved.valid), strict=True))
             if (i + mr0, j + mc0) in before]
    assert len(pairs) > 1000
    old_k, new_k = np.array(pairs).T
    assert np.abs(moved.uv[new_k] - view.uv[old_k] - [3.0, -2.0]).max() < 0.01


def test_footprint_means_is_the_box_mean_and_spread_footprints_paints_the_boxes():
    rng = np.random.default_rng(4)
    image = rng.random((40, 60)).astype(np.float32)
    u = np.array([10.3, 30.0, 45.7, 5.2])
    v = np.array([12.6, 20.0, 33.1, 3.3])
    kx = np.array([5.0, 3.0, 1.0, 2.2])
    ky = np.array([3.0, 4.0, 0.5, 1.0])
    means = footprint_means(image, u, v, kx, ky)
    for i in (0, 1, 3):  # boxes of two pixels or more: the mean over the box's pixels
        x0, x1 = int(np.rint(u[i] - kx[i] / 2)), int(np.rint(u[i] + kx[i] / 2))
        y0, y1 = int(np.rint(v[i] - max(ky[i], 1) / 2)), int(np.rint(v[i] + max(ky[i], 1) / 2))
        assert means[i] == pytest.approx(image[y0:y1, x0:x1].mean(), rel=1e-5)
    # a cell smaller than a pixel: bilinear between the pixel centres about (45.7, 33.1), i.e. at (45.2, 32.6)
    top = image[32, 45] * 0.8 + image[32, 46] * 0.2
    bottom = image[33, 45] * 0.8 + image[33, 46] * 0.2
    assert means[2] == pytest.approx(top * 0.4 + bottom * 0.6, abs=0.02)  # OpenCV's weights are in 1/32
    painted = spread_footprints((40, 60), np.array([10.0, 13.0]), np.array([10.0, 10.0]), np.array([4.0, 4.0]),
                                np.array([2.0, 2.0]), np.array([1.0, 0.5], np.float32))
    assert painted[9, 8] == 1.0 and painted[9, 14] == 0.5 and painted[9, 11] == pytest.approx(0.75)
    assert painted[20, 20] == 0.0 and painted[12, 10] == 0.0


def test_the_detector_cuts_at_the_terrains_first_mapped_row_and_takes_the_takeoff_from_the_first_pose():
    """Terrain(grid, None): each video takes the DEM's height under its first pose as the take-off's (as the
    detection pipeline does); the cut row is the first row that shows a mapped cell of the terrain, in both modes
    (the per-frame baseline has no window and cuts on a lattice about the UAV). Looking up the slope, that is the
    horizon margin's row (84: 3 deg below the horizontal), far above the flat ground's 120 m row (136)."""
    from agent.anomaly.ground import cut_row

    unset = Terrain(SLOPE.grid, None)
    rng = np.random.default_rng(2)
    frame = np.clip(90 + rng.normal(0, 20, (360, 640, 3)), 0, 255).astype(np.uint8)
    pose = _pose(north_m=10.0, height_m=20.0, pitch_deg=15.0)  # 3 m above the take-off's ground at the origin
    rows = {}
    for memory in (True, False):
        det = AnomalyDetector(AnomalyConfig(method="mean", terrain=unset, use_memory=memory))
        out = det.process(frame, pose, 0.0, CAM)
        terrain = det.terrain_for(pose)
        assert terrain is not None and terrain.takeoff_elevation_m == pytest.approx(TAKEOFF_M + 3.0, abs=1e-6)
        rows[memory] = out.cut_row
        first = int(np.ceil(out.cut_row / 2))
        assert out.scores[:first].max() == 0.0 and out.scores[first:].max() > 0.0
        det.reset()
        assert det._terrain is None
    cells = TerrainCells(SLOPE.grid)
    cut = terrain_cut_row(CAM, pose, SLOPE.with_takeoff_elevation(TAKEOFF_M + 3.0), cells, 0.4, 120.0, 3.0)
    assert abs(rows[False] - cut) <= 1 and abs(rows[True] - cut) <= 1
    assert abs(cut - 84) <= 1 and cut_row(CAM, pose, 120.0, 3.0) == 136
    with pytest.raises(ValueError, match="AnomalyConfig.terrain"):
        AnomalyConfig(terrain="dem.npz")  # type: ignore[arg-type]

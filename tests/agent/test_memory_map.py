"""Memory map and detection pipeline: boosting order, per-class maps, window, forgetting, joint layer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.memory_map import JointLayer, MemoryMap, MemoryMapConfig
from agent.pipeline import DetectionPipeline
from agent.pipeline_config import PipelineConfig
from shared.geo import Camera, Pose, latlon_to_pixel, local_to_latlon
from shared.tiles import TileGrid

LAT, LON = 48.0, 9.0
GRID = TileGrid()
CAM = Camera(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)
CLASSES = {1: "person", 2: "swimmer"}


def cell_of(east_m: float, north_m: float, lat0: float = LAT, lon0: float = LON):
    lat, lon = local_to_latlon(east_m, north_m, lat0, lon0)
    return GRID.latlon_to_cell(lat, lon)


# ----------------------------------------------------------------------------- MemoryMap

def test_stamp_peak_equals_amplitude_and_is_truncated_at_radius():
    mm = MemoryMap(MemoryMapConfig(radius_m=6.0))
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(0.0, 0.0)
    mm.add("person", [gx], [gy], [0.3])
    assert mm.values_at("person", [gx], [gy])[0] == pytest.approx(0.3, rel=1e-5)
    # Falls off with distance, nothing beyond the radius (square truncation: check along an axis).
    near = mm.values_at("person", *cell_of(3.0, 0.0))[0]
    far = mm.values_at("person", *cell_of(8.0, 0.0))[0]
    assert 0.0 < near < 0.3
    assert far == 0.0


def test_map_is_clipped_at_one():
    mm = MemoryMap(MemoryMapConfig(stamp="sum"))
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(5.0, 5.0)
    mm.add("person", [gx] * 50, [gy] * 50, [0.9] * 50)
    assert mm.values_at("person", [gx], [gy])[0] == pytest.approx(1.0)
    assert mm.layer("person").max() <= 1.0


def test_max_stamping_counts_a_cluster_once_sum_stamping_adds_it_up():
    gx, gy = cell_of(5.0, 5.0)
    values = {}
    for stamp in ("max", "sum"):
        mm = MemoryMap(MemoryMapConfig(stamp=stamp))
        mm.advance(0.0, LAT, LON)
        mm.add("person", [gx] * 5, [gy] * 5, [0.1, 0.05, 0.1, 0.02, 0.03])
        values[stamp] = mm.values_at("person", [gx], [gy])[0]
    assert values["max"] == pytest.approx(0.1, rel=1e-5)
    assert values["sum"] == pytest.approx(0.3, rel=1e-5)


def test_one_map_per_class():
    mm = MemoryMap()
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(0.0, 10.0)
    mm.add("person", [gx], [gy], [0.5])
    assert mm.values_at("person", [gx], [gy])[0] > 0.4
    assert mm.values_at("swimmer", [gx], [gy])[0] == 0.0
    assert mm.classes == ["person"]


@pytest.mark.parametrize("dt", [1 / 30, 0.5, 2.0])
def test_decay_follows_elapsed_time_not_calls(dt):
    cfg = MemoryMapConfig(half_life_s=1.0)
    mm = MemoryMap(cfg)
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(0.0, 0.0)
    mm.add("person", [gx], [gy], [0.8])
    mm.advance(dt, LAT, LON)
    assert mm.values_at("person", [gx], [gy])[0] == pytest.approx(0.8 * 0.5**dt, rel=1e-5)
    # One call after a long gap decays as much as many small steps.
    mm2 = MemoryMap(cfg)
    mm2.advance(0.0, LAT, LON)
    mm2.add("person", [gx], [gy], [0.8])
    for k in range(1, 31):
        mm2.advance(dt * k / 30, LAT, LON)
    assert mm2.values_at("person", [gx], [gy])[0] == pytest.approx(0.8 * 0.5**dt, rel=1e-4)


def test_window_moves_with_uav_and_forgets_what_leaves():
    cfg = MemoryMapConfig(window_m=100.0, recentre_m=5.0, half_life_s=1e6)
    mm = MemoryMap(cfg)
    mm.advance(0.0, LAT, LON)
    behind = cell_of(0.0, -30.0)   # will leave the window
    ahead = cell_of(0.0, 40.0)     # will stay
    mm.add("person", [behind[0], ahead[0]], [behind[1], ahead[1]], [0.5, 0.5])
    # Fly 60 m north in small steps.
    for k in range(1, 61):
        lat, lon = local_to_latlon(0.0, float(k), LAT, LON)
        mm.advance(k * 0.1, float(lat), float(lon))
    assert mm.values_at("person", [ahead[0]], [ahead[1]])[0] == pytest.approx(0.5, rel=1e-4)
    assert mm.values_at("person", [behind[0]], [behind[1]])[0] == 0.0
    # Even flying back does not bring forgotten evidence back.
    for k in range(59, -1, -1):
        lat, lon = local_to_latlon(0.0, float(k), LAT, LON)
        mm.advance(10 + (60 - k) * 0.1, float(lat), float(lon))
    assert mm.values_at("person", [behind[0]], [behind[1]])[0] == 0.0


def test_window_edge_matches_config():
    mm = MemoryMap(MemoryMapConfig(window_m=300.0))
    mm.advance(0.0, LAT, LON)
    assert mm.size_cells * mm.cell_m == pytest.approx(300.0, abs=mm.cell_m)
    assert mm.cell_m == pytest.approx(0.597 * math.cos(math.radians(LAT)), rel=1e-3)


def test_add_before_advance_is_an_error():
    with pytest.raises(RuntimeError, match="advance"):
        MemoryMap().add("person", [0], [0], [1.0])


def test_tiles_carry_the_window_values():
    mm = MemoryMap(MemoryMapConfig(window_m=300.0))
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(20.0, -15.0)
    mm.add("person", [gx], [gy], [0.7])
    tiles = mm.tiles("person")
    assert 4 <= len(tiles) <= 16
    n = GRID.n
    tx, ty = int(gx) // n, int(gy) // n
    (tile,) = [t for x, y, t in tiles if (x, y) == (tx, ty)]
    assert tile[int(gy) - ty * n, int(gx) - tx * n] == pytest.approx(0.7, rel=1e-5)
    assert sum(float(t.sum()) for _, _, t in tiles) == pytest.approx(float(mm.layer("person").sum()), rel=1e-5)
    assert len(mm.tiles("person", min_value=0.1)) in (1, 2, 4)


@settings(max_examples=30, deadline=None)
@given(e=st.floats(-140, 140), nn=st.floats(-140, 140), amp=st.floats(0.01, 1.0))
def test_values_round_trip_through_add(e, nn, amp):
    mm = MemoryMap()
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(e, nn)
    mm.add("swimmer", [gx], [gy], [amp])
    assert mm.values_at("swimmer", [gx], [gy])[0] == pytest.approx(amp, rel=1e-5)


def test_lazy_decay_reads_true_values_across_renormalisation_and_recentring():
    # 40 s at 30 fps with a 1 s half-life: the pending decay passes the renormalisation point twice
    # and the UAV drifts far enough north to move the window several times.
    mm = MemoryMap(MemoryMapConfig(stamp="sum", half_life_s=1.0, recentre_m=5.0))
    target = cell_of(10.0, 40.0)
    expected = 0.0
    for k in range(1200):
        t = k / 30
        lat, lon = local_to_latlon(0.0, k * 0.02, LAT, LON)
        mm.advance(t, float(lat), float(lon))
        expected *= 0.5 ** (1 / 30) if k else 1.0
        if k % 3 == 0:
            mm.add("person", [target[0]], [target[1]], [0.02])
            expected += 0.02
        if k % 97 == 0:
            assert mm.values_at("person", [target[0]], [target[1]])[0] == pytest.approx(expected, rel=1e-4)
    value = mm.values_at("person", [target[0]], [target[1]])[0]
    assert value == pytest.approx(expected, rel=1e-4)
    n = GRID.n
    tx, ty = int(target[0]) // n, int(target[1]) // n
    (tile,) = [v for x, y, v in mm.tiles("person") if (x, y) == (tx, ty)]
    assert tile[int(target[1]) - ty * n, int(target[0]) - tx * n] == pytest.approx(value, rel=1e-6)
    row, col, inside = mm.local_indices([target[0]], [target[1]])
    assert inside[0] and mm.layer("person")[row[0], col[0]] == pytest.approx(value, rel=1e-6)


def test_clip_at_one_applies_to_true_values_while_decay_is_pending():
    mm = MemoryMap(MemoryMapConfig(stamp="sum", half_life_s=1.0))
    mm.advance(0.0, LAT, LON)
    gx, gy = cell_of(5.0, 5.0)
    mm.advance(3.0, LAT, LON)  # evidence added now is stored at 8x its value
    mm.add("person", [gx] * 50, [gy] * 50, [0.9] * 50)
    assert mm.values_at("person", [gx], [gy])[0] <= 1.0
    assert mm.values_at("person", [gx], [gy])[0] == pytest.approx(1.0, rel=1e-6)
    assert max(float(v.max()) for _, _, v in mm.tiles("person")) <= 1.0
    mm.advance(4.0, LAT, LON)  # one half-life later: half of the clipped value, not of the sum
    assert mm.values_at("person", [gx], [gy])[0] == pytest.approx(0.5, rel=1e-5)
    assert mm.layer("person").max() == pytest.approx(0.5, rel=1e-5)


# ----------------------------------------------------------------------------- JointLayer

def test_joint_layer_reads_fresh_tiles_only():
    jl = JointLayer(GRID, ttl_s=2.0)
    gx, gy = cell_of(0.0, 0.0)
    x, y = int(gx) // GRID.n, int(gy) // GRID.n
    tile = np.zeros((GRID.n, GRID.n), np.float32)
    tile[int(gy) - y * GRID.n, int(gx) - x * GRID.n] = 0.6
    jl.update("person", x, y, tile, t=10.0)
    assert jl.values_at("person", [gx], [gy], now=11.0)[0] == pytest.approx(0.6)
    assert jl.values_at("swimmer", [gx], [gy], now=11.0)[0] == 0.0
    assert jl.values_at("person", [gx], [gy], now=12.5)[0] == 0.0
    assert jl.prune(now=12.5) == 1 and len(jl) == 0
    with pytest.raises(ValueError, match="joint tile"):
        jl.update("person", x, y, np.zeros((3, 3), np.float32), t=0.0)


def _square_latlon(east0: float, north0: float, size_m: float) -> np.ndarray:
    east = np.array([east0, east0 + size_m, east0 + size_m, east0])
    north = np.array([north0, north0, north0 + size_m, north0 + size_m])
    lat, lon = local_to_latlon(east, north, LAT, LON)
    return np.column_stack([lat, lon])


def test_joint_layer_counts_the_other_uavs_whose_recent_footprints_hold_a_cell():
    jl = JointLayer(GRID, ttl_s=3.0, cover_ttl_s=2.0)
    gx, gy = cell_of(0.0, 0.0)
    gx0, gy0 = int(gx) - 40, int(gy) - 40
    assert jl.others_cover(gx0, gy0, 80, 80, now=10.0) is None  # nothing known
    assert jl.put_footprint("uav2", _square_latlon(-10.0, -10.0, 20.0), t=10.0)
    assert jl.put_footprint("uav3", _square_latlon(0.0, 0.0, 20.0), t=10.5)
    cover = jl.others_cover(gx0, gy0, 80, 80, now=11.0)
    assert cover is not None and cover.shape == (80, 80) and cover.dtype == np.uint8

    def at(east: float, north: float) -> int:
        cx, cy = cell_of(east, north)
        return int(cover[int(cy) - gy0, int(cx) - gx0])

    assert (at(5.0, 5.0), at(-5.0, -5.0), at(15.0, 15.0), at(-15.0, 15.0)) == (2, 1, 1, 0)
    # uav2's footprint is older than cover_ttl_s at 12.2, uav3's is not; at 13 none is left
    cover = jl.others_cover(gx0, gy0, 80, 80, now=12.2)
    assert cover is not None and (at(5.0, 5.0), at(-5.0, -5.0)) == (1, 0)
    assert jl.others_cover(gx0, gy0, 80, 80, now=13.0) is None


def test_joint_layer_ignores_malformed_footprints():
    jl = JointLayer(GRID)
    good = _square_latlon(0.0, 0.0, 10.0)
    assert not jl.put_footprint("uav2", good[:2], t=1.0)
    assert not jl.put_footprint("uav2", np.column_stack([good, good[:, :1]]), t=1.0)
    assert not jl.put_footprint("uav2", np.where(np.eye(4, 2, dtype=bool), np.nan, good), t=1.0)
    assert not jl.put_footprint("uav2", [[95.0, 9.0], [95.0, 9.1], [95.1, 9.1]], t=1.0)  # beyond the map
    assert not jl.put_footprint("uav2", good, t=float("inf"))
    gx, gy = cell_of(0.0, 0.0)
    assert jl.others_cover(int(gx), int(gy), 4, 4, now=1.0) is None
    with pytest.raises(ValueError, match="cover_ttl_s"):
        JointLayer(GRID, cover_ttl_s=0.0)


# ----------------------------------------------------------------------------- pipeline

POSE = Pose(lat=LAT, lon=LON, height_m=40.0, pitch_deg=60.0, heading_deg=30.0)


def object_box(east: float, north: float, pose: Pose = POSE, size_px: float = 30.0) -> np.ndarray:
    lat, lon = local_to_latlon(np.array([east]), np.array([north]), LAT, LON)
    uv, ok = latlon_to_pixel(lat, lon, CAM, pose)
    assert ok[0]
    u, v = uv[0]
    # a person-sized box standing on its ground point ("auto" anchor ~ bottom at 60 deg pitch)
    return np.array([[u - size_px / 4, v - size_px * 0.75, u + size_px / 4, v + size_px * 0.25]], np.float32)


def frame(pipe: DetectionPipeline, box: np.ndarray, score: float, t: float, pose: Pose | None = POSE, cls: int = 1):
    return pipe.process(box, np.array([score], np.float32), np.array([cls]), pose, t)


def test_boost_uses_map_from_before_the_update():
    pipe = DetectionPipeline(CAM, CLASSES)
    box = object_box(5.0, 25.0)
    first = frame(pipe, box, 0.4, 0.0)
    assert first.scores[0] == pytest.approx(0.4)  # nothing in the map yet: this frame's own box not used
    second = frame(pipe, box, 0.4, 1 / 30)
    assert second.scores[0] > 0.4
    assert second.raw_scores[0] == pytest.approx(0.4)


def test_map_is_updated_with_original_not_boosted_confidence():
    cfg = PipelineConfig()
    a = DetectionPipeline(CAM, CLASSES, cfg)
    box = object_box(0.0, 30.0)
    for k in range(5):
        frame(a, box, 0.5, k / 30)
    gx, gy = GRID.latlon_to_cell(*local_to_latlon(0.0, 30.0, LAT, LON))
    # Replay by hand with the original confidences: same map.
    mm = MemoryMap(cfg.memory)
    gxa, gya = GRID.latlon_to_cell(*_ground_of(box, POSE, cfg))
    for k in range(5):
        mm.advance(k / 30, LAT, LON)
        mm.add("person", gxa, gya, cfg.memory.gain_per_s * (1 / 30) * np.array([0.5]))
    assert mm.values_at("person", [gx], [gy])[0] > 0.02
    assert a.memory.values_at("person", [gx], [gy])[0] == pytest.approx(mm.values_at("person", [gx], [gy])[0], rel=1e-5)


def _ground_of(box, pose, cfg):
    from agent.boxes import box_anchor_points
    from shared.geo import pixel_to_latlon

    lat, lon, _ = pixel_to_latlon(box_anchor_points(box, cfg.anchor, pose.pitch_deg), CAM, pose)
    return lat, lon


def test_classes_do_not_boost_each_other():
    pipe = DetectionPipeline(CAM, CLASSES)
    box = object_box(0.0, 30.0)
    for k in range(10):
        frame(pipe, box, 0.6, k / 30, cls=1)
    swimmer = frame(pipe, box, 0.3, 10 / 30, cls=2)
    assert swimmer.scores[0] == pytest.approx(0.3)


def test_frames_without_meta_pass_through_unboosted():
    pipe = DetectionPipeline(CAM, CLASSES)
    box = object_box(0.0, 30.0)
    for k in range(10):
        frame(pipe, box, 0.6, k / 30)
    before = pipe.memory.layer("person").copy()
    res = frame(pipe, box, 0.3, 10 / 30, pose=None)
    assert res.scores[0] == pytest.approx(0.3)
    assert np.isnan(res.lat[0])
    np.testing.assert_array_equal(pipe.memory.layer("person"), before)


def test_no_memory_is_the_baseline_with_same_filter_and_nms():
    base = DetectionPipeline(CAM, CLASSES, PipelineConfig(use_memory=False))
    box = object_box(0.0, 30.0)
    for k in range(10):
        res = frame(base, box, 0.6, k / 30)
        assert res.scores[0] == pytest.approx(0.6)
    assert base.memory.classes == []


def test_size_filter_drops_implausible_boxes_only():
    pipe = DetectionPipeline(CAM, CLASSES)
    good = object_box(0.0, 30.0, size_px=40.0)
    huge = object_box(0.0, 30.0, size_px=600.0)   # a "person" 15 m tall
    tiny = object_box(0.0, 30.0, size_px=1.0)
    # the video's confident boxes agree with the prior: the filter may act (agent.size_filter_check)
    pipe.prime([(POSE, CAM, np.repeat(good, 20, axis=0), np.full(20, 0.9, np.float32), np.ones(20, int))])
    res = pipe.process(np.vstack([good, huge + [[700, 0, 700, 0]], tiny + [[-500, 0, -500, 0]]]),
                       np.array([0.5, 0.9, 0.9], np.float32), np.array([1, 1, 1]), POSE, 0.0)
    assert res.n_size_filtered == 2
    assert len(res) == 1 and res.raw_scores[0] == pytest.approx(0.5)
    report = next(r for r in pipe.stage_reports() if r.stage == "size filter")
    assert report.acted and "person" in report.why


def test_size_filter_stands_down_where_the_confident_boxes_contradict_its_prior():
    # a camera or height reference the prior was not made for: every confident person is "too large"
    pipe = DetectionPipeline(CAM, CLASSES)
    large = object_box(0.0, 30.0, size_px=300.0)
    pipe.prime([(POSE, CAM, np.repeat(large, 20, axis=0), np.full(20, 0.9, np.float32), np.ones(20, int))])
    res = pipe.process(np.vstack([large, large + [[700, 0, 700, 0]]]), np.array([0.5, 0.9], np.float32),
                       np.array([1, 1]), POSE, 0.0)
    assert res.n_size_filtered == 0 and len(res) == 2
    report = next(r for r in pipe.stage_reports() if r.stage == "size filter")
    assert not report.acted and "not for these data" in report.why


def test_size_filter_waits_for_evidence_online():
    # a live feed: unfiltered until enough confident boxes were checked, then the prior acts
    pipe = DetectionPipeline(CAM, CLASSES, PipelineConfig(size_check_min_boxes=5))
    good = object_box(0.0, 30.0, size_px=40.0)
    huge = object_box(0.0, 30.0, size_px=600.0) + [[700, 0, 700, 0]]
    first = pipe.process(np.vstack([good, huge]), np.array([0.9, 0.3], np.float32), np.array([1, 1]), POSE, 0.0)
    assert first.n_size_filtered == 0  # one confident box checked: not enough to trust the prior
    for k in range(1, 5):
        pipe.process(good, np.array([0.9], np.float32), np.array([1]), POSE, k / 30.0)
    later = pipe.process(np.vstack([good, huge]), np.array([0.9, 0.3], np.float32), np.array([1, 1]), POSE, 0.2)
    assert later.n_size_filtered == 1


def test_joint_map_boosts_an_object_the_uav_never_saw():
    joint = JointLayer(GRID, ttl_s=5.0)
    # boosting alone (joint detections would promote this weak box further: tests/agent/test_joint_detections.py)
    pipe = DetectionPipeline(CAM, CLASSES, PipelineConfig(joint_detections=False), joint=joint)
    gx, gy = GRID.latlon_to_cell(*_ground_of(object_box(0.0, 30.0), POSE, pipe.config))
    x, y = int(gx[0]) // GRID.n, int(gy[0]) // GRID.n
    tile = np.zeros((GRID.n, GRID.n), np.float32)
    tile[int(gy[0]) - y * GRID.n, int(gx[0]) - x * GRID.n] = 0.5
    joint.update("person", x, y, tile, t=0.0)
    res = frame(pipe, object_box(0.0, 30.0), 0.2, 0.1)
    # default log-odds boost: logit(c_hat) = logit(0.2) + logodds_scale * 1.0 * 0.5
    expected = 1 / (1 + math.exp(-(math.log(0.2 / 0.8) + PipelineConfig().logodds_scale * 0.5)))
    assert res.scores[0] == pytest.approx(expected, rel=1e-4)
    add = DetectionPipeline(CAM, CLASSES, PipelineConfig(boost_mode="add", joint_detections=False), joint=joint)
    assert frame(add, object_box(0.0, 30.0), 0.2, 0.1).scores[0] == pytest.approx(0.7, rel=1e-4)
    local_only = DetectionPipeline(CAM, CLASSES, PipelineConfig(joint_mode="local"), joint=joint)
    assert frame(local_only, object_box(0.0, 30.0), 0.2, 0.1).scores[0] == pytest.approx(0.2)


def test_bad_input_is_named():
    pipe = DetectionPipeline(CAM, CLASSES)
    with pytest.raises(ValueError, match="unknown class id"):
        pipe.process(np.zeros((1, 4)), np.ones(1), np.array([7]), POSE, 0.0)
    with pytest.raises(ValueError, match="differ in length"):
        pipe.process(np.zeros((2, 4)), np.ones(1), np.array([1]), POSE, 0.0)
    with pytest.raises(ValueError, match="anchor"):
        PipelineConfig(anchor="top")
    with pytest.raises(ValueError, match="half_life_s"):
        MemoryMapConfig(half_life_s=0)


def _add_numpy(mm: MemoryMap, cls: str, gx, gy, amplitudes) -> None:
    """MemoryMap.add as it was before agent._kernels (local_indices, np.maximum.at / np.add.at)."""
    import cv2

    amp = np.atleast_1d(np.asarray(amplitudes, dtype=np.float32))
    row, col, inside = mm.local_indices(np.atleast_1d(gx), np.atleast_1d(gy))
    keep = inside & np.isfinite(amp) & (amp > 0)
    if not keep.any():
        return
    row, col, amp = row[keep], col[keep], amp[keep]
    if mm._scale != 1.0:
        amp = amp * np.float32(1.0 / mm._scale)
    m = mm._maps.setdefault(cls, np.zeros((mm.size_cells, mm.size_cells), dtype=np.float32))
    radius, kernel = mm._kernel_for()
    r0, r1 = max(int(row.min()) - radius, 0), min(int(row.max()) + radius + 1, mm.size_cells)
    c0, c1 = max(int(col.min()) - radius, 0), min(int(col.max()) + radius + 1, mm.size_cells)
    impulses = np.zeros((r1 - r0, c1 - c0), dtype=np.float32)
    (np.maximum if mm.config.stamp == "max" else np.add).at(impulses, (row - r0, col - c0), amp)
    roi = m[r0:r1, c0:c1]
    roi += cv2.sepFilter2D(impulses, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_CONSTANT)
    np.minimum(roi, np.float32(1.0 / mm._scale), out=roi)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # the reference's NaN cells
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["max", "sum"]), st.sampled_from([LON, 179.9995, -179.9995]))
def test_compiled_add_and_values_at_equal_the_numpy_implementation(seed, stamp, lon):
    # bit for bit, across the antimeridian, with points outside the window, NaN and non-positive amplitudes
    rng = np.random.default_rng(seed)
    maps = [MemoryMap(MemoryMapConfig(stamp=stamp)) for _ in range(2)]
    for frame in range(4):
        for mm in maps:
            mm.advance(frame * 0.1, LAT, lon)
        gx0, gy0 = maps[0].origin
        size = maps[0].size_cells
        n = int(rng.integers(1, 300))
        gx = (gx0 + rng.uniform(-0.2, 1.2, n) * size) % GRID.world_cells
        gy = gy0 + rng.uniform(-0.2, 1.2, n) * size
        amp = rng.uniform(-0.1, 1.0, n).astype(np.float32)
        gx[rng.integers(0, n, 2)] = np.nan
        amp[rng.integers(0, n, 2)] = np.nan
        stored = maps[1]._maps.get("person")
        if stored is not None:  # values_at as it was: stored value * float32(scale), clipped at 1
            row, col, inside = maps[1].local_indices(gx, gy)
            want = np.zeros(n, np.float32)
            want[inside] = stored[row[inside], col[inside]]
            want = np.minimum(want * np.float32(maps[1]._scale), 1.0)
            np.testing.assert_array_equal(maps[0].values_at("person", gx, gy), want)
        maps[0].add("person", gx, gy, amp)
        _add_numpy(maps[1], "person", gx, gy, amp)
        np.testing.assert_array_equal(maps[0]._maps.get("person"), maps[1]._maps.get("person"))


@settings(max_examples=40, deadline=None)
@given(shift=st.floats(-4.0, 4.0), spread=st.floats(0.2, 1.5), fp_share=st.floats(0.0, 0.1))
def test_property_the_size_check_widens_the_prior_to_the_bulk_of_the_confident_boxes(shift, spread, fp_share):
    # confident boxes at z ~ N(shift, spread) in the prior's band, plus implausible confident false positives
    from agent.size_filter import SizeFilter
    from agent.size_filter_check import SizeCheckSettings, SizeFilterCheck

    rng = np.random.default_rng(7)
    z = rng.normal(shift, spread, 2000)
    z[: int(fp_share * len(z))] = 8.0  # the filter's own business: far outside the band
    prior = SizeFilter.builtin()
    check = SizeFilterCheck(prior, SizeCheckSettings())
    check.observe("person", z)
    median = float(np.median(z))
    if abs(abs(median) - 3.0) > 0.1:  # away from the stand-down edge
        assert ("person" in check.active.bands) == (abs(median) <= 3.0)
    if abs(median) < 2.9:
        s = check.shift("person")
        assert abs(s - round(median / 0.25) * 0.25) <= 0.25 + 1e-9
        old, new = prior.bands["person"], check.active.bands["person"]
        lo_old = np.array(old.mean_log_m) - 3 * np.array(old.std_log)
        hi_old = np.array(old.mean_log_m) + 3 * np.array(old.std_log)
        lo_new = np.array(new.mean_log_m) - 3 * np.array(new.std_log)
        hi_new = np.array(new.mean_log_m) + 3 * np.array(new.std_log)
        sd = np.array(old.std_log)
        # never stricter than the prior; |s| std further out on the data's side only
        assert np.all(lo_new <= lo_old + 1e-9) and np.all(hi_new >= hi_old - 1e-9)
        assert np.allclose(hi_new - hi_old, max(s, 0.0) * sd) and np.allclose(lo_old - lo_new, max(-s, 0.0) * sd)
    assert "swimmer" not in check.active.bands  # nothing seen of it: not trusted

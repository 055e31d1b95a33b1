"""Joint-map peaks against the truth (sim.coop_peaks): one-to-one matching within a gate, the objects that
stand still, and on `coop-slope` the DEM puts the fused peaks on the people where flat earth does not."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from agent.dataset import Dataset
from agent.pipeline_config import PipelineConfig
from shared.geo import local_to_latlon
from sim.coop_eval import run_coop
from sim.coop_peaks import PEAK_BAR_M, PeakSampler, match_peaks, standing_objects
from sim.dataset import write_dataset

LAT0, LON0 = 48.53, 9.06


def _ll(points_en) -> np.ndarray:
    pts = np.asarray(points_en, dtype=np.float64).reshape(-1, 2)
    lat, lon = local_to_latlon(pts[:, 0], pts[:, 1], LAT0, LON0)
    return np.column_stack([lat, lon])


def test_matching_is_one_to_one_least_total_distance_within_the_gate():
    truth = _ll([[0.0, 0.0], [3.0, 0.0], [40.0, 0.0]])
    # peak 0 is closest to both first objects; greedy would give it to object 0 and object 1 would go to the
    # 3.5 m peak, the least total gives object 0 the 1 m peak and object 1 the 0.5 m one
    peaks = _ll([[1.5, 0.0], [-1.0, 0.0], [3.5, 0.0], [20.0, 0.0]])
    rows, cols, dist = match_peaks(truth, peaks, gate_m=5.0)
    pairs = dict(zip(rows.tolist(), cols.tolist(), strict=True))
    assert pairs == {0: 1, 1: 2}  # the far object has no peak within 5 m; the 20 m peak is left over
    assert dist == pytest.approx([1.0, 0.5], abs=1e-3)
    empty = match_peaks(truth, np.zeros((0, 2)))
    assert all(len(a) == 0 for a in empty)


def test_only_objects_that_stand_still_for_the_whole_flight_count(tmp_path):
    fixed, walker = _ll([[2.0, 3.0], [2.05, 3.0]]), _ll([[10.0, 0.0], [10.6, 0.0]])
    annotations = ([{"track_id": 1, "category_id": 1, "lat": a, "lon": b} for a, b in fixed]
                   + [{"track_id": 2, "category_id": 1, "lat": a, "lon": b} for a, b in walker])
    standing = standing_objects(tmp_path, annotations, {1: "person"})
    assert list(standing) == [1] and standing[1][0] == "person"
    assert standing[1][1] == pytest.approx(fixed[:, 0].mean())


def test_with_the_dem_the_joint_map_puts_its_peaks_on_the_people_and_flat_earth_does_not(tmp_path):
    """Two UAVs on opposite sides of the slope, noise-free telemetry: over flat earth each projects the people
    onto the plane of its own take-off and the fused peaks miss them by metres; with the DEM within the bar."""
    write_dataset("coop-slope", tmp_path, seed=0, frames=120, noise_scale=0.0, progress=False)
    dataset = Dataset.load(tmp_path / "images.json")
    standing = standing_objects(tmp_path, dataset.coco["annotations"], dataset.categories)
    seen: dict[int, set[int]] = defaultdict(set)
    for a in dataset.coco["annotations"]:
        seen[a["image_id"]].add(a["track_id"])
    assert len(standing) >= 10
    found = {}
    for dem in (False, True):
        sampler = PeakSampler(standing, seen)
        run_coop(tmp_path, PipelineConfig(), share=True, dem=dem, on_publish=sampler)
        found[dem] = sampler.summary()
    flat, dem = found[False], found[True]
    assert dem["peak_samples"] == flat["peak_samples"] == 1
    assert dem["peak_err_m"] <= PEAK_BAR_M and dem["peak_err_p90_m"] <= PEAK_BAR_M
    assert dem["objects_within_bar"] >= 90.0
    assert flat["peak_err_m"] > 2.0 and flat["objects_within_bar"] < 30.0
    assert flat["extra_peaks"] > dem["extra_peaks"] + 3  # flat earth splits the people between the two UAVs

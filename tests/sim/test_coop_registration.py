"""The joint registration measured against the truth (sim.coop_registration) on short simulated two-UAV flights:
the truth model gives no offset where the telemetry is exact, and on the tuning domain `coop-glare` with its
biases the registration removes most of the offset the telemetry makes. Real simulator, pipeline and fusion."""

from __future__ import annotations

import dataclasses
import math

import pytest

from agent.pipeline_config import PipelineConfig
from sim.coop_domain_eval import ensure_coop_domain_dataset
from sim.coop_domains import get_coop_domain
from sim.coop_eval import run_coop
from sim.coop_registration import registration_errors, true_offsets

SHORT = dataclasses.replace(get_coop_domain("coop-glare"), clip_s=3.0)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    cache = tmp_path_factory.mktemp("coop-registration")
    return {noise: ensure_coop_domain_dataset(SHORT, 0, noise, cache) for noise in (0.0, 1.0)}


def _errors(data_dir, **overrides):
    records: dict = {}
    run_coop(data_dir, dataclasses.replace(PipelineConfig(), **overrides), share=True, registration_out=records)
    return registration_errors(data_dir, records)


def test_exact_telemetry_makes_no_offset(datasets):
    # without telemetry errors or corrections the others' evidence lands on this UAV's view of the object
    errors = _errors(datasets[0.0], correct_telemetry=False)
    assert set(errors) == {"uav1", "uav2"}
    for uav in errors.values():
        assert uav["frames"] == 90
        assert uav["offset_px"] < 1.0
        assert uav["left_px"] < 15.0  # the registration's own estimation noise


def test_the_registration_removes_most_of_the_offset_telemetry_biases_make(datasets):
    errors = _errors(datasets[1.0])
    for uav in errors.values():
        assert uav["offset_px"] > 100.0  # GPS 1-2 m and heading 0.5-1.5 deg biases: ~150 px at ~50 m
        assert uav["left_px"] < 0.5 * uav["offset_px"]


def test_true_offsets_come_per_record(datasets):
    records: dict = {}
    run_coop(datasets[1.0], PipelineConfig(), share=True, registration_out=records)
    truth = true_offsets(datasets[1.0], records)
    assert {vid: len(v) for vid, v in truth.items()} == {vid: len(v) for vid, v in records.items()}
    lengths = [math.hypot(*o) for v in truth.values() for o in v if o is not None]
    assert len(lengths) >= 150 and min(lengths) > 20.0  # biased telemetry: every frame has an offset


def test_nothing_is_recorded_without_a_joint_map(datasets):
    records: dict = {}
    run_coop(datasets[1.0], PipelineConfig(), share=False, registration_out=records)
    assert records == {}
    errors = registration_errors(datasets[1.0], {1: []})
    assert errors["uav1"]["frames"] == 0 and math.isnan(errors["uav1"]["offset_px"])


def test_a_dataset_over_a_terrain_is_refused_naming_it(tmp_path):
    (tmp_path / "dem.npz").write_bytes(b"")
    with pytest.raises(ValueError, match="terrain"):
        registration_errors(tmp_path, {})

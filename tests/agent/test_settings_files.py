"""Settings files read as JSON (agent.boost.config_from_dict / load_params for --config, agent.tracking_io for
--tracker-config): any value JSON can hold in any setting gives the settings or a ValueError, never a traceback."""

from __future__ import annotations

import dataclasses
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent.boost import config_from_dict, load_params
from agent.memory_map import MemoryMapConfig
from agent.pipeline_config import PipelineConfig
from agent.tracking.config import ClassMotion, TrackerConfig
from agent.tracking_io import load_tracker_config

_VALUES = st.one_of(st.sampled_from([10**400, -10**400, 2**64, 0, -1, None, True, "", "x", [1], {"a": 1}, []]),
                    st.floats(allow_nan=True, allow_infinity=True))
_PIPELINE = sorted({f.name for f in dataclasses.fields(PipelineConfig)} - {"memory", "terrain"})
_MEMORY = sorted(f.name for f in dataclasses.fields(MemoryMapConfig))
_TRACKER = sorted(f.name for f in dataclasses.fields(TrackerConfig))
_MOTION = sorted(f.name for f in dataclasses.fields(ClassMotion))


@settings(max_examples=150, deadline=None)
@given(st.one_of(st.sampled_from(_PIPELINE), st.sampled_from([f"memory.{k}" for k in _MEMORY])), _VALUES)
def test_any_value_in_a_pipeline_setting_is_the_config_or_a_value_error(key, value):
    """Fuzzing (1 Dec 2026): an integer beyond float's range (1e400 written out) in boost_weight, joint_gate_m,
    memory.sigma_m, ... raised OverflowError in the settings' checks: a traceback from boost/track --config."""
    group, _, name = key.rpartition(".")
    try:
        config_from_dict({group: {name: value}} if group else {name: value})
    except (ValueError, TypeError):  # TypeError: load_params names the file (below)
        pass


def test_a_huge_integer_setting_is_named_with_the_file(tmp_path):
    path = tmp_path / "params.json"
    path.write_text(json.dumps({"memory": {"sigma_m": 10**400}}))
    with pytest.raises(ValueError, match=r"params\.json: setting 'memory\.sigma_m' is a number of 401 digits"):
        load_params(path)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.sampled_from(_TRACKER), st.sampled_from([f"default_motion.{k}" for k in _MOTION])), _VALUES)
def test_any_value_in_a_tracker_setting_is_the_config_or_a_value_error(tmp_path, key, value):
    """Fuzzing (1 Dec 2026): 1e400 written out raised OverflowError, a list for a number ('image_first_iou': [1])
    TypeError in TrackerConfig's checks: tracebacks from track --tracker-config."""
    group, _, name = key.rpartition(".")
    path = tmp_path / "tracker.json"
    path.write_text(json.dumps({group: {name: value}} if group else {name: value}))
    try:
        load_tracker_config(path)
    except ValueError:
        pass

"""The simulated source of the agent (`uavmm agent --sim`): the chosen UAV of a scenario, frame by frame."""

from __future__ import annotations

import pytest

from sim.source import SimSource
from tests.agent.test_sources import FRAMES, check_source_frames


@pytest.mark.parametrize("uav_index", [0, 1])
def test_sim_source_flies_the_chosen_uav_of_a_simultaneous_scenario(uav_index):
    source = SimSource("coop", seed=3, uav_index=uav_index, frames=FRAMES)
    frames = list(source.frames())
    assert len(frames) == FRAMES
    assert source.video.uav == f"uav{uav_index + 1}"
    check_source_frames(frames, set(source.class_names))
    assert source.class_names == {1: "person", 2: "swimmer"}
    assert sum(f.pose is not None for f in frames) >= FRAMES - 2
    assert all(abs(f.pose_t - f.t) < 0.2 for f in frames if f.pose is not None)  # 10 Hz telemetry
    assert sum(len(f.scores) for f in frames) > 0
    # the two UAVs fly different flights over one world
    other = next(iter(SimSource("coop", seed=3, uav_index=1 - uav_index, frames=FRAMES).frames()))
    assert (other.pose.lat, other.pose.lon) != (frames[0].pose.lat, frames[0].pose.lon)
    assert other.t == frames[0].t


def test_sim_source_of_a_later_flight_stops_at_its_end():
    source = SimSource("sea", uav_index=2, frames=10)  # three separate flights; the last one
    frames = list(source.frames())
    assert len(frames) == 10
    assert frames[0].t > SimSource("sea", uav_index=0, frames=10).sim.videos[0].t0


def test_sim_source_errors_name_the_valid_choices():
    with pytest.raises(ValueError, match="valid scenarios: .*coop"):
        SimSource("nosuch")
    with pytest.raises(ValueError, match=r"uav_index must be in 0\.\.1 .*uav1"):
        SimSource("coop", uav_index=2)

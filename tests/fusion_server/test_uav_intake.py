"""fusion_server.uav_intake: the rejections and liveliness the fusion node and the gateway share."""

from __future__ import annotations

import logging

import pytest
import zenoh

from fusion_server.metrics import FusionMetrics
from fusion_server.uav_intake import UavIntake
from fusion_server.uav_registry import UavRegistry
from shared.keys import KeySpace

KEYS = KeySpace()
LOG = logging.getLogger("tests.uav_intake")


class Sample:
    """The two fields of a zenoh.Sample the intake reads."""

    def __init__(self, key_expr: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT) -> None:
        self.key_expr = key_expr
        self.kind = kind


def intake(max_uavs: int = 4, prefix: str = "") -> UavIntake:
    return UavIntake(KEYS, UavRegistry(max_uavs=max_uavs), FusionMetrics(), LOG, prefix)


def test_a_token_coming_and_going_is_recorded_and_handed_on():
    node, seen = intake(), []

    def then(uav: str, online: bool) -> None:
        seen.append((uav, online))

    node.on_alive(Sample(KEYS.uav_alive("uav1")), then)
    assert node.uavs.online() == ["uav1"] and node.metrics.received == {"alive": 1}
    node.on_alive(Sample(KEYS.uav_alive("uav1"), zenoh.SampleKind.DELETE), then)
    assert node.uavs.online() == [] and seen == [("uav1", True), ("uav1", False)]


@pytest.mark.parametrize(("key", "reason"), [(f"{KEYS.prefix}/uav/a b/alive", "bad_key"),
                                             (KEYS.uav_state("uav1"), "unexpected_key")])
def test_a_sample_on_another_key_is_rejected_with_its_reason(key, reason):
    node, seen = intake(), []
    node.on_alive(Sample(key), lambda uav, online: seen.append(uav))
    assert node.metrics.rejected == {("alive", reason): 1} and seen == [] and node.uavs.online() == []


class FullRegistry(UavRegistry):
    def alive(self, uav: str, online: bool) -> bool:
        return False


def test_a_token_the_full_registry_refuses_is_rejected_and_not_handed_on():
    node, seen = UavIntake(KEYS, FullRegistry(), FusionMetrics(), LOG), []
    node.on_alive(Sample(KEYS.uav_alive("uav1")), lambda uav, online: seen.append(uav))
    assert node.metrics.rejected == {("alive", "too_many_uavs"): 1} and seen == [] and node.metrics.received == {}


def test_an_exception_after_the_registry_is_counted_not_raised(caplog):
    def boom(uav: str, online: bool) -> None:
        raise RuntimeError("bug")

    node = intake()
    with caplog.at_level(logging.ERROR, LOG.name):
        node.on_alive(Sample(KEYS.uav_alive("uav1")), boom)
    assert node.metrics.rejected == {("alive", "internal_error"): 1}
    assert "internal error handling liveliness" in caplog.text


def test_a_rejection_is_counted_on_its_uav_and_logged_once_per_interval_with_the_prefix(caplog):
    node = intake(prefix="gateway: ")
    node.uavs.message("uav1", "state", 10)
    with caplog.at_level(logging.WARNING, LOG.name):
        node.reject("state", "bad_version", KEYS.uav_state("uav1"), "v 2", "uav1")
        node.reject("state", "bad_version", KEYS.uav_state("uav1"), "v 2", "uav1")
    assert node.metrics.rejected == {("state", "bad_version"): 2}
    assert node.uavs.snapshot()[0]["rejected"] == {"bad_version": 2}
    assert [r.getMessage() for r in caplog.records] == [
        f"gateway: dropped state message on {KEYS.uav_state('uav1')}: bad_version: v 2"]



def test_a_uav_online_whose_every_message_is_dropped_shows_its_rejections():
    """A drone whose clock runs 2 minutes ahead: every message dropped as t_in_future, yet its /v1/uavs row (known by
    its liveliness token only) showed no rejection (a helper's live audit). Kept apart from the registry's entries:
    such ids never count against max_uavs nor lock a real UAV out (the fourth read), and go with their token."""
    registry = UavRegistry(max_uavs=2)
    for uav in ("slow-1", "slow-2"):
        registry.alive(uav, True)
        for _ in range(3):
            registry.rejected(uav, "t_in_future")
    registry.rejected("nobody", "t_in_future")  # a forged id: not counted
    rows = {row["id"]: row for row in registry.snapshot()}
    assert rows["slow-1"]["rejected"] == {"t_in_future": 3} and rows["slow-1"]["online"] is True
    assert "nobody" not in rows
    assert registry.message("real", "tile", 100)  # two token-only ids took no place of a real UAV
    assert [record.id for record in registry.drain_changes()[0]] == ["real"]  # nothing persisted for a token alone
    assert registry.message("slow-1", "tile", 100)  # once it sends a valid message its counts come along
    assert {row["id"]: row for row in registry.snapshot()}["slow-1"]["rejected"] == {"t_in_future": 3}
    registry.alive("slow-2", False)
    assert {row["id"]: row for row in registry.snapshot()}.get("slow-2") is None

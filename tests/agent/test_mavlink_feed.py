"""The live MAVLink feed (agent.mavlink_feed) on loopback UDP: the vehicle's own clock, a ground station's
SYSTEM_TIME ignored, a later jump of the vehicle's clock warned about while the records keep theirs."""

from __future__ import annotations

import pytest

from shared.telemetry import Telemetry
from tests.netutil import free_udp_port, wait_until
from tests.shared.mavlink_writer import flight_packets, replay_udp

pytest.importorskip("pymavlink")

T0 = 1_685_613_600.0


def _flight(n: int = 12, t0: float = T0) -> list[Telemetry]:
    return [Telemetry(t=t0 + 0.1 * i, lat=48.53 + 1e-5 * i, lon=9.06, height_m=30.0, pitch_deg=45.0,
                      heading_deg=10.0, vel_en_mps=(0.0, 0.0)) for i in range(n)]


def _system_time(sysid: int, compid: int, t_unix: float, boot_ms: int) -> bytes:
    from pymavlink.dialects.v20 import ardupilotmega

    link = ardupilotmega.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return link.system_time_encode(int(round(t_unix * 1e6)), boot_ms).pack(link)


@pytest.fixture
def feed():
    from agent.mavlink_feed import MavlinkUdpFeed

    port = free_udp_port()
    feed = MavlinkUdpFeed(f"udp:127.0.0.1:{port}")
    feed.port = port  # type: ignore[attr-defined]
    yield feed
    feed.close()


def test_a_ground_stations_system_time_does_not_anchor_the_live_clock(feed):
    """mavlink-routerd forwards QGC's SYSTEM_TIME (its UNIX time, time_boot_ms 0) to the agent just before the
    vehicle's positions: the records came out off by the vehicle's uptime."""
    flight = _flight()
    gcs = (0.0, _system_time(255, 190, T0 - 1.0, 0))
    replay_udp([gcs, *flight_packets(flight)], feed.port, rounds=1)
    records = feed.start(timeout_s=5.0)
    assert records[0].t == pytest.approx(T0, abs=2e-3)


def test_a_later_jump_of_the_vehicles_clock_is_warned_and_the_records_keep_theirs(feed, caplog):
    flight = _flight()
    replay_udp(flight_packets(flight), feed.port, rounds=1)
    first = feed.start(timeout_s=5.0)
    later = _flight(12, T0 + 1.2)
    packets = flight_packets(later, boot_ms0=21_200, system_time=False)
    with caplog.at_level("WARNING"):
        replay_udp([(0.0, _system_time(1, 1, T0 + 1.2 - 37.0, 21_200)), *packets], feed.port, rounds=1)
        wait_until(lambda: "jumped by -37.000 s" in caplog.text, 5.0, "the clock jump's warning")
    records = wait_until(lambda: len(feed.records()) == 24 and feed.records(), 5.0, "the later records")
    assert [r.t for r in records[:len(first)]] == pytest.approx([r.t for r in first])
    assert [r.t for r in records] == pytest.approx([f.t for f in flight + later], abs=2e-3)


def test_a_system_id_not_on_the_link_names_the_systems_that_are():
    """--mavlink-system-id 7 on a link where only system 1 sends positions: the timeout says whose came."""
    from agent.mavlink_feed import MavlinkUdpFeed

    port = free_udp_port()
    feed = MavlinkUdpFeed(f"udp:127.0.0.1:{port}", system_id=7)
    try:
        replay_udp(flight_packets(_flight()), port, rounds=1)
        with pytest.raises(ValueError, match=r"within 1 s \(\d+ datagrams received; positions came from system 1 "
                                             r"only\)"):
            feed.start(timeout_s=1.0)
    finally:
        feed.close()


@pytest.mark.parametrize(("t_first", "t_last", "want"), [
    (T0 + 0.35, T0 + 0.55, range(3, 7)),  # 0.3 .. 0.6: the records bracketing the span
    (T0 + 0.31, T0 + 0.32, range(3, 5)),  # between two records: those two
    (T0 - 5.0, T0 + 0.05, range(0, 2)),  # before the first: from the first
    (T0 + 1.05, T0 + 9.0, range(10, 12)),  # past the last: to the last
])
def test_records_between_are_the_slice_of_all_records_that_brackets_the_span(feed, t_first, t_last, want):
    """The video source asks per frame for the records around its time: the whole list, converted every frame, cost
    97 ms a frame after 30 minutes at 10 Hz."""
    flight = _flight()
    replay_udp(flight_packets(flight), feed.port, rounds=1)
    feed.start(timeout_s=5.0)
    every = wait_until(lambda: len(feed.records()) == len(flight) and feed.records(), 5.0, "the flight's records")
    got = feed.records_between(t_first, t_last)
    assert [r.t for r in got] == pytest.approx([every[i].t for i in want])
    assert got == [every[i] for i in want]

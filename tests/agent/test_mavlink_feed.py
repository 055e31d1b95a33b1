"""The live MAVLink feed (agent.mavlink_feed) on loopback UDP: the vehicle's own clock, a ground station's
SYSTEM_TIME ignored, a later jump of the vehicle's clock warned about while the records keep theirs."""

from __future__ import annotations

import threading

import pytest

from shared.telemetry import Telemetry
from tests.netutil import free_udp_port, wait_until
from tests.shared.mavlink_writer import flight_packets, port_is_bound, replay_udp

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


# ---- a reboot of the autopilot mid-flight: its boot clock restarts ------------------------------------------------

def _paced(packets, port: int, t0: float) -> None:
    """Send (receive time, packet) pairs at their times relative to t0 (a real link's timing: the reboot rule reads
    receive time minus boot time)."""
    import socket
    import time

    start = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for t, packet in packets:
            delay = (t - t0) - (time.monotonic() - start)
            if delay > 0:
                time.sleep(delay)
            sock.sendto(packet, ("127.0.0.1", port))


def _start_while_paced(feed, packets) -> None:
    """Start the feed while a thread sends the packets at their times (they start before it is anchored)."""
    wait_until(lambda: port_is_bound(feed.port), 10.0, "the feed's port")
    sender = threading.Thread(target=_paced, args=(packets, feed.port, T0))
    sender.start()
    feed.start(timeout_s=5.0, anchor_wait_s=0.5)
    sender.join()


def _rebooting_flight(*, new_boot_system_time: bool):
    before = _flight(15, T0)  # 1.4 s at boot 100 s
    after = _flight(16, T0 + 2.5)  # rebooted: 1.1 s of silence, then 1.5 s from boot 4 s
    packets = flight_packets(before, boot_ms0=100_000) + flight_packets(after, boot_ms0=4_000,
                                                                        system_time=new_boot_system_time)
    return before, after, packets


@pytest.fixture
def quick_feed():
    from agent.mavlink_feed import MavlinkUdpFeed

    port = free_udp_port()
    feed = MavlinkUdpFeed(f"udp:127.0.0.1:{port}", reboot_confirm_s=1.0)
    feed.port = port  # type: ignore[attr-defined]
    yield feed
    feed.close()


@pytest.mark.parametrize("new_boot_system_time", [False, True])
def test_a_reboot_mid_flight_puts_the_new_boots_positions_at_their_time(quick_feed, caplog, new_boot_system_time):
    """Before: the new boot's positions (boot time 4 s) landed 96 s in the past, and every frame after the reboot had
    no pose until the agent restarted. Now they continue the clock: from the vehicle's SYSTEM_TIME of the new boot
    (exact), else from the receive times (within the loopback's latency jitter)."""
    before, after, packets = _rebooting_flight(new_boot_system_time=new_boot_system_time)
    with caplog.at_level("WARNING"):
        _start_while_paced(quick_feed, packets)
        wait_until(lambda: quick_feed.reboots == 1, 5.0, "the reboot confirmed")
    records = wait_until(lambda: len(quick_feed.records()) == len(before) + len(after) and quick_feed.records(), 5.0,
                         "both boots' records")
    tol = 2e-3 if new_boot_system_time else 0.05
    assert [r.t for r in records] == pytest.approx([f.t for f in before + after], abs=tol)
    assert [r.lat for r in records] == pytest.approx([f.lat for f in before + after])
    assert "rebooted (its boot time went from 101.4 s back to 4.0 s)" in caplog.text
    assert ("by the vehicle's SYSTEM_TIME" in caplog.text) == new_boot_system_time
    assert "jumped by" not in caplog.text  # the new boot's SYSTEM_TIME is the reboot's, not a clock step
    # a frame after the reboot gets the new boot's records around it; one in the silence gets its two sides
    got = quick_feed.records_between(T0 + 3.05, T0 + 3.25)
    assert [r.t for r in got] == pytest.approx([T0 + 3.0, T0 + 3.1, T0 + 3.2, T0 + 3.3], abs=tol)
    gap = quick_feed.records_between(T0 + 2.0, T0 + 2.0)
    assert [r.t for r in gap] == pytest.approx([T0 + 1.4, T0 + 2.5], abs=tol)


def test_old_positions_received_late_while_the_stream_goes_on_are_no_reboot(quick_feed, caplog):
    """A second link with more latency repeats the first 0.5 s 4 s later (more than REBOOT_S behind the boot's latest
    time): they join the boot they are of once its stream goes on."""
    flight = _flight(46, T0)
    packets = flight_packets(flight, boot_ms0=100_000)
    late = [(t + 4.0, p) for t, p in packets if t < T0 + 0.5]
    schedule = sorted(packets + late, key=lambda item: item[0])
    with caplog.at_level("WARNING"):
        _start_while_paced(quick_feed, schedule)
    wait_until(lambda: quick_feed.late_repeats >= 1, 5.0, "the repeat taken back")
    assert quick_feed.reboots == 0
    records = wait_until(lambda: len(quick_feed.records()) == len(flight) and quick_feed.records(), 5.0, "the records")
    assert [r.t for r in records] == pytest.approx([f.t for f in flight], abs=2e-3)
    assert "rebooted" not in caplog.text


def test_a_frame_waiting_for_positions_does_not_stall_while_a_reboot_is_pending(quick_feed):
    """While the new boot is not yet confirmed no record of the old boot will come: wait_for returns at once instead
    of its timeout per frame (a 10 fps agent would fall 5 s behind a frame)."""
    import time

    quick_feed.reboot_confirm_s = 60.0  # the reboot stays pending for this test
    _before, _after, packets = _rebooting_flight(new_boot_system_time=False)
    _start_while_paced(quick_feed, packets)
    wait_until(lambda: quick_feed._pending is not None, 5.0, "the pending boot")
    began = time.monotonic()
    quick_feed.wait_for(T0 + 3.0, T0 + 3.1, timeout_s=30.0, idle_s=30.0)
    assert time.monotonic() - began < 10.0
    assert quick_feed.records_between(T0 + 3.0, T0 + 3.1)[-1].t == pytest.approx(T0 + 1.4, abs=2e-3)


def test_an_earlier_boots_positions_received_after_the_reboot_do_not_join_the_new_boot(quick_feed):
    """Old positions (boot 100.5 s) from a second, slower link arrive after the reboot was confirmed: their boot time
    is 96 s ahead of the new boot's, and filed under it they were records 96 s in the future."""
    before, after, packets = _rebooting_flight(new_boot_system_time=False)
    more = _flight(10, T0 + 4.1)
    stragglers = [(T0 + 4.05, p) for t, p in flight_packets(before, boot_ms0=100_000) if T0 + 0.5 <= t < T0 + 0.8]
    schedule = packets + stragglers + flight_packets(more, boot_ms0=5_600, system_time=False)
    _start_while_paced(quick_feed, schedule)
    truth = before + after + more
    records = wait_until(lambda: len(quick_feed.records()) >= len(truth) and quick_feed.records(), 5.0, "the records")
    assert quick_feed.reboots == 1
    assert len(records) == len(truth)
    assert [r.t for r in records] == pytest.approx([f.t for f in truth], abs=0.05)


def test_the_rebooted_autopilots_first_unix_time_after_confirmation_is_no_clock_jump(quick_feed, caplog):
    """The UNIX time comes back with GPS, after the reboot was confirmed: it was warned as a jump of +98.5 s that
    would put a --telemetry-offset-s off by as much, though the records were placed right."""
    before, after, packets = _rebooting_flight(new_boot_system_time=False)
    late = T0 + 3.9  # 1.4 s into the new boot, past the 1 s confirmation
    packets = sorted(packets + [(late, _system_time(1, 1, late, 4_000 + 1_400))], key=lambda item: item[0])
    with caplog.at_level("WARNING"):
        _start_while_paced(quick_feed, packets)
        records = wait_until(lambda: len(quick_feed.records()) == len(before) + len(after) and quick_feed.records(),
                             5.0, "both boots' records")
    assert quick_feed.reboots == 1 and "jumped by" not in caplog.text
    assert [r.t for r in records] == pytest.approx([f.t for f in before + after], abs=0.05)


def test_a_boot_keeps_the_last_minutes_of_positions_not_the_whole_flight():
    # probe (audit): every position of the flight was kept, 288k at 10 Hz after 8 h (~6 MB an hour, ~32 MB at 50 Hz)
    from agent.mavlink_feed import KEEP_S, TRIM_STEP, _Boot
    from shared.telemetry import MavlinkSample

    def sample(boot_s: float) -> MavlinkSample:
        return MavlinkSample(boot_s=boot_s, lat=47.6, lon=9.3, height_m=30.0, pitch_deg=45.0, heading_deg=90.0,
                             roll_deg=0.0, vel_en=(0.0, 0.0))

    rate = 50.0
    boot = _Boot(sample(12.0), rx=1000.0)
    n = int(3600 * rate)  # an hour at 50 Hz
    for k in range(1, n):
        boot_s = 12.0 + k / rate
        boot.add(sample(boot_s), 1000.0 + k / rate)
    assert len(boot.times) == len(boot.samples) <= KEEP_S * rate + 2 * TRIM_STEP
    assert boot.times == sorted(boot.times) and [s.boot_s for s in boot.samples] == boot.times
    assert boot.times[-1] == boot.top_boot == pytest.approx(12.0 + (n - 1) / rate)
    assert boot.top_boot - boot.times[0] >= KEEP_S  # at least the last KEEP_S are there
    assert boot.first_boot == 12.0  # where the boot began, for the reboot rules
    boot.add(sample(11.0), None)  # a late straggler from before: filed, and the boot's start moves back
    assert boot.first_boot == 11.0


def test_a_gimbal_that_stops_reporting_is_warned_and_not_carried_on(feed, caplog):
    """Live: the latest gimbal reading was held for the rest of the flight (the telemetry walk-through's left item:
    a .tlog gimbal silent after 5 s gave 44 deg heading and 17.6 deg pitch error; the log reader now bounds it)."""
    flight = _flight()
    replay_udp(flight_packets(flight), feed.port, rounds=1)
    first = feed.start(timeout_s=5.0)
    assert first[-1].pitch_deg == pytest.approx(45.0)
    threading.Event().wait(1.3)  # the gimbal falls silent for longer than its bound (1 s at least)
    later = _flight(12, T0 + 1.2)
    with caplog.at_level("WARNING"):
        replay_udp(flight_packets(later, gimbal="none", boot_ms0=21_200, system_time=False), feed.port, rounds=1)
        wait_until(lambda: "the gimbal stopped reporting" in caplog.text, 5.0, "the stale gimbal's warning")
    wait_until(lambda: len(feed.records()) >= 24, 5.0, "the later positions")
    assert all(r.pitch_deg is None for r in feed.records()[12:])
    assert caplog.text.count("the gimbal stopped reporting") == 1

"""The live MAVLink feed across a wrap of ``time_boot_ms`` (uint32 ms: 49.7 days up), on loopback UDP paced at the
stream's own times: the boot goes on (it was a reboot: 5 s of frames without pose, then a new boot placed by the
receive clock); a reboot near the wrap that the receive times contradict is still a reboot."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from shared.telemetry import Telemetry
from tests.netutil import free_udp_port, wait_until
from tests.shared.mavlink_writer import flight_packets, port_is_bound

pytest.importorskip("pymavlink")

WRAP = 1 << 32
T0 = 1_685_613_600.0


def _flight(n: int, t0: float = T0) -> list[Telemetry]:
    return [Telemetry(t=t0 + 0.1 * i, lat=65.0 + 1e-5 * i, lon=-179.9999 + 1e-6 * i, height_m=30.0, pitch_deg=45.0,
                      heading_deg=10.0, vel_en_mps=(0.0, 0.0)) for i in range(n)]


def _paced(packets: list[tuple[float, bytes]], port: int) -> None:
    """Send (time, packet) pairs at their times relative to T0 (a real link's timing: the rules read receive time
    minus boot time)."""
    start = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for t, packet in packets:
            delay = (t - T0) - (time.monotonic() - start)
            if delay > 0:
                time.sleep(delay)
            sock.sendto(packet, ("127.0.0.1", port))


@pytest.fixture
def live():
    """live(packets, **feed options): a feed on a free port, started while the packets go out paced."""
    from agent.mavlink_feed import MavlinkUdpFeed

    port = free_udp_port()
    feeds: list[MavlinkUdpFeed] = []
    senders: list[threading.Thread] = []

    def send(packets: list[tuple[float, bytes]], **options) -> MavlinkUdpFeed:
        feed = MavlinkUdpFeed(f"udp:127.0.0.1:{port}", **options)
        feeds.append(feed)
        wait_until(lambda: port_is_bound(port), 10.0, "the feed's port")
        sender = threading.Thread(target=_paced, args=(packets, port))
        senders.append(sender)
        sender.start()
        feed.start(timeout_s=5.0, anchor_wait_s=0.5)
        return feed

    yield send
    for sender in senders:
        sender.join()
    for feed in feeds:
        feed.close()


def test_a_wrap_of_time_boot_ms_on_a_live_link_continues_the_boot(live, caplog):
    """The boot clock passes 2**32 ms 1.25 s into a 3 s stream. Before, the positions after it were a pending reboot
    (frames got no pose for reboot_confirm_s, 5 s), then a second boot, and the SYSTEM_TIME clock 'jumped' by
    +4294967.296 s."""
    flight = _flight(30)
    at = 13  # the first record after the wrap
    packets = flight_packets(flight[:at], boot_ms0=WRAP - 100 * at + 50) + flight_packets(flight[at:], boot_ms0=50)
    with caplog.at_level("WARNING"):
        feed = live(packets)
        # by 4 s into the stream, before a reboot at 1.3 s could be confirmed (6.3 s): all the records, on the
        # vehicle's clock
        records = wait_until(lambda: len(feed.records()) == len(flight) and feed.records(), 4.0, "all the records")
        spanning = feed.records_between(flight[at - 2].t + 0.05, flight[at + 1].t - 0.05)
    assert feed.reboots == 0 and feed.late_repeats == 0
    assert [r.t for r in records] == pytest.approx([f.t for f in flight], abs=2e-3)
    assert [r.t for r in spanning] == pytest.approx([f.t for f in flight[at - 2:at + 2]], abs=2e-3)
    assert "rebooted" not in caplog.text and "jumped" not in caplog.text


def test_a_reboot_near_the_wrap_on_a_live_link_is_still_a_reboot(live, caplog):
    """The first boot ends 0.1 s before 2**32 ms; 4.5 s later the rebooted autopilot sends boot time 0.6 s: one wrap
    later that would be 0.7 s on, but the receive time moved on 4.5 s (more than REBOOT_S apart): a reboot (confirmed
    after 1 s here), each boot placed on the vehicle's SYSTEM_TIME."""
    before, after = _flight(5), _flight(16, T0 + 0.4 + 4.5)
    packets = flight_packets(before, boot_ms0=WRAP - 500) + flight_packets(after, boot_ms0=600)
    with caplog.at_level("WARNING"):
        feed = live(packets, reboot_confirm_s=1.0)
        wait_until(lambda: feed.reboots == 1, 10.0, "the reboot confirmed")
        records = wait_until(lambda: len(feed.records()) == len(before) + len(after) and feed.records(), 5.0,
                             "both boots' records")
    assert [r.t for r in records] == pytest.approx([f.t for f in before + after], abs=2e-3)
    assert "rebooted (its boot time went from 4294967.2 s back to 0.6 s)" in caplog.text

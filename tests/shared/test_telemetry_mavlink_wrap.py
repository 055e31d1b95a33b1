"""``time_boot_ms`` is a uint32: after 49.7 days up it wraps to 0. A wrap continues the boot (it was read as a reboot:
the gimbal state restarted until the next gimbal message); a reboot, even one near the wrap, is still a reboot."""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from shared.telemetry import Telemetry
from shared.telemetry.mavlink import BootTimeUnwrap
from shared.telemetry.mavlink_clock import REBOOT_S
from shared.telemetry.tlog import parse_tlog
from tests.shared.mavlink_writer import BOOT_MS0, flight_packets

pytest.importorskip("pymavlink")

WRAP = 1 << 32
T0 = 1_685_613_600.0  # 2023-06-01 10:00 UTC
_GIMBAL_MESSAGES = {"GIMBAL_DEVICE_ATTITUDE_STATUS", "MOUNT_ORIENTATION", "MOUNT_STATUS"}


def _flight(n: int = 30, t0: float = T0) -> list[Telemetry]:
    return [Telemetry(t=t0 + 0.1 * i, lat=-16.5 + 1e-5 * i, lon=179.99 - 2e-5 * i, height_m=30.0 + 0.1 * i,
                      pitch_deg=40.0 + i, heading_deg=(350.0 + 3 * i) % 360, roll_deg=0.0, vel_en_mps=(-1.5, 1.1))
            for i in range(n)]


def _type(packet: bytes) -> str:
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.MAVLink(None).decode(bytearray(packet)).get_type()


def _packets(records: list[Telemetry], boot_ms0: int, *, gimbal: str, gimbal_every: int, first: int = 0,
             system_time: bool = True) -> list[tuple[float, bytes]]:
    """flight_packets with the gimbal's message at every `gimbal_every`-th record only (a 1 Hz gimbal beside 10 Hz
    positions); `first` is the index of records[0] in the flight."""
    out, k = [], first
    for t, packet in flight_packets(records, gimbal=gimbal, boot_ms0=boot_ms0, system_time=system_time):
        kind = _type(packet)
        if kind not in _GIMBAL_MESSAGES or k % gimbal_every == 0:
            out.append((t, packet))
        k += kind == "GLOBAL_POSITION_INT"
    return out


def _tlog(packets: list[tuple[float, bytes]]) -> bytes:
    return b"".join(struct.pack(">Q", int(round(t * 1e6))) + p for t, p in packets)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(at=st.integers(1, 29), phase_ms=st.integers(0, 99), gimbal_every=st.sampled_from([1, 4, 10]),
       gimbal=st.sampled_from(["mount-status", "device-vehicle", "device-earth"]), system_time=st.booleans())
def test_a_wrap_of_time_boot_ms_continues_the_boot(caplog, at, phase_ms, gimbal_every, gimbal, system_time):
    """The flight's boot clock passes 2**32 ms between record at - 1 and at (phase_ms after it at record at): the
    records are those of the same flight logged without a wrap. Before, a reboot was warned and the positions after
    the wrap had no gimbal (pitch None, the vehicle's heading) until its next message."""
    flight = _flight()
    kw = {"gimbal": gimbal, "gimbal_every": gimbal_every, "system_time": system_time}
    wrapped = (_packets(flight[:at], WRAP - 100 * at + phase_ms, **kw)
               + _packets(flight[at:], phase_ms, first=at, **kw))
    caplog.clear()
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(wrapped))
    want = parse_tlog(_tlog(_packets(flight, BOOT_MS0, **kw)))
    assert "rebooted" not in caplog.text and "jumped" not in caplog.text
    assert len(records) == len(want) == len(flight)
    assert [r.t for r in records] == pytest.approx([w.t for w in want], abs=1e-5)
    # interpolated between the gimbal's readings, timed by receive times: float rounding of UNIX us (~1e-6 deg)
    assert [r.pitch_deg for r in records] == pytest.approx([w.pitch_deg for w in want], abs=1e-5)
    assert [r.heading_deg for r in records] == pytest.approx([w.heading_deg for w in want], abs=1e-5)
    if system_time:
        assert [r.t for r in records] == pytest.approx([f.t for f in flight], abs=2e-3)


def _shifted(records: list[Telemetry], dt: float) -> list[Telemetry]:
    return [Telemetry(t=r.t + dt, lat=r.lat, lon=r.lon + 0.01, height_m=r.height_m, pitch_deg=r.pitch_deg,
                      heading_deg=r.heading_deg, roll_deg=r.roll_deg, vel_en_mps=r.vel_en_mps) for r in records]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(to_wrap_ms=st.integers(0, 50_000), new_boot_ms=st.integers(300, 20_000),
       dead_s=st.floats(REBOOT_S + 0.5, 120.0))
def test_a_reboot_near_the_wrap_is_still_a_reboot(caplog, to_wrap_ms, new_boot_ms, dead_s):
    """The first boot ends `to_wrap_ms` before 2**32 ms; the autopilot reboots and its new clock starts `dead_s` after
    it (the receive times say so): read one wrap later its boot time would be too early for the receive time by
    more than REBOOT_S, so it is a reboot, each boot on its own SYSTEM_TIME."""
    first = _flight(12)
    gap_s = (to_wrap_ms + new_boot_ms) / 1e3 + dead_s  # receive time from the first boot's last to the second's first
    second = _shifted(_flight(12), 1.1 + gap_s)
    packets = (flight_packets(first, gimbal="mount-status", boot_ms0=WRAP - to_wrap_ms - 1100 - 1)
               + flight_packets(second, gimbal="mount-status", boot_ms0=new_boot_ms))
    caplog.clear()
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(packets))
    assert sum("rebooted 1 time" in r.getMessage() for r in caplog.records) == 1
    assert [r.t for r in records] == pytest.approx([f.t for f in first + second], abs=2e-3)
    assert [r.pitch_deg for r in records] == pytest.approx([f.pitch_deg for f in first + second], abs=0.02)


@pytest.mark.parametrize("last_ms", [WRAP - 61_000, 3_600_000])
def test_time_boot_ms_back_to_near_zero_from_far_from_the_wrap_is_a_reboot(caplog, last_ms):
    """Far from 2**32 ms (more than WRAP_WINDOW_S), going back to small values is a reboot whatever the receive
    times say."""
    first = _flight(12)
    second = _shifted(_flight(12), 1.2 + (WRAP - last_ms) / 1e3 if last_ms > WRAP // 2 else 5.0)
    packets = (flight_packets(first, boot_ms0=last_ms - 1100)
               + flight_packets(second, boot_ms0=100 if last_ms > WRAP // 2 else 1_000))
    with caplog.at_level("WARNING"):
        records = parse_tlog(_tlog(packets))
    assert sum("rebooted 1 time" in r.getMessage() for r in caplog.records) == 1
    assert [r.t for r in records] == pytest.approx([f.t for f in first + second], abs=2e-3)


# ---- the unwrapping itself -------------------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(before_ms=st.integers(1, 120_000), steps_ms=st.lists(st.integers(0, 2_000), min_size=2, max_size=80),
       jitter_s=st.lists(st.floats(0.0, 0.5), min_size=80, max_size=80), receive_times=st.booleans(),
       swap=st.integers(1, 78))
def test_unwrap_gives_the_time_since_boot_across_the_wrap(before_ms, steps_ms, jitter_s, receive_times, swap):
    """A boot clock from `before_ms` before 2**32 ms on, sent as uint32 and received with up to 0.5 s of latency
    jitter, two neighbours swapped (out of order): each value unwraps to the time since boot."""
    true_ms = [WRAP - before_ms]
    for step in steps_ms:
        true_ms.append(true_ms[-1] + step)
    rx = [T0 + ms / 1e3 + jitter_s[i] if receive_times else None for i, ms in enumerate(true_ms)]
    if swap + 1 < len(true_ms):  # the one sent first comes second, late
        true_ms[swap], true_ms[swap + 1] = true_ms[swap + 1], true_ms[swap]
    clock = BootTimeUnwrap()
    assert [clock.unwrap(ms % WRAP, r) for ms, r in zip(true_ms, rx, strict=True)] == true_ms


@settings(max_examples=200, deadline=None)
@given(to_wrap_ms=st.integers(1, 60_000), new_boot_ms=st.integers(0, 60_000), dead_s=st.floats(0.0, 600.0),
       later_ms=st.lists(st.integers(0, 1_000), max_size=20))
def test_unwrap_leaves_a_reboot_to_the_reboot_detection(to_wrap_ms, new_boot_ms, dead_s, later_ms):
    """The clock restarts `dead_s` after the old boot's last message (at `to_wrap_ms` before 2**32 ms): a wrap only
    where the receive times agree with one within REBOOT_S, else the new boot's values come out as they are."""
    assume(abs(dead_s - REBOOT_S) > 1e-3)  # not on the boundary
    clock = BootTimeUnwrap()
    clock.unwrap(WRAP - to_wrap_ms, T0)
    first_rx = T0 + (to_wrap_ms + new_boot_ms) / 1e3 + dead_s
    wraps = to_wrap_ms + new_boot_ms <= 60_000 and dead_s <= REBOOT_S  # one wrap later, just after it on its clock
    got = [clock.unwrap(new_boot_ms, first_rx)]
    ms = new_boot_ms
    for step in later_ms:
        ms += step
        got.append(clock.unwrap(ms, first_rx + (ms - new_boot_ms) / 1e3))
    offset = WRAP if wraps else 0
    assert got[0] == new_boot_ms + offset
    assert all(g - offset >= 0 for g in got) and got[-1] == ms + offset


def test_unwrap_without_receive_times_judges_by_the_values_alone():
    clock = BootTimeUnwrap()
    assert [clock.unwrap(v) for v in (WRAP - 1_000, WRAP - 500, 200, WRAP - 100, 700)] == [
        WRAP - 1_000, WRAP - 500, WRAP + 200, WRAP - 100, WRAP + 700]  # a late one before the wrap stays before it
    far = BootTimeUnwrap()
    assert [far.unwrap(v) for v in (WRAP - 61_000, 100)] == [WRAP - 61_000, 100]  # far from 2**32: not a wrap
    assert BootTimeUnwrap().unwrap(WRAP + 5) == WRAP + 5  # unwrapped already

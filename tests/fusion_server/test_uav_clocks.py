"""fusion_server.uav_clocks and the validator with it: a UAV whose clock runs ahead of the server's has its steady lead
taken on evidence, per UAV and kind, and its messages moved back by it; nothing else moves a lead."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fusion_server.uav_clocks import UavClocks
from fusion_server.validation import MessageValidator, Rejected
from shared.clock_lead import CONFIRM_MESSAGES, CONFIRM_S
from shared.keys import KeySpace
from shared.messages import CameraInfo, StateMessage, encode_state
from shared.tilecodec import TileMessage, encode_tile
from shared.tiles import TileGrid
from tests.fakeclock import Clocks
from tests.fusion_server.fake_agent import KEYS, TILE_X, TILE_Y

SKEW_S = 30.0
#: One message every STEP_S: the first CONFIRM_MESSAGES over CONFIRM_S is the fifth (at 2.0 s).
STEP_S = 0.5
ADOPTED_AT = max(CONFIRM_MESSAGES, int(CONFIRM_S / STEP_S) + 1) - 1




def clocks_and_time(**kwargs) -> tuple[UavClocks, Clocks]:
    clocks = Clocks()
    return UavClocks(SKEW_S, wall=lambda: clocks.wall, monotonic=lambda: clocks.mono, **kwargs), clocks


def run(uav_clocks: UavClocks, clocks: Clocks, uav: str, lead_s: float, n: int, kind: str = "tile",
        jitter_s: float = 0.0) -> list[float | None]:
    """n messages of ``uav`` stamped ``lead_s`` ahead, one every STEP_S: what lead_for answered."""
    shifts = []
    for i in range(n):
        shifts.append(uav_clocks.lead_for(uav, kind, clocks.wall + lead_s + (jitter_s if i % 2 else 0.0)))
        clocks.step(STEP_S)
    return shifts


@given(lead=st.floats(SKEW_S + 1.0, 3e9), jitter=st.floats(0.0, 2.0))
def test_a_steady_lead_is_taken_after_the_evidence_and_moves_the_messages_onto_the_server_clock(lead, jitter):
    uav_clocks, clocks = clocks_and_time()
    shifts = run(uav_clocks, clocks, "fast", lead, ADOPTED_AT + 4, jitter_s=jitter)
    assert shifts[:ADOPTED_AT] == [None] * ADOPTED_AT  # rejected, as before, until the evidence holds
    assert all(shift == pytest.approx(lead, abs=1e-6 * lead) for shift in shifts[ADOPTED_AT:])
    assert uav_clocks.leads() == {"fast": {"tile": pytest.approx(lead, abs=1e-6 * lead)}}
    t = clocks.wall + lead + 1.0
    assert abs(t - uav_clocks.lead_for("fast", "tile", t) - clocks.wall) <= 1.0 + 1e-6 * lead
    assert uav_clocks.lead_for("fast", "tile", clocks.wall + lead + SKEW_S + 5.0) is None  # beyond lead + skew


@given(offsets=st.lists(st.floats(-1e9, SKEW_S), min_size=1, max_size=30))
def test_a_uav_on_time_or_in_the_past_is_never_moved_nor_followed(offsets):
    uav_clocks, clocks = clocks_and_time()
    for offset in offsets:
        assert uav_clocks.lead_for("ontime", "tile", clocks.wall + offset) == 0.0
        clocks.step(STEP_S)
    assert uav_clocks.leads() == {} and not uav_clocks._clocks  # noqa: SLF001 - nothing held for it


def test_a_forged_stamp_or_a_burst_among_messages_on_time_moves_nothing():
    uav_clocks, clocks = clocks_and_time()
    for i in range(30):
        assert uav_clocks.lead_for("uav1", "tile", clocks.wall - 0.05) == 0.0  # the real UAV, on time
        if i % 3 == 0:
            assert uav_clocks.lead_for("uav1", "tile", clocks.wall + 3600.0) is None  # forged, interleaved
        clocks.step(0.2)
    for _ in range(50):  # fifty forged within one second
        assert uav_clocks.lead_for("uav1", "tile", clocks.wall + 600.0) is None
        clocks.step(0.02)
    assert uav_clocks.leads() == {}


@pytest.mark.parametrize("t", [1e300, math.inf, math.nan])
def test_an_absurd_stamp_stays_rejected_however_long_it_comes(t):
    uav_clocks, clocks = clocks_and_time()
    for _ in range(40):
        assert uav_clocks.lead_for("uav1", "tile", t) is None
        clocks.step(STEP_S)
    assert uav_clocks.leads() == {} and not uav_clocks._clocks  # noqa: SLF001


def test_the_message_confirming_a_lead_but_far_beyond_it_stays_out():
    uav_clocks, clocks = clocks_and_time()
    shifts = run(uav_clocks, clocks, "fast", 120.0, ADOPTED_AT)
    assert uav_clocks.lead_for("fast", "tile", clocks.wall + 1e9) is None  # the fifth: the lead taken is 120 s
    assert shifts == [None] * ADOPTED_AT and uav_clocks.leads() == {"fast": {"tile": 120.0}}


def test_two_uavs_with_different_leads_are_independent():
    uav_clocks, clocks = clocks_and_time()
    verdicts = []
    for _ in range(ADOPTED_AT + 3):
        verdicts.append((uav_clocks.lead_for("a", "tile", clocks.wall + 120.0),
                         uav_clocks.lead_for("b", "tile", clocks.wall + 3600.0),
                         uav_clocks.lead_for("c", "tile", clocks.wall)))
        clocks.step(STEP_S)
    assert verdicts[ADOPTED_AT:] == [(120.0, 3600.0, 0.0)] * 3
    assert uav_clocks.leads() == {"a": {"tile": 120.0}, "b": {"tile": 3600.0}}
    # b's lead lets none of a's messages 3600 s ahead in, and a forged burst under c's id moves nobody
    assert uav_clocks.lead_for("a", "tile", clocks.wall + 3600.0) is None
    for _ in range(3):
        assert uav_clocks.lead_for("c", "tile", clocks.wall + 120.0) is None
    assert uav_clocks.leads() == {"a": {"tile": 120.0}, "b": {"tile": 3600.0}}


def test_kinds_keep_their_own_lead_so_one_on_another_clock_never_flaps():
    # the tiles stamped from a GPS-disciplined source clock, the states from the companion's system clock
    uav_clocks, clocks = clocks_and_time()
    for i in range(40):
        assert uav_clocks.lead_for("uav1", "tile", clocks.wall) == 0.0
        state = uav_clocks.lead_for("uav1", "state", clocks.wall + 120.0)
        assert state == (None if i < ADOPTED_AT else 120.0)
        clocks.step(STEP_S)
    assert uav_clocks.leads() == {"uav1": {"state": 120.0}}


def test_a_uav_back_on_time_is_taken_as_it_is_at_once_and_its_lead_dropped_on_evidence():
    uav_clocks, clocks = clocks_and_time()
    run(uav_clocks, clocks, "fast", 120.0, ADOPTED_AT + 1)
    assert uav_clocks.leads() == {"fast": {"tile": 120.0}}
    # one replayed old message on time drops nothing, and the UAV's next message still gets its lead
    assert uav_clocks.lead_for("fast", "tile", clocks.wall - 600.0) == 0.0
    assert uav_clocks.lead_for("fast", "tile", clocks.wall + 120.0) == 120.0
    assert uav_clocks.leads() == {"fast": {"tile": 120.0}}
    # restarted with its clock set right: never moved, and after the evidence the lead is gone
    shifts = run(uav_clocks, clocks, "fast", 0.2, ADOPTED_AT + 2)
    assert shifts == [0.0] * (ADOPTED_AT + 2)
    assert uav_clocks.leads() == {} and not uav_clocks._clocks  # noqa: SLF001
    # and it is followed afresh: a lead comes back only on new evidence
    assert run(uav_clocks, clocks, "fast", 120.0, ADOPTED_AT + 1)[ADOPTED_AT - 1:] == [None, 120.0]


def test_a_clock_hours_ahead_put_back_to_minutes_ahead_takes_the_smaller_lead():
    uav_clocks, clocks = clocks_and_time()
    run(uav_clocks, clocks, "fast", 3600.0, ADOPTED_AT + 1)
    shifts = run(uav_clocks, clocks, "fast", 120.0, ADOPTED_AT + 2)
    assert shifts[:ADOPTED_AT] == [3600.0] * ADOPTED_AT  # in the past meanwhile: taken, moved back by the old lead
    assert shifts[ADOPTED_AT:] == [120.0, 120.0]
    assert uav_clocks.leads() == {"fast": {"tile": 120.0}}


def test_a_flood_of_made_up_ids_ahead_does_not_evict_a_uav_holding_a_lead():
    uav_clocks, clocks = clocks_and_time(max_clocks=8)
    run(uav_clocks, clocks, "real", 120.0, ADOPTED_AT + 1)
    for i in range(1000):
        assert uav_clocks.lead_for(f"forged{i}", "tile", clocks.wall + 600.0) is None
    assert len(uav_clocks._clocks) == 8  # noqa: SLF001 - bounded
    assert uav_clocks.lead_for("real", "tile", clocks.wall + 120.0) == 120.0


# ---- the validator with the clocks -------------------------------------------------------------------------

CAMERA = CameraInfo(width=1920, height=1080, fx=1400.0, fy=1400.0, cx=960.0, cy=540.0)


def validator_and_time() -> tuple[MessageValidator, Clocks]:
    uav_clocks, clocks = clocks_and_time()
    return MessageValidator(KeySpace(), TileGrid(), max_clock_skew_s=SKEW_S, wall=lambda: clocks.wall,
                            clocks=uav_clocks), clocks


def tile(t: float, seq: int, x: int = TILE_X) -> bytes:
    return encode_tile(TileMessage(uav="fast", cls="person", z=18, x=x, y=TILE_Y, n=256, t=t, seq=seq,
                                   values=np.zeros((256, 256), np.float32)))


def state(t: float) -> bytes:
    return encode_state(StateMessage(uav="fast", t=t, lat=47.67, lon=9.27, height_m=40.0, pitch_deg=60.0,
                                     heading_deg=0.0, footprint=(), camera=CAMERA))


def test_the_validator_moves_the_messages_of_a_uav_ahead_once_its_lead_is_taken():
    validator, clocks = validator_and_time()
    key = KEYS.uav_tile("fast", "person", 18, TILE_X, TILE_Y)
    reasons = []
    for _ in range(ADOPTED_AT + 2):
        t = clocks.wall + 120.0
        try:  # a seq in nanoseconds of the UAV's clock: beyond the server clock too
            received = validator.validate(key, tile(t, int(t * 1e9)), sparse=True)
        except Rejected as exc:
            reasons.append(exc.reason)
        else:
            assert received.lead_s == 120.0 and received.message.t == pytest.approx(clocks.wall)
            assert received.message.seq == int(t * 1e9)  # seq orders the UAV's own tiles: left as it came
        clocks.step(STEP_S)
    assert reasons == ["t_in_future"] * ADOPTED_AT
    for _ in range(ADOPTED_AT):  # the states are evidence of their own (their stamps may come from another clock)
        with pytest.raises(Rejected):
            validator.validate(KEYS.uav_state("fast"), state(clocks.wall + 120.0))
        clocks.step(STEP_S)
    received = validator.validate(KEYS.uav_state("fast"), state(clocks.wall + 120.0))
    assert received.lead_s == 120.0 and received.message.t == pytest.approx(clocks.wall)
    with pytest.raises(Rejected) as info:  # 2**64 - 1 stays out with the lead
        validator.validate(key, tile(clocks.wall + 120.0, 2**64 - 1))
    assert info.value.reason == "seq_in_future"


def test_a_malformed_message_ahead_keeps_its_reason_and_is_no_evidence():
    validator, clocks = validator_and_time()
    wrong_key = KEYS.uav_tile("fast", "person", 18, TILE_X + 1, TILE_Y)
    for i in range(ADOPTED_AT + 3):
        with pytest.raises(Rejected) as info:
            validator.validate(wrong_key, tile(clocks.wall + 120.0, i + 1))
        assert info.value.reason == "t_in_future"  # as before the clocks: the time is checked first
        clocks.step(STEP_S)
    assert validator.clocks is not None and validator.clocks.leads() == {}

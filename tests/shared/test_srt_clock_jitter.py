"""DJI SRT date-time lines that jitter by a few milliseconds about the subtitle timing (the real Matrice 30 sample
of tests/shared/test_telemetry.py has dates 182 ms apart under a 198 ms timing): a date now and then a little before
the one above it is jitter, not a new clock (shared.telemetry.srt_clock.monotonic_times)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.telemetry.srt import parse_srt_report
from shared.telemetry.srt_clock import BlockTimes, monotonic_times

T0 = 1_700_000_000.0


def _srt(times: np.ndarray, fps: float) -> str:
    blocks = []
    for k, stamp in enumerate(times):
        start, end = round(1000 * k / fps), round(1000 * (k + 1) / fps)
        ms = int(round(stamp * 1000.0))
        date = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ms // 1000)) + f".{ms % 1000:03d}"
        blocks.append(f"{k + 1}\n00:{start // 60000:02d}:{start // 1000 % 60:02d},{start % 1000:03d} --> "
                      f"00:{end // 60000:02d}:{end // 1000 % 60:02d},{end % 1000:03d}\n"
                      f'<font size="28">FrameCnt: {k + 1}, DiffTime: {round(1000 / fps)}ms\n{date}\n'
                      f"[latitude: {48.5 + 1e-6 * k:.6f}] [longitude: 9.060000] [rel_alt: 40.000 abs_alt: 440.000] "
                      "</font>\n")
    return "\n".join(blocks)


@settings(max_examples=15, deadline=None)
@given(jitter_ms=st.floats(1.0, 30.0), fps=st.sampled_from([25.0, 29.97, 30.0, 60.0]), seed=st.integers(0, 99))
def test_jittery_dates_stay_on_the_frames(jitter_ms: float, fps: float, seed: int) -> None:
    # 20 s of blocks whose dates are the frame times give or take `jitter_ms`: every record within the jitter of
    # its frame (until 1 Dec 2026 each date before the one above started a new clock one frame step on, and the
    # steps added up: 0.70 s late after 60 s at 30 fps and 20 ms)
    n = int(20 * fps)
    frames = np.arange(n) / fps
    jitter = np.random.default_rng(seed).uniform(-jitter_ms, jitter_ms, n) / 1000.0
    report = parse_srt_report(_srt(T0 + frames + jitter, fps), source="jitter.SRT")
    t = np.array([r.t for r in report.records])
    assert len(t) == n and np.all(np.diff(t) >= 0)  # (two dates may be equal to the ms)
    assert np.abs(t - T0 - frames).max() <= jitter_ms / 1000.0 + 0.002
    assert report.clock_notes == ()


def test_a_real_step_back_is_still_a_new_clock() -> None:
    # 0.1 s is jitter at most; a date 0.5 s before the one above (a clock set back) is joined on as before, and a
    # date that goes back where the subtitle timing starts again too (two recordings) as well
    def block(line: int, epoch: float, start: float) -> BlockTimes:
        return BlockTimes(line=line, epoch_s=epoch, start_s=start, counter=None, diff_time_s=None)

    times, notes = monotonic_times([block(1, 100.0, 0.0), block(5, 100.04, 0.033), block(9, 100.03, 0.066),
                                    block(13, 100.1, 0.1)])
    assert times == pytest.approx([100.0, 100.04, 100.041, 100.1]) and notes == []
    times, notes = monotonic_times([block(1, 100.0, 0.0), block(5, 100.033, 0.033), block(9, 99.5, 0.066)])
    assert times[2] == pytest.approx(100.066) and len(notes) == 1 and "goes back 0.533 s" in notes[0]
    times, notes = monotonic_times([block(1, 100.0, 0.0), block(5, 100.033, 0.033), block(9, 100.02, 0.0)])
    assert len(notes) == 1 and "goes back" in notes[0]

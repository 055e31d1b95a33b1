"""One monotonic clock for the blocks of a DJI SRT file, from its date-time lines, subtitle timing and frame counters.

A block's own time comes from its date-time line (UNIX epoch), else its subtitle start, else its frame counter
times ``DiffTime``. Files concatenated from several recordings mix these or jump back; this module joins them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from shared.telemetry.dates import truncated_date_offset

#: Date steps and subtitle-timing steps further apart than this disagree (DJI date lines of the oldest
#: firmware have whole seconds only, so 1 s of difference is normal).
CLOCK_TOLERANCE_S = 1.5
#: A date-time at most this much before the block before it, where the subtitle timing goes on, is jitter in the
#: stamps (a date now and then a few ms early), not a new clock: it is taken 1 ms after the block before
#: (`JITTER_STEP_S`). Taken as a new run, each such step moved every later block one frame step late, adding up.
JITTER_BACK_S = 0.1
JITTER_STEP_S = 0.001
_FALLBACK_STEP_S = 1.0


@dataclass(frozen=True, slots=True)
class BlockTimes:
    """The time sources of one block (None where the block lacks one) and its first line (for messages)."""

    line: int
    epoch_s: float | None
    start_s: float | None
    counter: int | None
    diff_time_s: float | None

    def source(self) -> str | None:
        """The block's own clock: 'date', 'timing', 'counter', or None when it has no time at all."""
        if self.epoch_s is not None:
            return "date"
        if self.start_s is not None:
            return "timing"
        if self.counter is not None and self.diff_time_s is not None:
            return "counter"
        return None


def _secondary_step(a: BlockTimes, b: BlockTimes) -> float | None:
    """The step from a to b by the relative clocks (subtitle timing, else frame counter), if both have one."""
    if a.start_s is not None and b.start_s is not None:
        return b.start_s - a.start_s
    if a.counter is not None and b.counter is not None and b.diff_time_s is not None:
        return (b.counter - a.counter) * b.diff_time_s
    return None


def _runs(blocks: Sequence[BlockTimes]) -> tuple[list[list[int]], list[float], list[str]]:
    """Split blocks into runs that share one clock source whose steps are forward and agree with the
    relative clock; also each block's value on its run's clock, and why each run after the first began."""
    runs: list[list[int]] = []
    values: list[float] = []
    reasons: list[str] = []
    for i, block in enumerate(blocks):
        source = block.source()
        value = 0.0
        if source == "date":
            assert block.epoch_s is not None
            value = block.epoch_s
        elif source == "timing":
            assert block.start_s is not None
            value = block.start_s
        else:
            assert block.counter is not None and block.diff_time_s is not None
            value = max(block.counter - 1, 0) * block.diff_time_s
        reason = ""
        if i > 0:
            prev = blocks[i - 1]
            step = value - values[-1]
            secondary = _secondary_step(prev, block)
            if source == "counter" and prev.source() == "counter" and secondary is not None and secondary >= 0.0:
                value = values[-1] + secondary  # cumulative: DiffTime alternates 41/42 ms at 23.976 fps
                step = secondary
            if source == "date" and prev.source() == source and -JITTER_BACK_S <= step < 0.0 \
                    and (secondary is None or secondary > 0.0):
                value = values[-1] + JITTER_STEP_S
                step = JITTER_STEP_S
            if prev.source() != source:
                reason = f"line {block.line}: the blocks' clock changes from {prev.source()} to {source}"
            elif step < 0.0:
                reason = f"line {block.line}: the {_name(source)} goes back {-step:.3f} s"
            elif secondary is not None and abs(step - secondary) > CLOCK_TOLERANCE_S:
                other = "subtitle timing" if prev.start_s is not None and block.start_s is not None else "frame counter"
                reason = (
                    f"line {block.line}: the {_name(source)} advances {step:.3f} s where the {other} "
                    f"advances {secondary:.3f} s"
                )
        if i == 0 or reason:
            runs.append([i])
            reasons.append(reason)
        else:
            runs[-1].append(i)
        values.append(value)
    return runs, values, reasons


def _refine_whole_second_dates(run: list[int], blocks: Sequence[BlockTimes], values: list[float]) -> None:
    """Date lines with whole seconds only (the oldest firmware) under finer subtitle timing: the blocks of one
    second share a date, and as stamps they would be one sample. Within a run of such dates every block has the
    time its subtitle timing gives, placed on the dates: the offset c with floor(c + timing) equal to each date
    (the middle of the offsets all dates allow; the median when truncation does not explain them, e.g. rounded
    dates). `values` (the blocks' dates) is changed in place."""
    dates = [values[i] for i in run]
    starts = [blocks[i].start_s for i in run]
    if blocks[run[0]].source() != "date" or len(run) < 2 or len(set(dates)) == len(dates) \
            or any(d != math.floor(d) for d in dates) or any(st is None for st in starts) \
            or any(b < a for a, b in zip(starts, starts[1:], strict=False)):  # type: ignore[operator]
        return  # (a timing that steps back inside the run would make the times go back: the dates stay)
    gaps = [d - st for d, st in zip(dates, starts, strict=True) if st is not None]
    c = truncated_date_offset(gaps)
    if c is None:
        c = sorted(gaps)[len(gaps) // 2] + 0.5
    for i, st in zip(run, starts, strict=True):
        assert st is not None
        values[i] = c + st


def _name(source: str | None) -> str:
    return {"date": "date-time", "timing": "subtitle timing", "counter": "frame counter"}.get(source or "", "clock")


def _typical_step(runs: list[list[int]], values: list[float]) -> float:
    steps = [values[j] - values[i] for run in runs for i, j in zip(run, run[1:], strict=False) if values[j] > values[i]]
    if not steps:
        return _FALLBACK_STEP_S
    steps.sort()
    return steps[len(steps) // 2]


def monotonic_times(blocks: Sequence[BlockTimes]) -> tuple[list[float], list[str]]:
    """Times for the blocks, non-decreasing in file order, and notes where the sources disagreed.

    Parameters
    ----------
    blocks : sequence of BlockTimes
        In file order; each must have a source (`BlockTimes.source` not None).

    Returns
    -------
    times : list of float
        Within a run of blocks on one consistent clock, the block's own value (so a file whose dates are
        consistent gets exactly its dates, one without dates its subtitle times; dates at whole seconds that
        repeat under finer subtitle timing get the timing, placed on the dates: `_refine_whole_second_dates`).
        Where the clock source changes or disagrees, the next run is joined on: a run of dates that lies
        ahead keeps its dates (absolute time matters for fusing several UAVs); any other run is shifted to
        continue one step
        after the previous block (the step from the subtitle timing or frame counter across the seam,
        else the file's typical step). Runs before the first dated run are shifted to end one step
        before it, so a file with any date gets an epoch clock throughout.
    notes : list of str
        One per seam where the sources disagreed or the clock changed, naming the line.
    """
    if not blocks:
        return [], []
    if any(block.source() is None for block in blocks):
        raise ValueError("monotonic_times: every block needs a date-time, subtitle timing or frame counter")
    runs, values, reasons = _runs(blocks)
    for run in runs:
        _refine_whole_second_dates(run, blocks, values)
    typical = _typical_step(runs, values)
    offsets = [0.0] * len(runs)
    notes: list[str] = []

    def seam_step(before: int, after: int) -> float:
        step = _secondary_step(blocks[before], blocks[after])
        return step if step is not None and 0.0 < step <= 10.0 * max(typical, _FALLBACK_STEP_S) else typical

    first_dated = next((k for k, run in enumerate(runs) if blocks[run[0]].source() == "date"), None)
    anchor = first_dated if first_dated is not None else 0
    for k in range(anchor - 1, -1, -1):  # undated runs before the first dated one end one step before it
        last, nxt = runs[k][-1], runs[k + 1][0]
        offsets[k] = values[nxt] + offsets[k + 1] - seam_step(last, nxt) - values[last]
        notes.append(f"{reasons[k + 1]}: the blocks before it were placed on its clock")
    for k in range(anchor + 1, len(runs)):
        last, first = runs[k - 1][-1], runs[k][0]
        previous_t = values[last] + offsets[k - 1]
        if blocks[first].source() == "date" and values[first] >= previous_t:
            if "clock changes" not in reasons[k]:
                notes.append(f"{reasons[k]}: kept the dates")
            continue
        offsets[k] = previous_t + seam_step(last, first) - values[first]
        notes.append(f"{reasons[k]}: continued {seam_step(last, first):.3f} s after the block before")
    times = [0.0] * len(blocks)
    for k, run in enumerate(runs):
        for i in run:
            times[i] = values[i] + offsets[k]
    assert all(math.isfinite(t) for t in times)
    return times, notes

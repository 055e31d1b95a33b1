"""DJI SRT text to blocks: where one subtitle block ends and the next begins, and the raw facts each one states.

Nothing here decides what a fact means for the record (axis order, height, clock): that is `shared.telemetry.srt`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from shared.telemetry.dates import DATE_START_RE, DATETIME_RE, epoch_from_match
from shared.telemetry.text import NUM, NUM_RE

TIMING_RE = re.compile(
    r"(\d{1,9}):(\d{1,2}):(\d{1,2})[,.](\d{1,3})\s*-->\s*(\d{1,9}):(\d{1,2}):(\d{1,2})[,.](\d{1,3})"
)
_INDEX_RE = re.compile(r"[0-9]{1,12}")
_HTML_TAG_RE = re.compile(r"<[^<>]*>")
_TOKEN = r"\s*:\s*([^\s\[\],]*)"  # the raw value after "key:", checked afterwards so garbage is reported
_SRT_KEYS = {
    "latitude": re.compile(r"\blatitude" + _TOKEN, re.IGNORECASE),
    "longitude": re.compile(r"\blongt?itude" + _TOKEN, re.IGNORECASE),  # Mavic 2 firmware writes "longtitude"
    "rel_alt": re.compile(r"\brel_alt" + _TOKEN, re.IGNORECASE),
    "abs_alt": re.compile(r"\babs_alt" + _TOKEN, re.IGNORECASE),
    "altitude": re.compile(r"\baltitude" + _TOKEN, re.IGNORECASE),
    "barometer": re.compile(r"\bBAROMETER" + _TOKEN, re.IGNORECASE),
    "Hb": re.compile(r"\bHb" + _TOKEN),  # the oldest firmware: barometric height ...
    "Hs": re.compile(r"\bHs" + _TOKEN),  # ... and sonar height
    "gb_pitch": re.compile(r"\bgb_pitch" + _TOKEN, re.IGNORECASE),
    "gb_yaw": re.compile(r"\bgb_yaw" + _TOKEN, re.IGNORECASE),
    "gb_roll": re.compile(r"\bgb_roll" + _TOKEN, re.IGNORECASE),
    "diff_time": re.compile(r"\bDiffTime" + _TOKEN, re.IGNORECASE),
}
_COUNTER_RE = re.compile(r"\b(?:FrameCnt|SrtCnt)" + _TOKEN, re.IGNORECASE)
_GPS_TUPLE_RE = re.compile(r"\b(GPS|RTK)\s*\(([^()]*)\)")
_GIMBAL_PRY_RE = re.compile(r"\bG\.PRY\s*\(([^()]*)\)")
_HEIGHT_H_RE = re.compile(rf"(?<![\w.])H\s*[:=]?\s*({NUM})\s*m(?![/\w])")
_SPEED_HS_RE = re.compile(rf"\bH\.S\s*[:=]?\s*({NUM})\s*m/s")
_METRES_RE = re.compile(rf"({NUM})\s*[mM]?")
_MS_RE = re.compile(rf"({NUM})\s*(?:ms)?")
_ANGLE_RE = re.compile(rf"({NUM})\s*(?:°|Â°|deg)?")
_NOT_AVAILABLE = ("n/a", "na", "nan", "")
_METRE_KEYS = ("barometer", "Hb", "Hs")
#: Camera items read leniently (a value that is not a number is left out, the block kept): the zoom.
_CAMERA_KEYS = {
    # [dzoom_ratio: 10000, delta:0] (Mini 3, Air 2S), [dzoom_ratio: 1.77] (Matrice 30), DZOOM 1.000 (Mini 2)
    "dzoom_ratio": re.compile(r"\b(?:dzoom_ratio\s*:|dzoom\s*[:=]?)\s*([^\s\[\],]*)", re.IGNORECASE),
    "focal_len": re.compile(r"\bfocal_len" + _TOKEN, re.IGNORECASE),
}


class BadBlock(ValueError):
    """One block that cannot become a record: the line it is about and why (the file goes on without it)."""

    def __init__(self, line: int, reason: str) -> None:
        super().__init__(f"line {line}: {reason}")
        self.line = line
        self.reason = reason


@dataclass
class RawBlock:
    """The lines of one block as split from the text: (line number, text without HTML tags)."""

    lines: list[tuple[int, str]] = field(default_factory=list)
    timing: int | None = None  # index into lines of the timing line
    markers: set[str] = field(default_factory=set)  # "date", "counter": a second one starts a new block

    @property
    def first_line(self) -> int:
        return self.lines[0][0]

    def only_index(self) -> bool:
        return len(self.lines) == 1 and _INDEX_RE.fullmatch(self.lines[0][1]) is not None

    def take_trailing_index(self) -> tuple[int, str] | None:
        """Remove and return a bare subtitle index that ends this block (it opens the next one)."""
        if len(self.lines) > 1 and self.timing != len(self.lines) - 1 and _INDEX_RE.fullmatch(self.lines[-1][1]):
            return self.lines.pop()
        return None


def split_blocks(text: str) -> list[RawBlock]:
    """Cut SRT text into blocks.

    A blank line ends a block. Where blocks are not separated by blank lines, a timing line
    (``HH:MM:SS,mmm --> HH:MM:SS,mmm``) starts a new block, and so does a second date-time or frame-counter
    line in a block without a timing line (firmware that writes no timing lines); a bare subtitle index
    just before such a line moves to the new block with it.
    """
    blocks: list[RawBlock] = []
    current: RawBlock | None = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip():
            current = None
            continue
        line = _HTML_TAG_RE.sub(" ", raw).strip()
        if not line:
            continue
        markers = set()
        if "-->" not in line:
            if DATETIME_RE.search(line) is not None:
                markers.add("date")
            if _COUNTER_RE.search(line) is not None:
                markers.add("counter")
        starts_block = current is None
        if current is not None and "-->" in line:
            starts_block = current.timing is not None or not current.only_index()
        elif current is not None and current.timing is None and markers & current.markers:
            starts_block = True
        if starts_block:
            moved = current.take_trailing_index() if current is not None else None
            current = RawBlock(lines=[moved] if moved is not None else [])
            blocks.append(current)
        assert current is not None
        if "-->" in line:
            current.timing = len(current.lines)
        current.lines.append((lineno, line))
        current.markers |= markers
    return blocks


@dataclass
class BlockFacts:
    """What one block states, each value with the line it came from; coordinates keep their decimals."""

    first_line: int
    index: int | None = None
    start_s: float | None = None  # subtitle start time
    epoch_s: float | None = None  # from a date-time line
    counter: int | None = None  # FrameCnt / SrtCnt
    values: dict[str, tuple[float, int]] = field(default_factory=dict)
    decimals: dict[str, int] = field(default_factory=dict)  # "latitude"/"longitude"/"gps" -> decimals written
    gps: tuple[float, float, bool, str, int] | None = None  # a, b, third value has an "M" suffix, "GPS"/"RTK", line
    gimbal_pry: tuple[float, float, float, int] | None = None

    @property
    def frame(self) -> int | None:
        return self.counter if self.counter is not None else self.index


def _number(line: int, key: str, token: str, pattern: re.Pattern[str] = NUM_RE) -> float:
    match = pattern.fullmatch(token)
    if match is None:
        raise BadBlock(line, f"{key} value {token!r} is not a number")
    value = float(match.group(1) if match.groups() else match.group(0))
    if not math.isfinite(value):
        raise BadBlock(line, f"{key} value {token!r} is not finite")
    return value


def _decimals(token: str) -> int:
    """Digits written after the decimal point: the resolution the firmware logs at."""
    digits = token.strip().lstrip("+-").split(".")
    return len(digits[1]) if len(digits) == 2 else 0


def block_facts(block: RawBlock, utc_offset_s: float) -> BlockFacts:
    """Read the facts of one block.

    Raises
    ------
    BadBlock
        For a malformed timing, date-time, counter, number, GPS or G.PRY field, naming its line.
    """
    facts = BlockFacts(first_line=block.first_line)
    lines = block.lines
    if lines and _INDEX_RE.fullmatch(lines[0][1]) and block.timing != 0:
        facts.index = int(lines[0][1])
        lines = lines[1:]
    gps_text: tuple[str, str, str, int] | None = None
    for lineno, line in lines:
        if "-->" in line:
            match = TIMING_RE.fullmatch(line)
            if match is None:
                raise BadBlock(lineno, f"malformed subtitle timing line {line[:80]!r}")
            if facts.start_s is None:
                h, m, s, frac = match.group(1, 2, 3, 4)
                facts.start_s = int(h) * 3600 + int(m) * 60 + int(s) + int(frac) / 10 ** len(frac)
            continue
        if facts.counter is None and (counter := _COUNTER_RE.search(line)) is not None:
            if not _INDEX_RE.fullmatch(counter.group(1)):
                raise BadBlock(lineno, f"frame counter {counter.group(1)!r} is not a non-negative integer")
            facts.counter = int(counter.group(1))
        for key, pattern in _SRT_KEYS.items():
            match = pattern.search(line)
            if match is None or key in facts.values:
                continue
            token = match.group(1)
            number_re = _METRES_RE if key in _METRE_KEYS else _MS_RE if key == "diff_time" else NUM_RE
            facts.values[key] = (_number(lineno, key, token, number_re), lineno)
            if key in ("latitude", "longitude"):
                facts.decimals[key] = _decimals(token)
        if facts.epoch_s is None:
            date = DATETIME_RE.search(line)
            if date is not None:
                try:
                    facts.epoch_s = epoch_from_match(date, utc_offset_s)
                except (ValueError, OverflowError) as err:
                    raise BadBlock(lineno, f"invalid date-time {date.group(0)!r}: {err}") from None
            elif DATE_START_RE.search(line):
                raise BadBlock(lineno, f"date-time does not parse: {line[:80]!r}")
        if gps_text is None and (gps := _GPS_TUPLE_RE.search(line)) is not None:
            gps_text = (gps.group(0), gps.group(1), gps.group(2), lineno)
        if facts.gimbal_pry is None and (pry := _GIMBAL_PRY_RE.search(line)) is not None:
            parts = [part.strip() for part in pry.group(1).split(",")]
            if len(parts) != 3:
                raise BadBlock(lineno, f"G.PRY {pry.group(0)!r} needs pitch, roll, yaw")
            p, r, y = (_number(lineno, "G.PRY", part, _ANGLE_RE) for part in parts)
            facts.gimbal_pry = (p, r, y, lineno)
        for key, pattern in _CAMERA_KEYS.items():
            if key not in facts.values and (match := pattern.search(line)) is not None:
                number = NUM_RE.fullmatch(match.group(1))
                if number is not None and math.isfinite(float(number.group(0))):
                    facts.values[key] = (float(number.group(0)), lineno)
        if "H" not in facts.values and (height := _HEIGHT_H_RE.search(line)) is not None:
            facts.values["H"] = (_number(lineno, "H", height.group(1)), lineno)
        if "H.S" not in facts.values and (speed := _SPEED_HS_RE.search(line)) is not None:
            facts.values["H.S"] = (_number(lineno, "H.S", speed.group(1)), lineno)
    if gps_text is not None and "latitude" not in facts.values:  # a named latitude beats a positional tuple
        _read_gps_tuple(facts, *gps_text)
    return facts


def _read_gps_tuple(facts: BlockFacts, whole: str, kind: str, inner: str, lineno: int) -> None:
    parts = [part.strip() for part in inner.split(",")]
    if len(parts) not in (2, 3):
        raise BadBlock(lineno, f"GPS tuple {whole!r} needs 2 or 3 values")
    if parts[0].lower() in _NOT_AVAILABLE or parts[1].lower() in _NOT_AVAILABLE:
        raise BadBlock(lineno, f"no GPS fix: {whole}")
    a = _number(lineno, "GPS", parts[0])
    b = _number(lineno, "GPS", parts[1])
    if len(parts) == 3 and parts[2].lower() not in _NOT_AVAILABLE:
        _number(lineno, "GPS third value", parts[2], _METRES_RE)
    facts.decimals["gps"] = max(_decimals(parts[0]), _decimals(parts[1]))
    facts.gps = (a, b, len(parts) == 3 and parts[2][-1:] in ("M", "m"), kind, lineno)

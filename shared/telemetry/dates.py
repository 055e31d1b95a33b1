"""Date-time strings of drone logs (ISO 8601, EXIF, DJI ``2017.07.29 15:18:50``, ``,ms,us``) to epoch seconds."""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import datetime, timedelta, timezone

# 2020-08-24T15:45:20 | 2017.07.29 15:18:50 | 2020:08:24 15:45:20 (EXIF) | 2022-08-07 13:40:40,774,808 (DJI ms,us)
# | 2024-05-01 01:01:53.100 PM (Litchi's local time)
DATETIME_RE = re.compile(
    r"(?P<y>\d{4})[-.:/](?P<mo>\d{1,2})[-.:/](?P<d>\d{1,2})(?:T|\s+)(?P<h>\d{1,2}):(?P<mi>\d{1,2}):(?P<s>\d{1,2})"
    r"(?:[.,](?P<frac>\d{1,9}))?(?:,(?P<us>\d{3}))?(?:\s*(?P<ampm>[AaPp][Mm]))?(?:\s*(?P<tz>Z|[+-]\d{2}:?\d{2}))?"
)
DATE_START_RE = re.compile(r"(?<![\d.])\d{4}[-./]\d{1,2}[-./]\d{1,2}(?![\d.])")


def epoch_from_match(match: re.Match[str], utc_offset_s: float) -> float:
    """Seconds since the epoch; a naive time is the drone clock at UTC + utc_offset_s."""
    fields = {k: int(v) for k, v in match.groupdict().items() if v is not None and k not in ("frac", "tz", "ampm")}
    if match["ampm"]:  # a 12-hour clock (Litchi's datetime(local): 2024-05-01 01:01:53.000 PM)
        if not 1 <= fields["h"] <= 12:
            raise ValueError(f"hour {fields['h']} is not on a 12-hour clock")
        fields["h"] = fields["h"] % 12 + (12 if match["ampm"].lower() == "pm" else 0)
    stamp = datetime(
        fields["y"], fields["mo"], fields["d"], fields["h"], fields["mi"], fields["s"], tzinfo=timezone.utc
    )
    seconds = stamp.timestamp()
    if match["frac"]:
        seconds += int(match["frac"]) / 10 ** len(match["frac"])
    if match["us"]:  # the ",808" of DJI's "40,774,808": microseconds after the milliseconds
        seconds += int(match["us"]) * 1e-6
    tz = match["tz"]
    if tz is None:
        return seconds - utc_offset_s
    if tz == "Z":
        return seconds
    sign = -1.0 if tz[0] == "-" else 1.0
    digits = tz[1:].replace(":", "")
    return seconds - sign * (int(digits[:2]) * 3600 + int(digits[2:]) * 60)


def parse_datetime(text: str, *, utc_offset_s: float = 0.0) -> float:
    """Parse a date-time string to seconds since the UNIX epoch.

    Parameters
    ----------
    text : str
        ISO 8601 (``2020-08-24T15:45:20.5``, optional ``Z`` or ``+02:00``), EXIF (``2020:08:24 15:45:20``)
        or DJI (``2017.07.29 15:18:50``, ``2022-08-07 13:40:40,774,808``).
    utc_offset_s : float
        Offset of the clock that wrote a naive time from UTC (e.g. 7200 for CEST); ignored when the text
        carries its own zone. Naive times are UTC by default.

    Raises
    ------
    ValueError
        If the text is not one of these forms or names an impossible date.
    """
    match = DATETIME_RE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"{text!r} is not a date-time like 2020-08-24T15:45:20")
    try:
        return epoch_from_match(match, utc_offset_s)
    except (ValueError, OverflowError) as err:
        raise ValueError(f"{text!r} is not a valid date-time: {err}") from None


def format_datetime(t: float) -> str:
    try:
        stamp = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(seconds=t)
    except OverflowError as err:
        raise ValueError(f"t={t!r} cannot be written as a date: {err}") from None
    return stamp.replace(tzinfo=None).isoformat(timespec="microseconds")


def truncated_date_offset(gaps: Sequence[float]) -> float | None:
    """The offset c with floor(c + time) = date for every row, from its date - time gaps (dates truncated to whole
    seconds beside a finer clock): the middle of the offsets all of them allow; None when truncation does not
    explain them (rounded dates, a start date on every row)."""
    lo, hi = max(gaps), min(gaps) + 1.0
    return 0.5 * (lo + hi) if lo < hi else None

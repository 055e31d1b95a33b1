"""Telemetry tables (CSV with a header row, e.g. AirData exports): column aliases, units, DJI pitch rule."""

from __future__ import annotations

import csv
import io
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.telemetry.columns import CSV_COLUMNS, OPTIONAL_FIELDS, UnknownUnit, match_column, unit_rank
from shared.telemetry.dates import DATETIME_RE, parse_datetime, truncated_date_offset
from shared.telemetry.interpolation import spread_whole_second_stamps
from shared.telemetry.record import PITCH_TOLERANCE_DEG, Telemetry, pitch_or_none
from shared.telemetry.text import NUM_RE, read_text

log = logging.getLogger(__name__)

_DJI_PITCH_COLUMNS = ("gb_pitch", "gimbal_pitch_dji", "gimbal.pitch", "gimbalpitchraw")
#: A bare `pitch` column below this depression in every row is likely the airframe's pitch (a warning says so).
_AIRFRAME_PITCH_DEG = 10.0
#: Columns that name the drone a row belongs to (a log of several drones): one drone per file is read.
_DRONE_COLUMNS = ("uav", "uav_id", "uas_id", "drone", "drone_id", "drone_name", "drone_serial", "vehicle",
                  "vehicle_id", "vehicle_name", "aircraft", "aircraft_id", "aircraft_name", "aircraft_serial",
                  "aircraft_sn", "serial", "serial_number", "sn", "sysid", "system_id")
#: Ground speed (m/s) no drone flies: consecutive rows further apart than this are not one flight.
_MAX_SPEED_MPS = 150.0
#: Longest time (s) between two rows with a position across which the rows written without one are filled
#: (`_fill_sparse_positions`: a log whose GPS is slower than its rows; 0.2 Hz is the slowest GPS such logs hold).
SPARSE_FILL_MAX_S = 5.0
#: A unitless time column whose values exceed this is in milliseconds since 1970 (in seconds: the year 5138).
_EPOCH_MS_MIN = 1e11
#: A unitless time column whose median step between distinct stamps is at least this is in milliseconds (a drone
#: log in seconds samples every few seconds at most; in milliseconds 50 Hz is a step of 20, 10 Hz of 100), unless
#: its values are epoch seconds (`_EPOCH_S_MIN` .. `_EPOCH_MS_MIN`).
_MS_STEP_MIN = 20.0
_EPOCH_S_MIN = 1e8
#: A time column stepping back by more than this (s) while the dates go on has started again (a reset).
_RESET_S = 1.0
#: Cells that say a value is missing (pandas writes NaN, R NA, JSON-minded tools null): read as an empty cell.
_MISSING = frozenset({"nan", "na", "n/a", "null", "none", "-"})
#: Yes/no columns and the words they may hold (AirData's isVideo as pandas writes it: True / False).
_BOOLEAN_COLUMNS = CSV_COLUMNS["recording"][0]
_BOOLEANS = {"true": 1.0, "false": 0.0, "yes": 1.0, "no": 0.0, "recording": 1.0}  # CUSTOM.isVideo: "Recording" or empty


@dataclass
class _CsvColumn:
    field: str
    name: str  # as written in the header
    alias: str
    index: int
    scale: float


def _csv_columns(header: list[str], header_line: int, source: str) -> dict[str, _CsvColumn]:
    found: dict[str, _CsvColumn] = {}
    for index, cell in enumerate(header):
        try:
            matched = match_column(cell)
        except UnknownUnit as err:
            if err.field not in OPTIONAL_FIELDS:
                raise ValueError(f"{source}:{header_line}: {err}") from None
            log.warning("%s:%d: %s: the column is left out (no pose needs it)", source, header_line, err)
            continue
        if matched is None:
            continue
        fld, name, scale = matched
        aliases = CSV_COLUMNS[fld][0]
        column = _CsvColumn(fld, cell.strip(), name, index, scale)
        previous = found.get(fld)
        if previous is not None and previous.alias == name:
            ranks = unit_rank(fld, previous.name), unit_rank(fld, cell)
            if ranks[0] == ranks[1]:
                raise ValueError(
                    f"{source}:{header_line}: columns {previous.name!r} and {cell.strip()!r} are the same field"
                )
            if ranks[1] < ranks[0]:  # one name in two units (height [m] and [ft]): the preferred unit
                found[fld] = column
            continue
        if previous is None or aliases.index(name) < aliases.index(previous.alias):
            found[fld] = column
    for required in ("lat", "lon", "height"):
        if required not in found:
            names = ", ".join(CSV_COLUMNS[required][0])
            separator = next((sep for sep in (";", "\t", "|") if any(sep in cell for cell in header)), None)
            hint = "" if separator is None else (f"; the header holds {separator!r}: the file is separated by "
                                                 f"{'tabs' if separator == chr(9) else repr(separator)}, not commas "
                                                 "(save it comma-separated, with '.' as the decimal mark)")
            raise ValueError(f"{source}: missing required column {required!r} (accepted names: {names}){hint}")
    if "time" not in found and "datetime" not in found:
        names = ", ".join(CSV_COLUMNS["time"][0] + CSV_COLUMNS["datetime"][0])
        raise ValueError(f"{source}: missing required column 'time' (accepted names: {names})")
    return found


def _csv_float(cell: str, line: int, column: _CsvColumn, source: str) -> float | None:
    text = cell.strip()
    if not text or text.lower() in _MISSING:  # pandas writes NaN, R NA: a missing value, as an empty cell
        return None
    if column.alias in _BOOLEAN_COLUMNS and text.lower() in _BOOLEANS:
        return _BOOLEANS[text.lower()]
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{source}:{line}: column {column.name!r}: {text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{source}:{line}: column {column.name!r}: {text[:40]!r} is not finite")
    return value * column.scale


def parse_csv(
    text: str, *, source: str = "<csv>", utc_offset_s: float = 0.0, height_offset_m: float = 0.0
) -> list[Telemetry]:
    """Parse a comma-separated telemetry table with a header row.

    Column names are matched case-insensitively, with an optional unit in parentheses or brackets, as
    AirData exports write them (``time(millisecond)``, ``height_above_takeoff(feet)``, ``speed(mph)``):

    - time: ``time_s, time, t, timestamp`` (seconds or ms; numbers, or date-times) and/or ``date_time,
      datetime, datetime(utc)``. With both, the dates anchor the epoch (t = date - time offset + time; whole-second
      dates: the offset every row's date allows, `date_offset`) and the finer time column spaces the rows; a time
      column that starts again is anchored part by part. A naive date is UTC unless ``utc_offset_s`` is given
      (a column named ``(utc)`` is UTC whatever ``utc_offset_s`` says).
    - required: ``lat, latitude``; ``lon, lng, longitude``; height ``height_m, rel_alt,
      height_above_takeoff, height, altitude`` (m or ft; ``height_offset_m`` is added).
    - optional: pitch ``pitch_deg, gimbal_pitch, gb_pitch, gimbal_pitch_dji, pitch``; heading
      ``heading_deg, gimbal_heading, gb_yaw, heading, yaw``; roll ``roll_deg, gimbal_roll, gb_roll, roll``;
      ``speed_mps, speed``; velocity ``vel_north_mps, xspeed`` and ``vel_east_mps, yspeed`` (DJI flight logs:
      x north, y east); ``frame, frame_index, framecnt``; ``isvideo, is_video, recording`` (AirData: 1 while
      the camera records). An empty optional cell is None.
    - Litchi's and converted DJI logs' names too (`shared.telemetry.columns.CSV_COLUMNS`: ``gimbalPitchRaw`` in
      tenths of a degree, ``isTakingVideo``, ``OSD.latitude``, ``GIMBAL.yaw [360]``, ``OSD.flyTime [s]``, ...). One
      name in two units (``OSD.height [m]`` and ``[ft]``, ``datetime(utc)`` and ``datetime(local)``): the first
      unit of `UNITS`' order (metres, UTC).

    When several names of one field are present the earlier one in these lists wins (a gimbal column
    beats the aircraft's ``pitch``/``yaw``/``roll``).

    DJI pitch rule: the pitch column is in DJI convention (negative down, -90 = nadir) when it is named
    ``gb_pitch`` or ``gimbal_pitch_dji``, or when more of its values are clearly negative than clearly positive
    (beyond `PITCH_TOLERANCE_DEG`); it is then converted
    with `pitch_from_dji`. Otherwise it is our depression 0..90. Either way readings within
    `PITCH_TOLERANCE_DEG` outside 0..90 are clamped and others rejected.

    Parameters
    ----------
    text : str
        The file's text (comma-separated, first non-blank row is the header).
    source : str
        Name used in error messages (``source:line: ...``).
    utc_offset_s : float
        Offset of naive date-times from UTC in seconds.
    height_offset_m : float
        Metres added to every height (e.g. minus the ground elevation for an above-sea-level column).

    Rows that cannot be a record (cut short, a bad or empty required cell, an out-of-range value) are skipped
    and counted in one warning with rows without a GPS fix (latitude and longitude 0: kept, `interpolate` gives
    them no pose); half the rows bad or more fails the file. Position cells left empty between the rows where a fix
    arrived (a GPS slower than the rows) are filled linear in time between those (`_fill_sparse_positions`). A
    unitless time column in milliseconds is read as such (`_seconds`); whole-second stamps that repeat are spread
    over their second.

    Returns
    -------
    list of Telemetry
        One per usable data row, in file order.

    Raises
    ------
    ValueError
        Naming the missing column, a column naming two drones, or, when half the rows or more are bad, the first
        bad one: ``source:line: column 'name': ...`` for a bad cell, a row with the wrong number of cells, or an
        out-of-range value.
    """
    if not isinstance(text, str):
        raise TypeError(f"parse_csv needs str, got {type(text).__name__}")
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff")), strict=True)
    rows: list[tuple[int, list[str]]] = []
    try:
        for row in reader:
            if any(cell.strip() for cell in row):
                rows.append((reader.line_num, row))
    except csv.Error as err:
        raise ValueError(f"{source}:{reader.line_num}: unreadable CSV: {err}") from None
    if not rows:
        raise ValueError(f"{source}: empty CSV file")
    header_line, header = rows[0]
    columns = _csv_columns(header, header_line, source)
    if len(rows) == 1:
        raise ValueError(f"{source}: no data rows after the header")
    _one_drone(header, rows[1:], source)
    times = _row_times(rows[1:], header, columns, source, utc_offset_s)
    data = rows[1:] if times is None else _fill_sparse_positions(rows[1:], header, columns, source, times)
    kept = _usable_rows(data, header, columns, source, utc_offset_s, height_offset_m)
    records = _records(kept, columns, source, utc_offset_s, height_offset_m, times=times)
    _warn_jumps(records, [line for line, _ in kept], source)
    return records


def _warn_jumps(records: list[Telemetry], lines: list[int], source: str) -> None:
    """One warning when consecutive rows are further apart than any drone flies in the time between them
    (`_MAX_SPEED_MPS`): rows of several drones interleaved (under a column not named like a drone's), or GPS
    glitches; those poses are wrong."""
    jumps: list[int] = []
    for i in range(1, len(records)):
        a, b = records[i - 1], records[i]
        if (a.lat, a.lon) == (0.0, 0.0) or (b.lat, b.lon) == (0.0, 0.0):
            continue  # no GPS fix
        north = (b.lat - a.lat) * 111_320.0
        east = (b.lon - a.lon) * 111_320.0 * math.cos(math.radians(a.lat))
        if math.hypot(north, east) > _MAX_SPEED_MPS * max(abs(b.t - a.t), 0.05) + 5.0:
            jumps.append(i)
    if jumps:
        log.warning("%s: the position jumps faster than %g m/s between %d pairs of rows (first at line %d): rows of "
                    "several drones in one file, or GPS glitches? Those rows' poses are wrong: keep the rows of the "
                    "drone that filmed the video", source, _MAX_SPEED_MPS, len(jumps), lines[jumps[0]])


def _row_times(rows: list[tuple[int, list[str]]], header: list[str], columns: dict[str, _CsvColumn], source: str,
               utc_offset_s: float) -> dict[int, float] | None:
    """The time of each data row whose time can be read, by line, judged on all of them (whole-second stamps
    spread over every row of their second, also those skipped later for another cell); None when they cannot be
    read together (then `_records` times the rows it keeps)."""

    def timed(line: int, row: list[str]) -> bool:
        try:
            _csv_times([(line, row)], columns, source, utc_offset_s, quiet=True)
        except (ValueError, IndexError):
            return False
        return True

    full = [(line, row) for line, row in rows if len(row) == len(header)]
    for attempt in range(2):  # all at once; else without the rows whose own time cannot be read
        ok = full if attempt == 0 else [(line, row) for line, row in full if timed(line, row)]
        if not ok:
            return None
        try:
            return dict(zip([line for line, _ in ok], _csv_times(ok, columns, source, utc_offset_s), strict=True))
        except (ValueError, IndexError):
            continue
    return None


def _records(rows: list[tuple[int, list[str]]], columns: dict[str, _CsvColumn], source: str, utc_offset_s: float,
             height_offset_m: float, *, quiet: bool = False, times: dict[int, float] | None = None) -> list[Telemetry]:
    """The records of data rows (all of them, or one at a time for `_usable_rows`' check; quiet: no warnings).
    times: the rows' times by line (`_row_times`), else judged on these rows. ValueError ``source:line: ...`` on
    the first row that cannot be one."""

    def floats(fld: str) -> list[float | None] | None:
        column = columns.get(fld)
        if column is None:
            return None
        return [_csv_float(row[column.index], line, column, source) for line, row in rows]

    def required(fld: str) -> list[float]:
        column, values = columns[fld], floats(fld)
        out: list[float] = []
        for (line, _), value in zip(rows, values or [], strict=True):
            if value is None:
                raise ValueError(f"{source}:{line}: column {column.name!r} is empty")
            out.append(value)
        return out

    lat, lon, height = required("lat"), required("lon"), required("height")
    if times is not None and all(line in times for line, _ in rows):
        row_times = [times[line] for line, _ in rows]
    else:
        row_times = _csv_times(rows, columns, source, utc_offset_s, quiet=quiet)
    pitch = _csv_pitch(rows, columns, floats("pitch"), source, quiet)
    heading, roll, speed = floats("heading"), floats("roll"), floats("speed")
    north, east = floats("vel_north"), floats("vel_east")
    recording = floats("recording")
    frames = _csv_frames(rows, columns.get("frame"), source)
    records = []
    for i, (line, _) in enumerate(rows):
        ve = None if east is None else east[i]
        vn = None if north is None else north[i]
        try:
            records.append(
                Telemetry(
                    t=row_times[i],
                    lat=lat[i],
                    lon=lon[i],
                    height_m=height[i] + height_offset_m,
                    pitch_deg=pitch[i],
                    heading_deg=None if heading is None else heading[i],
                    roll_deg=0.0 if roll is None else roll[i] or 0.0,
                    speed_mps=None if speed is None else speed[i],
                    vel_en_mps=None if ve is None or vn is None else (ve, vn),
                    frame=frames[i],
                    recording=None if recording is None or recording[i] is None else recording[i] != 0.0,
                )
            )
        except ValueError as err:
            raise ValueError(f"{source}:{line}: {err}") from None
    return records


def _csv_times(
    rows: list[tuple[int, list[str]]], columns: dict[str, _CsvColumn], source: str, utc_offset_s: float, *,
    quiet: bool = False
) -> list[float]:
    def dates(column: _CsvColumn) -> list[float]:
        out = []
        # a column that names its zone (AirData's datetime(utc)) is not shifted by the local offset
        utc = column.alias == "datetime_utc" or re.search(r"[(\[]\s*utc\s*[)\]]", column.name, re.IGNORECASE)
        offset = 0.0 if utc else utc_offset_s
        for line, row in rows:
            try:
                out.append(parse_datetime(row[column.index], utc_offset_s=offset))
            except ValueError as err:
                raise ValueError(f"{source}:{line}: column {column.name!r}: {err}") from None
        return out

    numeric: list[float] | None = None
    time_column = columns.get("time")
    if time_column is not None:
        first = rows[0][1][time_column.index].strip()
        if NUM_RE.fullmatch(first) or not DATETIME_RE.fullmatch(first):
            numeric = []
            for line, row in rows:
                value = _csv_float(row[time_column.index], line, time_column, source)
                if value is None:
                    raise ValueError(f"{source}:{line}: column {time_column.name!r} is empty")
                numeric.append(value)
            numeric = _seconds(numeric, time_column, source, warn=not quiet)
        else:
            return spread_whole_second_stamps(dates(time_column))
    date_column = columns.get("datetime")
    if date_column is None:
        assert numeric is not None
        return spread_whole_second_stamps(numeric)
    anchors = dates(date_column)
    if numeric is None:
        # a log stamped at whole seconds (AirData's datetime(utc) without its time(millisecond)): the rows of
        # one second are spread over it in their order
        return spread_whole_second_stamps(anchors)
    # the dates anchor the epoch, the finer time column spaces the rows; a time column that starts again while the
    # dates go on (two logs joined, a logger restarted) is anchored part by part
    starts = [0] + [i for i in range(1, len(numeric)) if numeric[i] < numeric[i - 1] - _RESET_S]
    if len(starts) > 1 and not quiet:
        line = rows[starts[1]][0]
        log.warning("%s: column %r starts again %d time(s) (first at line %d) while %r goes on: each part is placed "
                    "by its dates", source, time_column.name if time_column else "time", len(starts) - 1, line,
                    date_column.name)
    out: list[float] = []
    for a, b in zip(starts, [*starts[1:], len(numeric)], strict=True):
        offset = date_offset(anchors[a:b], numeric[a:b])
        out.extend(offset + value for value in numeric[a:b])
    return out


def date_offset(dates: list[float], times: list[float]) -> float:
    """The offset c with each row's date = c + its time, from rows with both. Dates at whole seconds that repeat
    (AirData's datetime(utc) beside time(millisecond)) are truncated: c is the middle of the offsets that every row
    allows (floor(c + time) = date); else, and where truncation does not explain them, the first row's date - its
    time (the old anchor: dates that do not step with the time, a start date on every row, stay exact). The first
    row's date alone was up to a second off for truncated dates (a flight starting at .9 s read 0.9 s early)."""
    first = dates[0] - times[0]
    if len(set(dates)) == len(dates) or any(d != math.floor(d) for d in dates):
        return first
    offset = truncated_date_offset([d - t for d, t in zip(dates, times, strict=True)])
    return first if offset is None else offset


def _seconds(values: list[float], column: _CsvColumn, source: str, *, warn: bool = True) -> list[float]:
    """A time column's numbers in seconds. A column that names its unit (``time_s``, ``time(millisecond)``) is
    taken at its word; a unitless ``time``, ``t`` or ``timestamp`` holding milliseconds (since 1970: values beyond
    1e11; since the start: a median step of at least 20 between distinct stamps, where a drone log in seconds
    steps by a few seconds at most, for values below epoch seconds) is read as milliseconds, with a warning
    naming the column (`warn` False: silently, for the per-row checks)."""
    unitless = column.alias != "time_s" and column.scale == 1.0 and "(" not in column.name and "[" not in column.name
    if not unitless or not values:
        return values
    distinct = sorted(set(values))
    steps = [b - a for a, b in zip(distinct, distinct[1:], strict=False)]
    median_step = sorted(steps)[len(steps) // 2] if steps else 0.0
    middle = sorted(abs(v) for v in values)[len(values) // 2]
    if middle > _EPOCH_MS_MIN:
        why = "milliseconds since 1970"
    elif median_step >= _MS_STEP_MIN and middle < _EPOCH_S_MIN:
        why = f"milliseconds (its stamps step by {median_step:g})"
    else:
        return values
    if warn:
        log.warning("%s: time column %r read as %s; name it time_s or time(ms) to say its unit", source,
                    column.name, why)
    return [v * 1e-3 for v in values]


def _one_drone(header: list[str], rows: list[tuple[int, list[str]]], source: str) -> None:
    """ValueError when a column naming the drone (`_DRONE_COLUMNS`) holds more than one: a video's telemetry is one
    drone's, and rows of two drones interleaved would be read as one zig-zagging flight."""
    for index, cell in enumerate(header):
        if cell.strip().lower() not in _DRONE_COLUMNS:
            continue
        drones = sorted({row[index].strip() for _, row in rows if index < len(row) and row[index].strip()})
        if len(drones) > 1:
            shown = ", ".join(repr(d) for d in drones[:5]) + (", ..." if len(drones) > 5 else "")
            raise ValueError(f"{source}: column {cell.strip()!r} names {len(drones)} drones ({shown}): keep the rows "
                             "of the drone that filmed the video (one drone per telemetry file)")


def _fill_sparse_positions(rows: list[tuple[int, list[str]]], header: list[str], columns: dict[str, _CsvColumn],
                           source: str, times: dict[int, float]) -> list[tuple[int, list[str]]]:
    """The rows of a log that writes each value only where it arrived (a 10 Hz log of the gimbal with a 1 Hz GPS;
    an export that merges topics, its GPS rows without the gimbal and its gimbal rows without a position): the
    empty cells of latitude and longitude (together) and height, and in such a log (some position filled) those of
    pitch, heading (the short way round) and roll, filled linear in time between the rows before and after that
    have them, when those are at most `SPARSE_FILL_MAX_S` apart, so that each row is a record with its own values
    (a value is where its row is), at its time in `times` (`_row_times`, as the records get). A row whose position
    is (0, 0) (no fix), or whose cell or time cannot be read, is no end of such an interval; the rows are taken in
    time order (merged exports need not be sorted). Rows whose position or height cannot be filled (before the
    first fix, after the last, across a longer gap) stay as they are, and `_usable_rows` skips and counts them. One
    log line says how many rows were filled."""
    full = [(line, row) for line, row in rows if line in times]
    groups = [g for g in (("lat", "lon"), ("height",), ("pitch",), ("heading",), ("roll",))
              if all(f in columns for f in g)]
    bad = object()  # a cell that cannot be read

    def cell(line: int, row: list[str], f: str) -> Any:
        try:
            return _csv_float(row[columns[f].index], line, columns[f], source)
        except ValueError:
            return bad

    values = [{f: cell(line, row, f) for g in groups for f in g} for line, row in full]
    if not any(v[f] is None for v in values for g in groups for f in g):
        return rows

    order = sorted(range(len(full)), key=lambda k: times[full[k][0]])  # by time: merged exports need not be sorted
    at = [times[full[k][0]] for k in order]
    filled: dict[int, dict[str, float]] = {}

    def fill(chosen: list[tuple[str, ...]]) -> None:
        for group in chosen:
            ends = [n for n, k in enumerate(order) if all(isinstance(values[k][f], float) for f in group)
                    and not (group == ("lat", "lon") and values[k]["lat"] == 0.0 and values[k]["lon"] == 0.0)]
            for a, b in zip(ends, ends[1:], strict=False):
                if b - a < 2 or not 0.0 < at[b] - at[a] <= SPARSE_FILL_MAX_S:
                    continue
                for n in range(a + 1, b):
                    k = order[n]
                    if any(values[k][f] is not None for f in group):
                        continue
                    w = (at[n] - at[a]) / (at[b] - at[a])
                    for f in group:
                        va, vb = values[order[a]][f], values[order[b]][f]
                        turn = f in ("lon", "heading")  # the short way round
                        v = va + w * ((vb - va + 180.0) % 360.0 - 180.0 if turn else vb - va)
                        filled.setdefault(k, {})[f] = (v + 180.0) % 360.0 - 180.0 if f == "lon" else v

    fill([g for g in groups if g[0] in ("lat", "height")])
    if any("lat" in cells for cells in filled.values()):  # a sparse log: its attitude may be sparse too
        fill([g for g in groups if g[0] not in ("lat", "height")])
    if not filled:
        return rows
    log.info("%s: %d of %d rows lack a value other rows hold (a GPS slower than the rows, merged topics): filled "
             "linear in time between the rows with one", source, len(filled), len(rows))
    out = {line: row for line, row in rows}
    for k, cells in filled.items():
        line, row = full[k]
        row = list(row)
        for f, v in cells.items():
            row[columns[f].index] = repr(v / columns[f].scale)
        out[line] = row
    return [(line, out[line]) for line, _ in rows]


def _usable_rows(rows: list[tuple[int, list[str]]], header: list[str], columns: dict[str, _CsvColumn], source: str,
                 utc_offset_s: float, height_offset_m: float) -> list[tuple[int, list[str]]]:
    """The data rows a record can be made of. A row cut short (a logger killed mid-line) or one that cannot be a
    record by itself (a bad or empty required cell, an unreadable time, an out-of-range value) is skipped; one
    warning counts them and names the first. ValueError (the first problem) when half the rows or more are bad:
    then the file, not a row, is wrong. Rows without a GPS fix (latitude and longitude both 0, as loggers write
    before the fix) are kept and counted in the warning: they keep the log's clock (its first time, the start of
    recording), and `interpolate` gives their times no pose."""
    kept: list[tuple[int, list[str]]] = []
    bad: list[str] = []
    no_fix = 0
    for line, row in rows:
        if len(row) != len(header):
            bad.append(f"{source}:{line}: {len(row)} cells, the header has {len(header)}")
            continue
        try:
            (record,) = _records([(line, row)], columns, source, utc_offset_s, height_offset_m, quiet=True)
        except ValueError as err:
            bad.append(str(err))
            continue
        kept.append((line, row))
        no_fix += not record.has_fix
    if not kept or len(bad) * 2 >= len(rows):
        raise ValueError(bad[0])
    if bad or no_fix:
        parts = ([f"{len(bad)} unreadable rows skipped"] if bad else []) \
            + ([f"{no_fix} without a GPS fix (0, 0) give no pose"] if no_fix else [])
        log.warning("%s: %d of %d rows: %s%s", source, len(bad) + no_fix, len(rows), ", ".join(parts),
                    f"; first skipped: {bad[0]}" if bad else "")
    return kept


def _csv_pitch(
    rows: list[tuple[int, list[str]]],
    columns: dict[str, _CsvColumn],
    raw: list[float | None] | None,
    source: str,
    quiet: bool = False,
) -> list[float | None]:
    if raw is None:
        return [None] * len(rows)
    column = columns["pitch"]
    # DJI's sign (negative below the horizon) when more readings are clearly negative than clearly positive: a camera
    # looks down far more than up, and one reading above the horizon (-3 where positive is down) is no DJI sign
    negative = sum(v is not None and v < -PITCH_TOLERANCE_DEG for v in raw)
    positive = sum(v is not None and v > PITCH_TOLERANCE_DEG for v in raw)
    dji = column.alias in _DJI_PITCH_COLUMNS or negative > positive or (negative and not positive)
    out: list[float | None] = []
    for (line, _), value in zip(rows, raw, strict=True):
        if value is None:
            out.append(None)
            continue
        if not math.isfinite(value):
            raise ValueError(f"{source}:{line}: column {column.name!r}: pitch {value!r} is not finite")
        depression = -value if dji else value
        # quiet: the per-row check; the whole file's pass says it once
        out.append(pitch_or_none(depression, f"{source}:{line}: column {column.name!r}: pitch {value:g}",
                                 warn=not quiet))
    given = [v for v in raw if v is not None]
    if not quiet and column.alias == "pitch" and given and all(abs(v) < _AIRFRAME_PITCH_DEG for v in given):
        log.warning("%s: column %r stays within %g deg of the horizon in every row: if it is the airframe's pitch "
                    "(not the gimbal's), remove it and pass --pitch-deg", source, column.name, _AIRFRAME_PITCH_DEG)
    return out


def _csv_frames(rows: list[tuple[int, list[str]]], column: _CsvColumn | None, source: str) -> list[int | None]:
    if column is None:
        return [None] * len(rows)
    out: list[int | None] = []
    for line, row in rows:
        value = _csv_float(row[column.index], line, column, source)
        if value is not None and (value < 0.0 or value != int(value)):
            raise ValueError(f"{source}:{line}: column {column.name!r}: {value:g} is not a frame index")
        out.append(None if value is None else int(value))
    return out


def read_csv(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a telemetry CSV file; keyword arguments as in `parse_csv` (``source`` defaults to the path)."""
    kw.setdefault("source", str(path))
    return parse_csv(read_text(path), **kw)

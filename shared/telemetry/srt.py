"""DJI SRT subtitle files: one record per usable subtitle block, across the firmware variants DJI has written.

Blocks come from `srt_blocks`, the clock from `srt_clock`; this module decides what the facts mean (GPS axis
order, height, gimbal) and reports what it skipped and how finely the file logs positions.
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from shared.telemetry.record import Telemetry, pitch_or_none
from shared.telemetry.srt_blocks import BadBlock, BlockFacts, RawBlock, block_facts, split_blocks
from shared.telemetry.srt_clock import BlockTimes, monotonic_times
from shared.telemetry.text import read_text

logger = logging.getLogger(__name__)

#: How many skipped blocks (or clock seams) a warning names before it says "and N more".
WARN_FIRST = 3
_SRT_FIELD_RE = re.compile(r"\b(?:latitude|longt?itude|GPS|RTK|rel_alt|abs_alt|BAROMETER)\b", re.IGNORECASE)
_METRES_PER_DEGREE_LAT = 111_320.0


@dataclass(frozen=True, slots=True)
class SrtReport:
    """What reading one SRT file gave: the records and what a caller may need to know about them.

    Attributes
    ----------
    source : str
        The name used in messages (the path for `read_srt_report`).
    records : list of Telemetry
        One per usable block, in file order, ``t`` non-decreasing (see `parse_srt`).
    blocks : int
        Blocks found, usable or not (stray text between blocks counts as one).
    skipped : tuple of (int, str)
        (line, reason) of every block that gave no record: no GPS fix, no position, a malformed value...
    heights_missing : int
        Records whose ``height_m`` is None (the file gives no height above ground for them).
    heights_above_sea_level_only : int
        Of those, the records whose block gives only ``abs_alt`` (above sea level): ``height_offset_m`` fixes them.
    gps_decimals : int or None
        The coarsest position resolution in the file: decimals of the coordinates as written (DJI writes a
        fixed number per firmware: 4 on the Mavic Pro, 6 on later models). None without records.
    gps_decimals_seen : dict of int to int
        Decimals -> number of records written with that resolution (several in concatenated files).
    clock_notes : tuple of str
        Where the date-time lines, subtitle timing and frame counters disagreed and how the clock was joined.
    video_start_t : float or None
        The records' time of video time 0, from the first usable block's subtitle timing (a subtitle's start is
        its place in the video): its time minus its start. So blocks skipped at the start (no GPS fix yet, as
        when recording begins before the lock) do not move the video's clock. None when that block has no
        timing line.
    digital_zoom : tuple of (int, float) or None
        (records, largest ratio) of the records whose block gives a DJI ``dzoom_ratio`` above 1 (written as the
        ratio, 1.77, or times 10,000, 10000 for 1x; Mini 2: ``DZOOM 1.000``), else None: the frame is a crop of the
        sensor, its focal length that many times the camera's. Each record carries its ratio (`Telemetry.zoom_ratio`)
        unless the focal length changes too (a hybrid zoom, whose ratio's reference moves with the lens: named in a
        warning, not applied).
    focal_lengths : tuple of (float, float) or None
        The smallest and largest ``focal_len`` of the records as the SRT writes it (35 mm equivalent, some firmware
        in tenths of a millimetre) when it changes during the file by more than 5 % (a zoom), else None.
    """

    source: str
    records: list[Telemetry]
    blocks: int
    skipped: tuple[tuple[int, str], ...] = ()
    heights_missing: int = 0
    heights_above_sea_level_only: int = 0
    gps_decimals: int | None = None
    gps_decimals_seen: dict[int, int] = field(default_factory=dict)
    clock_notes: tuple[str, ...] = ()
    video_start_t: float | None = None
    digital_zoom: tuple[int, float] | None = None
    focal_lengths: tuple[float, float] | None = None
    subtitle_starts: tuple[float | None, ...] = ()

    def on_video_clock(self, tolerance_s: float = 1.0) -> list[Telemetry]:
        """The records for its video: where a record's time and its subtitle start disagree with the first one's by
        more than `tolerance_s` (two recordings joined into one video and their SRTs into one: the dates jump 30
        minutes where the subtitle timing goes on), every record goes on the video's clock, `video_start_t` + its
        start, with one warning; the records as they are otherwise (a consistent file, or one without timing).
        Kept on their dates, the joined clip's records lay past the video's end and its frames got no pose."""
        starts = self.subtitle_starts
        if self.video_start_t is None or len(starts) != len(self.records) or any(st is None for st in starts) \
                or any(b < a for a, b in zip(starts, starts[1:], strict=False)):  # type: ignore[operator]
            return list(self.records)  # (a timing that starts again is no video clock either: the dates stay)
        moved = [i for i, (r, st) in enumerate(zip(self.records, starts, strict=True))
                 if abs(r.t - (self.video_start_t + st)) > tolerance_s]  # type: ignore[operator]
        if not moved:
            return list(self.records)
        first = moved[0]
        off = self.records[first].t - self.video_start_t - starts[first]  # type: ignore[operator]
        logger.warning("%s: from record %d on (subtitle time %.3f s) its dates are %.1f s off the subtitle timing (two "
                       "recordings joined, or a drifting clock?): every record is placed on the video's clock by its "
                       "subtitle timing", self.source, first + 1, starts[first], off)
        # all of them, not only those off: a seam where part of the records moved would interleave two clocks
        return [replace(r, t=self.video_start_t + st) for r, st in zip(self.records, starts, strict=True)]  # type: ignore

    @property
    def gps_step_m(self) -> float | None:
        """North-south size in metres of one step in the last written decimal (11.1 m at 4 decimals), or None.

        Positions are quantised to this step (east-west: times cos(latitude)); a gate or uncertainty for
        positions from this file should not be tighter than about half of it.
        """
        if self.gps_decimals is None:
            return None
        return _METRES_PER_DEGREE_LAT * 10.0 ** -self.gps_decimals


def _has_barometric_pair(facts: BlockFacts) -> bool:
    return "Hb" in facts.values or "Hs" in facts.values


def _gps_orders(facts: list[BlockFacts], gps_order: str, source: str) -> dict[tuple[bool, bool], str]:
    """'latlon' or 'lonlat' for each style of positional GPS tuple in the file (rule in `parse_srt`)."""
    if gps_order not in ("auto", "latlon", "lonlat"):
        raise ValueError(f"gps_order={gps_order!r} must be 'auto', 'latlon' or 'lonlat'")
    groups: dict[tuple[bool, bool], list[tuple[float, float, bool, str, int]]] = {}
    for block in facts:
        if block.gps is not None:
            groups.setdefault((_has_barometric_pair(block), block.gps[2]), []).append(block.gps)
    orders: dict[tuple[bool, bool], str] = {}
    for key, tuples in groups.items():
        first_is_lon = [t for t in tuples if abs(t[0]) > 90.0]
        second_is_lon = [t for t in tuples if abs(t[1]) > 90.0]
        if gps_order != "auto":
            contradiction = first_is_lon if gps_order == "latlon" else second_is_lon
            if contradiction:
                raise ValueError(
                    f"{source}:{contradiction[0][4]}: gps_order={gps_order!r} puts a longitude in latitude"
                )
            orders[key] = gps_order
        elif len(first_is_lon) != len(second_is_lon):  # values tell; a block that disagrees is skipped later
            orders[key] = "lonlat" if len(first_is_lon) > len(second_is_lon) else "latlon"
        elif key[0]:
            orders[key] = "lonlat"  # the oldest firmware (Hb/Hs heights): GPS(lon, lat, alt), even with "M"
        else:
            # Values cannot tell: a metre-suffixed third value is the Matrice's altitude, a bare one satellites.
            orders[key] = "latlon" if key[1] else "lonlat"
    return orders


def _position(facts: BlockFacts, orders: dict[tuple[bool, bool], str], line: int) -> tuple[float, float, int]:
    """(lat, lon, decimals written) of a block."""
    if "latitude" in facts.values or "longitude" in facts.values:
        for key in ("latitude", "longitude"):
            if key not in facts.values:
                raise BadBlock(line, f"block has no {key}")
        lat, lat_line = facts.values["latitude"]
        lon, lon_line = facts.values["longitude"]
        decimals = max(facts.decimals.get("latitude", 0), facts.decimals.get("longitude", 0))
    elif facts.gps is not None:
        a, b, _, _, lat_line = facts.gps
        lon_line = lat_line
        order = orders[(_has_barometric_pair(facts), facts.gps[2])]
        lat, lon = (a, b) if order == "latlon" else (b, a)
        decimals = facts.decimals.get("gps", 0)
    else:
        raise BadBlock(line, "block has no position (no [latitude: ...] or GPS(...))")
    if not -90.0 <= lat <= 90.0:
        raise BadBlock(lat_line, f"latitude {lat:g} is outside [-90, 90]")
    if not -180.0 <= lon <= 180.0:
        raise BadBlock(lon_line, f"longitude {lon:g} is outside [-180, 180]")
    if lat == 0.0 and lon == 0.0:
        raise BadBlock(line, "no GPS fix (position 0, 0)")
    return lat, lon, decimals


def _height(
    facts: BlockFacts, source: str, height_offset_m: float | None, warned: set[str]
) -> tuple[float | None, bool]:
    """(height above ground or None, whether only an above-sea-level altitude was there)."""
    offset = 0.0 if height_offset_m is None else height_offset_m
    for key in ("rel_alt", "H", "Hb", "Hs", "barometer"):
        if key in facts.values:
            return facts.values[key][0] + offset, False
    if "altitude" in facts.values:
        if height_offset_m is None and "altitude" not in warned:
            warned.add("altitude")
            logger.warning(
                "%s: using the SRT 'altitude' field as height above ground; Mavic 2 / Air 2S firmware writes "
                "altitude above sea level there: pass height_offset_m=-(ground elevation) if so",
                source,
            )
        return facts.values["altitude"][0] + offset, False
    if "abs_alt" in facts.values:
        if height_offset_m is None:
            return None, True
        return facts.values["abs_alt"][0] + offset, False
    return None, False


def _gimbal(facts: BlockFacts, source: str, line: int) -> tuple[float | None, float | None, float]:
    values = facts.values
    if "gb_pitch" in values or "gb_yaw" in values:
        raw_pitch, pitch_line = values.get("gb_pitch", (None, line))
        heading = values["gb_yaw"][0] if "gb_yaw" in values else None
        roll = values["gb_roll"][0] if "gb_roll" in values else 0.0
    elif facts.gimbal_pry is not None:
        raw_pitch, roll, heading, pitch_line = facts.gimbal_pry
    else:
        return None, None, 0.0
    pitch = None
    if raw_pitch is not None:
        if not math.isfinite(raw_pitch):
            raise BadBlock(pitch_line, f"gimbal pitch {raw_pitch!r} is not finite")
        pitch = pitch_or_none(-raw_pitch, f"{source}:{pitch_line}: DJI gimbal pitch {raw_pitch:g}")
    return pitch, heading, roll


def _block_line(raw: RawBlock) -> int:
    """The line a block is named by: its timing line, else its first line."""
    return raw.lines[raw.timing][0] if raw.timing is not None else raw.first_line


def _looks_like_a_block(raw: RawBlock) -> bool:
    return raw.timing is not None or bool(raw.markers) or raw.only_index()


def _listing(items: list[str], total: int) -> str:
    more = total - len(items)
    return "; ".join(items) + (f" (and {more} more)" if more > 0 else "")


def parse_srt_report(
    text: str,
    *,
    source: str = "<srt>",
    utc_offset_s: float = 0.0,
    height_offset_m: float | None = None,
    gps_order: str = "auto",
) -> SrtReport:
    """Parse a DJI SRT file into records and a report of what was skipped, the clock and GPS resolution.

    Parameters and the rules are those of `parse_srt`, which returns ``parse_srt_report(...).records``.
    Logs one warning each for skipped blocks, clock seams and missing heights (naming the first lines),
    and the GPS resolution at INFO.

    Raises
    ------
    ValueError
        ``source: what`` when no block gives a record: an empty file, no subtitle blocks, no position in
        any block (firmware that logs only exposure), no GPS fix anywhere, or every block malformed (the
        first reasons are named). Also for a ``gps_order`` that contradicts the values.
    """
    if not isinstance(text, str):
        raise TypeError(f"parse_srt needs str, got {type(text).__name__}")
    text = text.removeprefix("\ufeff")
    if not text.strip():
        raise ValueError(f"{source}: empty SRT file")
    raw_blocks = split_blocks(text)
    skipped: list[tuple[int, str]] = []
    parsed: list[tuple[int, BlockFacts]] = []
    subtitle_blocks = 0
    for raw in raw_blocks:
        line = _block_line(raw)
        if not _looks_like_a_block(raw) and not _SRT_FIELD_RE.search(" ".join(content for _, content in raw.lines)):
            skipped.append((line, f"text outside any subtitle block: {raw.lines[0][1][:40]!r}"))
            continue
        subtitle_blocks += 1
        try:
            parsed.append((line, block_facts(raw, utc_offset_s)))
        except BadBlock as bad:
            skipped.append((bad.line, bad.reason))
    if subtitle_blocks == 0:
        raise ValueError(
            f"{source}: no subtitle blocks (no 'HH:MM:SS,mmm --> HH:MM:SS,mmm' timing line, date-time line "
            "or frame counter)"
        )
    orders = _gps_orders([facts for _, facts in parsed], gps_order, source)
    warned: set[str] = set()
    kept: list[tuple[int, BlockFacts, Telemetry, bool]] = []  # line, facts, record without time, asl only
    last_diff_s: float | None = None
    times_in: list[BlockTimes] = []
    decimals_seen: Counter[int] = Counter()
    for line, facts in parsed:
        if "diff_time" in facts.values:
            last_diff_s = facts.values["diff_time"][0] / 1000.0
        try:
            lat, lon, decimals = _position(facts, orders, line)
            times = BlockTimes(line, facts.epoch_s, facts.start_s, facts.counter, last_diff_s)
            if times.source() is None:
                raise BadBlock(line, "block has no time (no timing line, date-time line or FrameCnt with DiffTime)")
            height_m, asl_only = _height(facts, source, height_offset_m, warned)
            pitch, heading, roll = _gimbal(facts, source, line)
            speed = facts.values.get("H.S")
            record = Telemetry(
                t=0.0,
                lat=lat,
                lon=lon,
                height_m=height_m,
                pitch_deg=pitch,
                heading_deg=heading,
                roll_deg=roll,
                speed_mps=None if speed is None else abs(speed[0]),
                frame=facts.frame,
            )
        except BadBlock as bad:
            skipped.append((bad.line, bad.reason))
            continue
        except ValueError as err:
            skipped.append((line, str(err)))
            continue
        kept.append((line, facts, record, asl_only))
        times_in.append(times)
        decimals_seen[decimals] += 1
    skipped.sort()
    if not kept:
        raise ValueError(_no_record_message(source, subtitle_blocks, skipped))
    times_out, clock_notes = monotonic_times(times_in)
    zoom = _zoom([facts for _, facts, _, _ in kept])
    # a digital zoom on a fixed lens goes with each record (applied by the video source where it changes); beside
    # a focal length that changes (a hybrid zoom: the ratio's reference moves with the lens) it is only named
    ratios = [_dzoom(facts) for _, facts, _, _ in kept] if zoom["focal_lengths"] is None else [None] * len(kept)
    records = [replace(record, t=t, zoom_ratio=ratio)
               for (_, _, record, _), t, ratio in zip(kept, times_out, ratios, strict=True)]
    report = SrtReport(
        source=source,
        records=records,
        blocks=len(raw_blocks),
        skipped=tuple(skipped),
        heights_missing=sum(r.height_m is None for r in records),
        heights_above_sea_level_only=sum(asl for *_, asl in kept),
        gps_decimals=min(decimals_seen),
        gps_decimals_seen=dict(sorted(decimals_seen.items())),
        clock_notes=tuple(clock_notes),
        video_start_t=None if times_in[0].start_s is None else times_out[0] - times_in[0].start_s,
        **zoom,
        subtitle_starts=tuple(times.start_s for times in times_in),
    )
    _log_report(report)
    return report


def _dzoom(facts: BlockFacts) -> float | None:
    """A block's digital zoom as a ratio (written as the ratio, 1.77, or times 10,000, 10000 for 1x), None without
    one or at a value that is no zoom (0)."""
    if "dzoom_ratio" not in facts.values:
        return None
    ratio = facts.values["dzoom_ratio"][0]
    ratio = ratio / 10_000.0 if ratio >= 1_000.0 else ratio
    return ratio if ratio > 0.0 else None


def _zoom(facts: list[BlockFacts]) -> dict[str, Any]:
    """SrtReport's digital_zoom and focal_lengths of the usable blocks."""
    ratios = [r for r in map(_dzoom, facts) if r is not None]
    zoomed = [r for r in ratios if r > 1.005]  # 1.00 as written; 10000 / 10000
    focals = [f.values["focal_len"][0] for f in facts if "focal_len" in f.values and f.values["focal_len"][0] > 0]
    changes = bool(focals) and max(focals) > 1.05 * min(focals)
    return {"digital_zoom": (len(zoomed), max(zoomed)) if zoomed else None,
            "focal_lengths": (min(focals), max(focals)) if changes else None}


def _no_record_message(source: str, blocks: int, skipped: list[tuple[int, str]]) -> str:
    reasons = [reason for _, reason in skipped if not reason.startswith("text outside")]
    if all("no position" in reason for reason in reasons):
        return (
            f"{source}: no block of {blocks} has a position ([latitude: ...] or GPS(...)): this SRT logs no "
            "GPS (early Mavic Air firmware writes only exposure settings)"
        )
    if all(reason.startswith("no GPS fix") or "no position" in reason for reason in reasons):
        return f"{source}: no block has a GPS fix (all {blocks} blocks are at 0, 0, N/A or without a position)"
    first = [f"line {line}: {reason}" for line, reason in skipped[:WARN_FIRST]]
    return f"{source}: no usable block among {blocks}: " + _listing(first, len(skipped))


def _log_report(report: SrtReport) -> None:
    source = report.source
    if report.skipped:
        first = [f"line {line}: {reason}" for line, reason in report.skipped[:WARN_FIRST]]
        logger.warning(
            "%s: skipped %d of %d blocks: %s", source, len(report.skipped), report.blocks,
            _listing(first, len(report.skipped)),
        )
    if report.clock_notes:
        logger.warning(
            "%s: the clock was made monotonic where its sources disagree: %s",
            source, _listing(list(report.clock_notes[:WARN_FIRST]), len(report.clock_notes)),
        )
    if report.heights_missing:
        asl = report.heights_above_sea_level_only
        why = []
        if asl:
            why.append(f"{asl} give only abs_alt, above sea level: pass height_offset_m=-(ground elevation in m)")
        if report.heights_missing - asl:
            why.append(f"{report.heights_missing - asl} give no height at all")
        logger.warning(
            "%s: %d of %d records have no height above ground (%s); their height_m is None",
            source, report.heights_missing, len(report.records), "; ".join(why),
        )
    if report.focal_lengths is not None:  # a digital zoom alone goes with the records (agent.field_of_view)
        what = []
        if report.digital_zoom is not None:
            what.append(f"digital zoom in {report.digital_zoom[0]} of {len(report.records)} records, up to "
                        f"{report.digital_zoom[1]:.2f}x")
        if report.focal_lengths is not None:
            what.append(f"focal_len {report.focal_lengths[0]:g} .. {report.focal_lengths[1]:g}")
        logger.warning(
            "%s: the camera zooms (%s): every frame is projected with the camera file's focal length, so in zoomed "
            "frames a point off the image centre is put that many times too far from the centre's ground point; "
            "use the clips recorded without zoom, or a camera file for the zoom in use", source, "; ".join(what))
    seen = ", ".join(f"{decimals} decimals in {count}" for decimals, count in report.gps_decimals_seen.items())
    logger.info("%s: GPS written with %s record(s): steps of about %.2g m", source, seen, report.gps_step_m)


def parse_srt(
    text: str,
    *,
    source: str = "<srt>",
    utc_offset_s: float = 0.0,
    height_offset_m: float | None = None,
    gps_order: str = "auto",
) -> list[Telemetry]:
    """Parse a DJI SRT subtitle file into one record per usable subtitle block.

    Variants read (one example block each in docs/geometry.md; real shapes in tests/shared/):

    - Phantom 3 era: ``GPS(lon,lat,alt) Hb:1.9 Hs:1.9`` (barometric and sonar heights; Hb is used).
    - Mavic Pro / Phantom 4: ``HOME(lon,lat) 2017.07.29 15:18:50`` / ``GPS(lon,lat,sats) BAROMETER:1.9``;
      blocks with ``GPS(N/A,N/A,0)`` (no fix) are skipped.
    - Mavic Mini / Phantom 4 (RTK): ``F/2.8, SS 206.14, ISO 150, EV 0, GPS (lon, lat, sats), D 2.80m,
      H 0.00m, H.S 0.00m/s, V.S 0.00m/s``, optionally ``RTK (lon, lat, n)``, ``F.PRY (p°, r°, y°)``
      (aircraft, ignored) and ``G.PRY (p°, r°, y°)`` (gimbal pitch, roll, yaw).
    - Matrice 300: ``2022.06.21 16:06:17`` / ``GPS(lat,lon,altM) BAROMETER:0.3M`` (latitude first).
    - Mavic 2 / Air 2 / Air 2S: ``<font ...>FrameCnt : 1, DiffTime : 41ms`` (or ``SrtCnt``), a date like
      ``2023-06-23 11:26:03,972,307`` (ms, us), ``[latitude : 38.9] [longtitude : -92.2]`` and
      ``[altitude: 274.2]``, or no altitude at all (height missing).
    - Blocks without a timing line: an index, a date-time line (``2017.08.05 14:11:51,393,525``) or
      ``FrameCnt``/``DiffTime``, then the fields.
    - Mini 3 / Mavic 3 / Matrice 30: ``FrameCnt: 1, DiffTime: 33ms``, ``2025-04-09 09:15:02.655``,
      ``[latitude: 53.38] [longitude: 5.36] [rel_alt: 55.774 abs_alt: 98.364]`` and optionally
      ``[gb_yaw: -83.6 gb_pitch: -9.1 gb_roll: 0.0]``; HTML ``<font>`` tags are dropped.
    - Files concatenated from several of these: read block by block.

    The positional ``GPS(a, b, c)`` form has no single axis order: consumer models write (lon, lat,
    satellites), the oldest firmware (lon, lat, altitude) beside ``Hb``/``Hs``, the Matrice 300 (lat, lon,
    altitude with an ``M`` suffix). With ``gps_order='auto'`` the order is decided per tuple style in the
    file: values beyond +-90 can only be longitudes (the majority decides); otherwise ``Hb``/``Hs`` mean
    (lon, lat), an ``M``-suffixed third value (lat, lon), a bare one (lon, lat).

    Height above ground, in order of preference: ``rel_alt`` (above the take-off point), ``H``, ``Hb``,
    ``Hs``, ``BAROMETER``, then ``altitude`` (logged as ambiguous: some firmware writes altitude above sea
    level there); ``abs_alt`` (above sea level) is used only with ``height_offset_m``. A block with none
    of these still gives a record, with ``height_m`` None (a warning counts them).

    Clock: a block's date-time line (UNIX epoch), else its subtitle start, else its frame counter times
    ``DiffTime``; the file's clock is made non-decreasing by `shared.telemetry.srt_clock.monotonic_times`,
    with a warning where these sources disagree (files concatenated from several recordings).

    Bad blocks (no GPS fix, no position, no time, a malformed value or timing line, text outside any
    block) are skipped and counted, with one warning naming the first lines; they never fail the file.

    Parameters
    ----------
    text : str
        The file's text (a leading BOM is ignored).
    source : str
        Name used in messages (``source: what``, ``line N: what``).
    utc_offset_s : float
        Offset of the drone clock from UTC in seconds (DJI writes local time without a zone; e.g. 7200
        for CEST). The default treats the date lines as UTC.
    height_offset_m : float, optional
        Metres added to every height. Needed when the file has only ``abs_alt`` (above sea level): pass
        minus the ground elevation. Also silences the warning about the ambiguous ``altitude`` field.
    gps_order : {'auto', 'latlon', 'lonlat'}
        Axis order of positional ``GPS(a, b, c)`` tuples; 'auto' decides per file.

    Returns
    -------
    list of Telemetry
        In file order, ``t`` non-decreasing: the UNIX epoch when the file has date-time lines, else the
        subtitle clock in seconds. ``frame`` is ``FrameCnt``/``SrtCnt`` or the subtitle index. Pitch and
        heading come only from the gimbal (``gb_pitch``/``gb_yaw``/``gb_roll`` or ``G.PRY``), converted
        with `pitch_from_dji`; aircraft attitude (``F.PRY``) is ignored; without gimbal fields they are None.
        `parse_srt_report` returns the same records with what was skipped and the GPS resolution.

    Raises
    ------
    ValueError
        ``source: what`` when the file gives no record at all (see `parse_srt_report`).
    """
    return parse_srt_report(
        text, source=source, utc_offset_s=utc_offset_s, height_offset_m=height_offset_m, gps_order=gps_order
    ).records


def read_srt_report(path: str | Path, **kw: Any) -> SrtReport:
    """Read a DJI SRT file with its report; keyword arguments as in `parse_srt` (``source``: the path)."""
    kw.setdefault("source", str(path))
    return parse_srt_report(read_text(path), **kw)


def read_srt(path: str | Path, **kw: Any) -> list[Telemetry]:
    """Read a DJI SRT file; keyword arguments as in `parse_srt` (``source`` defaults to the path)."""
    return read_srt_report(path, **kw).records

"""The telemetry record: one validated sample of a UAV's position, height and gimbal angles.

Also the DJI gimbal pitch convention (negative down) and the tolerance that clamps small overshoots.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from shared.geo import Pose

logger = logging.getLogger(__name__)

#: What a command says when the telemetry has no height above ground and none was given.
NO_HEIGHT_MESSAGE = (
    "telemetry has no height above ground: pass --height-m METRES (the flight's height above the ground) "
    "or, if it logs altitude above sea level, --height-offset-m=-(ground elevation in metres)"
)

#: Gimbal pitch readings this far outside 0..90 deg are measurement noise and are clamped; beyond, an error.
PITCH_TOLERANCE_DEG = 1.0

def finite_number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"Telemetry.{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"Telemetry.{name} must be finite, got {value!r}")
    return number


def wrap360(deg: float) -> float:
    wrapped = deg % 360.0
    return 0.0 if wrapped >= 360.0 else wrapped + 0.0  # -1e-20 % 360 rounds to 360.0; + 0.0 drops -0.0


def wrap180(deg: float) -> float:
    return wrap360(deg + 180.0) - 180.0


@dataclass(frozen=True, slots=True)
class Telemetry:
    """One telemetry sample of a UAV and its gimbal.

    Attributes
    ----------
    t : float
        Seconds. UNIX epoch (UTC) when the source gives a date; otherwise the source's own relative clock
        (SRT subtitle start time, a CSV's time column), which starts near 0 at the first sample.
    lat, lon : float
        WGS84 degrees, signed (S and W negative); lat in [-90, 90], lon in [-180, 180].
    height_m : float or None
        Metres above the ground under the UAV (SeaDronesSee ``altitude``, DJI ``rel_alt``). Any finite
        value is accepted (a UAV on its pad reads 0 or slightly below); `to_pose` needs > 0. None when the
        source gives no height above ground (some DJI SRT firmware): `to_pose` then needs one.
    pitch_deg : float or None
        Gimbal depression below the horizon, 0..90 (90 = nadir); None if the source lacks it.
    heading_deg : float or None
        Gimbal yaw clockwise from true north, normalised to [0, 360); None if the source lacks it.
    roll_deg : float
        Gimbal roll, normalised to [-180, 180); 0 when unknown (gimbals hold the horizon level).
    speed_mps : float or None
        Horizontal ground speed, >= 0.
    vel_en_mps : tuple of float or None
        (east, north) velocity in m/s if known.
    frame : int or None
        The source's frame counter or index (DJI counters start at 1), >= 0.
    recording : bool or None
        The camera was recording video at this sample (AirData's ``isVideo``); None when the source does
        not say.
    hfov_deg : float or None
        The camera's horizontal field of view at this sample, in (0, 180) degrees, when the source sends it (MISB
        ST 0601 tag 16: a zoom lens's current field of view); None otherwise. The video source applies it to the
        camera per frame when it changes during the flight (`agent.field_of_view`).
    zoom_ratio : float or None
        The camera's digital zoom at this sample, > 0 (1 = none): the frame is the centre 1 / zoom_ratio of the
        unzoomed view, so its field of view is the camera file's narrowed that many times (a DJI SRT's
        ``dzoom_ratio`` on a fixed lens); None when the source does not say. Applied like hfov_deg (which wins).
    """

    t: float
    lat: float
    lon: float
    height_m: float | None
    pitch_deg: float | None
    heading_deg: float | None
    roll_deg: float = 0.0
    speed_mps: float | None = None
    vel_en_mps: tuple[float, float] | None = None
    frame: int | None = None
    recording: bool | None = None
    hfov_deg: float | None = None
    zoom_ratio: float | None = None

    def __post_init__(self) -> None:
        put = object.__setattr__  # frozen: normalised values are written once, here
        put(self, "t", finite_number("t", self.t))
        lat = finite_number("lat", self.lat)
        if not -90.0 <= lat <= 90.0:
            raise ValueError(f"Telemetry.lat={lat!r} is outside [-90, 90] degrees")
        put(self, "lat", lat)
        lon = finite_number("lon", self.lon)
        if not -180.0 <= lon <= 180.0:
            raise ValueError(f"Telemetry.lon={lon!r} is outside [-180, 180] degrees")
        put(self, "lon", lon)
        if self.height_m is not None:
            put(self, "height_m", finite_number("height_m", self.height_m))
        if self.pitch_deg is not None:
            pitch = finite_number("pitch_deg", self.pitch_deg)
            if not 0.0 <= pitch <= 90.0:
                raise ValueError(f"Telemetry.pitch_deg={pitch!r} is outside [0, 90] (depression, 90 = nadir)")
            put(self, "pitch_deg", pitch + 0.0)
        if self.heading_deg is not None:
            put(self, "heading_deg", wrap360(finite_number("heading_deg", self.heading_deg)))
        put(self, "roll_deg", wrap180(finite_number("roll_deg", self.roll_deg)))
        if self.speed_mps is not None:
            speed = finite_number("speed_mps", self.speed_mps)
            if speed < 0.0:
                raise ValueError(f"Telemetry.speed_mps={speed!r} must be >= 0")
            put(self, "speed_mps", speed)
        if self.vel_en_mps is not None:
            if isinstance(self.vel_en_mps, (str, bytes)) or len(self.vel_en_mps) != 2:
                raise ValueError(f"Telemetry.vel_en_mps={self.vel_en_mps!r} must be (east, north)")
            east, north = self.vel_en_mps
            put(self, "vel_en_mps", (finite_number("vel_en_mps[0]", east), finite_number("vel_en_mps[1]", north)))
        if self.frame is not None:
            if isinstance(self.frame, bool) or not isinstance(self.frame, (int, np.integer)):
                raise ValueError(f"Telemetry.frame must be an integer, got {self.frame!r}")
            if self.frame < 0:
                raise ValueError(f"Telemetry.frame={self.frame!r} must be >= 0")
            put(self, "frame", int(self.frame))
        if self.recording is not None and not isinstance(self.recording, (bool, np.bool_)):
            raise ValueError(f"Telemetry.recording must be a bool or None, got {self.recording!r}")
        if self.recording is not None:
            put(self, "recording", bool(self.recording))
        if self.hfov_deg is not None:
            hfov = finite_number("hfov_deg", self.hfov_deg)
            if not 0.0 < hfov < 180.0:
                raise ValueError(f"Telemetry.hfov_deg={hfov!r} is outside (0, 180) degrees")
            put(self, "hfov_deg", hfov)
        if self.zoom_ratio is not None:
            zoom = finite_number("zoom_ratio", self.zoom_ratio)
            if zoom <= 0.0:
                raise ValueError(f"Telemetry.zoom_ratio={zoom!r} must be > 0 (1 = no zoom)")
            put(self, "zoom_ratio", zoom)

    @property
    def has_fix(self) -> bool:
        """False at latitude and longitude 0, where loggers write "no GPS fix": no position, so no pose from it."""
        return not (self.lat == 0.0 and self.lon == 0.0)

    def to_pose(
        self, pitch_deg: float | None = None, heading_deg: float | None = None, *, height_m: float | None = None,
        replace: bool = True,
    ) -> Pose:
        """Camera pose for `shared.geo`, with optional gimbal angles that override or supply missing ones.

        Parameters
        ----------
        pitch_deg, heading_deg : float, optional
            Depression 0..90 and heading in degrees; when given they replace the telemetry's values, or with
            ``replace=False`` only supply the ones it lacks (the commands' `--pitch-deg` / `--heading-deg`).
        height_m : float, optional
            Height above the ground used when the telemetry has none (it never replaces a logged height).

        Returns
        -------
        shared.geo.Pose

        Raises
        ------
        ValueError
            If an angle or the height is missing from both the telemetry and the arguments, or `shared.geo.Pose`
            rejects a value (e.g. height_m <= 0 on the ground).
        """
        from shared.geo import Pose  # geo imports OpenCV; telemetry parsing does not need it

        if not replace:
            pitch_deg = pitch_deg if self.pitch_deg is None else None
            heading_deg = heading_deg if self.heading_deg is None else None
        pitch = self.pitch_deg if pitch_deg is None else pitch_deg
        if pitch is None:
            raise ValueError("telemetry has no gimbal pitch: pass --pitch-deg or use a source with gimbal angles")
        heading = self.heading_deg if heading_deg is None else heading_deg
        if heading is None:
            raise ValueError("telemetry has no gimbal heading: pass --heading-deg or use a source with gimbal angles")
        heading = finite_number("heading_deg", heading)
        height = self.height_m if self.height_m is not None else height_m
        if height is None:
            raise ValueError(NO_HEIGHT_MESSAGE)
        return Pose(
            lat=self.lat,
            lon=self.lon,
            height_m=finite_number("height_m", height),
            pitch_deg=finite_number("pitch_deg", pitch),
            heading_deg=wrap360(heading),
            roll_deg=self.roll_deg,
        )


def pitch_from_dji(gb_pitch_deg: float, tolerance_deg: float = PITCH_TOLERANCE_DEG) -> float:
    """Convert a DJI gimbal pitch (negative down, -90 = nadir) to our depression 0..90.

    Parameters
    ----------
    gb_pitch_deg : float
        DJI ``gb_pitch`` / ``G.PRY`` pitch / XMP ``GimbalPitchDegree`` in degrees.
    tolerance_deg : float
        Readings up to this far beyond the range (e.g. -90.3, +0.5) are clamped to 90 or 0.

    Returns
    -------
    float
        Depression below the horizon in [0, 90].

    Raises
    ------
    ValueError
        If the reading is non-finite or further outside than the tolerance (camera tilted up, or past nadir).
    """
    return clamp_pitch(-float(gb_pitch_deg), tolerance_deg, f"DJI gimbal pitch {gb_pitch_deg!r}")


def clamp_pitch(depression_deg: float, tolerance_deg: float, what: str) -> float:
    if not math.isfinite(depression_deg):
        raise ValueError(f"{what} is not finite")
    if 0.0 <= depression_deg <= 90.0:
        return depression_deg + 0.0
    if -tolerance_deg <= depression_deg < 0.0:
        return 0.0
    if 90.0 < depression_deg <= 90.0 + tolerance_deg:
        return 90.0
    raise ValueError(
        f"{what} is a depression of {depression_deg:g} deg, outside 0..90 by more than {tolerance_deg:g} deg"
    )


def pitch_or_none(depression_deg: float, what: str, *, warn: bool = True) -> float | None:
    """A record's pitch, or None (with a warning unless `warn` is False) when the camera looks up or past nadir.

    A pilot tilting the gimbal above the horizon for a moment is normal flying: those samples
    have no ground view (no pose), the rest of the flight stays usable.
    """
    try:
        return clamp_pitch(depression_deg, PITCH_TOLERANCE_DEG, what)
    except ValueError as err:
        if warn:
            logger.warning("%s: no pose for this sample", err)
        return None


def recording_start(records: list[Telemetry]) -> tuple[float | None, int]:
    """(time of the first sample recording video, number of recordings) of records in time order.

    A log that marks when the camera records (AirData's ``isVideo``) says where a video's first frame
    lies on the telemetry's clock; (None, 0) when no record says it records.
    """
    start: float | None = None
    starts = 0
    previous = False
    for record in records:
        now = bool(record.recording)
        if now and not previous:
            starts += 1
            if start is None:
                start = record.t
        previous = now
    return start, starts

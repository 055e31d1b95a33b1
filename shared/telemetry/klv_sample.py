"""One decoded ST 0601 packet (`KlvSample`) and what it means for the camera: heading, depression, roll, height.

The platform's attitude and the sensor's angles relative to it are composed exactly (`camera_angles_deg`); the
height above ground comes from the sensor altitude and the frame centre's elevation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared.telemetry.record import PITCH_TOLERANCE_DEG, Telemetry, clamp_pitch, wrap180, wrap360

__all__ = ["KlvSample", "camera_angles_deg"]

_Matrix = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


def _zyx(yaw_deg: float, pitch_deg: float, roll_deg: float) -> _Matrix:
    """Rotation taking body (forward, right, down) vectors to the parent frame: yaw, then pitch up, then roll."""
    cy, sy = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    cp, sp = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    cr, sr = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    return ((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
            (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
            (-sp, cp * sr, cp * cr))


def _matmul(a: _Matrix, b: _Matrix) -> _Matrix:
    rows = tuple(tuple(sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)) for i in range(3))
    return rows  # type: ignore[return-value]


def camera_angles_deg(platform_heading_deg: float, platform_pitch_deg: float, platform_roll_deg: float,
                      rel_azimuth_deg: float, rel_elevation_deg: float,
                      rel_roll_deg: float = 0.0) -> tuple[float, float, float]:
    """The camera's heading, depression and roll from ST 0601 platform and sensor-relative angles.

    The platform's attitude (heading clockwise from north, pitch nose up, roll right wing down) and then the
    sensor's rotation relative to the platform (azimuth clockwise seen from above, elevation up, roll clockwise
    seen from behind; the standard's order) are composed exactly, so a banked or pitched aircraft moves the line
    of sight. With a level platform this is heading + azimuth and depression = -elevation.

    Returns
    -------
    heading_deg : float
        Of the optical axis, [0, 360).
    depression_deg : float
        Below the horizon, -90..90 (negative: looking up). A rotation whose roll would exceed +-90 deg is
        written as the same rotation past nadir (depression > 90, heading + 180), which callers clamp or reject.
    roll_deg : float
        About the optical axis, right side down positive (`shared.geo.Pose`), in [-90, 90] except past nadir.
    """
    r = _matmul(_zyx(platform_heading_deg, platform_pitch_deg, platform_roll_deg),
                _zyx(rel_azimuth_deg, rel_elevation_deg, rel_roll_deg))
    north, east, down = r[0][0], r[1][0], r[2][0]
    horizontal = math.hypot(north, east)
    depression = math.degrees(math.atan2(down, horizontal))
    if horizontal > 1e-9:
        heading = math.degrees(math.atan2(east, north))
        roll = math.degrees(math.atan2(r[2][1], r[2][2]))
    else:  # straight down or up: heading and roll turn the image alike; all of it goes in the heading (roll 0)
        heading = math.degrees(math.atan2(-r[0][1], r[1][1]))
        roll = 0.0
    if abs(roll) > 90.0:  # the same rotation with the image's top up: past nadir (or zenith), heading reversed
        heading += 180.0
        depression = math.copysign(180.0, depression) - depression
        roll -= math.copysign(180.0, roll)
    return wrap360(heading), depression, wrap180(roll)


@dataclass(frozen=True, slots=True)
class KlvSample:
    """The decoded values of one ST 0601 packet (items left out are held from earlier packets, see `read_klv`).

    Angles in degrees, lengths in metres, None where neither the packet nor a recent one gave the item.

    Attributes
    ----------
    t : float
        Precision Time Stamp, UNIX seconds.
    video_time_s : float or None
        Presentation time in the video, seconds after its first frame (from the PES PTS of a transport stream
        with video); None for raw KLV files or metadata without a PTS.
    platform_heading_deg, platform_pitch_deg, platform_roll_deg : float or None
        Aircraft attitude: heading clockwise from true north, pitch nose up, roll right wing down; NaN pitch or roll:
        sent as "out of range" (beyond the short items' +-20 / +-50 deg, no full-range item).
    sensor_lat, sensor_lon : float or None
        WGS84 position of the sensor.
    sensor_alt_msl_m, sensor_hae_m : float or None
        Sensor altitude above mean sea level (tag 15) and above the WGS84 ellipsoid (tag 75).
    hfov_deg, vfov_deg : float or None
        Fields of view; a camera's focal length in pixels is ``(width / 2) / tan(hfov / 2)``.
    sensor_rel_azimuth_deg, sensor_rel_elevation_deg, sensor_rel_roll_deg : float or None
        Sensor angles relative to the platform; elevation negative below the platform's plane.
    frame_center_lat, frame_center_lon, frame_center_elevation_m, frame_center_hae_m : float or None
        Where the image centre meets the terrain; elevation above MSL (tag 25) and the ellipsoid (tag 78).
    vel_north_mps, vel_east_mps : float or None
        Sensor velocity.
    version : int or None
        ST 0601 version of the packet (tag 65).
    """

    t: float
    video_time_s: float | None = None
    platform_heading_deg: float | None = None
    platform_pitch_deg: float | None = None
    platform_roll_deg: float | None = None
    sensor_lat: float | None = None
    sensor_lon: float | None = None
    sensor_alt_msl_m: float | None = None
    sensor_hae_m: float | None = None
    hfov_deg: float | None = None
    vfov_deg: float | None = None
    sensor_rel_azimuth_deg: float | None = None
    sensor_rel_elevation_deg: float | None = None
    sensor_rel_roll_deg: float | None = None
    frame_center_lat: float | None = None
    frame_center_lon: float | None = None
    frame_center_elevation_m: float | None = None
    frame_center_hae_m: float | None = None
    vel_north_mps: float | None = None
    vel_east_mps: float | None = None
    version: int | None = None

    def __post_init__(self) -> None:
        for name in ("t", "video_time_s"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"KlvSample.{name}={value!r} must be a finite number of seconds")

    def height_above_ground_m(self, height_offset_m: float | None = None) -> float | None:
        """Height of the sensor above the ground, or None when the packet cannot tell.

        Without ``height_offset_m``: sensor altitude - frame centre elevation (both above MSL), else the same
        with the ellipsoid heights (tags 75, 78): the height above the terrain where the camera looks, equal to
        the height above the ground below the UAV over level ground. With ``height_offset_m`` (minus the ground
        elevation above MSL, as ``--height-offset-m`` gives it): sensor altitude + offset (the height above the
        ellipsoid, tag 75, where no altitude above MSL is sent: the offset is then minus the ground's).
        """
        alt = self.sensor_alt_msl_m
        if height_offset_m is not None:  # above MSL, else above the ellipsoid (a stream with tag 75 only)
            alt = alt if alt is not None else self.sensor_hae_m
            return None if alt is None else alt + height_offset_m
        if alt is not None and self.frame_center_elevation_m is not None:
            return alt - self.frame_center_elevation_m
        if self.sensor_hae_m is not None and self.frame_center_hae_m is not None:
            return self.sensor_hae_m - self.frame_center_hae_m
        return None

    @property
    def attitude_out_of_range(self) -> bool:
        """The platform pitch or roll was sent as "out of range" (NaN): beyond tags 6 / 7, with no tag 90 / 91."""
        return any(v is not None and math.isnan(v) for v in (self.platform_pitch_deg, self.platform_roll_deg))

    def camera_angles(self) -> tuple[float | None, float | None, float]:
        """(heading or None, depression or None, roll) of the camera, by `camera_angles_deg`.

        Missing platform pitch / roll and sensor azimuth / roll count as 0; a pitch or roll sent as "out of range"
        (NaN, `attitude_out_of_range`) leaves heading and depression None. No platform heading: heading None.
        No sensor relative elevation: depression None, heading = platform heading + azimuth, roll 0 (a camera
        fixed on the airframe: its tilt comes from ``--pitch-deg``).
        """
        azimuth = self.sensor_rel_azimuth_deg or 0.0
        if self.attitude_out_of_range and self.sensor_rel_elevation_deg is not None:
            return None, None, 0.0  # a dive or a bank beyond the short items' range: the line of sight is unknown
        if self.sensor_rel_elevation_deg is None:
            heading = None if self.platform_heading_deg is None else wrap360(self.platform_heading_deg + azimuth)
            return heading, None, 0.0
        heading, depression, roll = camera_angles_deg(
            self.platform_heading_deg or 0.0, self.platform_pitch_deg or 0.0, self.platform_roll_deg or 0.0,
            azimuth, self.sensor_rel_elevation_deg, self.sensor_rel_roll_deg or 0.0)
        return (heading if self.platform_heading_deg is not None else None), depression, roll

    def to_telemetry(self, height_offset_m: float | None = None) -> Telemetry | None:
        """The `Telemetry` record of this sample at time ``t``, or None without a sensor position.

        pitch_deg is None when the camera looks above the horizon or past nadir by more than
        `PITCH_TOLERANCE_DEG` (smaller overshoots are clamped, as for every source); height as in
        `height_above_ground_m`; velocity from tags 79 / 80; the horizontal field of view from tag 16 (none at 0 or
        180 deg, which no pinhole camera has).
        """
        if self.sensor_lat is None or self.sensor_lon is None:
            return None
        heading, depression, roll = self.camera_angles()
        pitch = None
        if depression is not None:
            try:
                pitch = clamp_pitch(depression, PITCH_TOLERANCE_DEG, f"KLV camera depression at t={self.t:.3f}")
            except ValueError:
                pitch = None
        vel = None if self.vel_east_mps is None or self.vel_north_mps is None else (
            self.vel_east_mps, self.vel_north_mps)
        return Telemetry(t=self.t, lat=self.sensor_lat, lon=self.sensor_lon,
                         height_m=self.height_above_ground_m(height_offset_m), pitch_deg=pitch, heading_deg=heading,
                         roll_deg=roll, speed_mps=None if vel is None else math.hypot(*vel), vel_en_mps=vel,
                         hfov_deg=self.hfov_deg if self.hfov_deg is not None and 0.0 < self.hfov_deg < 180.0 else None)

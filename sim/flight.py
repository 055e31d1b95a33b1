"""UAV flights: the TRUE camera pose as a function of time.

Two kinds of trajectory (`KeyframeFlight` with smooth cosine easing between keyframes, and the analytic
`OrbitFlight`) and the flight specs a scenario lists (`HoverSweepsSpec`, `OrbitSpec`, `LawnmowerSpec`,
`ClimbSpec`, `LineSpec`), each of which draws its random parameters from a generator in `build`.

Positions are world-local east/north metres around the world origin; height is metres above the ground;
pitch is the gimbal's depression below the horizon (17..90 deg); heading is the gimbal's yaw clockwise from
north. `FlightState.aircraft_heading_deg` is the aircraft's nose (the SeaDronesSee ``compass_heading``),
which differs from the gimbal heading in some flights (an orbit with the nose along the track).
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import numpy as np

MIN_HEIGHT_M, MAX_HEIGHT_M = 10.0, 100.0
MIN_PITCH_DEG, MAX_PITCH_DEG = 17.0, 90.0
_DT_DIFF_S = 0.02  # step of the central differences that give velocities and turn rates


@dataclass(frozen=True, slots=True)
class FlightState:
    """True state of the UAV and its camera at time `t_s` (seconds since the flight started).

    Velocities are m/s in east/north/up; `heading_rate_deg_s` is the gimbal's yaw rate (deg/s).
    """

    t_s: float
    east_m: float
    north_m: float
    height_m: float
    pitch_deg: float
    heading_deg: float
    aircraft_heading_deg: float
    vel_east_mps: float
    vel_north_mps: float
    vel_up_mps: float
    heading_rate_deg_s: float


class Flight(abc.ABC):
    """Base class: subclasses implement `_raw(t_s)` -> (east, north, height, pitch, heading, aircraft_heading).

    Headings from `_raw` may be unwrapped (continuous); `state` wraps them to [0, 360).
    """

    kind = "flight"
    duration_s: float = math.inf

    @abc.abstractmethod
    def _raw(self, t_s: float) -> tuple[float, float, float, float, float, float]:
        """(east_m, north_m, height_m, pitch_deg, heading_deg, aircraft_heading_deg) at t_s seconds."""

    def state(self, t_s: float) -> FlightState:
        """The true state at t_s seconds (clamped to the flight's keyframes where they end)."""
        e, n, h, p, hd, ahd = self._raw(t_s)
        e0, n0, h0, _, hd0, _ = self._raw(t_s - _DT_DIFF_S)
        e1, n1, h1, _, hd1, _ = self._raw(t_s + _DT_DIFF_S)
        d = 2.0 * _DT_DIFF_S
        return FlightState(
            t_s=float(t_s), east_m=float(e), north_m=float(n), height_m=float(h),
            pitch_deg=float(min(max(p, 0.0), 90.0)), heading_deg=float(hd % 360.0),
            aircraft_heading_deg=float(ahd % 360.0),
            vel_east_mps=float((e1 - e0) / d), vel_north_mps=float((n1 - n0) / d),
            vel_up_mps=float((h1 - h0) / d), heading_rate_deg_s=float((hd1 - hd0) / d),
        )


class KeyframeFlight(Flight):
    """Piecewise flight through keyframes with cosine easing (zero velocity at each keyframe).

    Parameters
    ----------
    times_s : (K,) float, strictly increasing seconds
    east_m, north_m, height_m, pitch_deg, heading_deg : (K,) float
        Keyframe values; headings are unwrapped (a turn from 350 to 10 deg is written 350 -> 370).
    aircraft_offset_deg : float
        Constant offset of the aircraft's nose from the gimbal heading.
    kind : str
        A short name for logs and video names.
    """

    def __init__(self, times_s, east_m, north_m, height_m, pitch_deg, heading_deg, *,
                 aircraft_offset_deg: float = 0.0, kind: str = "keyframes") -> None:
        self._t = np.asarray(times_s, dtype=np.float64)
        if self._t.ndim != 1 or len(self._t) < 1 or np.any(np.diff(self._t) <= 0):
            raise ValueError("KeyframeFlight times_s must be a non-empty, strictly increasing (K,) array")
        values = [np.asarray(a, dtype=np.float64) for a in (east_m, north_m, height_m, pitch_deg, heading_deg)]
        if any(v.shape != self._t.shape for v in values):
            raise ValueError("KeyframeFlight keyframe arrays must all have the length of times_s")
        self._v = np.vstack(values)
        self.aircraft_offset_deg = float(aircraft_offset_deg)
        self.kind = kind
        self.duration_s = float(self._t[-1])

    def _raw(self, t_s: float) -> tuple[float, float, float, float, float, float]:
        t = self._t
        if t_s <= t[0]:
            v = self._v[:, 0]
        elif t_s >= t[-1]:
            v = self._v[:, -1]
        else:
            k = int(np.searchsorted(t, t_s, side="right")) - 1
            u = (t_s - t[k]) / (t[k + 1] - t[k])
            w = 0.5 - 0.5 * math.cos(math.pi * u)
            v = self._v[:, k] + w * (self._v[:, k + 1] - self._v[:, k])
        return v[0], v[1], v[2], v[3], v[4], v[4] + self.aircraft_offset_deg


class OrbitFlight(Flight):
    """Circle around a centre at constant height and speed, the camera looking at the centre.

    Parameters
    ----------
    centre_east_m, centre_north_m : float
        Orbit centre (world-local metres).
    radius_m, height_m, pitch_deg : float
    speed_mps : float
        Ground speed along the circle.
    start_bearing_deg : float
        Bearing from the centre to the UAV at t = 0.
    clockwise : bool
        Direction of travel seen from above.
    nose_along_track : bool
        True: the aircraft's nose points along the track (free gimbal, Matrice-style), so
        ``compass_heading`` differs from ``gimbal_heading`` by 90 deg. False: the nose follows the gimbal.
    """

    kind = "orbit"

    def __init__(self, centre_east_m: float, centre_north_m: float, radius_m: float, height_m: float,
                 pitch_deg: float, speed_mps: float, start_bearing_deg: float, clockwise: bool = True,
                 nose_along_track: bool = True) -> None:
        self.c = (float(centre_east_m), float(centre_north_m))
        self.r, self.h, self.p = float(radius_m), float(height_m), float(pitch_deg)
        self.omega_deg_s = math.degrees(speed_mps / radius_m) * (1.0 if clockwise else -1.0)
        self.b0 = float(start_bearing_deg)
        self.nose_along_track = nose_along_track

    def _raw(self, t_s: float) -> tuple[float, float, float, float, float, float]:
        b = self.b0 + self.omega_deg_s * t_s
        br = math.radians(b)
        e = self.c[0] + self.r * math.sin(br)
        n = self.c[1] + self.r * math.cos(br)
        heading = b + 180.0
        track = b + (90.0 if self.omega_deg_s > 0 else -90.0)
        return e, n, self.h, self.p, heading, track if self.nose_along_track else heading


# ---------------------------------------------------------------------------------------------
# Flight specs: what a scenario lists. Ranges are (low, high) and drawn per flight in `build`.
# ---------------------------------------------------------------------------------------------

def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(lo_hi[0], lo_hi[1]))


def _check_ranges(name: str, height_m: tuple[float, float], pitch_deg: tuple[float, float],
                  min_pitch_deg: float = MIN_PITCH_DEG) -> None:
    if not MIN_HEIGHT_M <= height_m[0] <= height_m[1] <= MAX_HEIGHT_M:
        raise ValueError(f"{name}.height_m={height_m!r} must lie in [{MIN_HEIGHT_M}, {MAX_HEIGHT_M}] m")
    if not min_pitch_deg <= pitch_deg[0] <= pitch_deg[1] <= MAX_PITCH_DEG:
        raise ValueError(f"{name}.pitch_deg={pitch_deg!r} must lie in [{min_pitch_deg}, {MAX_PITCH_DEG}] deg")


@dataclass(frozen=True, slots=True)
class HoverSweepsSpec:
    """Hover at a point looking at the scene centre, with fast heading sweeps to the sides and back.

    The UAV hovers `distance_m` from the origin at `bearing_deg`; the base heading looks at the origin.
    It dwells, turns by +-`sweep_deg` with a peak rate of `sweep_rate_deg_s`, dwells, turns back, and so
    on, alternating sides, so objects leave and re-enter the view. A turn lasts at least `min_turn_s`
    (0.2 s; a small value with a high rate makes the view jump within a frame or two).
    """

    uav: str = "uav1"
    bearing_deg: tuple[float, float] = (0.0, 360.0)
    distance_m: tuple[float, float] = (40.0, 60.0)
    height_m: tuple[float, float] = (20.0, 50.0)
    pitch_deg: tuple[float, float] = (25.0, 45.0)
    sweep_deg: tuple[float, float] = (50.0, 100.0)
    sweep_rate_deg_s: tuple[float, float] = (60.0, 100.0)
    dwell_s: tuple[float, float] = (2.0, 5.0)
    kind: str = "hover"
    min_turn_s: float = 0.2
    #: The lowest pitch the spec may ask for: MIN_PITCH_DEG, or lower (down to 3 deg) for a far, low view whose
    #: objects lie beyond the pipeline's range (sim.domains' far group); a view that low shows the horizon.
    min_pitch_deg: float = MIN_PITCH_DEG

    def __post_init__(self) -> None:
        if not 3.0 <= self.min_pitch_deg <= MIN_PITCH_DEG:
            raise ValueError(f"HoverSweepsSpec.min_pitch_deg={self.min_pitch_deg!r} must lie in [3, {MIN_PITCH_DEG}] "
                             "deg")
        _check_ranges("HoverSweepsSpec", self.height_m, self.pitch_deg, self.min_pitch_deg)
        if not (math.isfinite(self.min_turn_s) and self.min_turn_s > 0):
            raise ValueError(f"HoverSweepsSpec.min_turn_s={self.min_turn_s!r} must be > 0 s")

    def build(self, rng: np.random.Generator, duration_s: float) -> Flight:
        """A keyframe flight covering at least duration_s seconds."""
        bearing = _u(rng, self.bearing_deg)
        dist = _u(rng, self.distance_m)
        e = dist * math.sin(math.radians(bearing))
        n = dist * math.cos(math.radians(bearing))
        h, p = _u(rng, self.height_m), _u(rng, self.pitch_deg)
        base = (bearing + 180.0) % 360.0
        times, heads = [0.0], [base]
        t, side, at_base = 0.0, 1.0 if rng.uniform() < 0.5 else -1.0, True
        while t < duration_s:
            t += _u(rng, self.dwell_s)
            times.append(t)
            heads.append(heads[-1])
            if at_base:
                target = base + side * _u(rng, self.sweep_deg)
                side = -side
            else:
                target = base
            at_base = not at_base
            delta = abs(target - heads[-1])
            # Cosine easing: peak rate = pi/2 * delta / T.
            t += max(self.min_turn_s, math.pi / 2.0 * delta / _u(rng, self.sweep_rate_deg_s))
            times.append(t)
            heads.append(target)
        k = len(times)
        return KeyframeFlight(times, [e] * k, [n] * k, [h] * k, [p] * k, heads, kind=self.kind)


@dataclass(frozen=True, slots=True)
class OrbitSpec:
    """Orbit the scene centre, camera looking at the centre (pitch = atan(height / radius) + offset)."""

    uav: str = "uav1"
    radius_m: tuple[float, float] = (40.0, 70.0)
    height_m: tuple[float, float] = (30.0, 60.0)
    speed_mps: tuple[float, float] = (3.0, 5.0)
    pitch_offset_deg: tuple[float, float] = (-5.0, 5.0)
    nose_along_track: bool = True
    kind: str = "orbit"

    def __post_init__(self) -> None:
        _check_ranges("OrbitSpec", self.height_m, (MIN_PITCH_DEG, MAX_PITCH_DEG))

    def build(self, rng: np.random.Generator, duration_s: float) -> Flight:
        """An orbit (unbounded in time)."""
        r, h = _u(rng, self.radius_m), _u(rng, self.height_m)
        pitch = min(max(math.degrees(math.atan2(h, r)) + _u(rng, self.pitch_offset_deg), MIN_PITCH_DEG), 90.0)
        return OrbitFlight(0.0, 0.0, r, h, pitch, _u(rng, self.speed_mps), _u(rng, (0.0, 360.0)),
                           clockwise=bool(rng.uniform() < 0.5), nose_along_track=self.nose_along_track)


@dataclass(frozen=True, slots=True)
class LawnmowerSpec:
    """Survey lanes across the scene centre; the camera faces the direction of travel.

    At each lane end the UAV stops, turns 90 deg (at up to `turn_rate_deg_s`), moves `lane_spacing_m`,
    turns again and flies the next lane back. The lane direction is random.
    """

    uav: str = "uav1"
    height_m: tuple[float, float] = (40.0, 80.0)
    pitch_deg: tuple[float, float] = (70.0, 90.0)
    speed_mps: tuple[float, float] = (4.0, 6.0)
    lane_length_m: tuple[float, float] = (70.0, 90.0)
    lane_spacing_m: tuple[float, float] = (25.0, 35.0)
    turn_rate_deg_s: tuple[float, float] = (60.0, 90.0)
    kind: str = "lawnmower"

    def __post_init__(self) -> None:
        _check_ranges("LawnmowerSpec", self.height_m, self.pitch_deg)

    def build(self, rng: np.random.Generator, duration_s: float) -> Flight:
        """A keyframe flight covering at least duration_s seconds."""
        h, p, v = _u(rng, self.height_m), _u(rng, self.pitch_deg), _u(rng, self.speed_mps)
        length, spacing = _u(rng, self.lane_length_m), _u(rng, self.lane_spacing_m)
        turn_rate = _u(rng, self.turn_rate_deg_s)
        axis = _u(rng, (0.0, 360.0))
        ax = np.array([math.sin(math.radians(axis)), math.cos(math.radians(axis))])
        perp = np.array([ax[1], -ax[0]])  # 90 deg clockwise of the lane axis
        pos = -0.5 * length * ax - spacing * perp
        times, pts, heads = [0.0], [pos.copy()], [axis]
        t, direction, side_turn = 0.0, 1.0, 90.0

        def add(dt: float, new_pos: np.ndarray, new_head: float) -> None:
            nonlocal t
            t += dt
            times.append(t)
            pts.append(new_pos.copy())
            heads.append(new_head)

        while t < duration_s:
            pos = pos + direction * length * ax
            add(math.pi / 2.0 * length / v / 1.0, pos, heads[-1])  # peak speed ~ pi/2 * mean speed
            turn_t = max(0.3, math.pi / 2.0 * 90.0 / turn_rate)
            add(turn_t, pos, heads[-1] + side_turn)
            pos = pos + spacing * perp
            add(max(1.0, spacing / v * math.pi / 2.0), pos, heads[-1])
            add(turn_t, pos, heads[-1] + side_turn)
            direction, side_turn = -direction, -side_turn
        arr = np.array(pts)
        k = len(times)
        return KeyframeFlight(times, arr[:, 0], arr[:, 1], [h] * k, [p] * k, heads, kind=self.kind)


@dataclass(frozen=True, slots=True)
class ClimbSpec:
    """Climb and descend between two heights while the gimbal pitch follows; hovering off the centre."""

    uav: str = "uav1"
    bearing_deg: tuple[float, float] = (0.0, 360.0)
    distance_m: tuple[float, float] = (30.0, 50.0)
    height_low_m: tuple[float, float] = (12.0, 20.0)
    height_high_m: tuple[float, float] = (60.0, 90.0)
    climb_rate_mps: tuple[float, float] = (3.0, 5.0)
    pitch_low_deg: tuple[float, float] = (20.0, 30.0)
    pitch_high_deg: tuple[float, float] = (50.0, 70.0)
    heading_jitter_deg: tuple[float, float] = (-15.0, 15.0)
    kind: str = "climb"

    def __post_init__(self) -> None:
        _check_ranges("ClimbSpec", (self.height_low_m[0], self.height_high_m[1]),
                      (self.pitch_low_deg[0], self.pitch_high_deg[1]))

    def build(self, rng: np.random.Generator, duration_s: float) -> Flight:
        """A keyframe flight alternating low and high, covering at least duration_s seconds."""
        bearing = _u(rng, self.bearing_deg)
        dist = _u(rng, self.distance_m)
        e, n = dist * math.sin(math.radians(bearing)), dist * math.cos(math.radians(bearing))
        base = (bearing + 180.0) % 360.0
        lo, hi = _u(rng, self.height_low_m), _u(rng, self.height_high_m)
        p_lo, p_hi = _u(rng, self.pitch_low_deg), _u(rng, self.pitch_high_deg)
        times, hs, ps, heads = [0.0], [lo], [p_lo], [base]
        t, up = 0.0, True
        while t < duration_s:
            t += math.pi / 2.0 * (hi - lo) / _u(rng, self.climb_rate_mps)
            times.append(t)
            hs.append(hi if up else lo)
            ps.append(p_hi if up else p_lo)
            heads.append(base + _u(rng, self.heading_jitter_deg))
            up = not up
        k = len(times)
        return KeyframeFlight(times, [e] * k, [n] * k, hs, ps, heads, kind=self.kind)


@dataclass(frozen=True, slots=True)
class LineSpec:
    """Fly slowly back and forth along a line at a fixed height, pitch and camera heading.

    The line is centred `distance_m` from the origin at `bearing_deg`, perpendicular to that bearing,
    and the camera looks at the origin's direction (base heading) plus `heading_offset_deg`.
    """

    uav: str = "uav1"
    bearing_deg: tuple[float, float] = (0.0, 0.0)
    distance_m: tuple[float, float] = (50.0, 50.0)
    half_length_m: tuple[float, float] = (15.0, 25.0)
    height_m: tuple[float, float] = (30.0, 40.0)
    pitch_deg: tuple[float, float] = (30.0, 40.0)
    speed_mps: tuple[float, float] = (1.5, 3.0)
    heading_offset_deg: tuple[float, float] = (-5.0, 5.0)
    kind: str = "line"

    def __post_init__(self) -> None:
        _check_ranges("LineSpec", self.height_m, self.pitch_deg)

    def build(self, rng: np.random.Generator, duration_s: float) -> Flight:
        """A keyframe flight covering at least duration_s seconds."""
        bearing = math.radians(_u(rng, self.bearing_deg))
        dist, half = _u(rng, self.distance_m), _u(rng, self.half_length_m)
        h, p, v = _u(rng, self.height_m), _u(rng, self.pitch_deg), _u(rng, self.speed_mps)
        heading = (math.degrees(bearing) + 180.0 + _u(rng, self.heading_offset_deg)) % 360.0
        c = np.array([dist * math.sin(bearing), dist * math.cos(bearing)])
        along = np.array([math.cos(bearing), -math.sin(bearing)])
        times, pts = [0.0], [c - half * along]
        t, sign = 0.0, 1.0
        while t < duration_s:
            t += math.pi / 2.0 * 2.0 * half / v
            times.append(t)
            pts.append(c + sign * half * along)
            sign = -sign
        arr = np.array(pts)
        k = len(times)
        return KeyframeFlight(times, arr[:, 0], arr[:, 1], [h] * k, [p] * k, [heading] * k, kind=self.kind)


FlightSpec = HoverSweepsSpec | OrbitSpec | LawnmowerSpec | ClimbSpec | LineSpec

"""A zoom lens's field of view from the telemetry, applied to each frame's camera (the video sources of `uavmm
agent`, `detect` and `anomaly --video`).

MISB ST 0601 KLV sends the sensor's horizontal field of view (tag 16; `Telemetry.hfov_deg`), MAVLink its
``CAMERA_FOV_STATUS``, a DJI SRT a digital zoom (`Telemetry.zoom_ratio`: the camera file's view narrowed that many
times). A camera file holds
one focal length; a zoom lens's changes in flight, and every ground point off the image centre scales with it (a
box 100 px off centre seen at 8 deg, projected with a camera file's 65 deg, lands 40 m out where it is 4 m). What
the telemetry's fields of view say decides, and the rule stands down where they do not settle it:

- they change during the flight by more than `ZOOM_RATIO` (a zoom): each frame's camera is the camera file's with
  the focal length of the field of view at the frame's time (`FieldOfView.at`; principal point and distortion
  kept); one warning says so, with the range;
- they stay constant and agree with the camera file within `AGREE_FRACTION`: the camera file as it is, nothing
  said;
- they stay constant and differ from it: a camera file made for another zoom, or an encoder sending a configured
  constant, and nothing in the file tells which: the camera file stays and a warning names both.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from shared.camera import Camera
from shared.telemetry import Telemetry

__all__ = ["AGREE_FRACTION", "LINEAR_WITHIN_S", "ZOOM_RATIO", "FieldOfView", "LiveFieldOfView", "ZoomedCamera",
           "field_of_view_track", "zoomed_hfov_deg"]

log = logging.getLogger("agent.sources")  # the video source's warnings, under its name

#: Largest over smallest field of view above which the lens zooms during the flight.
ZOOM_RATIO = 1.05
#: A constant field of view within this fraction of the camera file's agrees with it.
AGREE_FRACTION = 0.15
#: Two field-of-view samples at most this far apart (s) are interpolated between; farther apart the earlier one
#: holds until the next (an encoder that sends the field of view only when it changes).
LINEAR_WITHIN_S = 1.0


def _fov_at(times: np.ndarray, hfovs: np.ndarray, t: float) -> float:
    """The field of view at t of samples (times sorted): interpolated between samples up to `LINEAR_WITHIN_S` apart,
    else the last one before t (held), the first one before the first sample."""
    after = int(np.searchsorted(times, t, side="right"))
    if after == 0:
        return float(hfovs[0])
    if after == len(times):
        return float(hfovs[-1])
    t0, t1 = times[after - 1], times[after]
    h0, h1 = hfovs[after - 1], hfovs[after]
    if t1 - t0 > LINEAR_WITHIN_S:
        return float(h0)
    return float(h0 + (h1 - h0) * (t - t0) / (t1 - t0))


class ZoomedCamera:
    """A camera at a field of view, the same object for the same base camera and field of view (to 0.001 deg) on
    consecutive frames: the pipeline compares cameras to see a change."""

    def __init__(self) -> None:
        self._last: tuple[Camera, float, Camera] | None = None

    def __call__(self, base: Camera, hfov_deg: float) -> Camera:
        hfov = round(hfov_deg, 3)
        if self._last is not None and self._last[0] is base and self._last[1] == hfov:
            return self._last[2]
        zoomed = base.with_hfov(hfov)
        self._last = (base, hfov, zoomed)
        return zoomed


class FieldOfView:
    """The horizontal field of view over a flight, from the records that send one, and the camera it makes."""

    def __init__(self, t: Sequence[float], hfov_deg: Sequence[float], camera: Camera) -> None:
        order = np.argsort(np.asarray(t, dtype=np.float64), kind="stable")
        self.t = np.asarray(t, dtype=np.float64)[order]
        self.hfov_deg = np.asarray(hfov_deg, dtype=np.float64)[order]
        if not len(self.t):
            raise ValueError("FieldOfView needs at least one sample")
        self.camera = camera
        self._zoomed = ZoomedCamera()

    def at(self, t: float) -> float:
        """The field of view (deg) at telemetry time t: interpolated between samples up to `LINEAR_WITHIN_S` apart,
        else the last one before t (held), the first one before the first sample."""
        return _fov_at(self.t, self.hfov_deg, t)

    def camera_at(self, t: float, camera: Camera | None = None) -> Camera:
        """`camera` (default the one given at construction; e.g. refitted to the frames' size) with the field of view
        at time t; the same object for the same field of view (to 0.001 deg) on consecutive frames."""
        return self._zoomed(self.camera if camera is None else camera, self.at(t))


class LiveFieldOfView:
    """The same rule on a live link, where the flight's fields of view are not known in advance: the camera file
    until the fields of view seen so far differ by more than `ZOOM_RATIO` (the lens zoomed: one warning), then each
    frame's from the records around it. A constant one is never applied (as in `field_of_view_track`)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.lo, self.hi = math.inf, -math.inf
        self.active = False
        self._zoomed = ZoomedCamera()

    def camera_at(self, t: float, records: Sequence[Telemetry], camera: Camera) -> Camera:
        """`camera` with the field of view at t of `records` (those around t, sorted) once the lens has zoomed."""
        sent = [(r.t, r.hfov_deg) for r in records if r.hfov_deg is not None]
        if sent:
            self.lo = min(self.lo, min(h for _, h in sent))
            self.hi = max(self.hi, max(h for _, h in sent))
        if not self.active and self.hi / self.lo > ZOOM_RATIO:
            self.active = True
            log.warning("telemetry %s: the horizontal field of view changed (%.1f .. %.1f deg so far, a zoom lens; the "
                        "camera file's is %.1f deg): from now on each frame's focal length follows it", self.name,
                        self.lo, self.hi, camera.hfov_deg)
        if not self.active or not sent:
            return camera
        return self._zoomed(camera, _fov_at(np.array([s[0] for s in sent]), np.array([s[1] for s in sent]), t))


def zoomed_hfov_deg(hfov_deg: float, zoom_ratio: float) -> float:
    """The horizontal field of view of a digital zoom `zoom_ratio` of a view `hfov_deg` wide (the centre 1 / ratio of
    the image: the tangent of the half angle shrinks that many times)."""
    return math.degrees(2.0 * math.atan(math.tan(math.radians(hfov_deg) / 2.0) / zoom_ratio))


def field_of_view_track(path: str | Path, records: Sequence[Telemetry], camera: Camera) -> FieldOfView | None:
    """The field of view to apply per frame when the telemetry's changes during the flight (a zoom), else None; warns
    as the module says (a zoom applied; a constant field of view unlike the camera file's, not applied). Records that
    send a field of view (`Telemetry.hfov_deg`) decide; else those that send a digital zoom (`Telemetry.zoom_ratio`,
    a DJI SRT's ``dzoom_ratio``), as the camera file's field of view narrowed by it."""
    sent = [(r.t, r.hfov_deg) for r in records if r.hfov_deg is not None]
    what, kind = "horizontal field of view", "a zoom lens"
    if not sent:
        sent = [(r.t, zoomed_hfov_deg(camera.hfov_deg, r.zoom_ratio)) for r in records if r.zoom_ratio is not None]
        what, kind = "digital zoom's field of view", "a digital zoom"
    if not sent:
        return None
    hfovs = [h for _, h in sent]
    lo, mid, hi = min(hfovs), statistics.median(hfovs), max(hfovs)
    if hi / lo > ZOOM_RATIO:
        log.warning("telemetry %s: the %s changes during the flight (%.1f .. %.1f deg, %s; the camera file's is "
                    "%.1f deg): each frame's focal length follows it", path, what, lo, hi, kind, camera.hfov_deg)
        return FieldOfView([t for t, _ in sent], hfovs, camera)
    if abs(mid / camera.hfov_deg - 1.0) > AGREE_FRACTION:
        log.warning("telemetry %s: the %s it sends is %.1f deg, constant over the flight, where the camera's is %.1f "
                    "deg: a camera file for another zoom, or an encoder sending a set value? Every frame is projected "
                    "with the camera file's focal length (a constant field of view is not applied): give a camera "
                    "file for the zoom in use", path, what, mid, camera.hfov_deg)
    return None

"""Camera intrinsics: the pinhole `Camera` value object, the DJI presets, and the camera JSON file.

Split from `shared.geo` (which re-exports every name here) so the geometry module holds no file I/O.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ["CAMERA_PRESETS", "Camera"]

def _check_finite(name: str, value: float) -> None:
    if not isinstance(value, (int, float, np.floating, np.integer)) or isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")


def _check_range(name: str, value: float, lo: float, hi: float) -> None:
    _check_finite(name, value)
    if not lo <= value <= hi:
        raise ValueError(f"{name}={value!r} is outside the allowed range [{lo}, {hi}]")




# Published sensor and lens figures of DJI cameras. The 4K/UHD video modes of these cameras read
# the full sensor width (no crop), so fx = focal_mm / sensor_width_mm * image_width_px. These are
# nominal values: calibrate (cv2.calibrateCamera) for best accuracy.
CAMERA_PRESETS: dict[str, dict[str, float]] = {
    # Mavic 2 Pro, Hasselblad L1D-20c: 1" CMOS 13.2 x 8.8 mm, 10.26 mm (28 mm equivalent)
    "dji-mavic2-pro": {"sensor_width_mm": 13.2, "focal_mm": 10.26},
    # Phantom 4 Pro / V2: 1" CMOS 13.2 x 8.8 mm, 8.8 mm (24 mm equivalent)
    "dji-phantom4-pro": {"sensor_width_mm": 13.2, "focal_mm": 8.8},
    # Air 2S: 1" CMOS 13.2 x 8.8 mm, 8.38 mm (22 mm equivalent)
    "dji-air2s": {"sensor_width_mm": 13.2, "focal_mm": 8.38},
    # Mavic 3 (Hasselblad): 4/3 CMOS 17.3 x 13.0 mm, 12.29 mm (24 mm equivalent)
    "dji-mavic3": {"sensor_width_mm": 17.3, "focal_mm": 12.29},
    # Mavic Pro: 1/2.3" CMOS 6.17 x 4.55 mm, 4.73 mm (26 mm equivalent)
    "dji-mavic-pro": {"sensor_width_mm": 6.17, "focal_mm": 4.73},
    # Matrice 30 wide camera: 1/2" CMOS 6.4 x 4.8 mm, 4.5 mm (24 mm equivalent)
    "dji-m30-wide": {"sensor_width_mm": 6.4, "focal_mm": 4.5},
    # Mavic 3 Pro medium tele: 1/1.3" CMOS 9.6 x 7.2 mm, 18.7 mm (70 mm equivalent)
    "dji-mavic3pro-tele": {"sensor_width_mm": 9.6, "focal_mm": 18.7},
}


@dataclass(frozen=True, slots=True)
class Camera:
    """Pinhole camera intrinsics in pixels, with optional OpenCV distortion coefficients.

    dist: None or a tuple of 4, 5, 8, 12 or 14 OpenCV coefficients (k1, k2, p1, p2[, k3, ...]).
    preset: the CAMERA_PRESETS name the camera was made from (None for a camera file's measured intrinsics).
    A preset knows the lens and the sensor width, not a frame size, so `fitted_to` makes it at any frame size
    (any aspect ratio, no warning). Not compared: equal intrinsics are the same camera.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] | None = None
    preset: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"Camera.{name} must be a positive integer, got {value!r}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            _check_finite(f"Camera.{name}", value)
            if value <= 0:
                raise ValueError(f"Camera.{name} must be > 0 pixels, got {value!r}")
        _check_finite("Camera.cx", self.cx)
        _check_finite("Camera.cy", self.cy)
        if self.dist is not None:
            dist = tuple(float(d) for d in self.dist)
            if len(dist) not in (4, 5, 8, 12, 14):
                raise ValueError(f"Camera.dist must have 4, 5, 8, 12 or 14 coefficients, got {len(dist)}")
            if not all(math.isfinite(d) for d in dist):
                raise ValueError(f"Camera.dist must be finite, got {dist!r}")
            object.__setattr__(self, "dist", dist if any(d != 0.0 for d in dist) else None)

    @property
    def K(self) -> FloatArray:  # noqa: N802 - the standard name of the intrinsic matrix
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> FloatArray | None:
        """Distortion coefficients as a float64 array, or None."""
        return None if self.dist is None else np.asarray(self.dist, dtype=np.float64)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees (of the undistorted pinhole model)."""
        return math.degrees(2.0 * math.atan2(self.width / 2.0, self.fx))

    @classmethod
    def from_preset(cls, name: str, width: int = 3840, height: int = 2160) -> Camera:
        """A camera from a named preset (CAMERA_PRESETS) at the given image size.

        Square pixels, principal point at the image centre, no distortion.
        """
        try:
            preset = CAMERA_PRESETS[name]
        except KeyError:
            valid = ", ".join(sorted(CAMERA_PRESETS))
            raise ValueError(f"unknown camera preset {name!r}; valid presets: {valid}") from None
        f_px = preset["focal_mm"] / preset["sensor_width_mm"] * width
        return cls(width=width, height=height, fx=f_px, fy=f_px, cx=width / 2.0, cy=height / 2.0, preset=name)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """A camera from a mapping: {width, height, fx, fy, cx, cy[, dist]} or {preset[, width, height]}.

        `cx`/`cy` default to the image centre, `fy` to `fx`.
        """
        if not isinstance(d, dict):
            raise ValueError(f"camera must be a JSON object, got {type(d).__name__}")
        if "preset" in d:
            both = [k for k in ("fx", "fy", "cx", "cy", "dist", "distortion") if k in d]
            if both:  # which one was meant? the preset would win silently over measured intrinsics
                raise ValueError(f"camera gives both a preset ({d['preset']!r}) and intrinsics ({', '.join(both)}): "
                                 "keep one")
            return cls.from_preset(str(d["preset"]), _as_int("width", d.get("width", 3840)),
                                   _as_int("height", d.get("height", 2160)))
        missing = [k for k in ("width", "height", "fx") if k not in d]
        if missing:
            raise ValueError(f"camera is missing field(s) {', '.join(missing)}")
        dist = d.get("dist", d.get("distortion"))
        try:
            return cls(
                width=_as_int("width", d["width"]),
                height=_as_int("height", d["height"]),
                fx=float(d["fx"]),
                fy=float(d.get("fy", d["fx"])),
                cx=float(d.get("cx", d["width"] / 2.0)),
                cy=float(d.get("cy", d["height"] / 2.0)),
                dist=None if dist is None else tuple(float(x) for x in np.ravel(dist)),
            )
        except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: float() of a 400-digit integer
            raise ValueError(f"bad camera: {exc}") from None

    @classmethod
    def from_file(cls, path: str | Path) -> Camera:
        """Read a camera JSON file (see from_dict). Errors name the file."""
        path = Path(path)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ValueError(f"camera file {path} does not exist") from None
        except UnicodeDecodeError:
            raise ValueError(f"camera file {path} is not text (UTF-8 JSON): a binary file?") from None
        except OSError as exc:  # a folder, no permission
            raise ValueError(f"camera file {path} cannot be read: {exc.strerror or exc}") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"camera file {path} is not valid JSON: {exc}") from None
        try:
            return cls.from_dict(d)
        except ValueError as exc:
            raise ValueError(f"camera file {path}: {exc}") from None

    @classmethod
    def from_spec(cls, spec: str | Path, width: int = 3840, height: int = 2160) -> Camera:
        """A camera from a camera file's path or a preset's name (CAMERA_PRESETS, at width x height).

        A path that exists is read as a file; otherwise a preset name is looked up. ValueError naming
        both possibilities when it is neither.
        """
        path = Path(spec)
        if path.exists() or str(spec).endswith(".json"):
            return cls.from_file(path)
        if str(spec) in CAMERA_PRESETS:
            return cls.from_preset(str(spec), width, height)
        valid = ", ".join(sorted(CAMERA_PRESETS))
        raise ValueError(f"camera {spec}: no such file, and not a camera preset (presets: {valid})")

    def fitted_to(self, width: int, height: int, *, source: str = "the frames") -> Camera:
        """This camera for frames of width x height: itself, or scaled when only the resolution differs.

        Raises ValueError when the aspect ratio differs by more than 1 %: scaling would stretch the
        intrinsics, so the camera file does not belong to these frames (a different camera or a crop).
        A preset's camera (`preset` set) is made again at the frames' size, whatever their aspect ratio:
        the preset's video and photo modes read the whole sensor width.
        """
        if (width, height) == (self.width, self.height):
            return self
        if self.preset is not None:
            return Camera.from_preset(self.preset, width, height)
        ratio = (width / height) / (self.width / self.height)
        if abs(ratio - 1.0) > 0.01:
            raise ValueError(f"the camera is {self.width}x{self.height} but {source} are {width}x{height} (another "
                             "aspect ratio): give the camera file of the camera that recorded them")
        return self.scaled(width, height)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form read by from_dict."""
        d: dict[str, Any] = {
            "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
        }
        if self.dist is not None:
            d["dist"] = list(self.dist)
        return d

    def with_hfov(self, hfov_deg: float) -> Camera:
        """The same camera with its focal lengths scaled so that its horizontal field of view is `hfov_deg` (a zoom
        lens at another focal length): principal point, aspect of fx to fy and distortion kept. ValueError outside
        (0, 180) degrees."""
        hfov = float(hfov_deg)
        if not (math.isfinite(hfov) and 0.0 < hfov < 180.0):
            raise ValueError(f"a horizontal field of view must be within (0, 180) degrees, got {hfov_deg!r}")
        factor = (self.width / 2.0) / math.tan(math.radians(hfov) / 2.0) / self.fx
        return replace(self, fx=self.fx * factor, fy=self.fy * factor)

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera at another resolution (e.g. a downscaled video)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=self.cx * sx, cy=self.cy * sy)


def _as_int(name: str, value: Any) -> int:
    """A whole number written as an int, a whole float or text; ValueError naming `name` for anything else
    (null, a list, inf and NaN included: int(inf) is an OverflowError, int(None) a TypeError)."""
    try:
        number = float(value)
        whole = not isinstance(value, bool) and math.isfinite(number) and number == int(number)
    except (TypeError, ValueError, OverflowError):  # OverflowError: a JSON integer beyond float's range
        whole = False
    if not whole:
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(number)

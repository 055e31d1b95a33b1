"""Distance-size filter (paper section IV-A): drop boxes whose size is implausible for their range.

The fit is camera-independent: a box's metric diameter = pixel diagonal x slant range / focal
length, modelled per class as log-normal with mean and spread depending on the viewing depression.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.files import write_chunks_atomic

if TYPE_CHECKING:
    from shared.geo import Pose

log = logging.getLogger(__name__)

FORMAT = "uavmm-size-filter"
VERSION = 1
#: Depression-angle knots (degrees) of the fitted curves.
KNOTS_DEG = np.arange(0.0, 90.0 + 1e-9, 5.0)
#: Spread (std of log diameter) a fit writes at the knots outside the depressions it has evidence for: at k = 3 a
#: factor e^15 either way, so no box there is judged (a band held flat beyond its data removed 311 of 466 true boats
#: at 0-15 deg on the real dev file when fitted on its views above 40 deg).
UNMEASURED_STD_LOG = 5.0


@dataclass(frozen=True, slots=True)
class SizeBand:
    """One class's model: log metric diameter ~ N(mean(d), std(d)^2), d = depression in degrees.

    depression_deg, mean_log_m, std_log: (K,) knots, interpolated linearly and held at the ends.
    fitted_deg: (lo, hi) depressions the band was measured over (a fit's; None: all, as the priors); outside it the
    fit wrote UNMEASURED_STD_LOG, which passes every box, and `SizeFilter.z_class` gives NaN (no evidence to check).
    """

    depression_deg: tuple[float, ...]
    mean_log_m: tuple[float, ...]
    std_log: tuple[float, ...]
    samples: int = 0
    fitted_deg: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        k = len(self.depression_deg)
        if k == 0 or len(self.mean_log_m) != k or len(self.std_log) != k:
            raise ValueError("SizeBand needs equally long, non-empty depression/mean/std knots")
        if not all(math.isfinite(v) for v in (*self.depression_deg, *self.mean_log_m, *self.std_log)):
            raise ValueError("SizeBand knots must be finite")
        if any(s <= 0 for s in self.std_log):
            raise ValueError("SizeBand std_log must be > 0")
        if list(self.depression_deg) != sorted(self.depression_deg):
            raise ValueError("SizeBand depression_deg must be increasing")
        if self.fitted_deg is not None and not (len(self.fitted_deg) == 2 and all(
                math.isfinite(v) for v in self.fitted_deg) and self.fitted_deg[0] <= self.fitted_deg[1]):
            raise ValueError(f"SizeBand fitted_deg must be (lo, hi) with lo <= hi, got {self.fitted_deg!r}")

    def measured(self, depression_deg: ArrayLike) -> NDArray[np.bool_]:
        """(N,) bool: the depressions inside fitted_deg (all when the band has none)."""
        d = np.asarray(depression_deg, dtype=np.float64)
        if self.fitted_deg is None:
            return np.ones(d.shape, dtype=bool)
        return (d >= self.fitted_deg[0]) & (d <= self.fitted_deg[1])

    def mean_std(self, depression_deg: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        d = np.asarray(depression_deg, dtype=np.float64)
        return (np.interp(d, self.depression_deg, self.mean_log_m),
                np.interp(d, self.depression_deg, self.std_log))

    def bounds_m(self, depression_deg: ArrayLike, k: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Accepted metric diameter range (lo, hi) in metres at the given depressions."""
        mean, std = self.mean_std(depression_deg)
        return np.exp(mean - k * std), np.exp(mean + k * std)

    def sure_bounds(self, k: float, bins: int) -> NDArray[np.float64]:
        """Where the filter's decision is sure without interpolating at a box's own depression.

        For boxes whose depression's sine (height / slant range) lies in [i / bins, (i + 1) / bins), row i
        of the (bins, 4) float64 table holds, in squared metric diameters (m^2): below [i, 0] every box is
        rejected, from [i, 1] up to [i, 2] every one is accepted, above [i, 3] every one is rejected;
        elsewhere only the exact test (|log d - mean| <= k std at its depression) decides. The bounds are
        the extremes of mean +- k std over the bin's depressions (piecewise linear: at the bin's ends or a
        knot inside), widened by a relative margin of 1e-6, far beyond the rounding of the exact test
        (~1e-15) and of a float32 box diagonal (~6e-8), so a sure decision equals the exact one.
        """
        eps_deg = 1e-9  # the bin's depressions as any arcsin rounds them (~1e-14 deg) lie inside
        edges = np.degrees(np.arcsin(np.arange(bins + 1) / bins))
        lo_deg, hi_deg = edges[:-1] - eps_deg, edges[1:] + eps_deg
        mean, std = self.mean_std(np.stack([lo_deg, hi_deg]))
        low, high = mean - k * std, mean + k * std
        low_min, low_max, high_min, high_max = low.min(0), low.max(0), high.min(0), high.max(0)
        knot_mean, knot_std = self.mean_std(self.depression_deg)
        for d, knot_low, knot_high in zip(self.depression_deg, knot_mean - k * knot_std, knot_mean + k * knot_std,
                                          strict=True):
            inside = (lo_deg < d) & (d < hi_deg)
            np.minimum(low_min, knot_low, out=low_min, where=inside)
            np.maximum(low_max, knot_low, out=low_max, where=inside)
            np.minimum(high_min, knot_high, out=high_min, where=inside)
            np.maximum(high_max, knot_high, out=high_max, where=inside)
        margin = 1e-6
        with np.errstate(over="ignore"):
            return np.column_stack([np.exp(2 * low_min) * (1 - margin), np.exp(2 * low_max) * (1 + margin),
                                    np.exp(2 * high_min) * (1 - margin), np.exp(2 * high_max) * (1 + margin)])


def _upright_prior(width_m: float, depth_m: float, height_m: float, std_log: float) -> SizeBand:
    """Prior for a box-shaped object: its image extent seen at each depression."""
    d = np.radians(KNOTS_DEG)
    vertical = height_m * np.cos(d) + depth_m * np.sin(d)  # extent along the image's v axis
    diag = np.sqrt(width_m**2 + vertical**2)
    return SizeBand(tuple(KNOTS_DEG.tolist()), tuple(np.log(diag).tolist()), (std_log,) * len(KNOTS_DEG))


# Built-in priors for users with no fit: nominal object dimensions (metres) and a wide spread,
# because detectors' boxes are loose and telemetry errors scale the range. Classes of
# SeaDronesSee and of person datasets (POG, VisDrone "pedestrian"/"people").
#: Nominal width, depth, height (m) and spread (std of log diameter) of each built-in class.
NOMINAL_DIMENSIONS_M: dict[str, tuple[float, float, float, float]] = {
    "person": (0.5, 0.3, 1.7, 0.35),
    "pedestrian": (0.5, 0.3, 1.7, 0.35),
    "people": (0.5, 0.3, 1.7, 0.35),
    "swimmer": (0.5, 0.5, 0.3, 0.35),
    "buoy": (0.6, 0.6, 0.6, 0.4),
    "life_saving_appliances": (0.8, 0.8, 0.3, 0.45),
    "jetski": (1.2, 3.0, 1.0, 0.4),
    "boat": (2.5, 6.0, 1.5, 0.55),
    "car": (1.8, 4.5, 1.5, 0.4),
}
BUILTIN_PRIORS: dict[str, SizeBand] = {cls: _upright_prior(*dims) for cls, dims in NOMINAL_DIMENSIONS_M.items()}


@dataclass(frozen=True, slots=True)
class SizeFilter:
    """Per-class size bands; a box outside mean +- k * std (in log metric diameter) is dropped.

    Classes without a band pass unfiltered (logged once per class; `SizeFilterCheck.reports` names them in a run's
    summary).
    """

    bands: dict[str, SizeBand] = field(default_factory=dict)
    k: float = 3.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.k) and self.k > 0):
            raise ValueError(f"SizeFilter.k must be > 0, got {self.k!r}")

    @classmethod
    def builtin(cls, k: float = 3.0) -> SizeFilter:
        """The documented built-in priors (BUILTIN_PRIORS)."""
        return cls(dict(BUILTIN_PRIORS), k)

    def accept(
        self, cls_names: list[str] | NDArray, diag_px: ArrayLike, slant_range_m: ArrayLike,
        depression_deg: ArrayLike, focal_px: float,
    ) -> NDArray[np.bool_]:
        """Which boxes are plausible: (N,) bool.

        cls_names: (N,) class name per box; diag_px: (N,) box diagonal in pixels; slant_range_m and
        depression_deg: (N,) of the box's ground point (NaN = unknown: accepted, nothing to test);
        focal_px: the camera's focal length in pixels.
        """
        names = np.asarray(cls_names)
        diag = np.asarray(diag_px, dtype=np.float64)
        rng = np.asarray(slant_range_m, dtype=np.float64)
        dep = np.asarray(depression_deg, dtype=np.float64)
        ok = np.ones(diag.shape, dtype=bool)
        known = np.isfinite(rng) & np.isfinite(dep)
        for name in np.unique(names):
            sel = (names == name) & known
            if sel.any():
                ok[sel] = self.accept_class(str(name), diag[sel], rng[sel], dep[sel], focal_px)
        return ok

    def accept_class(self, name: str, diag_px: ArrayLike, slant_range_m: ArrayLike,
                     depression_deg: ArrayLike, focal_px: float) -> NDArray[np.bool_]:
        """accept() for boxes of one class: (N,) bool; NaN range or depression is accepted."""
        diag = np.asarray(diag_px, dtype=np.float64)
        band = self.bands.get(name)
        if band is None:
            _warn_unfiltered(name)
            return np.ones(diag.shape, dtype=bool)
        rng = np.asarray(slant_range_m, dtype=np.float64)
        dep = np.asarray(depression_deg, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_size = np.log(diag * rng / focal_px)
        mean, std = band.mean_std(dep)
        inside = np.abs(log_size - mean) <= self.k * std
        return inside | ~(np.isfinite(rng) & np.isfinite(dep))

    def z_class(self, name: str, diag_px: ArrayLike, slant_range_m: ArrayLike, depression_deg: ArrayLike,
                focal_px: float) -> NDArray[np.float64]:
        """Where boxes of one class lie in its band: (log size - mean) / std at their depression, (N,) float64
        (|z| <= k is accepted); NaN for boxes without range or depression, and outside the depressions the band
        was fitted over (SizeBand.fitted_deg). ValueError for a class without a band."""
        band = self.bands.get(name)
        if band is None:
            raise ValueError(f"size filter has no band for class {name!r}")
        diag = np.asarray(diag_px, dtype=np.float64)
        rng = np.asarray(slant_range_m, dtype=np.float64)
        dep = np.asarray(depression_deg, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_size = np.log(diag * rng / focal_px)
        mean, std = band.mean_std(dep)
        return np.where(band.measured(dep), (log_size - mean) / std, np.nan)

    # ---------------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT, "version": VERSION, "k": self.k,
            "classes": {
                name: {"depression_deg": list(b.depression_deg), "mean_log_m": list(b.mean_log_m),
                       "std_log": list(b.std_log), "samples": b.samples,
                       **({} if b.fitted_deg is None else {"fitted_deg": list(b.fitted_deg)})}
                for name, b in self.bands.items()
            },
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "<size filter>") -> SizeFilter:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"{source}: not a size-filter file (expected format {FORMAT!r})")
        if d.get("version") != VERSION:
            raise ValueError(f"{source}: unsupported size-filter version {d.get('version')!r} (this is {VERSION})")
        try:
            bands = {
                str(name): SizeBand(tuple(map(float, b["depression_deg"])), tuple(map(float, b["mean_log_m"])),
                                    tuple(map(float, b["std_log"])), int(b.get("samples", 0)),
                                    _span(b.get("fitted_deg")))
                for name, b in d["classes"].items()
            }
            return cls(bands, float(d.get("k", 3.0)))
        except (KeyError, TypeError, AttributeError, ValueError, OverflowError) as exc:  # int(inf): OverflowError
            raise ValueError(f"{source}: malformed size-filter file: {exc!r}") from None

    def save(self, path: str | Path, *, evidence: dict[str, Any] | None = None) -> None:
        """Write the filter as JSON, whole or not at all (`shared.files.write_atomic`: a failed write leaves the
        file that was there); evidence: what it was fitted from, stored beside the bands (read by no one)."""
        doc = self.to_dict() if evidence is None else {**self.to_dict(), "evidence": evidence}
        write_chunks_atomic(Path(path), [json.dumps(doc, indent=1)])

    @classmethod
    def load(cls, path: str | Path) -> SizeFilter:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise ValueError(f"size-filter file {path} does not exist") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"size-filter file {path} is not JSON: {exc}") from None
        return cls.from_dict(d, source=str(path))


def _span(value: Any) -> tuple[float, float] | None:
    """A file's fitted_deg: None, or two numbers (ValueError otherwise, named by `from_dict`)."""
    if value is None:
        return None
    if not (isinstance(value, (list, tuple)) and len(value) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise ValueError(f"fitted_deg must be [lo, hi] in degrees, got {value!r}")
    return float(value[0]), float(value[1])


_warned: set[str] = set()


def _warn_unfiltered(name: str) -> None:
    if name not in _warned:
        _warned.add(name)
        log.warning("size filter: no band for class %r; its boxes pass unfiltered", name)


def fit_band(depression_deg: ArrayLike, log_size_m: ArrayLike, *, min_samples: int = 20,
             min_std: float = 0.08) -> SizeBand:
    """Fit one class's band from samples: robust mean and spread per depression knot.

    Each knot takes the samples within +-7.5 degrees (Gaussian weights, sigma 5 degrees) and their
    weighted median and 1.4826 * weighted MAD. Knots with fewer than min_samples effective samples
    borrow the nearest fitted knot (spread x 1.5) between fitted ones and one knot beyond them (within
    the knots' own reach); further out there is no evidence: UNMEASURED_STD_LOG (no box judged), and
    fitted_deg spans the knots with a band. A non-parametric heteroscedastic regression: like the
    paper's Gaussian process it gives mean and spread as smooth functions of the geometry, with no
    assumption about their shape. min_std floors the spread (telemetry noise alone gives ~0.05). The
    spread is the boxes', whatever objects they show: `fit_class` checks it on objects left out.
    """
    dep = np.asarray(depression_deg, dtype=np.float64)
    y = np.asarray(log_size_m, dtype=np.float64)
    good = np.isfinite(dep) & np.isfinite(y)
    dep, y = dep[good], y[good]
    if len(y) < min_samples:
        raise ValueError(f"size filter fit needs at least {min_samples} samples, got {len(y)}")
    means = np.full(len(KNOTS_DEG), np.nan)
    stds = np.full(len(KNOTS_DEG), np.nan)
    for i, knot in enumerate(KNOTS_DEG):
        w = np.exp(-0.5 * ((dep - knot) / 5.0) ** 2)
        w[np.abs(dep - knot) > 7.5] = 0.0
        if w.sum() < min_samples * 0.5:  # effective count
            continue
        med = _weighted_quantile(y, w, 0.5)
        mad = _weighted_quantile(np.abs(y - med), w, 0.5)
        means[i], stds[i] = med, max(1.4826 * mad, min_std)
    fitted = np.flatnonzero(np.isfinite(means))
    if len(fitted) == 0:
        raise ValueError("size filter fit: no depression range has enough samples")
    # one knot beyond the first and last fitted ones is within the knots' own reach (+-7.5 deg): held there
    first, last = max(int(fitted[0]) - 1, 0), min(int(fitted[-1]) + 1, len(KNOTS_DEG) - 1)
    for gap in np.flatnonzero(~np.isfinite(means)):
        j = fitted[np.argmin(np.abs(fitted - gap))]
        inside = first <= gap <= last
        means[gap], stds[gap] = means[j], stds[j] * 1.5 if inside else UNMEASURED_STD_LOG  # less sure / no evidence
    return SizeBand(tuple(KNOTS_DEG.tolist()), tuple(means.tolist()), tuple(stds.tolist()), int(len(y)),
                    (float(KNOTS_DEG[first]), float(KNOTS_DEG[last])))


#: A class's fit needs the boxes of at least this many objects (tracks; videos where the file has no track ids, or
#: parts of a single video that shows several at once: agent.size_filter_fit._time_parts):
#: the boxes of one say nothing of how the class's objects differ.
MIN_UNITS = 2
#: Objects (or videos) are dealt round-robin into at most this many parts; each part is checked against a band
#: fitted on the others.
HELD_OUT_FOLDS = 5
#: Share of the true boxes the band (at k) must hold: the boxes it was fitted on, and each object's boxes when that
#: object was left out of the fit. Its spread is widened until it does.
INSIDE_SHARE = 0.995


def fit_class(depression_deg: ArrayLike, log_size_m: ArrayLike, unit_ids: ArrayLike, *, k: float = 3.0,
              min_samples: int = 20, min_units: int = MIN_UNITS, min_std: float = 0.08,
              ) -> tuple[SizeBand | None, dict[str, Any]]:
    """Fit one class's band (`fit_band`) and check it on its own evidence: (band, or None where the evidence
    cannot make one, and what was found).

    depression_deg, log_size_m: (N,) per true box; unit_ids: (N,) which object (or video) each shows. Stands
    down (None) with fewer than min_samples boxes or min_units objects. Otherwise the objects are left out a part at
    a time (HELD_OUT_FOLDS) and their boxes placed in the band fitted on the others (z, where that band has
    evidence); the band's spread is multiplied by max(1, q / k), q the INSIDE_SHARE quantile of |z| over those and
    over the boxes in the band fitted on all, so it holds the sizes the class's objects showed. On the real dev file
    (8 videos, no track ids) the boxes' own spread, fitted on seven videos, refused 6.8 % of the eighth's true boats,
    9.7 % of its buoys and 58 % of its jetskis (and 24 of the 762 boats it was fitted on); checked, 0.4 %, 0 % and
    34 % (3 of 762). The evidence: samples, units, fitted_deg, held_out_boxes, held_out_outside (the share of those
    beyond k before the widening), spread_scale; why, when not fitted.
    """
    if not (math.isfinite(k) and k > 0):
        raise ValueError(f"size filter fit: k must be > 0, got {k!r}")
    dep = np.asarray(depression_deg, dtype=np.float64)
    y = np.asarray(log_size_m, dtype=np.float64)
    units = np.asarray(unit_ids)
    good = np.isfinite(dep) & np.isfinite(y)
    dep, y, units = dep[good], y[good], units[good]
    names, unit_of = np.unique(units, return_inverse=True)
    evidence: dict[str, Any] = {"samples": int(len(y)), "units": int(len(names))}
    if len(y) < min_samples:
        return None, {**evidence, "why": f"{len(y)} boxes, {min_samples} needed"}
    if len(names) < min_units:
        return None, {**evidence, "why": f"the boxes of {len(names)} object(s), {min_units} needed (track ids; "
                                         f"without them videos, or parts of one video showing several at once): "
                                         f"how the class's objects differ in size is not measured"}
    try:
        band = fit_band(dep, y, min_samples=min_samples, min_std=min_std)
    except ValueError as exc:
        return None, {**evidence, "why": str(exc)}
    held: list[NDArray[np.float64]] = []
    folds = min(HELD_OUT_FOLDS, len(names))
    for f in range(folds):
        out = unit_of % folds == f
        try:
            rest = fit_band(dep[~out], y[~out], min_samples=min_samples, min_std=min_std)
        except ValueError:  # the others alone are too few
            continue
        measured = out & rest.measured(dep)
        mean, std = rest.mean_std(dep[measured])
        held.append(np.abs(y[measured] - mean) / std)
    z_held = np.concatenate(held) if held else np.zeros(0)
    if not len(z_held):
        return None, {**evidence, "why": "no object could be left out and checked: the others alone fit no band"}
    mean, std = band.mean_std(dep)
    z_own = (np.abs(y - mean) / std)[band.measured(dep)]
    scale = max(1.0, float(np.quantile(np.concatenate([z_held, z_own]), INSIDE_SHARE)) / k)
    if scale > 1.0:
        band = dataclasses.replace(band, std_log=tuple(sd * scale if sd < UNMEASURED_STD_LOG else sd
                                                       for sd in band.std_log))
    assert band.fitted_deg is not None
    return band, {**evidence, "fitted_deg": list(band.fitted_deg), "held_out_boxes": int(len(z_held)),
                  "held_out_outside": round(float(np.mean(z_held > k)), 4), "spread_scale": round(scale, 3)}


def _weighted_quantile(values: NDArray, weights: NDArray, q: float) -> float:
    order = np.argsort(values)
    v, w = values[order], weights[order]
    cw = np.cumsum(w)
    return float(np.interp(q * cw[-1], cw, v))


def slant_and_depression(east_m: NDArray, north_m: NDArray, up_m: NDArray | None,
                         pose: Pose) -> tuple[NDArray, NDArray]:
    """Camera-to-ground-point distance (m) and depression below the horizontal (deg) of ground points in the
    pose's local frame (up_m None: on the flat ground, up = 0)."""
    if up_m is None:
        slant = np.sqrt(east_m**2 + north_m**2 + pose.height_m**2)
        return slant, np.degrees(np.arcsin(pose.height_m / slant))
    drop = pose.height_m - up_m
    slant = np.sqrt(east_m**2 + north_m**2 + drop**2)
    return slant, np.degrees(np.arcsin(drop / slant))

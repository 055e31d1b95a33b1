"""How rough and murky the rendered sea is: knobs a scenario sets to make its frames harder than `sea`'s.

`SeaState()` (all factors 1, no extra wash) is the calm sea the `sea` scenario has always rendered; the renderer
applies a sea state only when it differs from that, so calm renders are pixel-identical to those before this
module existed. A scenario carries its sea state (`sim.scenarios.Scenario.sea_state`), the dataset writer puts
it into truth.json (only when not calm) and the renderer reads it from there, so `uavmm render DIR` and
`uavmm sim SCENARIO --render` draw the same pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any


@dataclass(frozen=True, slots=True)
class SeaState:
    """Multipliers and offsets on the calm sea's appearance.

    Attributes
    ----------
    whitecap_rate : float
        Factor on the breaking whitecaps' rate (`sea_motion.WHITECAPS`, ~0.2 % of the sea white at a time:
        ~6 m/s wind). Whitecap coverage grows with wind speed ~U^3.4 (Monahan & O'Muircheartaigh 1980):
        x5 is ~1 % (~10 m/s, Beaufort 5).
    sparkle_rate : float
        Factor on the glint sparkles' rate inside the glint patch (a rougher sea has more facets).
    glint_gain : float
        Factor on the sun glint's peak strength (0..255 per unit glint potential, calm 230).
    visibility_scale : float
        Factor on the world's meteorological visibility (calm: 4-15 km); sea haze lowers contrast with range.
    swimmer_wash : float
        Extra share (0..1) by which the swimmers' head and shoulder colours are pulled towards the water's
        (spray, a film of water, more of the body under the surface), on top of their own 30-75 %.
    foam_rate : float
        Patches of residual foam per m^2 per s (`sea_motion.FOAM`: what a broken crest leaves behind, 0.15-0.45 m,
        living 1.5-4 s); 0 = none (the calm sea has none).
    blur_mrad : float
        Gaussian blur of the whole frame, sigma in milliradians of view (lens softness, atmospheric shimmer over
        warm water, video compression); sigma in pixels = blur_mrad / 1000 x fx. 0 = sharp.
    """

    whitecap_rate: float = 1.0
    sparkle_rate: float = 1.0
    glint_gain: float = 1.0
    visibility_scale: float = 1.0
    swimmer_wash: float = 0.0
    foam_rate: float = 0.0
    blur_mrad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("whitecap_rate", "sparkle_rate", "glint_gain", "visibility_scale", "foam_rate", "blur_mrad"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SeaState.{name}={v!r} must be a finite number >= 0")
        if self.visibility_scale <= 0:
            raise ValueError(f"SeaState.visibility_scale={self.visibility_scale!r} must be > 0")
        if not (isinstance(self.swimmer_wash, (int, float)) and 0.0 <= self.swimmer_wash <= 1.0):
            raise ValueError(f"SeaState.swimmer_wash={self.swimmer_wash!r} must be in 0..1")

    @property
    def calm(self) -> bool:
        """True for the `sea` scenario's sea (every knob at its neutral value)."""
        return self == CALM

    def to_dict(self) -> dict[str, float]:
        """The knobs as a JSON-ready dict."""
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> SeaState:
        """Inverse of `to_dict`; None or {} gives the calm sea; unknown keys raise ValueError naming them."""
        if not d:
            return CALM
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown sea state field(s) {unknown}; valid: {sorted(known)}")
        return cls(**{k: float(v) for k, v in d.items()})


#: The calm sea of the `sea` scenario.
CALM = SeaState()

"""Heatmap methods by name (STYLE: plug-ins looked up in a registry): `make_method("median")`.

Kept apart from the methods so that the learned method (`agent.anomaly.autoencoder`, which builds on the
helpers in `agent.anomaly.methods`) and the classic ones are registered in one place without importing
each other.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from agent.anomaly.autoencoder import OnnxAutoencoder
from agent.anomaly.methods import AnomalyMethod, FilterResidual, FrameDifference, Mog2


def _autoencoder(**kwargs: Any) -> AnomalyMethod:
    return OnnxAutoencoder(**kwargs)


#: Heatmap methods by name (STYLE: plug-ins looked up by name). Each factory takes keyword options.
ANOMALY_METHODS: dict[str, Callable[..., AnomalyMethod]] = {
    "autoencoder": _autoencoder,
    "diff": FrameDifference,
    "mean": lambda **kw: FilterResidual("mean", **kw),
    "median": lambda **kw: FilterResidual("median", **kw),
    "mog2": Mog2,
}
#: The method `uavmm anomaly` and the agent use when none is named.
DEFAULT_METHOD = "autoencoder"


def make_method(name: str, **options: Any) -> AnomalyMethod:
    """A heatmap method by name with keyword options; ValueError listing the valid names for an unknown one."""
    factory = ANOMALY_METHODS.get(name)
    if factory is None:
        raise ValueError(f"unknown anomaly method {name!r}; valid: {', '.join(sorted(ANOMALY_METHODS))}")
    return factory(**options)



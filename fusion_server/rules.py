"""Fusion rules: how the tiles of the UAVs covering a cell combine into the joint value (DESIGN.md 4).

A rule maps a (k, n, n) uint8 stack (value = byte / 255, one layer per covering UAV, k >= 1) to one
(n, n) uint8 tile. ``mean`` is the paper's rule and the default; ``max`` and ``noisy-or`` are options.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["FUSION_RULES", "FusionRule", "get_fusion_rule"]

FusionRule = Callable[[NDArray[np.uint8]], NDArray[np.uint8]]


def fuse_mean(stack: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Per-cell mean over the covering UAVs, rounded half up to the nearest byte."""
    k = stack.shape[0]
    total = stack.sum(axis=0, dtype=np.uint32)
    return ((total * 2 + k) // (2 * k)).astype(np.uint8)


def fuse_max(stack: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Per-cell maximum over the covering UAVs."""
    return stack.max(axis=0)


def fuse_noisy_or(stack: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Per-cell ``1 - prod(1 - v)``: independent evidence accumulates (never below the max)."""
    miss = np.prod(1.0 - stack.astype(np.float32) / np.float32(255.0), axis=0)
    return np.clip(np.rint((1.0 - miss) * np.float32(255.0)), 0, 255).astype(np.uint8)


FUSION_RULES: dict[str, FusionRule] = {"mean": fuse_mean, "max": fuse_max, "noisy-or": fuse_noisy_or}


def get_fusion_rule(name: str) -> FusionRule:
    """The fusion rule registered under ``name``; ValueError listing the valid names otherwise."""
    try:
        return FUSION_RULES[name]
    except KeyError:
        raise ValueError(f"unknown fusion rule {name!r}; valid: {', '.join(FUSION_RULES)}") from None

"""Fusion rules: how the tiles of the UAVs covering a cell combine into the joint value (DESIGN.md 4).

A rule maps a (k, n, n) uint8 stack (value = byte / 255, one layer per UAV covering the tile, k >= 1)
and an optional (k, n, n) bool ``covered`` mask (which UAV covers which cell: its recent camera
footprints, see :mod:`fusion_server.joint_map`) to one (n, n) uint8 tile. Per cell only the layers
that cover it count; a cell no layer covers falls back to all k layers (the tile-level rule), so
``covered=None`` is the plain per-tile rule. ``mean`` is the paper's rule and the default; ``max``
and ``noisy-or`` are options.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["FUSION_RULES", "FusionRule", "get_fusion_rule"]

FusionRule = Callable[..., NDArray[np.uint8]]
"""``rule(stack, covered=None) -> (n, n) uint8``."""


def _effective_mask(stack: NDArray[np.uint8], covered: NDArray[np.bool_] | None) -> NDArray[np.bool_] | None:
    """The (k, n, n) mask of layers that count per cell (None: all), after the no-coverage fallback."""
    if covered is None:
        return None
    covered = np.asarray(covered, dtype=bool)
    if covered.shape != stack.shape:
        raise ValueError(f"covered mask {covered.shape} does not match the stack {stack.shape}")
    if covered.all():
        return None
    # a cell nobody's footprint holds keeps the tile-level rule over every layer
    return covered | ~covered.any(axis=0, keepdims=True)


def fuse_mean(stack: NDArray[np.uint8], covered: NDArray[np.bool_] | None = None) -> NDArray[np.uint8]:
    """Per-cell mean over the covering UAVs, rounded half up to the nearest byte."""
    mask = _effective_mask(stack, covered)
    if mask is None:
        k = stack.shape[0]
        total = stack.sum(axis=0, dtype=np.uint32)
        return ((total * 2 + k) // (2 * k)).astype(np.uint8)
    count = mask.sum(axis=0, dtype=np.uint32)
    total = np.where(mask, stack, 0).sum(axis=0, dtype=np.uint32)
    return ((total * 2 + count) // (2 * count)).astype(np.uint8)


def fuse_max(stack: NDArray[np.uint8], covered: NDArray[np.bool_] | None = None) -> NDArray[np.uint8]:
    """Per-cell maximum over the covering UAVs."""
    mask = _effective_mask(stack, covered)
    return stack.max(axis=0) if mask is None else np.where(mask, stack, 0).max(axis=0).astype(np.uint8)


def fuse_noisy_or(stack: NDArray[np.uint8], covered: NDArray[np.bool_] | None = None) -> NDArray[np.uint8]:
    """Per-cell ``1 - prod(1 - v)``: independent evidence accumulates (never below the max)."""
    mask = _effective_mask(stack, covered)
    values = stack if mask is None else np.where(mask, stack, 0)
    miss = np.prod(1.0 - values.astype(np.float32) / np.float32(255.0), axis=0)
    return np.clip(np.rint((1.0 - miss) * np.float32(255.0)), 0, 255).astype(np.uint8)


FUSION_RULES: dict[str, FusionRule] = {"mean": fuse_mean, "max": fuse_max, "noisy-or": fuse_noisy_or}


def get_fusion_rule(name: str) -> FusionRule:
    """The fusion rule registered under ``name``; ValueError listing the valid names otherwise."""
    try:
        return FUSION_RULES[name]
    except KeyError:
        raise ValueError(f"unknown fusion rule {name!r}; valid: {', '.join(FUSION_RULES)}") from None

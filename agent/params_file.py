"""The parameters file `uavmm tune` writes and `boost`/`track`/`agent` read (PARAMS.json).

A JSON object ``{"format": "uavmm-params", "version": 1, "pipeline": {...}, "size_filter": {...} | null,
"tuned_on": {...}}``: ``pipeline`` is what a plain pipeline config file holds (flat or with a
``memory`` object, see `agent.boost.config_from_dict`), ``size_filter`` a fitted size filter (the
`uavmm fit-size-filter` format) or null for the built-in priors, ``tuned_on`` where the values come from
(read by people, ignored here). A plain pipeline config file is read as before.
"""

from __future__ import annotations

from typing import Any

from agent.size_filter import SizeFilter

__all__ = ["PARAMS_FORMAT", "PARAMS_VERSION", "is_params", "make_params", "split_params"]

PARAMS_FORMAT = "uavmm-params"
PARAMS_VERSION = 1


def is_params(data: object) -> bool:
    """Whether ``data`` (a parsed JSON value) is a parameters file rather than a plain pipeline config."""
    return isinstance(data, dict) and data.get("format") == PARAMS_FORMAT


def make_params(pipeline: dict[str, Any], size_filter: SizeFilter | None, tuned_on: dict[str, Any]) -> dict[str, Any]:
    """The JSON object of a parameters file."""
    return {"format": PARAMS_FORMAT, "version": PARAMS_VERSION, "pipeline": pipeline,
            "size_filter": None if size_filter is None else size_filter.to_dict(), "tuned_on": tuned_on}


def split_params(data: dict[str, Any], source: str) -> tuple[dict[str, Any], SizeFilter | None]:
    """(pipeline settings, fitted size filter or None) of a parameters file; ValueError naming source."""
    if data.get("version") != PARAMS_VERSION:
        raise ValueError(f"{source}: unsupported {PARAMS_FORMAT} version {data.get('version')!r} "
                         f"(this uavmm reads {PARAMS_VERSION})")
    unknown = sorted(set(data) - {"format", "version", "pipeline", "size_filter", "tuned_on"})
    if unknown:
        raise ValueError(f"{source}: unknown keys {unknown} in a {PARAMS_FORMAT} file")
    pipeline = data.get("pipeline", {})
    if not isinstance(pipeline, dict):
        raise ValueError(f"{source}: 'pipeline' must be an object, got {type(pipeline).__name__}")
    raw_filter = data.get("size_filter")
    size_filter = None if raw_filter is None else SizeFilter.from_dict(raw_filter, source=f"{source} size_filter")
    return pipeline, size_filter

"""Comma-separated command-line values (`--seeds 0,1,2`, `--domains tune,grass-jumps`)."""

from __future__ import annotations

__all__ = ["csv_list"]


def csv_list(text: str, kind: type, flag: str) -> list:
    """The non-empty items of `text` converted by `kind`; ValueError naming `flag` for an item `kind` refuses or
    an empty list."""
    try:
        values = [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{flag}: expected a comma-separated list of {kind.__name__}, got {text!r}") from None
    if not values:
        raise ValueError(f"{flag}: empty list")
    return values

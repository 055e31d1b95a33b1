"""JSON files as users have them: parsed whole (`read_json`), or a long top-level list entry by entry
(`iter_json_list`: an hour's pre-NMS candidates is a list of millions of small objects, ~660 bytes each as Python
dicts, where the arrays made of them keep ~40).
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["NotAJsonList", "iter_json_list", "read_json"]

_CHUNK_CHARS = 1 << 20


class NotAJsonList(ValueError):
    """The file's JSON value is valid but not a list; ``kind`` is its type's name."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind
_WHITESPACE = " \t\n\r"


def read_json(path: str | Path, what: str) -> Any:
    """Parse a JSON file; errors name the file and what it was meant to be."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            return json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{what} file {path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} file {path} is not valid JSON: {exc}") from None


def iter_json_list(path: str | Path, what: str, *, chunk_chars: int = _CHUNK_CHARS) -> Iterator[Any]:
    """The entries of a file holding one JSON list, decoded one at a time from chunks of the file.

    Errors as `read_json` (the file missing, not valid JSON: the message of parsing it whole, which names the
    place); a file whose value is not a list gives NotAJsonList (a ValueError) naming the file. Only the current
    chunk and entry are held in memory.
    """
    path = Path(path)
    decoder = json.JSONDecoder()
    try:
        raw = path.open("rb")
    except FileNotFoundError:
        raise ValueError(f"{what} file {path} does not exist") from None
    # the encoding json.load finds (UTF-8 with or without a BOM, UTF-16 / 32 as Windows tools write them)
    encoding = json.detect_encoding(raw.peek(4)[:4])
    with io.TextIOWrapper(raw, encoding=encoding, errors="surrogatepass") as f:
        buf, pos, eof = "", 0, False

        def more(at_least: int = 0) -> bool:
            """Read on (at least `at_least` characters: an entry that keeps failing to decode reads geometrically
            more, so a broken or huge one costs the file's length once, not once per chunk)."""
            nonlocal buf, pos, eof
            if eof:
                return False
            chunk = f.read(max(chunk_chars, at_least))
            if not chunk:
                eof = True
                return False
            buf, pos = buf[pos:] + chunk, 0
            return True

        def skip_space() -> str:
            """The next character that is not whitespace ('' at the end of the file)."""
            nonlocal pos
            while True:
                while pos < len(buf) and buf[pos] in _WHITESPACE:
                    pos += 1
                if pos < len(buf) or not more():
                    return buf[pos] if pos < len(buf) else ""

        try:
            if skip_space() != "[":
                _not_a_list(path, what)
            pos += 1
            first = True
            while True:
                c = skip_space()
                if c == "]":
                    pos += 1
                    if skip_space():
                        raise json.JSONDecodeError("Extra data", buf, pos)
                    return
                if not first:
                    if c != ",":
                        raise json.JSONDecodeError("Expecting ',' delimiter", buf, pos)
                    pos += 1
                    skip_space()
                first = False
                if buf[pos:pos + 1] not in ("{", "[", '"'):  # a number or a word: its end is the next , or ]
                    while buf.find(",", pos) < 0 and buf.find("]", pos) < 0 and more():
                        pass
                while True:
                    try:
                        entry, end = decoder.raw_decode(buf, pos)
                    except json.JSONDecodeError:
                        if more(len(buf) - pos):
                            continue  # the entry runs past what was read
                        raise
                    break
                pos = end
                yield entry
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            read_json(path, what)  # the whole file's message, which names the place
            raise ValueError(f"{what} file {path} is not valid JSON: {exc}") from None  # (parsed whole it was)


def _not_a_list(path: Path, what: str) -> None:
    """Raise the error for a file whose JSON value is not a list (or is not JSON)."""
    value = read_json(path, what)
    raise NotAJsonList(f"{what} file {path}: expected a JSON list, got {type(value).__name__}", type(value).__name__)

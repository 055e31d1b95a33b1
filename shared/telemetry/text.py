"""Reading telemetry files as text (UTF-8 with or without BOM, else Latin-1) and the number token they share."""

from __future__ import annotations

import logging
import re
from pathlib import Path

logger = logging.getLogger(__name__)

NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
NUM_RE = re.compile(NUM)


def read_text(path: str | Path) -> str:
    """A telemetry file's text: UTF-8 (BOM dropped), UTF-16 with a BOM (files re-saved by subtitle editors),
    else Latin-1 (which never fails, so a binary file reaches the parser and is refused there by content)."""
    data = Path(path).read_bytes()
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError:
            logger.debug("%s starts with a UTF-16 BOM but does not decode as UTF-16", path)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        logger.debug("%s is not UTF-8; reading it as Latin-1", path)
        return data.decode("latin-1")

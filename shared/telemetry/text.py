"""Reading telemetry files as text (UTF-8 with or without BOM, else Latin-1) and the number token they share."""

from __future__ import annotations

import logging
import re
from pathlib import Path

logger = logging.getLogger(__name__)

NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
NUM_RE = re.compile(NUM)


def read_text(path: str | Path) -> str:
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        logger.debug("%s is not UTF-8; reading it as Latin-1", path)
        return data.decode("latin-1")

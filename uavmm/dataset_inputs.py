"""The image files a dataset run reads, as inputs of the CLI's output check (`uavmm.cli.require_outputs_apart`).

`uavmm track` and `uavmm anomaly --frames` read the images an images.json names: an output must not be one of them.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

__all__ = ["DatasetImages"]


class DatasetImages:
    """The image files an images.json names, as (flag, path) inputs of `require_outputs_apart`: each ``file_name``,
    absolute or relative to ``image_dir`` (default: the folder of images.json), as `agent.dataset.image_file` finds
    them. images.json is read when first iterated, once; one that cannot be read gives none (the command says why).
    """

    def __init__(self, flag: str, images_json: Path | str, image_dir: Path | str | None = None) -> None:
        self.flag = flag
        self.images_json = Path(images_json)
        self.image_dir = self.images_json.parent if image_dir is None else Path(image_dir)
        self._files: list[tuple[str, Path | str | None]] | None = None

    def __iter__(self) -> Iterator[tuple[str, Path | str | None]]:
        if self._files is None:
            try:
                with open(self.images_json, "rb") as handle:
                    images = json.load(handle).get("images")
            except (OSError, ValueError, AttributeError):
                images = None
            names = [im.get("file_name") for im in images if isinstance(im, dict)] if isinstance(images, list) else []
            self._files = [(self.flag, self.image_dir / name) for name in names if isinstance(name, str) and name]
        return iter(self._files)

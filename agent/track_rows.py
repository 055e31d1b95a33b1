"""The rows `uavmm agent --tracks-out` writes at the end of a run, held as columns while it runs.

A row is one track reported in one frame. Held as `TrackOutput` objects they cost ~540-665 B each: an agent tracking
ten objects at 30 fps grew ~580 MB an hour, `uavmm detect` on a video with ~20 people ~840 MB an hour. Here they are
104 B each, in fixed-size column chunks, and the outputs are written from them piece by piece: the GeoJSON
(`agent.tracking_io.geojson_tracks`'s layout), the MOT rows (`mot_lines`') and the objects (`uavmm detect`'s), byte for
byte.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from agent.tracking import TrackOutput
from shared.files import collection_chunks, write_chunks_atomic  # re-exported: agent.offline.outputs uses them

log = logging.getLogger("agent.node")  # its messages, under the agent's name

__all__ = ["ROW_DTYPE", "FirstPass", "TrackRowLog", "collection_chunks", "write_chunks_atomic"]

ROW_DTYPE = np.dtype([("frame", "<i8"), ("t", "<f8"), ("id", "<i8"), ("cls", "<i8"), ("lat", "<f8"),
                      ("lon", "<f8"), ("score", "<f8"), ("ve", "<f8"), ("vn", "<f8"), ("x1", "<f8"), ("y1", "<f8"),
                      ("x2", "<f8"), ("y2", "<f8")])

_LINES_AT_ONCE = 65_536


class TrackRowLog:
    """Append-only rows (frame index, time, track); ``write_geojson`` at the end. Not thread-safe (the agent's loop)."""

    def __init__(self, chunk_rows: int = 8192) -> None:
        self._chunk_rows = int(chunk_rows)
        self._full: list[np.ndarray] = []
        self._open = np.empty(self._chunk_rows, ROW_DTYPE)
        self._n_open = 0

    def __len__(self) -> int:
        return len(self._full) * self._chunk_rows + self._n_open

    @property
    def nbytes(self) -> int:
        """Bytes the rows' chunks hold."""
        return (len(self._full) + 1) * self._chunk_rows * ROW_DTYPE.itemsize

    def extend(self, frame_index: int, t: float, tracks: Iterable[TrackOutput]) -> None:
        """Add one frame's tracks."""
        for tr in tracks:
            if self._n_open == self._chunk_rows:
                self._full.append(self._open)
                self._open = np.empty(self._chunk_rows, ROW_DTYPE)
                self._n_open = 0
            self._open[self._n_open] = (frame_index, t, tr.id, tr.cls, tr.lat, tr.lon, tr.score, tr.vel_en[0],
                                        tr.vel_en[1], *tr.box_xyxy)
            self._n_open += 1

    def rows(self) -> np.ndarray:
        """Every row, in the order added (a copy)."""
        return np.concatenate([*self._full, self._open[: self._n_open]])

    def track_ids(self) -> int:
        """Distinct track ids."""
        return len(np.unique(self.rows()["id"]))

    def mot_lines(self) -> Iterator[str]:
        """`agent.tracking_io.mot_lines` of the rows (frame = frame index + 1), sorted by frame and id."""
        rows = self.rows()
        order = np.lexsort((rows["id"], rows["frame"]))
        for a in range(0, len(order), _LINES_AT_ONCE):  # as Python numbers a slice at a time, not every row at once
            part = rows[order[a:a + _LINES_AT_ONCE]]
            for frame, tid, x1, y1, x2, y2, score in zip(*(part[k].tolist() for k in (
                    "frame", "id", "x1", "y1", "x2", "y2", "score")), strict=True):
                yield f"{frame + 1},{tid},{x1:.2f},{y1:.2f},{x2 - x1:.2f},{y2 - y1:.2f},{score:.5f},-1,-1,-1"

    def by_track(self) -> Iterator[np.ndarray]:
        """The rows with a finite position, one array per track id (ascending), in the order added."""
        rows = self.rows()
        rows = rows[np.isfinite(rows["lat"]) & np.isfinite(rows["lon"])]
        rows = rows[np.argsort(rows["id"], kind="stable")]
        if not len(rows):
            return
        starts = np.flatnonzero(np.r_[True, rows["id"][1:] != rows["id"][:-1]])
        for a, b in zip(starts.tolist(), np.r_[starts[1:], len(rows)].tolist(), strict=True):
            yield rows[a:b]

    def features(self, class_names: dict[int, str], properties: Callable[[dict[str, Any]], None] | None = None
                 ) -> Iterable[dict[str, Any]]:
        """One GeoJSON feature per track id (ascending), as `geojson_tracks` builds them for video 0; rows without a
        finite position are left out. properties: called on each feature's properties (to add to them)."""
        for trs in self.by_track():
            coords = [[round(lon, 8), round(lat, 8)] for lon, lat in zip(trs["lon"].tolist(), trs["lat"].tolist(),
                                                                         strict=True)]
            geometry = ({"type": "Point", "coordinates": coords[0]} if len(coords) == 1
                        else {"type": "LineString", "coordinates": coords})
            cls = int(trs["cls"][0])
            props = {"id": int(trs["id"][0]), "video_id": 0, "cls": cls, "cls_name": class_names.get(cls, str(cls)),
                     "frames": trs["frame"].tolist(), "times": [round(t, 3) for t in trs["t"].tolist()],
                     "scores": [round(s, 4) for s in trs["score"].tolist()],
                     "vel_en": [[round(e, 3), round(n, 3)] for e, n in zip(trs["ve"].tolist(), trs["vn"].tolist(),
                                                                           strict=True)]}
            if properties is not None:
                properties(props)
            yield {"type": "Feature", "geometry": geometry, "properties": props}

    def write_geojson(self, path: str | Path, class_names: dict[int, str],
                      properties: Callable[[dict[str, Any]], None] | None = None) -> int:
        """Write the FeatureCollection to path, feature by feature (`write_chunks_atomic`). Returns the number of
        features."""
        n = 0

        def counted() -> Iterator[dict[str, Any]]:
            nonlocal n
            for feature in self.features(class_names, properties):
                n += 1
                yield feature

        write_chunks_atomic(Path(path), collection_chunks(counted()))
        return n


class FirstPass:
    """The image ids an agent's output files hold: `take` says whether a frame goes to them, not when they hold
    its image already (--loop played the source again: a COCO result list with each frame twice scores as one
    image; the contract audit of 1 Dec 2026), said once; `skipped` counts those frames."""

    def __init__(self) -> None:
        self.seen: set[int] = set()
        self.skipped = 0

    def take(self, image: int) -> bool:
        if image not in self.seen:
            self.seen.add(image)
            return True
        if not self.skipped:
            log.warning("frame %s came again (--loop started the source over): --detections-out / --tracks-out "
                        "hold the first pass; the later passes are not written", image)
        self.skipped += 1
        return False

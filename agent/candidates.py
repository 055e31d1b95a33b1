"""Pre-NMS candidates (a COCO result list) per image, validated against their dataset.

The file is read entry by entry (`agent.json_files.iter_json_list`) into typed buffers: parsed whole, an hour of
video's candidates (~8 M entries at 30 frames/s and 230 a frame) took ~270 MB per 1,000 frames as Python dicts,
~10 GB at 36,000 frames, where the arrays kept take ~40 bytes an entry.
"""

from __future__ import annotations

import logging
from array import array
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from agent.json_files import NotAJsonList, iter_json_list


class Dataset(Protocol):
    """What the candidates are checked against (agent.dataset.Dataset): its image and category ids."""

    @property
    def images(self) -> Mapping[int, Any]: ...

    @property
    def categories(self) -> Mapping[int, Any]: ...

__all__ = ["Candidates", "scores_outside_unit_error"]

#: Finite scores outside [0, 1] are skipped and counted (a detector's glitch) while they are at most this share of
#: the boxes or fewer than OUT_OF_RANGE_MIN; more means the file's scores are on another scale (percentages, logits,
#: boosted scores) and the run is refused: skipped, they left a percent-scaled file 0 of 4,216 candidates and wrote
#: an empty results file with exit 0.
OUT_OF_RANGE_SHARE = 0.01
OUT_OF_RANGE_MIN = 10
#: Scores this close outside [0, 1] are rounding (1.000000001 is 1.0 in float32, as the pipeline holds scores) and
#: are clipped into it, not skipped or refused.
SCORE_ROUNDING = 1e-6

log = logging.getLogger("agent.dataset")  # its messages as before the split


@dataclass
class Candidates:
    """Pre-NMS candidates per image: boxes_xyxy (N, 4) float32, scores (N,) float32, class ids (N,).

    embeddings: per image, (N, D) float32 appearance descriptors from the optional ``embedding`` field
    of the entries (NaN rows for entries without one); only images where some entry has one.
    """

    by_image: dict[int, tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]]
    skipped: dict[str, int]
    embeddings: dict[int, NDArray[np.float32]] = field(default_factory=dict)

    def get_embeddings(self, image_id: int) -> NDArray[np.float32] | None:
        """(N, D) descriptors of the image's candidates in `get`'s order, or None when it has none."""
        return self.embeddings.get(image_id)

    def get(self, image_id: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
        return self.by_image.get(image_id, empty)

    @classmethod
    def load(cls, path: str | Path, dataset: Dataset) -> Candidates:
        """Read and validate a candidates file (entry by entry: its size in memory is the arrays', not the
        file's as Python objects); errors as `from_list`'s, and for a file that is missing or not valid JSON."""
        source = str(path)
        try:
            return cls._from_entries(iter_json_list(path, "candidates"), dataset, source)
        except NotAJsonList:
            raise ValueError(_NOT_A_LIST.format(source=source)) from None
        except MalformedEntry:
            # parsed whole, a file broken further on said that first: check the rest (entry by entry) before
            for _ in iter_json_list(path, "candidates"):
                pass
            raise

    @classmethod
    def from_list(cls, entries: Any, dataset: Dataset, *, source: str = "<candidates>") -> Candidates:
        """Validate a COCO result list.

        Entries naming an unknown image_id or category_id, or malformed ones (missing fields,
        non-numeric values) raise ValueError naming the entry: they mean the files do not belong
        together. Degenerate boxes (NaN/inf, width or height <= 0), NaN scores and finite scores outside [0, 1]
        are skipped and counted in `skipped` (detectors emit those; one should not stop a run), the last while
        fewer than OUT_OF_RANGE_MIN or at most OUT_OF_RANGE_SHARE of the boxes: more raise ValueError (the scores
        are on another scale: `scores_outside_unit_error`). Scores within SCORE_ROUNDING of [0, 1] are clipped.
        """
        if not isinstance(entries, list):
            raise ValueError(_NOT_A_LIST.format(source=source))
        return cls._from_entries(entries, dataset, source)

    @classmethod
    def _from_entries(cls, entries: Iterable[Any], dataset: Dataset, source: str) -> Candidates:
        ids_buf, cats_buf, boxes_buf, scores_buf = array("q"), array("q"), array("d"), array("d")
        # optional appearance descriptors (docs/tracking.md): the rows of the first length seen, and which entries
        emb_buf, emb_at, dims = array("f"), array("q"), set()
        i = -1
        # one entry's values put into numpy scalars first, in the order and with the conversions of the arrays the
        # whole list was once put into: the same values accepted (null -> NaN, skipped below), the same errors
        id1, cat1, box1, score1 = np.empty(1, np.int64), np.empty(1, np.int64), np.empty(4), np.empty(1)
        for i, e in enumerate(entries):
            try:
                id1[0] = e["image_id"]
                cat1[0] = e["category_id"]
                bbox = e["bbox"]
                if len(bbox) != 4:
                    raise ValueError(f"bbox must have 4 numbers, got {len(bbox)}")
                box1[:] = bbox
                score1[0] = e["score"]
                ids_buf.append(int(id1[0]))
                cats_buf.append(int(cat1[0]))
                boxes_buf.frombytes(box1.tobytes())
                scores_buf.append(float(score1[0]))
                if "embedding" in e:
                    emb = e["embedding"]
                    if not isinstance(emb, list) or not emb or not all(
                            isinstance(v, (int, float)) and not isinstance(v, bool) for v in emb):
                        raise ValueError("embedding must be a non-empty list of numbers")
                    dims.add(len(emb))
                    if len(dims) == 1:
                        emb_buf.extend(emb)
                        emb_at.append(i)
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                raise MalformedEntry(f"{source}: entry {i} is malformed ({exc!r}): {str(e)[:200]}") from None
        n = i + 1
        image_ids = np.frombuffer(ids_buf, np.int64) if n else np.zeros(0, np.int64)
        cat_ids = np.frombuffer(cats_buf, np.int64) if n else np.zeros(0, np.int64)
        boxes = np.frombuffer(boxes_buf, np.float64).reshape(n, 4) if n else np.zeros((0, 4))
        scores = np.frombuffer(scores_buf, np.float64).copy() if n else np.zeros(0)
        rounding = (scores >= -SCORE_ROUNDING) & (scores <= 1.0 + SCORE_ROUNDING)
        scores[rounding] = np.clip(scores[rounding], 0.0, 1.0)
        if len(dims) > 1:
            raise ValueError(f"{source}: embeddings of different lengths {sorted(dims)}")
        unknown_img = ~np.isin(image_ids, np.fromiter(dataset.images, np.int64, len(dataset.images)))
        if unknown_img.any():
            i = int(np.flatnonzero(unknown_img)[0])
            raise ValueError(f"{source}: entry {i} references unknown image_id {int(image_ids[i])} "
                             f"({int(unknown_img.sum())} such entries)")
        unknown_cat = ~np.isin(cat_ids, np.fromiter(dataset.categories, np.int64, len(dataset.categories)))
        if unknown_cat.any():
            i = int(np.flatnonzero(unknown_cat)[0])
            raise ValueError(f"{source}: entry {i} references unknown category_id {int(cat_ids[i])}; "
                             f"known: {sorted(dataset.categories)}")
        finite = np.isfinite(boxes).all(axis=1)
        positive = finite & (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
        good_score = np.isfinite(scores) & (scores >= 0) & (scores <= 1)
        outside = positive & np.isfinite(scores) & ~good_score
        n_outside = int(outside.sum())
        if n_outside >= OUT_OF_RANGE_MIN and n_outside > OUT_OF_RANGE_SHARE * int(positive.sum()):
            error = scores_outside_unit_error(scores[positive], source, "and run on the rest")
            assert error is not None
            raise error
        skipped = {
            "non_finite_box": int((~finite).sum()),
            "non_positive_size": int((finite & ~positive).sum()),
            "score_out_of_range": int((positive & ~good_score).sum()),
        }
        if any(skipped.values()):
            log.warning("%s: skipped candidates: %s", source, skipped)
        # the kept entries in image order, taken once (each copy of an hour's arrays is hundreds of MB)
        take = np.flatnonzero(positive & good_score)
        take = take[np.argsort(image_ids[take], kind="stable")]
        image_ids, cat_ids, scores = image_ids[take], cat_ids[take], scores[take]
        xyxy = boxes[take]
        xyxy[:, 2:] += xyxy[:, :2]
        emb_all = None
        if dims:  # NaN rows for the entries without one
            emb_all = np.full((len(take), dims.pop()), np.nan, np.float32)
            place = np.full(n, -1, np.int64)
            place[take] = np.arange(len(take))
            rows = place[np.frombuffer(emb_at, np.int64)]
            have = rows >= 0
            emb_all[rows[have]] = np.frombuffer(emb_buf, np.float32).reshape(len(emb_at), -1)[have]
        by_image = {}
        embeddings = {}
        if len(image_ids):
            splits = np.flatnonzero(np.diff(image_ids)) + 1
            for idx in np.split(np.arange(len(image_ids)), splits):
                by_image[int(image_ids[idx[0]])] = (xyxy[idx].astype(np.float32), scores[idx].astype(np.float32),
                                                    cat_ids[idx])
                if emb_all is not None and np.isfinite(emb_all[idx]).all(axis=1).any():
                    embeddings[int(image_ids[idx[0]])] = emb_all[idx]
        return cls(by_image, skipped, embeddings)


_NOT_A_LIST = "{source}: expected a JSON list of {{image_id, category_id, bbox, score}}"


def scores_outside_unit(scores: Iterable[float]) -> list[float]:
    """The finite scores outside [0, 1] beyond rounding (SCORE_ROUNDING; NaN and infinities are a detector's
    glitches, skipped elsewhere)."""
    return [float(v) for v in scores if np.isfinite(v) and not -SCORE_ROUNDING <= v <= 1.0 + SCORE_ROUNDING]


def scores_outside_unit_error(scores: Iterable[float], source: str, consequence: str) -> ValueError | None:
    """A ValueError naming how many of the scores are finite and outside [0, 1] (beyond rounding), with an example
    and what they look like (percentages when most are above 1, some above 1.5 and none above 100; else not a
    detector's confidences, e.g. `uavmm detect`'s boosted scores); None when there are none. consequence: what the
    caller would do with them, after "the pipeline would drop them"."""
    values = list(scores)
    outside = scores_outside_unit(values)
    if not outside:
        return None
    hint = (" (percentages? divide them by 100)" if 1.5 < max(outside) <= 100.0 and min(outside) >= 0.0
            and sum(v > 1.0 for v in values) > len(values) / 2 else
            " (a detector's confidences are in [0, 1]; `uavmm detect`'s boosted scores are not a detector's output)")
    return ValueError(f"{source}: {len(outside)} of the detections have a score outside [0, 1]: e.g. {outside[0]!r}; "
                      f"the pipeline would drop them, {consequence}{hint}")


class MalformedEntry(ValueError):
    """An entry that is not {image_id, category_id, bbox, score} (reading the file stops there)."""

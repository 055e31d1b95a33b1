"""Joint-map peaks against the truth in the cooperative evaluation: where the fused map puts the objects.

Once a second (after a warm-up) the joint map's object candidates are taken as the REST API's ``/v1/objects``
takes them (`fusion_server.peaks.find_peaks` over the joint tiles of each class, min_score 0.5) and matched one
to one (Hungarian, within a gate of 5 m) to the true ground positions (the annotations' lat/lon) of the objects
that stand still for the whole flight and that a UAV sees at that moment. The ground distances of the matched
pairs give the peaks' error (median, 90th percentile), the matched share how many objects got a peak; peaks
left over (clutter, walkers, an object split in two) are counted apart. Per UAV the same figures count the
objects that UAV sees at the sample (the joint map is one; what each UAV's operator finds in it differs).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from fusion_server.joint_map import JointMap
from fusion_server.peaks import find_peaks
from shared.geo import latlon_to_local

__all__ = ["MATCH_GATE_M", "PEAK_BAR_M", "PEAK_MIN_SCORE", "PeakSampler", "match_peaks", "standing_objects"]

#: A peak farther than this from an object is not its peak (metres).
MATCH_GATE_M = 5.0
#: The REST API's default min_score of /v1/objects.
PEAK_MIN_SCORE = 0.5
#: An object whose true positions over the flight lie within this of each other stands still (metres).
STANDING_SPAN_M = 0.2
#: The issue's bar: a peak within this of the truth (metres).
PEAK_BAR_M = 1.0


def standing_objects(data_dir: Path, annotations: list[dict[str, Any]],
                     categories: dict[int, str]) -> dict[int, tuple[str, float, float]]:
    """Objects that stand still for the whole flight: track id -> (class name, lat, lon).

    annotations: the dataset's (each with track_id, category_id and the true lat/lon); truth.json's
    occluded_boxes (objects in view behind an occluder) add their positions too. An object counts when all
    its positions lie within STANDING_SPAN_M of their mean.
    """
    truth_path = data_dir / "truth.json"
    hidden = json.loads(truth_path.read_text()).get("occluded_boxes", []) if truth_path.exists() else []
    cls_of = {a["track_id"]: categories.get(a["category_id"], str(a["category_id"])) for a in annotations}
    positions: dict[int, list[tuple[float, float]]] = {}
    for a in list(annotations) + list(hidden):
        if "lat" in a and "lon" in a:
            positions.setdefault(a["track_id"], []).append((float(a["lat"]), float(a["lon"])))
    out = {}
    for tid, pts in positions.items():
        if tid not in cls_of:
            continue
        arr = np.asarray(pts)
        lat0, lon0 = arr.mean(axis=0)
        east, north = latlon_to_local(arr[:, 0], arr[:, 1], lat0, lon0)
        if float(np.max(np.hypot(east, north))) <= STANDING_SPAN_M:
            out[tid] = (cls_of[tid], float(lat0), float(lon0))
    return out


def match_peaks(truth_latlon: NDArray[np.float64], peak_latlon: NDArray[np.float64],
                gate_m: float = MATCH_GATE_M) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """One-to-one matching of peaks to true positions, least total distance, pairs within gate_m.

    truth_latlon: (T, 2), peak_latlon: (P, 2) degrees. Returns truth rows (M,), peak rows (M,) and their ground
    distances (M,) in metres (local tangent plane at the first true position).
    """
    if not len(truth_latlon) or not len(peak_latlon):
        empty = np.zeros(0, np.intp)
        return empty, empty, np.zeros(0)
    lat0, lon0 = float(truth_latlon[0, 0]), float(truth_latlon[0, 1])
    te, tn = latlon_to_local(truth_latlon[:, 0], truth_latlon[:, 1], lat0, lon0)
    pe, pn = latlon_to_local(peak_latlon[:, 0], peak_latlon[:, 1], lat0, lon0)
    dist = np.hypot(np.asarray(te)[:, None] - np.asarray(pe)[None, :],
                    np.asarray(tn)[:, None] - np.asarray(pn)[None, :])
    # beyond the gate a pair costs more than any in-gate pair set could, so it is chosen only when nothing else is
    cost = np.where(dist <= gate_m, dist, gate_m * (1.0 + len(truth_latlon) + len(peak_latlon)))
    rows, cols = linear_sum_assignment(cost)
    keep = dist[rows, cols] <= gate_m
    return rows[keep].astype(np.intp), cols[keep].astype(np.intp), dist[rows[keep], cols[keep]]


@dataclass
class PeakSampler:
    """Samples the joint map's peaks against the standing objects in view; call it after each publish.

    standing: `standing_objects`; seen: image id -> track ids annotated in that image (visible to its UAV);
    uav_of: image id -> the UAV that took it (per-UAV figures; without it all is one view);
    every_s, warmup_s: sample period and the time before the first sample (seconds from the first
    call).
    """

    standing: dict[int, tuple[str, float, float]]
    seen: dict[int, set[int]]
    uav_of: dict[int, str] = field(default_factory=dict)
    every_s: float = 1.0
    warmup_s: float = 3.0
    gate_m: float = MATCH_GATE_M
    min_score: float = PEAK_MIN_SCORE
    errors_m: list[float] = field(default_factory=list)
    objects: int = 0
    errors_by_uav: dict[str, list[float]] = field(default_factory=dict)
    objects_by_uav: dict[str, int] = field(default_factory=dict)
    extra_peaks: int = 0
    samples: int = 0
    _t0: float | None = None
    _next: float | None = None

    def __call__(self, t: float, joint: JointMap, image_ids: list[int]) -> None:
        """One publish cycle at time t (seconds) with the joint map as fused now and the cycle's image ids."""
        if self._t0 is None:
            self._t0, self._next = t, t + self.warmup_s
        if self._next is None or t < self._next:
            return
        self._next = t + self.every_s
        by_uav: dict[str, set[int]] = {}
        for i in image_ids:
            by_uav.setdefault(self.uav_of.get(i, ""), set()).update(self.seen.get(i, set()) & set(self.standing))
        in_view = set().union(*by_uav.values())
        self.samples += 1
        for cls in sorted({self.standing[tid][0] for tid in in_view} | joint.classes()):
            tids = [tid for tid in sorted(in_view) if self.standing[tid][0] == cls]
            truth = np.array([self.standing[tid][1:] for tid in tids], np.float64).reshape(-1, 2)
            peaks = find_peaks(joint.tiles(cls), joint.grid, self.min_score)
            peak_ll = np.array([(p.lat, p.lon) for p in peaks], np.float64).reshape(-1, 2)
            rows, _, dist = match_peaks(truth, peak_ll, self.gate_m)
            self.errors_m.extend(dist.tolist())
            self.objects += len(truth)
            self.extra_peaks += len(peak_ll) - len(dist)
            for uav, tids_uav in by_uav.items():
                if not uav:
                    continue
                errors = self.errors_by_uav.setdefault(uav, [])
                errors.extend(d for r, d in zip(rows.tolist(), dist.tolist(), strict=True) if tids[r] in tids_uav)
                self.objects_by_uav[uav] = self.objects_by_uav.get(uav, 0) + sum(t in tids_uav for t in tids)

    def summary(self, uav: str | None = None) -> dict[str, float | int]:
        """peak_err_m, peak_err_p90_m (of the matched peaks: NaN without a match), objects_with_peak and
        objects_within_bar (% of the standing objects in view with a matched peak, and with one within
        PEAK_BAR_M; NaN without any), extra_peaks (unmatched peaks per sample, of the whole map), peak_samples.

        uav: only the objects that UAV saw at each sample (`uav_of`); None: those any UAV saw.
        """
        errors = np.asarray(self.errors_m if uav is None else self.errors_by_uav.get(uav, []))
        objects = self.objects if uav is None else self.objects_by_uav.get(uav, 0)
        return {
            "peak_err_m": float(np.median(errors)) if errors.size else math.nan,
            "peak_err_p90_m": float(np.percentile(errors, 90)) if errors.size else math.nan,
            "objects_with_peak": 100.0 * errors.size / objects if objects else math.nan,
            "objects_within_bar": 100.0 * int(np.sum(errors <= PEAK_BAR_M)) / objects if objects else math.nan,
            "extra_peaks": self.extra_peaks / self.samples if self.samples else math.nan,
            "peak_samples": self.samples,
        }

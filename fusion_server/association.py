"""Gated one-to-one association of ground points that stays cheap for any number of them.

Only pairs within the gate are ever formed (a k-d tree over unit-sphere coordinates), they split
into independent groups (connected components of the bipartite gate graph), and each group is
solved exactly (``scipy.optimize.linear_sum_assignment``) when it is small, greedily (nearest pairs
first) when it is not. The exact answer over all points is the exact answers of the groups, so
ordinary scenes keep the optimal assignment and thousands of points piled inside one gate (a flood)
cost near-linear time instead of a cubic one. No I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["MAX_CANDIDATES", "MAX_EXACT_CELLS", "M_PER_DEG_LAT", "Assignment", "gated_assignment",
           "ground_distance_m", "sphere_xyz", "weighted_lon"]

#: Metres per degree of latitude (and of longitude at the equator) of the equirectangular distance.
M_PER_DEG_LAT = 111_320.0
_EARTH_RADIUS_M = M_PER_DEG_LAT * 180.0 / np.pi
#: Largest group (rows x columns) solved exactly; larger ones are solved greedily.
MAX_EXACT_CELLS = 250_000
#: Candidates per point considered inside the gate (the nearest ones).
MAX_CANDIDATES = 16
_NOT_A_PAIR = 1e9  # a cell of an exact group's matrix that is no gated pair (costs stay far below)


def ground_distance_m(lat1, lon1, lat2, lon2) -> np.ndarray:
    """Ground distance in metres between points (degrees, broadcastable), equirectangular.

    Accurate to well under 1 % at association distances (up to kilometres); longitudes differing
    by more than 180 deg are wrapped.
    """
    lat1, lon1, lat2, lon2 = (np.asarray(v, dtype=np.float64) for v in (lat1, lon1, lat2, lon2))
    dlon = (lon2 - lon1 + 180.0) % 360.0 - 180.0
    east = dlon * M_PER_DEG_LAT * np.cos(np.radians(0.5 * (lat1 + lat2)))
    north = (lat2 - lat1) * M_PER_DEG_LAT
    return np.hypot(east, north)


def weighted_lon(weights: ArrayLike, lon: ArrayLike) -> float:
    """Weighted mean of longitudes (degrees) that lie near each other, across the antimeridian: taken on their
    differences from the first, wrapped, then put back in [-180, 180) (a plain mean of 179.999997 and -179.999997
    put a track at 0, 20,000 km away)."""
    w = np.asarray(weights, dtype=np.float64)
    lo = np.asarray(lon, dtype=np.float64)
    offsets = (lo - lo[0] + 180.0) % 360.0 - 180.0
    mean = float(lo[0] + np.dot(w, offsets) / w.sum())
    return mean if -180.0 <= mean < 180.0 else (mean + 180.0) % 360.0 - 180.0


def sphere_xyz(lat: NDArray[np.float64], lon: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3) points (metres) on a sphere of the earth's radius, for k-d trees: a chord is never longer than the
    ground distance and equals it within 1e-6 at association distances."""
    lat_r, lon_r = np.radians(lat), np.radians(lon)
    return _EARTH_RADIUS_M * np.column_stack([np.cos(lat_r) * np.cos(lon_r), np.cos(lat_r) * np.sin(lon_r),
                                              np.sin(lat_r)])


@dataclass(frozen=True, slots=True)
class Assignment:
    """rows, cols: (K,) int64 matched indices into the two point sets (each index at most once);
    cost_m: (K,) float64 their distances (all <= the gate). greedy_groups: groups too large for the
    exact assignment."""

    rows: NDArray[np.int64]
    cols: NDArray[np.int64]
    cost_m: NDArray[np.float64]
    greedy_groups: int


def gated_assignment(lat_a: ArrayLike, lon_a: ArrayLike, lat_b: ArrayLike, lon_b: ArrayLike, gate_m: float,
                     max_exact_cells: int = MAX_EXACT_CELLS, max_candidates: int = MAX_CANDIDATES,
                     forbid: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                     cost: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
                     unmatched_cost: float | ArrayLike | None = None) -> Assignment:
    """Match points a (N,) to points b (M,) one-to-one, only within ``gate_m`` metres.

    Each point of a considers its ``max_candidates`` nearest points of b inside the gate (more than
    that many inside one gate is a pile-up, not a scene: the bound keeps the work O(N log M)).
    Per group of points connected by gated pairs: with at most ``max_exact_cells`` rows x columns,
    the most pairs with the least total distance (``linear_sum_assignment``, the same answer as over
    the whole matrix with pairs beyond the gate forbidden); larger groups greedily, shortest pairs
    first. Degrees in, metres out (:func:`ground_distance_m`). forbid(ia, ib) -> (K,) bool: gated pairs (indexes
    into a and b) that may not be matched whatever their distance. cost(ia, ib, dist_m) -> (K,): the gated pairs'
    costs to minimise instead of their distances (inf: may not be matched); Assignment.cost_m stays the distances.
    unmatched_cost: what leaving a point of a unmatched costs, one for all or (N,) one each (None or inf: the most
    pairs first, then the least cost); a pair costing as much or more is never formed.
    """
    lat_a, lon_a, lat_b, lon_b = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (lat_a, lon_a, lat_b, lon_b))
    empty = np.zeros(0, np.int64)
    if lat_a.size == 0 or lat_b.size == 0:
        return Assignment(empty, empty, np.zeros(0), 0)
    # chords are never longer than ground distances, and equal them within 1e-6 at gate lengths
    radius = gate_m * (1.0 + 1e-3) + 1e-3
    k = min(max_candidates, lat_b.size)
    dist, nearest = cKDTree(sphere_xyz(lat_b, lon_b)).query(sphere_xyz(lat_a, lon_a), k=k,
                                                             distance_upper_bound=radius)
    dist, nearest = dist.reshape(lat_a.size, k), nearest.reshape(lat_a.size, k)
    found = np.isfinite(dist)
    ia = np.broadcast_to(np.arange(lat_a.size)[:, None], found.shape)[found].astype(np.int64)
    ib = nearest[found].astype(np.int64)
    dist = ground_distance_m(lat_a[ia], lon_a[ia], lat_b[ib], lon_b[ib])
    keep = dist <= gate_m
    if forbid is not None and keep.any():
        keep[keep] = ~forbid(ia[keep], ib[keep])
    ia, ib, dist = ia[keep], ib[keep], dist[keep]
    if cost is not None and ia.size:
        dist = np.asarray(cost(ia, ib, dist), dtype=np.float64)
        allowed = np.isfinite(dist)
        ia, ib, dist = ia[allowed], ib[allowed], dist[allowed]
    unmatched = None if unmatched_cost is None else np.broadcast_to(np.asarray(unmatched_cost, np.float64),
                                                                     lat_a.shape)
    if unmatched is not None:  # a pair dearer than leaving its point unmatched is never worth forming
        cheaper = dist < unmatched[ia]
        ia, ib, dist = ia[cheaper], ib[cheaper], dist[cheaper]
    if ia.size == 0:
        return Assignment(empty, empty, np.zeros(0), 0)
    na, nb = lat_a.size, lat_b.size
    graph = coo_matrix((np.ones(ia.size), (ia, na + ib)), shape=(na + nb, na + nb))
    _, labels = connected_components(graph, directed=False)
    edge_group = labels[ia]
    order = np.argsort(edge_group, kind="stable")
    ia, ib, dist, edge_group = ia[order], ib[order], dist[order], edge_group[order]
    starts = np.flatnonzero(np.r_[True, edge_group[1:] != edge_group[:-1]])
    ends = np.r_[starts[1:], ia.size]
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    greedy = 0
    single = ends - starts == 1  # one gated pair: matched as it is (most groups in ordinary scenes)
    rows.append(ia[starts[single]])
    cols.append(ib[starts[single]])
    for start, end in zip(starts[~single], ends[~single], strict=True):
        ga, gb, gc = ia[start:end], ib[start:end], dist[start:end]
        ua, a_local = np.unique(ga, return_inverse=True)
        ub, b_local = np.unique(gb, return_inverse=True)
        if ua.size * ub.size <= max_exact_cells:
            # with unmatched_cost, one more column per point of a: leaving it unmatched, at its cost
            extra = ua.size if unmatched is not None else 0
            block = np.full((ua.size, ub.size + extra), _NOT_A_PAIR)
            block[a_local, b_local] = gc
            if unmatched is not None:
                block[np.arange(ua.size), ub.size + np.arange(ua.size)] = np.minimum(unmatched[ua], _NOT_A_PAIR)
            r, c = linear_sum_assignment(block)
            ok = (block[r, c] < _NOT_A_PAIR) & (c < ub.size)
            rows.append(ua[r[ok]])
            cols.append(ub[c[ok]])
        else:
            greedy += 1
            used_a = np.zeros(ua.size, bool)
            used_b = np.zeros(ub.size, bool)
            picked = []
            for k in np.argsort(gc, kind="stable"):
                if not used_a[a_local[k]] and not used_b[b_local[k]]:
                    used_a[a_local[k]] = used_b[b_local[k]] = True
                    picked.append(k)
            chosen = np.asarray(picked, np.int64)
            rows.append(ga[chosen])
            cols.append(gb[chosen])
    r_all, c_all = np.concatenate(rows), np.concatenate(cols)
    return Assignment(r_all, c_all, ground_distance_m(lat_a[r_all], lon_a[r_all], lat_b[c_all], lon_b[c_all]),
                      greedy)

"""Who goes with whom: pairs of points within reach (k-d tree) and optimal assignment over gated pairs,
solved per independent group so that large scenes stay cheap.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["gated_assignment", "near_pairs", "sparse_assignment"]

FloatArray = NDArray[np.float64]
#: Cost given to gated-out pairs before the assignment (finite: linear_sum_assignment rejects inf rows).
_GATED_COST = 1e9
#: Up to this many rows x columns an assignment is solved as one dense problem.
_DENSE_CELLS = 2500


def near_pairs(a_xy: FloatArray, a_radius: FloatArray, b_xy: FloatArray,
               b_radius: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs (i, j) with |a_i - b_j| <= a_radius_i + b_radius_j, found with a k-d tree.

    a_xy (A, 2), a_radius (A,), b_xy (B, 2), b_radius (B,), any consistent unit. Returns (K,) int64
    arrays i, j (every pair, i ascending); rows with NaN coordinates never pair.
    """
    empty = np.zeros(0, np.int64)
    a_ok = np.flatnonzero(np.isfinite(a_xy).all(axis=1))
    b_ok = np.flatnonzero(np.isfinite(b_xy).all(axis=1))
    if not len(a_ok) or not len(b_ok):
        return empty, empty
    reach = float(np.max(np.asarray(a_radius)[a_ok])) + float(np.max(np.asarray(b_radius)[b_ok]))
    found = cKDTree(a_xy[a_ok]).sparse_distance_matrix(cKDTree(b_xy[b_ok]), reach, output_type="ndarray")
    if not len(found):
        return empty, empty
    i, j = a_ok[found["i"]], b_ok[found["j"]]
    keep = np.hypot(*(a_xy[i] - b_xy[j]).T) <= np.asarray(a_radius)[i] + np.asarray(b_radius)[j]
    i, j = i[keep], j[keep]
    order = np.lexsort((j, i))
    return i[order].astype(np.int64), j[order].astype(np.int64)


def sparse_assignment(rows: NDArray[np.int64], cols: NDArray[np.int64], cost: FloatArray, *,
                      unassigned_cost: float | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Optimal assignment over the allowed pairs (rows[k], cols[k]) with costs cost[k].

    Without unassigned_cost: minimises the total cost among the assignments of largest size, like
    linear_sum_assignment on the dense matrix with the other pairs gated out. With it, a row and a
    column may also stay unassigned, which together cost unassigned_cost: pairs costing more are
    never used, and two cheap pairs are not traded for one good and one poor pair. Each connected
    group of rows and columns is solved on its own (far-apart tracks never compete). Returns the
    assigned (rows, cols).
    """
    empty = np.zeros(0, np.int64)
    if unassigned_cost is not None:
        keep = cost < unassigned_cost
        rows, cols, cost = rows[keep], cols[keep], cost[keep] - unassigned_cost
    if not len(rows):
        return empty, empty
    r_ids, r_inv = np.unique(rows, return_inverse=True)
    c_ids, c_inv = np.unique(cols, return_inverse=True)
    n_r = len(r_ids)
    if n_r * len(c_ids) <= _DENSE_CELLS:  # small: one dense problem is cheaper than finding the groups
        r, c = _dense_assignment(r_inv, c_inv, cost, n_r, len(c_ids), unassigned_cost is not None)
        return r_ids[r].astype(np.int64), c_ids[c].astype(np.int64)
    graph = coo_matrix((np.ones(len(rows)), (r_inv, c_inv + n_r)), shape=(n_r + len(c_ids),) * 2)
    _, labels = connected_components(graph, directed=False)
    lab = labels[r_inv]
    n_labels = int(labels.max()) + 1
    rows_per = np.bincount(np.unique(lab * n_r + r_inv) // n_r, minlength=n_labels)
    cols_per = np.bincount(np.unique(lab * len(c_ids) + c_inv) // len(c_ids), minlength=n_labels)
    # One row or one column in the group (most groups): its cheapest pair is the optimum.
    star = (rows_per[lab] == 1) | (cols_per[lab] == 1)
    out_r, out_c = [], []
    s_idx = np.flatnonzero(star)
    if len(s_idx):
        order = s_idx[np.lexsort((cost[s_idx], lab[s_idx]))]
        first = np.ones(len(order), dtype=bool)
        first[1:] = lab[order][1:] != lab[order][:-1]
        out_r.append(rows[order[first]])
        out_c.append(cols[order[first]])
    multi = np.flatnonzero(~star)
    if len(multi):
        order = multi[np.argsort(lab[multi], kind="stable")]
        bounds = np.flatnonzero(np.diff(lab[order])) + 1
        for group in np.split(order, bounds):
            gr, gr_inv = np.unique(r_inv[group], return_inverse=True)
            gc, gc_inv = np.unique(c_inv[group], return_inverse=True)
            r, c = _dense_assignment(gr_inv, gc_inv, cost[group], len(gr), len(gc), unassigned_cost is not None)
            out_r.append(r_ids[gr[r]])
            out_c.append(c_ids[gc[c]])
    return np.concatenate(out_r).astype(np.int64), np.concatenate(out_c).astype(np.int64)


def _dense_assignment(r: NDArray[np.int64], c: NDArray[np.int64], cost: FloatArray, n_rows: int, n_cols: int,
                      optional: bool) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """linear_sum_assignment of pairs (r, c) with costs in an (n_rows, n_cols) problem; with optional,
    dummy rows and columns at cost 0 let every row and column stay unassigned (costs are < 0 then)."""
    if optional:
        dense = np.zeros((n_rows + n_cols, n_cols + n_rows))
        dense[:n_rows, :n_cols] = _GATED_COST
    else:
        dense = np.full((n_rows, n_cols), _GATED_COST)
    dense[r, c] = cost
    allowed = np.zeros(dense.shape, dtype=bool)
    allowed[r, c] = True
    rr, cc = linear_sum_assignment(dense)
    ok = allowed[rr, cc]
    return rr[ok], cc[ok]


def gated_assignment(cost: FloatArray, allowed: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Optimal assignment (linear_sum_assignment) restricted to allowed pairs.

    cost: (R, C) float; allowed: (R, C) bool. Returns row and column indices (K,) of the assigned
    allowed pairs, minimising the total cost of those; empty when nothing is allowed.
    """
    rows_any = allowed.any(axis=1)
    cols_any = allowed.any(axis=0)
    if not rows_any.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ri = np.flatnonzero(rows_any)
    ci = np.flatnonzero(cols_any)
    sub_allowed = allowed[np.ix_(ri, ci)]
    sub = np.where(sub_allowed, cost[np.ix_(ri, ci)], _GATED_COST)
    r, c = linear_sum_assignment(sub)
    ok = sub_allowed[r, c]
    return ri[r[ok]].astype(np.int64), ci[c[ok]].astype(np.int64)

"""Chain stripe centres of consecutive rows into segments (pieces of one stripe)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.validation import SlitExtractionError

I64 = NDArray[np.int64]

#: Default minimum number of centre points of a kept segment: shorter runs are noise or residues
#: of dots, and a segment must be long enough to carry a dot template for identification.
DEFAULT_MIN_LENGTH = 10


def link_segments(
    u: ArrayLike,
    v: ArrayLike,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
) -> I64:
    """Chain centre points of consecutive rows into segments continuous along v.

    A point p in row v is linked to a point q in the first row v + g (g = 1 .. max_gap + 1)
    that has any point within ``max_du * g`` px of p's column, if q is the only such point
    there and p is likewise the only candidate in q's first non-empty row above. Ambiguities
    (two candidates), jumps and longer gaps break the chain. One sort and a compiled linear
    pass (the windows move monotonically along the sorted points).

    Parameters
    ----------
    u, v : (K,) centre columns and rows (px); v is rounded to integer rows
    max_du : largest column change per row (px) within a segment
    max_gap : largest number of missing rows bridged
    min_length : segments with fewer points get label -1

    Returns
    -------
    labels : (K,) int64, segment id per point (0..S-1, ordered by the segments' mean u), -1 for
        points of too-short segments
    """
    uu = np.asarray(u, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    if uu.ndim != 1 or vv.shape != uu.shape:
        raise SlitExtractionError(
            f"u and v must be 1-D arrays of the same length, got {uu.shape} and {vv.shape}"
        )
    if not (np.isfinite(uu).all() and np.isfinite(vv).all()):
        raise SlitExtractionError("u and v must be finite")
    if not math.isfinite(max_du) or max_du < 0:
        raise SlitExtractionError(f"max_du must be >= 0, got {max_du}")
    if int(max_gap) != max_gap or max_gap < 0:
        raise SlitExtractionError(f"max_gap must be an integer >= 0, got {max_gap}")
    if int(min_length) != min_length or min_length < 1:
        raise SlitExtractionError(f"min_length must be an integer >= 1, got {min_length}")
    n = uu.size
    if n == 0:
        return np.empty(0, np.int64)
    rows = np.rint(vv)
    if n > 1 and bool(
        np.all((rows[1:] > rows[:-1]) | ((rows[1:] == rows[:-1]) & (uu[1:] >= uu[:-1])))
    ):
        order = np.arange(n)  # already sorted by (row, u), as the centres come
    else:
        order = np.lexsort((uu, rows))
    us = uu[order] - uu.min()
    rs = rows[order] - rows.min()
    max_g = int(max_gap) + 1
    # key = row * span + u is sorted; span exceeds the u range plus the search tolerance, so a
    # search window never spills into another row
    span = float(us.max()) + 2 * max_du * max_g + 2.0
    key = rs * span + us
    comp, size, sum_u = _chains(key, us, span, float(max_du), max_g)
    keep = size >= min_length
    mean_u = sum_u / size
    kept = np.flatnonzero(keep)
    new_id = np.full(size.size, -1, np.int64)
    new_id[kept[np.argsort(mean_u[kept], kind="stable")]] = np.arange(kept.size)
    labels = np.empty(n, np.int64)
    labels[order] = new_id[comp]
    return labels


@njit(cache=True)
def _first_neighbour(key, span, max_du, max_g, sign):
    """Per point of the sorted ``key`` (K,): index of the unique point within ``max_du * g``
    px of its column in the first row g = 1 .. ``max_g`` away (``sign`` +1 below, -1 above)
    that has any, -1 if none, -2 if ambiguous. The windows move monotonically with the key,
    so two pointers per g replace the binary searches (the same comparisons)."""
    n = key.size
    found = np.full(n, -1, np.int64)
    for g in range(1, max_g + 1):
        tol = max_du * g
        shift = float(sign * g) * span
        lo = 0
        hi = 0
        for i in range(n):
            centre = key[i] + shift
            a = centre - tol
            b = centre + tol
            while lo < n and key[lo] < a:  # searchsorted(key, a, "left")
                lo += 1
            if hi < lo:
                hi = lo
            while hi < n and key[hi] <= b:  # searchsorted(key, b, "right")
                hi += 1
            if found[i] == -1 and hi > lo:
                found[i] = lo if hi - lo == 1 else -2
    return found


@njit(cache=True)
def _chains(key, us, span, max_du, max_g):
    """Chain the points of the sorted ``key`` (K,): a point and the first candidate below it
    are linked where each is the other's unique candidate (:func:`link_segments`). Returns
    each point's chain (K,) int64, numbered in the order of the chains' first points, and
    each chain's size and sum of ``us`` (summed in point order)."""
    n = key.size
    nxt = _first_neighbour(key, span, max_du, max_g, 1)
    prv = _first_neighbour(key, span, max_du, max_g, -1)
    comp = np.empty(n, np.int64)
    m = 0
    for i in range(n):  # a link goes to a later row: the predecessor has a lower index
        p = prv[i]
        if p >= 0 and nxt[p] == i:
            comp[i] = comp[p]
        else:
            comp[i] = m
            m += 1
    size = np.zeros(m, np.int64)
    sum_u = np.zeros(m, np.float64)
    for i in range(n):
        size[comp[i]] += 1
        sum_u[comp[i]] += us[i]
    return comp, size, sum_u

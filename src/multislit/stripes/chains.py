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


def lex_order(minor: ArrayLike, major: ArrayLike) -> NDArray[np.intp]:
    """``np.lexsort((minor, major))``: the stable order by ``major``, then ``minor``.

    One stable sort of the key ``major * span + minor`` (``span`` wider than ``minor``'s
    range), which on points that come nearly in order (the centres row by row, a few others
    after them) is a pass or two, where lexsort sorts each float key in full. Where two
    different points share a key (``minor`` closer than the key's rounding), lexsort itself.

    Parameters
    ----------
    minor : (K,) float, finite
    major : (K,) float, finite whole numbers (rows, columns)

    Returns
    -------
    (K,) intp, the order
    """
    mi = np.asarray(minor, np.float64)
    ma = np.asarray(major, np.float64)
    if mi.size < 2:
        return np.arange(mi.size, dtype=np.intp)
    lo = float(mi.min())
    span = float(mi.max()) - lo + 1.0
    key = (ma - float(ma.min())) * span + (mi - lo)
    order = np.argsort(key, kind="stable")
    k, m = key[order], mi[order]
    if bool(np.all((k[1:] > k[:-1]) | (m[1:] == m[:-1]))):
        return order
    return np.lexsort((mi, ma))


def link_segments(
    u: ArrayLike,
    v: ArrayLike,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
    slope: ArrayLike | None = None,
) -> I64:
    """Chain centre points of consecutive rows into segments continuous along v.

    A point p in row v is linked to a point q in the first row v + g (g = 1 .. max_gap + 1)
    that has any point within ``max_du * g`` px of p's column, if q is the only such point
    there and p is likewise the only candidate in q's first non-empty row above. Ambiguities
    (two candidates), jumps and longer gaps break the chain. With ``slope``, each point's
    windows lie along its stripe's lean instead: around its column plus (below) or minus
    (above) ``slope * g``. One sort and a compiled linear pass (the windows move along the
    sorted points).

    Parameters
    ----------
    u, v : (K,) centre columns and rows (px); v is rounded to integer rows
    max_du : largest column change per row (px) within a segment, from the column the
        stripe's lean predicts
    max_gap : largest number of missing rows bridged
    min_length : segments with fewer points get label -1
    slope : (K,) float, px per row, the stripe's lean du/dv at each point; default 0 (the
        windows straight above and below)

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
        order = lex_order(uu, rows)
    us = uu[order] - uu.min()
    rs = rows[order] - rows.min()
    max_g = int(max_gap) + 1
    if slope is None:
        shift = np.zeros(n)
    else:
        shift = np.asarray(slope, dtype=np.float64)
        if shift.shape != uu.shape or not np.isfinite(shift).all():
            raise SlitExtractionError(f"slope must be finite, of shape {uu.shape}")
        shift = shift[order]
    # key = row * span + u is sorted; span exceeds the u range plus the search tolerance and
    # the windows' shift, so a search window never spills into another row
    reach = 2 * (max_du + float(np.abs(shift).max(initial=0.0))) * max_g
    span = float(us.max()) + reach + 2.0
    key = rs * span + us
    comp, size, sum_u = _chains(key, us, shift, span, float(max_du), max_g)
    keep = size >= min_length
    mean_u = sum_u / size
    kept = np.flatnonzero(keep)
    new_id = np.full(size.size, -1, np.int64)
    new_id[kept[np.argsort(mean_u[kept], kind="stable")]] = np.arange(kept.size)
    labels = np.empty(n, np.int64)
    labels[order] = new_id[comp]
    return labels


@njit(cache=True)
def _first_neighbour(key, lean, span, max_du, max_g, sign):
    """Per point of the sorted ``key`` (K,): index of the unique point within ``max_du * g``
    px of its column plus ``sign * lean * g`` (``lean`` (K,) px per row) in the first row
    g = 1 .. ``max_g`` away (``sign`` +1 below, -1 above) that has any, -1 if none, -2 if
    ambiguous. The windows move along the sorted key (back a little where the lean changes),
    so two pointers per g replace the binary searches (the same comparisons); a point's rows
    are searched nearest first, and no further than the first with a candidate (a pointer
    left behind catches up when its row is searched again)."""
    n = key.size
    found = np.full(n, -1, np.int64)
    los = np.zeros(max_g + 1, np.int64)
    his = np.zeros(max_g + 1, np.int64)
    for i in range(n):
        for g in range(1, max_g + 1):
            tol = max_du * g
            centre = key[i] + float(sign * g) * span + sign * g * lean[i]
            a = centre - tol
            b = centre + tol
            lo = los[g]
            hi = his[g]
            while lo > 0 and key[lo - 1] >= a:
                lo -= 1
            while lo < n and key[lo] < a:  # searchsorted(key, a, "left")
                lo += 1
            if hi < lo:
                hi = lo
            while hi > lo and key[hi - 1] > b:
                hi -= 1
            while hi < n and key[hi] <= b:  # searchsorted(key, b, "right")
                hi += 1
            los[g] = lo
            his[g] = hi
            if hi > lo:
                found[i] = lo if hi - lo == 1 else -2
                break
    return found


@njit(cache=True)
def _chains(key, us, lean, span, max_du, max_g):
    """Chain the points of the sorted ``key`` (K,): a point and the first candidate below it
    are linked where each is the other's unique candidate (:func:`link_segments`). Returns
    each point's chain (K,) int64, numbered in the order of the chains' first points, and
    each chain's size and sum of ``us`` (summed in point order)."""
    n = key.size
    nxt = _first_neighbour(key, lean, span, max_du, max_g, 1)
    prv = _first_neighbour(key, lean, span, max_du, max_g, -1)
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


#: A segment of weak centres only (found by the ridge response alone) is kept where it holds
#: at least this many times ``min_length`` points: dots that happen to lie one above another
#: make short faint streaks; a faint stripe runs on.
WEAK_LENGTH_FACTOR = 2

#: A run of weak centres at the end of a segment with strong ones is kept where it holds at
#: least this many times ``min_length`` points: the response's smoothing along the stripe
#: reaches a few rows past a bright stripe's end, and a dot's refill can leave a faint tail
#: below one (:data:`WEAK_GAP_FRACTION` drops those much fainter than the stripe).
WEAK_TAIL_FACTOR = 1


#: A weak centre between strong ones whose peak is below this fraction of theirs is no part of
#: their stripe (:func:`settle_weak`).
WEAK_GAP_FRACTION = 0.4


def drop_short(segment: I64, min_length: int) -> I64:
    """``segment`` (K,) int64 with -1 for the segments of fewer than ``min_length`` points."""
    lk = segment >= 0
    if not lk.any():
        return segment
    count = np.bincount(segment[lk])
    return np.where(lk & (count[np.maximum(segment, 0)] >= min_length), segment, -1)


def settle_weak(
    along: NDArray[np.float64],
    segment: I64,
    strong: NDArray[np.bool_],
    min_length: int,
    weak_length: int | None = None,
    peak: NDArray[np.float64] | None = None,
) -> I64:
    """The segments of linked centres some of which are weak (found by the ridge response
    alone, :func:`~multislit.stripes.centres.find_ridge_centres_validated`).

    In each segment, the weak centres before its first strong one and after its last are
    dropped where they are fewer than :data:`WEAK_TAIL_FACTOR` times ``min_length`` (weak
    centres between strong ones stay: the stripe runs on across them); a segment without a
    strong centre is dropped where it is shorter than ``weak_length``. The segments left
    with fewer than ``min_length`` points are dropped too. With ``peak``, a weak centre is
    dropped where its peak is below :data:`WEAK_GAP_FRACTION` times that of the strong ones
    next to it in its segment (the lower of the two between strong ones): there the stripe
    is gone (a shadow, a gap between two surfaces, its end), and the response's smoothing
    along the stripe reaches on.

    Parameters
    ----------
    along : (K,) float64, px, the centres' position along their segments (v for the rows)
    segment : (K,) int64, segment id (-1: unlinked), e.g. :func:`link_segments` with
        ``min_length`` 1
    strong : (K,) bool
    min_length : int
    weak_length : int, default :data:`WEAK_LENGTH_FACTOR` times ``min_length``
    peak : (K,) float64, the centres' peaks (intensity units), or None

    Returns
    -------
    (K,) int64, segment ids (-1: dropped or unlinked; ids are not renumbered)
    """
    lk = np.flatnonzero(segment >= 0)
    if lk.size == 0:
        return segment
    order = lk[np.lexsort((along[lk], segment[lk]))]
    if weak_length is None:
        weak_length = WEAK_LENGTH_FACTOR * int(min_length)
    tail = WEAK_TAIL_FACTOR * int(min_length)
    p = np.zeros(0) if peak is None else np.asarray(peak, np.float64)[order]
    drop = _weak_drops(segment[order], strong[order], p, tail, int(weak_length))
    out = segment.copy()
    out[order[drop]] = -1
    return drop_short(out, min_length)


@njit(cache=True, inline="always")
def run_end(seg, lo):
    """The end of the run of equal values of ``seg`` (K,) that starts at ``lo``."""
    hi = lo + 1
    while hi < seg.size and seg[hi] == seg[lo]:
        hi += 1
    return hi


@njit(cache=True)
def _weak_drops(seg, strong, peak, tail, weak_length):
    """:func:`settle_weak`'s drops along the points sorted by segment and position (``seg``,
    ``strong`` (K,); ``peak`` (K,) float64 or (0,) for none): (K,) bool. One pass per
    segment: its first and last strong points; the weak runs before the first and after the
    last shorter than ``tail``; a segment without strong points shorter than
    ``weak_length``; with peaks, the weak points below :data:`WEAK_GAP_FRACTION` of the
    strong ones next to them (the lower of the two between strong ones)."""
    n = seg.size
    drop = np.zeros(n, np.bool_)
    nxt = np.empty(n, np.int64)
    lo = 0
    while lo < n:
        hi = run_end(seg, lo)
        first = -1
        last = -1
        for q in range(lo, hi):
            if strong[q]:
                if first < 0:
                    first = q
                last = q
        if last < 0:
            if hi - lo < weak_length:
                drop[lo:hi] = True
            lo = hi
            continue
        if first - lo < tail:
            drop[lo:first] = True
        if hi - 1 - last < tail:
            drop[last + 1 : hi] = True
        if peak.size:
            after = -1
            for q in range(hi - 1, lo - 1, -1):  # the next strong point at or after each
                if strong[q]:
                    after = q
                nxt[q] = after
            before = -1
            for q in range(lo, hi):
                if strong[q]:
                    before = q
                    continue
                pb = peak[before] if before >= 0 else np.inf
                pa = peak[nxt[q]] if nxt[q] >= 0 else np.inf
                flank = np.nan if pb != pb or pa != pa else min(pb, pa)
                if peak[q] < WEAK_GAP_FRACTION * flank:
                    drop[q] = True
        lo = hi
    return drop


def link_weak(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    strong: NDArray[np.bool_],
    slope: NDArray[np.float64] | None,
    peak: NDArray[np.float64] | None,
    max_du: float,
    max_gap: int,
    min_length: int,
) -> I64:
    """:func:`link_segments` (along the stripes' ``slope``) of centres some of which are
    weak, settled by :func:`settle_weak`; where that drops weak centres next to strong ones,
    the rest is linked and settled again (the stripe is cut there). With every centre strong,
    :func:`link_segments` itself.

    Parameters
    ----------
    u, v : (K,) float64, px, the centres (v whole rows)
    strong : (K,) bool
    slope : (K,) float64, px per row, the stripes' lean at the centres, or None (upright)
    peak : (K,) float64, the centres' peaks (intensity units), or None
    max_du, max_gap, min_length : see :func:`link_segments`

    Returns
    -------
    (K,) int64, segment ids (-1: none)
    """
    if strong.all():
        return link_segments(u, v, max_du, max_gap, min_length, slope)
    vv = np.asarray(v, np.float64)
    seg = link_segments(u, v, max_du, max_gap, 1, slope)
    settled = settle_weak(vv, seg, strong, min_length, peak=peak)
    cut = (seg >= 0) & (settled < 0) & ~strong
    if peak is None or not cut.any():
        return settled
    keep = ~cut
    sl = None if slope is None else np.asarray(slope)[keep]
    again = link_segments(np.asarray(u)[keep], vv[keep], max_du, max_gap, 1, sl)
    out = np.full(vv.size, -1, np.int64)
    out[keep] = settle_weak(vv[keep], again, strong[keep], min_length)
    return out

"""Stripe pieces: the extraction's segments in windows, cut where the dots change their slit.

A segment of the extraction (:func:`~multislit.stripes.link_segments`) is one run of stripe
centres, but the linking may join two slits' stripes where they meet (at an object's edge a
stripe on the object continues a stripe on the wall). Identification works on **windows** of a
segment's points (:func:`windows`), scores every slit for each window
(:mod:`~multislit.identify.evidence`); the frame's labelling (:mod:`~multislit.identify.graph`)
gives each window a slit, and a segment's **pieces** are its runs of windows with one slit.
Two pieces side by side across their stripes form a **gap** (:func:`gaps_across`: along the
rows, and along the columns for stripes found along the columns), whose dots say whether they
are neighbouring slits of one surface.

Units: px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit._groups import group_medians
from multislit.stripes.chains import lex_order

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Windows:
    """The linked stripe points in windows of consecutive points along their stripe, segment
    by segment.

    Attributes
    ----------
    order : (P,) int64, point indices (into the extraction), by segment, then along the stripe
    start : (W+1,) int64, window w holds ``order[start[w]:start[w+1]]``
    segment : (W,) int64, the segment of each window
    piece : (W,) int64, the piece of each window (numbered from 0)
    """

    order: I64
    start: I64
    segment: I64
    piece: I64

    @property
    def num_windows(self) -> int:
        return len(self.segment)

    @property
    def num_pieces(self) -> int:
        return int(self.piece.max()) + 1 if len(self.piece) else 0

    def piece_of_points(self, num_points: int) -> I64:
        """(K,) int64: the piece of every point (-1: in no window)."""
        out = np.full(num_points, -1, np.int64)
        counts = np.diff(self.start)
        out[self.order] = np.repeat(self.piece, counts)
        return out


def _within_runs(n: I64) -> I64:
    """(sum(n),) int64: each item's place within its run, for runs of ``n`` (R,) items laid
    one after the other (0 .. n[0] - 1, then 0 .. n[1] - 1, ...)."""
    return np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)


def windows(segment: I64, along: F64, rows: int) -> Windows:
    """The linked points (``segment >= 0``) in windows of about ``rows`` points each: a
    segment of n points gets ``max(1, round(n / rows))`` windows of nearly equal size.

    Parameters
    ----------
    segment : (K,) int64, segment id per point (-1: unlinked)
    along : (K,) float64, px, the points' positions along their stripe (their rows; their
        columns for stripes found along the columns)
    rows : int, the windows' target length (points)
    """
    lk = np.flatnonzero(segment >= 0)
    lk = lk[np.lexsort((along[lk], segment[lk]))]
    seg = segment[lk]
    if lk.size == 0:
        e = np.zeros(0, np.int64)
        return Windows(e, np.zeros(1, np.int64), e.copy(), e.copy())
    bounds = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1], True])
    n = np.diff(bounds)
    nwin = np.maximum(1, np.rint(n / max(1, rows)).astype(np.int64))
    # window j of a segment of n points with m windows ends at round(n (j + 1) / m)
    seg_of_win = np.repeat(np.arange(len(n)), nwin)
    j = _within_runs(nwin)
    ends = bounds[seg_of_win] + np.rint(n[seg_of_win] * (j + 1) / nwin[seg_of_win]).astype(np.int64)
    start = np.r_[0, ends].astype(np.int64)
    return Windows(lk.astype(np.int64), start, seg[bounds[:-1]][seg_of_win], seg_of_win)


@dataclass(frozen=True, eq=False)
class Gaps:
    """Pairs of pieces side by side across their stripes: a on the lower slit's side (the left
    in a row), b next to it (no stripe centre between them), in the rows (columns) they
    share.

    Attributes
    ----------
    a, b : (G,) int64, the pieces
    a_order, a_start : gap g's left piece has the points ``a_order[a_start[g]:a_start[g+1]]``
        (in the shared rows, by row)
    b_order, b_start : the same for the right piece
    spacing_ratio : (G,) float64, the gap's width over the mean width of the gaps beside it
        in the row (median over its rows; NaN where no gap is beside it): near 1 on a smooth
        surface, off where a stripe of another surface lies between two of the wall's
    """

    a: I64
    b: I64
    a_order: I64
    a_start: I64
    b_order: I64
    b_start: I64
    spacing_ratio: F64

    @property
    def num_gaps(self) -> int:
        return len(self.a)

    @property
    def rows(self) -> I64:
        """(G,) int64: the rows each gap's pieces share."""
        return np.diff(self.a_start)


def gaps(u: F64, v: F64, piece: I64, max_gap_px: float, min_rows: int) -> Gaps:
    """The gaps between pieces side by side in the rows.

    Parameters
    ----------
    u, v : (K,) float64, px, the points
    piece : (K,) int64, the piece of each point (-1: none)
    max_gap_px : px, pieces farther apart in a row are not neighbours there
    min_rows : a pair sharing fewer rows is not a gap
    """
    lk = np.flatnonzero(piece >= 0)
    r = np.rint(v[lk]).astype(np.int64)
    o = lex_order(u[lk], r)
    lk, r = lk[o], r[o]
    # the pairs of neighbouring points of two pieces in a row (a piece of a stripe leaning
    # towards the horizontal holds a run of points in a row: its inner pairs are no gap)
    pair = np.flatnonzero((r[1:] == r[:-1]) & (piece[lk[1:]] != piece[lk[:-1]]))
    a, b, row = lk[pair], lk[pair + 1], r[pair]
    # each pair's width, and the widths of the gaps beside it in the row (NaN: none)
    width = u[b] - u[a]
    same = row[1:] == row[:-1]
    before = np.r_[np.nan, np.where(same, width[:-1], np.nan)]
    after = np.r_[np.where(same, width[1:], np.nan), np.nan]
    keep = width < max_gap_px
    a, b, width, before, after = a[keep], b[keep], width[keep], before[keep], after[keep]
    if a.size == 0:
        e = np.zeros(0, np.int64)
        return Gaps(
            e,
            e.copy(),
            e.copy(),
            np.zeros(1, np.int64),
            e.copy(),
            np.zeros(1, np.int64),
            np.zeros(0),
        )
    n_beside = np.isfinite(before).astype(float) + np.isfinite(after)
    total = np.nan_to_num(before) + np.nan_to_num(after)
    beside = np.where(n_beside > 0, total / np.maximum(n_beside, 1.0), np.nan)
    key = piece[a] * (int(piece.max()) + 1) + piece[b]
    o = np.lexsort((v[a], key))
    a, b, key = a[o], b[o], key[o]
    ratio = (width / beside)[o]
    bounds = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    n = np.diff(bounds)
    ok = n >= min_rows
    sel = np.repeat(ok, n)
    start = np.r_[0, np.cumsum(n[ok])].astype(np.int64)
    # per gap, the median ratio of its width to the widths beside it (NaN: none beside)
    with np.errstate(divide="ignore"):  # a zero width (two pieces crossing): no ratio
        log_ratio = np.log(ratio)
    med = group_medians(log_ratio, np.repeat(np.arange(len(n)), n), len(n))
    return Gaps(
        piece[a[bounds[:-1][ok]]],
        piece[b[bounds[:-1][ok]]],
        a[sel].astype(np.int64),
        start,
        b[sel].astype(np.int64),
        start.copy(),
        np.exp(med[ok]),
    )


def gaps_across(
    u: F64,
    v: F64,
    piece: I64,
    by_column: NDArray[np.bool_],
    angle: F64,
    max_gap_px: float,
    min_rows: int,
) -> Gaps:
    """The gaps between pieces side by side across their stripes: along the rows
    (:func:`gaps`), and along the columns between the pieces found along the columns
    (stripes leaning towards the horizontal, ``by_column``). A gap along a column is given
    with the piece on the lower slit's side first: the side a stripe's left side turns to as it
    leans from the vertical (below for a stripe leaning right going down, ``angle`` > 0;
    above for one leaning left).

    Parameters
    ----------
    u, v : (K,) float64, px, the points
    piece : (K,) int64, the piece of each point (-1: none)
    by_column : (K,) bool, the point was found along its column
    angle : (K,) float64, rad, the stripe's direction at the point from the image's vertical
    max_gap_px : px, pieces farther apart in a row (a column) are not neighbours there
    min_rows : a pair sharing fewer rows (columns) is not a gap
    """
    rows = gaps(u, v, piece, max_gap_px, min_rows)
    if not by_column.any():
        return rows
    cols = gaps(v, u, np.where(by_column, piece, -1), max_gap_px, min_rows)
    # the piece above comes first; where the stripe leans right going down (its left side
    # turned downwards), the lower slit's side is below: the pair turns round
    n = np.diff(cols.a_start)
    lean = group_medians(angle[cols.a_order], np.repeat(np.arange(len(n)), n), len(n))
    turn = lean > 0
    a = np.where(turn, cols.b, cols.a)
    b = np.where(turn, cols.a, cols.b)
    turn_pts = np.repeat(turn, n)
    a_order = np.where(turn_pts, cols.b_order, cols.a_order)
    b_order = np.where(turn_pts, cols.a_order, cols.b_order)
    off = rows.a_start[-1]
    return Gaps(
        np.r_[rows.a, a],
        np.r_[rows.b, b],
        np.r_[rows.a_order, a_order],
        np.r_[rows.a_start, cols.a_start[1:] + off],
        np.r_[rows.b_order, b_order],
        np.r_[rows.b_start, cols.b_start[1:] + off],
        np.r_[rows.spacing_ratio, cols.spacing_ratio],
    )


def continuations(u: F64, v: F64, piece: I64, max_rows: int, max_du: float) -> tuple[I64, I64]:
    """Pairs of pieces where one stripe continues another below it: piece b's first point lies
    at most ``max_rows`` rows below piece a's last and within ``max_du`` px (plus half a px a
    row) of its column. Returns (a, b), each (C,) int64."""
    lk = np.flatnonzero(piece >= 0)
    if lk.size == 0:
        e = np.zeros(0, np.int64)
        return e, e.copy()
    o = np.lexsort((v[lk], piece[lk]))
    lk = lk[o]
    p = piece[lk]
    bounds = np.flatnonzero(np.r_[True, p[1:] != p[:-1], True])
    first, last = lk[bounds[:-1]], lk[bounds[1:] - 1]
    ids = p[bounds[:-1]]
    # candidates: every first point within max_rows below each last point
    fo = np.argsort(v[first], kind="stable")
    fv = v[first][fo]
    lo = np.searchsorted(fv, v[last], side="right")
    hi = np.searchsorted(fv, v[last] + max_rows, side="right")
    # every (last point i, candidate first point c) pair, i in order, c in fo's order
    n = hi - lo
    i = np.repeat(np.arange(len(last)), n)
    c = fo[np.repeat(lo, n) + _within_runs(n)]
    e = last[i]
    dv = v[first[c]] - v[e]
    ok = (np.abs(u[first[c]] - u[e]) <= max_du + 0.5 * dv) & (ids[c] != ids[i])
    return ids[i[ok]].astype(np.int64), ids[c[ok]].astype(np.int64)


@njit(cache=True)
def _kink_steps(u, v, start, window, out):
    """Per point of runs ``start[i]:start[i+1]`` of (u, v) (by v): how far apart, at the
    point, the lines fitted to the ``window`` points before it and from it on put the stripe
    (px); 0 where a side has fewer points."""
    for r in range(len(start) - 1):
        a, b = start[r], start[r + 1]
        for i in range(a + window, b - window + 1):
            # least-squares lines u = p + q (v - v_i) on each side
            x0 = v[i]
            s0 = s1 = s2 = t0 = t1 = 0.0
            for j in range(i - window, i):
                d = v[j] - x0
                s0 += 1.0
                s1 += d
                s2 += d * d
                t0 += u[j]
                t1 += u[j] * d
            den = s0 * s2 - s1 * s1
            pb = (t0 * s2 - t1 * s1) / den if den > 1e-9 else t0 / s0
            s0 = s1 = s2 = t0 = t1 = 0.0
            for j in range(i, i + window):
                d = v[j] - x0
                s0 += 1.0
                s1 += d
                s2 += d * d
                t0 += u[j]
                t1 += u[j] * d
            den = s0 * s2 - s1 * s1
            pa = (t0 * s2 - t1 * s1) / den if den > 1e-9 else t0 / s0
            out[i] = abs(pa - pb)


def split_at_kinks(segment: I64, u: F64, v: F64, window: int, max_step_px: float) -> I64:
    """Cut segments where the stripe steps sideways: the lines fitted to the ``window`` points
    before a point and from it on put the stripe more than ``max_step_px`` apart there (where a
    stripe runs into another slit's stripe, the linking may have joined them across a small
    step). Each cut is at the largest step, ``window`` points clear of the next.

    Returns
    -------
    (K,) int64, new segment ids (new pieces get ids after the largest one)
    """
    seg = segment.copy()
    lk = np.flatnonzero(seg >= 0)
    if lk.size < 2 * window + 1:
        return seg
    lk = lk[np.lexsort((v[lk], seg[lk]))]
    s = seg[lk]
    start = np.flatnonzero(np.r_[True, s[1:] != s[:-1], True]).astype(np.int64)
    step = np.zeros(len(lk))
    _kink_steps(u[lk].astype(np.float64), v[lk].astype(np.float64), start, int(window), step)
    nxt = int(seg.max()) + 1
    for a, b in zip(start[:-1], start[1:], strict=True):
        st = step[a:b].copy()
        cuts = []
        while st.size and st.max() > max_step_px:
            j = int(np.argmax(st))
            cuts.append(j)
            st[max(0, j - window) : j + window] = 0.0
        for c in sorted(cuts):
            seg[lk[a + c : b][seg[lk[a + c : b]] == s[a]]] = nxt
            nxt += 1
    return seg

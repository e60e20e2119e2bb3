"""Stripe segments of a scan: their points in order, sample points, ends and splits.

A segment is a piece of one stripe linked by the extraction
(:func:`~multislit.stripes.link_segments`); the identification labels whole segments, after
splitting those that join two slits' stripes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Keys up to this many times the number of items (plus a constant) are grouped by counting;
#: sparser keys by a comparison sort.
_DENSE_KEYS = 4


@njit(cache=True)
def _counting_order(key, pre, n_keys):
    """The items ``pre`` with ``key >= 0``, stably ordered by ``key`` (0 .. ``n_keys`` - 1)."""
    count = np.zeros(n_keys + 1, np.int64)
    for i in pre:
        if key[i] >= 0:
            count[key[i] + 1] += 1
    for k in range(n_keys):
        count[k + 1] += count[k]
    out = np.empty(count[n_keys], np.intp)
    for i in pre:
        k = key[i]
        if k >= 0:
            out[count[k]] = i
            count[k] += 1
    return out


def group_order(key: NDArray[np.integer], pre: NDArray[np.intp] | None = None) -> NDArray[np.intp]:
    """The items with ``key >= 0``, stably ordered by their key.

    Parameters
    ----------
    key : (K,) int, group id per item (-1 or below: the item is left out)
    pre : (K,) intp, the items in a prior order (a permutation of 0..K-1) that ties keep;
        default: 0..K-1

    Returns
    -------
    (K',) intp, item indices: ``pre[key[pre] >= 0]`` stably sorted by key (a counting sort)
    """
    key = np.asarray(key)
    if pre is None:
        pre = np.arange(len(key))
    if len(key) == 0:
        return np.zeros(0, np.intp)
    n_keys = int(key.max()) + 1
    if n_keys > _DENSE_KEYS * len(key) + 1024:  # sparse ids: a comparison sort
        sel = pre[key[pre] >= 0]
        return sel[np.argsort(key[sel], kind="stable")].astype(np.intp)
    return _counting_order(key.astype(np.int64), pre.astype(np.intp), n_keys)


def by_segment(seg: I64, v: F64) -> NDArray[np.intp]:
    """The linked points (``seg >= 0``) ordered by (segment, v, index): (K',) intp, the same
    as ``idx[np.lexsort((v[idx], seg[idx]))]`` for ``idx = np.flatnonzero(seg >= 0)``."""
    return group_order(seg, np.argsort(v, kind="stable"))


def segment_runs(seg: I64, v: F64) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The linked points ordered by (segment, v), and for each of them the positions (in that
    order) of its segment's first and last point: ``order, first, last``, each (K',)."""
    order = by_segment(seg, v)
    pos = np.arange(len(order))
    if order.size == 0:
        return order, pos, pos
    s = seg[order]
    starts = np.r_[True, s[1:] != s[:-1]]
    ends = np.r_[s[1:] != s[:-1], True]
    first = np.maximum.accumulate(np.where(starts, pos, 0))
    # the last point of each run, propagated backwards
    last = np.minimum.accumulate(np.where(ends, pos, len(order))[::-1])[::-1]
    return order, first, last


def _sampled_runs(
    seg: I64, v: F64, step_px: float
) -> tuple[NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
    """The linked points ordered by (segment, v) (:func:`segment_runs`), and per point in that
    order whether it is a sample point (the first of its segment's ``step_px``-high bucket,
    buckets counted from the segment's first row) and whether it is its segment's last point."""
    order, first, last = segment_runs(seg, v)
    pos = np.arange(len(order))
    if order.size == 0:
        return order, pos > 0, pos > 0
    s = seg[order]
    rel = v[order] - v[order][first]
    bucket = np.floor(rel / step_px + 0.5).astype(np.int64)
    # keep the first point of each (segment, bucket)
    key = s.astype(np.int64) * 1_000_000 + bucket
    keep = np.r_[True, key[1:] != key[:-1]]
    return order, keep, last == pos


def _sample_points(seg: I64, v: F64, step_px: float) -> NDArray[np.intp]:
    """Indices of points spaced about ``step_px`` rows apart along each segment."""
    order, keep, _ = _sampled_runs(seg, v, step_px)
    return order[keep]


def band_samples(seg: I64, v: F64, step_px: float, lo: float, hi: float) -> NDArray[np.intp]:
    """Sample points (:func:`_sample_points`) only in the rows ``lo <= v <= hi``.

    A template centred outside the band would be cut by the image's top or bottom: partly
    empty rows, which say little. Each segment's sampling starts at its first row in the band,
    and a segment that runs on below the band also gets its last row in the band, so the rows
    between the band and the image edge lie within a template's half height of a sample.
    The samples are ordered by segment, then row.
    """
    inside = (v >= lo) & (v <= hi)
    order, keep, last = _sampled_runs(np.where(inside, seg, -1), v, step_px)
    below = (seg >= 0) & (v > hi)
    if order.size == 0 or not below.any():
        return order[keep]
    # the last row in the band of each segment that runs on below it
    runs_below = np.zeros(int(seg.max()) + 1, bool)
    runs_below[seg[below]] = True
    return order[keep | (last & runs_below[seg[order]])]


def near_segment_ends(
    u: F64, v: F64, seg: I64, label: I64, trim: int, junction: int
) -> NDArray[np.bool_]:
    """(K,) bool: points within ``trim`` rows of their segment's first or last row, or within
    ``junction`` rows of an end that meets the end of a segment of another slit (within 3 rows
    and 3 px; ``label`` (S,) is each segment's slit, -1 if none).

    Where a stripe runs into another slit's stripe on another surface (an occlusion edge), the
    split between the two segments is placed from sampled evidence (brightness medians, sample
    winners) and can be off by a few samples: the rows next to such a junction may belong to
    the other stripe, so more of them are left out than at a free end.
    """
    out = np.zeros(len(seg), bool)
    o, fi, li = segment_runs(seg, v)
    if o.size == 0:
        return out
    sg = seg[o]
    pos = np.arange(len(o))
    ends = np.r_[pos[fi == pos], pos[li == pos]]  # positions in o of first and last points
    pts = np.c_[u[o[ends]], v[o[ends]]]
    joined = np.zeros(len(o), bool)  # per position in o: is this end a junction
    if len(ends) > 1:
        from scipy.spatial import cKDTree

        pairs = cKDTree(pts).query_pairs(3.0 * math.sqrt(2.0), output_type="ndarray")
        if len(pairs):
            a, b = ends[pairs[:, 0]], ends[pairs[:, 1]]
            la, lb = label[sg[a]], label[sg[b]]
            close = (la >= 0) & (lb >= 0) & (la != lb)
            close &= (np.abs(pts[pairs[:, 0]] - pts[pairs[:, 1]]) <= 3.0).all(1)
            joined[a[close]] = True
            joined[b[close]] = True
    rows_first = np.where(joined[fi], junction, trim)
    rows_last = np.where(joined[li], junction, trim)
    vv = v[o]
    out[o] = (vv - vv[fi] < rows_first) | (vv[li] - vv < rows_last)
    return out


@njit(cache=True)
def _rolling_median(x, window):
    """(len(x) - ``window`` + 1,) float64: the median of ``x[i : i + window]`` at i (NaN where
    one of them is NaN), as ``np.median`` gives it."""
    n = max(len(x) - window + 1, 0)
    out = np.empty(n)
    buf = np.empty(window)
    h = window // 2
    for i in range(n):
        nan = False
        for j in range(window):
            a = x[i + j]
            nan |= np.isnan(a)
            # insertion into the sorted buf[:j]
            k = j
            while k > 0 and buf[k - 1] > a:
                buf[k] = buf[k - 1]
                k -= 1
            buf[k] = a
        if nan:
            out[i] = np.nan
        elif window % 2:
            out[i] = buf[h]
        else:
            out[i] = (buf[h - 1] + buf[h]) / 2.0
    return out


@njit(cache=True)
def _brightness_steps(logp, s_o, window):
    """Per point i of the points by (segment, v) (segment ids ``s_o``), the step of the log
    brightness ``logp`` from the median of points i .. i + w - 1 to that of the next ``w``
    (``w`` = ``window``): (K - 2w + 1,) float64, 0 where the 2w points leave the segment or
    the segment has fewer than 2w + 2 points."""
    med = _rolling_median(logp, window)  # med[i] = points i .. i + w - 1
    n = max(len(med) - window, 0)
    out = np.zeros(n)
    start = end = 0  # the segment of point g: points start .. end - 1
    for g in range(n):
        if g >= end:
            start, end = g, g + 1
            while end < len(s_o) and s_o[end] == s_o[g]:
                end += 1
        if g + 2 * window <= end and end - start >= 2 * window + 2:
            out[g] = abs(med[g + window] - med[g])
    return out


def split_at_brightness_steps(
    seg: I64, v: F64, peak: F64, ratio: float = 1.6, window: int = 6
) -> I64:
    """Split segments where the stripe's brightness steps abruptly along v.

    Where a stripe on one surface runs into another slit's stripe on a surface at another depth
    (or albedo), linking can join them; the peak brightness then changes by a large factor from
    one side of the junction to the other, while along one surface it changes slowly. The split
    is placed where the median brightness of the ``window`` rows before and after differ most,
    if they differ by more than ``ratio``.
    """
    seg = seg.copy()
    next_id = int(seg.max()) + 1 if seg.size else 0
    idx = np.flatnonzero(seg >= 0)
    if idx.size < 2 * window + 2:
        return seg
    # all segments at once: points by (segment, v); rolling medians of log brightness
    order = by_segment(seg, v)
    s_o = seg[order]
    logp = peak[order].astype(np.float64)
    np.log(np.maximum(logp, 1e-3, out=logp), out=logp)
    step_all = _brightness_steps(logp, s_o, window)
    candidates = np.unique(s_o[: len(step_all)][step_all > np.log(ratio)])
    a = np.searchsorted(s_o, candidates, side="left")
    b = np.searchsorted(s_o, candidates, side="right")
    _cut_at_steps(seg, order, step_all, a, b, window, float(np.log(ratio)), next_id)
    return seg


@njit(cache=True)
def _cut_at_steps(seg, order, step, a, b, window, log_ratio, next_id):
    """In place on ``seg``: the cuts of :func:`split_at_brightness_steps` in the segments whose
    points are ``order[a[i] : b[i]]`` (by v), from ``step`` (the brightness step at each
    point, in the order ``order``): repeatedly at the largest step above ``log_ratio`` (the
    first of equal ones; none where a step is NaN), clearing ``window`` points either side;
    each cut gives the rest of its piece the next new id from ``next_id``."""
    for i in range(len(a)):
        pts = order[a[i] : b[i]]
        st = step[a[i] : b[i] - 2 * window + 1].copy()  # this segment's own steps
        cuts = np.empty(len(st), np.int64)
        n_cuts = 0
        while len(st):
            j = 0
            nan = False
            for t in range(len(st)):
                nan |= np.isnan(st[t])
                if st[t] > st[j]:
                    j = t
            if nan or not st[j] > log_ratio:
                break
            cuts[n_cuts] = j + window  # first point of the new piece
            n_cuts += 1
            st[max(0, j - window) : min(len(st), j + window + 1)] = 0.0
        for c in np.sort(cuts[:n_cuts]):
            old = seg[pts[c]]
            for t in range(c, len(pts)):
                if seg[pts[t]] == old:
                    seg[pts[t]] = next_id
            next_id += 1


#: A sample clearly prefers its best slit when that slit's NCC leads the second best by this.
WINNER_LEAD = 0.1


def clear_winners(scores: F64, min_score: float) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Each sample's best slit, and whether the sample clearly prefers it.

    Parameters
    ----------
    scores : (M, N) float64, NCC per sample and slit (NaN: no candidate)
    min_score : the best NCC must reach this ...

    Returns
    -------
    win : (M,) intp, the best slit
    clear : (M,) bool, the best NCC reaches ``min_score`` and leads the second best by
        :data:`WINNER_LEAD`
    """
    win, best, second = _top_two(np.ascontiguousarray(scores, dtype=np.float64))
    return win, (best >= min_score) & (best - second >= WINNER_LEAD)


@njit(cache=True)
def _top_two(scores):
    """Per row of ``scores`` (M, N), NaN and infinities counting -1: the first column with the
    largest value, that value and the second largest (the largest again if it occurs twice;
    -1 for one column)."""
    m, n = scores.shape
    win = np.zeros(m, np.intp)
    best = np.empty(m)
    second = np.empty(m)
    for i in range(m):
        b1 = b2 = -np.inf
        k = 0
        for j in range(n):
            x = scores[i, j]
            if not np.isfinite(x):
                x = -1.0
            if x > b1:
                b1, b2, k = x, b1, j
            elif x > b2:
                b2 = x
        win[i], best[i], second[i] = k, b1, -1.0 if n == 1 else b2
    return win, best, second


def split_at_winner_changes(
    seg: I64, v: F64, si: NDArray[np.intp], scores: F64, min_score: float
) -> I64:
    """Split segments whose samples clearly change winner along v (two slits linked by chance).

    A stripe on a near surface can run into another slit's stripe on a far surface at the same
    image column; linking then joins them. Along such a segment the per-sample best slit changes
    from one run of samples to another: each run of >= 2 confident samples becomes a segment.

    Parameters
    ----------
    seg : (K,) int64, segment id per point (-1: none)
    v : (K,) float64, px, rows of the points
    si : (M,) intp, the sample points (indices into the points)
    scores : (M, N) float64, NCC per sample and slit (NaN: no candidate)
    min_score : a sample is confident if its best score reaches this and leads the second
        best by :data:`WINNER_LEAD` (:func:`clear_winners`)

    Returns
    -------
    seg : (K,) int64, the segment ids, new ids for the split-off pieces
    """
    seg = seg.copy()
    if len(si) == 0:
        return seg
    win, strong = clear_winners(scores, min_score)
    next_id = int(seg.max()) + 1
    ss = seg[si]
    # only segments with >= 4 strong samples whose winner changes can split
    st = np.flatnonzero(strong)
    st = st[np.lexsort((v[si[st]], ss[st]))]
    same = ss[st][1:] == ss[st][:-1]
    changing = np.unique(ss[st][1:][same & (win[st][1:] != win[st][:-1])])
    for sid in changing:
        rows = np.flatnonzero((ss == sid) & strong)
        if rows.size < 4:
            continue
        rows = rows[np.argsort(v[si[rows]])]
        w_ = win[rows]
        change = np.flatnonzero(w_[1:] != w_[:-1])
        if change.size == 0:
            continue
        # runs of equal winners; only runs of >= 2 samples count, single outliers are noise
        starts = np.r_[0, change + 1]
        ends = np.r_[change + 1, len(w_)]
        runs = [(a, b) for a, b in zip(starts, ends, strict=True) if b - a >= 2]
        if len(runs) < 2:
            continue
        # merge neighbouring runs with the same winner
        merged = [runs[0]]
        for a, b in runs[1:]:
            if w_[a] == w_[merged[-1][0]]:
                merged[-1] = (merged[-1][0], b)
            else:
                merged.append((a, b))
        if len(merged) < 2:
            continue
        pts = np.flatnonzero(seg == sid)
        for (_, b_prev), (a_next, _) in zip(merged[:-1], merged[1:], strict=True):
            cut = 0.5 * (v[si[rows[b_prev - 1]]] + v[si[rows[a_next]]])
            seg[pts[v[pts] > cut]] = next_id
            next_id += 1
    return seg

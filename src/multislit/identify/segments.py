"""Stripe segments of a scan: their points in order, sample points, ends and splits.

A segment is a piece of one stripe linked by the extraction
(:func:`~multislit.stripes.link_segments`); the identification labels whole segments, after
splitting those that join two slits' stripes.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def segment_runs(seg: I64, v: F64) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The linked points ordered by (segment, v), and for each of them the positions (in that
    order) of its segment's first and last point: ``order, first, last``, each (K',)."""
    idx = np.flatnonzero(seg >= 0)
    order = idx[np.lexsort((v[idx], seg[idx]))]
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


def _sample_points(seg: I64, v: F64, step_px: float) -> NDArray[np.intp]:
    """Indices of points spaced about ``step_px`` rows apart along each segment."""
    order, start_v, _ = segment_runs(seg, v)
    if order.size == 0:
        return order
    s = seg[order]
    rel = v[order] - v[order][start_v]
    bucket = np.floor(rel / step_px + 0.5).astype(np.int64)
    # keep the first point of each (segment, bucket)
    key = s.astype(np.int64) * 1_000_000 + bucket
    keep = np.r_[True, key[1:] != key[:-1]]
    return order[keep]


def band_samples(seg: I64, v: F64, step_px: float, lo: float, hi: float) -> NDArray[np.intp]:
    """Sample points (:func:`_sample_points`) only in the rows ``lo <= v <= hi``.

    A template centred outside the band would be cut by the image's top or bottom: partly
    empty rows, which say little. Each segment's sampling starts at its first row in the band,
    and a segment that runs on below the band also gets its last row in the band, so the rows
    between the band and the image edge lie within a template's half height of a sample.
    """
    inside = (v >= lo) & (v <= hi)
    seg_in = np.where(inside, seg, -1)
    si = _sample_points(seg_in, v, step_px)
    below = np.unique(seg[(seg >= 0) & (v > hi)])
    if below.size == 0 or si.size == 0:
        return si
    # the last row in the band of each segment that runs on below it
    m = np.flatnonzero(inside & np.isin(seg, below))
    o = m[np.lexsort((v[m], seg[m]))]
    ends = o[np.r_[seg[o][1:] != seg[o][:-1], True]] if o.size else o
    si = np.unique(np.r_[si, ends])
    return si[np.lexsort((v[si], seg[si]))]  # by segment, then row, as _sample_points


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
    from numpy.lib.stride_tricks import sliding_window_view

    seg = seg.copy()
    next_id = int(seg.max()) + 1 if seg.size else 0
    idx = np.flatnonzero(seg >= 0)
    if idx.size < 2 * window + 2:
        return seg
    # all segments at once: points by (segment, v); rolling medians of log brightness
    order = idx[np.lexsort((v[idx], seg[idx]))]
    s_o = seg[order]
    bounds = np.flatnonzero(np.r_[True, s_o[1:] != s_o[:-1], True])
    start = np.repeat(bounds[:-1], np.diff(bounds))  # first point of each point's segment
    end = np.repeat(bounds[1:], np.diff(bounds))
    logp = np.log(np.maximum(peak[order], 1e-3))
    med = np.median(sliding_window_view(logp, window), axis=1)  # med[i] = points i..i+w-1
    g = np.arange(len(med) - window)  # before: g..g+w-1, after: g+w..g+2w-1
    inside = (g + 2 * window <= end[g]) & (end[g] - start[g] >= 2 * window + 2)
    step_all = np.where(inside, np.abs(med[g + window] - med[g]), 0.0)
    candidates = np.unique(s_o[g[step_all > np.log(ratio)]])
    for sid in candidates:
        a = int(np.searchsorted(s_o, sid, side="left"))
        b = int(np.searchsorted(s_o, sid, side="right"))
        pts = order[a:b]
        step = step_all[a : b - 2 * window + 1].copy()  # same as this segment's own medians
        cut_at = []
        while step.size and step.max() > np.log(ratio):
            j = int(np.argmax(step))
            cut_at.append(j + window)  # first point of the new piece
            lo, hi = max(0, j - window), min(len(step), j + window + 1)
            step[lo:hi] = 0
        for c in sorted(cut_at):
            seg[pts[c:]] = np.where(seg[pts[c:]] == seg[pts[c]], next_id, seg[pts[c:]])
            next_id += 1
    return seg


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
    S = np.where(np.isfinite(scores), scores, -1.0)
    top2 = np.sort(S, axis=1)[:, -2:] if S.shape[1] > 1 else np.c_[np.full(len(S), -1.0), S]
    win = np.argmax(S, axis=1)
    return win, (top2[:, 1] >= min_score) & (top2[:, 1] - top2[:, 0] >= WINNER_LEAD)


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

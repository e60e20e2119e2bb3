"""Stripe order along image rows: runs of consecutive slits and their offsets.

Along an image row on one surface the slits appear in their left-to-right order. Centres are cut
into *runs* where the gap to the next one is far above the local spacing (a hidden stripe) or far
below it (a double detection); within a run consecutive centres are consecutive slits, so a run
needs one offset ``slit - rank``, agreed by votes (e.g. dot identifications). Used by the scan
identification (:mod:`multislit.identify`) and the calibration labelling
(:mod:`multislit.calibrate.slit_labels`).

The identification's order rules are here too: per point the slit its place in its row implies
(:func:`order_labels`), slit numbers for segments the dots left unidentified
(:func:`fill_by_order`, :func:`confirm_by_neighbours`), and the points of neighbouring segments
out of slit order (:func:`order_violations`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.identify.segments import group_order

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: :func:`fill_by_order` rule 2: least confidence of the dots' own vote.
_MIN_CONFIRM = 0.05
#: :func:`fill_by_order` rule 2: least share of the run labels that agree with the dots' vote.
_CONFIRM_SHARE = 0.8
#: :func:`fill_by_order` rule 3: the run label must be among the dots' this many best slits.
_EXTRAPOLATE_TOP = 5


@dataclass(frozen=True)
class OrderParams:
    """Tuning of :func:`~multislit.calibrate.label_by_order`.

    max_gap_ratio : a gap above this many times the local stripe spacing ends a run
    min_gap_ratio : centres closer than this many times the local spacing to a neighbour in the
        row (double detections) are left out and end a run
    spacing_window : gaps either side whose median is the local spacing
    min_agree : least fraction (by weight) of a run's votes that must agree on its offset
    min_votes : least number of agreeing votes for a run's offset
    max_rounds : rounds of row-to-row propagation
    match_px : a neighbouring-row centre votes when it lies within this many px (default: the
        stripe width, at least 1 px)
    """

    max_gap_ratio: float = 1.6
    min_gap_ratio: float = 0.6
    spacing_window: int = 3
    min_agree: float = 0.8
    min_votes: int = 3
    max_rounds: int = 2000
    match_px: float | None = None


@njit(cache=True)
def _sort_rows(o, u, row):
    """In place: ``o`` (item indices ordered by ``row``) sorted stably by ``u`` within each run
    of equal ``row`` (NaN last, as ``np.lexsort``), by insertion (the rows are short and their
    centres usually come in order already)."""
    m = len(o)
    i0 = 0
    while i0 < m:
        r0 = row[o[i0]]
        i1 = i0 + 1
        while i1 < m and (row[o[i1]] == r0 or (r0 != r0 and row[o[i1]] != row[o[i1]])):
            i1 += 1
        for a in range(i0 + 1, i1):
            x = o[a]
            ux = u[x]
            b = a
            while b > i0 and (ux < u[o[b - 1]] or (np.isnan(u[o[b - 1]]) and not np.isnan(ux))):
                o[b] = o[b - 1]
                b -= 1
            o[b] = x
        i0 = i1


def by_row(u: F64, row: NDArray, idx: NDArray[np.intp]) -> NDArray[np.intp]:
    """The items ``idx`` ordered by (``row``, ``u``, index): (n,) intp, the same as
    ``idx[np.lexsort((u[idx], row[idx]))]``."""
    order = idx[np.argsort(row[idx], kind="stable")]
    _sort_rows(order, np.asarray(u, np.float64), row)
    return order


@njit(cache=True)
def _median_of(buf, n):
    """Median of ``buf[:n]`` (sorted in place), NaN for n = 0."""
    if n == 0:
        return np.nan
    for a in range(1, n):
        x = buf[a]
        b = a
        while b > 0 and buf[b - 1] > x:
            buf[b] = buf[b - 1]
            b -= 1
        buf[b] = x
    return 0.5 * (buf[(n - 1) // 2] + buf[n // 2])


@njit(cache=True)
def _nanmedian_rows(a):
    """``np.nanmedian(a, axis=1)`` of a narrow (n, w) float64 array, NaN for all-NaN rows."""
    out = np.empty(a.shape[0])
    buf = np.empty(a.shape[1])
    for i in range(a.shape[0]):
        n = 0
        for j in range(a.shape[1]):
            if not np.isnan(a[i, j]):
                buf[n] = a[i, j]
                n += 1
        out[i] = _median_of(buf, n)
    return out


@njit(cache=True)
def _runs_in_rows(order, u, v, w, min_gap_ratio, max_gap_ratio, run, rank):
    """:func:`row_runs` on the centres ``order`` (ordered by row, then u): fills ``run`` and
    ``rank`` (K,) at the centres kept."""
    m = len(order)
    ng = max(m - 1, 0)  # gap i: between centres i and i + 1 (in order)
    same = np.zeros(ng, np.bool_)
    gap = np.full(ng, np.nan)
    rowid = np.zeros(ng, np.int64)
    for i in range(ng):
        same[i] = v[order[i + 1]] == v[order[i]]
        if same[i]:
            gap[i] = u[order[i + 1]] - u[order[i]]
        if i > 0:
            rowid[i] = rowid[i - 1] + (0 if same[i - 1] else 1)
    # a gap is judged against the local spacing: the smaller of the medians of the w gaps
    # before and after it in its row
    small = np.zeros(ng, np.bool_)
    big = np.zeros(ng, np.bool_)
    buf = np.empty(max(w, 1))
    for i in range(ng):
        n = 0
        for j in range(max(i - w, 0), i):
            if rowid[j] == rowid[i] and not np.isnan(gap[j]):
                buf[n] = gap[j]
                n += 1
        before = _median_of(buf, n)
        n = 0
        for j in range(i + 1, min(i + w + 1, ng)):
            if rowid[j] == rowid[i] and not np.isnan(gap[j]):
                buf[n] = gap[j]
                n += 1
        after = _median_of(buf, n)
        spacing = np.fmin(before, after)
        small[i] = same[i] and gap[i] < min_gap_ratio * spacing
        big[i] = not same[i] or not gap[i] <= max_gap_ratio * spacing
    bad = np.zeros(m, np.bool_)  # double detections
    for i in range(ng):
        if small[i]:
            bad[i] = True
            bad[i + 1] = True
    rid = -1
    start = 0
    for i in range(m):
        if i == 0 or big[i - 1] or small[i - 1] or bad[i - 1] or bad[i]:  # cut before i
            rid += 1
            start = i
        if not bad[i]:
            run[order[i]] = rid
            rank[order[i]] = i - start


def row_runs(
    u: F64, v: F64, ok: NDArray[np.bool_], p: OrderParams
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Run id and rank in the run of each centre (-1 for centres left out).

    Parameters
    ----------
    u, v : (K,) float64, px, the centres (v: their row)
    ok : (K,) bool, the centres to consider
    p : the gap ratios and the spacing window

    Returns
    -------
    run, rank : (K,) intp
    """
    n = len(u)
    run = np.full(n, -1, np.intp)
    rank = np.full(n, -1, np.intp)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return run, rank
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    order = by_row(u, v, idx)
    # local spacing either side: median of the ``w`` gaps before / after in the row. A gap is
    # judged against the smaller one: where the spacing changes (a face edge) a hidden stripe
    # still makes the gap >= 2x the smaller spacing.
    _runs_in_rows(
        order,
        u,
        v,
        int(p.spacing_window),
        float(p.min_gap_ratio),
        float(p.max_gap_ratio),
        run,
        rank,
    )
    return run, rank


def run_offsets(
    run: NDArray[np.intp],
    rank: NDArray[np.intp],
    vote: NDArray[np.intp],
    weight: F64,
    n_runs: int,
    p: OrderParams,
) -> NDArray[np.intp]:
    """Per run, the agreed offset ``slit - rank`` of the voting centres, or a sentinel."""
    NONE = np.iinfo(np.intp).min
    out = np.full(n_runs, NONE, np.intp)
    sel = (vote >= 0) & (run >= 0) & (weight > 0)
    if not sel.any():
        return out
    r, off, wt = run[sel], vote[sel] - rank[sel], weight[sel]
    if r.max() >= n_runs:
        raise ValueError(f"run_offsets: run ids go up to {r.max()} but n_runs is {n_runs}")
    by_run = group_order(r)  # the votes of each run in their order
    _best_offsets(
        r.astype(np.int64),
        off.astype(np.int64),
        wt.astype(np.float64),
        by_run,
        float(p.min_agree),
        int(p.min_votes),
        out,
    )
    return out


@njit(cache=True)
def _best_offsets(r, off, wt, by_run, min_agree, min_votes, out):
    """:func:`run_offsets` on the votes (run ``r``, offset ``off``, weight ``wt``) taken in the
    order ``by_run`` (by run, then as given): per run the offset of the largest total weight
    (the largest such offset on ties), written to ``out`` where it holds ``min_agree`` of the
    run's weight and ``min_votes`` votes."""
    lo = off.min()
    span = off.max() - lo + 1
    kw = np.zeros(span)
    kc = np.zeros(span, np.int64)
    n = len(by_run)
    i = 0
    while i < n:
        g = r[by_run[i]]
        total = 0.0
        j = i
        while j < n and r[by_run[j]] == g:
            x = by_run[j]
            kw[off[x] - lo] += wt[x]
            kc[off[x] - lo] += 1
            total += wt[x]
            j += 1
        best = -1
        for k in range(span):
            if kc[k] > 0 and (best < 0 or kw[k] >= kw[best]):
                best = k
        if kw[best] >= min_agree * total and kc[best] >= min_votes:
            out[g] = best + lo
        for jj in range(i, j):
            kw[off[by_run[jj]] - lo] = 0.0
            kc[off[by_run[jj]] - lo] = 0
        i = j


def apply_run_offsets(
    run: NDArray[np.intp], rank: NDArray[np.intp], offset: NDArray[np.intp], num_slits: int
) -> NDArray[np.intp]:
    """Labels rank + offset of the runs with an offset; a run leaving 0..N-1 stays unlabelled."""
    NONE = np.iinfo(np.intp).min
    n_runs = len(offset)
    slit = np.full(len(run), -1, np.intp)
    has = run >= 0
    if not has.any():
        return slit
    lab = np.where(offset[run[has]] != NONE, rank[has] + offset[run[has]], -1)
    bad_run = np.zeros(n_runs, bool)
    out_of_range = (offset[run[has]] != NONE) & ((lab < 0) | (lab >= num_slits))
    bad_run[run[has][out_of_range]] = True
    lab[bad_run[run[has]]] = -1
    slit[has] = lab
    return slit


def order_violations(
    u: F64, v: F64, slit: I64, seg: I64, max_gap_px: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Points side by side in a row (closer than ``max_gap_px``), of two segments, out of slit
    order.

    Across an occlusion or a shadow the order of slits can legitimately change, but two stripes
    directly next to each other on one surface keep the projector's left-to-right order. Where
    a stripe on an object's edge meets a stripe of the surface behind, the two lie side by side
    in only the rows of the edge: the contradiction is local to those rows.

    Parameters
    ----------
    u, v : (K,) float64, px, stripe centres
    slit : (K,) int64, slit number (-1: none; those points are ignored)
    seg : (K,) int64, segment id
    max_gap_px : px, largest gap between two centres that counts as side by side

    Returns
    -------
    left, right : (P,) intp, the point indices of each violating pair, ``left`` left of
        ``right`` in its row, with ``slit[left] >= slit[right]``
    """
    m = np.flatnonzero(slit >= 0)
    if m.size < 2:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    row = np.zeros(len(v), np.int64)
    row[m] = np.round(v[m])
    idx = by_row(u, row, m)
    row = row[idx]
    uu, ss, gg = u[idx], slit[idx], seg[idx]
    same = row[1:] == row[:-1]
    near = (uu[1:] - uu[:-1]) < max_gap_px
    bad = np.flatnonzero(same & near & (ss[1:] <= ss[:-1]) & (gg[1:] != gg[:-1]))
    return idx[bad], idx[bad + 1]


@njit(cache=True)
def _run_votes(run, rank, seg, voted, n_runs):
    """The dot-identified (``voted``) centres of each row-run, walked in rank order (``run``
    (K,) below ``n_runs``, -1: in no run; ranks unique within a run, as :func:`row_runs`
    gives them; ``seg`` (K,) the centres' segment ids, >= -1).

    Returns
    -------
    n_segs : (n_runs,) int64, number of different segments among the run's voted centres
    lo, hi : (n_runs,) intp, the run's lowest and highest voted rank (max intp and -1: none)
    left, right : (K,) intp, per centre the nearest voted centre of its run before it, and at
        or after it (the centre itself if voted); -1: none
    """
    k = len(run)
    base = np.zeros(n_runs + 1, np.int64)  # slots of run g: base[g] .. base[g + 1] - 1, by rank
    n_ids = 1
    for i in range(k):
        if run[i] >= 0:
            base[run[i] + 1] = max(base[run[i] + 1], rank[i] + 1)
            n_ids = max(n_ids, seg[i] + 2)
    for g in range(n_runs):
        base[g + 1] += base[g]
    slot = np.full(base[n_runs], -1, np.intp)
    for i in range(k):
        if run[i] >= 0:
            slot[base[run[i]] + rank[i]] = i
    n_segs = np.zeros(n_runs, np.int64)
    lo = np.full(n_runs, np.iinfo(np.intp).max, np.intp)
    hi = np.full(n_runs, -1, np.intp)
    left = np.full(k, -1, np.intp)
    right = np.full(k, -1, np.intp)
    seen_in = np.full(n_ids, -1, np.int64)  # per segment id + 1: the last run it voted in
    for g in range(n_runs):
        prev = -1
        for t in range(base[g], base[g + 1]):
            i = slot[t]
            if i < 0:
                continue
            left[i] = prev
            if voted[i]:
                prev = i
                lo[g] = min(lo[g], rank[i])
                hi[g] = max(hi[g], rank[i])
                if seen_in[seg[i] + 1] != g:
                    seen_in[seg[i] + 1] = g
                    n_segs[g] += 1
        nxt = -1
        for t in range(base[g + 1] - 1, base[g] - 1, -1):
            i = slot[t]
            if i < 0:
                continue
            if voted[i]:
                nxt = i
            right[i] = nxt
    return n_segs, lo, hi, left, right


def _agreeing(
    rank: NDArray[np.intp],
    vote: NDArray[np.intp],
    lab: NDArray[np.intp],
    left: NDArray[np.intp],
    right: NDArray[np.intp],
) -> NDArray[np.bool_]:
    """For each point: do the nearest dot-identified stripes left and right of it in its run,
    ``left`` and ``right`` (:func:`_run_votes`; -1: none), agree with each other and with its
    order label ``lab``? (their slits differ by their rank difference, and ``lab`` is the left
    one's slit plus the rank step). A run's majority offset can disagree with the stripes right
    beside a point where a hidden slit leaves no gap wide enough to cut the run."""
    a, b = np.maximum(left, 0), np.maximum(right, 0)
    ok = (lab >= 0) & (left >= 0) & (right >= 0)
    ok &= (vote[b] - vote[a]) == (rank[b] - rank[a])
    return ok & (lab == vote[a] + (rank - rank[a]))


class RowOrder(NamedTuple):
    """Order labels of every point (:func:`order_labels`); -1 where the order says nothing.

    run, rank : (K,) the point's row-run and its rank in it (-1: in no run)
    extended : (K,) run label wherever the run has an agreed offset (also beyond the run's
        first or last dot-identified stripe)
    inside : (K,) run label from the run's first to its last dot-identified stripe
    between : (K,) run label strictly between the run's first and last dot-identified
        stripes, where the nearest ones on either side agree with it (:func:`_agreeing`)
    """

    run: NDArray[np.intp]
    rank: NDArray[np.intp]
    extended: NDArray[np.intp]
    inside: NDArray[np.intp]
    between: NDArray[np.intp]


def order_labels(u: F64, v: F64, seg: I64, slit: I64, conf: F64, num_slits: int) -> RowOrder:
    """Per point, the slit its place in its row implies (-1 where the order says nothing).

    Along a row, stripes closer than ~1.6 local spacings belong to consecutive slits (a larger
    gap or a double detection cuts the run); each run's offset ``slit - rank`` must be agreed by
    its dot-identified points (>= 80 %, >= 3 votes, from >= 2 different stripes; the defaults
    of :class:`OrderParams`).

    Returns
    -------
    :class:`RowOrder`
    """
    op = OrderParams()
    ok = seg >= 0
    run, rank = row_runs(u, v, ok, op)
    n_runs = int(run.max()) + 1 if (run >= 0).any() else 0
    if n_runs == 0:
        none = np.full(len(u), -1, np.intp)
        return RowOrder(run, rank, none, none, none)
    vote = np.where(slit >= 0, slit, -1).astype(np.intp)
    offset = run_offsets(run, rank, vote, np.where(slit >= 0, conf, 0.0), n_runs, op)
    voted = (vote >= 0) & (run >= 0)
    n_segs, lo, hi, left, right = _run_votes(run, rank, seg.astype(np.int64), voted, n_runs)
    # an offset must be confirmed by the dots of >= 2 different stripes (segments) of the run
    offset = np.where(n_segs >= 2, offset, np.iinfo(np.intp).min)
    run_label = apply_run_offsets(run, rank, offset, num_slits)
    # interpolate only: a point is labelled only between dot-identified stripes of its run
    r = np.maximum(run, 0)
    span_ = (run >= 0) & (rank >= lo[r]) & (rank <= hi[r])
    lab = np.where(span_ & (rank > lo[r]) & (rank < hi[r]), run_label, -1)
    # ... where the nearest dot-identified stripes either side agree (:func:`_agreeing`)
    between = np.where(_agreeing(rank, vote, lab, left, right), lab, -1)
    return RowOrder(run, rank, run_label, np.where(span_, run_label, -1), between)


def fill_by_order(
    seg: I64,
    slit: I64,
    usable: NDArray[np.bool_],
    order: RowOrder,
    num_slits: int,
    dots: dict[int, tuple[int, float, F64]] | None = None,
    *,
    min_score: float,
) -> dict[int, tuple[int, float]]:
    """Slit numbers for segments the dots left unidentified, from the order along the rows.

    ``order`` holds the order labels (:func:`order_labels`); ``dots`` holds,
    per segment the dots left unidentified, their vote: (best slit, confidence, (N,) mean score
    per slit). A free segment takes, by the first rule that holds:

    1. the ``order.between`` label, if it covers >= 50 % (>= 5) of the segment's points and
       >= 95 % of those agree; confidence 0.6 x agreement (order-inferred labels never count
       as certain);
    2. the dots' best slit, if their confidence reaches ``_MIN_CONFIRM`` (0.05) and the run
       label (``order.extended``, also beyond the run's last dot-identified stripe) covers
       >= 30 % (>= 5) of the points and >= ``_CONFIRM_SHARE`` (80 %) of those agree with it:
       two independent sources agreeing on one of N slits; confidence 0.6 x agreement;
    3. the run label, if it covers >= 50 % (>= 5) of the points, >= 95 % of those agree, and
       the dots do not contradict it: it is among their ``_EXTRAPOLATE_TOP`` (5) best slits
       with a mean score >= ``min_score``; confidence 0.4 x agreement (extrapolated order, weak
       dots).

    Parameters
    ----------
    seg, slit : (K,) int64, segment id and slit number (-1: none) per point
    usable : (K,) bool, the points the dots vouch for
    order : the order labels
    num_slits : N
    dots : dict segment -> (best slit or -1, confidence, (N,) float64 mean score per slit)
    min_score : least mean NCC of the run label's slit in rule 3

    Returns
    -------
    dict segment -> (slit, confidence), for the segments filled
    """
    dots = dots or {}
    out: dict[int, tuple[int, float]] = {}
    ok = seg >= 0
    span = int(seg.max()) + 2
    free = np.flatnonzero(np.bincount(seg[ok & (slit < 0) & usable], minlength=span))
    if free.size == 0:
        return out
    n_pts = np.bincount(seg[ok], minlength=span)

    def majority(lab: NDArray[np.intp]) -> tuple[NDArray[np.int64], F64, F64]:
        """Per segment: most frequent label (the smallest of equally frequent ones), its count,
        and the number of labelled points."""
        lm = ok & (lab >= 0)
        L = max(num_slits, int(lab.max()) + 1)
        cnt = np.bincount(seg[lm] * L + lab[lm], minlength=span * L).reshape(span, L)
        best = np.argmax(cnt, axis=1)
        best_cnt = cnt[np.arange(span), best].astype(np.float64)
        best = np.where(best_cnt > 0, best, -1)
        return best, best_cnt, cnt.sum(axis=1).astype(np.float64)

    b_lab, b_cnt, b_n = majority(order.between)
    r_lab, r_cnt, r_n = majority(order.extended)
    # per segment: how many of its run labels name the dots' best slit (rule 2)
    dot_k = np.full(span, -1, np.int64)
    for sid, (k, _, _) in dots.items():
        dot_k[sid] = k
    named = ok & (order.extended >= 0) & (order.extended == dot_k[np.maximum(seg, 0)])
    n_named = np.bincount(seg[named], minlength=span)
    for sid in free:
        nb, nr = b_n[sid], r_n[sid]
        if nb >= 5 and nb >= 0.5 * n_pts[sid] and b_cnt[sid] >= 0.95 * nb:
            out[int(sid)] = (int(b_lab[sid]), float(0.6 * b_cnt[sid] / nb))
            continue
        if int(sid) not in dots or nr < 5:
            continue
        k, c, mean = dots[int(sid)]
        agree = float(n_named[sid] / nr)
        if k >= 0 and c >= _MIN_CONFIRM and nr >= 0.3 * n_pts[sid] and agree >= _CONFIRM_SHARE:
            out[int(sid)] = (int(k), 0.6 * agree)
            continue
        kr = int(r_lab[sid])
        if nr >= 0.5 * n_pts[sid] and r_cnt[sid] >= 0.95 * nr and mean[kr] >= min_score:
            if np.sum(mean > mean[kr]) < _EXTRAPOLATE_TOP:
                out[int(sid)] = (kr, float(0.4 * r_cnt[sid] / nr))
    return out


def confirm_by_neighbours(
    order: RowOrder,
    seg: I64,
    slit: I64,
    weak: I64,
    usable: NDArray[np.bool_],
    min_share: float,
) -> dict[int, int]:
    """Weak dot votes that their neighbours in the rows confirm.

    ``weak`` (S,) is, per segment, the dots' best slit where they were too unsure to label it
    (-1 elsewhere). A point is supported where the next stripe to its left in its row-run
    (another segment) carries its slit - 1, or the next one to its right its slit + 1, counting
    labels and weak votes alike. A segment whose weak vote is supported on >= ``min_share`` of
    its usable points (>= 5) takes it: two neighbouring stripes whose dots each point to
    consecutive slits confirm each other.

    Returns
    -------
    dict segment -> slit, for the segments confirmed
    """
    lab = np.where(slit >= 0, slit, np.where(seg >= 0, weak[np.maximum(seg, 0)], -1))
    # the pairs of consecutive stripes a, b in a run (b's rank is a's + 1)
    run, rank = order.run, order.rank
    n_runs = int(run.max()) + 1 if len(run) else 0
    _, _, _, prev, _ = _run_votes(run, rank, np.zeros(len(run), np.int64), run >= 0, n_runs)
    b = np.flatnonzero(prev >= 0)
    a = prev[b]
    nxt = rank[b] == rank[a] + 1
    a, b = a[nxt], b[nxt]
    pair = (lab[a] >= 0) & (lab[b] == lab[a] + 1) & (seg[a] != seg[b])
    support = np.zeros(len(seg), bool)
    support[a[pair]] = True
    support[b[pair]] = True
    out: dict[int, int] = {}
    m = usable & (seg >= 0)
    m &= weak[np.maximum(seg, 0)] >= 0
    m &= slit < 0
    if not m.any():
        return out
    n = np.bincount(seg[m], minlength=len(weak))
    n_sup = np.bincount(seg[m], weights=support[m], minlength=len(weak))
    for sid in np.flatnonzero((n >= 5) & (n_sup >= min_share * np.maximum(n, 1))):
        out[int(sid)] = int(weak[sid])
    return out

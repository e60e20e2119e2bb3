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
from numpy.typing import NDArray

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


def _nanmedian_rows(a: F64) -> F64:
    """``np.nanmedian(a, axis=1)`` of a narrow (n, w) array, NaN for all-NaN rows, no warning."""
    a = np.sort(a, axis=1)  # NaN sort last
    n = np.sum(~np.isnan(a), axis=1)
    rows = np.arange(len(a))
    lo = a[rows, np.maximum(n - 1, 0) // 2]
    hi = a[rows, np.maximum(n, 1) // 2 * (n > 0)]
    with np.errstate(invalid="ignore"):
        return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def row_runs(
    u: F64, v: F64, ok: NDArray[np.bool_], p: OrderParams
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Run id and rank in the run of each centre (-1 for centres left out)."""
    n = len(u)
    run = np.full(n, -1, np.intp)
    rank = np.full(n, -1, np.intp)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return run, rank
    order = idx[np.lexsort((u[idx], v[idx]))]
    uu, vv = u[order], v[order]
    m = len(order)
    same = vv[1:] == vv[:-1]
    gap = np.where(same, uu[1:] - uu[:-1], np.nan)  # gap i: between i and i+1
    # local spacing either side: median of the ``w`` gaps before / after in the row. A gap is
    # judged against the smaller one: where the spacing changes (a face edge) a hidden stripe
    # still makes the gap >= 2x the smaller spacing.
    w = p.spacing_window
    rowid = np.cumsum(np.r_[0, ~same])[:-1]  # row of each gap (gap i: centres i, i+1)
    pad = np.concatenate([np.full(w, np.nan), gap, np.full(w, np.nan)])
    rpad = np.concatenate([np.full(w, -1), rowid, np.full(w, -1)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * w + 1)
    rwin = np.lib.stride_tricks.sliding_window_view(rpad, 2 * w + 1)
    win = np.where(rwin == rowid[:, None], win, np.nan)
    before = _nanmedian_rows(win[:, :w])  # all-NaN windows: NaN spacing
    after = _nanmedian_rows(win[:, w + 1 :])
    spacing = np.fmin(before, after)
    small = same & (gap < p.min_gap_ratio * spacing)
    big = ~same | ~(gap <= p.max_gap_ratio * spacing)  # NaN spacing (lonely pair): cut
    bad = np.zeros(m, bool)
    bad[:-1] |= small
    bad[1:] |= small
    cut = np.ones(m, bool)  # cut before centre i
    cut[1:] = big | small | bad[:-1] | bad[1:]
    rid = np.cumsum(cut) - 1
    start = np.flatnonzero(cut)
    rk = np.arange(m) - start[rid]
    keep = ~bad
    run[order[keep]] = rid[keep]
    rank[order[keep]] = rk[keep]
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
    lo = int(off.min())
    span = int(off.max()) - lo + 1
    key = r.astype(np.int64) * span + (off - lo)
    uk, inv = np.unique(key, return_inverse=True)
    kw = np.bincount(inv, weights=wt)
    kc = np.bincount(inv)
    kr = uk // span
    total_w = np.bincount(r, weights=wt, minlength=n_runs)
    # best key per run: sort by (run, weight) and take the last of each run
    o = np.lexsort((kw, kr))
    last = np.r_[kr[o][1:] != kr[o][:-1], True]
    best = o[last]
    br = kr[best]
    ok = (kw[best] >= p.min_agree * total_w[br]) & (kc[best] >= p.min_votes)
    out[br[ok]] = (uk[best][ok] % span + lo).astype(np.intp)
    return out


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
    row = np.round(v[m]).astype(np.int64)
    o = np.lexsort((u[m], row))
    idx, row = m[o], row[o]
    uu, ss, gg = u[idx], slit[idx], seg[idx]
    same = row[1:] == row[:-1]
    near = (uu[1:] - uu[:-1]) < max_gap_px
    bad = np.flatnonzero(same & near & (ss[1:] <= ss[:-1]) & (gg[1:] != gg[:-1]))
    return idx[bad], idx[bad + 1]


def _between_agreeing(
    run: NDArray[np.intp],
    rank: NDArray[np.intp],
    vote: NDArray[np.intp],
    voted: NDArray[np.bool_],
    lab: NDArray[np.intp],
) -> NDArray[np.bool_]:
    """For each point: do the nearest dot-identified stripes left and right of it in its run
    agree with each other and with its order label ``lab``? (their slits differ by their rank
    difference, and ``lab`` is the left one's slit plus the rank step). A run's majority offset
    can disagree with the stripes right beside a point where a hidden slit leaves no gap wide
    enough to cut the run."""
    out = np.zeros(len(run), bool)
    vi = np.flatnonzero(voted)
    if vi.size == 0:
        return out
    big = np.int64(rank.max()) + 2
    key_v = run[vi].astype(np.int64) * big + rank[vi]
    o = np.argsort(key_v, kind="stable")
    vi, key_v = vi[o], key_v[o]
    q = np.flatnonzero((run >= 0) & (lab >= 0))
    if q.size == 0:
        return out
    key_q = run[q].astype(np.int64) * big + rank[q]
    j = np.searchsorted(key_v, key_q)  # first voted at or after the point
    has_l = j > 0
    has_r = j < len(vi)
    jl = np.clip(j - 1, 0, len(vi) - 1)
    jr = np.clip(j, 0, len(vi) - 1)
    left, right = vi[jl], vi[jr]
    ok = has_l & has_r & (run[left] == run[q]) & (run[right] == run[q])
    ok &= (vote[right] - vote[left]) == (rank[right] - rank[left])
    ok &= lab[q] == vote[left] + (rank[q] - rank[left])
    out[q] = ok
    return out


class RowOrder(NamedTuple):
    """Order labels of every point (:func:`order_labels`); -1 where the order says nothing.

    run, rank : (K,) the point's row-run and its rank in it (-1: in no run)
    extended : (K,) run label wherever the run has an agreed offset (also beyond the run's
        first or last dot-identified stripe)
    inside : (K,) run label from the run's first to its last dot-identified stripe
    between : (K,) run label strictly between the run's first and last dot-identified
        stripes, where the nearest ones on either side agree with it (:func:`_between_agreeing`)
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
    # an offset must be confirmed by the dots of >= 2 different stripes (segments) of the run
    voted = (vote >= 0) & (run >= 0)
    span = int(seg.max()) + 2
    pairs = np.unique(run[voted].astype(np.int64) * span + (seg[voted] + 1))
    n_seg_votes = np.bincount(pairs // span, minlength=n_runs)
    offset = np.where(n_seg_votes >= 2, offset, np.iinfo(np.intp).min)
    run_label = apply_run_offsets(run, rank, offset, num_slits)
    # interpolate only: a point is labelled only between dot-identified stripes of its run
    big = np.iinfo(np.intp).max
    lo = np.full(n_runs, big, np.intp)
    hi = np.full(n_runs, -1, np.intp)
    np.minimum.at(lo, run[voted], rank[voted])
    np.maximum.at(hi, run[voted], rank[voted])
    r = np.maximum(run, 0)
    span_ = (run >= 0) & (rank >= lo[r]) & (rank <= hi[r])
    lab = np.where(span_ & (rank > lo[r]) & (rank < hi[r]), run_label, -1)
    between = np.where(_between_agreeing(run, rank, vote, voted, lab), lab, -1)
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
    free = np.unique(seg[ok & (slit < 0) & usable])
    if free.size == 0:
        return out
    span = int(seg.max()) + 2
    n_pts = np.bincount(seg[ok], minlength=span)

    def majority(lab: NDArray[np.intp]) -> tuple[NDArray[np.int64], F64, F64]:
        """Per segment: most frequent label (the smallest of equally frequent ones), its count,
        and the number of labelled points."""
        lm = ok & (lab >= 0)
        L = num_slits + 1
        keys, cnt = np.unique(seg[lm].astype(np.int64) * L + lab[lm], return_counts=True)
        ks, kl = keys // L, keys % L
        n_lab = np.bincount(ks, weights=cnt, minlength=span)
        o = np.lexsort((kl, -cnt, ks))
        first = o[np.r_[True, ks[o][1:] != ks[o][:-1]]] if len(o) else o
        best = np.full(span, -1, np.int64)
        best_cnt = np.zeros(span)
        best[ks[first]] = kl[first]
        best_cnt[ks[first]] = cnt[first]
        return best, best_cnt, n_lab

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
    o = np.lexsort((order.rank, order.run))
    o = o[order.run[o] >= 0]
    nxt = (order.run[o][1:] == order.run[o][:-1]) & (order.rank[o][1:] == order.rank[o][:-1] + 1)
    a, b = o[:-1][nxt], o[1:][nxt]
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

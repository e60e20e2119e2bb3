"""Stripe order along image rows, for the calibration's labelling of the target's stripes.

Along an image row on one surface the slits appear in their left-to-right order. Centres are cut
into *runs* where the gap to the next one is far above the local spacing (a hidden stripe) or far
below it (a double detection); within a run consecutive centres are consecutive slits, so a run
needs one offset ``slit - rank``, agreed by votes (e.g. dot identifications). Used by
:func:`~multislit.calibrate.slit_labels.label_by_order`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.identify.segments import group_order

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class OrderParams:
    """Tuning of :func:`~multislit.calibrate.slit_labels.label_by_order`.

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

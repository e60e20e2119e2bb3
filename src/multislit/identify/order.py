"""Stripe order along image rows: runs of consecutive slits and their offsets.

Along an image row on one surface the slits appear in their left-to-right order. Centres are cut
into *runs* where the gap to the next one is far above the local spacing (a hidden stripe) or far
below it (a double detection); within a run consecutive centres are consecutive slits, so a run
needs one offset ``slit - rank``, agreed by votes (e.g. dot identifications). Used by the scan
identification (:mod:`multislit.identify`) and the calibration labelling
(:mod:`multislit.calibrate_labels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class OrderParams:
    """Tuning of :func:`label_by_order`.

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


def _runs(
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


def _run_offsets(
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


def _apply(
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

"""The compiled kernels of the template labelling and the calibration's row order against
straightforward NumPy."""

import warnings

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from multislit.calibrate.row_order import OrderParams, by_row, row_runs, run_offsets
from multislit.identify.labelling import _rows_to_sample
from multislit.identify.segments import (
    _rolling_median,
    by_segment,
    clear_winners,
    group_order,
    segment_runs,
)


def _rows(rng, n_rows=40, per_row=12, seg_ids=9):
    """Centres in rows (v integer, some rows shuffled), their segments (some -1)."""
    v = np.repeat(np.arange(n_rows, dtype=float), per_row)
    u = np.cumsum(rng.uniform(0.5, 12.0, (n_rows, per_row)), axis=1).ravel()
    u[rng.random(u.size) < 0.05] += 30.0  # out of order in its row
    u[::37] = u[1::37][: len(u[::37])]  # equal u in a row
    seg = rng.integers(-1, seg_ids, u.size)
    perm = rng.permutation(u.size)
    return u[perm], v[perm], seg[perm]


@pytest.mark.parametrize("sparse", [False, True])
def test_group_order_is_a_stable_sort(sparse):
    rng = np.random.default_rng(0)
    key = rng.integers(-2, 30, 500) * (10**7 if sparse else 1)
    pre = rng.permutation(500)
    got = group_order(key, pre)
    sel = pre[key[pre] >= 0]
    assert np.array_equal(got, sel[np.argsort(key[sel], kind="stable")])
    assert np.array_equal(
        group_order(key), np.flatnonzero(key >= 0)[np.argsort(key[key >= 0], kind="stable")]
    )
    assert group_order(np.zeros(0, np.int64)).size == 0


def test_by_segment_and_by_row_equal_lexsort():
    rng = np.random.default_rng(1)
    u, v, seg = _rows(rng)
    v[rng.random(v.size) < 0.02] = np.nan
    u[rng.random(u.size) < 0.02] = np.nan
    idx = np.flatnonzero(seg >= 0)
    assert np.array_equal(by_segment(seg, v), idx[np.lexsort((v[idx], seg[idx]))])
    assert np.array_equal(by_row(u, v, idx), idx[np.lexsort((u[idx], v[idx]))])
    row = np.round(np.nan_to_num(v, nan=-7.0)).astype(np.int64)
    assert np.array_equal(by_row(u, row, idx), idx[np.lexsort((u[idx], row[idx]))])
    order, first, last = segment_runs(seg, v)
    s = seg[order]
    assert np.all(s[first] == s) and np.all(s[last] == s)
    assert np.all((first == 0) | (s[np.maximum(first - 1, 0)] != s))


@pytest.mark.parametrize("window", [5, 6])
def test_rolling_median_equals_numpy_median(window):
    rng = np.random.default_rng(2)
    x = np.round(rng.normal(size=3000), 1)  # ties
    x[rng.random(x.size) < 0.01] = np.nan
    want = np.median(sliding_window_view(x, window), axis=1)
    assert np.array_equal(_rolling_median(x, window), want, equal_nan=True)


def test_clear_winners_equal_a_sort():
    rng = np.random.default_rng(3)
    for n in (1, 2, 7):
        s = np.round(rng.uniform(-1, 1, (400, n)), 1)
        s[rng.random(s.shape) < 0.2] = np.nan
        s[0] = np.inf
        win, clear = clear_winners(s, 0.15)
        S = np.where(np.isfinite(s), s, -1.0)
        top2 = np.sort(S, axis=1)[:, -2:] if n > 1 else np.c_[np.full(len(S), -1.0), S]
        assert np.array_equal(win, np.argmax(S, axis=1))
        assert np.array_equal(clear, (top2[:, 1] >= 0.15) & (top2[:, 1] - top2[:, 0] >= 0.1))


def _row_runs_numpy(u, v, ok, p):
    """:func:`row_runs` written with whole-array NumPy operations."""
    n = len(u)
    run = np.full(n, -1, np.intp)
    rank = np.full(n, -1, np.intp)
    idx = np.flatnonzero(ok)
    order = idx[np.lexsort((u[idx], v[idx]))]
    uu, vv = u[order], v[order]
    m = len(order)
    same = vv[1:] == vv[:-1]
    gap = np.where(same, uu[1:] - uu[:-1], np.nan)
    w = p.spacing_window
    rowid = np.cumsum(np.r_[0, ~same])[:-1]
    pad = np.concatenate([np.full(w, np.nan), gap, np.full(w, np.nan)])
    rpad = np.concatenate([np.full(w, -1), rowid, np.full(w, -1)])
    win = sliding_window_view(pad, 2 * w + 1)
    rwin = sliding_window_view(rpad, 2 * w + 1)
    win = np.where(rwin == rowid[:, None], win, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        spacing = np.fmin(np.nanmedian(win[:, :w], axis=1), np.nanmedian(win[:, w + 1 :], axis=1))
    small = same & (gap < p.min_gap_ratio * spacing)
    big = ~same | ~(gap <= p.max_gap_ratio * spacing)
    bad = np.zeros(m, bool)
    bad[:-1] |= small
    bad[1:] |= small
    cut = np.ones(m, bool)
    cut[1:] = big | small | bad[:-1] | bad[1:]
    rid = np.cumsum(cut) - 1
    rk = np.arange(m) - np.flatnonzero(cut)[rid]
    run[order[~bad]] = rid[~bad]
    rank[order[~bad]] = rk[~bad]
    return run, rank


def test_row_runs_equal_numpy():
    rng = np.random.default_rng(4)
    for _ in range(5):
        u, v, seg = _rows(rng)
        u[rng.random(u.size) < 0.05] += rng.uniform(0, 2)  # double detections
        for p in (OrderParams(), OrderParams(spacing_window=2)):
            got = row_runs(u, v, seg >= 0, p)
            want = _row_runs_numpy(u, v, seg >= 0, p)
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def _run_offsets_numpy(run, rank, vote, weight, n_runs, p):
    """:func:`run_offsets` with ``np.unique`` and ``np.bincount``."""
    out = np.full(n_runs, np.iinfo(np.intp).min, np.intp)
    sel = (vote >= 0) & (run >= 0) & (weight > 0)
    r, off, wt = run[sel], vote[sel] - rank[sel], weight[sel]
    lo = int(off.min())
    span = int(off.max()) - lo + 1
    uk, inv = np.unique(r.astype(np.int64) * span + (off - lo), return_inverse=True)
    kw, kc, kr = np.bincount(inv, weights=wt), np.bincount(inv), uk // span
    total_w = np.bincount(r, weights=wt, minlength=n_runs)
    o = np.lexsort((kw, kr))
    best = o[np.r_[kr[o][1:] != kr[o][:-1], True]]
    br = kr[best]
    ok = (kw[best] >= p.min_agree * total_w[br]) & (kc[best] >= p.min_votes)
    out[br[ok]] = uk[best][ok] % span + lo
    return out


def test_run_offsets_equal_numpy():
    rng = np.random.default_rng(5)
    n = 3000
    run = rng.integers(-1, 200, n)
    rank = rng.integers(0, 20, n)
    vote = np.where(rng.random(n) < 0.7, rank + rng.integers(0, 3, n), -1)
    weight = np.round(rng.random(n), 1)  # ties of weight between offsets
    p = OrderParams(min_agree=0.5, min_votes=2)
    got = run_offsets(run, rank, vote, weight, 200, p)
    assert np.array_equal(got, _run_offsets_numpy(run, rank, vote, weight, 200, p))
    assert (got != np.iinfo(np.intp).min).sum() > 20


def test_rows_to_sample_equal_brute_force():
    rng = np.random.default_rng(7)
    seg = rng.integers(-1, 15, 800)
    v = np.round(rng.uniform(0, 300, 800), 1)
    sample = rng.random(800) < 0.1
    got = _rows_to_sample(by_segment(seg, v), seg, v, sample)
    for i in range(800):
        s = np.flatnonzero(sample & (seg == seg[i]))
        want = np.min(np.abs(v[s] - v[i])) if seg[i] >= 0 and s.size else np.inf
        assert got[i] == want

"""The vote of a segment's samples (paper section 4.2): the slit whose templates match best on
average, and a confidence from its margin over the second-best slit.

Used by the template identification (:mod:`~multislit.identify.labelling`) and the check of
the previous frame's labels (:mod:`~multislit.identify.prior`).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.identify.segments import group_order

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Segments with fewer sample points are dropped (too short to vote).
MIN_SAMPLES = 3
#: A segment's best mean NCC must reach this.
MIN_SCORE = 0.15
#: Standard error taken for a segment with one sample, whose spread cannot be measured (NCC).
ONE_SAMPLE_SE = 0.3
#: NCC counted for a hypothesis without a candidate (the slit's reference curve does not meet
#: the sample's epipolar line in the rows it was seen in, or its template would leave the
#: image).
NO_CANDIDATE = -0.2


def _mean_difference(
    X: F64, starts: NDArray[np.intp], n: NDArray[np.intp], a: I64, b: I64
) -> tuple[F64, F64]:
    """Per group of consecutive rows of ``X`` (M, N) (group g: ``n[g]`` rows from
    ``starts[g]``): the mean of ``X[:, a[g]] - X[:, b[g]]`` over its rows, and the standard
    error of that mean (from the rows' spread; 0 for a group of one row)."""
    grp = np.repeat(np.arange(len(starts)), n)
    rows = np.arange(len(X))
    d = X[rows, a[grp]] - X[rows, b[grp]]
    dm = np.add.reduceat(d, starts) / n
    ss = np.add.reduceat((d - dm[grp]) ** 2, starts)
    return dm, np.sqrt(ss / np.maximum(n - 1, 1)) / np.sqrt(n)


@njit(cache=True)
def scored_rows(scores):
    """(M,) bool: the rows of ``scores`` (M, N) with a finite score (a candidate)."""
    out = np.zeros(scores.shape[0], np.bool_)
    for i in range(scores.shape[0]):
        for j in range(scores.shape[1]):
            if np.isfinite(scores[i, j]):
                out[i] = True
                break
    return out


@njit(cache=True)
def filled_rows(scores, rows, fill):
    """(R, N) float64: the rows ``rows`` (R,) of ``scores`` (M, N), ``fill`` for the scores
    that are not finite."""
    out = np.empty((len(rows), scores.shape[1]))
    for i in range(len(rows)):
        for j in range(scores.shape[1]):
            x = scores[rows[i], j]
            out[i, j] = x if np.isfinite(x) else fill
    return out


def segment_votes(seg_of_sample: I64, scores: F64) -> dict[int, tuple[int, float, float, int]]:
    """Per segment: (best slit, confidence, best mean score, number of samples).

    The samples' scores ``scores`` (M, N) are averaged per slit (a hypothesis without a
    candidate counting ``NO_CANDIDATE``); the best slit's confidence is its margin over the
    second best, less the standard error of that margin (from the samples' spread;
    ``ONE_SAMPLE_SE`` for one sample), over 0.3, clipped to 0..1.
    """
    out: dict[int, tuple[int, float, float, int]] = {}
    if len(scores) == 0:
        return out
    N = scores.shape[1]
    good = scored_rows(scores)
    lo = int(seg_of_sample.min())
    key = seg_of_sample - lo  # >= 0
    n_all = np.bincount(key)
    n_good = np.bincount(key[good], minlength=len(n_all))
    for sid in np.flatnonzero((n_all > 0) & (n_good == 0)) + lo:
        out[int(sid)] = (-1, 0.0, np.nan, 0)
    rows = group_order(np.where(good, key, -1))  # by segment, then as given
    if rows.size == 0:
        return out
    s_sorted = seg_of_sample[rows]
    starts = np.flatnonzero(np.r_[True, s_sorted[1:] != s_sorted[:-1]])
    n = np.diff(np.r_[starts, len(rows)])
    # a hypothesis without a candidate counts as a bad match
    Sz = filled_rows(scores, rows, NO_CANDIDATE)
    mean = np.add.reduceat(Sz, starts, axis=0) / n[:, None]  # (G, N)
    k1 = np.argmax(mean, axis=1)
    g = np.arange(len(starts))
    m1 = mean[g, k1]
    if N > 1:
        rest = mean.copy()
        rest[g, k1] = -np.inf
        k2 = np.argmax(rest, axis=1)
        m2 = rest[g, k2]
        _, se = _mean_difference(Sz, starts, n, k1, k2)
    else:  # one slit: its margin over a score of -1
        m2 = np.full(len(starts), -1.0)
        d1 = np.c_[Sz[:, 0] + 1.0, np.zeros(len(Sz))]
        _, se = _mean_difference(d1, starts, n, np.zeros_like(g), np.ones_like(g))
    # margin, discounted by its uncertainty (few or disagreeing samples)
    se = np.where(n > 1, se, ONE_SAMPLE_SE)
    margin = np.maximum(0.0, m1 - m2 - se)
    conf = np.clip(margin / 0.3, 0.0, 1.0)
    for j, sid in enumerate(s_sorted[starts]):
        out[int(sid)] = (int(k1[j]), float(conf[j]), float(m1[j]), int(n[j]))
    return out

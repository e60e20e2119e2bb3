"""Scoring results against the simulator's ground truth (for tests, benchmarks and rig design)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def identification_metrics(ident, truth_slit: NDArray) -> dict:
    """Score an identification against the simulator's per-pixel truth.

    correct : share of output points whose slit is the true one at their pixel (or a neighbour
        in the row: a centre can round onto the stripe's edge pixel)
    wrong_confident : share of output points that are wrong and have confidence >= 0.5
    coverage : share of true stripe-centre pixels (the middle of each lit run of one slit in a
        row) that have an output point of that slit within 1.5 px in the same row
    """
    h, w = truth_slit.shape
    ok = ident.identified
    u, v, k = ident.u[ok], ident.v[ok], ident.slit[ok]
    r = np.clip(np.round(v).astype(int), 0, h - 1)
    cand = np.stack(
        [truth_slit[r, np.clip(np.round(u).astype(int) + d, 0, w - 1)] for d in (0, -1, 1)], 1
    )
    correct = (cand == k[:, None]).any(1)
    wrong = ~correct & (cand >= 0).any(1)
    hi = ident.confidence[ok] >= 0.5
    # true stripe-centre pixels: middle of each run of one slit label along a row
    pad = np.full((h, 1), -1, truth_slit.dtype)
    t = np.hstack([pad, truth_slit, pad])
    change = np.diff(t, axis=1) != 0
    rows, cols = np.nonzero(change)
    centres = []
    for row in np.unique(rows):
        b = cols[rows == row]
        for a, e in zip(b[:-1], b[1:], strict=True):
            lab = truth_slit[row, a]
            if lab >= 0 and e - a >= 2:
                centres.append((row, (a + e - 1) / 2, lab))
    got = 0
    pts: dict = {}
    for uu, vv, kk in zip(u, np.round(v).astype(int), k, strict=True):
        pts.setdefault((vv, kk), []).append(uu)
    for row, c, lab in centres:
        us = pts.get((row, lab))
        got += bool(us) and min(abs(x - c) for x in us) <= 1.5
    n = max(int(ok.sum()), 1)
    return {
        "points": int(ok.sum()),
        "correct": float(correct.sum() / n),
        "wrong_confident": float((wrong & hi).sum() / n),
        "coverage": got / max(len(centres), 1),
    }

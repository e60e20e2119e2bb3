"""Prototype: slit labels for groups of stripe pieces tied by their order in the rows.

A comparison for the identification's next model, kept beside the benchmarks (not used by the
library). Two pieces side by side in a row of one run of stripes (:func:`~multislit.identify.
order.row_runs`) are taken to be consecutive slits where that holds in at least ``SUPPORT``
rows and ``SHARE`` of the rows both pieces have, their gap is 0.75-1.33 reference slit spacings
and their brightness differs by less than ``PEAK_RATIO``. Such relations, strongest first, merge
pieces into groups with one unknown slit offset each, unless the dots of either side contradict
the merged group's best slit (its mean NCC lower than the side's own best by more than ``Z``
standard errors). A group takes the slit its summed dot scores prefer; its confidence is the
margin over the next slit less its standard error, as for one piece. A piece whose own dots
contradict its group's slit is left out.

It prints, per scan, object and backdrop figures (coverage / wrong / wrong with confidence >=
0.5, %) of :func:`multislit.identify.identify` (the dots, the order rules and the dots' veto) and
of the groups, then the means over all scans.

Run:  .venv/bin/python benchmarks/bench_piece_groups.py CAPTURE [CAPTURE ...]
(captures from :func:`multislit.sim.simulate_zoo_capture`; their truth files hold the object
mask).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from multislit.identify import Identification, identify, prepare_reference
from multislit.identify.labelling import (
    _MIN_SAMPLES,
    _MIN_SCORE,
    _sample_scores,
    _sampled_segments,
    _vouched_points,
)
from multislit.identify.matching import _Options
from multislit.identify.order import OrderParams, row_runs
from multislit.identify.reference import curve_u
from multislit.identify.segments import (
    split_at_winner_changes,
)
from multislit.io import Capture
from multislit.sim import object_metrics
from multislit.stripes import as_image, extract_slits

SUPPORT = 3  # least rows in which two pieces are neighbours in a run
SHARE = 0.6  # least share of their common rows in which they are
GAP = (0.75, 1.33)  # their gap, in reference slit spacings
PEAK_RATIO = 1.5  # most brightness ratio of the two stripes
Z = 2.0  # standard errors by which dots contradict a slit
MISSING = -0.2  # NCC counted for a hypothesis without a candidate


def local_spacing(ref, u, v):
    """(M,) px: the middle reference's slit spacing at (u, v)."""
    r = ref.curves.shape[0] // 2
    U = np.sort(curve_u(ref.curves[r][None], v[:, None]), axis=1)
    j = np.clip([np.searchsorted(U[i], u[i]) for i in range(len(u))], 1, U.shape[1] - 1)
    rows = np.arange(len(u))
    return U[rows, j] - U[rows, j - 1]


def relations(ex, seg, ref):
    """Pairs of pieces (left, right) neighbours in runs, and the rows they are."""
    run, rank = row_runs(ex.u, ex.v, seg >= 0, OrderParams())
    idx = np.flatnonzero(run >= 0)
    o = idx[np.lexsort((rank[idx], run[idx]))]
    a, b = o[:-1], o[1:]
    keep = (run[a] == run[b]) & (rank[b] == rank[a] + 1) & (seg[a] != seg[b])
    a, b = a[keep], b[keep]
    gap = (ex.u[b] - ex.u[a]) / local_spacing(ref, 0.5 * (ex.u[a] + ex.u[b]), ex.v[a])
    ratio = ex.peak[b] / np.maximum(ex.peak[a], 1e-6)
    ok = (gap > GAP[0]) & (gap < GAP[1]) & (ratio < PEAK_RATIO) & (ratio > 1 / PEAK_RATIO)
    key = seg[a[ok]].astype(np.int64) * 1_000_000 + seg[b[ok]]
    uk, cnt = np.unique(key, return_counts=True)
    return uk // 1_000_000, uk % 1_000_000, cnt


def shifted(X, offset, n):
    """Rows of scores per slit k -> per group slit b (k = b + offset)."""
    b = np.arange(n) + offset
    ok = (b >= 0) & (b < n)
    out = np.full_like(X, MISSING)
    out[:, ok] = X[:, b[ok]]
    return out


def stats(X):
    mean = X.mean(0)
    k = int(np.argmax(mean))
    if len(X) < 2:
        return mean, k, np.full(len(mean), 0.3)
    se = (X[:, k : k + 1] - X).std(0, ddof=1) / np.sqrt(len(X))
    return mean, k, np.maximum(se, 1e-3)


def compatible(X, j):
    """Do the rows' dots allow slit j (not below their best by Z standard errors)?"""
    if len(X) == 0:
        return True
    mean, k, se = stats(X)
    return mean[k] - mean[j] <= Z * se[j] + 0.02


def vote(X):
    if len(X) < _MIN_SAMPLES:
        return -1, 0.0
    mean, k, se = stats(X)
    rest = mean.copy()
    rest[k] = -np.inf
    k2 = int(np.argmax(rest))
    return k, float(np.clip((mean[k] - mean[k2] - se[k2]) / 0.3, 0, 1))


def group_labels(seg, si, scores, ex, ref):
    n = ref.num_slits
    Sz = np.where(np.isfinite(scores), scores, MISSING)
    ss = seg[si]
    pieces = [int(s) for s in np.unique(seg[seg >= 0])]
    rows = {s: Sz[ss == s] for s in pieces}
    vrows = {s: set(np.rint(ex.v[seg == s]).astype(int).tolist()) for s in pieces}
    members = {s: {s: 0} for s in pieces}
    group = {s: s for s in pieces}
    ev = dict(rows)
    pa, pb, cnt = relations(ex, seg, ref)
    for i in np.argsort(-cnt, kind="stable"):
        a, b, c = int(pa[i]), int(pb[i]), int(cnt[i])
        if c < SUPPORT or c < SHARE * len(vrows[a] & vrows[b]):
            continue
        ga, gb = group[a], group[b]
        if ga == gb:
            continue
        delta = members[ga][a] + 1 - members[gb][b]
        xb = shifted(ev[gb], delta, n)
        X = np.vstack([ev[ga], xb])
        if len(X):
            best = int(np.argmax(X.mean(0)))
            if not (compatible(ev[ga], best) and compatible(xb, best)):
                continue
        for p, o in members[gb].items():
            members[ga][p] = o + delta
            group[p] = ga
        ev[ga] = X
        del members[gb], ev[gb]
    lut_k = np.full(int(seg.max()) + 1, -1)
    lut_c = np.zeros(int(seg.max()) + 1)
    for g, mem in members.items():
        k, c = vote(ev[g])
        for p, o in mem.items():
            if k < 0 or not 0 <= k + o < n or not compatible(rows[p], k + o):
                continue
            lut_k[p], lut_c[p] = k + o, c
    return lut_k, lut_c


def prepare(img, ref, p):
    ex = extract_slits(img, stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px)
    seg, si, step, hh = _sampled_segments(ex, ref, p)
    scores = _sample_scores(ex, seg, si, ref, hh, p)
    seg = split_at_winner_changes(seg, ex.v, si, scores, _MIN_SCORE)
    return ex, seg, si, scores, max(step, hh), hh


def groups_identify(img, ref):
    p = _Options()
    img = as_image(img)
    ex, seg, si, scores, reach, hh = prepare(img, ref, p)
    lut_k, lut_c = group_labels(seg, si, scores, ex, ref)
    lut_k[lut_c < p.min_confidence] = -1
    has = _vouched_points(ex, seg, si, scores, reach, lut_k, hh)
    # pieces labelled by their group alone (no sample of their own): all their points
    sampled = np.zeros(len(lut_k), bool)
    sampled[seg[si]] = True
    has |= (seg >= 0) & (lut_k[np.maximum(seg, 0)] >= 0) & ~sampled[np.maximum(seg, 0)]
    slit = np.where(has, lut_k[np.maximum(seg, 0)], -1)
    conf = np.where(slit >= 0, lut_c[np.maximum(seg, 0)], 0.0)
    return Identification(ex.u, ex.v, slit, conf, seg, ex.peak, ex.width, 0, 0, {}, "", ex)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", type=Path, nargs="+")
    args = ap.parse_args()
    methods = {"identify": identify, "groups": groups_identify}
    table = {name: [] for name in methods}
    for d in args.captures:
        cap = Capture.open(d)
        ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
        for p in cap.scans:
            img = cap.image(p)
            tr = np.load(d / "truth" / f"{p.stem}.npz")
            out = []
            for name, fn in methods.items():
                t = time.perf_counter()
                ident = fn(img, ref)
                dt = time.perf_counter() - t
                m = object_metrics(ident, tr["slit"], tr["object"])
                o, b = m["object"], m["backdrop"]
                row = [o["coverage"], o["wrong"], o["wrong_confident"], b["coverage"], b["wrong"]]
                table[name].append(100 * np.array(row))
                out.append(
                    f"{name}: objects {100 * o['coverage']:.1f} / {100 * o['wrong']:.2f} / "
                    f"{100 * o['wrong_confident']:.2f}, backdrop {100 * b['coverage']:.1f} / "
                    f"{100 * b['wrong']:.2f}, {dt:.1f} s"
                )
            print(f"{d.name} {p.stem}: " + " | ".join(out), flush=True)
    for name, rows in table.items():
        a = np.array(rows)
        print(
            f"{name}: objects covered {a[:, 0].mean():.1f} % (mean; worst {a[:, 0].min():.1f}), "
            f"wrong {a[:, 1].mean():.2f} % (worst {a[:, 1].max():.2f}), wrong conf>=0.5 "
            f"{a[:, 2].mean():.2f} % (worst {a[:, 2].max():.2f}); backdrop covered "
            f"{a[:, 3].mean():.1f} % (worst {a[:, 3].min():.1f}), wrong worst {a[:, 4].max():.2f} %"
        )


if __name__ == "__main__":
    main()

"""Prototype: slit identification as ONE labelling of stripe chunks (not used by the library).

A comparison for the identification's next model, kept beside the benchmarks. Every segment is
cut into chunks of a few sample points. Each chunk gets a cost per slit hypothesis from the dot
templates (NCC deficit to the sample's best slit
a hypothesis without an epipolar candidate is
penalised). Two kinds of terms tie the chunks together: consecutive chunks of one segment should
keep their slit (a Potts cost, weakened where the stripe kinks between them), and two chunks side
by side in a row should be consecutive slits (a cost per shared row when not, larger when out of
order). Min-sum loopy belief propagation solves it
a chunk's confidence is the margin of its
best slit's belief over the next. Points of chunks under ``--margin`` are left out, as are the
rows at segment ends and junctions.

It prints, per scan, object and backdrop figures of :func:`multislit.identify.identify` (the
rules) next to the prototype's: coverage / wrong / wrong with confidence >= 0.5 (%).

Run:  .venv/bin/python benchmarks/bench_graph_labelling.py CAPTURE [CAPTURE ...] [--margin 8]
(captures from :func:`multislit.sim.simulate_zoo_capture` or ``multislit simulate``
their
truth files must hold the object mask).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from multislit.identify import Identification, identify, prepare_reference
from multislit.identify.labelling import _sample_scores, _sampled_segments
from multislit.identify.matching import _Options
from multislit.identify.segments import near_segment_ends
from multislit.io import Capture
from multislit.sim import object_metrics
from multislit.stripes import as_image, extract_slits

NO_CAND = 0.6  # per-sample cost of a hypothesis with no candidate (outside the volume / image)
BETA = 10.0  # cost per unit of NCC deficit, per sample
LINK = 6.0  # cost of two consecutive chunks of one segment taking different slits
ROW_ADJ = 0.6  # per row, cost of adjacent stripes not being consecutive slits
ROW_REV = 1.0  # per row, cost of two stripes in a row out of slit order
ROW_CAP = 30  # rows counted per pair at most
ADJ_RATIO = 1.6  # gaps below this many reference spacings count as adjacent stripes
KINK_PX = 1.0
KINK_SLOPE = 0.25
LINK_WEAK = 1.0
CHUNK = 3  # samples per chunk
ITER = 40
DAMP = 0.5


def chunks(seg, v, si, usable):
    """Chunk id per sample (-1 unusable), chunk's segment, and per point chunk id."""
    ss = seg[si]
    o = np.lexsort((v[si], ss))
    o = o[usable[o]]
    so = ss[o]
    first = np.r_[True, so[1:] != so[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(o)), 0))
    rank = np.arange(len(o)) - start
    new = first | (rank % CHUNK == 0)
    cid_o = np.cumsum(new) - 1
    cid = np.full(len(si), -1)
    cid[o] = cid_o
    cseg = so[new]
    return cid, cseg, o


def point_chunks(seg, v, si, cid):
    """Per point: chunk of the nearest usable sample of its segment (-1 if none)."""
    ok = cid >= 0
    s_i = si[ok]
    c_i = cid[ok]
    o = np.lexsort((v[s_i], seg[s_i]))
    s_i, c_i = s_i[o], c_i[o]
    key_s = seg[s_i].astype(float) * 1e6 + v[s_i]
    key_p = seg.astype(float) * 1e6 + v
    out = np.full(len(seg), -1)
    if len(s_i) == 0:
        return out, np.full(len(seg), np.inf)
    j = np.clip(np.searchsorted(key_s, key_p), 1, max(1, len(s_i) - 1))
    best = np.full(len(seg), np.inf)
    for jj in (j - 1, np.minimum(j, len(s_i) - 1)):
        same = seg[s_i[jj]] == seg
        d = np.where(same, np.abs(v[s_i[jj]] - v), np.inf)
        better = d < best
        out[better] = c_i[jj][better]
        best = np.minimum(best, d)
    out[seg < 0] = -1
    return out, best


def unary(scores, cid, n_chunks):
    S = np.where(np.isfinite(scores), scores, np.nan)
    usable = cid >= 0
    top = np.nanmax(np.where(np.isfinite(S), S, -1), axis=1)
    cost = np.where(
        np.isfinite(S),
        BETA * np.maximum(top[:, None] - S, 0),
        BETA * NO_CAND + BETA * np.maximum(top[:, None], 0),
    )
    U = np.zeros((n_chunks, S.shape[1]))
    np.add.at(U, cid[usable], cost[usable])
    return U


def row_edges(u, v, pchunk, spacing):
    """Pairs (a, b) of chunks side by side in rows (a left of b): rows counted, adjacent or gap."""
    r = np.rint(v).astype(np.int64)
    o = np.lexsort((u, r))
    ro, co, uo = r[o], pchunk[o], u[o]
    same_row = ro[1:] == ro[:-1]
    a, b = co[:-1], co[1:]
    gap = uo[1:] - uo[:-1]
    m = same_row & (a >= 0) & (b >= 0) & (a != b)
    adj = gap < ADJ_RATIO * spacing
    A, B, ADJ = a[m], b[m], adj[m]
    if len(A) == 0:
        return np.zeros((0, 2), int), np.zeros(0), np.zeros(0, bool)
    k = A.astype(np.int64) * (2**31) + B
    uk, inv = np.unique(k, return_inverse=True)
    n = np.bincount(inv)
    nadj = np.bincount(inv, weights=ADJ.astype(float))
    pairs = np.c_[uk // (2**31), uk % (2**31)]
    return pairs, np.minimum(n, ROW_CAP).astype(float), nadj >= 0.5 * n


def _order_msg(h, w_adj, w_rev, forward, is_adj):
    """min over the source label of h(src) + pairwise(d = dst - src) (forward) or d = src - dst."""
    E, N = h.shape
    big = 1e9
    if forward:  # destination kb, source ka, d = kb - ka
        shift1 = np.c_[np.full((E, 1), big), h[:, :-1]]  # ka = kb - 1
        pre = np.minimum.accumulate(h, axis=1)  # min_{ka <= j}
        skip = np.c_[np.full((E, 2), big), pre[:, :-2]][:, :N]  # ka <= kb - 2
        suf = np.minimum.accumulate(h[:, ::-1], axis=1)[:, ::-1]  # min_{ka >= kb}
        rev = suf
    else:  # destination ka, source kb, d = kb - ka
        shift1 = np.c_[h[:, 1:], np.full((E, 1), big)]  # kb = ka + 1
        suf = np.minimum.accumulate(h[:, ::-1], axis=1)[:, ::-1]
        skip = np.c_[suf[:, 2:], np.full((E, 2), big)][:, :N]  # kb >= ka + 2
        pre = np.minimum.accumulate(h, axis=1)
        rev = pre  # kb <= ka
    skip_cost = np.where(is_adj, w_adj, 0.0)[:, None]
    return np.minimum(np.minimum(shift1, skip + skip_cost), rev + w_rev[:, None])


def solve(U, link_pairs, row_pairs, row_n, row_adj, link_w):
    C, N = U.shape
    # directed edges: potts (link) both ways, order (row) forward and backward
    Lp = link_pairs
    src = np.r_[Lp[:, 0], Lp[:, 1], row_pairs[:, 0], row_pairs[:, 1]]
    dst = np.r_[Lp[:, 1], Lp[:, 0], row_pairs[:, 1], row_pairs[:, 0]]
    nL, nR = len(Lp), len(row_pairs)
    kind = np.r_[np.zeros(2 * nL, int), np.ones(nR, int), 2 * np.ones(nR, int)]
    rev_idx = np.r_[
        np.arange(nL, 2 * nL),
        np.arange(nL),
        np.arange(2 * nL + nR, 2 * nL + 2 * nR),
        np.arange(2 * nL, 2 * nL + nR),
    ]
    w_adj = np.r_[np.zeros(2 * nL), ROW_ADJ * row_n, ROW_ADJ * row_n]
    w_rev = np.r_[np.zeros(2 * nL), ROW_REV * row_n, ROW_REV * row_n]
    is_adj = np.r_[np.zeros(2 * nL, bool), row_adj, row_adj]
    M = np.zeros((len(src), N))
    for _ in range(ITER):
        Bel = U.copy()
        np.add.at(Bel, dst, M)
        h = Bel[src] - M[rev_idx]
        new = np.empty_like(M)
        k0 = kind == 0
        lw = np.r_[link_w, link_w]
        new[k0] = np.minimum(h[k0], h[k0].min(axis=1, keepdims=True) + lw[:, None])
        for kd, fw in ((1, True), (2, False)):
            kk = kind == kd
            if kk.any():
                new[kk] = _order_msg(h[kk], w_adj[kk], w_rev[kk], fw, is_adj[kk])
        new -= new.min(axis=1, keepdims=True)
        M = DAMP * M + (1 - DAMP) * new
    Bel = U.copy()
    np.add.at(Bel, dst, M)
    return Bel


def label(ex, seg, si, scores, spacing):
    usable = np.isfinite(scores).any(axis=1)
    cid, cseg, _ = chunks(seg, ex.v, si, usable)
    C = int(cid.max()) + 1 if (cid >= 0).any() else 0
    K = len(ex.u)
    if C == 0:
        return np.full(K, -1), np.zeros(K), np.full(K, -1), np.full(K, np.inf)
    U = unary(scores, cid, C)
    # link edges between consecutive chunks of a segment
    same = cseg[1:] == cseg[:-1]
    link = np.c_[np.arange(C - 1)[same], np.arange(1, C)[same]]
    pch, dist = point_chunks(seg, ex.v, si, cid)
    # each chunk's line u = a + b v from its points; a kink between two chunks weakens the link
    ok = pch >= 0
    n = np.bincount(pch[ok], minlength=C).astype(float)
    sv = np.bincount(pch[ok], ex.v[ok], C)
    su = np.bincount(pch[ok], ex.u[ok], C)
    svv = np.bincount(pch[ok], ex.v[ok] ** 2, C)
    suv = np.bincount(pch[ok], ex.u[ok] * ex.v[ok], C)
    vm = sv / np.maximum(n, 1)
    um = su / np.maximum(n, 1)
    var = svv / np.maximum(n, 1) - vm**2
    b = np.where(var > 1e-6, (suv / np.maximum(n, 1) - um * vm) / np.maximum(var, 1e-6), 0.0)
    vmax = np.full(C, -np.inf)
    np.maximum.at(vmax, pch[ok], ex.v[ok])
    i, j = link[:, 0], link[:, 1]
    vb = vmax[i]
    ui = um[i] + b[i] * (vb - vm[i])
    uj = um[j] + b[j] * (vb - vm[j])
    kink = (np.abs(ui - uj) > KINK_PX) | (np.abs(b[i] - b[j]) > KINK_SLOPE)
    link_w = np.where(kink, LINK_WEAK, LINK)
    rp, rn, radj = row_edges(ex.u, ex.v, pch, spacing)
    Bel = solve(U, link, rp, rn, radj, link_w)
    k1 = np.argmin(Bel, axis=1)
    srt = np.sort(Bel, axis=1)
    margin = srt[:, 1] - srt[:, 0]
    return k1, margin, pch, dist


def graph_identify(img, ref, margin_min):
    p = _Options()
    img = as_image(img)
    ex = extract_slits(img, stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px)
    seg, si, step, hh = _sampled_segments(ex, ref, p)
    scores = _sample_scores(ex, seg, si, ref, hh, p)
    k1, margin, pch, dist = label(ex, seg, si, scores, ref.spacing_px)
    K = len(ex.u)
    slit = np.full(K, -1)
    conf = np.zeros(K)
    ok = pch >= 0
    slit[ok] = k1[pch[ok]]
    conf[ok] = np.clip(margin[pch[ok]] / (2 * margin_min), 0, 1)
    keep = ok & (margin[np.maximum(pch, 0)] >= margin_min) & (dist <= max(step, hh))
    lut_k = np.full(int(seg.max()) + 1, -1)
    lut_k[seg[ok]] = k1[pch[ok]]
    keep &= ~near_segment_ends(ex.u, ex.v, seg, lut_k, 2, max(2, int(np.ceil(0.4 * hh))))
    slit[~keep] = -1
    conf[~keep] = 0
    return Identification(ex.u, ex.v, slit, conf, seg, ex.peak, ex.width, 0, 0, {}, "", ex)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", type=Path, nargs="+")
    ap.add_argument("--margin", type=float, default=8.0, help="least belief margin kept")
    args = ap.parse_args()
    for d in args.captures:
        cap = Capture.open(d)
        ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
        for p in cap.scans:
            img = cap.image(p)
            tr = np.load(d / "truth" / f"{p.stem}.npz")
            out = []
            for name in ("rules", "graph"):
                t = time.perf_counter()
                if name == "rules":
                    ident = identify(img, ref)
                else:
                    ident = graph_identify(img, ref, args.margin)
                dt = time.perf_counter() - t
                m = object_metrics(ident, tr["slit"], tr["object"])
                o, b = m["object"], m["backdrop"]
                out.append(
                    f"{name}: objects {100 * o['coverage']:.1f} / {100 * o['wrong']:.2f} / "
                    f"{100 * o['wrong_confident']:.2f}, backdrop {100 * b['coverage']:.1f} / "
                    f"{100 * b['wrong']:.2f}, {dt:.1f} s"
                )
            print(f"{d.name} {p.stem}: " + " | ".join(out), flush=True)


if __name__ == "__main__":
    main()

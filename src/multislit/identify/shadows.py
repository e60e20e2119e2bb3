"""Shadows: where a slit's stripe breaks off on a surface, something nearer took its light.

A slit's light fans out from the projector in its plane; along each of its rays it lights the
first surface it meets and nothing behind. Seen from the dot source, the rays of slit k are
told apart by their angle along the slits (``psi``), and a stripe piece under slit k covers an
interval of it at some range. Where the stripe of slit k on one surface (a wall behind the
objects) breaks off and resumes at the same range, its rays in between lit something nearer:
a piece that lies in front of the gap under slit k is the shadow's caster. One of the pieces
that could be the caster must carry slit k, or the gap stays unexplained
(:func:`shadow_factors`, "one of them" factors of the labelling,
:func:`~multislit.identify.graph.label_pieces`).

An object's stripe that sits where another slit would fall on the wall behind it (a "ghost"
of the wall's stripe) lies at the wall's range under that slit and casts no shadow; under its
own slit it casts the shadow seen on the wall.

Units: rad (angles from the dot source), mm (ranges), nats.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Log-likelihood lost by a gap in a stripe that no piece casts (a stripe broken off and
#: resumed on one surface without a cause) ...
SHADOW_COST = 4.0
#: ... where the gap spans at least this angle along the slits (rad: several rows) ...
_MIN_GAP = 0.004
#: ... and its two sides lie at one range (within this share).
_SAME_SURFACE = 0.03
#: A caster lies nearer than the surface by at least this share of its range.
_NEARER = 0.03


def shadow_factors(
    span: F64, label: I64, confident: NDArray[np.bool_]
) -> tuple[I64, F64, I64, I64]:
    """The gaps in the stripes of a first labelling, each with the pieces that could cast it.

    A gap of slit k is a stretch of angles along the slits where slit k does not light the
    surface its stripe lies on: where its stripe breaks off and resumes at one range, or
    where the stripes of slits k - 1 and k + 1 both run on at one range without it.

    Parameters
    ----------
    span : (W, N, 3) float, per window and slit: the sines of its least and largest angle along
        the slits and its mean range (mm) from the dot source (NaN: not a hypothesis)
    label : (W,) int64, a first labelling (-1: none)
    confident : (W,) bool, its windows trusted to say where each slit lights

    Returns
    -------
    slit (F,) int64, cost (F,) float64, start (F+1,) int64, candidates (M,) int64: factor f's
    candidate windows are ``candidates[start[f]:start[f+1]]``
    """
    w, n, _ = span.shape
    lo, hi, rng = (span[..., i].astype(np.float64) for i in range(3))
    cover = []
    for k in range(n):
        src = np.flatnonzero(confident & (label == k) & np.isfinite(lo[:, k]))
        src = src[np.argsort(lo[src, k])]
        cover.append((lo[src, k], hi[src, k], rng[src, k]))
    f_slit, f_cost, f_cand = [], [], []
    for k in range(n):
        cand = np.flatnonzero(np.isfinite(lo[:, k]))
        ca, cb, cr = lo[cand, k], hi[cand, k], rng[cand, k]
        gaps = _breaks(*cover[k])
        if 0 < k < n - 1:
            # missing where no stripe lies at that place under slit k (a stripe that is there
            # but not yet labelled is no gap)
            gaps += _missing(cover[k - 1], cover[k + 1], (ca, cb, cr))
        if not gaps:
            continue
        for g0, g1, r in _merged(gaps):
            inside = (cb > g0) & (ca < g1) & (cr < (1.0 - _NEARER) * r)
            if inside.any():
                f_slit.append(k)
                f_cost.append(SHADOW_COST)
                f_cand.append(cand[inside])
    start = np.r_[0, np.cumsum([len(c) for c in f_cand])].astype(np.int64)
    cands = np.concatenate(f_cand).astype(np.int64) if f_cand else np.zeros(0, np.int64)
    return np.asarray(f_slit, np.int64), np.asarray(f_cost, np.float64), start, cands


def _breaks(a: F64, b: F64, r: F64) -> list[tuple[float, float, float]]:
    """Where a stripe's cover (intervals ``a``..``b`` sorted by ``a``, ranges ``r``) breaks off
    and resumes at one range: (start, end, range) each."""
    out = []
    if len(a) < 2:
        return out
    reach = np.maximum.accumulate(b)
    last = np.maximum.accumulate(np.where(b == reach, np.arange(len(b)), 0))
    for i in range(len(a) - 1):
        g0, g1 = reach[i], a[i + 1]
        r0, r1 = r[last[i]], r[i + 1]
        if g1 - g0 >= _MIN_GAP and abs(r1 - r0) <= _SAME_SURFACE * max(r0, r1):
            out.append((float(g0), float(g1), float(min(r0, r1))))
    return out


def _missing(left: tuple, right: tuple, here: tuple) -> list[tuple[float, float, float]]:
    """Where the stripes on either side (covers ``left`` and ``right``: intervals and ranges)
    both run at one range and no stripe lies between them at that range (``here``: every
    window's interval and range under the slit between): (start, end, range) each."""
    out = []
    la, lb, lr = left
    ra, rb, rr = right
    ha, hb_, hr = here
    for i in range(len(la)):
        # the right stripe's intervals that overlap this one at one range
        ov = (ra < lb[i]) & (rb > la[i]) & (np.abs(rr - lr[i]) <= _SAME_SURFACE * lr[i])
        for j in np.flatnonzero(ov):
            s0, s1 = max(la[i], ra[j]), min(lb[i], rb[j])
            r = 0.5 * (lr[i] + rr[j])
            at = (np.abs(hr - r) <= _SAME_SURFACE * r) & (hb_ > s0) & (ha < s1)
            o = np.argsort(ha[at])
            for g0, g1 in _less(s0, s1, ha[at][o], hb_[at][o]):
                if g1 - g0 >= _MIN_GAP:
                    out.append((g0, g1, float(r)))
    return out


def _less(s0: float, s1: float, a: F64, b: F64) -> list[tuple[float, float]]:
    """The interval ``s0``..``s1`` less the intervals ``a``..``b`` (sorted by ``a``)."""
    out = []
    cur = s0
    for x0, x1 in zip(a.tolist(), b.tolist(), strict=True):
        if x1 <= cur or x0 >= s1:
            continue
        if x0 > cur:
            out.append((cur, min(x0, s1)))
        cur = max(cur, x1)
        if cur >= s1:
            break
    if cur < s1:
        out.append((cur, s1))
    return out


def _merged(gaps: list[tuple[float, float, float]]) -> list[tuple[float, float, float]]:
    """Overlapping gaps (start, end, range) merged, the nearer range kept."""
    gaps = sorted(gaps)
    out = [list(gaps[0])]
    for g0, g1, r in gaps[1:]:
        if g0 <= out[-1][1]:
            out[-1][1] = max(out[-1][1], g1)
            out[-1][2] = min(out[-1][2], r)
        else:
            out.append([g0, g1, r])
    return [tuple(x) for x in out]

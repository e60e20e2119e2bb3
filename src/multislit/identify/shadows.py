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

    Parameters
    ----------
    span : (W, N, 3) float, per window and slit: least and largest angle along the slits (rad)
        and mean range (mm) from the dot source (NaN: not a hypothesis)
    label : (W,) int64, a first labelling (-1: none)
    confident : (W,) bool, its windows trusted to say where each slit lights

    Returns
    -------
    slit (F,) int64, cost (F,) float64, start (F+1,) int64, candidates (M,) int64: factor f's
    candidate windows are ``candidates[start[f]:start[f+1]]``
    """
    w, n, _ = span.shape
    lo, hi, rng = (span[..., i].astype(np.float64) for i in range(3))
    f_slit, f_cost, f_cand = [], [], []
    for k in range(n):
        src = np.flatnonzero(confident & (label == k) & np.isfinite(lo[:, k]))
        if src.size < 2:
            continue
        src = src[np.argsort(lo[src, k])]
        a, b, r = lo[src, k], hi[src, k], rng[src, k]
        reach = np.maximum.accumulate(b)
        last = np.maximum.accumulate(np.where(b == reach, np.arange(len(b)), 0))
        cand = np.flatnonzero(np.isfinite(lo[:, k]))
        ca, cb, cr = lo[cand, k], hi[cand, k], rng[cand, k]
        for i in range(len(src) - 1):
            g0, g1 = reach[i], a[i + 1]
            if g1 - g0 < _MIN_GAP:
                continue
            r0, r1 = r[last[i]], r[i + 1]
            if abs(r1 - r0) > _SAME_SURFACE * max(r0, r1):
                continue
            inside = (cb > g0) & (ca < g1) & (cr < (1.0 - _NEARER) * min(r0, r1))
            if not inside.any():
                continue
            f_slit.append(k)
            f_cost.append(SHADOW_COST)
            f_cand.append(cand[inside])
    start = np.r_[0, np.cumsum([len(c) for c in f_cand])].astype(np.int64)
    cands = np.concatenate(f_cand).astype(np.int64) if f_cand else np.zeros(0, np.int64)
    return np.asarray(f_slit, np.int64), np.asarray(f_cost, np.float64), start, cands

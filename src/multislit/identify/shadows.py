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
from numba import njit
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
    where the stripes of slits k - 1 and k + 1 both run on at one range without it, and no
    stripe lies there at that range under slit k (a stripe that is there but not yet labelled
    is no gap). The angles are taken in bins of a quarter of the least gap.

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
    sp = np.ascontiguousarray(span, np.float64)
    ok = np.isfinite(sp[..., 0])
    if w == 0 or not ok.any():
        e = np.zeros(0, np.int64)
        return e, np.zeros(0), np.zeros(1, np.int64), e.copy()
    lo0 = float(np.min(sp[..., 0][ok]))
    binw = 0.25 * _MIN_GAP
    nb = int((float(np.max(sp[..., 1][ok])) - lo0) / binw) + 2
    f_slit = np.zeros(4 * n + 4, np.int64)
    f_start = np.zeros(4 * n + 5, np.int64)
    f_cand = np.zeros(max(1, w * 8), np.int64)
    nf = _gap_kernel(
        sp,
        np.ascontiguousarray(label, np.int64),
        np.ascontiguousarray(confident, np.bool_),
        lo0,
        binw,
        nb,
        _MIN_GAP,
        _SAME_SURFACE,
        _NEARER,
        f_slit,
        f_start,
        f_cand,
    )
    cand = f_cand[: f_start[nf]].copy()
    return f_slit[:nf].copy(), np.full(nf, SHADOW_COST), f_start[: nf + 1].copy(), cand


@njit(cache=True)
def _paint(cover, lo, hi, r, lo0, binw):
    """``cover`` (B,) keeps the least range ``r`` over the bins of ``lo`` .. ``hi``."""
    b0 = int((lo - lo0) / binw)
    b1 = int((hi - lo0) / binw)
    for b in range(max(b0, 0), min(b1, len(cover) - 1) + 1):
        if not cover[b] <= r:  # (also NaN)
            cover[b] = r


@njit(cache=True)
def _gap_kernel(span, label, confident, lo0, binw, nb, min_gap, same, nearer, f_slit, f_start,
                f_cand):  # fmt: skip
    """:func:`shadow_factors`' gaps and candidates; returns how many factors were written."""
    w, n, _ = span.shape
    cover = np.full((n, nb), np.nan)
    for i in range(w):
        k = label[i]
        if confident[i] and k >= 0 and np.isfinite(span[i, k, 0]):
            _paint(cover[k], span[i, k, 0], span[i, k, 1], span[i, k, 2], lo0, binw)
    surf = np.empty(nb)
    present = np.zeros(nb, np.bool_)
    nf = 0
    nc = 0
    for k in range(n):
        surf[:] = np.nan
        # where its own stripe breaks off and resumes at one range
        last = -1
        for b in range(nb):
            if np.isfinite(cover[k, b]):
                if last >= 0 and b - last > 1:
                    r0, r1 = cover[k, last], cover[k, b]
                    if abs(r1 - r0) <= same * max(r0, r1):
                        for g in range(last + 1, b):
                            surf[g] = min(r0, r1)
                last = b
        # where the stripes on either side run on at one range
        if 0 < k < n - 1:
            for b in range(nb):
                r0, r1 = cover[k - 1, b], cover[k + 1, b]
                if np.isfinite(r0) and np.isfinite(r1) and not np.isfinite(cover[k, b]):
                    if abs(r1 - r0) <= same * max(r0, r1):
                        r = 0.5 * (r0 + r1)
                        if not surf[b] <= r:
                            surf[b] = r
        # less where a stripe lies at that range under slit k
        present[:] = False
        for i in range(w):
            if not np.isfinite(span[i, k, 0]):
                continue
            b0 = max(int((span[i, k, 0] - lo0) / binw), 0)
            b1 = min(int((span[i, k, 1] - lo0) / binw), nb - 1)
            r = span[i, k, 2]
            for b in range(b0, b1 + 1):
                if np.isfinite(surf[b]) and abs(r - surf[b]) <= same * surf[b]:
                    present[b] = True
        b = 0
        while b < nb:
            if not (np.isfinite(surf[b]) and not present[b]):
                b += 1
                continue
            e = b
            rmin = surf[b]
            while e + 1 < nb and np.isfinite(surf[e + 1]) and not present[e + 1]:
                e += 1
                rmin = min(rmin, surf[e])
            g0 = lo0 + b * binw
            g1 = lo0 + (e + 1) * binw
            b = e + 1
            if g1 - g0 < min_gap or nf >= len(f_slit):
                continue
            start = nc
            for i in range(w):
                if (
                    np.isfinite(span[i, k, 0])
                    and span[i, k, 1] > g0
                    and span[i, k, 0] < g1
                    and span[i, k, 2] < (1.0 - nearer) * rmin
                    and nc < len(f_cand)
                ):
                    f_cand[nc] = i
                    nc += 1
            if nc > start:
                f_slit[nf] = k
                f_start[nf + 1] = nc
                nf += 1
    return nf

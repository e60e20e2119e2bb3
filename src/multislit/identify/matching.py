"""Dot templates of a scan matched with the reference dot images (paper, section 4.2).

Sample points are taken along each slit segment of a scan; the dot image around each one (its
template) is compared by normalised cross-correlation (NCC) with the reference dot images only
where the point's epipolar line meets each slit's reference curve: N candidates per reference
image instead of a search over the image. The result is a score per sample and slit, which
:mod:`~multislit.identify.labelling` turns into votes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.identify.patches import (
    bilinear_ncc_cells,
    cell_of,
    sample_sheared_patches,
)
from multislit.identify.reference import (
    ReferenceSet,
    curve_du,
    curve_u,
    intersect_line_curves,
)
from multislit.identify.segments import segment_runs

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Template half width across the slit, in reference slit spacings.
_TEMPLATE_HALF_WIDTH = 0.40
#: The template's height is chosen to hold about this many dots (from the dot density measured
#: in the references), between 0.5 and 4 slit spacings.
_TEMPLATE_DOTS = 12.0


def template_size(reference: ReferenceSet) -> tuple[int, int]:
    """Half width and half height (px) of the scan templates :func:`identify` matches.

    As wide as a band of dots beside a slit, tall enough to hold a dozen dots (from the dot
    density measured in the references), between 0.5 and 4 slit spacings.

    Parameters
    ----------
    reference : the prepared :class:`~multislit.identify.reference.ReferenceSet`

    Returns
    -------
    half_width, half_height : int, px
    """
    hw = max(3, int(round(_TEMPLATE_HALF_WIDTH * reference.spacing_px)))
    want = _TEMPLATE_DOTS / max(reference.dot_density, 1e-6) / (2 * hw + 1)
    hh = int(round(np.clip(want / 2, 0.5 * reference.spacing_px, 4.0 * reference.spacing_px)))
    return hw, max(4, hh)


@njit(cache=True)
def _sorted_positions(keys, want, pos):
    """``pos`` = ``np.clip(np.searchsorted(keys, want), 0, len(keys) - 1)`` for rows of
    ``want`` (M, J) that increase along each row (one binary search per row, then a walk)."""
    K = keys.size
    for m in range(want.shape[0]):
        p = np.searchsorted(keys, want[m, 0])
        for j in range(want.shape[1]):
            while p < K and keys[p] < want[m, j]:
                p += 1
            pos[m, j] = min(p, K - 1)


def _middle_curves_u(v: F64, si: NDArray[np.intp], ref: ReferenceSet) -> F64:
    """(M, N) px: the middle reference's slit curves at the rows ``v[si]`` of the samples."""
    r = ref.curves.shape[0] // 2
    return curve_u(ref.curves[r][None, :, :], v[si][:, None])


def template_row_shift(
    u: F64,
    v: F64,
    seg: I64,
    si: NDArray[np.intp],
    ref: ReferenceSet,
    hh: int,
    *,
    ref_u: F64 | None = None,
) -> F64:
    """(M, 2*hh+1) px: sideways shift of each template row so that the template follows its
    stripe's lean.

    A line u = a + s dv is fitted (least squares, all samples at once) to the centres of the
    sample's segment within +-hh rows; a sample with fewer than 3 such centres, or spanning
    fewer than 4 rows, keeps an upright template. The reference curves' own slant at the sample
    (the curve nearest it in the middle reference) is kept in the template. ``ref_u`` (M, N)
    px: the middle reference's curves in the samples' rows, if already at hand (default: made
    here).
    """
    dy = np.arange(-hh, hh + 1, dtype=np.float64)
    # the segment's centre in every template row (absent where the segment has no point there)
    order = segment_runs(seg, v)[0]
    span = float(np.ceil(v.max()) + 2 * hh + 2)
    keys = seg[order] * span + np.rint(v[order])
    want = (seg[si] * span + np.rint(v[si]))[:, None] + dy[None, :]
    pos = np.empty(want.shape, np.intp)
    _sorted_positions(keys, want, pos)
    found = keys[pos] == want
    w = found.astype(np.float64)
    uu = np.where(found, u[order[pos]] - u[si][:, None], 0.0)
    n = w.sum(axis=1)
    sy, syy = w @ dy, w @ (dy * dy)
    su, suy = uu.sum(axis=1), uu @ dy
    det = n * syy - sy * sy
    lo = np.where(found, dy, np.inf).min(axis=1)
    hi = np.where(found, dy, -np.inf).max(axis=1)
    use = (n >= 3) & (hi - lo >= min(4.0, hh)) & (det > 0)
    slope = np.where(use, (n * suy - sy * su) / np.where(use, det, 1.0), 0.0)
    # the reference curves' slant around the point stays in the template
    r = ref.curves.shape[0] // 2
    U = _middle_curves_u(v, si, ref) if ref_u is None else ref_u  # (M, N)
    k = np.argmin(np.abs(U - u[si][:, None]), axis=1)
    s_ref = np.where(use, curve_du(ref.curves[r, k], v[si]), 0.0)
    return (slope - s_ref)[:, None] * dy[None, :]


#: Neighbouring stripes in a row count for :func:`template_col_scale` at gaps of this range of
#: the reference's local slit spacing (the order's run gaps: a double detection below, a
#: hidden stripe above), and where the gaps either side agree within this share.
_GAP_RANGE = (0.3, 1.6)
_GAP_AGREE = 0.25


def template_col_scale(
    u: F64, v: F64, si: NDArray[np.intp], ref: ReferenceSet, *, ref_u: F64 | None = None
) -> F64:
    """(M,) px per template column: how far apart each sample's template samples its columns.

    A surface turned away from the projector squeezes the stripes and the dots between them
    alike (turned towards it, spreads them). Where the stripe centres next to a sample in its
    row, left and right, lie at gaps that agree within 25 % and within 0.3-1.6 of the
    reference's local slit spacing (between the middle reference's curves there), the template
    takes its columns that mean gap over the reference spacing apart; elsewhere 1 (a sample at
    an object's edge, a lone stripe).

    Parameters
    ----------
    u, v : (K,) float64, px, all the scan's stripe centres
    si : (M,) intp, the sample points (indices into ``u``, ``v``)
    ref : the prepared references
    ref_u : (M, N) float64, px, the middle reference's slit curves in the samples' rows, if
        already at hand (default: made here)

    Returns
    -------
    (M,) float64, 0.3-1.6 where measured, else 1
    """
    out = np.ones(len(si))
    if len(si) == 0 or ref.num_slits < 2:
        return out
    rows = np.rint(v).astype(np.int64)
    same = rows[1:] == rows[:-1]
    if np.all(rows[1:] >= rows[:-1]) and np.all(u[1:][same] >= u[:-1][same]):
        order = pos = np.arange(len(u))  # the extraction's order: by row, then column
    else:
        order = np.lexsort((u, rows))
        pos = np.empty(len(u), np.intp)
        pos[order] = np.arange(len(u))
    p = pos[si]
    left = order[np.maximum(p - 1, 0)]
    right = order[np.minimum(p + 1, len(u) - 1)]
    gl = np.where((p > 0) & (rows[left] == rows[si]), u[si] - u[left], np.nan)
    gr = np.where((p < len(u) - 1) & (rows[right] == rows[si]), u[right] - u[si], np.nan)
    # the reference's spacing at the sample: the middle reference's curves in its row
    U = np.sort(_middle_curves_u(v, si, ref) if ref_u is None else ref_u, axis=1)
    gaps = np.diff(U, axis=1)
    k = np.minimum(np.argmin(np.abs(U - u[si][:, None]), axis=1), gaps.shape[1] - 1)
    g_ref = gaps[np.arange(len(si)), k]
    lo, hi = _GAP_RANGE[0] * g_ref, _GAP_RANGE[1] * g_ref
    with np.errstate(invalid="ignore"):
        gl = np.where((gl > lo) & (gl < hi), gl, np.nan)
        gr = np.where((gr > lo) & (gr < hi), gr, np.nan)
        agree = np.abs(gl - gr) <= _GAP_AGREE * np.fmin(gl, gr)
        c = 0.5 * (gl + gr) / g_ref
    use = agree & np.isfinite(c)
    out[use] = np.clip(c[use], *_GAP_RANGE)
    return out


def template_geometry(
    u: F64, v: F64, seg: I64, si: NDArray[np.intp], ref: ReferenceSet, hh: int
) -> tuple[F64, F64]:
    """How the templates at the samples ``si`` follow their stripes: their rows' sideways
    shifts (:func:`template_row_shift`, (M, 2*hh+1) px) and their columns' spacing
    (:func:`template_col_scale`, (M,) px)."""
    if len(si) == 0:
        return np.zeros((0, 2 * hh + 1)), np.ones(0)
    U = _middle_curves_u(v, si, ref)
    shift = template_row_shift(u, v, seg, si, ref, hh, ref_u=U)
    return shift, template_col_scale(u, v, si, ref, ref_u=U)


def _candidates(ref: ReferenceSet, uv: F64, lines: F64, hw: int, hh: int) -> tuple[F64, F64]:
    """Where each sample's epipolar line meets each slit's curve in each reference image.

    Parameters
    ----------
    uv : (M, 2) float64, px, sample points
    lines : (M, 3) float64, their epipolar lines (unit normal)
    hw, hh : template half sizes, px

    Returns
    -------
    uu, vv : (R, M, N) float64, px, the intersections; NaN where there is none, where it lies
        beyond the rows the curve was seen in (+- ``hh``), or where the template would leave
        the image
    """
    w, h = ref.image_size
    R, N = ref.curves.shape[:2]
    M = len(uv)
    step = max(1, 2**16 // (R * N))  # samples per block: the Newton steps' arrays stay in cache
    vv = intersect_line_curves(
        lines[None, :, None, :],
        ref.curves[:, None, :, :],
        np.broadcast_to(uv[None, :, 1:2], (R, M, N)),
        block=step,
    )
    uu = np.empty((R, M, N))
    _mask_candidates(ref.curves, ref.vrange, hw, hh, w, h, vv, uu)
    return uu, vv


@njit(cache=True)
def _mask_candidates(curves, vrange, hw, hh, w, h, vv, uu):
    """:func:`_candidates`' checks, in place: ``uu`` (R, M, N) = the curves (R, N, D+1) at
    the rows ``vv`` (the float64 operations of :func:`curve_u`), both NaN where the
    intersection is missing, beyond the curve's rows ``vrange`` (R, N, 2) +- ``hh``, or where
    a template of half size ``hw``, ``hh`` would leave the ``w`` x ``h`` image."""
    R, M, N = vv.shape
    for r in range(R):
        for m in range(M):
            for n in range(N):
                x = vv[r, m, n]
                u = 0.0
                for e in range(curves.shape[2]):
                    u = u * x + curves[r, n, e]
                ok = np.isfinite(x) and vrange[r, n, 0] - hh <= x <= vrange[r, n, 1] + hh
                ok = ok and hw <= u <= w - 1 - hw and hh <= x <= h - 1 - hh
                uu[r, m, n] = u if ok else np.nan
                if not ok:
                    vv[r, m, n] = np.nan


#: Squared distances closer than this share are compared by their hypot (which decides).
_NEAR_TIE = 1e-9


@njit(cache=True)
def _nearest_candidates(uu, vv, uv, r_sel, cu, cv, valid):
    """Per sample and slit, the reference whose candidate (``uu``, ``vv`` (R, M, N), NaN: none)
    lies nearest the sample ``uv`` (M, 2) (by ``math.hypot``, the first of equals; 0 if none):
    its index ``r_sel`` and the candidate ``cu``, ``cv`` (M, N); ``valid`` (M, N): a candidate
    in any reference. (Squared distances order the candidates; only near ties take the
    hypot.)"""
    R, M, N = vv.shape
    for m in range(M):
        for n in range(N):
            best = np.inf
            k = 0
            any_ok = False
            for r in range(R):
                if not np.isfinite(vv[r, m, n]):
                    continue
                any_ok = True
                du, dv = uu[r, m, n] - uv[m, 0], vv[r, m, n] - uv[m, 1]
                d2 = du * du + dv * dv
                if not np.isfinite(d2) or d2 > best * (1.0 + _NEAR_TIE):
                    continue
                if d2 < best * (1.0 - _NEAR_TIE) or math.hypot(du, dv) < math.hypot(
                    uu[k, m, n] - uv[m, 0], vv[k, m, n] - uv[m, 1]
                ):
                    best = d2
                    k = r
            r_sel[m, n] = k
            cu[m, n] = uu[k, m, n]
            cv[m, n] = vv[k, m, n]
            valid[m, n] = any_ok


def _ncc_at(
    ref: ReferenceSet,
    sums: NDArray[np.float32],
    patches: NDArray[np.float32],
    r: NDArray[np.intp],
    cells: tuple[NDArray[np.intp], NDArray[np.intp], F64, F64],
    hw: int,
    hh: int,
    out: F64,
) -> None:
    """NCC of each sample's template (its patch, normalised) with bilinear reference patches
    at given places (:func:`~multislit.identify.patches.bilinear_ncc_cells` on the reference's
    dot images).

    Parameters
    ----------
    sums : (R, W', H', 6) float32, ``ref.window_sums(hw, hh)`` (x-major)
    patches : (m, 2*hh+1, 2*hw+1) float32, the samples' patches (the templates before
        :func:`~multislit.identify.patches.normalise_patches`)
    r : (m, C) intp, reference image of each candidate
    cells : x0, y0 (m, C) intp and fx, fy (m, C) float64: the pixel cell of each patch's
        top-left sample position (centre - half size) and the fractions past it
        (:func:`~multislit.identify.patches.cell_of`), with the patch inside the image
    hw, hh : patch half sizes, px
    out : (m, C) float64, the NCC, 0 for a flat (all equal) reference patch or template
    """
    images, images_t = _scoring_images(ref, hw, hh)
    bilinear_ncc_cells(images, patches, r, *cells, sums, hw, hh, out, images_t=images_t)


def _scoring_images(ref: ReferenceSet, hw: int, hh: int) -> tuple[NDArray, NDArray | None]:
    """The reference's dot images as :func:`_ncc_at` reads them for templates of half size
    ``hw`` x ``hh`` px: tall patches along their columns (the padded transposed copy), wide
    ones along their rows (the padded copy)."""
    if hh > hw:
        return ref.dots, ref.padded_dots(transposed=True)
    return ref.padded_dots(), None


def prepare_scoring(reference: ReferenceSet) -> ReferenceSet:
    """Compute now the data the scoring of :func:`identify`'s templates derives from
    ``reference`` (the dot images' window sums and padded copy), which the set keeps.

    Without this call they are made on the first scan. A set prepared before it is sent to
    worker processes carries them along instead of each worker making its own.

    Returns
    -------
    the same ``reference``
    """
    hw, hh = template_size(reference)
    reference.window_sums(hw, hh)
    _scoring_images(reference, hw, hh)
    return reference


def _hypotheses(
    ref: ReferenceSet,
    uv: F64,
    lines: F64,
    hw: int,
    hh: int,
    allowed: NDArray[np.bool_] | None,
) -> tuple[F64, F64, NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
    """The reference patch centres each sample's hypotheses are compared at: per sample and
    slit, the candidate in the reference image where it lies nearest the sample (the board
    depth closest to the surface's, the least deformed dots).

    ``lines`` (M, 3) are the samples' epipolar lines (``ref.epipolar_lines(uv)``).

    Returns
    -------
    cu, cv : (M, N) float64, px, the centres
    rr : (M, N) intp, the reference image of each centre
    ok : (M, N) bool, where the centre is a candidate (and the hypothesis ``allowed``)
    valid_any : (M, N) bool, the same: the hypotheses with a candidate in any reference
    """
    M, N = len(uv), ref.curves.shape[1]
    uu_all, vv_all = _candidates(ref, uv, lines, hw, hh)  # (R, M, N)
    rr = np.empty((M, N), np.intp)
    cu, cv = np.empty((M, N)), np.empty((M, N))
    valid_any = np.empty((M, N), np.bool_)
    _nearest_candidates(uu_all, vv_all, uv, rr, cu, cv, valid_any)
    if allowed is not None:
        valid_any &= allowed
    return cu, cv, rr, np.isfinite(cv) & valid_any, valid_any


#: Largest vertical dot motion per px of sideways motion that a template follows (the slope of
#: the dot projector's epipolar lines; beyond it the rig has the dots move mostly vertically).
_MAX_RISE = 1.0


def _dot_rise(lines: F64) -> F64:
    """(M,) the vertical motion of the dots per px of sideways motion on each epipolar line
    (M, 3), unit normal (a, b): its slope (a surface's depth change moves the slit along the
    row but the dots along that line)."""
    dx, dy = lines[:, 1], -lines[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(dx) > 1e-12, dy / dx, 0.0)
    return np.clip(t, -_MAX_RISE, _MAX_RISE)


@njit(cache=True)
def _fast_cells(cu, cv, rr, ok, hw, hh, ws, hs, r_fast, cells):
    """Where :func:`_ncc_at` reads the candidate patches centred at ``cu``, ``cv`` (M, K) px
    in the references ``rr``, where ``ok`` (inside the image, as :func:`_candidates` keeps
    them): ``r_fast`` and the ``cells`` x0, y0, fx, fy of the top-left sample position in
    ``ws`` x ``hs`` windows (0 where not ``ok``). Returns the most candidates of a sample."""
    x0, y0, fx, fy = cells
    M, K = cu.shape
    n_max = 0
    for m in range(M):
        n = 0
        for k in range(K):
            f = ok[m, k]
            r_fast[m, k] = rr[m, k] if f else 0
            x0[m, k], fx[m, k] = cell_of((cu[m, k] if f else hw) - hw, ws)
            y0[m, k], fy[m, k] = cell_of((cv[m, k] if f else hh) - hh, hs)
            n += f
        n_max = max(n_max, n)
    return n_max


def score_candidates(
    ref: ReferenceSet,
    scan_dots: NDArray,
    pu: F64,
    pv: F64,
    row_shift: F64,
    col_scale: F64,
    allowed: NDArray[np.bool_] | None = None,
) -> F64:
    """NCC of each sample's template at each slit's epipolar intersection.

    Parameters
    ----------
    ref : the prepared references
    scan_dots : (H, W) float32, the scan's dot image
    pu, pv : (M,) float64, px, the sample points
    row_shift : (M, 2*hh+1) float64, px, sideways shift of the template's rows
        (:func:`template_row_shift`); each row also moves along the dot projector's epipolar
        line as far as the shift says (a depth change moves the dots along that line, the
        slit along the row)
    col_scale : (M,) float64, px per template column (:func:`template_col_scale`)
    allowed : (M, N) bool, the hypotheses scored per sample (others stay NaN); default all

    Returns
    -------
    scores : (M, N) float64, the NCC per sample and slit; NaN where the slit has no candidate
        or the template is flat (no dots around the sample)
    """
    N = ref.curves.shape[1]
    hw, hh = template_size(ref)
    M = len(pu)
    if M == 0:
        return np.full((M, N), np.nan)
    sums = ref.window_sums(hw, hh)
    uv = np.c_[pu, pv]
    lines = ref.epipolar_lines(uv)  # (M, 3), unit normal (a, b)
    cu, cv, rr, ok, valid_any = _hypotheses(ref, uv, lines, hw, hh, allowed)
    r_fast = np.empty((M, N), np.intp)
    cells = (np.empty_like(r_fast), np.empty_like(r_fast), np.empty((M, N)), np.empty((M, N)))
    n_max = _fast_cells(cu, cv, rr, ok, hw, hh, *sums.shape[1:3], r_fast, cells)
    patches = sample_sheared_patches(
        scan_dots,
        uv,
        hw,
        hh,
        row_shift,
        row_rise=row_shift * _dot_rise(lines)[:, None],
        col_scale=col_scale,
    )
    # a flat template (no dots around the point) says nothing
    flat = ~np.any(patches != patches[:, :1, :1], axis=(1, 2))
    if n_max == N:  # every sample has all its candidates: score every entry
        sc = np.empty((M, N))
        _ncc_at(ref, sums, patches, r_fast, cells, hw, hh, sc)
    else:
        sc = np.full((M, N), -np.inf)
        if n_max > 0:
            # few hypotheses per sample (a prior's, missing candidates): score only those,
            # packed to the front of each sample's row
            cols = np.argsort(~ok, axis=1, kind="stable")[:, :n_max]
            r_p, *cells_p = (np.take_along_axis(a, cols, axis=1) for a in (r_fast, *cells))
            scored = np.empty(cols.shape)
            _ncc_at(ref, sums, patches, r_p, tuple(cells_p), hw, hh, scored)
            np.put_along_axis(sc, cols, scored, axis=1)
        sc[~ok] = -np.inf
    scores = np.where(valid_any & np.isfinite(sc), sc, np.nan)
    scores[flat] = np.nan
    return scores

"""Dot templates of a scan matched with the reference dot images (paper, section 4.2).

Sample points are taken along each slit segment of a scan; the dot image around each one (its
template) is compared by normalised cross-correlation (NCC) with the reference dot images only
where the point's epipolar line meets each slit's reference curve: N candidates per reference
image instead of a search over the image. The result is a score per sample and slit, which
:mod:`~multislit.identify.labelling` turns into votes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.identify.patches import (
    bilinear_ncc_cells,
    cell_of,
    normalise_patches,
    sample_patches,
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


@dataclass(frozen=True)
class _Options:
    """Settings of the identification: the user's (``min_confidence``, see
    :func:`~multislit.identify.labelling.identify_template`) and internal modes that tests and
    benchmarks vary.

    template_half_width : template half width across the slit, in reference slit spacings
    search_px : the reference patch is also compared at this many px either side of each
        candidate along the epipolar line (0: at the candidate only)
    depth_margin : a slit is a hypothesis for a sample only if it lights the sample at a depth
        within the references' depth span widened by this fraction of it on either side
        (inf: no depth limit)
    references : "nearest": each hypothesis is compared in the reference image where its
        candidate lies nearest the sample (the least deformed dots); "all": in every reference,
        keeping the best score
    follow_stripe : "line": the template's rows are shifted so that it follows its stripe's
        lean (a line fitted to the segment's centres); "off": upright templates
    coarse_every, keep_hypotheses : coarse to fine: every slit is scored on every
        ``coarse_every``-th sample of a segment, then on all its samples only the segment's
        ``keep_hypotheses`` best slits (``coarse_every`` 1: every slit everywhere)
    """

    min_confidence: float = 0.30
    template_half_width: float = _TEMPLATE_HALF_WIDTH
    search_px: int = 0
    depth_margin: float = math.inf
    references: str = "nearest"
    follow_stripe: str = "line"
    coarse_every: int = 1
    keep_hypotheses: int = 3

    def template_size(self, ref: ReferenceSet) -> tuple[int, int]:
        """Template half width and half height (px): as wide as a dot band, tall enough for
        dots."""
        hw = max(3, int(round(self.template_half_width * ref.spacing_px)))
        want = _TEMPLATE_DOTS / max(ref.dot_density, 1e-6) / (2 * hw + 1)
        hh = int(round(np.clip(want / 2, 0.5 * ref.spacing_px, 4.0 * ref.spacing_px)))
        return hw, max(4, hh)


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
    return _Options().template_size(reference)


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
    mode: str,
    *,
    ref_u: F64 | None = None,
) -> F64 | None:
    """(M, 2*hh+1) px: sideways shift of each template row so that the template follows its
    stripe (``_Options.follow_stripe``); None for ``mode`` "off".

    A line u = a + s dv is fitted (least squares, all samples at once) to the centres of the
    sample's segment within +-hh rows; a sample with fewer than 3 such centres, or spanning
    fewer than 4 rows, keeps an upright template. The reference curves' own slant at the sample
    (the curve nearest it in the middle reference) is kept in the template. ``ref_u`` (M, N)
    px: the middle reference's curves in the samples' rows, if already at hand (default: made
    here).
    """
    if mode == "off" or len(si) == 0:
        return None
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
    u: F64, v: F64, seg: I64, si: NDArray[np.intp], ref: ReferenceSet, hh: int, mode: str
) -> tuple[F64 | None, F64 | None]:
    """How the templates at the samples ``si`` follow their stripes (``_Options.follow_stripe``
    ``mode``): their rows' sideways shifts (:func:`template_row_shift`) and their columns'
    spacing (:func:`template_col_scale`); (None, None) for "off" (upright templates)."""
    if mode == "off" or len(si) == 0:
        return None, None
    U = _middle_curves_u(v, si, ref)
    shift = template_row_shift(u, v, seg, si, ref, hh, mode, ref_u=U)
    return shift, template_col_scale(u, v, si, ref, ref_u=U)


def _in_volume(ref: ReferenceSet, uv: F64, margin: float) -> NDArray[np.bool_]:
    """(M, N) bool: could slit n light sample m at a depth inside the measuring volume?

    In the sample's row, slit n's reference curves span [lo, hi] over the boards' depths; the
    sample must lie within [lo - margin (hi - lo), hi + margin (hi - lo)].
    """
    U = curve_u(ref.curves[:, None, :, :], uv[None, :, 1:2])  # (R, M, N)
    lo, hi = U.min(axis=0), U.max(axis=0)
    pad = margin * (hi - lo)
    u = uv[:, 0:1]
    return (u >= lo - pad) & (u <= hi + pad)


def _candidates(
    ref: ReferenceSet, uv: F64, lines: F64, hw: int, hh: int, depth_margin: float = np.inf
) -> tuple[F64, F64]:
    """Where each sample's epipolar line meets each slit's curve in each reference image.

    Parameters
    ----------
    uv : (M, 2) float64, px, sample points
    lines : (M, 3) float64, their epipolar lines (unit normal)
    hw, hh : template half sizes, px
    depth_margin : ``_Options.depth_margin`` (inf: no depth limit)

    Returns
    -------
    uu, vv : (R, M, N) float64, px, the intersections; NaN where there is none, where it lies
        beyond the rows the curve was seen in (+- ``hh``), where the template would leave
        the image, or where the slit would put the sample outside the measuring volume
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
    if np.isfinite(depth_margin):
        out = ~_in_volume(ref, uv, depth_margin)[None]
        uu = np.where(out, np.nan, uu)
        vv = np.where(out, np.nan, vv)
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
    p: _Options,
    allowed: NDArray[np.bool_] | None,
) -> tuple[F64, F64, NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
    """The reference patch centres each sample's hypotheses are compared at.

    ``lines`` (M, 3) are the samples' epipolar lines (``ref.epipolar_lines(uv)``).

    Returns
    -------
    cu, cv : (M, N, R', O) float64, px, the centres: per sample and slit, in the reference(s)
        ``p.references`` selects (R' of them), at the ``O = 2 p.search_px + 1`` offsets along
        the epipolar line
    rr : (M, N, R', O) intp, the reference image of each centre
    ok : (M, N, R', O) bool, where the centre is a candidate
    valid_any : (M, N) bool, the hypotheses with a candidate in any reference (and allowed)
    """
    R, N = ref.curves.shape[:2]
    M = len(uv)
    offs = np.arange(-p.search_px, p.search_px + 1, dtype=float)
    direction = np.c_[lines[:, 1], -lines[:, 0]]  # along the line
    uu_all, vv_all = _candidates(ref, uv, lines, hw, hh, p.depth_margin)  # (R, M, N)
    if p.references == "nearest":
        # compare each hypothesis in the reference where its candidate lies nearest the
        # scan point: the board depth closest to the surface's, the least deformed dots
        r_sel = np.empty((M, N, 1), np.intp)
        cu, cv = np.empty((M, N, 1)), np.empty((M, N, 1))
        valid_any = np.empty((M, N), np.bool_)
        _nearest_candidates(uu_all, vv_all, uv, r_sel[..., 0], cu[..., 0], cv[..., 0], valid_any)
    else:
        valid_any = np.isfinite(vv_all).any(axis=0)
        r_sel = np.broadcast_to(np.arange(R)[None, None, :], (M, N, R))
        ii = np.arange(M)[:, None, None]
        kk = np.arange(N)[None, :, None]
        cu = uu_all[r_sel, ii, kk]  # (M, N, R') candidate centres
        cv = vv_all[r_sel, ii, kk]
    if allowed is not None:
        valid_any &= allowed
    ok = np.isfinite(cv) & valid_any[:, :, None]
    # search along the epipolar line: (M, N, R', O)
    cu, cv = cu[..., None], cv[..., None]
    if p.search_px:
        cu = cu + offs * direction[:, None, None, 0:1]
        cv = cv + offs * direction[:, None, None, 1:2]
    rr = np.broadcast_to(r_sel[..., None], cu.shape)
    ok = np.broadcast_to(ok[..., None], cu.shape)
    return cu, cv, rr, ok, valid_any


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
def _split_candidates(cu, cv, rr, ok, hw, hh, w, h, ws, hs, r_fast, cells, fast, direct):
    """Sort the candidate patch centres ``cu``, ``cv`` (M, K) px (in reference ``rr``, where
    ``ok``) of :func:`score_candidates`: ``fast`` where the patch of half size ``hw``, ``hh``
    lies inside the ``w`` x ``h`` image (scored by :func:`_ncc_at`, from ``r_fast`` and the
    ``cells`` x0, y0, fx, fy of the top-left sample position in ``ws`` x ``hs`` windows; 0
    elsewhere), ``direct`` where it does not (sampled). Returns the most ``fast`` candidates
    of a sample."""
    x0, y0, fx, fy = cells
    M, K = cu.shape
    n_max = 0
    for m in range(M):
        n = 0
        for k in range(K):
            u, v = cu[m, k], cv[m, k]
            inside = hw <= u <= w - 1 - hw and hh <= v <= h - 1 - hh  # (False for NaN)
            f = ok[m, k] and inside
            fast[m, k] = f
            direct[m, k] = ok[m, k] and not inside
            r_fast[m, k] = rr[m, k] if f else 0
            x0[m, k], fx[m, k] = cell_of((u if f else hw) - hw, ws)
            y0[m, k], fy[m, k] = cell_of((v if f else hh) - hh, hs)
            n += f
        n_max = max(n_max, n)
    return n_max


def score_candidates(
    ref: ReferenceSet,
    scan_dots: NDArray,
    pu: F64,
    pv: F64,
    p: _Options,
    allowed: NDArray[np.bool_] | None = None,
    row_shift: F64 | None = None,
    col_scale: F64 | None = None,
) -> F64:
    """NCC of each sample's template at each slit's epipolar intersection.

    Parameters
    ----------
    ref : the prepared references
    scan_dots : (H, W) float32, the scan's dot image
    pu, pv : (M,) float64, px, the sample points
    p : the template size and matching modes
    allowed : (M, N) bool, the hypotheses scored per sample (others stay NaN); default all
    row_shift : (M, 2*hh+1) float64, px, sideways shift of the template's rows
        (:func:`template_row_shift`); each row also moves along the dot projector's epipolar
        line as far as the shift says (a depth change moves the dots along that line, the
        slit along the row); default upright templates
    col_scale : (M,) float64, px per template column (:func:`template_col_scale`), with
        ``row_shift`` only; default 1

    Returns
    -------
    scores : (M, N) float64, the best NCC per sample and slit; NaN where the slit has no
        candidate or the template is flat (no dots around the sample)
    """
    N = ref.curves.shape[1]
    w, h = ref.image_size
    hw, hh = p.template_size(ref)
    M = len(pu)
    if M == 0:
        return np.full((M, N), np.nan)
    sums = ref.window_sums(hw, hh)
    uv = np.c_[pu, pv]
    lines = ref.epipolar_lines(uv)  # (M, 3), unit normal (a, b)
    cu, cv, rr, ok, valid_any = _hypotheses(ref, uv, lines, hw, hh, p, allowed)
    shape = cu.shape
    # a patch shifted off the image is zero-padded: sample it directly (rare)
    rr_f = np.empty((M, cu[0].size), np.intp)
    cells = (np.empty_like(rr_f), np.empty_like(rr_f), np.empty(rr_f.shape), np.empty(rr_f.shape))
    fast_flat, direct = np.empty(rr_f.shape, np.bool_), np.empty(shape, np.bool_)
    n_max = _split_candidates(
        *(a.reshape(M, -1) for a in (cu, cv, rr, ok)),
        hw,
        hh,
        w,
        h,
        *sums.shape[1:3],
        rr_f,
        cells,
        fast_flat,
        direct.reshape(M, -1),
    )
    if row_shift is None:
        patches = sample_patches(scan_dots, uv, hw, hh)
    else:
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
    # (every entry is scored when every sample has all its candidates)
    sc = np.empty(shape) if n_max == fast_flat.shape[1] else np.full(shape, -np.inf)
    sc_flat = sc.reshape(M, -1)
    if n_max == fast_flat.shape[1]:
        _ncc_at(ref, sums, patches, rr_f, cells, hw, hh, sc_flat)
    elif n_max > 0:
        # few hypotheses per sample (coarse to fine, missing candidates): score only those,
        # packed to the front of each sample's row
        cols = np.argsort(~fast_flat, axis=1, kind="stable")[:, :n_max]
        r_p, *cells_p = (np.take_along_axis(a, cols, axis=1) for a in (rr_f, *cells))
        scored = np.empty(cols.shape)
        _ncc_at(ref, sums, patches, r_p, tuple(cells_p), hw, hh, scored)
        np.put_along_axis(sc_flat, cols, scored, axis=1)
    sc_flat[~fast_flat] = -np.inf
    if direct.any():
        di = np.nonzero(direct)
        tmpl = np.zeros((M, patches[0].size), np.float32)
        rows = np.unique(di[0])
        tmpl[rows] = normalise_patches(patches[rows])
        for r in np.unique(rr[di]):
            sel = tuple(q[rr[di] == r] for q in di)
            pat = normalise_patches(sample_patches(ref.dots[r], np.c_[cu[sel], cv[sel]], hw, hh))
            sc[sel] = np.einsum("ij,ij->i", pat, tmpl[sel[0]])
    best = sc.reshape(M, N) if sc.size == M * N else sc.reshape(M, N, -1).max(axis=2)
    scores = np.where(valid_any & np.isfinite(best), best, np.nan)
    scores[flat] = np.nan
    return scores

"""Re-centre identified stripe points for triangulation (Steger's centre, fitted along v)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import scipy.stats
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.openings import stripe_opening
from multislit.stripes.separation import (
    dot_mask,
    fill_dots,
    noise_from_difference,
    row_median_background,
)
from multislit.stripes.sizes import FWHM_PER_SIGMA, median_stride, opening_length
from multislit.stripes.slope import (
    LEAN_DECIMATION,
    _sobel_row,
    reflect101,
    slope_sigma,
    stripe_slope,
)
from multislit.stripes.validation import SlitExtractionError, as_image, int_at_least, positive_px

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Steger's smoothing sigma in :func:`refine_centres`, in units of the stripe's own sigma.
REFINE_STEGER_SCALE = 1.25

#: Significance level of the test that picks degree 2 over degree 1 for a point's fit in
#: :func:`refine_centres` (``degree="auto"``), for Gaussian noise.
_CURVED_ALPHA = 1e-4
#: Fewest pairs of windows for the noise scale of that test (else degree 1 everywhere).
_CURVED_MIN_PAIRS = 50
#: Where ``degree="auto"`` keeps the line, the stripe's curvature is read from a parabola over
#: this many times the line's half window, and the line's bias on the curve taken off.
_BEND_WINDOWS = 3
#: The median of chi2 with 1 degree of freedom, and its upper ``_CURVED_ALPHA`` quantile.
_CHI2_MEDIAN = float(scipy.stats.chi2.median(1))
_CHI2_CURVED = float(scipy.stats.chi2.isf(_CURVED_ALPHA, 1))


def refine_slit_image(
    img: NDArray,
    stripe_width_px: float,
    dot_size_px: float,
    bg_rows: int,
    bg_cols: int,
) -> F32:
    """Slit image for :func:`refine_centres`: the extraction's, on a smoothed background.

    The row median background (:func:`row_median_background`) has pixel-to-pixel noise
    (neighbouring pixels' medians are taken over different samples) and follows the flanks
    of nearby stripes; a stripe's profile inherits both as a slope that moves its centre. Here
    it is averaged by a ``bg_cols`` x ``bg_rows`` box (along u and v), not clipped at 0, and
    the dots are found (the opening following leaning stripes) and refilled by interpolation
    along the stripe as in the extraction.

    Parameters
    ----------
    img : (H, W) validated image (uint8, uint16 or float32)
    stripe_width_px, dot_size_px : FWHMs (px)
    bg_rows, bg_cols : box size (px) of the background average along v and u

    Returns
    -------
    (H, W) float32, stripes on a background ~ 0 (intensity units)
    """
    f = img.astype(np.float32)
    bg = row_median_background(f, median_stride(stripe_width_px))
    if bg_rows > 1 or bg_cols > 1:
        bg = cv2.blur(bg, (bg_cols, bg_rows), borderType=cv2.BORDER_REFLECT)
    hp = f - bg
    noise = noise_from_difference(img)
    length = opening_length(dot_size_px)
    slope = stripe_slope(hp, slope_sigma(length))
    return fill_dots(hp, stripe_opening(hp, length, 3.0 * noise), 3.0 * noise, length, slope)


def refine_half_rows(stripe_width_px: float) -> int:
    """Default half window (rows) of :func:`refine_centres`: round(2.5 FWHM), at least 1.

    Parameters
    ----------
    stripe_width_px : stripe FWHM (px)
    """
    return max(1, round(2.5 * stripe_width_px))


def refine_centres(
    image: ArrayLike,
    u: ArrayLike,
    v: ArrayLike,
    segment: ArrayLike,
    stripe_width_px: float,
    dot_size_px: float | None = None,
    *,
    half_rows: int | None = None,
    degree: int | str = "auto",
    max_shift_px: float = 1.0,
    steger_scale: float = REFINE_STEGER_SCALE,
    end_rows: int | None = None,
) -> tuple[F64, NDArray[np.bool_]]:
    """Re-centre identified stripe points for triangulation: less laser-speckle noise.

    Meant to run after the slit identification, which keeps the extraction's own centres.
    For each point:

    1. Steger's centre in its row: the zero of the first derivative of the row profile
       smoothed by a Gaussian of ``steger_scale`` stripe sigmas, by two Newton steps from the
       given centre, on :func:`refine_slit_image` (the row median background averaged over
       2 ``half_rows`` + 1 rows and 2 :func:`median_stride` + 1 columns, dots refilled).
    2. Along the stripe: a polynomial in v fitted by least squares to the Steger centres of
       the *same segment* in rows v - R .. v + R (R = ``half_rows``), evaluated at v. The
       window is symmetric about v, shrunk near the segment's ends, and never takes rows of
       another segment, so the centre does not cross segment ends or occlusion edges. A line
       (degree 1) follows a slanted stripe exactly; on a curved one it is biased by
       c R (R + 1) / 3 px (c = d2u/dv2 / 2: 0.01 px for c = 1e-4 px/row^2 and R = 9, but
       ~0.3 px on the arcs of a 40 mm sphere at 0.9 m, c ~ 0.01 px/row^2); a parabola
       (degree 2) is not, at ~1.4x the noise. ``degree="auto"`` (default) takes the
       parabola only where the window's curvature is significant: where the two fits differ,
       d = u2 - u1, by more than the noise explains, d^2 > s^2 g chi2_1(1 - 1e-4). Here g is
       var(u2 - u1) for unit independent noise (var(u2) - var(u1), from the window's rows)
       and s^2 the noise variance, from pairs of disjoint windows 2 R + 1 rows apart on one
       segment, whose curvature cancels in d_a - d_b: median((d_a - d_b)^2 / (g_a + g_b)) /
       median(chi2_1) over the image (degree 1 everywhere with fewer than 50 pairs). The
       noise scale comes from the image, not the window's residuals: the Steger centres of
       neighbouring rows are correlated (speckle, dot refill, background average), which
       makes a per-window F-test pick the parabola on straight stripes far more often than
       its level says. The test must also hold, with the same sign of d, for a window R rows
       before or after on the segment: a surface's curvature goes on along the stripe,
       while one bad row centre changes the sign of d from one window to the other.
       Where the line is kept, its bias is taken off: c is read from a parabola over the
       rows v - W .. v + W (W = 3 R, :data:`_BEND_WINDOWS`; shrunk at the segment's ends,
       none where it would reach fewer than W // 2 rows on either side), and the line's
       value on c dv^2 subtracted. Below the test's level the curvature still biases the line
       (on the arcs of a 120 mm sphere at 0.8-1 m by ~0.05 px, all towards the arc's inside:
       its points would lie ~0.07-0.1 mm inside it), while over the wide window its noise adds
       little to the line's (a few per cent on straight speckled stripes).

    A point keeps its given centre (``ok`` False) where the refinement is not trustworthy: no
    segment (< 0; give the points the extraction found along their columns,
    :attr:`SlitExtraction.by_column`, no segment: their stripes lean towards the horizontal,
    and the refinement centres along rows and fits along columns); within ``end_rows`` + R // 2 rows of its segment's end (the rows within
    ``end_rows`` of an end also stay out of the other rows' fits: there the extraction's and
    this dot refill mix the stripe with what lies beyond the end); fewer than ``degree + 2``
    rows in the window (3 for "auto"); another stripe point in its row within the Steger
    kernel's reach (3 smoothing sigmas + 2.5 stripe sigmas); or a move of more than
    ``max_shift_px``.

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float grayscale, the image the points came from
    u, v : (K,) float, px, stripe centres (v integer rows, as from :func:`extract_slits`)
    segment : (K,) int, segment id per point (-1: none); the points of one segment are one
        stripe piece with at most one point per row (as from :func:`link_segments`)
    stripe_width_px : stripe FWHM (px), e.g. :attr:`SlitExtraction.stripe_width_px`
    dot_size_px : dot FWHM (px) for the dot refill; default ``stripe_width_px``
    half_rows : R, rows on each side in the along-stripe fit; default
        :func:`refine_half_rows` (2.5 FWHM)
    degree : "auto", 0, 1 or 2, degree of the along-stripe polynomial; default "auto":
        2 where the test above finds the stripe curved, else 1
    max_shift_px : largest accepted move of a centre (px); default 1
    steger_scale : Steger's smoothing sigma in stripe sigmas (FWHM / 2.355); default
        :data:`REFINE_STEGER_SCALE`
    end_rows : rows at each segment end left out; default :func:`opening_length` of the dot
        size (7 px for 1.9 px dots). 0 refines more points, but a stripe that jumps at a
        segment's end then pulls the refined centres next to the jump

    Returns
    -------
    u_refined : (K,) float64, px; the given ``u`` where ``ok`` is False
    ok : (K,) bool, True where the centre was refined

    Raises
    ------
    SlitExtractionError
        bad image; ``u``, ``v``, ``segment`` not 1-D of one length, not finite or outside
        the image; bad parameters.
    """
    img = as_image(image)
    h, w = img.shape
    uu, seg, rows = _check_points(u, v, segment, w, h)
    sw, ds, R, deg, end = _check_options(
        stripe_width_px, dot_size_px, half_rows, degree, max_shift_px, steger_scale, end_rows
    )
    K = uu.size
    out = uu.copy()
    if K == 0:
        return out, np.zeros(0, bool)

    sigma = sw / FWHM_PER_SIGMA
    ss = max(steger_scale * sigma, 0.7)
    r = rows.astype(np.intp)
    # > row range + the widest window: keys of two segments never meet
    span = h + 2 * max(1, _BEND_WINDOWS) * R + 2
    key, order, pos, skey, inner = _segment_rows(seg, r, span, end)
    # Steger's centres of the points that can take part in a fit (on a segment, not at its end),
    # on the slit image of refine_slit_image, made only in their windows
    length = opening_length(ds)
    hp, put, pvt, g = _highpass_and_tensor(img, sw, R, length)
    active = (seg >= 0) & (inner >= 0)
    tau = 3.0 * noise_from_difference(img)
    rad = math.ceil(3.0 * ss) + 1  # the Steger kernel's half width (px)
    # the opening follows leaning stripes only in the cells the dot mask is read at
    cells = _opening_cells(uu, r, active, rad, length, h, w)
    opened = stripe_opening(hp, length, tau, cells=cells)
    mask = dot_mask(hp, opened, tau)
    # the slit image: the highpass with the dots refilled only where the points' windows read
    # them; the slope's Gaussian only where those refills need it
    slit = hp.copy()
    hx, hy = np.empty((w, h), np.float32), np.empty((w, h), np.float32)
    _refill_dots(hp, mask, opened, put, pvt, g, hx, hy, slit, uu, r, active, rad, length)
    m, row_ok = _steger_kernel(slit, uu, r, active, ss, max_shift_px)
    delta, ok, delta2, gain, bend = _fit_kernel(
        seg, key, order, pos, skey, inner, m, uu, row_ok, R, deg
    )
    if deg < 0:
        # the line less its bias on a curved stripe: the curvature from a parabola over
        # _BEND_WINDOWS times the rows, whose noise the wide window keeps far below the line's
        curv, has = _bend_kernel(seg, order, skey, inner, m, row_ok, _BEND_WINDOWS * R)
        take = has & np.isfinite(bend)
        base = delta - np.where(take, curv * bend, 0.0)
        delta = _pick_curved(delta, delta2, gain, key, order, R, base)
    # another stripe within the kernel's reach in the same row: its flank biases the centre
    ok &= _row_gaps_kernel(uu, r, h) >= 3.0 * ss + 2.5 * sigma
    ok &= np.abs(delta) <= max_shift_px
    out[ok] = uu[ok] + delta[ok]
    return out, ok


def _pick_curved(
    delta1: F64,
    delta2: F64,
    gain: F64,
    key: NDArray[np.int64],
    by_key: NDArray[np.intp],
    R: int,
    base: F64,
) -> F64:
    """The shifts of ``degree="auto"``: ``delta2`` (degree 2) where the difference from
    ``delta1`` (degree 1) is significant against the noise and so is that of a window R rows
    before or after on the segment, with the same sign; else ``base`` (the line less its
    curvature's bias). ``gain`` (K,) is
    var(delta2 - delta1) per unit iid noise (NaN where there is no degree-2 fit); ``key``
    (K,) the points' segment * span + row of :func:`_segment_rows` and ``by_key`` (K,) the
    stable order that sorts it; ``R`` the half window."""
    valid = np.isfinite(gain) & (gain > 0)
    d = delta2 - delta1
    order = by_key[valid[by_key]]  # the points with a gain, sorted by key (stable)
    sk = key[order]
    # pairs of disjoint windows 2 R + 1 rows apart: their difference of d has variance
    # (g_a + g_b) s^2, the curvature they share cancelling
    pair, j = _partner_kernel(sk, 2 * R + 1)
    if pair.sum() < _CURVED_MIN_PAIRS:
        return base
    a, b = order[pair], order[j[pair]]
    s2 = np.median((d[a] - d[b]) ** 2 / (gain[a] + gain[b])) / _CHI2_MEDIAN
    return _curved_kernel(order, sk, base, delta2, d, gain, s2, _CHI2_CURVED, R)


def _highpass_and_tensor(img: NDArray, sw: float, R: int, length: int) -> tuple[F32, F32, F32, F32]:
    """The highpass of :func:`refine_slit_image` (image minus its row median background
    averaged over 2 R + 1 rows and 2 :func:`median_stride` + 1 columns), (H, W) float32; the
    structure tensor products gu^2 and gu gv of :func:`~multislit.stripes.slope.stripe_slope`
    on it, transposed (W, H) float32; and the Gaussian (float32) that integrates them."""
    stride = median_stride(sw)
    # the median of integer data is exact in its own type; the box mean as cv2.blur's
    bg = row_median_background(img, stride)
    ksize = (2 * stride + 1, 2 * R + 1)
    hp = cv2.boxFilter(bg, cv2.CV_32F, ksize, normalize=True, borderType=cv2.BORDER_REFLECT)
    # the highpass in place of the background
    if img.dtype != np.float32:
        hp = cv2.subtract(img, hp, dst=hp, dtype=cv2.CV_32F)
    else:
        hp = np.subtract(img, hp, out=hp)
    sig = slope_sigma(length)
    taps = round(sig * 8 + 1) | 1  # cv2.GaussianBlur's kernel size for float data
    g = cv2.getGaussianKernel(taps, sig, cv2.CV_32F).ravel()
    # the products transposed (W, H): the slope's Gaussian runs along their rows
    h, w = hp.shape
    if h < 3 or w < 3:  # too small for the compiled pass's row views
        hpt = cv2.transpose(hp)
        gu = cv2.Sobel(hpt, cv2.CV_32F, 0, 1, ksize=3)
        gv = cv2.Sobel(hpt, cv2.CV_32F, 1, 0, ksize=3)
        pvt = cv2.multiply(gu, gv, dst=gv)
        return hp, cv2.multiply(gu, gu, dst=gu), pvt, g
    put = np.empty((w, h), np.float32)
    pvt = np.empty((w, h), np.float32)
    _tensor_products_t(hp, put, pvt)
    return hp, put, pvt, g


#: Rows of the highpass per block of :func:`_tensor_products_t` (16 float32: one cache line
#: of each transposed row written at a time).
_PRODUCT_ROWS = 16


@njit(cache=True)
def _tensor_products_t(hp, put, pvt):
    """The structure tensor products gu^2 and gu gv of ``hp`` (H, W) float32, transposed:
    ``put``, ``pvt`` (W, H) float32, from cv2.Sobel's 3x3 derivatives
    (cv2.BORDER_REFLECT_101; H, W >= 3). The derivatives of a block of rows at a time, then
    written column by column."""
    h, w = hp.shape
    nb = _PRODUCT_ROWS
    gu = np.empty((nb, w), np.float32)
    gv = np.empty((nb, w), np.float32)
    for r0 in range(0, h, nb):
        n = min(nb, h - r0)
        for k in range(n):
            _sobel_row(hp, r0 + k, gu[k], gv[k])
        for c in range(w):
            ou = put[c, r0 : r0 + n]
            ov = pvt[c, r0 : r0 + n]
            for k in range(n):
                a = gu[k, c]
                ou[k] = a * a
                ov[k] = a * gv[k, c]


def _check_points(
    u: ArrayLike, v: ArrayLike, segment: ArrayLike, w: int, h: int
) -> tuple[F64, NDArray[np.int64], F64]:
    """The points of :func:`refine_centres` checked: u (K,) float64, segment (K,) int64 and
    the rounded rows (K,) float64, in a ``w`` x ``h`` px image."""
    uu = np.asarray(u, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    seg = np.asarray(segment)
    if uu.ndim != 1:
        raise SlitExtractionError(f"u must be a 1-D (K,) array, got shape {uu.shape}")
    if vv.shape != uu.shape or seg.shape != uu.shape:
        raise SlitExtractionError(
            f"u, v and segment must be (K,) arrays of one length, got shapes {uu.shape}, "
            f"{vv.shape} and {seg.shape}"
        )
    if seg.size and not np.issubdtype(seg.dtype, np.integer):
        raise SlitExtractionError(f"segment must be an integer array, got dtype {seg.dtype}")
    seg = seg.astype(np.int64)
    if not (np.isfinite(uu).all() and np.isfinite(vv).all()):
        raise SlitExtractionError("u and v must be finite")
    rows = np.rint(vv)
    if uu.size and (uu.min() < -0.5 or uu.max() > w - 0.5 or rows.min() < 0 or rows.max() > h - 1):
        raise SlitExtractionError(
            f"u, v must lie in the {w}x{h} px image, got u in [{uu.min():g}, {uu.max():g}] "
            f"and v in [{vv.min():g}, {vv.max():g}]"
        )
    return uu, seg, rows


def _check_options(
    stripe_width_px: float,
    dot_size_px: float | None,
    half_rows: int | None,
    degree: int | str,
    max_shift_px: float,
    steger_scale: float,
    end_rows: int | None,
) -> tuple[float, float, int, int, int]:
    """The options of :func:`refine_centres` checked, defaults filled in: stripe width, dot
    size, half window R, degree (-1 for "auto") and end rows."""
    sw = positive_px(stripe_width_px, "stripe_width_px")
    if sw is None:
        raise SlitExtractionError("stripe_width_px must be given (a positive number of pixels)")
    ds = positive_px(dot_size_px, "dot_size_px") or sw
    if not math.isfinite(max_shift_px) or max_shift_px <= 0:
        raise SlitExtractionError(f"max_shift_px must be > 0, got {max_shift_px}")
    if not math.isfinite(steger_scale) or steger_scale <= 0:
        raise SlitExtractionError(f"steger_scale must be > 0, got {steger_scale}")
    if isinstance(degree, str):
        if degree != "auto":
            raise SlitExtractionError(f'degree must be "auto", 0, 1 or 2, got {degree!r}')
        deg = -1
    else:
        deg = int_at_least(degree, "degree", 0)
        if deg > 2:
            raise SlitExtractionError(f'degree must be "auto", 0, 1 or 2, got {degree}')
    R = refine_half_rows(sw) if half_rows is None else int_at_least(half_rows, "half_rows", 0)
    end = opening_length(ds) if end_rows is None else int_at_least(end_rows, "end_rows", 0)
    return sw, ds, R, deg, end


# --------------------------------------------------------------------------- compiled kernels
# The refinement reads the slit image only in the points' Steger windows. The highpass, the
# vertical opening and the stripes' lean are whole-image passes (OpenCV), the structure
# tensor's products (transposed, :func:`_tensor_products_t`) and the dot mask whole-image
# compiled passes; the opening along leaning stripes is made only in the cells
# the dot mask is read at (:func:`_opening_cells`); the dot
# refill (a run of dot pixels at a time, only in the rows the windows read) and the stripe
# slope it needs (the tensor's Gaussian: its pass along u column by column, for the blocks of
# rows around those runs; its pass along v at their middles) are made in compiled loops only
# for the runs the windows can meet, ahead of Steger's derivatives, with the values of
# :func:`refine_slit_image` there (to float32 rounding).

#: Rows per block of the horizontal pass of the slope's Gaussian (made where needed).
_SLOPE_BLOCK = 32


@njit(cache=True)
def _slope_rows(put, pvt, g, hx, hy, c, q0, q1):
    """The Gaussian ``g``'s pass along u (cv2.BORDER_REFLECT_101) of the structure tensor
    products ``put``, ``pvt`` (W, H) in rows ``q0`` .. ``q1`` - 1 of column ``c``, to ``hx``,
    ``hy`` (W, H): each sum float32, in order of the taps."""
    w = put.shape[0]
    nt = g.size
    rk = nt // 2
    # 1-D views: the inner loops vectorise (the longer the rows, the faster per row); four
    # taps per pass over the sums, added one after the other (the same order as one by one)
    sx = hx[c, q0:q1]
    sy = hy[c, q0:q1]
    sx[:] = 0.0
    sy[:] = 0.0
    j = 0
    while j + 4 <= nt:
        c0 = reflect101(c + j - rk, w)
        c1 = reflect101(c + j + 1 - rk, w)
        c2 = reflect101(c + j + 2 - rk, w)
        c3 = reflect101(c + j + 3 - rk, w)
        g0, g1, g2, g3 = g[j], g[j + 1], g[j + 2], g[j + 3]
        p0, p1, p2, p3 = put[c0, q0:q1], put[c1, q0:q1], put[c2, q0:q1], put[c3, q0:q1]
        for q in range(sx.size):
            sx[q] = (((sx[q] + g0 * p0[q]) + g1 * p1[q]) + g2 * p2[q]) + g3 * p3[q]
        p0, p1, p2, p3 = pvt[c0, q0:q1], pvt[c1, q0:q1], pvt[c2, q0:q1], pvt[c3, q0:q1]
        for q in range(sy.size):
            sy[q] = (((sy[q] + g0 * p0[q]) + g1 * p1[q]) + g2 * p2[q]) + g3 * p3[q]
        j += 4
    for jj in range(j, nt):
        cc = reflect101(c + jj - rk, w)
        gj = g[jj]
        px = put[cc, q0:q1]
        py = pvt[cc, q0:q1]
        for q in range(sx.size):
            sx[q] += gj * px[q]
            sy[q] += gj * py[q]


@njit(cache=True, inline="always")
def _slope_value(juu, juv):
    """The stripe slope du/dv from the integrated tensor products J_uu, J_uv (float32),
    clipped to +-1, float32 (as :func:`~multislit.stripes.slope.stripe_slope`)."""
    s = np.float32(-juv / max(juu, np.float32(1e-6)))
    return min(max(s, np.float32(-1.0)), np.float32(1.0))


@njit(cache=True)
def _run_slopes(hx, hy, g, cols, mids):
    """:func:`~multislit.stripes.slope.stripe_slope` at rows ``mids`` of columns ``cols``
    (n,): the Gaussian ``g``'s pass along v (cv2.BORDER_REFLECT_101) of the pass along u
    ``hx``, ``hy`` (W, H), each sum float32 in order of rows; (n,) float32. Four sums at a time
    away from the borders: independent sums interleaved, each in its own order."""
    h = hx.shape[1]
    nt = g.size
    rk = nt // 2
    n = cols.size
    out = np.empty(n, np.float32)
    inside = np.empty(n, np.intp)
    n_in = 0
    for j in range(n):
        mid = mids[j]
        c = cols[j]
        if mid - rk >= 0 and mid + rk < h:
            inside[n_in] = j
            n_in += 1
            continue
        juu = np.float32(0.0)
        juv = np.float32(0.0)
        for i in range(-rk, rk + 1):
            q = reflect101(mid + i, h)
            juu += g[i + rk] * hx[c, q]
            juv += g[i + rk] * hy[c, q]
        out[j] = _slope_value(juu, juv)
    t = 0
    while t + 4 <= n_in:
        j0, j1, j2, j3 = inside[t], inside[t + 1], inside[t + 2], inside[t + 3]
        x0 = hx[cols[j0], mids[j0] - rk : mids[j0] + rk + 1]
        x1 = hx[cols[j1], mids[j1] - rk : mids[j1] + rk + 1]
        x2 = hx[cols[j2], mids[j2] - rk : mids[j2] + rk + 1]
        x3 = hx[cols[j3], mids[j3] - rk : mids[j3] + rk + 1]
        y0 = hy[cols[j0], mids[j0] - rk : mids[j0] + rk + 1]
        y1 = hy[cols[j1], mids[j1] - rk : mids[j1] + rk + 1]
        y2 = hy[cols[j2], mids[j2] - rk : mids[j2] + rk + 1]
        y3 = hy[cols[j3], mids[j3] - rk : mids[j3] + rk + 1]
        a0 = a1 = a2 = a3 = np.float32(0.0)
        b0 = b1 = b2 = b3 = np.float32(0.0)
        for i in range(nt):
            gi = g[i]
            a0 += gi * x0[i]
            b0 += gi * y0[i]
            a1 += gi * x1[i]
            b1 += gi * y1[i]
            a2 += gi * x2[i]
            b2 += gi * y2[i]
            a3 += gi * x3[i]
            b3 += gi * y3[i]
        out[j0] = _slope_value(a0, b0)
        out[j1] = _slope_value(a1, b1)
        out[j2] = _slope_value(a2, b2)
        out[j3] = _slope_value(a3, b3)
        t += 4
    for tt in range(t, n_in):
        j = inside[tt]
        x = hx[cols[j], mids[j] - rk : mids[j] + rk + 1]
        y = hy[cols[j], mids[j] - rk : mids[j] + rk + 1]
        juu = np.float32(0.0)
        juv = np.float32(0.0)
        for i in range(nt):
            juu += g[i] * x[i]
            juv += g[i] * y[i]
        out[j] = _slope_value(juu, juv)
    return out


@njit(cache=True, inline="always")
def _run_bounds(mask, r, c, lim):
    """The run of dot pixels (``mask`` non-zero) through (r, c) in column c: rows start ..
    stop - 1, followed at most ``lim`` + 1 rows from r up and from start down (a longer run
    comes out longer than ``lim``)."""
    h = mask.shape[0]
    start = r
    while start > 0 and r - start <= lim and mask[start - 1, c]:
        start -= 1
    stop = r + 1
    while stop < h and stop - start <= lim and mask[stop, c]:
        stop += 1
    return start, stop


@njit(cache=True, inline="always")
def _row_sample(hp: F32, r: int, x: float) -> np.float32:
    """``hp`` interpolated linearly along row ``r`` at column ``x`` (as :func:`fill_dots`)."""
    w = hp.shape[1]
    x = min(max(x, 0.0), w - 1.0)
    u0 = min(int(math.floor(x)), w - 2) if w > 1 else 0
    f = np.float32(x - u0)
    a = hp[r, u0]
    b = hp[r, min(u0 + 1, w - 1)]
    return np.float32(a + np.float32(np.float32(b - a) * f))


@njit(cache=True, inline="always")
def _fill_run(hp, opened, slit, start, stop, c, lim, s, q0, q1):
    """:func:`fill_dots` for the run of dot pixels in rows ``start`` .. ``stop`` - 1 of column
    ``c`` (as :func:`_run_bounds` finds it), in its rows ``q0`` .. ``q1`` - 1: each pixel
    interpolated along the local stripe slope ``s`` (float32, :func:`_run_slopes`) between
    the clean pixels above and below the run, or the opening where the run is longer than
    ``lim`` or touches the image border; written to ``slit``."""
    h = hp.shape[0]
    n = stop - start
    if start == 0 or stop == h or n > lim:
        for q in range(q0, q1):
            slit[q, c] = opened[q, c]
        return
    for q in range(q0, q1):
        t = q - start + 1
        above = _row_sample(hp, start - 1, c - float(s) * t)
        below = _row_sample(hp, stop, c + float(s) * (n + 1 - t))
        frac = t / float(np.float32(n + 1))
        val = float(above) + float(np.float32(below - above)) * frac
        slit[q, c] = np.float32(min(val, float(hp[q, c])))


def _opening_cells(
    u: F64,
    r: NDArray[np.intp],
    active: NDArray[np.bool_],
    rad: int,
    length: int,
    h: int,
    w: int,
) -> NDArray[np.bool_]:
    """The cells of :func:`~multislit.stripes.slope.lean_map` ((``h`` // D, ``w`` // D), D x D
    px, the last ones taking the image's remainder) that can hold a pixel whose opening :func:`_refill_dots`
    reads through the dot mask, for the ``active`` points at columns ``u`` (K,) px, rows ``r``
    (K,), in an ``h`` x ``w`` px image: the mask is read in columns floor(u) - 1 - ``rad`` ..
    floor(u) + 1 + ``rad`` of the point's row and, along the dot runs there, up to 2
    ``length`` + 1 rows above and 2 ``length`` below; the mask's dilation widens that by 1 px.
    The cells of those columns in the point's row, widened along v by (2 ``length`` + 2) // D
    + 1 cells, which covers those rows. (nr, nc) bool."""
    f = LEAN_DECIMATION
    seeds = _seed_cells(u, r, active, rad, w, max(h // f, 1), max(w // f, 1))
    reach = (2 * length + 2) // f + 1
    cells = cv2.dilate(seeds, np.ones((2 * reach + 1, 1), np.uint8))
    return cells.view(np.bool_)


@njit(cache=True)
def _seed_cells(u, r, active, rad, w, nr, nc):
    """(nr, nc) uint8, 1 on the cells of D x D px (:data:`LEAN_DECIMATION`, a compile-time
    constant; the last ones taking the remainder) that hold columns floor(u) - 2 - ``rad`` ..
    floor(u) + 2 + ``rad`` of an ``active`` point's row ``r``."""
    f = LEAN_DECIMATION
    cells = np.zeros((nr, nc), np.uint8)
    for i in range(u.size):
        if not active[i]:
            continue
        c0 = int(math.floor(min(max(u[i], 0.0), w - 1.0)))
        q = min(r[i] // f, nr - 1)
        for cc in range(max(c0 - 2 - rad, 0) // f, min(c0 + 2 + rad, w - 1) // f + 1):
            cells[q, min(cc, nc - 1)] = 1
    return cells


@njit(cache=True)
def _refill_dots(hp, mask, opened, put, pvt, g, hx, hy, slit, u, r, active, rad, length):
    """The dot pixels (``mask`` non-zero) that :func:`_steger_kernel` can read refilled in
    ``slit`` (H, W) float32: those of columns floor(u) - 1 - ``rad`` .. floor(u) + 1 + ``rad``
    of the ``active`` points' rows (the Newton steps move by at most 1 px before the last
    evaluation), each as :func:`fill_dots` refills its run of dot pixels in its column
    (:func:`_fill_run`). ``put``, ``pvt`` (W, H) are the structure tensor products transposed
    and ``g`` the slope's Gaussian (:func:`_highpass_and_tensor`); ``hx``, ``hy`` (W, H)
    float32 work arrays for its pass along u. First the runs are found, in the points' order
    (row by row), with the rows the windows read in each (a run longer than 2 ``length``, which
    keeps the opening, is walked once and then followed row by row, not walked again from
    each row); then the slope Gaussian's pass along
    u is made, column by column in runs of blocks (:func:`_slope_rows` is fastest on long
    runs), around the middle of each run to interpolate, and its pass along v at those middles
    (:func:`_run_slopes`); then the runs are refilled in those rows."""
    h, w = mask.shape
    rk = g.size // 2
    lim = 2 * length
    nb = -(-h // _SLOPE_BLOCK)
    need = np.zeros((w, nb), np.uint8)
    # the last run found per column: rows start .. stop - 1, its index, the rows read in it
    seen_start = np.full(w, -1)
    seen_stop = np.full(w, -1)
    seen_run = np.full(w, -1)
    seen_lo = np.zeros(w, np.int64)
    seen_hi = np.zeros(w, np.int64)
    # (column, start, stop, first and last row read) of the runs found
    runs = np.empty((2 * u.size + 64, 5), np.int32)
    n_runs = 0
    for i in range(u.size):
        if not active[i]:
            continue
        ri = r[i]
        c0 = int(math.floor(min(max(u[i], 0.0), w - 1.0)))
        for cc in range(max(c0 - 1 - rad, 0), min(c0 + 1 + rad, w - 1) + 1):
            if not mask[ri, cc]:
                continue
            start, stop = seen_start[cc], seen_stop[cc]
            if start <= ri < stop or (stop - start > lim and start - 1 <= ri <= stop):
                # in the column's last run; or next to it where that is longer than lim: the
                # same run (a dot pixel next to its dot pixels), kept by the opening
                seen_start[cc] = min(start, ri)
                seen_stop[cc] = max(stop, ri + 1)
                seen_lo[cc] = min(seen_lo[cc], ri)
                seen_hi[cc] = max(seen_hi[cc], ri)
                continue
            if seen_run[cc] >= 0:  # the column's last run: the rows read in it
                runs[seen_run[cc], 3] = seen_lo[cc]
                runs[seen_run[cc], 4] = seen_hi[cc]
            start, stop = _run_bounds(mask, ri, cc, lim)
            seen_start[cc] = start
            seen_stop[cc] = stop
            seen_run[cc] = n_runs
            seen_lo[cc] = ri
            seen_hi[cc] = ri
            if n_runs == runs.shape[0]:
                more = np.empty((2 * n_runs, 5), np.int32)
                more[:n_runs] = runs
                runs = more
            runs[n_runs, 0] = cc
            runs[n_runs, 1] = start
            runs[n_runs, 2] = stop
            n_runs += 1
            n = stop - start
            if start == 0 or stop == h or n > lim:
                continue
            mid = start + n // 2
            lo = max(mid - rk, 0)
            hi = min(mid + rk, h - 1)  # reflected rows near the borders fall inside lo .. hi
            for b in range(lo // _SLOPE_BLOCK, hi // _SLOPE_BLOCK + 1):
                need[cc, b] = 1
    for cc in range(w):
        if seen_run[cc] >= 0:
            runs[seen_run[cc], 3] = seen_lo[cc]
            runs[seen_run[cc], 4] = seen_hi[cc]
    # the slope Gaussian's pass along u where the runs to interpolate need it
    for c in range(w):
        b = 0
        while b < nb:
            if not need[c, b]:
                b += 1
                continue
            e = b
            while e < nb and need[c, e]:
                e += 1
            _slope_rows(put, pvt, g, hx, hy, c, b * _SLOPE_BLOCK, min(e * _SLOPE_BLOCK, h))
            b = e
    # its pass along v at their middles
    cols = np.empty(n_runs, np.intp)
    mids = np.empty(n_runs, np.intp)
    which = np.empty(n_runs, np.intp)
    n_in = 0
    for k in range(n_runs):
        start = runs[k, 1]
        stop = runs[k, 2]
        if start > 0 and stop < h and stop - start <= lim:
            cols[n_in] = runs[k, 0]
            mids[n_in] = start + (stop - start) // 2
            which[n_in] = k
            n_in += 1
    slope = np.zeros(n_runs, np.float32)
    slope[which[:n_in]] = _run_slopes(hx, hy, g, cols[:n_in], mids[:n_in])
    # in the order found: row by row, as the memory lies
    for k in range(n_runs):
        c, start, stop, q0, q1 = runs[k, 0], runs[k, 1], runs[k, 2], runs[k, 3], runs[k, 4]
        _fill_run(hp, opened, slit, start, stop, c, lim, slope[k], q0, q1 + 1)


#: Points per batch of :func:`_steger_kernel`.
_STEGER_BATCH = 16


@njit(cache=True)
def _steger_kernel(slit, u, r, active, ss, max_shift):
    """Steger's centres (K,) px and where they are usable, by two Newton steps from ``u`` on
    the slit image ``slit`` (H, W) float32 (the dots that the steps can read refilled by
    :func:`_refill_dots`), for the ``active`` points (the others keep ``u``, not usable)."""
    h, w = slit.shape
    K = u.size
    rad = int(math.ceil(3.0 * ss)) + 1
    inv2 = 1.0 / (ss * ss)
    inv4 = inv2 * inv2
    # Gaussian weights exp(-(t / ss)^2 / 2) at t = f + k (f = c0 - x, k = -rad .. rad) as
    # exp(-f^2 / 2 ss^2) exp(-k^2 / 2 ss^2) exp(-f / ss^2)^k: two exponentials per evaluation
    gk = np.empty(2 * rad + 1)
    for k in range(-rad, rad + 1):
        gk[k + rad] = math.exp(-0.5 * k * k * inv2)
    m = u.copy()
    ok = np.zeros(K, np.bool_)
    # the active points _STEGER_BATCH at a time: each Newton step's samples for the batch,
    # then its sums (:func:`_steger_sums`), the batch's independent sums interleaved
    idx = np.flatnonzero(active)
    nb = _STEGER_BATCH
    p = np.empty((2 * rad + 1, nb))
    mi, fb, eb, ek = np.empty(nb), np.empty(nb), np.empty(nb), np.empty(nb)
    d1, d2 = np.empty(nb), np.empty(nb)
    good = np.zeros(nb, np.bool_)
    for s0 in range(0, idx.size, nb):
        n = min(nb, idx.size - s0)
        for j in range(n):
            mi[j] = u[idx[s0 + j]]
        for _ in range(2):  # Newton steps
            for j in range(n):
                ri = r[idx[s0 + j]]
                x = min(max(mi[j], 0.0), w - 1.0)
                c0 = int(math.floor(x))
                f = c0 - x
                e = math.exp(-f * inv2)
                fb[j] = f
                eb[j] = e
                ek[j] = math.exp(-0.5 * f * f * inv2) / e**rad  # the k = -rad factor
                for k in range(-rad, rad + 1):
                    p[k + rad, j] = float(slit[ri, min(max(c0 + k, 0), w - 1)])
            _steger_sums(p, fb[:n], eb[:n], ek[:n], gk, d1[:n], d2[:n], inv2, inv4)
            for j in range(n):
                good[j] = d2[j] < 0
                step = -(d1[j] * inv2) / d2[j] if good[j] else 0.0
                mi[j] = mi[j] + min(max(step, -1.0), 1.0)
        for j in range(n):
            i = idx[s0 + j]
            m[i] = mi[j]
            ok[i] = good[j] and abs(mi[j] - u[i]) <= max_shift
    return m, ok


@njit(cache=True, inline="always")
def _steger_sums(p, f, e, ek, gk, d1, d2, inv2, inv4):
    """The Gaussian derivative sums of :func:`_steger_kernel` for a batch of n points, each
    in order of the taps k = -rad .. rad: the samples ``p`` (2 rad + 1, >= n) px values, the
    offsets t = ``f`` + k (``f`` (n,) px), the weights ``ek`` ``gk[k]`` (``gk`` (2 rad + 1,)
    the Gaussian at integer k; ``ek`` (n,), the k = -rad factor, times ``e`` (n,) after each
    tap, updated); ``d1`` (n,) the sum of p t weight, ``d2`` (n,) of p (t^2 ``inv4`` -
    ``inv2``) weight (float64, written)."""
    n = f.size
    rad = gk.size // 2
    d1[:] = 0.0
    d2[:] = 0.0
    for k in range(-rad, rad + 1):
        gkk = gk[k + rad]
        pk = p[k + rad]
        fk = float(k)
        for j in range(n):
            t = f[j] + fk
            g = ek[j] * gkk
            ek[j] *= e[j]
            d1[j] += pk[j] * t * g
            d2[j] += pk[j] * (t * t * inv4 - inv2) * g


@njit(cache=True)
def _segment_rows(seg, r, span, end):
    """Points keyed by (segment, row): the key (K,) (-1 without a segment), the order that
    sorts it (stable), each point's place in that order, the sorted keys, and how far each
    point lies inside its segment beyond ``end`` rows from either end (K,)."""
    K = seg.size
    key = np.empty(K, np.int64)
    top = -1
    bottom = -1
    for i in range(K):
        key[i] = seg[i] * span + r[i] if seg[i] >= 0 else -1
        top = max(top, seg[i])
        bottom = min(bottom, seg[i])
    order = np.empty(K, np.intp)
    ordered = bottom == -1 and top <= 2 * K  # segment ids -1 .. a few per point
    if ordered:
        # the points come in row order (as from the extraction): a stable counting sort by
        # segment sorts the keys, found by checking them; else the merge sort
        start = np.zeros(top + 3, np.intp)
        for i in range(K):
            start[seg[i] + 2] += 1
        for b in range(1, top + 3):
            start[b] += start[b - 1]
        for i in range(K):
            order[start[seg[i] + 1]] = i
            start[seg[i] + 1] += 1
        for j in range(1, K):
            if key[order[j]] < key[order[j - 1]]:
                ordered = False
                break
    if not ordered:
        order = np.argsort(key, kind="mergesort")
    pos = np.empty(K, np.intp)
    skey = np.empty(K, np.int64)
    for j in range(K):
        pos[order[j]] = j
        skey[j] = key[order[j]]
    inner = np.empty(K, np.int64)
    j = 0
    while j < K:
        e = j
        while e + 1 < K and seg[order[e + 1]] == seg[order[j]]:
            e += 1
        for q in range(j, e + 1):
            i = order[q]
            inner[i] = min(r[i] - r[order[j]], r[order[e]] - r[i]) - end
        j = e + 1
    return key, order, pos, skey, inner


@njit(cache=True)
def _fit_kernel(seg, key, order, pos, skey, inner, m, u, row_ok, R, deg):
    """Least-squares polynomial of degree ``deg`` in dv through the Steger centres ``m`` of the
    same segment's rows v - R .. v + R (symmetric window shrunk at the segment's ends, rows
    with ``inner`` < 0 left out), relative to each point's ``u``: shift and ok (K,). ``deg``
    -1: both degree 1 (the shift) and 2; then also the degree-2 shift and var(shift2 - shift)
    per unit iid noise (K,), NaN where there is no degree-2 fit (else 0 and NaN), and the
    line's shift per unit of curvature (the line's intercept weights applied to dv^2; a
    stripe u = c dv^2 moves the line's shift by c times it), NaN where there is no line."""
    K = seg.size
    auto = deg < 0
    n = 3 if auto else deg + 1
    delta = np.zeros(K)
    delta2 = np.zeros(K)
    gain = np.full(K, np.nan)
    bend = np.full(K, np.nan)
    ok = np.zeros(K, np.bool_)
    need = min(3 if auto else deg + 2, 2 * R + 1)
    for i in range(K):
        reach = min(inner[i], R)
        if seg[i] < 0 or inner[i] < 0 or reach < R // 2:
            continue
        # the normal equations' moments sum(dv^k) (integers, exact) and right-hand sides
        # sum((m - u) dv^k), in order of dv
        m0 = m1 = m2 = m3 = m4 = 0.0
        r0 = r1 = r2 = 0.0
        count = 0
        # leftmost sorted position with skey >= key + dv (np.searchsorted), walked back from
        # the point's own position for dv = -reach, then forward as dv grows
        q = pos[i]
        while q > 0 and skey[q - 1] >= key[i] - reach:
            q -= 1
        for dv in range(-reach, reach + 1):
            target = key[i] + dv
            while q < K and skey[q] < target:
                q += 1
            if q == K or skey[q] != target:
                continue
            nb = order[q]
            if not row_ok[nb] or inner[nb] < 0:
                continue
            count += 1
            e = m[nb] - u[i]
            fv = float(dv)
            f2 = fv * fv
            m0 += 1.0
            r0 += e
            if n >= 2:
                m1 += fv
                m2 += f2
                r1 += e * fv
            if n >= 3:
                m3 += f2 * fv
                m4 += f2 * f2
                r2 += e * f2
        if count < need:
            continue
        if n == 1:
            det = m0
            if abs(det) > 1e-9 * max(m0, 1.0):
                delta[i] = r0 / det
                ok[i] = True
            continue
        det = m0 * m2 - m1 * m1
        line = abs(det) > 1e-9 * max(m0, 1.0) ** 2
        if n == 2 or auto:
            if line:
                delta[i] = (r0 * m2 - m1 * r1) / det
                ok[i] = True
                if auto:
                    bend[i] = (m2 * m2 - m1 * m3) / det
            if n == 2 or not line or count < 4:
                continue
        # the normal matrix's first row of cofactors (it is symmetric, Hankel in the moments)
        c0 = m2 * m4 - m3 * m3
        c1 = m2 * m3 - m1 * m4
        c2 = m1 * m3 - m2 * m2
        det3 = m0 * c0 + m1 * c1 + m2 * c2
        if abs(det3) <= 1e-9 * max(m0, 1.0) ** 3:
            continue
        d2 = (c0 * r0 + c1 * r1 + c2 * r2) / det3
        if auto:
            delta2[i] = d2
            # var(shift2) - var(shift1) for unit noise: (A3^-1)_00 - (A2^-1)_00
            gain[i] = c0 / det3 - m2 / det
        else:
            delta[i] = d2
            ok[i] = True
    return delta, ok, delta2, gain, bend


@njit(cache=True)
def _bend_kernel(seg, order, skey, inner, m, row_ok, W):
    """The dv^2 coefficient of the least-squares parabola through the Steger centres ``m`` of
    the same segment's rows v - W .. v + W (as :func:`_fit_kernel` with degree 2: symmetric,
    shrunk at the segment's ends, rows with ``inner`` < 0 or not ``row_ok`` left out; none
    where the window reaches fewer than W // 2 rows or holds fewer than 4), and ok (K,): from
    running sums over each segment's rows, so that a wide window costs what a narrow one does.
    Rows are counted from the segment's first, centres from its first centre (the sums stay
    small). The windows' ends only move forward along the sorted keys ``skey`` (a point's key
    less its reach and plus it never decrease along a segment), so two pointers find them."""
    K = seg.size
    # running sums, restarted at each segment, over the sorted points that take part:
    # 1, x, x^2, x^3, x^4, y, y x, y x^2 (x the row, y the centre, both from the segment's first)
    a0 = np.zeros(K)
    a1 = np.zeros(K)
    a2 = np.zeros(K)
    a3 = np.zeros(K)
    a4 = np.zeros(K)
    b0 = np.zeros(K)
    b1 = np.zeros(K)
    b2 = np.zeros(K)
    start = np.zeros(K, np.intp)
    k0 = 0
    y0 = 0.0
    for q in range(K):
        i = order[q]
        if q == 0 or seg[order[q - 1]] != seg[i]:
            k0 = skey[q]
            y0 = m[i]
            start[q] = q
            s0 = s1 = s2 = s3 = s4 = t0 = t1 = t2 = 0.0
        else:
            start[q] = start[q - 1]
            s0, s1, s2, s3, s4 = a0[q - 1], a1[q - 1], a2[q - 1], a3[q - 1], a4[q - 1]
            t0, t1, t2 = b0[q - 1], b1[q - 1], b2[q - 1]
        if seg[i] >= 0 and row_ok[i] and inner[i] >= 0:
            x = float(skey[q] - k0)
            y = m[i] - y0
            x2 = x * x
            s0 += 1.0
            s1 += x
            s2 += x2
            s3 += x2 * x
            s4 += x2 * x2
            t0 += y
            t1 += y * x
            t2 += y * x2
        a0[q], a1[q], a2[q], a3[q], a4[q] = s0, s1, s2, s3, s4
        b0[q], b1[q], b2[q] = t0, t1, t2
    curv = np.zeros(K)
    ok = np.zeros(K, np.bool_)
    lo = 0
    hi = 0
    for q in range(K):
        i = order[q]
        reach = min(inner[i], W)
        if seg[i] < 0 or inner[i] < 0 or reach < W // 2:
            continue
        while skey[lo] < skey[q] - reach:
            lo += 1
        hi = max(hi, q)
        while hi + 1 < K and skey[hi + 1] <= skey[q] + reach:
            hi += 1
        p = lo - 1
        inside = lo > start[q]  # else the window starts at the segment's first point
        m0 = a0[hi] - (a0[p] if inside else 0.0)
        if m0 < 4:
            continue
        S1 = a1[hi] - (a1[p] if inside else 0.0)
        S2 = a2[hi] - (a2[p] if inside else 0.0)
        S3 = a3[hi] - (a3[p] if inside else 0.0)
        S4 = a4[hi] - (a4[p] if inside else 0.0)
        T0 = b0[hi] - (b0[p] if inside else 0.0)
        T1 = b1[hi] - (b1[p] if inside else 0.0)
        T2 = b2[hi] - (b2[p] if inside else 0.0)
        xi = float(skey[q] - skey[start[q]])
        # the moments about the point's row: sum(dv^k), sum(y dv^k)
        m1 = S1 - xi * m0
        m2 = S2 - 2.0 * xi * S1 + xi * xi * m0
        m3 = S3 - 3.0 * xi * S2 + 3.0 * xi * xi * S1 - xi**3 * m0
        m4 = S4 - 4.0 * xi * S3 + 6.0 * xi * xi * S2 - 4.0 * xi**3 * S1 + xi**4 * m0
        r1 = T1 - xi * T0
        r2 = T2 - 2.0 * xi * T1 + xi * xi * T0
        c0 = m2 * m4 - m3 * m3
        c1 = m2 * m3 - m1 * m4
        c2 = m1 * m3 - m2 * m2
        det3 = m0 * c0 + m1 * c1 + m2 * c2
        if abs(det3) <= 1e-9 * max(m0, 1.0) ** 3:
            continue
        curv[i] = (c2 * T0 + (m1 * m2 - m0 * m3) * r1 + (m0 * m2 - m1 * m1) * r2) / det3
        ok[i] = True
    return curv, ok


@njit(cache=True)
def _partner_kernel(sk, off):
    """For sorted keys ``sk`` (n,): where ``sk + off`` occurs in ``sk`` (n,) bool, and the
    position np.searchsorted(sk, sk + off) clipped to 0 .. n - 1 (n,), by one merge walk."""
    n = sk.size
    there = np.zeros(n, np.bool_)
    j = np.zeros(n, np.intp)
    q = 0
    for i in range(n):
        t = sk[i] + off  # non-decreasing in i
        while q < n and sk[q] < t:
            q += 1
        jj = min(q, n - 1)
        j[i] = jj
        there[i] = sk[jj] == t
    return there, j


@njit(cache=True)
def _curved_kernel(order, sk, delta1, delta2, d, gain, s2, level, R):
    """The end of :func:`_pick_curved`: ``delta2`` where d = ``delta2`` - ``delta1`` is
    significant, d^2 > ``gain`` ``s2`` ``level``, and so is d, with the same sign, in the window
    R rows before or after on the segment; else ``delta1`` (K,). ``order`` (n,): the points
    with a gain sorted by key, ``sk`` (n,) their keys."""
    n = order.size
    sig = np.zeros(d.size, np.bool_)
    for t in range(n):
        i = order[t]
        sig[i] = d[i] * d[i] > gain[i] * s2 * level
    # a surface's curvature goes on along the stripe; one bad row centre flips the sign of d
    # between windows R rows apart
    confirmed = np.zeros(n, np.bool_)
    for off in (-R, R):
        there, j = _partner_kernel(sk, off)
        for t in range(n):
            nb = order[j[t]]
            if there[t] and sig[nb] and np.sign(d[nb]) == np.sign(d[order[t]]):
                confirmed[t] = True
    out = delta1.copy()
    for t in range(n):
        i = order[t]
        if sig[i] and confirmed[t]:
            out[i] = delta2[i]
    return out


@njit(cache=True)
def _row_gaps_kernel(u, r, h):
    """(K,) px: distance from each point to the nearest other point of its row (inf if none)."""
    K = u.size
    start = np.zeros(h + 1, np.intp)
    for i in range(K):
        start[r[i] + 1] += 1
    for q in range(h):
        start[q + 1] += start[q]
    order = np.empty(K, np.intp)
    fill = start[:h].copy()
    for i in range(K):
        order[fill[r[i]]] = i
        fill[r[i]] += 1
    gap = np.full(K, np.inf)
    for q in range(h):
        idx = order[start[q] : start[q + 1]]
        if idx.size < 2:
            continue
        srt = idx[np.argsort(u[idx], kind="mergesort")]
        for j in range(srt.size - 1):
            d = u[srt[j + 1]] - u[srt[j]]
            gap[srt[j]] = min(gap[srt[j]], d)
            gap[srt[j + 1]] = min(gap[srt[j + 1]], d)
    return gap


def compile_kernels() -> None:
    """Compile the refinement's and the row median's Numba kernels now.

    Numba compiles them on first use (about 20 s) and caches the machine code on disk beside
    the package, so only the first refinement after an install pays it;
    :func:`multislit.stripes.compile_kernels` calls this.
    """
    img = np.zeros((48, 48), np.uint8)
    img[:, 22:26] = 200
    img[10:12, 30:32] = 120  # a dot beside the stripe
    img[30:32, 26:28] = 255  # and one touching it (its refill)
    v = np.arange(4.0, 44.0)
    refine_centres(img, np.full(len(v), 23.5), v, np.zeros(len(v), np.int64), 4.0, 2.0)
    one = np.zeros(1)  # the curved fit's choice, which a straight stripe never reaches
    _curved_kernel(np.zeros(1, np.intp), np.zeros(1, np.int64), one, one, one, one, 1.0, 1.0, 1)
    row_median_background(img, 3)

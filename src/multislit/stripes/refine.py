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
    _DOT_OPENING_FRACTION,
    _above_opening,
    fill_dots,
    noise_from_difference,
    row_median_background,
)
from multislit.stripes.sizes import FWHM_PER_SIGMA, median_stride, opening_length
from multislit.stripes.slope import (
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
    """The whole image on the background of :func:`refine_centres`, its dots refilled.

    The row median background (:func:`row_median_background`) has pixel-to-pixel noise
    (neighbouring pixels' medians are taken over different samples) and follows the flanks
    of nearby stripes; a stripe's profile inherits both as a slope that moves its centre. Here
    it is averaged by a ``bg_cols`` x ``bg_rows`` box (along u and v), not clipped at 0, and
    the dots are found (the opening following leaning stripes) and refilled by interpolation
    along the stripe as in the extraction. :func:`refine_centres` makes its slit image only
    on strips along the identified segments, each strip's opening and refill following the
    segment's own line; this is the image-wide view of it.

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
    noise_sigma: float | None = None,
) -> tuple[F64, NDArray[np.bool_]]:
    """Re-centre identified stripe points for triangulation: less laser-speckle noise.

    Meant to run after the slit identification, which keeps the extraction's own centres.
    For each point:

    1. Steger's centre in its row: the zero of the first derivative of the row profile
       smoothed by a Gaussian of ``steger_scale`` stripe sigmas, by one Newton step from the
       given centre (clamped to 1 px; the profile is symmetric about its centre, so the
       step's error is of third order in the given centre's), on the image less its row
       median background averaged over 2 ``half_rows`` + 1 rows and 2 :func:`median_stride`
       + 1 columns, its dots refilled. That
       slit image is made only on a strip along each segment (the Steger window's reach and
       3 px to spare either side of the segment's line, a least-squares parabola through its
       points over 3 R rows either side of each row): the dots are the pixels above the
       strip's opening along the segment's line by 3 noise sigmas and 5 % (widened by 1 px),
       and each run of them in a column is interpolated along the line from the pixels above
       and below it, as :func:`fill_dots` does along the stripe's slope. The opening's line
       (``length`` rows, :func:`opening_length` of the dot size) follows the segment's line
       itself, and the refill reads along the parabola of each run's middle row, its bend less
       the bend that the given centres' noise puts in it (:func:`_shrink_bend`): on a curved
       stripe (the arcs on a sphere near its outline) a straight line along the slope leaves
       the stripe towards the outside of the curve at its ends, the opening then lies below
       the stripe's outer flank, which is taken for dots and refilled lower, and the centre
       moves to the inside of the curve; on a straight one, following the noise's bend would
       read beside the stripe.
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
    noise_sigma : the image's pixel noise sigma (intensity units) for the dot threshold, as
        :func:`~multislit.stripes.separation.noise_from_difference` measures it: give the
        extraction's (:attr:`SlitExtraction.noise_sigma`, the same measure of the same image)
        not to measure it again; default measured here

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
    noise = _check_noise(noise_sigma)
    K = uu.size
    out = uu.copy()
    if K == 0:
        return out, np.zeros(0, bool)

    sigma = sw / FWHM_PER_SIGMA
    ss = max(steger_scale * sigma, 0.7)
    r = rows.astype(np.intp)
    # > row range + the widest window: keys of two segments never meet
    span = h + 2 * max(1, _BEND_WINDOWS) * R + 2
    key, order, skey, inner = _segment_rows(seg, r, span, end)
    # Steger's centres of the points that can take part in a fit (on a segment, not at its end),
    # on the slit image made only on strips along their segments
    active = (seg >= 0) & (inner >= 0)
    rad = math.ceil(3.0 * ss) + 1  # the Steger kernel's half width (px)
    length = opening_length(ds)
    bg = _background(img, sw, R)
    # the strips: the Steger window's reach and 3 px to spare, along the centre line of each
    # segment; beyond its ends as far as the opening reaches
    half = rad + 3
    W = _BEND_WINDOWS * R
    rows, centre, slope, bend, bounds, where = _strip_layout(
        seg, order, skey, span, uu, active, W, length - 1, h
    )
    col0 = np.rint(centre).astype(np.int64) - half
    strip = _gather_strips(img, bg, rows, col0, 2 * half + 1)
    # the dots: the opening along the segment's line (its curve) in image coordinates, the
    # dot mask on it, widened by 1 px
    tau = 3.0 * (noise_from_difference(img) if noise is None else noise)
    r_open = length // 2
    opened = _line_extreme(strip, col0, bounds, centre, r_open, False)
    opened = _line_extreme(opened, col0, bounds, centre, r_open, True)
    mask = np.empty(strip.shape, np.uint8)
    _above_opening(strip, opened, np.float32(_DOT_OPENING_FRACTION), np.float32(tau), mask)
    mask = _dilate_mask(mask, col0, bounds)
    # the refill along each run's parabola, its bend less the given centres' noise in it
    bend = _shrink_bend(bend, bounds, length - 1, W)
    slit = _refill_strips(strip, opened, mask, slope, bend, col0, bounds, 2 * length)
    # the active points in the order of their strips' rows (sorted by segment and row)
    m, row_ok = _steger_kernel(slit, col0, where, uu, order[active[order]], ss, max_shift_px, w)
    delta, ok, delta2, gain, bend = _fit_kernel(seg, key, order, skey, inner, m, uu, row_ok, R, deg)
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


def _shrink_bend(bend: F64, bounds: NDArray[np.int64], pad: int, W: int) -> F64:
    """The centre line's bend (N,) px/row^2 (:func:`_strip_layout`) less its noise: the given
    centres' errors (correlated along the stripe) bend the parabola through them, by s ~ 2e-4
    px/row^2 at 25 slits (u'' ~ 4e-4), as much as a straight stripe's lens-distortion bow; the
    refill that followed that noise would read beside the stripe. s^2 is measured as in
    :func:`_pick_curved`: from pairs of stacked rows 2 ``W`` + 1 apart inside one strip's
    segment rows (``bounds`` (S + 1,), ``pad`` rows beyond each end), whose windows are
    disjoint and whose difference of bend has variance 2 s^2 where the stripe's own bend
    changes little between them: median((b_a - b_b)^2) / (2 median(chi2_1)). Each bend b is
    shrunk to b max(0, 1 - s^2 / b^2) (the positive-part James-Stein estimate: nought where
    it is within its noise, the bend of a sphere's arc near its outline, ~0.01 px/row^2, kept
    to a few per cent). With fewer than 50 pairs, nought everywhere (the slope's line)."""
    lag = 2 * W + 1
    n = bend.size
    if n <= lag:
        return np.zeros_like(bend)
    strip_of = np.repeat(np.arange(bounds.size - 1), np.diff(bounds))
    t = np.arange(n - lag)
    g = strip_of[t]
    pair = (g == strip_of[t + lag]) & (t - bounds[g] >= pad) & (bounds[g + 1] - 1 - pad >= t + lag)
    if pair.sum() < _CURVED_MIN_PAIRS:
        return np.zeros_like(bend)
    d = bend[t[pair]] - bend[t[pair] + lag]
    s2 = float(np.median(d * d)) / (2.0 * _CHI2_MEDIAN)
    b2 = bend * bend
    return np.where(b2 > s2, bend * (1.0 - s2 / np.maximum(b2, 1e-300)), 0.0)


def _background(img: NDArray, sw: float, R: int) -> F32:
    """The background of :func:`refine_slit_image`, (H, W) float32: the row median background
    of ``img`` averaged over 2 ``R`` + 1 rows and 2 :func:`median_stride` + 1 columns (``sw``
    the stripe FWHM, px)."""
    stride = median_stride(sw)
    # the median of integer data is exact in its own type; the box mean as cv2.blur's
    bg = row_median_background(img, stride)
    ksize = (2 * stride + 1, 2 * R + 1)
    return cv2.boxFilter(bg, cv2.CV_32F, ksize, normalize=True, borderType=cv2.BORDER_REFLECT)


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


def _check_noise(noise_sigma: float | None) -> float | None:
    """The ``noise_sigma`` of :func:`refine_centres` checked: None, or a positive float."""
    if noise_sigma is None:
        return None
    try:
        x = float(noise_sigma)
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise SlitExtractionError(
            f"noise_sigma must be a positive number (intensity units), got {noise_sigma!r}"
        )
    return x


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
# The refinement makes the slit image only along the identified stripes: on strips that follow
# each segment's line (:func:`_strip_layout`), the Steger window's reach wide, stacked into
# one (N, D) array. The background is a whole-image pass (the row median and OpenCV's box
# mean); the strips are gathered from the image less it (:func:`_gather_strips`), opened along
# the segment's line in image coordinates (:func:`_line_extreme`), their dots masked
# (:func:`_dilate_mask`) and refilled along it (:func:`_refill_strips`) in compiled
# loops ahead of Steger's derivatives (:func:`_steger_kernel`), which read the strips.


@njit(cache=True)
def _centre_parabola(s0, s1, s2, s3, s4, t0, t1, t2, xi, c):
    """The least-squares parabola y = c0 + c1 d + c2 d^2 (d = x - ``xi``) through points
    whose sums of x^k are ``s0`` .. ``s4`` (int) and of y x^k ``t0`` .. ``t2``, into ``c`` (3,);
    the line (c2 = 0) through fewer than three points or where the parabola's normal
    equations are singular; ``c`` left as it is (the row before's) through fewer than two."""
    # the moments about xi (exact integers), and the right-hand sides
    m1 = s1 - xi * s0
    m2 = s2 - 2 * xi * s1 + xi * xi * s0
    m3 = s3 - 3 * xi * s2 + 3 * xi * xi * s1 - xi * xi * xi * s0
    m4 = s4 - 4 * xi * s3 + 6 * xi * xi * s2 - 4 * xi * xi * xi * s1 + xi * xi * xi * xi * s0
    f = float(xi)
    r0 = t0
    r1 = t1 - f * t0
    r2 = t2 - 2.0 * f * t1 + f * f * t0
    n, a1, a2, a3, a4 = float(s0), float(m1), float(m2), float(m3), float(m4)
    if s0 >= 3:
        c0 = a2 * a4 - a3 * a3
        c1 = a2 * a3 - a1 * a4
        c2 = a1 * a3 - a2 * a2
        det3 = n * c0 + a1 * c1 + a2 * c2
        if abs(det3) > 1e-9 * n**3:
            c[0] = (c0 * r0 + c1 * r1 + c2 * r2) / det3
            c[1] = (c1 * r0 + (n * a4 - a2 * a2) * r1 + (a1 * a2 - n * a3) * r2) / det3
            c[2] = (c2 * r0 + (a1 * a2 - n * a3) * r1 + (n * a2 - a1 * a1) * r2) / det3
            return
    det = n * a2 - a1 * a1
    if s0 >= 2 and det > 1e-9 * n * n:
        c[1] = (n * r1 - a1 * r0) / det
        c[0] = (r0 - c[1] * a1) / n
        c[2] = 0.0


@njit(cache=True)
def _strip_layout(seg, order, skey, span, u, active, W, pad, h):
    """The strips of :func:`refine_centres`: one per segment that holds an ``active`` point,
    over its rows from first to last and ``pad`` rows beyond each end (the rows beyond the
    image's ``h`` rows repeat its first or last), stacked. ``seg``, ``u``, ``active`` (K,) the points; ``order`` and ``skey``
    (K,) their sorted order and keys (segment * ``span`` + row, :func:`_segment_rows`).

    The centre line in each row is a least-squares parabola in v through the segment's points
    (the given ``u``) in rows v - W .. v + W, the window cut at the segment's ends (the end
    row's parabola beyond them), read at v (:func:`_centre_parabola`: the line through fewer
    than three points, the row before's through fewer than two); its slope and half its
    second derivative are the parabola's there.

    Returns
    -------
    rows : (N,) int64, the image row of each stacked row
    centre : (N,) float64, px, the centre line's column in it
    slope : (N,) float64, px per row, its slope du/dv there
    bend : (N,) float64, px per row^2, half its second derivative (the parabola's dv^2
        coefficient)
    bounds : (S + 1,) int64, strip s holds stacked rows bounds[s] .. bounds[s + 1] - 1
    where : (K,) int64, the stacked row of each active point (-1 for the others)
    """
    K = seg.size
    # the segments with an active point: their runs of sorted positions
    n_strips = 0
    n_rows = 0
    j = 0
    first = np.empty(K + 1, np.int64)
    last = np.empty(K + 1, np.int64)
    while j < K:
        e = j
        while e + 1 < K and seg[order[e + 1]] == seg[order[j]]:
            e += 1
        keep = False
        if seg[order[j]] >= 0:
            for q in range(j, e + 1):
                keep = keep or active[order[q]]
        if keep:
            first[n_strips] = j
            last[n_strips] = e
            n_strips += 1
            r0 = skey[j] - seg[order[j]] * span
            r1 = skey[e] - seg[order[j]] * span
            n_rows += r1 - r0 + 1 + 2 * pad
        j = e + 1
    rows = np.empty(n_rows, np.int64)
    centre = np.empty(n_rows)
    slope = np.empty(n_rows)
    bend = np.empty(n_rows)
    bounds = np.empty(n_strips + 1, np.int64)
    where = np.full(K, -1, np.int64)
    at = 0
    for g in range(n_strips):
        qa, qb = first[g], last[g]
        base = seg[order[qa]] * span
        r0 = skey[qa] - base
        r1 = skey[qb] - base
        y0 = u[order[qa]]
        bounds[g] = at
        lo = qa  # the window's points: sorted positions lo .. hi - 1
        hi = qa
        # sums over them of x^k (k = 0 .. 4; integers, exact) and y x^k (k = 0 .. 2), x the
        # row from r0, y the centre from y0
        s0 = s1 = s2 = s3 = s4 = 0
        t0 = t1 = t2 = 0.0
        c = np.zeros(3)  # the parabola about row t: value, slope, half the second derivative
        top = r0 - pad
        for row in range(top, r1 + pad + 1):
            t = min(max(row, r0), r1)  # beyond the ends: the end row's parabola
            if row == t or row == top:
                while hi <= qb and skey[hi] - base <= t + W:
                    x = skey[hi] - base - r0
                    y = u[order[hi]] - y0
                    s0 += 1
                    s1 += x
                    s2 += x * x
                    s3 += x * x * x
                    s4 += x * x * x * x
                    t0 += y
                    t1 += x * y
                    t2 += x * x * y
                    hi += 1
                while lo < hi and skey[lo] - base < t - W:
                    x = skey[lo] - base - r0
                    y = u[order[lo]] - y0
                    s0 -= 1
                    s1 -= x
                    s2 -= x * x
                    s3 -= x * x * x
                    s4 -= x * x * x * x
                    t0 -= y
                    t1 -= x * y
                    t2 -= x * x * y
                    lo += 1
                _centre_parabola(s0, s1, s2, s3, s4, t0, t1, t2, t - r0, c)
            d = min(max(row, 0), h - 1) - t  # the row read, from the parabola's
            rows[at] = t + d
            centre[at] = y0 + c[0] + (c[1] + c[2] * d) * d
            slope[at] = c[1] + 2.0 * c[2] * d
            bend[at] = c[2]
            at += 1
        for q in range(qa, qb + 1):
            i = order[q]
            if active[i]:
                where[i] = bounds[g] + (skey[q] - base) - top
    bounds[n_strips] = at
    return rows, centre, slope, bend, bounds, where


@njit(cache=True)
def _gather_strips(img, bg, rows, col0, width):
    """(N, ``width``) float32, the strips: the highpass ``img`` - ``bg`` ((H, W), ``bg``
    float32; float32 arithmetic) in row ``rows[t]``, columns ``col0[t]`` .. ``col0[t]`` +
    ``width`` - 1 (clamped to the image), for each stacked row t."""
    w = img.shape[1]
    n = rows.size
    out = np.empty((n, width), np.float32)
    for t in range(n):
        src = img[rows[t]]
        back = bg[rows[t]]
        dst = out[t]
        c = col0[t]
        for k in range(width):
            cc = min(max(c + k, 0), w - 1)
            dst[k] = np.float32(src[cc]) - back[cc]
    return out


@njit(cache=True, inline="always")
def _line_offset(centre, t, j):
    """The column offset of stacked row t + ``j`` from row ``t`` on the centre line ``centre``
    (N,) px: its difference between the rows rounded half away from zero (the offset from t + j
    back to t is its negative: the line through each pixel is the same curve moved sideways)."""
    x = centre[t + j] - centre[t]
    return int(math.floor(x + 0.5)) if x >= 0 else -int(math.floor(0.5 - x))


@njit(cache=True)
def _line_extreme(src, col0, bounds, centre, r, take_max):
    """The min (or with ``take_max`` the max) of the strips ``src`` (N, D) over the digital
    curve of 2 ``r`` + 1 rows through each pixel in image coordinates that follows the centre
    line ``centre`` (N,) px: for stacked row t, rows t + j (j = -r .. r, within the strip;
    ``bounds`` (S + 1,) the strips' first rows) at image column c + round(``centre[t + j]`` -
    ``centre[t]``) (:func:`_line_offset`; stacked row t holds image columns ``col0[t]`` ..);
    samples beyond the strip are left out (N, D), dtype of ``src``. A straight centre line
    gives the digital line along its slope, a constant one the vertical line; the curve
    through a pixel passes through the pixels whose curves pass through it, so the dilation by
    it is the max over the same curve. For each j, the rows whose sample lies the same number
    of columns over run as one loop over their pixels (most often none over: the strip's first
    column follows the centre line)."""
    width = src.shape[1]
    out = src.copy()
    a = out.ravel()  # row t, column k at t D + k
    b = src.ravel()
    for g in range(bounds.size - 1):
        t0, t1 = bounds[g], bounds[g + 1]
        for j in range(-r, r + 1):
            if j == 0:
                continue
            t = max(t0, t0 - j)  # the rows t whose row t + j lies in the strip
            end = min(t1, t1 - j)
            while t < end:
                d = col0[t] + _line_offset(centre, t, j) - col0[t + j]  # column k: k + d in t + j
                e = t + 1
                while e < end and col0[e] + _line_offset(centre, e, j) - col0[e + j] == d:
                    e += 1
                # rows t .. e - 1: columns lo .. hi - 1 (all of them where d is 0)
                lo = max(0, -d)
                hi = min(width, width - d)
                for q in range(t, e if d != 0 else t + 1):
                    first = q * width + lo if d != 0 else t * width
                    n = hi - lo if d != 0 else (e - t) * width
                    x = a[first : first + n]  # 1-D views from 0: the loops vectorise
                    y = b[first + j * width + d : first + j * width + d + n]
                    if take_max:
                        for k in range(n):
                            x[k] = max(x[k], y[k])
                    else:
                        for k in range(n):
                            x[k] = min(x[k], y[k])
                t = e
    return out


@njit(cache=True)
def _dilate_mask(mask, col0, bounds):
    """The dot mask ``mask`` (N, D) uint8 of the strips dilated by 3 x 3 px in image
    coordinates (as :func:`~multislit.stripes.separation.dot_mask` widens it): along the
    rows, then over the stacked rows above and below (:func:`_line_extreme` with a constant
    centre line: the pixels straight above and below in the image)."""
    n, width = mask.shape
    wide = mask.copy()
    a = mask.ravel()  # row t, column k at t D + k: one loop over all rows, then their ends
    b = wide.ravel()
    lo, mid, hi = a[: a.size - 2], a[1 : a.size - 1], a[2:]
    out = b[1 : b.size - 1]
    for i in range(out.size):
        out[i] = max(lo[i], max(mid[i], hi[i]))
    for t in range(n):
        m = mask[t]
        wide[t, 0] = max(m[0], m[min(1, width - 1)])
        wide[t, width - 1] = max(m[width - 1], m[max(width - 2, 0)])
    return _line_extreme(wide, col0, bounds, np.zeros(n), 1, True)


@njit(cache=True, inline="always")
def _strip_sample(strip, t, x):
    """The strips ``strip`` (N, D) interpolated linearly along stacked row ``t`` at column
    ``x`` (clamped to 0 .. D - 1), float32 (as :func:`fill_dots` reads a row)."""
    d = strip.shape[1]
    x = min(max(x, 0.0), d - 1.0)
    k = min(int(math.floor(x)), d - 2)
    f = np.float32(x - k)
    a = strip[t, k]
    return np.float32(a + np.float32(np.float32(strip[t, k + 1] - a) * f))


@njit(cache=True)
def _refill_strips(strip, opened, mask, slope, bend, col0, bounds, lim):
    """The strips' dot pixels refilled, (N, D) float32, as :func:`fill_dots` refills along
    the stripe's slope, here along a parabola. ``strip`` (N, D): the strips as
    :func:`_gather_strips` makes them, stacked row t holding image columns ``col0[t]`` ..;
    ``opened`` and ``mask`` (N, D) their opening and dot mask (non-zero on dot pixels). In
    each column of a strip, a run of dot pixels in stacked rows start .. stop - 1 is
    interpolated linearly between the rows start - 1 and stop, read along the parabola of the
    run's middle row m, f(x) = s (x - m) + b (x - m)^2 (``slope`` s px per row and ``bend`` b
    px per row^2 (N,) at m): pixel q at image column c reads row x at c + f(x) - f(q) (by
    linear interpolation in ``strip``); the value is kept below the pixel's own. A run longer
    than ``lim`` or reaching the strip's first or last row takes the opening."""
    out = strip.copy()
    width = strip.shape[1]
    for g in range(bounds.size - 1):
        t0, t1 = bounds[g], bounds[g + 1]
        for k in range(width):
            t = t0
            while t < t1:
                if not mask[t, k]:
                    t += 1
                    continue
                start = t
                while t < t1 and mask[t, k]:
                    t += 1
                stop = t
                n = stop - start
                if start == t0 or stop == t1 or n > lim:
                    for q in range(start, stop):
                        out[q, k] = opened[q, k]
                    continue
                a = start - 1
                mid = start + n // 2
                s = slope[mid]
                b = bend[mid]
                fa = s * (a - mid) + b * (a - mid) * (a - mid)
                fb = s * (stop - mid) + b * (stop - mid) * (stop - mid)
                step = 1.0 / float(np.float32(n + 1))
                for q in range(start, stop):
                    # the pixel's image column less the parabola at its row
                    c = col0[q] + k - (s * (q - mid) + b * (q - mid) * (q - mid))
                    above = _strip_sample(strip, a, c + fa - col0[a])
                    below = _strip_sample(strip, stop, c + fb - col0[stop])
                    val = float(above) + float(np.float32(below - above)) * ((q - a) * step)
                    out[q, k] = np.float32(min(val, float(strip[q, k])))
    return out


#: Points per batch of :func:`_steger_kernel`.
_STEGER_BATCH = 16


@njit(cache=True)
def _steger_kernel(strip, col0, where, u, idx, ss, max_shift, w):
    """Steger's centres (K,) px and where they are usable, by one Newton step from ``u`` on
    the slit image's strips ``strip`` (N, D) float32 (the dots refilled,
    :func:`_refill_strips`; stacked row t holds image columns ``col0[t]`` .. of a ``w`` px
    wide image, clamped to it), for the points ``idx`` (in the order of their stacked rows
    ``where`` (K,), so that the reads follow the memory; the other points keep ``u``, not
    usable; so does a point whose window would reach beyond its strip). The step is clamped
    to 1 px."""
    width = strip.shape[1]
    K = u.size
    rad = int(math.ceil(3.0 * ss)) + 1
    inv2 = 1.0 / (ss * ss)
    inv4 = inv2 * inv2
    # Gaussian weights exp(-(t / ss)^2 / 2) at t = f + k (f = c0 - x, k = -rad .. rad) as
    # exp(-f^2 / 2 ss^2) exp(-k^2 / 2 ss^2) exp(-f / ss^2)^k: two exponentials per point
    gk = np.empty(2 * rad + 1)
    for k in range(-rad, rad + 1):
        gk[k + rad] = math.exp(-0.5 * k * k * inv2)
    m = u.copy()
    ok = np.zeros(K, np.bool_)
    # the points _STEGER_BATCH at a time: the batch's samples, then its sums
    # (:func:`_steger_sums`), the batch's independent sums interleaved
    nb = _STEGER_BATCH
    p = np.empty((2 * rad + 1, nb))
    fb, eb, ek = np.empty(nb), np.empty(nb), np.empty(nb)
    d1, d2 = np.empty(nb), np.empty(nb)
    inside = np.zeros(nb, np.bool_)
    for s0 in range(0, idx.size, nb):
        n = min(nb, idx.size - s0)
        for j in range(n):
            i = idx[s0 + j]
            t = where[i]
            x = min(max(u[i], 0.0), w - 1.0)
            c0 = int(math.floor(x))
            f = c0 - x
            e = math.exp(-f * inv2)
            fb[j] = f
            eb[j] = e
            ek[j] = math.exp((rad - 0.5 * f) * f * inv2)  # the k = -rad factor
            k0 = c0 - rad - col0[t]  # the first sample's column in the strip
            inside[j] = 0 <= k0 and k0 + 2 * rad < width
            k0 = min(max(k0, 0), width - 2 * rad - 1)
            for k in range(2 * rad + 1):
                p[k, j] = float(strip[t, k0 + k])
        _steger_sums(p, fb[:n], eb[:n], ek[:n], gk, d1[:n], d2[:n], inv2, inv4)
        for j in range(n):
            i = idx[s0 + j]
            good = d2[j] < 0
            step = -(d1[j] * inv2) / d2[j] if good else 0.0
            m[i] = u[i] + min(max(step, -1.0), 1.0)
            ok[i] = good and inside[j] and abs(m[i] - u[i]) <= max_shift
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
    sorts it (stable), the sorted keys, and how far each point lies inside its segment beyond
    ``end`` rows from either end (K,)."""
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
    skey = np.empty(K, np.int64)
    for j in range(K):
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
    return key, order, skey, inner


@njit(cache=True)
def _fit_kernel(seg, key, order, skey, inner, m, u, row_ok, R, deg):
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
    # the centres and the rows that take part, in sorted order: the windows read them in a row
    ms = np.empty(K)
    use = np.empty(K, np.bool_)
    for q in range(K):
        ms[q] = m[order[q]]
        use[q] = row_ok[order[q]] and inner[order[q]] >= 0
    for p in range(K):
        i = order[p]
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
        q = p
        while q > 0 and skey[q - 1] >= key[i] - reach:
            q -= 1
        for dv in range(-reach, reach + 1):
            target = key[i] + dv
            while q < K and skey[q] < target:
                q += 1
            if q == K or skey[q] != target:
                continue
            if not use[q]:
                continue
            count += 1
            e = ms[q] - u[i]
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
        srt = idx  # the points of a row come in order of u as from the extraction
        for j in range(idx.size - 1):
            if u[idx[j + 1]] < u[idx[j]]:
                srt = idx[np.argsort(u[idx], kind="mergesort")]
                break
        for j in range(srt.size - 1):
            d = u[srt[j + 1]] - u[srt[j]]
            gap[srt[j]] = min(gap[srt[j]], d)
            gap[srt[j + 1]] = min(gap[srt[j + 1]], d)
    return gap


def compile_kernels() -> None:
    """Compile the refinement's and the row median's Numba kernels now.

    Numba compiles them on first use (about 20 s) and caches the machine code on disk beside
    the package, so only the first refinement after an install pays it;
    :func:`multislit.stripes.compile_kernels` calls this. The refinement is run on small
    uint8, uint16 and float32 images (the strips are read from each pixel type by its own
    machine code).
    """
    img = np.zeros((48, 48), np.uint8)
    img[:, 22:26] = 200
    img[10:12, 30:32] = 120  # a dot beside the stripe
    img[30:32, 26:28] = 255  # and one touching it (its refill)
    v = np.arange(4.0, 44.0)
    for x in (img, img.astype(np.uint16) << 4, img.astype(np.float32) / 255.0):
        refine_centres(x, np.full(len(v), 23.5), v, np.zeros(len(v), np.int64), 4.0, 2.0)
    one = np.zeros(1)  # the curved fit's choice, which a straight stripe never reaches
    _curved_kernel(np.zeros(1, np.intp), np.zeros(1, np.int64), one, one, one, one, 1.0, 1.0, 1)
    row_median_background(img, 3)

"""Re-centre identified stripe points for triangulation (Steger's centre, fitted along v)."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.separation import (
    fill_dots,
    noise_from_difference,
    row_median_background,
    slope_sigma,
    stripe_slope,
    vertical_opening,
)
from multislit.stripes.sizes import FWHM_PER_SIGMA, median_stride, opening_length
from multislit.stripes.validation import SlitExtractionError, as_image, int_at_least, positive_px

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Steger's smoothing sigma in :func:`refine_centres`, in units of the stripe's own sigma.
REFINE_STEGER_SCALE = 1.25


def _steger_at(img: NDArray, u: F64, r: NDArray[np.intp], ss: float) -> tuple[F64, F64]:
    """First and second derivative of the row profile smoothed by a Gaussian of ``ss`` px,
    evaluated at the sub-pixel columns ``u`` of rows ``r`` (both (K,)): (S', S'')."""
    h, w = img.shape
    rad = math.ceil(3.0 * ss) + 1
    c = np.floor(u).astype(np.intp)
    x = np.arange(-rad, rad + 1)
    cols = np.clip(c[:, None] + x[None, :], 0, w - 1)
    p = img[r[:, None], cols].astype(np.float64)
    t = (c - u)[:, None] + x[None, :]  # sample position relative to u
    g = np.exp(-0.5 * (t / ss) ** 2)
    d1 = np.einsum("kn,kn->k", p, t * g) / ss**2
    d2 = np.einsum("kn,kn->k", p, (t * t / ss**4 - 1.0 / ss**2) * g)
    return d1, d2


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
    the dots are refilled by interpolation along the stripe as in the extraction.

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
    return fill_dots(hp, vertical_opening(hp, length), 3.0 * noise, length, slope)


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
    degree: int = 1,
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
    2. Along the stripe: a polynomial in v of ``degree`` (default 1, a line) fitted by least
       squares to the Steger centres of the *same segment* in rows v - R .. v + R
       (R = ``half_rows``), evaluated at v. The fit follows a slanted stripe exactly; for a
       curved one, degree 1 is biased by c R (R + 1) / 3 px (c = d2u/dv2 / 2, ~0.01 px for
       c = 1e-4 px/row^2 and R = 9) and degree 2 is not, at ~1.5x the noise. The window is
       symmetric about v, shrunk near the segment's ends, and never takes rows of another
       segment, so the centre does not cross segment ends or occlusion edges.

    A point keeps its given centre (``ok`` False) where the refinement is not trustworthy: no
    segment (< 0); within ``end_rows`` + R // 2 rows of its segment's end (the rows within
    ``end_rows`` of an end also stay out of the other rows' fits: there the extraction's and
    this dot refill mix the stripe with what lies beyond the end); fewer than ``degree + 2``
    rows in the window; another stripe point in its row within the Steger kernel's reach
    (3 smoothing sigmas + 2.5 stripe sigmas); or a move of more than ``max_shift_px``.

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
    degree : 0, 1 or 2, degree of the along-stripe polynomial; default 1
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
    slit = refine_slit_image(img, sw, ds, 2 * R + 1, 2 * median_stride(sw) + 1)
    r = rows.astype(np.intp)
    m, row_ok = _steger_centres(slit, uu, r, ss, max_shift_px)
    delta, ok = _fit_along_segments(seg, r, m, uu, row_ok, h, R, deg, end)
    # another stripe within the kernel's reach in the same row: its flank biases the centre
    ok &= _row_gaps(uu, r) >= 3.0 * ss + 2.5 * sigma
    ok &= np.abs(delta) <= max_shift_px
    out[ok] = uu[ok] + delta[ok]
    return out, ok


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
    degree: int,
    max_shift_px: float,
    steger_scale: float,
    end_rows: int | None,
) -> tuple[float, float, int, int, int]:
    """The options of :func:`refine_centres` checked, defaults filled in: stripe width, dot
    size, half window R, degree and end rows."""
    sw = positive_px(stripe_width_px, "stripe_width_px")
    if sw is None:
        raise SlitExtractionError("stripe_width_px must be given (a positive number of pixels)")
    ds = positive_px(dot_size_px, "dot_size_px") or sw
    if not math.isfinite(max_shift_px) or max_shift_px <= 0:
        raise SlitExtractionError(f"max_shift_px must be > 0, got {max_shift_px}")
    if not math.isfinite(steger_scale) or steger_scale <= 0:
        raise SlitExtractionError(f"steger_scale must be > 0, got {steger_scale}")
    deg = int_at_least(degree, "degree", 0)
    if deg > 2:
        raise SlitExtractionError(f"degree must be 0, 1 or 2, got {degree}")
    R = refine_half_rows(sw) if half_rows is None else int_at_least(half_rows, "half_rows", 0)
    end = opening_length(ds) if end_rows is None else int_at_least(end_rows, "end_rows", 0)
    return sw, ds, R, deg, end


def _steger_centres(
    slit: F32, u: F64, r: NDArray[np.intp], ss: float, max_shift_px: float
) -> tuple[F64, NDArray[np.bool_]]:
    """Steger's centre of each point in its row, by two Newton steps from ``u`` on the slit
    image smoothed by ``ss`` px: the centres (K,) px and where they are usable (a maximum,
    moved by at most ``max_shift_px``)."""
    w = slit.shape[1]
    m = u.copy()
    for _ in range(2):  # Newton steps
        d1, d2 = _steger_at(slit, np.clip(m, 0, w - 1), r, ss)
        good = d2 < 0
        m = m + np.clip(np.where(good, -d1 / np.where(good, d2, -1.0), 0.0), -1.0, 1.0)
    return m, good & (np.abs(m - u) <= max_shift_px)


def _segment_rows(
    seg: NDArray[np.int64], r: NDArray[np.intp], span: int
) -> tuple[
    NDArray[np.int64], NDArray[np.intp], NDArray[np.int64], NDArray[np.intp], NDArray[np.intp]
]:
    """Points keyed by (segment, row): the key (K,) (-1 without a segment), the order that
    sorts it, the sorted keys, and each point's segment's first and last row (K,)."""
    K = seg.size
    has = seg >= 0
    key = np.where(has, seg * span + r, -1)
    order = np.argsort(key, kind="stable")
    skey = key[order]
    sseg = seg[order]
    first = np.r_[True, sseg[1:] != sseg[:-1]]
    last = np.r_[sseg[1:] != sseg[:-1], True]
    first_i = np.maximum.accumulate(np.where(first, np.arange(K), 0))
    last_i = np.minimum.accumulate(np.where(last, np.arange(K), K)[::-1])[::-1]
    v_first = np.empty(K, np.intp)
    v_last = np.empty(K, np.intp)
    v_first[order] = r[order][first_i]
    v_last[order] = r[order][last_i]
    return key, order, skey, v_first, v_last


def _fit_along_segments(
    seg: NDArray[np.int64],
    r: NDArray[np.intp],
    m: F64,
    u: F64,
    row_ok: NDArray[np.bool_],
    h: int,
    R: int,
    deg: int,
    end: int,
) -> tuple[F64, NDArray[np.bool_]]:
    """Least-squares polynomial of degree ``deg`` in dv through the Steger centres ``m``
    (K,) px of the same segment's rows v - R .. v + R (symmetric window, shrunk at the
    segment's ends, rows within ``end`` of an end left out), relative to each point's ``u``
    (K,) px and evaluated at its row: the shift (K,) px and where the fit is trustworthy."""
    K = seg.size
    has = seg >= 0
    span = h + 2 * R + 2  # > row range + window: keys of two segments never meet
    key, order, skey, v_first, v_last = _segment_rows(seg, r, span)
    # rows near a segment's end mix two stripes (and the dot refill acts across the end):
    # they neither get refined nor take part in other rows' fits
    inner = np.minimum(r - v_first, v_last - r) - end
    reach = np.minimum(inner, R)  # symmetric window half width
    n = deg + 1
    mom = np.zeros((K, 2 * n - 1))  # sums of dv^k, k = 0 .. 2 deg
    rhs = np.zeros((K, n))  # sums of dv^k (m - u), k = 0 .. deg
    count = np.zeros(K, np.int64)
    powers = np.arange(2 * n - 1)
    for dv in range(-R, R + 1):  # loop over the window's rows only
        j = np.minimum(np.searchsorted(skey, key + dv), K - 1)
        nb = order[j]
        found = has & (skey[j] == key + dv) & (abs(dv) <= reach) & row_ok[nb] & (inner[nb] >= 0)
        wt = found.astype(np.float64)
        p = float(dv) ** powers
        mom += wt[:, None] * p[None, :]
        rhs += (wt * (m[nb] - u))[:, None] * p[None, :n]
        count += found
    ok = has & (reach >= R // 2) & (inner >= 0) & (count >= min(deg + 2, 2 * R + 1))
    idx = np.arange(n)
    A = mom[:, idx[:, None] + idx[None, :]]  # (K, n, n) normal equations (Hankel)
    ok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(mom[:, 0], 1.0) ** n
    A[~ok] = np.eye(n)
    delta = np.linalg.solve(A, np.where(ok[:, None], rhs, 0.0)[..., None])[:, 0, 0]
    return delta, ok


def _row_gaps(u: F64, r: NDArray[np.intp]) -> F64:
    """(K,) px: distance from each point to the nearest other point of its row (inf if none)."""
    K = u.size
    o = np.lexsort((u, r))
    du = np.where(r[o][1:] == r[o][:-1], np.diff(u[o]), np.inf)
    gap = np.full(K, np.inf)
    gap[o[:-1]] = du
    gap[o[1:]] = np.minimum(gap[o[1:]], du)
    return gap

"""Sub-pixel stripe centres in every row of a slit image (paper, section 4.1)."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import trailing_zeros
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.chains import lex_order
from multislit.stripes.response import lean_slopes, ridge_response, slopes_at, wide_centres
from multislit.stripes.separation import mask_runs, quantisation_step
from multislit.stripes.sizes import FWHM_PER_SIGMA, MIN_RIDGE_CONTRAST, ridge_contrast
from multislit.stripes.validation import (
    SlitExtractionError,
    as_image,
    positive_px,
    smoothing_taps,
)

F64 = NDArray[np.float64]

#: Sub-pixel centre methods of :func:`find_stripe_centres`; the first is the default.
CENTRE_METHODS = ("gaussian", "parabolic", "centroid", "steger")
#: Default detection threshold in units of the highpass noise sigma. The slit image's background
#: is an opening of clipped noise, which almost never exceeds ~1.5 sigma; stripe pixels carry
#: several times more (shot) noise than the background, so the threshold is set well above it.
DEFAULT_K_SIGMA = 8.0
#: Default number of rows (binomial weights) averaged along the stripe for the sub-pixel fit.
DEFAULT_V_SMOOTH = 5


class StripeCentres(NamedTuple):
    """Result of :func:`find_stripe_centres`: K centre points, sorted by (v, u).

    Attributes
    ----------
    u : (K,) float64, sub-pixel column of the stripe centre (px)
    v : (K,) float64, row (px, integer valued)
    peak : (K,) float64, slit-image value at the peak pixel (intensity units); for saturated
        stripes the largest value of the flat top
    width : (K,) float64, stripe FWHM along the row (px) from the Gaussian fit; NaN where the
        fit is not possible (non-positive neighbour)
    """

    u: F64
    v: F64
    peak: F64
    width: F64


def estimate_noise(image: ArrayLike) -> float:
    """Robust noise sigma of an image (intensity units) from horizontal first differences.

    sigma = 1.4826 * MAD(diff) / sqrt(2); stripes and dots are a minority of the pixels. For a
    raw or highpass image; on a slit image (mostly exact zeros) it returns the quantisation /
    residual level only (step / sqrt(12), :func:`~multislit.stripes.separation.
    quantisation_step`: 0.29 for 8-bit data, never 0), so prefer the highpass noise that
    :func:`extract_slits` uses.
    """
    img = as_image(image)
    d = np.diff(img[::2].astype(np.float32), axis=1)
    med = np.median(d)
    sigma = 1.4826 * float(np.median(np.abs(d - med))) / math.sqrt(2.0)
    return max(sigma, quantisation_step(img) / math.sqrt(12.0))  # at least quantisation noise


@njit(cache=True)
def _gather_kernel(img, r, c, offsets, wts):
    """:func:`_gather`: (K, len(offsets)) float64, the binomial rows ``wts`` accumulated in
    order (as ``out += wts[i] * img[...]``)."""
    h, w = img.shape
    half = wts.size // 2
    out = np.zeros((r.size, offsets.size), np.float64)
    for k in range(r.size):
        for j in range(offsets.size):
            col = min(max(c[k] + offsets[j], 0), w - 1)
            acc = 0.0
            for i in range(wts.size):
                row = min(max(r[k] + i - half, 0), h - 1)
                acc += wts[i] * float(img[row, col])
            out[k, j] = acc
    return out


def _binomial_weights(taps: int) -> F64:
    """(taps,) float64, the binomial weights of ``taps`` rows (at least 1), summing to 1."""
    taps = max(int(taps), 1)
    if taps == 1:
        return np.ones(1)
    return np.array([math.comb(taps - 1, i) for i in range(taps)], np.float64) / 2.0 ** (taps - 1)


def _gather(img: NDArray, r: NDArray, c: NDArray, offsets: NDArray, taps: int = 1) -> F64:
    """Values img[r, c + offsets] as (K, len(offsets)) float64, averaged over ``taps`` rows.

    With ``taps`` > 1 (odd), each value is a binomial-weighted average over rows r - taps // 2
    .. r + taps // 2 (clamped to the image): smoothing along the stripe, which for a straight,
    tilted stripe keeps the row's profile symmetric about its centre and divides the noise.
    Columns are clamped to the image too. One compiled pass.
    """
    return _gather_kernel(
        img,
        np.ascontiguousarray(r, np.intp),
        np.ascontiguousarray(c, np.intp),
        np.ascontiguousarray(offsets, np.intp),
        _binomial_weights(taps),
    )


@njit(cache=True)
def _peak_samples(img, r, c, wts, lean):
    """The three samples of :func:`find_stripe_centres`'s sub-pixel fit at the peaks (``r``,
    ``c``) (K,) intp: the values of :func:`_gather` (``wts`` the binomial rows) at c - 2 ..
    c + 2, the peak moved to the largest of those at c - 1 .. c + 1 (the first of equal
    ones, as np.argmax). Where ``lean`` (K,) float64 (px per row; (0,) for none) is not 0,
    row r + i is read along the stripe, shifted by ``lean * i`` px (linear interpolation
    along the row, columns clamped). Returns the moved columns (K,) intp and the samples left
    of, at and right of them (K,) float64 each; one pass, no (K, 5) array."""
    h, w = img.shape
    half = wts.size // 2
    n = r.size
    cm = np.empty(n, np.intp)
    left = np.empty(n, np.float64)
    mid = np.empty(n, np.float64)
    right = np.empty(n, np.float64)
    rows = np.empty(wts.size, np.intp)
    v = np.empty(5, np.float64)
    for k in range(n):
        for i in range(wts.size):
            rows[i] = min(max(r[k] + i - half, 0), h - 1)
        t = lean[k] if lean.size else 0.0
        for j in range(5):
            acc = 0.0
            if t == 0.0:
                col = min(max(c[k] + j - 2, 0), w - 1)
                for i in range(wts.size):
                    acc += wts[i] * float(img[rows[i], col])
            else:
                for i in range(wts.size):
                    x = min(max(c[k] + j - 2 + t * (i - half), 0.0), w - 1.0)
                    x0 = min(int(x), w - 2) if w > 1 else 0
                    f = x - x0
                    a = float(img[rows[i], x0])
                    b = float(img[rows[i], min(x0 + 1, w - 1)])
                    acc += wts[i] * (a + (b - a) * f)
            v[j] = acc
        j = 1
        if v[2] > v[j]:
            j = 2
        if v[3] > v[j]:
            j = 3
        cm[k] = c[k] + j - 2
        left[k] = v[j - 1]
        mid[k] = v[j]
        right[k] = v[j + 1]
    return cm, left, mid, right


@njit(cache=True)
def _row_maxima_kernel(s, thr, strict, near, use_near):
    """:func:`_row_maxima` with the threshold ``thr`` in the image's type: a peak exceeds it
    (``strict``) or reaches it. One compiled pass: each row's tests into a byte per pixel
    (no branches, in the image's own lanes: the loop vectorises), read 8 bytes at a time."""
    h, w = s.shape
    nw = (w + 7) // 8
    flags = np.zeros(8 * nw, np.uint8)
    words = flags.view(np.uint64)
    # two maxima are never side by side: at most w // 2 + 1 a row (pages never written are
    # never touched)
    rr = np.empty(h * (w // 2 + 1), np.intp)
    cc = np.empty(rr.size, np.intp)
    k = 0
    zero = np.uint64(0)
    byte = np.uint64(0xFF)
    fl = flags[1 : max(w - 1, 1)]  # 1-D views from 0: the loop vectorises
    for r in range(h):
        row = s[r]
        left, mid, right = row[: max(w - 2, 0)], row[1 : max(w - 1, 1)], row[2:]
        if strict:
            for c in range(w - 2):
                m = mid[c]
                fl[c] = (m > thr) & (m > left[c]) & (m >= right[c])
        else:
            for c in range(w - 2):
                m = mid[c]
                fl[c] = (m >= thr) & (m > left[c]) & (m >= right[c])
        for blk in range(nw):
            x = words[blk]
            while x != zero:
                bit = trailing_zeros(x) & 56
                x &= ~(byte << np.uint64(bit))
                c = blk * 8 + bit // 8
                if use_near and near[r, c]:
                    continue
                rr[k] = r
                cc[k] = c
                k += 1
    return rr[:k].copy(), cc[:k].copy()


def _row_maxima(
    s: NDArray, thr: float, near: NDArray[np.bool_], use_near: bool
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Rows and columns (K,) of the pixels of ``s`` (H, W) greater than their left and not
    less than their right neighbour and than ``thr`` (float64, compared exactly), outside
    ``near`` (H, W) where ``use_near``; row-major. The threshold is compared in the image's
    type (the same pixels): an integer pixel exceeds ``thr`` where it reaches floor(thr) + 1,
    a float32 one where it exceeds the largest float32 <= ``thr``."""
    empty = np.empty(0, np.intp)
    if math.isnan(thr):
        return empty, empty.copy()
    if np.issubdtype(s.dtype, np.integer):
        info = np.iinfo(s.dtype)
        first = math.floor(thr) + 1 if math.isfinite(thr) else (info.min if thr < 0 else None)
        if first is None or first > info.max:
            return empty, empty.copy()
        return _row_maxima_kernel(s, s.dtype.type(max(first, info.min)), False, near, use_near)
    if s.dtype == np.float32:
        with np.errstate(over="ignore"):
            t = np.float32(thr)
        if float(t) > thr:
            t = np.nextafter(t, np.float32(-np.inf))
        return _row_maxima_kernel(s, t, True, near, use_near)
    return _row_maxima_kernel(s, thr, True, near, use_near)


def row_maxima(s: NDArray, threshold: float) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Rows and columns (K,) intp, row-major, of the pixels of ``s`` (H, W) greater than their
    left and not less than their right neighbour that exceed ``threshold`` (intensity units,
    compared as :func:`find_stripe_centres` compares it: floored for integer images)."""
    if s.shape[1] < 3:
        e = np.empty(0, np.intp)
        return e, e.copy()
    return _row_maxima(s, _exact_threshold(s, threshold), np.zeros((1, 1), bool), False)


@njit(cache=True)
def _log_arguments(a, b, c):
    """The samples of :func:`_three_point` whose logs it takes: (K,) float64 copies of ``a``,
    ``b``, ``c`` with 1 where any of the three is <= 0, and the mask (K,) bool where all three
    are > 0."""
    n = a.size
    ok = np.empty(n, np.bool_)
    xa = np.empty(n)
    xb = np.empty(n)
    xc = np.empty(n)
    for k in range(n):
        good = (a[k] > 0) & (c[k] > 0) & (b[k] > 0)
        ok[k] = good
        xa[k] = a[k] if good else 1.0
        xb[k] = b[k] if good else 1.0
        xc[k] = c[k] if good else 1.0
    return xa, xb, xc, ok


@njit(cache=True)
def _three_point_fit(a, b, c, la, lb, lc, ok, gaussian):
    """:func:`_three_point` from the samples ``a``, ``b``, ``c`` (K,) and the logs ``la``,
    ``lb``, ``lc`` (K,) of :func:`_log_arguments`' values (``ok`` its mask): the same
    operations, in the same order, as the array formulation, one point at a time."""
    n = a.size
    delta = np.empty(n)
    width = np.empty(n)
    for k in range(n):
        den_g = la[k] - 2 * lb[k] + lc[k]
        good = ok[k] and den_g < 0
        width[k] = FWHM_PER_SIGMA * np.sqrt(-1.0 / den_g) if good else np.nan
        den_p = a[k] - 2 * b[k] + c[k]
        d = 0.5 * (a[k] - c[k]) / den_p if den_p < 0 else 0.0
        if gaussian and good:  # else the parabola (where the log is undefined)
            d = 0.5 * (la[k] - lc[k]) / den_g
        delta[k] = min(max(d, -0.5), 0.5)
    return delta, width


def _three_point(a: F64, b: F64, c: F64, method: str) -> tuple[F64, F64]:
    """Sub-pixel offset and FWHM from three samples at -1, 0, +1 (b the maximum): a parabola
    through their logs (``method`` "gaussian", where all three are > 0 and the logs curve
    down) or through the samples (elsewhere, and for "parabolic"); the offset clipped to
    +-0.5, the FWHM NaN where there is no Gaussian. The logs by NumPy, the rest compiled."""
    la, lb, lc, ok = _log_arguments(a, b, c)
    for x in (la, lb, lc):
        np.log(x, out=x)
    return _three_point_fit(a, b, c, la, lb, lc, ok, method == "gaussian")


def _window_offset(
    img: NDArray, r: NDArray, c: NDArray, method: str, fwhm: float, taps: int
) -> tuple[F64, F64]:
    """Sub-pixel offset by centre of mass or Steger's derivative ratio over a window."""
    sigma = fwhm / FWHM_PER_SIGMA
    if method == "centroid":
        # centre of mass over +-1.5 sigma (~ the part above 1/3 of the peak), background ~ 0
        rad = max(1, round(1.5 * sigma))
        x = np.arange(-rad, rad + 1)
        p = np.maximum(_gather(img, r, c, x, taps), 0.0)
        s = p.sum(1)
        delta = np.where(s > 0, (p @ x) / np.where(s > 0, s, 1.0), 0.0)
    else:  # steger: zero of the first derivative of the Gaussian-smoothed profile
        # smoothing sigma_s = w / sqrt(3) with w the half-width ~ sigma * sqrt(3) (Steger 1998)
        ss = max(sigma, 0.7)
        rad = math.ceil(3 * ss)
        x = np.arange(-rad, rad + 1)
        g = np.exp(-0.5 * (x / ss) ** 2)
        k1 = -x / ss**2 * g
        k2 = (x * x / ss**4 - 1 / ss**2) * g
        p = _gather(img, r, c, x, taps)
        g1, g2 = -(p @ k1), p @ k2  # correlation with g' = minus the convolution
        delta = np.where(g2 < 0, -g1 / np.where(g2 < 0, g2, -1.0), 0.0)
    return np.clip(delta, -1.0, 1.0), np.full(r.shape, np.nan)


def _saturated_centres(
    slit: NDArray, sat: NDArray[np.bool_]
) -> tuple[F64, F64, F64, F64, F64, NDArray[np.bool_]]:
    """Centres of saturated runs: weighted log-parabola fit to 2 unsaturated pixels per flank.

    Returns u, v, peak, width, reach (px from the centre to the run's farther end) of every
    run and the (H, W) mask of pixels within 1 px of a run (no ordinary peak is taken there).
    """
    h, w = sat.shape
    if not sat.any():  # the usual case: nothing saturates
        e = np.empty(0)
        return e, e, e, e, e, np.zeros((h, w), bool)
    m = np.zeros((h, w + 2), np.int8)
    m[:, 1:-1] = sat
    d = np.diff(m, axis=1)
    rs, c0, c1 = mask_runs(d)
    c1 = c1 - 1
    near = cv2.dilate(sat.view(np.uint8), np.ones((1, 3), np.uint8)).view(bool)
    if rs.size == 0:
        e = np.empty(0)
        return e, e, e, e, e, near
    mid = 0.5 * (c0 + c1)
    x = np.stack([c0 - 2, c0 - 1, c1 + 1, c1 + 2], axis=1).astype(np.float64)
    inside = (x >= 0) & (x <= w - 1)
    xi = np.clip(x, 0, w - 1).astype(np.intp)
    y = slit[rs[:, None], xi].astype(np.float64)
    ok = inside & (y > 0) & ~sat[rs[:, None], xi]
    wt = np.where(ok, y * y, 0.0)  # var(log y) ~ sigma^2 / y^2
    ly = np.log(np.where(ok, y, 1.0))
    xr = x - mid[:, None]
    basis = np.stack([np.ones_like(xr), xr, xr * xr], axis=2)  # (K, 4, 3)
    ata = np.einsum("kn,kni,knj->kij", wt, basis, basis)
    atb = np.einsum("kn,kni,kn->ki", wt, basis, ly)
    usable = (ok[:, :2].sum(1) >= 1) & (ok[:, 2:].sum(1) >= 1) & (ok.sum(1) >= 3)
    ata[~usable] = np.eye(3)
    coef = np.linalg.solve(ata, atb[..., None])[..., 0]
    cc = coef[:, 2]
    good = usable & (cc < 0)
    off = np.where(good, -coef[:, 1] / (2 * np.where(good, cc, -1.0)), 0.0)
    half = 0.5 * (c1 - c0) + 0.5
    good &= np.abs(off) <= half  # the centre must lie on the flat top
    u = mid + np.where(good, off, 0.0)  # else the run midpoint
    width = np.where(good, FWHM_PER_SIGMA * np.sqrt(-0.5 / np.where(good, cc, -1.0)), np.nan)
    # peak: the highest slit value on the run (runs are short: gather up to the longest)
    offs = np.arange(int((c1 - c0).max()) + 1)
    cols = np.minimum(c0[:, None] + offs[None, :], c1[:, None])
    peak = slit[rs[:, None], cols].astype(np.float64).max(1)
    reach = np.maximum(u - c0, c1 - u)  # from the centre to the farther end of the run
    return u, rs.astype(np.float64), peak, width, reach, near


def find_stripe_centres(
    slit_image: ArrayLike,
    noise_sigma: float | None = None,
    method: str = "gaussian",
    *,
    k_sigma: float = DEFAULT_K_SIGMA,
    saturated: ArrayLike | None = None,
    stripe_width_px: float | None = None,
    v_smooth: int = DEFAULT_V_SMOOTH,
    reject_texture: bool = False,
) -> StripeCentres:
    """Sub-pixel centre of every stripe in every row of a slit image.

    A peak is a pixel greater than its left and not less than its right neighbour (one pixel
    per 2-pixel tie) and above ``k_sigma * noise_sigma``. Its sub-pixel column is refined by
    ``method``:

    - ``"gaussian"`` (default): parabola through the logs of the 3 samples (exact for a
      Gaussian profile; falls back to the parabola where a neighbour is <= 0);
    - ``"parabolic"``: parabola through the 3 samples;
    - ``"centroid"``: centre of mass over +-1.5 sigma of the stripe;
    - ``"steger"``: zero of the derivative of the Gaussian-smoothed row profile (Steger).

    Runs of ``saturated`` pixels give one centre each, from a weighted Gaussian fit to the two
    unsaturated pixels on each flank (the run midpoint if the fit fails). Centres that do not
    look like a stripe (:func:`stripe_like`: edges, plateaus) are dropped with
    ``reject_texture``, and so are centres a window method moves off the image.

    Parameters
    ----------
    slit_image : (H, W) slit image (e.g. :attr:`Separation.slits`), background ~ 0
    noise_sigma : noise sigma of the highpass image (intensity units); default
        :func:`estimate_noise` of ``slit_image`` (prefer passing the highpass noise)
    method : one of :data:`CENTRE_METHODS`
    k_sigma : detection threshold in noise sigmas
    saturated : (H, W) bool mask of saturated stripe pixels (:attr:`Separation.saturated`)
    stripe_width_px : stripe FWHM (px) for ``centroid``/``steger`` and the stripe test;
        default the median Gaussian-fit width of the peaks
    v_smooth : rows (odd) averaged along the stripe for the sub-pixel fit; default
        :data:`DEFAULT_V_SMOOTH`
    reject_texture : drop the centres :func:`stripe_like` rejects (edges and plateaus, for
        photos; it also drops ~0.25 % of the linked centres of the simulated rig's stripes);
        default False

    Returns
    -------
    StripeCentres
        (u, v, peak, width), each (K,) float64, sorted by (v, u).
    """
    s = as_image(slit_image, name="slit_image")
    if method not in CENTRE_METHODS:
        raise SlitExtractionError(f"method must be one of {CENTRE_METHODS}, got {method!r}")
    if noise_sigma is None:
        noise_sigma = estimate_noise(s)
    noise_sigma = float(noise_sigma)
    if not math.isfinite(noise_sigma) or noise_sigma < 0:
        raise SlitExtractionError(f"noise_sigma must be >= 0, got {noise_sigma}")
    if not math.isfinite(k_sigma) or k_sigma < 0:
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma}")
    sw = positive_px(stripe_width_px, "stripe_width_px")
    if saturated is None:
        sat = np.zeros(s.shape, bool)
    else:
        sat = np.asarray(saturated, dtype=bool)
        if sat.shape != s.shape:
            raise SlitExtractionError(
                f"saturated must have the slit image's shape {s.shape}, got {sat.shape}"
            )
    return find_centres_validated(
        s, noise_sigma * k_sigma, method, sat, sw, smoothing_taps(v_smooth), bool(reject_texture)
    )


def find_centres_validated(
    s: NDArray,
    threshold: float,
    method: str,
    sat: NDArray[np.bool_],
    sw: float | None,
    taps: int = 1,
    reject_texture: bool = False,
) -> StripeCentres:
    """:func:`find_stripe_centres` on validated arguments; ``threshold`` in intensity units."""
    return _centres(s, threshold, method, sat, sw, taps, reject_texture, None)[0]


class RidgeCentres(NamedTuple):
    """Result of :func:`find_ridge_centres_validated`.

    Attributes
    ----------
    centres : StripeCentres, K points sorted by (v, u)
    strong : (K,) bool, the slit image's largest pixel within 1 px in the row exceeds the
        single pixel's threshold (else the ridge response alone found the centre: weak)
    slope : (K,) float64, px per row, the stripes' lean du/dv at the centre
        (:func:`~multislit.stripes.response.lean_slopes`; 0 where they stand upright)
    """

    centres: StripeCentres
    strong: NDArray[np.bool_]
    slope: F64


#: A centre the ridge response alone finds (:func:`find_ridge_centres_validated`) is kept where
#: the slit image at its peak, averaged over the fit's rows, reaches this fraction of the
#: response there: on a stripe the two are about equal (both the stripe's amplitude); a few
#: rows past a stripe's end, where the response's smoothing along the stripe still reaches,
#: the slit image has fallen to nothing.
RIDGE_SUPPORT = 0.5


def find_ridge_centres_validated(
    s: NDArray,
    threshold: float,
    ridge_threshold: float,
    method: str,
    sat: NDArray[np.bool_],
    sw: float,
    taps: int = 1,
    follow: bool = True,
    image: NDArray | None = None,
    levels: tuple[NDArray, NDArray, NDArray] | None = None,
) -> RidgeCentres:
    """Stripe centres where the ridge response stands out, which of them a single pixel
    shows too, and the stripes' lean at them.

    The peaks are the row maxima of the ridge response (:func:`~multislit.stripes.response.
    ridge_response`: a matched filter across the stripe, integrated along it) above
    ``ridge_threshold``; each is centred to sub-pixel on the slit image as
    :func:`find_stripe_centres` centres its peaks (the largest smoothed sample within 1 px,
    ``method``'s 3-point fit). A centre is *strong* where the slit image's largest pixel
    within 1 px of it in its row exceeds ``threshold`` (what :func:`find_stripe_centres`
    takes; both thresholds scaled by the noise at its level, with ``levels``), *weak*
    otherwise; a weak centre is kept where its smoothed peak reaches
    :data:`RIDGE_SUPPORT` times the response at it. Saturated runs are centred as in
    :func:`find_stripe_centres` (strong). The response integrates along the stripes' lean
    where they lean (:func:`~multislit.stripes.response.lean_slopes`), and each centre
    carries that lean for the linking (:func:`~multislit.stripes.chains.link_segments`'
    ``slope``); the sub-pixel fit averages the rows along it too. On a stripe much wider than
    ``sw`` (where the surface grazes the projector) the centre is the response's at twice the
    width (:func:`~multislit.stripes.response.wide_centres`): the 3-point fit would find the
    speckle grains on it.

    Parameters
    ----------
    s : (H, W) slit image, background ~ 0
    threshold : float, intensity units, the single pixel's detection threshold
    ridge_threshold : float, intensity units, the response's detection threshold
    method : one of :data:`CENTRE_METHODS`
    sat : (H, W) bool, saturated stripe pixels
    sw : float, px, the stripes' FWHM (the response's scale)
    taps : int, rows (odd) averaged along the stripe for the sub-pixel fit
    follow : bool, integrate and fit along the stripes' lean where they lean (default), else
        along the columns everywhere (all slopes 0)
    image : (H, W) the image the slit image was made from, or None: a centre (not on a wide
        stripe) whose pixels do not exceed ``threshold`` is kept only where it stands out of
        both sides alike in it (:func:`edge_contrast`)
    levels : (background (H, W), level (B,), scale (B,)) or None: the noise grows with the
        background's level (:func:`~multislit.stripes.separation.noise_by_level`); both
        thresholds are scaled at each peak by ``scale`` at its background's level (linear
        between the ``level``s): a peak on a dark surface, where the noise is less than the
        frame's, is found and is strong at a lower level. None: the thresholds hold
        everywhere.

    Returns
    -------
    RidgeCentres
    """
    return RidgeCentres(
        *_centres(
            s, threshold, method, sat, sw, taps, False, ridge_threshold, follow, image, levels
        )
    )


def _exact_threshold(s: NDArray, threshold: float | F64) -> float | F64:
    """``threshold`` (a number, or an array of them) as the image's pixels are compared with
    it: floored for integer images, rounded to float32 for float32 ones."""
    t = np.asarray(threshold, np.float64)
    if np.issubdtype(s.dtype, np.integer):
        out = np.floor(t)
    else:
        with np.errstate(over="ignore"):
            out = t.astype(np.float32).astype(np.float64)
    return out if out.ndim else float(out)


def _centres(
    s: NDArray,
    threshold: float,
    method: str,
    sat: NDArray[np.bool_],
    sw: float | None,
    taps: int,
    reject_texture: bool,
    ridge_threshold: float | None,
    follow: bool = True,
    image: NDArray | None = None,
    levels: tuple[NDArray, NDArray, NDArray] | None = None,
) -> tuple[StripeCentres, NDArray[np.bool_], F64]:
    """The centres of :func:`find_centres_validated` (``ridge_threshold`` None: the peaks are
    the slit image's row maxima above ``threshold``, all strong, upright) or of
    :func:`find_ridge_centres_validated`, which are strong, and the lean at them."""
    h, w = s.shape
    if w < 3:
        e = np.empty(0)
        return StripeCentres(e, e, e, e), np.zeros(0, bool), e.copy()
    thr_exact = _exact_threshold(s, threshold)
    su, sv, speak, swidth, sreach, near = _saturated_centres(s, sat)
    wts = _binomial_weights(taps)
    if ridge_threshold is None:
        r, c = _row_maxima(s, thr_exact, near, sv.size > 0)
        # smoothed samples at c-2 .. c+2; re-centre on the smoothed maximum among c-1 .. c+1
        c, a, b, cc = _peak_samples(s, r, c, wts, np.zeros(0))
        strong = np.ones(r.size, bool)
        lean = np.zeros(r.size)
    else:
        cells = lean_slopes(s, float(sw)) if follow else None
        resp = ridge_response(s, float(sw), cells)
        if levels is None:
            r, c0 = _row_maxima(resp, float(ridge_threshold), near, sv.size > 0)
        else:  # the peaks above the lowest level's threshold, then each above its own
            bg, lv, sc = levels
            low = float(ridge_threshold) * float(np.min(sc))
            r, c0 = _row_maxima(resp, low, near, sv.size > 0)
            scale = np.interp(bg[r, c0], lv, sc)
            keep = resp[r, c0] > float(ridge_threshold) * scale
            r, c0, scale = r[keep], c0[keep], scale[keep]
        lean = slopes_at(cells, r, c0) if follow else np.zeros(r.size)
        c, a, b, cc = _peak_samples(s, r, c0, wts, lean)
        # strong: above its level's threshold; bright: above the frame's (a dim peak, strong
        # where its level is quiet, is still checked for a shadow's rim below)
        bright = _pixel_above(s, r, c, np.full(r.size, thr_exact))
        strong = (
            bright
            if levels is None
            else _pixel_above(s, r, c, _exact_threshold(s, threshold * scale))
        )
        keep = strong | (b >= RIDGE_SUPPORT * resp[r, c0])
        r, c, a, b, cc, strong = r[keep], c[keep], a[keep], b[keep], cc[keep], strong[keep]
        lean, c0, bright = lean[keep], c0[keep], bright[keep]
        wide, u_wide = wide_centres(s, float(sw), r, c0, resp[r, c0].astype(np.float64))
        if image is not None:  # a wide stripe's sides lie beyond the nominal width's reach
            dim = np.flatnonzero(~bright & ~wide)
            keep = np.ones(r.size, bool)
            keep[dim] = edge_contrast(image, r[dim], c[dim], float(sw)) >= EDGE_CONTRAST
            r, c, a, b, cc, strong = r[keep], c[keep], a[keep], b[keep], cc[keep], strong[keep]
            lean, wide, u_wide = lean[keep], wide[keep], u_wide[keep]
    delta, width = _three_point(a, b, cc, "gaussian" if method == "gaussian" else "parabolic")
    known = width[np.isfinite(width)]
    fwhm = sw if sw is not None else float(np.median(known)) if known.size else 3.0
    if not math.isfinite(fwhm):
        fwhm = 3.0
    if method in ("centroid", "steger"):
        delta, _ = _window_offset(s, r, c, method, fwhm, taps)
    u = c + delta
    if ridge_threshold is not None and wide.any():
        u = np.where(wide, u_wide, u)
    v = r.astype(np.float64)
    reach = np.zeros(u.shape)
    if sv.size:
        keep = speak > threshold
        u = np.concatenate([u, su[keep]])
        v = np.concatenate([v, sv[keep]])
        b = np.concatenate([b, speak[keep]])
        width = np.concatenate([width, swidth[keep]])
        reach = np.concatenate([reach, sreach[keep]])
        strong = np.concatenate([strong, np.ones(int(keep.sum()), bool)])
        lean = np.concatenate([lean, np.zeros(int(keep.sum()))])
        order = lex_order(u, v)
        u, v, b, width, reach = u[order], v[order], b[order], width[order], reach[order]
        strong, lean = strong[order], lean[order]
    # one stripe, one centre: a dot or speckle on a stripe's flank can make a second local
    # maximum a px or two away; of two centres closer than half a stripe width keep the stronger
    min_sep = 0.5 * (sw if sw is not None and math.isfinite(sw) else 3.0)
    for _ in range(3):
        close = (v[1:] == v[:-1]) & (u[1:] - u[:-1] < min_sep)
        if not close.any():
            break
        i = np.flatnonzero(close)
        weaker = np.where(b[i] < b[i + 1], i, i + 1)
        keep = np.ones(len(u), bool)
        keep[weaker] = False
        u, v, b, width, reach = u[keep], v[keep], b[keep], width[keep], reach[keep]
        strong, lean = strong[keep], lean[keep]
    # a centre lies in the image (a window method can move it off the border pixel)
    keep = (u >= -0.5) & (u <= w - 0.5)
    if reject_texture:
        keep &= stripe_like(s, u, v, fwhm, reach)
    return StripeCentres(u[keep], v[keep], b[keep], width[keep]), strong[keep], lean[keep]


#: A weak centre is kept where :func:`edge_contrast` reaches this: a stripe stands out of both
#: sides alike; the bright rim of a shadow's or an object's edge (a few grey levels above the
#: lit side, which the row background takes away with the step) stands out of the dark side by the
#: step as well.
EDGE_CONTRAST = 0.7


def edge_contrast(
    image: NDArray, r: NDArray[np.intp], c: NDArray[np.intp], stripe_width_px: float
) -> F64:
    """(K,) float64: how alike a peak at (``r``, ``c``) (K,) of ``image`` (H, W) stands out of
    its two sides: (p - max(L, R)) / (p - min(L, R)), with p the image averaged over the three
    rows about the peak at its column and L, R the lowest of those averages 1 to 2 stripe
    widths to either side (a side outside the image taking the other's value); 1 on a stripe
    on an even background, 0 on a step. 0 where p is no higher than the sides."""
    if r.size == 0:
        return np.zeros(0)
    d0 = max(1, math.ceil(stripe_width_px))
    d1 = max(d0 + 1, math.ceil(2.0 * stripe_width_px))
    return _edge_contrast(image, r, c, d0, d1)


@njit(cache=True, inline="always")
def _column_mean(img, r0, r1, j):
    """The mean of ``img``'s column ``j`` over rows ``r0`` .. ``r1`` - 1."""
    acc = 0.0
    for i in range(r0, r1):
        acc += float(img[i, j])
    return acc / (r1 - r0)


@njit(cache=True)
def _edge_contrast(img, r, c, d0, d1):
    """:func:`edge_contrast` with the sides ``d0`` .. ``d1`` px from the peak."""
    h, w = img.shape
    out = np.zeros(r.size)
    for k in range(r.size):
        r0 = max(r[k] - 1, 0)
        r1 = min(r[k] + 2, h)
        p = _column_mean(img, r0, r1, c[k])
        sides = np.full(2, np.inf)
        for si, sign in ((0, -1), (1, 1)):
            for o in range(d0, d1 + 1):
                j = c[k] + sign * o
                if 0 <= j < w:
                    sides[si] = min(sides[si], _column_mean(img, r0, r1, j))
        if sides[0] == np.inf:
            sides[0] = sides[1]
        if sides[1] == np.inf:
            sides[1] = sides[0]
        lo = min(sides[0], sides[1])
        hi = max(sides[0], sides[1])
        if p > hi and hi != np.inf:
            out[k] = (p - hi) / (p - lo)
    return out


@njit(cache=True)
def _pixel_above(s, r, c, thr):
    """(K,) bool: the largest of ``s``'s (H, W) pixels c - 1 .. c + 1 (within the image) in
    row r exceeds ``thr[k]`` ((K,) float64, compared as the image's pixels are:
    :func:`_exact_threshold`), for the points ``r``, ``c`` (K,) intp."""
    w = s.shape[1]
    out = np.empty(r.size, np.bool_)
    for k in range(r.size):
        row = s[r[k]]
        best = -np.inf
        for j in range(max(c[k] - 1, 0), min(c[k] + 2, w)):
            best = max(best, float(row[j]))
        out[k] = best > thr[k]
    return out


#: Largest angle (deg) between a stripe and the image's vertical that :func:`along_slits`
#: keeps: the slits run roughly along v, and linking follows at most 1.5 px per row (56 deg).
MAX_LEAN_DEG = 45.0


def along_slits(slit_image: NDArray, u: F64, v: F64, stripe_width_px: float) -> NDArray[np.bool_]:
    """Which centres lie on structure that runs roughly along the slits (image v).

    The structure tensor of the slit image, integrated over a Gaussian of one stripe width,
    gives the local direction of the intensity gradient: across a stripe it is along the row
    (u); along a horizontal edge or at a checker corner's bright bits it is along v. A centre
    is kept where the structure leans at most ``MAX_LEAN_DEG`` from v (J_vv <= tan^2 J_uu).

    Parameters
    ----------
    slit_image : (H, W) slit image
    u, v : (K,) centres (px; v integer rows)
    stripe_width_px : stripe FWHM (px), the integration scale

    Returns
    -------
    (K,) bool
    """
    if u.size == 0:
        return np.ones(0, bool)
    # Sobel straight from integer data: its sums are integers below 2^24, exact in float32
    ok = slit_image.dtype in (np.uint8, np.uint16, np.float32)
    x = slit_image if ok else slit_image.astype(np.float32)
    gu = cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=3)
    r = np.rint(v).astype(np.intp)
    c = np.clip(np.rint(u).astype(np.intp), 0, x.shape[1] - 1)
    juu = cv2.GaussianBlur(cv2.multiply(gu, gu, dst=gu), (0, 0), stripe_width_px)[r, c]
    jvv = cv2.GaussianBlur(cv2.multiply(gv, gv, dst=gv), (0, 0), stripe_width_px)[r, c]
    return jvv <= math.tan(math.radians(MAX_LEAN_DEG)) ** 2 * juu


#: The texture a centre must stand out of is read beside it: in a ring from
#: ``TEXTURE_INNER_WIDTHS`` to ``TEXTURE_OUTER_WIDTHS`` stripe widths to either side of it,
#: ``TEXTURE_HALF_HEIGHT_WIDTHS`` stripe widths above and below (not on the line itself,
#: whose own bends and brightness steps along a checkerboard would count as texture).
TEXTURE_INNER_WIDTHS = 1.5
TEXTURE_OUTER_WIDTHS = 4.0
TEXTURE_HALF_HEIGHT_WIDTHS = 3.0
#: A centre is kept in the photo mode where its peak reaches ``TEXTURE_FRACTION * k_sigma``
#: times :func:`texture_sigma` (the ring's highest local level, an envelope rather than a
#: typical sigma: a fraction of the detection threshold in sigmas).
TEXTURE_FRACTION = 0.32


def texture_sigma(slit_image: NDArray, stripe_width_px: float) -> NDArray[np.float32]:
    """(H, W) float32, the level of texture beside each pixel of a slit image (intensity
    units, as a sigma).

    Stripes run along v, so the difference of the slit image and itself shifted by one
    stripe width along v cancels them (like :func:`~multislit.stripes.separation.
    noise_from_difference` cancels them in the image); texture, edges and blotches do not
    cancel. The mean absolute difference over windows of one stripe width, as a Gaussian
    sigma (times sqrt(pi) / 2), gives a local level; a pixel's texture is the highest level
    in the ring beside it (:data:`TEXTURE_INNER_WIDTHS` to :data:`TEXTURE_OUTER_WIDTHS`
    stripe widths to either side, :data:`TEXTURE_HALF_HEIGHT_WIDTHS` above and below):
    noise where the surroundings are clean, more on a textured surface, and never the
    line's own structure.
    """
    h, w = slit_image.shape
    lag = max(1, math.ceil(stripe_width_px))
    x = slit_image.astype(np.float32)
    if h > lag:
        d = np.abs(x[lag:] - x[:-lag])
        d = np.pad(d, ((0, lag), (0, 0)), mode="edge")
    else:
        d = np.zeros_like(x)
    k = max(3, round(stripe_width_px) | 1)
    level = cv2.blur(d, (k, k), borderType=cv2.BORDER_REFLECT) * np.float32(math.sqrt(math.pi) / 2)
    # the windows of the ring reach no closer than the inner half-width
    inner = round(TEXTURE_INNER_WIDTHS * stripe_width_px) + k // 2
    outer = max(inner + 1, round(TEXTURE_OUTER_WIDTHS * stripe_width_px))
    tall = round(TEXTURE_HALF_HEIGHT_WIDTHS * stripe_width_px)
    ring = np.ones((2 * tall + 1, 2 * outer + 1), np.uint8)
    ring[:, outer - inner : outer + inner + 1] = 0
    return cv2.dilate(level, ring, borderType=cv2.BORDER_REFLECT)


def stripe_like(
    slit_image: NDArray, u: F64, v: F64, stripe_width_px: float, reach: F64 | float = 0.0
) -> NDArray[np.bool_]:
    """Which centres look like a laser line and not like an edge or texture.

    A stripe stands out of the slit image (the row's background removed) on *both* sides:
    :func:`~multislit.stripes.sizes.ridge_contrast` at least
    :data:`~multislit.stripes.sizes.MIN_RIDGE_CONTRAST`. An edge
    (checker, board or albedo step) and the inside of a plateau (a bright square narrower
    than the row background's window) are as bright as the maximum on one or both sides, so their maxima
    go; stripes, isolated or in a dense fan, keep ~1.

    Parameters
    ----------
    slit_image : (H, W) slit image, background ~ 0
    u, v : (K,) centres (px; v integer rows)
    stripe_width_px : stripe FWHM (px): the sides are read 1 to 2 FWHM from the centre
    reach : (K,) or scalar, px from each centre to the far end of its saturated run (0 for an
        unsaturated peak): the sides are read from the ends of the flat top

    Returns
    -------
    (K,) bool
    """
    r = np.rint(v).astype(np.intp)
    c = np.clip(np.rint(u).astype(np.intp), 0, slit_image.shape[1] - 1)
    return ridge_contrast(slit_image, r, c, stripe_width_px, reach) >= MIN_RIDGE_CONTRAST

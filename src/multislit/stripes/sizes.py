"""Stripe and dot sizes: estimated from an image, and the filter sizes they give."""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.validation import SlitExtractionError, as_image

#: FWHM / sigma of a Gaussian, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def median_stride(stripe_width_px: float) -> int:
    """Sample spacing s (px) of the row-wise sparse median for a stripe of FWHM w (px).

    The background at u is the median of the 9 pixels u + s*j, j = -4..4, of its row (a window
    of 8 s + 1 px). A median of 9 ignores up to 4 bright samples. A Gaussian stripe exceeds 10 %
    of its peak over 2 * 2.15 sigma = 1.83 FWHM, so s >= 0.92 FWHM keeps it within 3 samples,
    leaving one spare for a dot, a neighbour stripe's flank or the bright side of an albedo
    step; the window is then ~7-8 FWHM.
    """
    return max(1, math.ceil(0.92 * stripe_width_px))


def opening_length(dot_size_px: float) -> int:
    """Length L (px, odd) of the vertical line that removes dots of FWHM d (px) by opening.

    An opening with a line of length L removes a bump whose vertical extent is < L. A Gaussian
    dot falls below 2 % of its peak at 2.8 sigma = 1.19 FWHM from its centre, so the line must
    span at least +-1.2 FWHM; we use +-ceil(1.5 FWHM) for margin (d = 1.9 px -> L = 7).
    """
    return 2 * math.ceil(1.5 * dot_size_px) + 1


# --------------------------------------------------------------------------- size estimation
# Scales (Gaussian sigma, px) searched by the ridge-scale estimator: sigma 0.6 .. 7.5 px covers
# FWHM 1.4 .. 18 px, every practical stripe or dot size; ratio 1.25 with log-parabolic refinement.
_SCALES = 0.6 * 1.25 ** np.arange(12)
#: The strongest ridge of each profile is taken for the stripes' own width when the median of
#: those differs from that of all ridges by more than this factor.
_WIDTH_DISAGREEMENT = 1.5


@functools.lru_cache(maxsize=64)
def _d2_kernel(sigma: float) -> NDArray[np.float32]:
    """Sampled second derivative of a unit-area Gaussian (zero sum, exact on x^2 / 2); one
    read-only array per ``sigma`` (cached)."""
    r = max(2, math.ceil(4 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    k = g * (x * x - sigma * sigma)
    k -= k.mean()  # no response to a constant
    k /= 0.5 * np.sum(k * x * x)  # response exactly 1 to x^2 / 2
    k = k.astype(np.float32)
    k.flags.writeable = False
    return k


@njit(cache=True)
def _best_scale(resp):
    """For responses (S, R, N): the first scale of the largest response at each point
    (``resp.argmax(axis=0)``, (R, N) intp), that response ((R, N) float32) and the largest
    absolute response over all, in one compiled pass."""
    n_scales, nr, nc = resp.shape
    best = np.zeros((nr, nc), np.intp)
    strength = resp[0].copy()
    peak = 0.0
    for i in range(n_scales):
        for r in range(nr):
            for c in range(nc):
                x = resp[i, r, c]
                peak = max(peak, abs(float(x)))
                if x > strength[r, c]:
                    strength[r, c] = x
                    best[r, c] = i
    return best, strength, peak


def _ridge_fwhm(
    profiles: NDArray[np.float32],
    pixel_noise: float,
    z_min: float = 6.0,
    strongest: bool = False,
) -> float | None:
    """Typical FWHM (px) of the bright ridges along the rows of ``profiles`` (R, N), or None.

    Lindeberg's scale selection: the gamma-normalised second derivative -t^(3/4) d2/dx2 of
    the Gaussian-smoothed profile (t = sigma^2) peaks, for a Gaussian ridge of sigma s, exactly
    at sigma = s. Ridge points are local maxima along the row with a response > ``z_min`` times
    the robust noise of that scale's response; the scale is refined by a parabola in log sigma
    and the median over all ridge points is returned as FWHM. With ``strongest`` (stripes, not
    dots), the median over each profile's strongest ridge replaces it where the two differ by
    more than ``_WIDTH_DISAGREEMENT``.
    """
    n_scales = len(_SCALES)
    resp = np.empty((n_scales,) + profiles.shape, np.float32)
    for i, s in enumerate(_SCALES):
        k = _d2_kernel(float(s))
        resp[i] = -(s**1.5) * cv2.sepFilter2D(
            profiles, cv2.CV_32F, k, np.ones(1, np.float32), borderType=cv2.BORDER_REFLECT
        )
    # per-scale noise of the response, propagated from the pixel noise (white noise through
    # the kernel): robust even where stripes cover most of a row (dense slits)
    noise = np.array(
        [pixel_noise * s**1.5 * float(np.linalg.norm(_d2_kernel(float(s)))) for s in _SCALES]
    )
    best, strength, peak = _best_scale(resp)
    noise = np.maximum(noise, 1e-6 * max(peak, 1e-30))
    z = strength / noise[best]
    mid = strength[:, 1:-1]
    is_max = (mid > strength[:, :-2]) & (mid >= strength[:, 2:]) & (z[:, 1:-1] > z_min)
    r, c = np.nonzero(is_max)
    if r.size == 0:
        return None
    c = c + 1
    st = strength[r, c]
    # drop weak ridges (texture, faint dots) next to the bright stripes
    keep = st > 0.1 * np.percentile(st, 99)
    r, c = r[keep], c[keep]
    b = best[r, c]
    log_s = np.log(_SCALES)[b].astype(np.float64)
    inner = (b > 0) & (b < n_scales - 1)
    bi = b[inner]
    y0 = resp[bi - 1, r[inner], c[inner]].astype(np.float64)
    y1 = resp[bi, r[inner], c[inner]].astype(np.float64)
    y2 = resp[bi + 1, r[inner], c[inner]].astype(np.float64)
    den = y0 - 2 * y1 + y2
    off = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    log_s[inner] += np.clip(off, -0.5, 0.5) * math.log(1.25)
    if log_s.size < 3:
        return None
    typical = float(np.median(log_s))
    if not strongest:
        return float(np.exp(typical) * FWHM_PER_SIGMA)
    # the brightest ridge of each profile is a stripe: where the ridges at large are much
    # narrower or wider (edges, texture and JPEG blocks outnumbering a few laser lines in a
    # photo), the stripes' own width is taken
    sk = st[keep]
    order = np.lexsort((-sk, r))  # by row, strongest first
    strong = np.zeros(r.size, bool)
    strong[order[np.r_[True, r[order][1:] != r[order][:-1]]]] = True  # each row's strongest
    if strong.sum() >= 3:
        top = float(np.median(log_s[strong]))
        if abs(top - typical) > math.log(_WIDTH_DISAGREEMENT):
            typical = top
    return float(np.exp(typical) * FWHM_PER_SIGMA)


#: Least :func:`ridge_contrast` of a stripe (or dot): a Gaussian ridge has ~1, an edge or the
#: inside of a plateau ~0.
MIN_RIDGE_CONTRAST = 0.5


@njit(cache=True)
def _brighter_side(profiles, r, c, d0, d1, reach):
    """(K,) float64 for :func:`ridge_contrast`: the larger of the two sides' lowest values
    ``d0`` .. ``d1`` px beyond the flat top's ends (``c`` -+ ``reach``), a side outside the
    image not counting; 0 where neither side is inside."""
    n = profiles.shape[1]
    out = np.empty(r.size, np.float64)
    for k in range(r.size):
        hi = -np.inf
        for sign in (-1, 1):
            side = np.inf
            for o in range(d0[k], d1[k] + 1):
                col = c[k] + sign * reach[k] + sign * o
                if 0 <= col <= n - 1:
                    side = min(side, float(profiles[r[k], col]))
            if side != np.inf:
                hi = max(hi, side)
        out[k] = 0.0 if hi == -np.inf else hi
    return out


def ridge_contrast(
    profiles: NDArray,
    r: NDArray[np.intp],
    c: NDArray[np.intp],
    fwhm_px: NDArray | float,
    reach_px: NDArray | float = 0.0,
) -> NDArray[np.float64]:
    """How much a maximum of a background-free row profile stands out on both sides.

    With p the value at (r, c) and L, R the lowest values from 1 to 2 FWHM left and right of
    it (counted from the ends of a flat top reaching ``reach_px`` from c), the contrast is
    (p - max(L, R)) / p: ~1 for a ridge (a stripe), ~0 for an edge or the inside of a
    plateau (one or both sides as bright as the maximum). A side outside the image does not
    count; with neither side inside, the contrast is 1.

    Parameters
    ----------
    profiles : (R, N) image whose rows are the profiles, background ~ 0 (a slit image)
    r, c : (K,) int, row and column of each maximum
    fwhm_px : ridge FWHM (px), scalar or (K,)
    reach_px : px from c to the far end of each flat top, scalar or (K,); 0 for a peak pixel

    Returns
    -------
    (K,) float64, at most 1; 0 where p <= 0
    """
    n = profiles.shape[1]
    fw = np.broadcast_to(np.asarray(fwhm_px, np.float64), r.shape)
    d0 = np.maximum(1, np.ceil(fw)).astype(np.intp)
    d1 = np.maximum(d0 + 1, np.ceil(2.0 * fw).astype(np.intp))
    reach = np.rint(np.broadcast_to(np.asarray(reach_px, np.float64), r.shape)).astype(np.intp)
    peak = profiles[r, np.clip(c, 0, n - 1)].astype(np.float64)
    hi = _brighter_side(
        profiles,
        np.ascontiguousarray(r, np.intp),
        np.ascontiguousarray(c, np.intp),
        np.ascontiguousarray(d0),
        np.ascontiguousarray(d1),
        np.ascontiguousarray(reach),
    )
    return np.where(peak > 0, (peak - hi) / np.where(peak > 0, peak, 1.0), 0.0)


def sample_rows(n: int, count: int) -> NDArray[np.intp]:
    """``count`` evenly spaced indices in [0, n) (all if n <= count)."""
    if n <= count:
        return np.arange(n)
    return np.linspace(0, n - 1, count).round().astype(np.intp)


def estimate_stripe_width(image: ArrayLike, *, channel: str = "red", order: str = "rgb") -> float:
    """Estimate the typical stripe FWHM (px, along the row) of an image.

    Ridge scale selection (see ``_ridge_fwhm``) on 24 evenly spaced rows: the stripes are
    the dominant bright ridges along rows; the median over all of them is robust to dots.

    Where edges, texture or JPEG blocks outnumber the stripes (a photo with one laser line),
    the median of each profile's strongest ridge is taken instead when the two disagree by
    more than 1.5 times. Where the rows' maxima are flat tops (a clipped, over-exposed line:
    the scale selection answers at its corners), their full width at half maximum, measured
    directly, is taken when it is wider.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB image, uint8, uint16 or float
    channel : the plane of a colour image (:data:`~multislit.stripes.validation.CHANNELS`);
        default ``"red"``
    order : {'rgb', 'bgr'}, the order of a colour image's planes; default ``"rgb"``

    Returns
    -------
    fwhm : float, px

    Raises
    ------
    SlitExtractionError
        if the image is invalid or shows no stripe-like ridge.
    """
    img = as_image(image, channel=channel, order=order)
    idx = sample_rows(img.shape[0] - 1, 24)
    rows = img[idx].astype(np.float32)
    # pixel noise from vertical neighbours: the (near-vertical) stripes cancel, noise does not
    diff = rows - img[idx + 1].astype(np.float32)
    pixel_noise = max(1.4826 * float(np.median(np.abs(diff))) / math.sqrt(2.0), 1e-3)
    w = _ridge_fwhm(rows, pixel_noise, strongest=True)
    if w is None:
        raise SlitExtractionError("estimate_stripe_width: no stripes found in image")
    flat = _flat_top_width(rows, w)
    if flat is None or abs(math.log(flat / w)) < math.log(_FLAT_TOP_DISAGREEMENT):
        return w
    return flat


#: Flat tops: a row's maximum is a flat top when it lies within ``_FLAT_TOP_BAND`` of the
#: range of the sampled rows below their top and spans at least ``_FLAT_TOP_MIN_PX`` pixels
#: (a clipped line; a JPEG rings over its top, 250-255 for 255).
_FLAT_TOP_BAND = 0.03
_FLAT_TOP_MIN_PX = 3
#: Flat-topped rows needed, as a fraction of the sampled rows, to measure them directly.
_FLAT_TOP_ROWS = 0.25
#: The direct width of flat-topped lines replaces the scale selection's when the two differ by
#: more than this factor: the scale selection answers at a flat top's corners (a fraction of
#: the line's width) or at its whole plateau.
_FLAT_TOP_DISAGREEMENT = 1.25


def _flat_top_width(rows: NDArray[np.float32], fwhm: float) -> float | None:
    """The median FWHM (px) of the lines whose clipping makes the maxima of ``rows`` (R, N)
    flat tops, or None when fewer than ``_FLAT_TOP_ROWS`` of the rows have one.

    A Gaussian of peak P clipped at c is flat over 2 x_c and crosses c / 2 at +-x_h, with
    x_h^2 - x_c^2 = 2 ln 2 sigma^2 whatever P: its FWHM is 2 sqrt(x_h^2 - x_c^2). The flat
    top is measured at the clip level, the crossing halfway between it and the local
    background (of the lowest values within a flat-top length plus ``fwhm`` on either side,
    the higher), both to the pixel."""
    top, bottom = float(rows.max()), float(rows.min())
    if top <= bottom:
        return None
    level = top - _FLAT_TOP_BAND * (top - bottom)
    n = rows.shape[1]
    widths = []
    for row in rows:
        k = int(np.argmax(row))
        if row[k] < level:
            continue
        a = b = k
        while a > 0 and row[a - 1] >= level:
            a -= 1
        while b < n - 1 and row[b + 1] >= level:
            b += 1
        length = b - a + 1
        if length < _FLAT_TOP_MIN_PX:
            continue
        reach = length + math.ceil(fwhm)
        left, right = row[max(0, a - reach) : a], row[b + 1 : b + 1 + reach]
        sides = [float(x.min()) for x in (left, right) if x.size]
        if not sides:
            continue
        base = max(sides)  # the brighter side: a line along a dark square's edge
        half = 0.5 * (level + base)
        while a > 0 and row[a - 1] >= half:
            a -= 1
        while b < n - 1 and row[b + 1] >= half:
            b += 1
        x_c, x_h = 0.5 * length, 0.5 * (b - a + 1)
        widths.append(2.0 * math.sqrt(max(x_h * x_h - x_c * x_c, 1.0)))
    if len(widths) < _FLAT_TOP_ROWS * len(rows):
        return None
    return float(np.median(widths))


def estimate_dot_size(highpass: ArrayLike) -> float | None:
    """Estimate the typical dot FWHM (px) from a highpass image (stripes + dots).

    Along a column the (vertical) stripes are flat and only the dots form ridges, so the ridge
    scale selection of :func:`estimate_stripe_width` on 48 evenly spaced columns measures the
    dots. Returns None if no dot is found.

    Parameters
    ----------
    highpass : (H, W) array, e.g. :attr:`Separation.highpass`

    Returns
    -------
    fwhm : float (px) or None
    """
    hp = as_image(highpass, name="highpass")
    cols = np.ascontiguousarray(hp[:, sample_rows(hp.shape[1], 48)].T, dtype=np.float32)
    # noise from neighbours along each column: the dots are sparse there
    pixel_noise = max(
        1.4826 * float(np.median(np.abs(np.diff(cols, axis=1)))) / math.sqrt(2.0), 1e-3
    )
    return _ridge_fwhm(cols, pixel_noise)

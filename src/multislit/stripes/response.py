"""The stripes' ridge response: a matched filter across the stripe, integrated along it.

A stripe whose peak stands only a few noise sigmas above its background per pixel (a dark
surface, a surface the projector grazes) is lost by a threshold on single pixels, although
along the stripe, over tens of rows, it is clearly there. The response integrates it: the
slit image is filtered across the stripe by the negative second derivative of a Gaussian of
the stripe's own sigma (Steger's line detector at the line's width: zero response to a
constant or a linear background, the largest at the centre of a line of that width) and
smoothed along the stripe by a Gaussian of :data:`ALONG_SIGMA` rows. The filter is scaled so
that a straight, upright Gaussian stripe of amplitude A gives A at its centre; the response's
noise is the image's pixel noise times :func:`ridge_kernels`' gain (white noise: the norm of
the two kernels), far less than one pixel's. Along the stripe the smoothing reaches a few
rows past a stripe's end: :func:`~multislit.stripes.chains.settle_weak` trims what only the
response found there.

Units: px, intensity units of the slit image; the response is (H, W) float32 in intensity
units (the amplitude of the stripe it matches).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.stripes.sizes import FWHM_PER_SIGMA
from multislit.stripes.slope import _sobel_row
from multislit.stripes.slope import reflect101 as reflect

F32 = NDArray[np.float32]

#: The Gaussian (sigma, rows) over which the response integrates along the stripe. Over the
#: +-3 sigma it reaches, a stripe leaning 45 degrees moves 12 px across its row: its profile
#: is widened from sigma s to sqrt(s^2 + 4), still a ridge.
ALONG_SIGMA = 2.0
#: The response's detection threshold, in sigmas of its own noise, as a fraction of the single
#: pixel's threshold in sigmas of the pixel noise (``k_sigma``, 8 by default: 6 sigmas).
RIDGE_K_FRACTION = 0.75
#: Where the stripes lean by this many px per row or more, the response integrates along the
#: lean (:func:`ridge_response`): over the +-3 sigma the smoothing reaches, a stripe leaning
#: 0.25 px per row moves 3 px across its row.
SHEAR_MIN_SLOPE = 0.25
#: :func:`lean_slopes` reads a lean where the structure tensor's coherence ((l1 - l2) /
#: (l1 + l2) of its eigenvalues) is at least this (1: one direction, 0: none).
_LEAN_COHERENCE = 0.5
#: The cells (px) of the stripes' lean (:func:`lean_slopes`).
LEAN_CELL = 4
#: The kernels reach this many of their sigmas from their centre.
_REACH_SIGMAS = 2.5
#: The narrowest across-filter sigma (px): a Gaussian narrower than this is no longer sampled.
_MIN_SIGMA_PX = 0.7


@functools.lru_cache(maxsize=32)
def ridge_kernels(stripe_width_px: float) -> tuple[F32, F32, float]:
    """The response's two kernels for stripes of FWHM ``stripe_width_px`` (px).

    Returns
    -------
    across : (2 a + 1,) float32, along the row: minus the second derivative of a Gaussian of
        the stripe's sigma (at least 0.7 px), zero sum, scaled so that a Gaussian profile of
        that sigma and amplitude 1 gives 1 at its centre
    along : (2 b + 1,) float32, along the column: a Gaussian of :data:`ALONG_SIGMA` rows,
        unit sum
    gain : float, the response's noise sigma per unit of the image's pixel noise sigma
        (white noise: the product of the kernels' norms)

    Read-only arrays, cached per width.
    """
    s = max(stripe_width_px / FWHM_PER_SIGMA, _MIN_SIGMA_PX)
    a = max(2, math.ceil(_REACH_SIGMAS * s))
    x = np.arange(-a, a + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / s) ** 2)
    across = g * (1.0 - (x / s) ** 2)
    across -= across.mean()  # no response to a constant background
    across /= np.sum(across * g)  # 1 at the centre of a unit Gaussian profile of sigma s
    b = math.ceil(_REACH_SIGMAS * ALONG_SIGMA)
    y = np.arange(-b, b + 1, dtype=np.float64)
    along = np.exp(-0.5 * (y / ALONG_SIGMA) ** 2)
    along /= along.sum()
    gain = float(np.linalg.norm(across) * np.linalg.norm(along))
    out = (across.astype(np.float32), along.astype(np.float32))
    for k in out:
        k.flags.writeable = False
    return out[0], out[1], gain


def lean_slopes(slits: NDArray, stripe_width_px: float) -> F32:
    """The stripes' lean du/dv (px per row) per cell of :data:`LEAN_CELL` px of a slit image
    (the last cells take the image's remainder): (H // D, W // D) float32, 0 where they stand
    upright (lean below :data:`SHEAR_MIN_SLOPE`) or have no one direction (the structure
    tensor's coherence below :data:`_LEAN_COHERENCE`), at most 1 (45 degrees) either way.

    The structure tensor of the gradients (Sobel) of the image averaged over 2 x 2 px
    (stripes as dense as 6.5 px apart are still resolved: a coarser grid reads dense leaning
    stripes with the wrong sign), averaged over each cell and integrated over a Gaussian of
    one stripe width.
    """
    h, w = slits.shape
    d = LEAN_CELL
    if h < 2 * d or w < 2 * d:
        return np.zeros((max(h // d, 1), max(w // d, 1)), np.float32)
    half = cv2.resize(slits, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    tensor = _cell_tensor(half, h // d, w // d, d // 2)
    tensor = cv2.GaussianBlur(tensor, (0, 0), max(stripe_width_px / d, 0.5))
    return _tensor_slopes(tensor, np.float32(_LEAN_COHERENCE), np.float32(SHEAR_MIN_SLOPE))


@njit(cache=True)
def _cell_tensor(img, ch, cw, f):
    """(ch, cw, 3) float32: per cell of ``f`` x ``f`` px of ``img`` (H, W) (the last cells
    take the remainder), the means of gu^2, gv^2 and 2 gu gv of its 3 x 3 Sobel derivatives
    (the image's border pixels left out). Row by row: the derivatives of a row in one pass
    (:func:`~multislit.stripes.slope._sobel_row`), then summed into its cells."""
    h, w = img.shape
    out = np.zeros((ch, cw, 3), np.float32)
    count = np.zeros((ch, cw), np.float32)
    cell = np.empty(w, np.intp)
    for j in range(w):
        cell[j] = min(j // f, cw - 1)
    gu = np.zeros(w, np.float32)
    gv = np.zeros(w, np.float32)
    uu = np.zeros(w, np.float32)
    vv = np.zeros(w, np.float32)
    uv = np.zeros(w, np.float32)
    for i in range(1, h - 1):
        _sobel_row(img, i, gu, gv)
        for j in range(1, w - 1):
            uu[j] = gu[j] * gu[j]
            vv[j] = gv[j] * gv[j]
            uv[j] = 2 * gu[j] * gv[j]
        ci = min(i // f, ch - 1)
        row = out[ci]
        for j in range(1, w - 1):
            k = cell[j]
            row[k, 0] += uu[j]
            row[k, 1] += vv[j]
            row[k, 2] += uv[j]
            count[ci, k] += 1
    for ci in range(ch):
        for cj in range(cw):
            n = max(count[ci, cj], np.float32(1.0))
            for k in range(3):
                out[ci, cj, k] /= n
    return out


@njit(cache=True)
def _tensor_slopes(tensor, coherence, min_slope):
    """(ch, cw) float32, the lean of the stripes from ``tensor`` (ch, cw, 3) (J_uu, J_vv,
    2 J_uv): the gradients lie across the stripe at theta from the u axis, tan 2 theta =
    2 J_uv / (J_uu - J_vv), and a stripe f(u - t v) has gradients along (1, -t), so
    t = -tan theta, clipped to +-1; 0 where the coherence is below ``coherence`` or
    |t| below ``min_slope``."""
    ch, cw = tensor.shape[0], tensor.shape[1]
    out = np.zeros((ch, cw), np.float32)
    for i in range(ch):
        for j in range(cw):
            juu, jvv, juv2 = tensor[i, j, 0], tensor[i, j, 1], tensor[i, j, 2]
            diff = juu - jvv
            mag = np.sqrt(diff * diff + juv2 * juv2)
            if not mag >= coherence * (juu + jvv) + 1e-12:
                continue
            # tan theta = sin 2 theta / (1 + cos 2 theta) = 2 J_uv / (J_uu - J_vv + mag)
            den = diff + mag
            t = -juv2 / den if den > 0 else (-1.0 if juv2 > 0 else 1.0)
            t = min(max(t, -1.0), 1.0)
            if abs(t) >= min_slope:
                out[i, j] = t
    return out


def slopes_at(cells: F32, r: NDArray[np.intp], c: NDArray[np.intp]) -> NDArray[np.float64]:
    """(K,) float64, px per row: the lean of :func:`lean_slopes`' ``cells`` at the pixels
    (``r``, ``c``) (K,)."""
    d = LEAN_CELL
    ch, cw = cells.shape
    return cells[np.minimum(r // d, ch - 1), np.minimum(c // d, cw - 1)].astype(np.float64)


def ridge_response(slits: NDArray, stripe_width_px: float, slope: F32 | None = None) -> F32:
    """(H, W) float32, the ridge response of a slit image (see the module).

    Along the stripe means along the image's columns where the stripes stand upright, and
    along their lean where ``slope`` (:func:`lean_slopes`' cells) has one: there the rows
    filtered across are summed along the line u = u0 + s (v - v0), each read by linear
    interpolation along its row.

    Parameters
    ----------
    slits : (H, W) slit image (uint8, uint16 or float32), background ~ 0
    stripe_width_px : float, px, the stripes' FWHM along the row
    slope : (H // D, W // D) float32, px per row, the lean per cell (:func:`lean_slopes`);
        default None: along the columns everywhere

    Returns
    -------
    (H, W) float32, intensity units; the border is reflected
    """
    across, along, _ = ridge_kernels(float(stripe_width_px))
    x = slits if slits.dtype in (np.uint8, np.uint16, np.float32) else slits.astype(np.float32)
    if slope is None or not slope.any():
        return cv2.sepFilter2D(x, cv2.CV_32F, across, along, borderType=cv2.BORDER_REFLECT)
    one = np.ones(1, np.float32)
    rows = cv2.sepFilter2D(x, cv2.CV_32F, across, one, borderType=cv2.BORDER_REFLECT)
    out = cv2.sepFilter2D(rows, cv2.CV_32F, one, along, borderType=cv2.BORDER_REFLECT)
    _shear_cells(rows, out, np.ascontiguousarray(slope, np.float32), LEAN_CELL, along)
    return out


@njit(cache=True)
def _shear_cells(rows, out, slope, d, taps):
    """Where a cell of ``slope`` ((H // d, W // d) float32, px per row; the last cells take
    the image's remainder) is not 0, ``out`` (H, W) float32 is ``rows`` (H, W) float32
    summed with the weights ``taps`` (odd) along the line of that slope through each pixel
    (rows reflected at the border, columns clamped, read by linear interpolation along the
    row); in place. Within a cell each tap reads its row at one sub-pixel offset, worked out
    once for the cell's rows; each pixel's sum runs over the taps in order."""
    h, w = rows.shape
    ch, cw = slope.shape
    half = taps.size // 2
    for ci in range(ch):
        r0 = ci * d
        r1 = h if ci == ch - 1 else r0 + d
        for cj in range(cw):
            t = np.float32(slope[ci, cj])
            if t == 0.0:
                continue
            c0 = cj * d
            c1 = w if cj == cw - 1 else c0 + d
            for r in range(r0, r1):
                o_row = out[r]
                for c in range(c0, c1):
                    o_row[c] = 0.0
            for k in range(-half, half + 1):
                x = t * np.float32(k)
                o = int(np.floor(x))
                f = np.float32(x - o)
                g = np.float32(taps[k + half])
                inside = c0 + o >= 0 and c1 + o < w
                for r in range(r0, r1):
                    o_row = out[r]
                    src = rows[reflect(r + k, h)]
                    if inside:
                        for c in range(c0, c1):
                            a = src[c + o]
                            o_row[c] += g * (a + (src[c + o + 1] - a) * f)
                    else:
                        for c in range(c0, c1):
                            i0 = min(max(c + o, 0), w - 1)
                            i1 = min(max(c + o + 1, 0), w - 1)
                            a = src[i0]
                            o_row[c] += g * (a + (src[i1] - a) * f)


def ridge_threshold(threshold: float, stripe_width_px: float) -> float:
    """The ridge response's detection threshold (intensity units) that goes with a single
    pixel's ``threshold`` (``k_sigma`` times the pixel noise, intensity units):
    :data:`RIDGE_K_FRACTION` times as many sigmas of the response's noise (the kernels' gain
    for stripes of FWHM ``stripe_width_px``, :func:`ridge_kernels`)."""
    return RIDGE_K_FRACTION * threshold * ridge_kernels(float(stripe_width_px))[2]


#: A stripe is wide where the response at twice the stripe's sigma (on the image averaged over
#: 2 x 2 px) exceeds the response at its sigma by this factor: about 1 on a stripe of the
#: nominal width, 1.5 on one 1.5 times as wide, 2 on one twice as wide (where the surface
#: grazes the projector, a sphere's limb); and where the slit image at the wide centre keeps
#: :data:`_WIDE_PEAK` of the narrow peak (not a valley between two stripes that the wide
#: filter takes for one).
WIDE_RATIO = 1.6
#: The wide response's maximum is sought up to this many px (of the averaged image) from a
#: centre: on a wide speckled stripe the narrow response peaks on the speckle grains.
_WIDE_REACH = 3
_WIDE_PEAK = 0.6


def wide_centres(
    slits: NDArray,
    stripe_width_px: float,
    r: NDArray[np.intp],
    c: NDArray[np.intp],
    response: NDArray[np.float64],
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Which centres lie on a wide stripe, and their centre at its width.

    The ridge response of the slit image averaged over 2 x 2 px at the stripe's sigma (twice
    the sigma in the image's px, integrated along the columns over twice the rows), at each
    centre's row (between the averaged rows about it), its maximum within
    :data:`_WIDE_REACH` averaged px of the centre's column: where it exceeds
    :data:`WIDE_RATIO` times ``response`` (the response at the stripe's own width at the
    centre) and the slit image there keeps :data:`_WIDE_PEAK` of its value at ``c`` (over
    three rows), the stripe is wide, and its centre is that maximum's (a parabola through
    three samples), which the speckle on it moves far less than the narrow filter's.

    Parameters
    ----------
    slits : (H, W) slit image (uint8, uint16 or float32)
    stripe_width_px : float, px, the stripes' nominal FWHM
    r, c : (K,) intp, the centres' rows and columns (px; ``c`` the narrow response's peak)
    response : (K,) float64, :func:`ridge_response` at the centres

    Returns
    -------
    wide : (K,) bool
    u : (K,) float64, px, the centre column at the stripe's width where ``wide`` (NaN else)
    """
    h, w = slits.shape
    if h < 4 or w < 8 or r.size == 0:
        return np.zeros(r.size, bool), np.full(r.size, np.nan)
    half = cv2.resize(slits, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    resp = ridge_response(half, stripe_width_px)
    wide, u = _wide_at(resp, r, c, np.asarray(response, np.float64), WIDE_RATIO, _WIDE_REACH)
    if wide.any():
        # the slit image over three rows at the wide centre and at the narrow peak
        k = np.flatnonzero(wide)
        rows = np.clip(r[k][:, None] + np.arange(-1, 2)[None, :], 0, h - 1)
        at = slits[rows, np.clip(np.rint(u[k]).astype(np.intp), 0, w - 1)[:, None]]
        peak = slits[rows, c[k][:, None]]
        valley = at.astype(np.float64).sum(1) < _WIDE_PEAK * peak.astype(np.float64).sum(1)
        wide[k[valley]] = False
        u[k[valley]] = np.nan
    return wide, u


@njit(cache=True)
def _wide_at(resp, r, c, narrow, ratio, reach):
    """:func:`wide_centres` on the averaged image's response ``resp`` (H // 2, W // 2):
    per centre (``r``, ``c``) (K,), the response's maximum in each of the two averaged rows
    about row r (hill-climbed from column c // 2 within ``reach``), blended by the row's
    position between them; wide where the blend exceeds ``ratio`` times ``narrow`` (K,)."""
    hh, hw = resp.shape
    n = r.size
    wide = np.zeros(n, np.bool_)
    u = np.full(n, np.nan)
    for k in range(n):
        y = (r[k] - 0.5) / 2.0
        i0 = min(max(int(np.floor(y)), 0), hh - 1)
        i1 = min(i0 + 1, hh - 1)
        fy = min(max(y - i0, 0.0), 1.0)
        j0 = min(c[k] // 2, hw - 1)
        val = 0.0
        pos = 0.0
        ok = True
        for ii, wt in ((i0, 1.0 - fy), (i1, fy)):
            row = resp[ii]
            j = j0
            for _ in range(reach):
                if j > 0 and row[j - 1] > row[j]:
                    j -= 1
                elif j < hw - 1 and row[j + 1] > row[j]:
                    j += 1
                else:
                    break
            if j == 0 or j == hw - 1 or row[j - 1] > row[j] or row[j + 1] > row[j]:
                ok = False
                break
            a, b, cc = float(row[j - 1]), float(row[j]), float(row[j + 1])
            den = a - 2.0 * b + cc
            off = 0.5 * (a - cc) / den if den < 0 else 0.0
            val += wt * b
            pos += wt * (j + min(max(off, -0.5), 0.5))
        if ok and val > ratio * narrow[k]:
            wide[k] = True
            u[k] = 2.0 * pos + 0.5
    return wide, u

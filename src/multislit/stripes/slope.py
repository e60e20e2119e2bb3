"""The local lean of the stripes (du/dv) from the structure tensor of the highpass image: the
slope along which the dots on a leaning stripe are refilled and its opening follows it."""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

F32 = NDArray[np.float32]


@njit(cache=True)
def reflect101(i: int, n: int) -> int:
    """cv2.BORDER_REFLECT_101 index (gfedcb|abcdefgh|gfedcba)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


def slope_sigma(length: int) -> float:
    """Integration scale (px) of :func:`stripe_slope` for an opening of ``length`` px: half the
    line, a few stripe widths."""
    return 0.5 * length


def _structure_tensor(hp: NDArray, sigma: float) -> tuple[F32, F32]:
    """J_uu and J_uv of :func:`stripe_slope`: the products gu^2, gu gv of the Sobel
    derivatives of ``hp`` (uint8, uint16 or float32) integrated over a Gaussian of ``sigma``
    px, (H, W) float32 each."""
    # Sobel straight from integer data: its sums are integers below 2^24, exact in float32
    gu = cv2.Sobel(hp, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(hp, cv2.CV_32F, 0, 1, ksize=3)
    juv = cv2.GaussianBlur(cv2.multiply(gu, gv, dst=gv), (0, 0), sigma)
    juu = cv2.GaussianBlur(cv2.multiply(gu, gu, dst=gu), (0, 0), sigma)
    return juu, juv


def stripe_slope(hp: NDArray, sigma: float) -> NDArray[np.float32]:
    """(H, W) float32, px per row: the local lean of the stripes, du/dv, from the structure
    tensor of ``hp`` integrated over a Gaussian of ``sigma`` px (a stripe f(u - s v) has
    gradients (f', -s f'), so s = -J_uv / J_uu); clipped to +-1."""
    x = hp if hp.dtype in (np.uint8, np.uint16, np.float32) else hp.astype(np.float32)
    juu, juv = _structure_tensor(x, sigma)
    s = -juv / np.maximum(juu, 1e-6)
    return np.clip(s, -1.0, 1.0)


def slope_cells(hp: NDArray, sigma: float, cell: int) -> F32:
    """The stripes' lean du/dv per cell of ``cell`` x ``cell`` px: (H // cell, W // cell)
    float32, px per row, clipped to +-1; NaN where the image has no one direction (an
    isolated dot, blank background: the structure tensor's coherence below
    :data:`_LEAN_COHERENCE`). Read at a pixel by :func:`cell_slopes`.

    The direction of the structure tensor of ``hp``'s gradients (3 x 3 Sobel, at full
    resolution) averaged over each cell (:func:`cell_tensor`; the last cells take the
    image's remainder) and integrated over a Gaussian of ``sigma`` px, as :func:`lean_map`
    reads it. Gradients on a coarser grid than the image's (:func:`lean_map`'s) read the end
    of a stripe beside its continuation (an occlusion's jump) as a lean, and dense stripes
    too upright; averaged after the products, the cells keep what the image's own tensor says
    at the scale of a few stripe widths.

    Parameters
    ----------
    hp : (H, W) highpass image (uint8, uint16 or float32)
    sigma : float, px, the integration scale (:func:`slope_sigma`)
    cell : int, px
    """
    h, w = hp.shape
    tensor = cell_tensor(hp, max(h // cell, 1), max(w // cell, 1), cell)
    tensor = cv2.GaussianBlur(tensor, (0, 0), max(sigma / cell, 0.5))
    return tensor_slopes(tensor, np.float32(_LEAN_COHERENCE), np.float32(0.0), np.float32(np.nan))


def cell_slopes(slopes: F32, cell: int, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> F32:
    """(K,) float32, px per row: :func:`slope_cells`' ``slopes`` ((H // cell, W // cell)
    float32, NaN: no direction) at the pixels (``rows``, ``cols``) (K,), interpolated
    bilinearly between the centres of the four cells around each (clamped at the outer cells'
    centres) over those with a direction; 0 (upright) where none has one."""
    return _cell_slopes(np.ascontiguousarray(slopes, np.float32), int(cell), rows, cols)


@njit(cache=True)
def _cell_slopes(t, d, rows, cols):
    """:func:`cell_slopes` from the cells' slopes ``t`` (ch, cw) float32."""
    ch, cw = t.shape
    out = np.zeros(rows.size, np.float32)
    one = np.float32(1.0)
    for i in range(rows.size):
        y = min(max((rows[i] + 0.5) / d - 0.5, 0.0), ch - 1.0)
        x = min(max((cols[i] + 0.5) / d - 0.5, 0.0), cw - 1.0)
        y0 = min(int(y), max(ch - 2, 0))
        x0 = min(int(x), max(cw - 2, 0))
        fy = np.float32(y - y0)
        fx = np.float32(x - x0)
        num = np.float32(0.0)
        den = np.float32(0.0)
        for k in range(4):
            yy = min(y0 + 1, ch - 1) if k >= 2 else y0
            xx = min(x0 + 1, cw - 1) if k % 2 else x0
            wt = (fy if k >= 2 else one - fy) * (fx if k % 2 else one - fx)
            v = t[yy, xx]
            if not np.isnan(v):
                num += wt * v
                den += wt
        if den > 0:
            out[i] = num / den
    return out


#: :func:`lean_map` reads the stripes' direction on the image decimated this many times.
LEAN_DECIMATION = 4
#: ... where the structure there is at least this coherent (1: one direction, 0: none).
_LEAN_COHERENCE = 0.5


def lean_map(hp: NDArray, sigma: float, decimation: int = LEAN_DECIMATION) -> F32:
    """The stripes' direction, deg from the vertical (positive leaning right going down), on
    the image decimated D = ``decimation`` times (default :data:`LEAN_DECIMATION`):
    (H // D, W // D) float32, NaN where the image has no one direction (an isolated dot, blank
    background).

    The structure tensor of ``hp`` integrated over a Gaussian of ``sigma`` px, on the image
    averaged over blocks of D x D px: the direction is smooth over a few stripe widths, and it
    only chooses among lines 15 deg apart
    (:func:`~multislit.stripes.openings.follow_stripe_opening`). Where the tensor's coherence
    ((l1 - l2) / (l1 + l2) of its eigenvalues) is below :data:`_LEAN_COHERENCE`, NaN. Pixel
    (r, c) of the image lies in cell (r // D, c // D) (the last cells take the remainder).

    Parameters
    ----------
    hp : (H, W) highpass image (uint8, uint16 or float32)
    sigma : float, px, the integration scale (:func:`slope_sigma`)
    decimation : int, D, px; the decimated image must resolve the stripes, or the direction
        comes out too upright, the more so the closer they are: of stripes leaning 17.5
        degrees, 20, 12 and 6.5 px apart along the rows, D = 4 reads 14, 9 and -15 degrees,
        D = 2 reads 15, 15 and 12
    """
    h, w = hp.shape
    f = int(decimation)
    if h < 2 * f or w < 2 * f:
        return np.full((max(h // f, 1), max(w // f, 1)), np.nan, np.float32)
    small = cv2.resize(hp, (w // f, h // f), interpolation=cv2.INTER_AREA).astype(np.float32)
    gu = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
    s = max(sigma / f, 0.5)
    juu = cv2.GaussianBlur(cv2.multiply(gu, gu), (0, 0), s)
    jvv = cv2.GaussianBlur(cv2.multiply(gv, gv), (0, 0), s)
    juv2 = cv2.GaussianBlur(cv2.multiply(gu, gv, scale=2.0), (0, 0), s)
    return _tensor_angles(juu, jvv, juv2)


def _tensor_angles(juu: F32, jvv: F32, juv2: F32) -> F32:
    """The stripes' direction, deg from the vertical in [-90, 90), of the structure tensor
    (J_uu, J_vv, 2 J_uv) (same shape, float32 each); NaN where its coherence is below
    :data:`_LEAN_COHERENCE`."""
    # the gradients lie across the stripe, at half the angle of (J_uu - J_vv, 2 J_uv) from the
    # u axis; a stripe f(u - s v) has gradients along (1, -s): it leans atan(s), minus that
    mag, phase = cv2.cartToPolar(cv2.subtract(juu, jvv), juv2, angleInDegrees=True)
    theta = phase * np.float32(0.5)  # [0, 180)
    ang = np.where(theta > 90.0, np.float32(180.0) - theta, -theta)  # [-90, 90)
    incoherent = mag < cv2.add(juu, jvv) * np.float32(_LEAN_COHERENCE) + np.float32(1e-12)
    ang[incoherent] = np.nan
    return ang


@njit(cache=True)
def _sobel_row(hp, r, gur, gvr):
    """Row ``r`` of cv2.Sobel's 3x3 derivatives of an integer image ``hp`` (H, W) along u and
    v (cv2.BORDER_REFLECT_101), as float32 into ``gur``, ``gvr`` (W,): sums of integers below
    2^24, exact in float32 in any order (so the loop runs in float32 lanes, not Numba's int64
    ones)."""
    h, w = hp.shape
    ra = hp[reflect101(r - 1, h)]
    rb = hp[r]
    rc = hp[reflect101(r + 1, h)]
    two = np.float32(2.0)
    # shifted 1-D views, indices from 0: the loop vectorises
    al, am, ar = ra[: w - 2], ra[1 : w - 1], ra[2:]
    bl, br = rb[: w - 2], rb[2:]
    cl, cm, cr = rc[: w - 2], rc[1 : w - 1], rc[2:]
    ou = gur[1 : w - 1]
    ov = gvr[1 : w - 1]
    for q in range(w - 2):
        a0, a1, a2 = np.float32(al[q]), np.float32(am[q]), np.float32(ar[q])
        b0, b2 = np.float32(bl[q]), np.float32(br[q])
        c0, c1, c2 = np.float32(cl[q]), np.float32(cm[q]), np.float32(cr[q])
        ou[q] = (a2 - a0) + two * (b2 - b0) + (c2 - c0)
        ov[q] = (c0 + two * c1 + c2) - (a0 + two * a1 + a2)
    for c in (0, w - 1):  # the reflected borders
        cl = reflect101(c - 1, w)
        cr = reflect101(c + 1, w)
        a0, a1, a2 = np.float32(ra[cl]), np.float32(ra[c]), np.float32(ra[cr])
        b0, b2 = np.float32(rb[cl]), np.float32(rb[cr])
        c0, c1, c2 = np.float32(rc[cl]), np.float32(rc[c]), np.float32(rc[cr])
        gur[c] = (a2 - a0) + two * (b2 - b0) + (c2 - c0)
        gvr[c] = (c0 + two * c1 + c2) - (a0 + two * a1 + a2)


@njit(cache=True)
def cell_tensor(img, ch, cw, f):
    """(ch, cw, 3) float32: per cell of ``f`` x ``f`` px of ``img`` (H, W) (the last cells
    take the remainder), the means of gu^2, gv^2 and 2 gu gv of its 3 x 3 Sobel derivatives
    (the image's border pixels left out). Row by row: the derivatives of a row
    (:func:`_sobel_row`), added to the sums of its row of cells column by column (both loops
    vectorise); the columns' sums are summed into the cells once per row of cells."""
    h, w = img.shape
    out = np.zeros((ch, cw, 3), np.float32)
    su = np.zeros(w, np.float32)
    sv = np.zeros(w, np.float32)
    suv = np.zeros(w, np.float32)
    # the columns 1 .. W - 2 of each cell: [lo, hi)
    lo = np.empty(cw, np.intp)
    hi = np.empty(cw, np.intp)
    for k in range(cw):
        lo[k] = max(k * f, 1)
        hi[k] = w - 1 if k == cw - 1 else min((k + 1) * f, w - 1)
    gu = np.zeros(w, np.float32)
    gv = np.zeros(w, np.float32)
    two = np.float32(2.0)
    rows = 0
    for i in range(1, h - 1):
        _sobel_row(img, i, gu, gv)
        for j in range(1, w - 1):
            su[j] += gu[j] * gu[j]
            sv[j] += gv[j] * gv[j]
            suv[j] += two * gu[j] * gv[j]
        rows += 1
        ci = min(i // f, ch - 1)
        if i == h - 2 or min((i + 1) // f, ch - 1) != ci:  # the row of cells is complete
            row = out[ci]
            for k in range(cw):
                tu = np.float32(0.0)
                tv = np.float32(0.0)
                tuv = np.float32(0.0)
                for j in range(lo[k], hi[k]):
                    tu += su[j]
                    tv += sv[j]
                    tuv += suv[j]
                m = np.float32(max(rows * (hi[k] - lo[k]), 1))
                row[k, 0] = tu / m
                row[k, 1] = tv / m
                row[k, 2] = tuv / m
            su[:] = 0.0
            sv[:] = 0.0
            suv[:] = 0.0
            rows = 0
    return out


@njit(cache=True)
def tensor_slopes(tensor, coherence, min_slope, none):
    """(ch, cw) float32, px per row, the lean of the stripes from ``tensor`` (ch, cw, 3)
    float32 (J_uu, J_vv, 2 J_uv): the gradients lie across the stripe at theta from the u
    axis, tan 2 theta = 2 J_uv / (J_uu - J_vv), and a stripe f(u - t v) has gradients along
    (1, -t), so t = -tan theta, clipped to +-1; ``none`` where the coherence
    ((l1 - l2) / (l1 + l2) of the eigenvalues) is below ``coherence``, 0 where |t| is below
    ``min_slope``."""
    ch, cw = tensor.shape[0], tensor.shape[1]
    out = np.full((ch, cw), none, np.float32)
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
            out[i, j] = t if abs(t) >= min_slope else 0.0
    return out

"""The dots' centres: where each projected dot lies in a dot image, to a fraction of a pixel.

The separation leaves the dots on a flat background (:class:`~multislit.stripes.SlitExtraction`'s
``dots``). A dot is a small blob about ``dot_size_px`` across; :func:`find_dots` smooths the
dot image with a Gaussian of the dot's own size (the matched filter for a Gaussian spot), takes
every local maximum that stands ``k_sigma`` noise sigmas of the smoothed image above zero, and
centres it to sub-pixel by a parabola through the logarithms of the three samples along each
axis (exact for a Gaussian spot). :func:`dot_response` is how strongly each place of a frame
looks like a dot, in noise sigmas, with no threshold.

Where a dot must be centred as finely as the image allows, it is fitted as a spot, with the
spots around it, on the image's *sharp response* (:func:`sharp_response`): the image smoothed by
a Gaussian of half a pixel, less its mean a little before and after along the stripes (a stripe
and the background cancel), less its median at its zone (near a stripe or not) and level, its
noise measured per zone and level. On it a dot is a round Gaussian spot with two negative half
copies before and after it along the stripe. Dots closer than about three pixels blend into one
peak in a dot-sized smoothing, and a peak-based centre then lies between them; here every dot
is fitted as that spot, with its own centre and height, beside the spots of all the others
(:func:`fit_dot_spots`). The calibration centres its reference boards' dots so
(:func:`~multislit.calibrate.board_dots.board_catalogue`), and a scan the dots it identified
(:func:`centre_dots`): the boards' dots give the dot projector's rays, and a frame's dots centred
the same way are biased as the boards' were.

Units: px, (u, v) = (column, row), (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from multislit.stripes.separation import saturation_level_of
from multislit.stripes.sizes import FWHM_PER_SIGMA
from multislit.stripes.validation import SlitExtractionError

if TYPE_CHECKING:
    from multislit.stripes.linking import SlitExtraction

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

#: Default detection threshold of :func:`find_dots`, in noise sigmas of the smoothed dot image.
DEFAULT_DOT_K_SIGMA = 4.0
#: Places closer than this many stripe widths (FWHM) to a stripe centre are near it: speckle on
#: the stripe leaves dot-like peaks there ...
STRIPE_CLEARANCE = 0.9
#: ... so a dot near a stripe counts only when its peak reaches this share of the stripe's.
MIN_DOT_RATIO = 0.2
#: Smallest smoothing sigma, px (a dot is never sharper than the pixel).
_MIN_SIGMA = 0.5


@dataclass(frozen=True, eq=False)
class DotCentres:
    """The dots found in one dot image.

    Attributes
    ----------
    u, v : (M,) float64, px, sub-pixel dot centres, sorted by (row, column) of their peaks
    peak : (M,) float64, the smoothed dot image at the peak pixel (intensity units)
    """

    u: F64
    v: F64
    peak: F64

    def __len__(self) -> int:
        return len(self.u)

    @property
    def uv(self) -> F64:
        """(M, 2) float64, px, the centres."""
        return np.stack([self.u, self.v], axis=1)

    def subset(self, keep: NDArray[np.bool_]) -> DotCentres:
        """The dots where ``keep`` (M,) bool is True."""
        return DotCentres(self.u[keep], self.v[keep], self.peak[keep])


def smoothed_noise(noise_sigma: float, sigma_px: float) -> float:
    """Noise sigma of white noise of ``noise_sigma`` after a 2-D Gaussian blur of ``sigma_px``
    (px): the blur's kernel has a squared sum of 1 / (4 pi sigma^2)."""
    return float(noise_sigma) / (2.0 * math.sqrt(math.pi) * max(float(sigma_px), _MIN_SIGMA))


def find_dots(
    dot_image: ArrayLike,
    noise_sigma: float,
    dot_size_px: float,
    *,
    k_sigma: float = DEFAULT_DOT_K_SIGMA,
) -> DotCentres:
    """The centres of the dots of a dot image.

    Parameters
    ----------
    dot_image : (H, W) float, the dots on a zero background (e.g. ``extract_slits(img).dots``)
    noise_sigma : float, intensity units, the noise sigma of the unsmoothed image (e.g.
        ``SlitExtraction.noise_sigma``)
    dot_size_px : float, px, the dots' FWHM
    k_sigma : float, the threshold in noise sigmas of the smoothed image; default 4

    Returns
    -------
    DotCentres (empty when there are none)

    Raises
    ------
    SlitExtractionError
        ``dot_image`` is not a 2-D array, or a parameter is not a positive finite number.
    """
    d = np.asarray(dot_image)
    if d.ndim != 2 or d.size == 0:
        raise SlitExtractionError(f"dot_image must be a non-empty 2-D array, got shape {d.shape}")
    for name, x in (("noise_sigma", noise_sigma), ("dot_size_px", dot_size_px)):
        if not (isinstance(x, int | float | np.floating) and math.isfinite(x) and x > 0):
            raise SlitExtractionError(f"{name} must be a positive number, got {x!r}")
    if not (math.isfinite(k_sigma) and k_sigma >= 0):
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma!r}")
    sigma = max(_MIN_SIGMA, float(dot_size_px) / FWHM_PER_SIGMA)
    thr = np.float32(k_sigma * smoothed_noise(noise_sigma, sigma))
    floor = 1e-3 * float(thr) if thr > 0 else 1e-6
    # the smoothing and its maxima a strip of rows at a time, while the strip is in the cache:
    # each strip smoothed with the rows its kernel and the maxima reach beyond it, so its own
    # rows take the values the whole image's smoothing gives them
    src, g = _filterable(d), _gaussian_kernel(sigma)
    h = d.shape[0]
    reach = len(g) // 2 + 1
    u, v, peak = np.empty(_PEAKS_FIRST), np.empty(_PEAKS_FIRST), np.empty(_PEAKS_FIRST)
    n = 0
    for r0 in range(0, h, _STRIP_ROWS):
        r1 = min(r0 + _STRIP_ROWS, h)
        a, b = max(r0 - reach, 0), min(r1 + reach, h)
        s = cv2.sepFilter2D(src[a:b], cv2.CV_32F, g, g)
        while True:
            m = _local_maxima(s, max(r0, 1) - a, min(r1, h - 1) - a, a, thr, floor, u, v, peak, n)
            if m <= len(u):
                break
            u, v, peak = (np.concatenate([x[:n], np.empty(2 * m - n)]) for x in (u, v, peak))
        n = m
    return DotCentres(u[:n], v[:n], peak[:n])


#: :func:`find_dots` makes room for this many dots first (more: it makes room for twice those
#: found when they fill it) ...
_PEAKS_FIRST = 1 << 14
#: ... and smooths the dot image and finds its maxima this many rows at a time.
_STRIP_ROWS = 128


def gaussian_f32(img: NDArray, sigma: float) -> F32:
    """(H, W) float32: ``img`` (H, W) smoothed by a Gaussian of ``sigma`` px reaching
    :data:`_GAUSS_REACH` sigmas (OpenCV's kernel size for 8-bit data; reflected at the border),
    8- and 16-bit data filtered straight into float32, without a float copy first."""
    g = _gaussian_kernel(sigma)
    return cv2.sepFilter2D(_filterable(img), cv2.CV_32F, g, g)


def _gaussian_kernel(sigma: float) -> F32:
    """(T, 1) float32: :func:`gaussian_f32`'s Gaussian, T = 2 * 3 sigma + 1 rounded to odd."""
    return cv2.getGaussianKernel(round(2.0 * _GAUSS_REACH * sigma + 1.0) | 1, sigma, cv2.CV_32F)


def _filterable(img: NDArray) -> NDArray:
    """``img`` as OpenCV's filters read it: 8- and 16-bit data as they are, the rest float32."""
    return img if img.dtype in (np.uint8, np.uint16) else img.astype(np.float32, copy=False)


#: :func:`gaussian_f32`'s kernel reaches this many sigmas either side (its tails beyond hold
#: under 0.3 % of its weight).
_GAUSS_REACH = 3.0


def _nan_near_clipped(img: NDArray, level: float | None, radius: int, out: F32) -> None:
    """NaN into ``out`` (H, W) at the pixels within the disc of ``radius`` px (OpenCV's
    elliptic structuring element) of every pixel of ``img`` (H, W) at or above ``level`` (None:
    none): a smoothing of ``img`` does not show a dot there."""
    if level is None:
        return
    clipped = cv2.compare(img, float(level), cv2.CMP_GE)
    if not cv2.countNonZero(clipped):
        return
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    out[cv2.dilate(clipped, disc) > 0] = np.nan


@njit(cache=True)
def _local_maxima(s, r_lo, r_hi, row0, thr, floor, u, v, peak, n):
    """The local maxima of ``s`` (R, W) in its rows ``r_lo`` to ``r_hi`` - 1 above ``thr`` (at
    least each of their 8 neighbours; not in the first or last column), row by row: their
    centres (:func:`_log_vertex` along each axis, the values taken as at least ``floor``; the
    rows counted from ``row0``) into ``u``, ``v`` and ``s`` there into ``peak`` (C,) each from
    entry ``n`` on; returns ``n`` and how many there are (more than C: up to C written). Each
    row's maxima are marked first in a loop without branches, which the compiler vectorises."""
    w = s.shape[1]
    cap = u.shape[0]
    nw = (w + 7) // 8
    mark = np.zeros(8 * nw, np.uint8)
    words = mark.view(np.uint64)  # the marks 8 at a time: the rows' empty stretches skipped
    for r in range(r_lo, r_hi):
        up, row, down = s[r - 1], s[r], s[r + 1]
        for c in range(1, w - 1):
            x = row[c]
            mark[c] = (
                (x > thr) & (x >= row[c - 1]) & (x >= row[c + 1]) & (x >= up[c - 1])
                & (x >= up[c]) & (x >= up[c + 1]) & (x >= down[c - 1]) & (x >= down[c])
                & (x >= down[c + 1])
            )  # fmt: skip
        for k in range(nw):
            if words[k] == 0:
                continue
            for c in range(8 * k, 8 * k + 8):
                if mark[c] == 0:
                    continue
                if n < cap:
                    x = row[c]
                    lc = math.log(max(x, floor))
                    u[n] = c + _log_vertex(
                        math.log(max(row[c - 1], floor)), lc, math.log(max(row[c + 1], floor))
                    )
                    dv = _log_vertex(math.log(max(up[c], floor)), lc, math.log(max(down[c], floor)))
                    v[n] = row0 + r + dv
                    peak[n] = x
                n += 1
    return n


@njit(cache=True, inline="always")
def _log_vertex(a, b, c):
    """Offset (-0.5..0.5) of the vertex of the parabola through (-1, a), (0, b), (1, c); 0 where
    it opens upwards."""
    den = a - 2.0 * b + c
    if not den < 0.0:
        return 0.0
    return min(max(0.5 * (a - c) / den, -0.5), 0.5)


def near_stripes(u: F64, v: F64, shape: tuple[int, int], radius_px: float) -> NDArray[np.bool_]:
    """(H, W) bool: the pixels closer than ``radius_px`` to a stripe centre (``u``, ``v`` (K,)
    px, rounded to pixels), by OpenCV's distance transform (``DIST_L2``, 3 x 3 mask): the
    centres' pixels dilated by the offsets at less than that distance, without the distance
    map of the whole image."""
    h, w = shape
    r = np.clip(np.rint(v).astype(np.intp), 0, h - 1)
    c = np.clip(np.rint(u).astype(np.intp), 0, w - 1)
    marks = np.zeros((h, w), np.uint8)
    marks[r, c] = 1
    # the offsets: the same distance transform from one centre (it never steps outside the
    # square of the offset, so the image's edges do not change it)
    n = int(math.ceil(max(float(radius_px), 0.0) / 0.9)) + 1
    one = np.full((2 * n + 1, 2 * n + 1), 255, np.uint8)
    one[n, n] = 0
    ball = (cv2.distanceTransform(one, cv2.DIST_L2, 3) < radius_px).astype(np.uint8)
    return cv2.dilate(marks, ball) > 0


def point_grid(
    u: F64, v: F64, shape: tuple[int, int], cell: float
) -> tuple[NDArray[np.intp], NDArray[np.intp], int, int]:
    """Points (``u``, ``v`` (M,) px) in a grid of ``cell`` px over an image of ``shape`` (H, W):
    (order (M,), cell_start (C+1,), nx, ny): the points of cell (cy, cx) are
    ``order[cell_start[cy*nx+cx]:cell_start[cy*nx+cx+1]]`` (those outside the image in the
    cells at its edges)."""
    h, w = shape
    nx, ny = max(1, math.ceil(w / cell)), max(1, math.ceil(h / cell))
    order = np.empty(len(u), np.intp)
    start = np.zeros(nx * ny + 1, np.intp)
    _bucket(np.asarray(u, np.float64), np.asarray(v, np.float64), float(cell), nx, ny, order, start)
    return order, start, nx, ny


@njit(cache=True)
def _bucket(u, v, cell, nx, ny, order, start):
    """:func:`point_grid`'s cells, by a counting sort (the points of a cell in their order):
    ``order`` (M,) and ``start`` (C + 1,), zero on entry."""
    n = u.shape[0]
    key = np.empty(n, np.intp)
    for i in range(n):
        cx = min(max(int(u[i] / cell), 0), nx - 1)
        cy = min(max(int(v[i] / cell), 0), ny - 1)
        key[i] = cy * nx + cx
        start[key[i] + 1] += 1
    for g in range(nx * ny):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[key[i]]] = i
        fill[key[i]] += 1


@njit(cache=True)
def _speckle_test(du, dv, dpeak, zone, pr, pc, peak, disc, order, start, nx, ny, cell, min_ratio,
                  keep, near):  # fmt: skip
    """Per dot (``du``, ``dv`` px, ``dpeak`` (M,)): whether its pixel is ``near`` a stripe
    (``zone`` (H, W) uint8 set there) and whether to ``keep`` it (M,) each: clear of the
    stripes, or its peak at least ``min_ratio`` of the largest stripe ``peak`` (K,) whose
    centre's pixel (``pr``, ``pc``) (K,) lies at an offset where ``disc`` (2R+1, 2R+1) is set
    (0 where none does); the centres' pixels in the grid (``order``, ``start``, ``nx``, ``ny``)
    of ``cell`` px (:func:`point_grid`)."""
    h, w = zone.shape
    rad = disc.shape[0] // 2
    for i in range(du.shape[0]):
        r = min(max(int(np.rint(dv[i])), 0), h - 1)
        c = min(max(int(np.rint(du[i])), 0), w - 1)
        near[i] = zone[r, c] != 0
        if not near[i]:
            keep[i] = True
            continue
        best = 0.0
        cx0 = max(0, int((c - rad) / cell))
        cx1 = min(nx - 1, int((c + rad) / cell))
        cy0 = max(0, int((r - rad) / cell))
        cy1 = min(ny - 1, int((r + rad) / cell))
        for cy in range(cy0, cy1 + 1):
            for cx in range(cx0, cx1 + 1):
                g = cy * nx + cx
                for e in range(start[g], start[g + 1]):
                    k = order[e]
                    dr = pr[k] - r
                    dc = pc[k] - c
                    if abs(dr) <= rad and abs(dc) <= rad and disc[dr + rad, dc + rad]:
                        best = max(best, peak[k])
        keep[i] = dpeak[i] >= min_ratio * best


def dots_off_stripes(
    dots: DotCentres,
    near_zone: NDArray[np.bool_],
    u: F64,
    v: F64,
    peak: F64,
    clearance_px: float,
    min_ratio: float,
) -> tuple[DotCentres, NDArray[np.bool_]]:
    """The dots that are not speckle on a stripe, and which of them lie near one.

    Speckle on a stripe leaves dot-like peaks in the dot image, weaker than a dot: a dot in
    ``near_zone`` (H, W) (:func:`near_stripes` at ``clearance_px``) is kept only when its peak
    is at least ``min_ratio`` times the largest stripe peak within ``clearance_px`` of it (the
    stripe centres ``u``, ``v`` (K,) px and their ``peak`` (K,), read at those dots only).

    Returns
    -------
    kept : DotCentres
    near : (M',) bool, the kept dots in ``near_zone``
    """
    h, w = near_zone.shape
    # the stripe centres' pixels, in a grid of cells about the disc's size
    rad = max(1, int(math.ceil(clearance_px)))
    pr = np.clip(np.rint(v).astype(np.intp), 0, h - 1)
    pc = np.clip(np.rint(u).astype(np.intp), 0, w - 1)
    cell = float(2 * rad + 1)
    order, start, nx, ny = point_grid(pc, pr, (h, w), cell)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
    keep = np.empty(len(dots), bool)
    near = np.empty(len(dots), bool)
    _speckle_test(dots.u, dots.v, dots.peak, np.ascontiguousarray(near_zone).view(np.uint8), pr,
                  pc, np.asarray(peak, np.float64), disc, order, start, nx, ny, cell,
                  float(min_ratio), keep, near)  # fmt: skip
    return dots.subset(keep), near[keep]


# --------------------------------------------------------------------------- the dots' response
#: The dots' response compares the image, smoothed by a dot's Gaussian, at a place with its mean
#: this many smoothing sigmas (plus one px) before and after the place along the stripes'
#: direction: a stripe, a smooth background and their gradients across the stripe cancel, a dot
#: stands out.
RESPONSE_REACH = 2.5
#: Level bins of the response's noise table, per zone (clear of the stripes, near one) ...
_NOISE_BINS = 12
#: ... measured at this many places beside the stripes (at most).
_NOISE_SAMPLES = 12000
#: A bin's noise is never taken as less than this share of its zone's median.
_NOISE_FLOOR = 0.25
#: The noise table is read through a look-up of this many levels per zone.
_LUT = 256


@njit(cache=True, inline="always")
def _bilinear(img, u, v):
    """``img`` (H, W) at (u, v) px, bilinear; NaN outside."""
    h, w = img.shape
    if not (u >= 0.0 and u <= w - 1.0 and v >= 0.0 and v <= h - 1.0):
        return np.nan
    c = min(int(u), w - 2)
    r = min(int(v), h - 2)
    fu = u - c
    fv = v - r
    top = img[r, c] + fu * (img[r, c + 1] - img[r, c])
    bot = img[r + 1, c] + fu * (img[r + 1, c + 1] - img[r + 1, c])
    return top + fv * (bot - top)


@njit(cache=True, inline="always")
def response_at(smoothed, u, v, su, sv, reach):
    """The dots' response at (u, v) px and the level it stands on: ``smoothed`` there less
    its mean at ``reach`` px before and after along the stripes' direction (``su``, ``sv``: the
    unit direction in the image), and that mean. NaN where a sample leaves the image or lies
    on a saturated place (NaN in ``smoothed``)."""
    a = _bilinear(smoothed, u, v)
    b = _bilinear(smoothed, u - reach * su, v - reach * sv)
    c = _bilinear(smoothed, u + reach * su, v + reach * sv)
    level = 0.5 * (b + c)
    return a - level, level


@njit(cache=True)
def _responses(smoothed, u, v, su, sv, reach, out, level):
    for i in range(len(u)):
        out[i], level[i] = response_at(smoothed, u[i], v[i], su[i], sv[i], reach)


@njit(cache=True)
def z_many(smoothed, u, v, su, sv, zone, n, reach, lut_lo, lut_scale, lut_offset, lut_inv_sigma,
           z, inv):  # fmt: skip
    """The dots' response at the places (``u[i]``, ``v[i]``) px, i < ``n`` (:func:`response_at`,
    along the directions ``su``, ``sv``) in noise sigmas of each place's ``zone`` (0 clear of
    the stripes, 1 near one) and level, into ``z``, and the inverse of that noise (1 /
    intensity units) into ``inv``; NaN, 0 where it cannot be read. One loop without branches
    on the data, which the compiler vectorises."""
    top = lut_offset.shape[1] - 1.0
    for i in range(n):
        r, level = response_at(smoothed, u[i], v[i], su[i], sv[i], reach)
        ok = np.isfinite(r)
        zn = np.intp(zone[i])
        x = (level - lut_lo[zn]) * lut_scale[zn]
        k = int(min(max(x if ok else 0.0, 0.0), top))
        s = lut_inv_sigma[zn, k]
        zi = (r - lut_offset[zn, k]) * s
        z[i] = zi if ok else np.nan
        inv[i] = s if ok else 0.0


@dataclass(frozen=True, eq=False)
class DotResponse:
    """How strongly each place of a frame looks like a dot, in noise sigmas.

    The image is smoothed by a Gaussian of the dot's size (the matched filter of a Gaussian
    spot); the response at a place is the smoothed image there less its mean at
    ``reach_px`` before and after the place along the stripes' direction. A stripe and a smooth
    background cancel; a dot stands out, however faint, and is not thresholded away: the
    identification reads the response where its hypotheses put dots. Its noise is measured on
    the frame beside the stripes, per zone (clear of the stripes, near one: speckle on a stripe
    is noise there) and per level of the smoothed image (shot noise grows with it), and read
    through a look-up table of the level.

    Attributes
    ----------
    smoothed : (H, W) float32, the image plane smoothed by the dot's Gaussian (intensity
        units); NaN near saturated pixels (a dot cannot be seen there)
    reach_px : px, how far along the stripe the response compares
    edges : (2, B + 1) float32, per zone, the level bins of ``smoothed``
    offset, sigma : (2, B) float32, per zone and level bin, the median and the robust sigma
        of the response at places beside the stripes (intensity units)
    lut_lo, lut_scale : (2,) float64, per zone: level ``x`` is read at entry
        ``(x - lut_lo) * lut_scale`` of ...
    lut_offset, lut_inv_sigma : (2, L) float64, ... the bins' median and inverse sigma
    """

    smoothed: F32
    reach_px: float
    edges: F32
    offset: F32
    sigma: F32
    lut_lo: F64
    lut_scale: F64
    lut_offset: F64
    lut_inv_sigma: F64

    def kernel_args(self) -> tuple:
        """What the compiled kernels read (:func:`z_many`): (smoothed, reach, lut_lo, lut_scale,
        lut_offset, lut_inv_sigma)."""
        return (
            self.smoothed,
            float(self.reach_px),
            self.lut_lo,
            self.lut_scale,
            self.lut_offset,
            self.lut_inv_sigma,
        )

    def at(self, u: ArrayLike, v: ArrayLike, angle: ArrayLike) -> tuple[F64, F64]:
        """The response at (u, v) px along the stripe direction ``angle`` (rad from the
        image's vertical, as :attr:`~multislit.stripes.SlitExtraction.angle`), and the level it
        stands on (:func:`response_at`): (M,) float64 each, intensity units, NaN outside the
        image or near saturated pixels."""
        u = np.ascontiguousarray(u, np.float64).ravel()
        v = np.ascontiguousarray(v, np.float64).ravel()
        a = np.broadcast_to(np.asarray(angle, np.float64), u.shape)
        out = np.empty(u.size)
        level = np.empty(u.size)
        _responses(self.smoothed, u, v, np.sin(a), np.cos(a), self.reach_px, out, level)
        return out, level

    def z(self, u: ArrayLike, v: ArrayLike, angle: ArrayLike, near: ArrayLike) -> F64:
        """(M,) float64: the response at (u, v) in noise sigmas of its zone (``near`` (M,)
        bool: near a stripe) and level (:func:`z_many`); NaN where it cannot be read."""
        u = np.ascontiguousarray(u, np.float64).ravel()
        v = np.ascontiguousarray(v, np.float64).ravel()
        a = np.broadcast_to(np.asarray(angle, np.float64), u.shape)
        zone = np.ascontiguousarray(np.broadcast_to(np.asarray(near, bool), u.shape), np.intp)
        out = np.empty(u.size)
        z_many(self.smoothed, u, v, np.sin(a), np.cos(a), zone, u.size, *self.kernel_args()[1:],
               out, np.empty(u.size))  # fmt: skip
        return out


@njit(cache=True)
def _response_noise(x, level, zone, fallback, edges, offset, sig):
    """:class:`DotResponse`'s noise per zone and level bin from the response ``x`` at places
    beside the stripes, sorted by their ``level`` (M,), in ``zone`` (M,) (0 clear, 1 near a
    stripe): per zone, bins of equal counts (``edges`` (2, B + 1): the levels' quantiles,
    linear between the sorted levels, the first and last the float32 extremes), each bin's
    median (``offset`` (2, B)) and robust sigma (``sig`` (2, B): 1.4826 median absolute
    deviations, at least :data:`_NOISE_FLOOR` of the zone's median). A zone with fewer than 4
    places a bin takes every place; with fewer in all, edges 0..1 and the ``fallback`` sigma.
    The bins without places keep offset 0 and sigma 1, as given."""
    nb = offset.shape[1]
    e = np.empty(nb + 1)
    for z in range(2):
        sel = np.flatnonzero(zone == z)
        if sel.shape[0] < 4 * nb:  # too few places: every one
            sel = np.arange(x.shape[0])
        m = sel.shape[0]
        if m < 4 * nb:
            for i in range(nb + 1):
                edges[z, i] = i / nb
            sig[z, :] = fallback
            continue
        xs = x[sel]
        ls = level[sel]
        for i in range(nb + 1):
            pos = (m - 1) * (i / nb)
            lo = min(int(pos), m - 1)
            hi = min(lo + 1, m - 1)
            e[i] = ls[lo] + (pos - lo) * (ls[hi] - ls[lo])
        e[0] = -np.inf
        e[nb] = np.inf
        start = np.searchsorted(ls, e)  # the levels sorted: each bin is a run of them
        for j in range(nb):
            a, b = start[j], start[j + 1]
            if b > a:
                med = np.median(xs[a:b])
                offset[z, j] = med
                sig[z, j] = 1.4826 * np.median(np.abs(xs[a:b] - med))
        floor = _NOISE_FLOOR * max(np.median(sig[z]), 1e-12)
        for j in range(nb):
            sig[z, j] = max(sig[z, j], floor)
        for i in range(nb + 1):
            edges[z, i] = min(max(e[i], -_F32_MAX), _F32_MAX)


#: The largest float32.
_F32_MAX = float(np.finfo(np.float32).max)


def places_beside_stripes(
    u: F64, v: F64, angle: F64, spread_px: float, n: int, seed: int = 0
) -> tuple[F64, F64, F64]:
    """Places beside the stripes, where a frame's noise is measured: ``n`` of the stripe
    centres (``u``, ``v`` (K,) px) taken at random (every one when there are fewer), each moved
    across its stripe (``angle`` (K,) rad from the image's vertical; NaN: vertical) by up to
    ``spread_px`` either way; the same places for the same centres and ``seed``.

    Returns
    -------
    u, v : (M,) float64, px
    angle : (M,) float64, rad, the stripe's direction there (0 where unknown)
    """
    pick, off = _beside_draw(len(u), n, spread_px, seed)
    pu, pv, a = np.empty(len(pick)), np.empty(len(pick)), np.empty(len(pick))
    _beside(u, v, np.asarray(angle, np.float64), pick, off, pu, pv, a)
    return pu, pv, a


def _beside_draw(k: int, n: int, spread_px: float, seed: int) -> tuple[NDArray[np.intp], F64]:
    """:func:`places_beside_stripes`' draw: ``n`` of ``k`` stripe centres at random (every one
    when there are fewer), (M,) intp, and their offsets across the stripe (M,) px."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(k, size=min(k, n), replace=False) if k else np.zeros(0, np.intp)
    return pick.astype(np.intp, copy=False), rng.uniform(-spread_px, spread_px, len(pick))


@njit(cache=True, inline="always")
def _beside_at(u, v, angle, k, off):
    """Stripe centre ``k`` (of ``u``, ``v``, ``angle`` (K,)) moved ``off`` px across its
    stripe: the place (u, v) px and the stripe's direction there (0 where unknown)."""
    a = angle[k] if np.isfinite(angle[k]) else 0.0
    return u[k] + off * math.cos(a), v[k] - off * math.sin(a), a


@njit(cache=True)
def _beside(u, v, angle, pick, off, pu, pv, a):
    """:func:`_beside_at` of the centres ``pick`` (M,) by ``off`` (M,) into ``pu``, ``pv``,
    ``a`` (M,)."""
    for i in range(pick.shape[0]):
        pu[i], pv[i], a[i] = _beside_at(u, v, angle, pick[i], off[i])


@njit(cache=True)
def _beside_responses(smoothed, reach, u, v, angle, pick, off, zone_map, resp, level, zone):
    """The dots' response (:func:`response_at`) and its level at the places beside the stripes
    (:func:`_beside_at` of the distinct centres ``pick`` (M,) by ``off`` (M,)), taken in the
    centres' order (the image read as it lies in memory, by row), into ``resp``, ``level``
    (M,), and their zone (``zone_map`` (H, W) uint8 at their pixel) into ``zone`` (M,)."""
    h, w = zone_map.shape
    slot = np.full(u.shape[0], -1, np.int64)
    for i in range(pick.shape[0]):
        slot[pick[i]] = i
    i = 0
    for k in range(u.shape[0]):
        j = slot[k]
        if j < 0:
            continue
        pu, pv, a = _beside_at(u, v, angle, k, off[j])
        resp[i], level[i] = response_at(smoothed, pu, pv, math.sin(a), math.cos(a), reach)
        r = min(max(int(np.rint(pv)), 0), h - 1)
        c = min(max(int(np.rint(pu)), 0), w - 1)
        zone[i] = zone_map[r, c]
        i += 1


def stripe_spacing(u: F64, v: F64) -> float:
    """px, the median gap between neighbouring stripe centres (``u``, ``v`` (K,) px) along the
    rows (NaN: none)."""
    row = np.rint(v).astype(np.intp)
    o = np.lexsort((u, row))
    du = np.diff(u[o])
    same = (np.diff(row[o]) == 0) & (du > 2.0)
    return float(np.median(du[same])) if same.any() else float("nan")


def dot_response(
    plane: ArrayLike,
    dot_size_px: float,
    u: F64,
    v: F64,
    angle: F64,
    near_zone: NDArray[np.bool_],
    spread_px: float,
    saturation_level: float | None = None,
) -> DotResponse:
    """The dots' response of a frame (:class:`DotResponse`), its noise measured beside the
    stripes.

    Parameters
    ----------
    plane : (H, W) the image plane (e.g. :attr:`~multislit.stripes.SlitExtraction.plane`)
    dot_size_px : px, the dots' FWHM
    u, v : (K,) float64, px, stripe centres
    angle : (K,) float64, rad, the stripes' direction at the centres (NaN: taken as vertical)
    near_zone : (H, W) bool, the places near a stripe
    spread_px : px, the noise is measured at places up to this far across the stripes from
        their centres (about half the slits' spacing)
    saturation_level : the plane's saturation level; None: none (float data) ...
    """
    img = np.asarray(plane)
    sigma = max(_MIN_SIGMA, float(dot_size_px) / FWHM_PER_SIGMA)
    sm = gaussian_f32(img, sigma)
    reach = RESPONSE_REACH * sigma + 1.0
    _nan_near_clipped(img, saturation_level, int(math.ceil(2.0 * sigma)), sm)
    # the noise, beside the stripes
    pick, off = _beside_draw(len(u), _NOISE_SAMPLES, spread_px, 0)
    resp, level = np.empty(len(pick)), np.empty(len(pick))
    zone = np.empty(len(pick), np.uint8)
    _beside_responses(sm, reach, u, v, np.asarray(angle, np.float64), pick, off,
                      np.ascontiguousarray(near_zone).view(np.uint8), resp, level, zone)  # fmt: skip
    ok = np.isfinite(resp) & np.isfinite(level)
    x, lv, zone = resp[ok], level[ok], zone[ok]
    o = np.argsort(lv)
    edges = np.zeros((2, _NOISE_BINS + 1), np.float32)
    offset = np.zeros((2, _NOISE_BINS), np.float32)
    sig = np.ones((2, _NOISE_BINS), np.float32)
    _response_noise(x[o], lv[o], zone[o], smoothed_noise(1.0, sigma), edges, offset, sig)
    # the look-up: _LUT levels over twice the span of the inner edges, each reading its bin
    lut_lo = np.zeros(2)
    lut_scale = np.ones(2)
    lut_off = np.zeros((2, _LUT))
    lut_inv = np.zeros((2, _LUT))
    for z in (0, 1):
        inner = edges[z, 1:-1].astype(np.float64)
        lo, hi = float(inner[0]), float(inner[-1])
        if not hi > lo:
            hi = lo + 1.0
        lut_lo[z] = lo - 0.5 * (hi - lo)
        lut_scale[z] = _LUT / (2.0 * (hi - lo))
        x = lut_lo[z] + (np.arange(_LUT) + 0.5) / lut_scale[z]
        b = np.clip(np.searchsorted(edges[z], x, side="right") - 1, 0, _NOISE_BINS - 1)
        lut_off[z] = offset[z, b]
        lut_inv[z] = 1.0 / sig[z, b]
    return DotResponse(sm, float(reach), edges, offset, sig, lut_lo, lut_scale, lut_off, lut_inv)


# ------------------------------------------------------------ the dots as spots, fitted jointly
#: The sharp response smooths the image by a Gaussian of this sigma (px): the least that keeps
#: its noise from being one pixel's.
SHARP_SIGMA = 0.5
#: The sharp response compares a place with the mean this many first spot sigmas (plus one px)
#: before and after it along the stripes: clear of the dot's own light.
_SHARP_REACH = 2.5
#: A spot's sigma on the sharp response is first taken as this many times the dots' Gaussian
#: sigma (from their FWHM; a dot's tails reach farther), combined with :data:`SHARP_SIGMA`, then
#: fitted: the trial factors, on up to _SIGMA_MAX_DOTS spots of at least _SIGMA_Z noise sigmas
#: with no other spot within _SIGMA_CLEAR first sigmas (at least _SIGMA_MIN_DOTS of them).
_SIZE_GUESS = 1.2
_SIGMA_TRIALS = (0.7, 0.85, 1.0, 1.2, 1.45, 1.75)
_SIGMA_Z = 8.0
_SIGMA_CLEAR = 5.0
_SIGMA_MIN_DOTS = 20
_SIGMA_MAX_DOTS = 200
#: A spot is drawn out to this many of its sigma, its radial profile tabulated every
#: SPOT_PROFILE_STEP px.
_PROFILE_SIGMAS = 3.0
SPOT_PROFILE_STEP = 0.05
#: Half side of the square of pixels each spot is fitted to (px).
SPOT_FIT_HALF = 3
#: A step of a spot's centre in one round is at most this (px), and the rounds take this share
#: of each step.
_MAX_STEP = 0.5
_DAMPING = 1.0
#: A place is a spot's first guess when the sharp response there is a local maximum of at
#: least this many noise sigmas ...
_DETECT_Z = 3.0
#: ... and a place where the response less every fitted spot still is, at least _ADD_CLEAR
#: sigmas from every spot and above _ADD_SHARE of the fitted spots there (their shape is not
#: exactly a Gaussian's), gets one more spot.
_ADD_Z = 3.0
_ADD_CLEAR_SIGMAS = 1.0
_ADD_SHARE = 0.5
#: The spots added, and the spots within this many sigmas of them, are fitted again (the others
#: held).
_ACTIVE_SIGMAS = 2.5
#: Rounds of the joint fit before the spots are added, and of the added spots and their
#: neighbours after.
_ROUNDS = (2, 10)
#: :func:`centre_dots` measures the sharp response's noise at (up to) this many places beside
#: the stripes, taking each stripe centre at most _SHARP_NOISE_ROUNDS times.
_SHARP_NOISE_PLACES = 50000
_SHARP_NOISE_ROUNDS = 8
#: The places of :func:`sharp_response` are resampled in rows of this many.
_REMAP_ROW = 4096
#: A given dot is the spot nearest it (and it the given dot nearest that spot) within this
#: many px; else it keeps its centre.
_MAX_SHIFT_PX = 1.0
#: :func:`centre_dots` fits the spots within this many px of the given dots: every spot whose
#: light reaches a given dot's square of fitted pixels.
_REGION_PX = 2 * SPOT_FIT_HALF + 1
#: A spot whose fitted height is below this many of its standard errors shows no dot.
SPOT_KEEP_Z = 2.0


def sharp_image(plane: ArrayLike, saturation_level: float | None = None) -> F32:
    """(H, W) float32: the image plane smoothed by a Gaussian of :data:`SHARP_SIGMA` px, NaN
    within a pixel or two of the pixels at or above ``saturation_level`` (None: none)."""
    img = np.asarray(plane)
    sharp = gaussian_f32(img, SHARP_SIGMA)
    _nan_near_clipped(img, saturation_level, int(math.ceil(2.0 * SHARP_SIGMA)) + 1, sharp)
    return sharp


@dataclass(frozen=True, eq=False)
class SharpResponse:
    """The dots' sharp response of one image, ready for fitting spots to it
    (:func:`sharp_response`).

    On it a dot is a round spot (a Gaussian's radial profile ``profile``) with two negative
    copies of half its height ``reach`` px before and after it along the stripe (the mean it
    is compared with).

    Attributes
    ----------
    response : (H, W) float64, the image smoothed by :data:`SHARP_SIGMA` less its mean
        ``reach`` px before and after along the stripes, less its median at its zone and level
        (intensity units; 0 where unknown)
    valid : (H, W) bool, where it is known (inside the image and the places asked for, clear
        of saturated pixels)
    sigma : (H, W) float64, its noise sigma at each pixel (per zone and level)
    angle : (H, W) float64, rad, the stripes' direction from the image's vertical
    profile : (L,) float64, the spots' radial profile (a Gaussian's: 1 at the centre, every
        :data:`SPOT_PROFILE_STEP` px, 0 at the end)
    reach : px, how far along the stripe it compares
    profile_sigma : px, the sigma of the Gaussian the profile is made from
    z_scale : the spread of a spot's height in its standard errors fitted at places taken at
        random (the noise is correlated over neighbouring pixels): :meth:`spot_fit` scales by it
    """

    response: F64
    valid: NDArray[np.bool_]
    sigma: F64
    angle: F64
    profile: F64
    reach: float
    profile_sigma: float
    z_scale: float = 1.0

    def with_profile(self, sigma_px: float) -> SharpResponse:
        """The response with the spots' profile of a Gaussian of ``sigma_px`` px."""
        return replace(self, profile=gaussian_profile(sigma_px), profile_sigma=float(sigma_px))

    @property
    def spot_sigma(self) -> float:
        """px, the radius at which the profile falls to exp(-1/2) (a Gaussian's sigma)."""
        p = self.profile
        i = int(np.argmax(p < math.exp(-0.5))) if np.any(p < math.exp(-0.5)) else len(p) - 1
        if i == 0:
            return SPOT_PROFILE_STEP
        f = (p[i - 1] - math.exp(-0.5)) / max(p[i - 1] - p[i], 1e-12)
        return (i - 1 + f) * SPOT_PROFILE_STEP

    def spot_fit(self, uv: F64) -> tuple[F64, F64]:
        """A spot fitted at each place ``uv`` (M, 2) px, its centre held there: its height in
        standard errors, and the standard error (intensity units), both with the noise's
        spread :attr:`z_scale` (M,) each; NaN where no pixel is known."""
        uv = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
        z = np.full(len(uv), np.nan)
        se = np.full(len(uv), np.nan)
        _spot_z(
            self.response,
            self.valid,
            self.sigma,
            self.angle,
            uv,
            self.profile,
            self.reach,
            SPOT_FIT_HALF,
            z,
            se,
        )
        return z / self.z_scale, se * self.z_scale

    def model(self, P: F64, A: F64) -> F64:
        """(H, W) float64: the spots of heights ``A`` (N,) centred at ``P`` (N, 2) px."""
        out = np.zeros(self.response.shape)
        splat_spots(P, A, self.angle, self.profile, self.reach, out)
        return out


def sharp_response(
    sharp: F32,
    angle: NDArray,
    near: NDArray[np.bool_],
    dot_sigma_px: float,
    where: NDArray[np.bool_] | None = None,
    beside: tuple[F64, F64, F64] | None = None,
) -> SharpResponse:
    """The sharp response of an image (:class:`SharpResponse`), its spots' profile the first
    guess of their size, less its median per zone and level, its noise measured per zone and
    level (the robust sigma of :data:`_NOISE_BINS` level bins).

    Parameters
    ----------
    sharp : (H, W) float32, :func:`sharp_image` of the image
    angle : (H, W) float, rad, the stripes' direction at each place (finite everywhere)
    near : (H, W) bool, the places near a stripe (closer than :data:`STRIPE_CLEARANCE` stripe
        widths to a centre)
    dot_sigma_px : px, the dots' Gaussian sigma in the image (from their FWHM)
    where : (H, W) bool, the places where the response is wanted (None: everywhere)
    beside : (u, v, angle) (M,) float64 each (px, px, rad): places at which its median and
        noise are measured (:func:`places_beside_stripes`); None: at the places of the response
    """
    h, w = sharp.shape
    sg0 = _first_sigma(dot_sigma_px)
    reach = _SHARP_REACH * sg0 + 1.0
    near = np.asarray(near, bool)
    if where is None:
        ys, xs = np.mgrid[:h, :w].astype(np.float32)
        level = _level_along(sharp, xs, ys, np.asarray(angle, np.float32), reach).ravel()
        r = sharp.ravel() - level
        zone = near.ravel()
    else:
        flat = np.flatnonzero(where)
        ys, xs = np.divmod(flat, w)
        level = _level_along(sharp, xs, ys, np.asarray(angle).ravel()[flat], reach)
        r = sharp.ravel()[flat] - level
        zone = near.ravel()[flat]
    if beside is None:
        tables = _noise_tables(level, r, zone)
    else:
        # at their pixels, as the response's places (interpolating between pixels would
        # smooth the noise)
        bu, bv, ba = (np.asarray(x, np.float64) for x in beside)
        iv = np.clip(np.rint(bv).astype(np.intp), 0, h - 1)
        iu = np.clip(np.rint(bu).astype(np.intp), 0, w - 1)
        b_level = _level_along(sharp, iu, iv, ba, reach)
        tables = _noise_tables(b_level, sharp[iv, iu] - b_level, near[iv, iu])
    sig = np.full(len(r), np.nan, np.float32)
    ok = np.isfinite(r)
    for z, table in enumerate(tables):
        if table is None:
            continue
        e, med, s_ = table
        m = ok & (zone == z)
        b_ = np.clip(np.searchsorted(e, level[m], side="right") - 1, 0, _NOISE_BINS - 1)
        sig[m] = s_[b_]
        r[m] -= med[b_].astype(np.float32)
    fallback = float(np.nanmedian(sig)) if np.isfinite(sig).any() else 1.0
    sig[~np.isfinite(sig)] = fallback
    if where is None:
        response = np.nan_to_num(r).astype(np.float64).reshape(h, w)
        valid = np.isfinite(r).reshape(h, w)
        sigma = sig.astype(np.float64).reshape(h, w)
    else:
        response = np.zeros((h, w))
        valid = np.zeros((h, w), bool)
        sigma = np.full((h, w), fallback)
        response.ravel()[flat] = np.nan_to_num(r)
        valid.ravel()[flat] = np.isfinite(r)
        sigma.ravel()[flat] = sig
    ang = np.asarray(angle, np.float64)
    return SharpResponse(response, valid, sigma, ang, gaussian_profile(sg0), float(reach), sg0)


def _noise_tables(level: F32, r: F32, zone: NDArray[np.bool_]) -> list:
    """Per zone (clear of the stripes, near one), from places' response ``r`` (M,) and the
    level it stands on (M,): the level bins' edges (B + 1,), and per bin the response's median
    and robust sigma (B,) each; None for a zone of too few places."""
    out: list = []
    ok = np.isfinite(r)
    for z in (False, True):
        m = ok & (zone == z)
        if m.sum() < 4 * _NOISE_BINS:
            out.append(None)
            continue
        lv = level[m]
        x = r[m]
        e = np.quantile(lv[:: max(1, lv.size // 100000)], np.linspace(0.0, 1.0, _NOISE_BINS + 1))
        b_ = np.clip(np.searchsorted(e, lv, side="right") - 1, 0, _NOISE_BINS - 1)
        med = np.zeros(_NOISE_BINS)
        s_ = np.zeros(_NOISE_BINS)
        for k in range(_NOISE_BINS):
            xb = x[b_ == k][:: max(1, int(np.count_nonzero(b_ == k)) // 20000)]
            if xb.size:
                med[k] = np.median(xb)
                s_[k] = 1.4826 * np.median(np.abs(xb - med[k]))
        out.append((e, med, np.maximum(s_, _NOISE_FLOOR * max(float(np.median(s_)), 1e-9))))
    return out


def _remapped(img: F32, xs: NDArray, ys: NDArray) -> F32:
    """``img`` (H, W) at the places (``xs``, ``ys``) px (any one shape; float32), bilinear
    (:func:`cv2.remap`); NaN where a place leaves the image (or its pixels are NaN)."""
    shape = np.shape(xs)
    if len(shape) == 2:
        return cv2.remap(
            img, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        )
    # a list of places: in rows of _REMAP_ROW (OpenCV's maps are less than 32767 wide)
    n = int(np.size(xs))
    rows = max(-(-n // _REMAP_ROW), 1)
    mx = np.zeros(rows * _REMAP_ROW, np.float32)
    my = np.zeros_like(mx)
    mx[:n] = np.ravel(xs)
    my[:n] = np.ravel(ys)
    out = _remapped(img, mx.reshape(rows, _REMAP_ROW), my.reshape(rows, _REMAP_ROW))
    return out.ravel()[:n].reshape(shape)


def _level_along(sharp: F32, xs: NDArray, ys: NDArray, angle: NDArray, reach: float) -> F32:
    """The mean of ``sharp`` (H, W) ``reach`` px before and after each place (``xs``, ``ys``)
    along the stripes' direction ``angle`` there (rad; all three of one shape), bilinear; NaN
    where a sample leaves the image or is NaN."""
    a = np.asarray(angle, np.float32)
    su = np.sin(a) * np.float32(reach)
    sv = np.cos(a) * np.float32(reach)
    xs = np.asarray(xs, np.float32)
    ys = np.asarray(ys, np.float32)
    return 0.5 * (_remapped(sharp, xs - su, ys - sv) + _remapped(sharp, xs + su, ys + sv))


def _first_sigma(dot_sigma_px: float) -> float:
    """px, the first guess of the spots' sigma on the sharp response of dots of Gaussian sigma
    ``dot_sigma_px`` in the image."""
    return math.hypot(_SIZE_GUESS * float(dot_sigma_px), SHARP_SIGMA)


def gaussian_profile(sg: float, extent: float | None = None) -> F64:
    """(L,) a Gaussian's radial profile of sigma ``sg`` px out to ``extent`` px (None:
    :data:`_PROFILE_SIGMAS` sigmas), every :data:`SPOT_PROFILE_STEP` px, 0 at the end."""
    extent = _PROFILE_SIGMAS * sg if extent is None else extent
    r = np.arange(int(math.ceil(extent / SPOT_PROFILE_STEP)) + 1) * SPOT_PROFILE_STEP
    g = np.exp(-0.5 * (r / sg) ** 2)
    return np.clip((g - g[-1]) / (1.0 - g[-1]), 0.0, None)


def local_maxima(z: NDArray, floor: float, margin: int) -> tuple[F64, F64]:
    """(u, v) px of the 3 x 3 local maxima of ``z`` (H, W) above ``floor``, ``margin`` px clear
    of the image's sides (NaN: never a maximum)."""
    zz = np.nan_to_num(np.asarray(z, np.float32), nan=-np.inf)
    pk = (zz >= cv2.dilate(zz, np.ones((3, 3), np.uint8))) & (zz > floor)
    pk[:margin] = pk[-margin:] = False
    pk[:, :margin] = pk[:, -margin:] = False
    v, u = np.nonzero(pk)
    return u.astype(np.float64), v.astype(np.float64)


def fit_spots(
    sr: SharpResponse, P: F64, A: F64, rounds: int, held: F64 | None = None
) -> tuple[F64, F64, F64, F64]:
    """``rounds`` rounds of the joint fit of spots to a sharp response: in each, every spot's
    centre and height in turn (one Gauss-Newton step over its :data:`SPOT_FIT_HALF` square)
    fitted to the response less every other spot, the others' latest included (Gauss-Seidel).

    Parameters
    ----------
    sr : SharpResponse
    P : (N, 2) float64, px, the spots' centres
    A : (N,) float64, their heights (intensity units)
    rounds : int
    held : (H, W) float64, spots held fixed beside them (None: none)

    Returns
    -------
    P, A : the fitted centres and heights (copies)
    se : (N, 4) float64, the standard errors of (u, v, height) in the last round (px, px,
        intensity units; 0 where a spot has too few known pixels) and the sum of squares of
        the response less the spots over its pixels
    model : (H, W) float64, ``held`` and the fitted spots
    """
    P = np.array(P, np.float64).reshape(-1, 2)
    A = np.array(A, np.float64)
    model = np.zeros(sr.response.shape) if held is None else held.copy()
    # each spot's values in the model, kept to take them out again as it moves
    side = 2 * int(math.ceil((len(sr.profile) - 1) * SPOT_PROFILE_STEP)) + 1
    foot = np.empty((len(P), 3, side, side))
    origin = np.empty((len(P), 3, 2), np.int64)
    _splat_kept(P, A, sr.angle, sr.profile, sr.reach, model, foot, origin)
    se = np.zeros((len(P), 4))
    for _ in range(rounds):
        _gauss_seidel(
            sr.response,
            sr.valid,
            sr.sigma,
            model,
            P,
            A,
            sr.angle,
            sr.profile,
            sr.reach,
            SPOT_FIT_HALF,
            _MAX_STEP,
            _DAMPING,
            se,
            foot,
            origin,
        )
    return P, A, se, model


def _spot_sigma(sr: SharpResponse, P: F64, A: F64, sg0: float) -> float:
    """The spots' sigma (px): per bright spot with no other spot near (``P``, ``A``), the
    trial sigma around ``sg0`` (refined by a parabola) whose Gaussian spot fits it best; their
    median (two dots blended into one peak want a wider spot, and are few)."""
    trials = sg0 * np.array(_SIGMA_TRIALS)
    ss = np.stack(
        [fit_spots(sr.with_profile(t), P, A, 3)[2][:, 3] for t in trials],
        axis=1,
    )
    k = np.argmin(ss, axis=1)
    kk = np.clip(k, 1, len(trials) - 2)
    rows = np.arange(len(ss))
    a, b, c = ss[rows, kk - 1], ss[rows, kk], ss[rows, kk + 1]
    den = a - 2.0 * b + c
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(den > 0, np.clip(0.5 * (a - c) / den, -0.5, 0.5), 0.0)
    pos = np.where((k > 0) & (k < len(trials) - 1), kk + off, k)
    return float(np.interp(np.median(pos), np.arange(len(trials)), trials))


def fit_dot_spots(
    sr: SharpResponse, dot_sigma_px: float, spot_sigma_px: float | None = None
) -> tuple[F64, F64, F64, SharpResponse]:
    """Every dot of a sharp response fitted as a spot beside its neighbours.

    Every local maximum of the response of at least 3 noise sigmas is a spot; the spots' sigma
    is fitted on the bright ones with no other spot near; all spots are fitted together
    (:func:`fit_spots`), so dots closer than about three pixels, one peak in a dot-sized
    smoothing, are each centred; where the response less every spot still shows a dot clearly,
    the clearest such place beside each spot gets one more spot, fitted again with its
    neighbours (the others held); a last round gives every spot's standard errors.

    Parameters
    ----------
    sr : SharpResponse (:func:`sharp_response`)
    dot_sigma_px : px, the dots' Gaussian sigma in the image, as given to
        :func:`sharp_response`
    spot_sigma_px : px, the spots' Gaussian sigma (None or NaN: fitted, as above)

    Returns
    -------
    P : (N, 2) float64, px, the spots' centres
    A : (N,) float64, their heights (intensity units)
    se : (N, 4) float64, as :func:`fit_spots`
    sr : the response with the spots' profile
    """
    sg0 = _first_sigma(dot_sigma_px)
    z = np.where(sr.valid, sr.response / sr.sigma, np.nan)
    u, v = local_maxima(z, _DETECT_Z, SPOT_FIT_HALF)
    P = np.stack([u, v], axis=1)
    iu, iv = u.astype(np.intp), v.astype(np.intp)
    A = np.maximum(sr.response[iv, iu], 0.0)
    zp = z[iv, iu]
    if spot_sigma_px is not None and math.isfinite(spot_sigma_px):
        sr = sr.with_profile(spot_sigma_px)
    elif len(P) > 1:
        d, _ = cKDTree(P).query(P, k=2)
        iso = (zp > _SIGMA_Z) & (d[:, 1] > _SIGMA_CLEAR * sg0)
        if iso.sum() >= _SIGMA_MIN_DOTS:
            pick = np.flatnonzero(iso)[:: max(1, int(iso.sum()) // _SIGMA_MAX_DOTS)]
            sr = sr.with_profile(_spot_sigma(sr, P[pick], A[pick], sg0))
    P, A, se, model = fit_spots(sr, P, A, _ROUNDS[0])
    # one more spot where the response less every fitted spot still shows a dot clearly
    res = np.where(sr.valid, sr.response - model, np.nan)
    zres = res / sr.sigma
    add = (zres > _ADD_Z) & (res > _ADD_SHARE * np.abs(model))
    au, av = local_maxima(np.where(add, zres, np.nan), _ADD_Z, SPOT_FIT_HALF)
    if len(au) and len(P):
        d, j = cKDTree(P).query(np.stack([au, av], axis=1))
        keep = d > _ADD_CLEAR_SIGMAS * sr.spot_sigma
        # one spot more per fitted spot at most: the clearest of the places beside it (a
        # spot fitted between two blended dots leaves one on either side)
        zr = zres[av.astype(np.intp), au.astype(np.intp)]
        order = np.lexsort((-zr, j))
        first = np.ones(len(j), bool)
        first[1:] = j[order][1:] != j[order][:-1]
        best = np.zeros(len(j), bool)
        best[order[first]] = True
        keep &= best
        au, av = au[keep], av[keep]
    n_old = len(P)
    P = np.concatenate([P, np.stack([au, av], axis=1)])
    A = np.concatenate([A, np.maximum(sr.response[av.astype(np.intp), au.astype(np.intp)], 0.0)])
    # the added spots and their neighbours, fitted on, the others held
    active = np.zeros(len(P), bool)
    active[n_old:] = True
    if n_old < len(P) and n_old:
        near = cKDTree(P[n_old:]).query_ball_point(P[:n_old], _ACTIVE_SIGMAS * sr.spot_sigma)
        active[:n_old] = np.array([len(x) > 0 for x in near], bool)
    held = sr.model(P[~active], A[~active])
    Pa, Aa, _, _ = fit_spots(sr, P[active], A[active], _ROUNDS[1], held)
    P[active], A[active] = Pa, Aa
    P, A, se, _ = fit_spots(sr, P, A, 1)
    return P, A, se, sr


def centre_dots(
    extraction: SlitExtraction, u: F64, v: F64, angle: F64, spot_sigma_px: float | None = None
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Dots of a frame centred as the calibration centres the dots of its reference boards:
    each a spot on the frame's sharp response, fitted beside the spots around it
    (:func:`fit_dot_spots`).

    The response is made within :data:`_REGION_PX` of the given dots, each place along the
    stripe direction of the dot nearest it; its median and noise are measured per zone and
    level at places beside the frame's stripes (:func:`places_beside_stripes`: up to half their
    spacing across them; a board's are measured over the whole board, every place of which is
    as near a stripe). A given dot is the spot that shows a dot (of at least
    :data:`SPOT_KEEP_Z` standard errors) nearest it, where it is the given dot nearest that
    spot and within :data:`_MAX_SHIFT_PX` of it; else it keeps its centre.

    Parameters
    ----------
    extraction : SlitExtraction, the frame's (its plane, stripes, stripe width and dot size)
    u, v : (M,) float64, px, the dots' centres as found
    angle : (M,) float64, rad, the stripes' direction beside each dot (from the image's
        vertical)
    spot_sigma_px : px, the spots' Gaussian sigma (the calibration's:
        :attr:`~multislit.geometry.dots.DotProjector.spot_sigma_px`); None or NaN: fitted on
        the frame's bright spots with no other spot near, as a board's are

    Returns
    -------
    u, v : (M,) float64, px, the centres
    fitted : (M,) bool, the dots centred by their spot (the others keep the given centre)
    """
    ex = extraction
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    if len(u) == 0:
        return u.copy(), v.copy(), np.zeros(0, bool)
    sharp = sharp_image(ex.plane, saturation_level_of(ex.plane))
    h, w = sharp.shape
    clearance = STRIPE_CLEARANCE * ex.stripe_width_px
    near = near_stripes(ex.u, ex.v, (h, w), clearance)
    spacing = stripe_spacing(ex.u, ex.v)
    spread = 0.5 * max(spacing if math.isfinite(spacing) else 0.0, 2.0 * clearance)
    # the places where its noise is measured: the stripe centres taken again (with other
    # offsets) until there are enough of them
    rounds = min(_SHARP_NOISE_ROUNDS, -(-_SHARP_NOISE_PLACES // max(len(ex.u), 1)))
    beside = tuple(
        np.concatenate(x)
        for x in zip(
            *(
                places_beside_stripes(ex.u, ex.v, ex.angle, spread, _SHARP_NOISE_PLACES, seed)
                for seed in range(rounds)
            ),
            strict=True,
        )
    )
    d2 = np.full((h, w), np.inf, np.float32)
    amap = np.zeros((h, w), np.float64)
    _nearest_angle(u, v, np.nan_to_num(np.asarray(angle, np.float64)), _REGION_PX, d2, amap)
    sigma = float(ex.dot_size_px) / FWHM_PER_SIGMA
    sr = sharp_response(sharp, amap, near, sigma, np.isfinite(d2), beside)
    P, A, se, _ = fit_dot_spots(sr, sigma, spot_sigma_px)
    # each dot's spot: the nearest, where it is the dot's nearest too and shows a dot
    z = np.where(se[:, 2] > 0, A / np.where(se[:, 2] > 0, se[:, 2], 1.0), 0.0)
    P = P[(z >= SPOT_KEEP_Z) & np.isfinite(P).all(axis=1)]
    if len(P) == 0:
        return u.copy(), v.copy(), np.zeros(len(u), bool)
    uv = np.stack([u, v], axis=1)
    shift, j = cKDTree(P).query(uv)
    _, back = cKDTree(uv).query(P[j])
    fitted = (shift <= _MAX_SHIFT_PX) & (back == np.arange(len(u)))
    return np.where(fitted, P[j, 0], u), np.where(fitted, P[j, 1], v), fitted


@njit(cache=True)
def _nearest_angle(u, v, angle, radius, d2, out):
    """Each pixel within ``radius`` px of a dot (``u``, ``v``) takes the ``angle`` of the
    nearest: ``out`` (H, W); ``d2`` (H, W) holds the squared distance to it (inf elsewhere)."""
    h, w = d2.shape
    r2 = radius * radius
    k = int(math.ceil(radius))
    for i in range(len(u)):
        if not (np.isfinite(u[i]) and np.isfinite(v[i])):
            continue
        cu = int(np.rint(u[i]))
        cv = int(np.rint(v[i]))
        for y in range(max(cv - k, 0), min(cv + k + 1, h)):
            for x in range(max(cu - k, 0), min(cu + k + 1, w)):
                e = (x - u[i]) ** 2 + (y - v[i]) ** 2
                if e <= r2 and e < d2[y, x]:
                    d2[y, x] = e
                    out[y, x] = angle[i]


@njit(cache=True, inline="always")
def _lobe(eu, ev, prof):
    """A unit spot's radial profile ``prof`` (every :data:`SPOT_PROFILE_STEP` px) at offset
    (eu, ev) px from its centre, and its derivatives with respect to the centre's u and v."""
    n = prof.shape[0]
    r2 = eu * eu + ev * ev
    ext = (n - 1) * SPOT_PROFILE_STEP
    if r2 >= ext * ext:
        return 0.0, 0.0, 0.0
    rr = math.sqrt(r2)
    x = rr / SPOT_PROFILE_STEP
    i = int(x)
    f = x - i
    g = prof[i] + f * (prof[i + 1] - prof[i])
    if rr < 1e-9:
        return g, 0.0, 0.0
    dg = (prof[i + 1] - prof[i]) / (SPOT_PROFILE_STEP * rr)
    return g, -dg * eu, -dg * ev


@njit(cache=True, inline="always")
def spot_at(du, dv, tu, tv, prof, reach):
    """The sharp response of a unit spot at offset (du, dv) px from its centre (its radial
    profile ``prof``) with its two negative half copies at ``reach`` px before and after it
    along the stripe (unit direction ``tu``, ``tv``), and its derivatives with respect to the
    centre's u and v."""
    k, ku, kv = _lobe(du, dv, prof)
    for s in (-1.0, 1.0):
        g, gu, gv = _lobe(du + s * reach * tu, dv + s * reach * tv, prof)
        k -= 0.5 * g
        ku -= 0.5 * gu
        kv -= 0.5 * gv
    return k, ku, kv


@njit(cache=True)
def splat_spots(P, A, ang, prof, reach, out):
    """Add every spot's response (height ``A`` (N,), centre ``P`` (N, 2) px; the stripes'
    direction ``ang`` (H, W) at its pixel) to ``out`` (H, W)."""
    for i in range(P.shape[0]):
        if np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]):
            add_spot(out, P[i, 0], P[i, 1], A[i], ang, prof, reach)


@njit(cache=True, inline="always")
def add_spot(out, pu, pv, a_i, ang, prof, reach):
    """Add a spot of height ``a_i`` centred at (pu, pv) px to ``out`` (H, W)."""
    if a_i == 0.0:
        return
    h, w = out.shape
    ext = (prof.shape[0] - 1) * SPOT_PROFILE_STEP
    half = int(math.ceil(ext))
    cu = int(np.rint(pu))
    cv = int(np.rint(pv))
    a = ang[min(max(cv, 0), h - 1), min(max(cu, 0), w - 1)]
    tu = math.sin(a)
    tv = math.cos(a)
    for j in range(3):  # the spot and its two negative half copies along the stripe
        s = 0.0 if j == 0 else (-1.0 if j == 1 else 1.0)
        c = 1.0 if j == 0 else -0.5
        qu = pu + s * reach * tu
        qv = pv + s * reach * tv
        iu = int(np.rint(qu))
        iv = int(np.rint(qv))
        for y in range(max(iv - half, 0), min(iv + half + 1, h)):
            for x in range(max(iu - half, 0), min(iu + half + 1, w)):
                g, _, _ = _lobe(x - qu, y - qv, prof)
                out[y, x] += c * a_i * g


@njit(cache=True)
def _splat_kept(P, A, ang, prof, reach, out, foot, origin):
    """:func:`splat_spots`, each spot's values kept (:func:`_put_spot`)."""
    for i in range(P.shape[0]):
        if np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]):
            _put_spot(out, i, P[i, 0], P[i, 1], A[i], ang, prof, reach, foot, origin)
        else:
            origin[i, :, :] = _NOWHERE


#: The origin of a spot's kept values that were never added.
_NOWHERE = -(2**40)


@njit(cache=True, inline="always")
def _put_spot(out, i, pu, pv, a_i, ang, prof, reach, foot, origin):
    """:func:`add_spot` of spot ``i``, its values kept in ``foot[i]`` (3, S, S) (the spot and
    its two half copies) with their first pixels' (u, v) in ``origin[i]`` (3, 2)."""
    if a_i == 0.0:
        origin[i, :, :] = _NOWHERE
        return
    h, w = out.shape
    ext = (prof.shape[0] - 1) * SPOT_PROFILE_STEP
    half = int(math.ceil(ext))
    cu = int(np.rint(pu))
    cv = int(np.rint(pv))
    a = ang[min(max(cv, 0), h - 1), min(max(cu, 0), w - 1)]
    tu = math.sin(a)
    tv = math.cos(a)
    for j in range(3):
        s = 0.0 if j == 0 else (-1.0 if j == 1 else 1.0)
        c = 1.0 if j == 0 else -0.5
        qu = pu + s * reach * tu
        qv = pv + s * reach * tv
        iu = int(np.rint(qu))
        iv = int(np.rint(qv))
        origin[i, j, 0] = iu - half
        origin[i, j, 1] = iv - half
        for y in range(max(iv - half, 0), min(iv + half + 1, h)):
            for x in range(max(iu - half, 0), min(iu + half + 1, w)):
                g, _, _ = _lobe(x - qu, y - qv, prof)
                val = c * a_i * g
                foot[i, j, y - iv + half, x - iu + half] = val
                out[y, x] += val


@njit(cache=True, inline="always")
def _take_spot(out, i, foot, origin):
    """Take spot ``i``'s kept values (:func:`_put_spot`) out of ``out`` (H, W)."""
    h, w = out.shape
    n = foot.shape[2]
    for j in range(3):
        x0 = origin[i, j, 0]
        y0 = origin[i, j, 1]
        if x0 == _NOWHERE:
            continue
        for y in range(max(y0, 0), min(y0 + n, h)):
            for x in range(max(x0, 0), min(x0 + n, w)):
                out[y, x] -= foot[i, j, y - y0, x - x0]


@njit(cache=True)
def _gauss_seidel(
    r, valid, sig, model, P, A, ang, prof, reach, half, max_step, damping, se, foot, origin
):
    """One round of :func:`fit_spots`: every spot's centre and height fitted in turn (one
    Gauss-Newton step) to ``r`` less the other spots (``model`` less its own), ``model``
    updated after each spot (its values kept in ``foot`` and ``origin``: :func:`_put_spot`);
    ``se`` (N, 4) gets the standard errors of (u, v, height) from the response's noise ``sig``
    at the spot, and the sum of squares of the response less the spots over the spot's
    pixels."""
    h, w = r.shape
    n = P.shape[0]
    for i in range(n):
        pu = P[i, 0]
        pv = P[i, 1]
        if not (np.isfinite(pu) and np.isfinite(pv)):
            continue
        cu = int(np.rint(pu))
        cv = int(np.rint(pv))
        if cu < 0 or cu >= w or cv < 0 or cv >= h:
            continue
        a = ang[cv, cu]
        tu = math.sin(a)
        tv = math.cos(a)
        ai = A[i]
        m00 = m01 = m02 = m11 = m12 = m22 = 0.0
        b0 = b1 = b2 = 0.0
        ss = 0.0
        npx = 0
        for y in range(max(cv - half, 0), min(cv + half + 1, h)):
            for x in range(max(cu - half, 0), min(cu + half + 1, w)):
                if not valid[y, x]:
                    continue
                k, ku, kv = spot_at(x - pu, y - pv, tu, tv, prof, reach)
                e = r[y, x] - model[y, x]  # the data less every spot, its own included
                j0 = ai * ku
                j1 = ai * kv
                m00 += j0 * j0
                m01 += j0 * j1
                m02 += j0 * k
                m11 += j1 * j1
                m12 += j1 * k
                m22 += k * k
                ss += e * e
                b0 += j0 * e
                b1 += j1 * e
                b2 += k * e
                npx += 1
        if npx < 6 or m22 <= 0.0:
            se[i, 0] = se[i, 1] = se[i, 2] = se[i, 3] = 0.0
            continue
        lam = 1e-9 + 1e-4 * (m00 + m11 + m22) / 3.0
        m00 += lam
        m11 += lam
        m22 += lam
        # the inverse of the symmetric 3 x 3 normal matrix, by its cofactors
        c00 = m11 * m22 - m12 * m12
        c01 = m02 * m12 - m01 * m22
        c02 = m01 * m12 - m02 * m11
        det = m00 * c00 + m01 * c01 + m02 * c02
        if not det > 0.0:
            se[i, 0] = se[i, 1] = se[i, 2] = se[i, 3] = 0.0
            continue
        i00 = c00 / det
        i01 = c01 / det
        i02 = c02 / det
        i11 = (m00 * m22 - m02 * m02) / det
        i12 = (m01 * m02 - m00 * m12) / det
        i22 = (m00 * m11 - m01 * m01) / det
        s2 = sig[cv, cu] ** 2
        se[i, 0] = math.sqrt(max(i00 * s2, 0.0))
        se[i, 1] = math.sqrt(max(i11 * s2, 0.0))
        se[i, 2] = math.sqrt(max(i22 * s2, 0.0))
        se[i, 3] = ss
        su = min(max(i00 * b0 + i01 * b1 + i02 * b2, -max_step), max_step)
        sv = min(max(i01 * b0 + i11 * b1 + i12 * b2, -max_step), max_step)
        na = max(ai + damping * (i02 * b0 + i12 * b1 + i22 * b2), 0.0)
        nu = pu + damping * su
        nv = pv + damping * sv
        # the model follows at once (Gauss-Seidel: a blended neighbour fitted next sees it)
        _take_spot(model, i, foot, origin)
        _put_spot(model, i, nu, nv, na, ang, prof, reach, foot, origin)
        P[i, 0] = nu
        P[i, 1] = nv
        A[i] = na


@njit(cache=True)
def _spot_z(resp, valid, sig, ang, uv, prof, reach, half, out, out_se):
    """Per place (M, 2): the height of a spot fitted there (its centre held) over its standard
    error, weighted by the pixels' noise ``sig`` (``out``), and the standard error
    (``out_se``); both untouched where no pixel is known."""
    h, w = resp.shape
    for i in range(uv.shape[0]):
        pu = uv[i, 0]
        pv = uv[i, 1]
        if not (np.isfinite(pu) and np.isfinite(pv)):
            continue
        cu = int(np.rint(pu))
        cv = int(np.rint(pv))
        if cu < 0 or cu >= w or cv < 0 or cv >= h:
            continue
        a = ang[cv, cu]
        tu = math.sin(a)
        tv = math.cos(a)
        skr = 0.0
        skk = 0.0
        for y in range(max(cv - half, 0), min(cv + half + 1, h)):
            for x in range(max(cu - half, 0), min(cu + half + 1, w)):
                if not valid[y, x]:
                    continue
                k, _, _ = spot_at(x - pu, y - pv, tu, tv, prof, reach)
                wt = 1.0 / (sig[y, x] * sig[y, x])
                skr += wt * k * resp[y, x]
                skk += wt * k * k
        if skk > 0.0:
            out[i] = skr / math.sqrt(skk)
            out_se[i] = 1.0 / math.sqrt(skk)

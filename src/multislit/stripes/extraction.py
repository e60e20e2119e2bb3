"""Separate slits from dots and extract the slit centre lines (paper, section 4.1 and Fig. 11).

The pipeline, for one camera image with many roughly vertical laser stripes (slits) and the
random dots scattered along them:

1. :func:`separate` -- a running median along each row, wider than a stripe, estimates the
   background (ambient light, albedo, texture); subtracting it (clipped at 0) leaves the stripes
   and dots on a flat background (Fig. 11 c). A morphological opening with a vertical line longer
   than a dot keeps the vertical stripes and removes the dots (d); the dots are the difference
   (e).
2. :func:`find_stripe_centres` -- in every row, each stripe's local maximum above a noise
   threshold, refined to sub-pixel by a 3-point fit (Gaussian by default); saturated (flat-top)
   stripes are centred from a Gaussian fit to the unsaturated flanks.
3. :func:`link_segments` -- centre points in consecutive rows are chained into segments,
   broken at jumps, gaps and ambiguities.

:func:`extract_slits` runs the three steps. Pixel convention: (u, v), u right (column), v down
(row), (0, 0) the centre of the top-left pixel. Everything is vectorised over the whole image;
a 1280x1024 frame takes a few milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from multislit.errors import IdentificationError

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: FWHM / sigma of a Gaussian, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: Sub-pixel centre methods of :func:`find_stripe_centres`; the first is the default.
CENTRE_METHODS = ("gaussian", "parabolic", "centroid", "steger")
#: Default detection threshold in units of the highpass noise sigma. The slit image's background
#: is an opening of clipped noise, which almost never exceeds ~1.5 sigma, so 4 sigma gives no
#: false peaks from noise while keeping stripes whose peak is ~4x the noise.
DEFAULT_K_SIGMA = 8.0  # x the background noise; stripe pixels carry several times more shot noise
#: Default minimum number of centre points of a kept segment: shorter runs are noise or residues
#: of dots, and a segment must be long enough to carry a dot template for identification.
DEFAULT_MIN_LENGTH = 10
#: Default number of rows (binomial weights) averaged along the stripe for the sub-pixel fit.
DEFAULT_V_SMOOTH = 5


def _taps(v_smooth: int) -> int:
    if int(v_smooth) != v_smooth or v_smooth < 1 or v_smooth % 2 == 0:
        raise SlitExtractionError(f"v_smooth must be an odd integer >= 1, got {v_smooth}")
    return int(v_smooth)


class SlitExtractionError(IdentificationError):
    """Slit extraction cannot run on the given input (bad image or parameters)."""


# --------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class Separation:
    """Result of :func:`separate` (Fig. 11 c, d, e); all images (H, W) float32, intensity units.

    Attributes
    ----------
    highpass : image minus its row-wise running median, clipped at 0: stripes + dots (c)
    slits : ``highpass`` with the dots found by a vertical opening refilled along the stripe:
        the stripes only (d)
    dots : ``highpass - slits``: the dots only (e), >= 0
    saturated : (H, W) bool, pixels of saturated stripes (image >= saturation level, in vertical
        runs at least as long as the opening line); all False for float images
    stripe_width_px : stripe FWHM (px) used to size the median
    dot_size_px : dot FWHM (px) used to size the opening
    """

    highpass: F32
    slits: F32
    dots: F32
    saturated: NDArray[np.bool_]
    stripe_width_px: float
    dot_size_px: float


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


@dataclass(frozen=True, eq=False)
class SlitExtraction:
    """Result of :func:`extract_slits`.

    Attributes
    ----------
    u, v : (K,) float64, sub-pixel stripe centres (px), sorted by (v, u)
    peak : (K,) float64, slit intensity at the centre (intensity units above background)
    width : (K,) float64, stripe FWHM along the row (px), NaN where unknown
    segment : (K,) int64, segment id from :func:`link_segments` (0..S-1, ordered by mean u),
        -1 for points in segments shorter than ``min_length``
    dots : (H, W) float32, the dot image (Fig. 11 e) less its streaks (:func:`remove_streaks`:
        pieces of stripes that lean too far for the vertical opening, on curved surfaces)
    noise_sigma : noise sigma of the highpass image (intensity units)
    stripe_width_px : stripe FWHM used (px); NaN if no stripe could be found to estimate it
    dot_size_px : dot FWHM used (px); NaN if not estimated (no stripes)
    """

    u: F64
    v: F64
    peak: F64
    width: F64
    segment: I64
    dots: F32
    noise_sigma: float
    stripe_width_px: float
    dot_size_px: float

    @property
    def num_segments(self) -> int:
        """Number of kept segments S."""
        return int(self.segment.max()) + 1 if self.segment.size else 0


# --------------------------------------------------------------------------- validation
def _as_image(image: ArrayLike, name: str = "image") -> NDArray:
    """Validate a grayscale image; return uint8/uint16 unchanged, anything else as float32."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise SlitExtractionError(
            f"{name} must be a 2-D (H, W) grayscale array, got shape {arr.shape}"
        )
    if arr.size == 0:
        raise SlitExtractionError(f"{name} is empty (shape {arr.shape})")
    if arr.dtype == np.uint8 or arr.dtype == np.uint16:
        return arr
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise SlitExtractionError(f"{name} must be uint8, uint16 or float, got dtype {arr.dtype}")
    out = arr.astype(np.float32)
    if not np.isfinite(out).all():
        raise SlitExtractionError(f"{name} contains NaN or infinite values")
    return out


def _positive(x: float | None, name: str) -> float | None:
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x) or x <= 0:
        raise SlitExtractionError(f"{name} must be a positive number of pixels, got {x}")
    return x


# --------------------------------------------------------------------------- filter sizes
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


def _d2_kernel(sigma: float) -> NDArray[np.float32]:
    """Sampled second derivative of a unit-area Gaussian (zero sum, exact on x^2 / 2)."""
    r = max(2, math.ceil(4 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    k = g * (x * x - sigma * sigma)
    k -= k.mean()  # no response to a constant
    k /= 0.5 * np.sum(k * x * x)  # response exactly 1 to x^2 / 2
    return k.astype(np.float32)


def _ridge_fwhm(
    profiles: NDArray[np.float32], pixel_noise: float, z_min: float = 6.0
) -> float | None:
    """Typical FWHM (px) of the bright ridges along the rows of ``profiles`` (R, N), or None.

    Lindeberg's scale selection: the gamma-normalised second derivative -t^(3/4) d2/dx2 of
    the Gaussian-smoothed profile (t = sigma^2) peaks, for a Gaussian ridge of sigma s, exactly
    at sigma = s. Ridge points are local maxima along the row with a response > ``z_min`` times
    the robust noise of that scale's response; the scale is refined by a parabola in log sigma
    and the median over all ridge points is returned as FWHM.
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
    noise = np.maximum(noise, 1e-6 * max(float(np.abs(resp).max()), 1e-30))
    best = resp.argmax(axis=0)
    strength = np.take_along_axis(resp, best[None], 0)[0]
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
    return float(np.exp(np.median(log_s)) * FWHM_PER_SIGMA)


def _sample(n: int, count: int) -> NDArray[np.intp]:
    """``count`` evenly spaced indices in [0, n) (all if n <= count)."""
    if n <= count:
        return np.arange(n)
    return np.linspace(0, n - 1, count).round().astype(np.intp)


def estimate_stripe_width(image: ArrayLike) -> float:
    """Estimate the typical stripe FWHM (px, along the row) of an image.

    Ridge scale selection (see ``_ridge_fwhm``) on 24 evenly spaced rows: the stripes are
    the dominant bright ridges along rows; the median over all of them is robust to dots.

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float

    Returns
    -------
    fwhm : float, px

    Raises
    ------
    SlitExtractionError
        if the image is invalid or shows no stripe-like ridge.
    """
    img = _as_image(image)
    idx = _sample(img.shape[0] - 1, 24)
    rows = img[idx].astype(np.float32)
    # pixel noise from vertical neighbours: the (near-vertical) stripes cancel, noise does not
    diff = rows - img[idx + 1].astype(np.float32)
    pixel_noise = max(1.4826 * float(np.median(np.abs(diff))) / math.sqrt(2.0), 1e-3)
    w = _ridge_fwhm(rows, pixel_noise)
    if w is None:
        raise SlitExtractionError("estimate_stripe_width: no stripes found in image")
    return w


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
    hp = _as_image(highpass, "highpass")
    cols = np.ascontiguousarray(hp[:, _sample(hp.shape[1], 48)].T, dtype=np.float32)
    # noise from neighbours along each column: the dots are sparse there
    pixel_noise = max(
        1.4826 * float(np.median(np.abs(np.diff(cols, axis=1)))) / math.sqrt(2.0), 1e-3
    )
    return _ridge_fwhm(cols, pixel_noise)


# --------------------------------------------------------------------------- separation
# Median of 9 by Devillard's 19 compare-exchange network ("Fast median search", 1998), pruned to
# the 30 min/max operations whose results are used: (i, j, keep_min, keep_max).
_MED9 = (
    (1, 2, True, True), (4, 5, True, True), (7, 8, True, True), (0, 1, True, True),
    (3, 4, True, True), (6, 7, True, True), (1, 2, True, True), (4, 5, True, True),
    (7, 8, True, True), (0, 3, False, True), (5, 8, True, False), (4, 7, True, True),
    (3, 6, False, True), (1, 4, False, True), (2, 5, True, False), (4, 7, True, False),
    (4, 2, True, True), (6, 4, False, True), (4, 2, True, False),
)  # fmt: skip


def _median9(p: list[NDArray]) -> NDArray:
    p = list(p)
    for i, j, keep_min, keep_max in _MED9:
        lo = cv2.min(p[i], p[j]) if keep_min else None
        hi = cv2.max(p[i], p[j]) if keep_max else None
        p[i], p[j] = lo, hi
    return p[4]


def row_median_background(image: NDArray, stride: int) -> NDArray:
    """Row-wise sparse median background, same dtype as ``image`` (H, W).

    Median of the 9 pixels at u + stride * j (j = -4..4) of each row, by a sorting network
    of 30 vectorised min/max passes (~2 ms for 1280x1024 uint8, against ~50 ms for
    ``cv2.medianBlur`` with a 13 px kernel and ~280 ms for a 1x13 ``scipy.ndimage``
    median). Like any median it keeps steps (albedo edges) sharp; the image border is
    reflected.
    """
    h, w = image.shape
    pad = 4 * stride
    border = cv2.BORDER_REFLECT_101 if pad < w else cv2.BORDER_REPLICATE
    p = cv2.copyMakeBorder(image, 0, 0, pad, pad, border)
    return _median9([p[:, pad + j * stride : pad + j * stride + w] for j in range(-4, 5)])


def _running_extreme(x: NDArray, length: int, op: str) -> NDArray:
    """Min (``op='min'``) or max over a centred vertical window of odd ``length`` (per column).

    Doubling trick: log2(length) + 1 vectorised min/max passes; out-of-image samples are
    ignored (padded with the neutral value).
    """
    fn = cv2.min if op == "min" else cv2.max
    if np.issubdtype(x.dtype, np.integer):
        info = np.iinfo(x.dtype)
        neutral = float(info.max if op == "min" else info.min)
    else:
        neutral = float(np.finfo(x.dtype).max if op == "min" else -np.finfo(x.dtype).max)
    r = length // 2
    h = x.shape[0]
    y = cv2.copyMakeBorder(x, r, r, 0, 0, cv2.BORDER_CONSTANT, value=neutral)
    span = 1
    while 2 * span <= length:
        y = fn(y[:-span], y[span:])
        span *= 2
    if span < length:
        y = fn(y[: len(y) - (length - span)], y[length - span :])
    return y[:h]


def vertical_opening(x: NDArray, length: int) -> NDArray:
    """Grey opening with a vertical line of odd ``length`` px (erosion then dilation)."""
    if length <= 1:
        return x.copy()
    return _running_extreme(_running_extreme(x, length, "min"), length, "max")


#: Directions (deg from the image's vertical) of the line openings that find streaks in the dot
#: image: pieces of stripes leaning too far for the vertical opening (curved surfaces), and
#: edges; vertical streaks are left alone (dots in bands along the slits line up vertically).
STREAK_ANGLES_DEG = (-75.0, -60.0, -45.0, -30.0, -15.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)


def line_kernel(length: int, angle_deg: float) -> NDArray[np.uint8]:
    """Structuring element: a digital line of ``length`` px through the centre of a square
    (length x length) kernel, ``angle_deg`` from the vertical (positive leans right going down)."""
    k = np.zeros((length, length), np.uint8)
    r = (length - 1) // 2
    a = math.radians(angle_deg)
    # half offsets rounded half away from zero, so the line is symmetric about the centre
    # (Python's round() rounds 1.5 and 2.5 both to 2, which made 15 and 30 deg one kernel)
    dx = int(math.copysign(math.floor(abs(r * math.sin(a)) + 0.5), math.sin(a)))
    dy = int(math.copysign(math.floor(abs(r * math.cos(a)) + 0.5), math.cos(a)))
    cv2.line(k, (r - dx, r - dy), (r + dx, r + dy), 1, 1)
    return k


def remove_streaks(
    dots: NDArray, length: int, angles_deg: tuple[float, ...] = STREAK_ANGLES_DEG
) -> NDArray:
    """The dot image less its streaks: ``dots`` minus the supremum of its grey openings with
    lines of ``length`` px at ``angles_deg``. A dot is shorter than the line in every direction
    and stays; a piece of stripe or an edge that contains such a line goes."""
    if length <= 1:
        return dots.copy()
    out = None
    for a in angles_deg:
        o = cv2.morphologyEx(dots, cv2.MORPH_OPEN, line_kernel(length, a))
        out = o if out is None else cv2.max(out, o)
    return cv2.subtract(dots, out)


def _saturation_level(img: NDArray, saturation_level: float | None) -> float | None:
    if saturation_level is not None:
        return float(saturation_level)
    if np.issubdtype(img.dtype, np.integer):
        return float(np.iinfo(img.dtype).max)
    return None


def _nonzero2d(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``np.nonzero`` of a 2-D mask, row-major; flatnonzero + divmod is ~8x faster."""
    flat = np.flatnonzero(mask)
    return np.divmod(flat, mask.shape[1])


def _runs(d: NDArray[np.int8]) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Runs of ones along the rows of a 0/1 mask from ``d = np.diff(padded mask, axis=1)``.

    Returns row, start (first index in the padded-minus-one frame, i.e. the original column)
    and stop (one past the last) of every run, row-major. Starts (+1) and stops (-1) alternate
    in a row-major scan, so one flatnonzero finds both.
    """
    flat = np.flatnonzero(d)
    row, col = np.divmod(flat, d.shape[1])
    return row[0::2], col[0::2], col[1::2]


def slope_sigma(length: int) -> float:
    """Integration scale (px) of :func:`stripe_slope` for an opening of ``length`` px: half the
    line, a few stripe widths. Measured on the half-size identification benchmark (length 5):
    2, 3 and 5 px gave coverage and correctness within 1 point of each other."""
    return 0.5 * length


def stripe_slope(hp: NDArray, sigma: float) -> NDArray[np.float32]:
    """(H, W) float32, px per row: the local lean of the stripes, du/dv, from the structure
    tensor of ``hp`` integrated over a Gaussian of ``sigma`` px (a stripe f(u - s v) has
    gradients (f', -s f'), so s = -J_uv / J_uu); clipped to +-1."""
    x = hp.astype(np.float32)
    gu = cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=3)
    juu = cv2.GaussianBlur(gu * gu, (0, 0), sigma)
    juv = cv2.GaussianBlur(gu * gv, (0, 0), sigma)
    s = -juv / np.maximum(juu, 1e-6)
    return np.clip(s, -1.0, 1.0)


def _fill_dots(
    hp: NDArray,
    opened: NDArray,
    tau: float,
    length: int,
    slope: NDArray | None = None,
) -> NDArray:
    """Slit image: ``hp`` with the dot pixels refilled by interpolation along the stripe.

    The opening alone distorts a tilted stripe's profile near a dot (the line windows that
    avoid the dot are off-centre, so they sample the stripe at a shifted position, ~0.1 px
    centre bias). Instead the opening only *finds* the dots (``hp - opened > tau + 5 %``, dilated by
    1 px for their tails); each vertical run of dot pixels in a column is replaced by linear
    interpolation between the clean rows just above and below it. With ``slope`` (px per row,
    :func:`stripe_slope`) those two samples are taken along the stripe (shifted sideways by the
    slope, interpolated along their rows), exact for a straight stripe of any lean; without it
    they are the pixels straight above and below, exact only for a vertical stripe: on a stripe
    leaning ~10 deg the speckle peaks along it are flagged too and vertical interpolation cut
    its core out (staircase centres, doubled ridges and gaps on tilted and curved surfaces).
    Runs longer than 2 ``length`` or touching the image border keep the opened value.
    The result is clipped to ``hp`` so that ``hp - slits >= 0``.
    """
    h, w = hp.shape
    diff = cv2.subtract(hp, opened)
    # + 5 % of the opening: the opening flattens the top of a tilted stripe by
    # A (1 - exp(-(s (L - 1) / 2)^2 / (2 sigma^2))), ~2.5 % of its peak A at slope s = 0.1; that
    # is not a dot, and flagging whole stripe tops would make runs too long to interpolate
    thr = cv2.addWeighted(opened, 0.05, opened, 0.0, tau)
    mask = cv2.compare(diff, thr, cv2.CMP_GT)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    out = hp.copy()
    if not mask.any():
        return out
    mt = np.zeros((w, h + 2), np.int8)
    mt[:, 1:-1] = cv2.transpose(mask) != 0
    d = np.diff(mt, axis=1)
    col, start, stop = _runs(d)
    n = stop - start
    ok = (start > 0) & (stop < h) & (n <= 2 * length)
    # fallback for every masked pixel: the opening
    np.copyto(out, opened, where=mask != 0)
    col, start, stop, n = col[ok], start[ok], stop[ok], n[ok]
    if n.size == 0:
        return out
    run = np.repeat(np.arange(n.size), n)
    t = np.arange(run.size) - np.repeat(np.cumsum(n) - n, n) + 1  # 1..n within each run
    frac = t / (n[run] + 1).astype(np.float32)
    rows = start[run] + t - 1
    cols = col[run]
    if slope is None:
        above = hp[start - 1, col].astype(np.float32)[run]
        below = hp[stop, col].astype(np.float32)[run]
    else:
        # along the stripe: the clean pixels t rows above and n + 1 - t rows below, shifted
        # sideways by the local slope (linear interpolation along their rows)
        s = slope[start + n // 2, col].astype(np.float32)[run]
        above = _row_sample(hp, start[run] - 1, cols - s * t)
        below = _row_sample(hp, stop[run], cols + s * (n[run] + 1 - t))
    val = above + (below - above) * frac
    if np.issubdtype(hp.dtype, np.integer):
        val = np.rint(val)
    out[rows, cols] = np.minimum(val, hp[rows, cols]).astype(hp.dtype)
    return out


def _row_sample(img: NDArray, r: NDArray, u: NDArray) -> NDArray[np.float32]:
    """Linear interpolation of ``img`` along rows ``r`` at (fractional) columns ``u``."""
    w = img.shape[1]
    u = np.clip(u, 0.0, w - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.intp), w - 2) if w > 1 else np.zeros(u.shape, np.intp)
    f = (u - u0).astype(np.float32)
    a = img[r, u0].astype(np.float32)
    b = img[r, np.minimum(u0 + 1, w - 1)].astype(np.float32)
    return a + (b - a) * f


def _separate(
    img: NDArray, stripe_width_px: float, dot_size_px: float, saturation_level: float | None
) -> tuple[NDArray, NDArray, NDArray, float]:
    """Core of :func:`separate` on a validated image, native dtype (exact integer arithmetic).

    Returns highpass, slits, saturated mask, noise sigma of the highpass.
    """
    bg = row_median_background(img, median_stride(stripe_width_px))
    hp = cv2.subtract(img, bg)  # saturates at 0 for integer images
    if hp.dtype == np.float32:
        np.maximum(hp, 0, out=hp)
    noise = _noise_from_difference(img, bg)
    length = opening_length(dot_size_px)
    opened = vertical_opening(hp, length)
    # dot pixels: more than 3 noise sigmas above the opening (0.1 % false alarms on background;
    # false alarms on stripes are harmless, they are interpolated from their neighbours along
    # the stripe's local slope)
    slits = _fill_dots(hp, opened, 3.0 * noise, length, stripe_slope(hp, slope_sigma(length)))
    level = _saturation_level(img, saturation_level)
    if level is None:
        sat = np.zeros(img.shape, bool)
    else:
        sat = (img >= level).view(np.uint8)
        # keep saturated runs that are stripes (vertically long), not saturated dots
        sat = vertical_opening(sat, length).view(bool)
    return hp, slits, sat, noise


def _noise_from_difference(img: NDArray, bg: NDArray) -> float:
    """Pixel noise sigma from differences of vertical neighbours.

    The stripes run along v, so a pixel minus the one below cancels them (and the background);
    what is left is noise, plus dots and stripe bends, which are a minority that the median
    ignores. Unlike the spread of ``img - bg`` this does not depend on how well the background
    was estimated (a row median lifted by dense stripes). ``bg`` is unused, kept for the call.
    """
    d = img[1::2].astype(np.float32) - img[:-1:2].astype(np.float32)
    sigma = 1.4826 * float(np.median(np.abs(d))) / math.sqrt(2.0)
    if np.issubdtype(img.dtype, np.integer):
        sigma = max(sigma, 1.0 / math.sqrt(12.0))  # quantisation noise floor
    return sigma


def separate(
    image: ArrayLike,
    stripe_width_px: float | None = None,
    dot_size_px: float | None = None,
    *,
    saturation_level: float | None = None,
) -> Separation:
    """Split an image into stripes (slits) and dots on a flat background (paper Fig. 11).

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float grayscale
    stripe_width_px : stripe FWHM along the row (px); estimated by
        :func:`estimate_stripe_width` if None. Sizes the row median (:func:`median_stride`).
    dot_size_px : dot FWHM (px); estimated by :func:`estimate_dot_size` if None (falling back
        to the stripe width). Sizes the opening (:func:`opening_length`).
    saturation_level : pixel value at which the camera saturates; default the dtype maximum
        for integer images (pass e.g. 4095 for 12-bit data in uint16), none for float.

    Returns
    -------
    Separation
        highpass, slits, dots (H, W) float32, saturated (H, W) bool, sizes used.

    Raises
    ------
    SlitExtractionError
        bad image or sizes, or no stripe to estimate the width from.
    """
    img = _as_image(image)
    sw = _positive(stripe_width_px, "stripe_width_px")
    ds = _positive(dot_size_px, "dot_size_px")
    if sw is None:
        sw = estimate_stripe_width(img)
    if ds is None:
        hp0 = cv2.subtract(img, row_median_background(img, median_stride(sw)))
        ds = estimate_dot_size(hp0) or sw
    hp, slits, sat, _ = _separate(img, sw, ds, saturation_level)
    hpf = hp.astype(np.float32)
    sf = slits.astype(np.float32)
    return Separation(
        highpass=hpf,
        slits=sf,
        dots=hpf - sf,
        saturated=sat,
        stripe_width_px=sw,
        dot_size_px=ds,
    )


# --------------------------------------------------------------------------- centres
def estimate_noise(image: ArrayLike) -> float:
    """Robust noise sigma of an image (intensity units) from horizontal first differences.

    sigma = 1.4826 * MAD(diff) / sqrt(2); stripes and dots are a minority of the pixels. For a
    raw or highpass image; on a slit image (mostly exact zeros) it returns the quantisation /
    residual level only, so prefer the highpass noise that :func:`extract_slits` uses.
    """
    img = _as_image(image)
    d = np.diff(img[::2].astype(np.float32), axis=1)
    med = np.median(d)
    sigma = 1.4826 * float(np.median(np.abs(d - med))) / math.sqrt(2.0)
    if np.issubdtype(img.dtype, np.integer):
        sigma = max(sigma, 1.0 / math.sqrt(12.0))
    return sigma


def _gather(img: NDArray, r: NDArray, c: NDArray, offsets: NDArray, taps: int = 1) -> F64:
    """Values img[r, c + offsets] as (K, len(offsets)) float64, averaged over ``taps`` rows.

    With ``taps`` > 1 (odd), each value is a binomial-weighted average over rows r - taps // 2
    .. r + taps // 2 (clamped to the image): smoothing along the stripe, which for a straight,
    tilted stripe keeps the row's profile symmetric about its centre and divides the noise.
    """
    h, w = img.shape
    cols = np.clip(c[:, None] + offsets[None, :], 0, w - 1)
    if taps <= 1:
        return img[r[:, None], cols].astype(np.float64)
    half = taps // 2
    wts = np.array([math.comb(taps - 1, i) for i in range(taps)], np.float64) / 2.0 ** (taps - 1)
    out = np.zeros(cols.shape, np.float64)
    for i, dv in enumerate(range(-half, half + 1)):  # loop over the few taps only
        rows = np.clip(r + dv, 0, h - 1)
        out += wts[i] * img[rows[:, None], cols]
    return out


def _three_point(a: F64, b: F64, c: F64, method: str) -> tuple[F64, F64]:
    """Sub-pixel offset and FWHM from three samples at -1, 0, +1 (b the maximum)."""
    ok = (a > 0) & (c > 0) & (b > 0)
    la = np.log(np.where(ok, a, 1.0))
    lb = np.log(np.where(ok, b, 1.0))
    lc = np.log(np.where(ok, c, 1.0))
    den_g = la - 2 * lb + lc
    ok &= den_g < 0
    width = np.where(ok, FWHM_PER_SIGMA * np.sqrt(-1.0 / np.where(ok, den_g, -1.0)), np.nan)
    den_p = a - 2 * b + c
    delta_p = np.where(den_p < 0, 0.5 * (a - c) / np.where(den_p < 0, den_p, -1.0), 0.0)
    if method == "gaussian":
        delta_g = 0.5 * (la - lc) / np.where(ok, den_g, -1.0)
        delta = np.where(ok, delta_g, delta_p)  # parabola where the log is undefined
    else:
        delta = delta_p
    return np.clip(delta, -0.5, 0.5), width


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
) -> tuple[F64, F64, F64, F64, NDArray[np.bool_]]:
    """Centres of saturated runs: weighted log-parabola fit to 2 unsaturated pixels per flank.

    Returns u, v, peak, width of every run and the (H, W) mask of pixels within 1 px of a run
    (no ordinary peak is taken there).
    """
    h, w = sat.shape
    m = np.zeros((h, w + 2), np.int8)
    m[:, 1:-1] = sat
    d = np.diff(m, axis=1)
    rs, c0, c1 = _runs(d)
    c1 = c1 - 1
    near = cv2.dilate(sat.view(np.uint8), np.ones((1, 3), np.uint8)).view(bool)
    if rs.size == 0:
        e = np.empty(0)
        return e, e, e, e, near
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
    return u, rs.astype(np.float64), peak, width, near


def find_stripe_centres(
    slit_image: ArrayLike,
    noise_sigma: float | None = None,
    method: str = "gaussian",
    *,
    k_sigma: float = DEFAULT_K_SIGMA,
    saturated: ArrayLike | None = None,
    stripe_width_px: float | None = None,
    v_smooth: int = DEFAULT_V_SMOOTH,
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
    unsaturated pixels on each flank (the run midpoint if the fit fails).

    Parameters
    ----------
    slit_image : (H, W) slit image (e.g. :attr:`Separation.slits`), background ~ 0
    noise_sigma : noise sigma of the highpass image (intensity units); default
        :func:`estimate_noise` of ``slit_image`` (prefer passing the highpass noise)
    method : one of :data:`CENTRE_METHODS`
    k_sigma : detection threshold in noise sigmas
    saturated : (H, W) bool mask of saturated stripe pixels (:attr:`Separation.saturated`)
    stripe_width_px : stripe FWHM (px) for ``centroid``/``steger``; default the median
        Gaussian-fit width of the peaks

    Returns
    -------
    StripeCentres
        (u, v, peak, width), each (K,) float64, sorted by (v, u).
    """
    s = _as_image(slit_image, "slit_image")
    if method not in CENTRE_METHODS:
        raise SlitExtractionError(f"method must be one of {CENTRE_METHODS}, got {method!r}")
    if noise_sigma is None:
        noise_sigma = estimate_noise(s)
    noise_sigma = float(noise_sigma)
    if not math.isfinite(noise_sigma) or noise_sigma < 0:
        raise SlitExtractionError(f"noise_sigma must be >= 0, got {noise_sigma}")
    if not math.isfinite(k_sigma) or k_sigma < 0:
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma}")
    sw = _positive(stripe_width_px, "stripe_width_px")
    if saturated is None:
        sat = np.zeros(s.shape, bool)
    else:
        sat = np.asarray(saturated, dtype=bool)
        if sat.shape != s.shape:
            raise SlitExtractionError(
                f"saturated must have the slit image's shape {s.shape}, got {sat.shape}"
            )
    return _find_centres(s, noise_sigma * k_sigma, method, sat, sw, _taps(v_smooth))


def _find_centres(
    s: NDArray,
    threshold: float,
    method: str,
    sat: NDArray[np.bool_],
    sw: float | None,
    taps: int = 1,
) -> StripeCentres:
    h, w = s.shape
    if w < 3:
        e = np.empty(0)
        return StripeCentres(e, e, e, e)
    mid = s[:, 1:-1]
    thr = math.floor(threshold) if np.issubdtype(s.dtype, np.integer) else threshold
    is_max = (mid > s[:, :-2]) & (mid >= s[:, 2:]) & (mid > thr)
    su, sv, speak, swidth, near = _saturated_centres(s, sat)
    if sv.size:
        is_max &= ~near[:, 1:-1]
    r, c = np.nonzero(is_max)
    c = c + 1
    # smoothed samples at c-2 .. c+2; re-centre on the smoothed maximum among c-1 .. c+1
    vals = _gather(s, r, c, np.arange(-2, 3), taps)
    j = 1 + np.argmax(vals[:, 1:4], axis=1)
    k = np.arange(r.size)
    c = c + (j - 2)
    a, b, cc = vals[k, j - 1], vals[k, j], vals[k, j + 1]
    delta, width = _three_point(a, b, cc, "gaussian" if method == "gaussian" else "parabolic")
    if method in ("centroid", "steger"):
        fwhm = sw if sw is not None else float(np.nanmedian(width)) if r.size else 3.0
        if not math.isfinite(fwhm):
            fwhm = 3.0
        delta, _ = _window_offset(s, r, c, method, fwhm, taps)
    u = c + delta
    v = r.astype(np.float64)
    if sv.size:
        keep = speak > thr
        u = np.concatenate([u, su[keep]])
        v = np.concatenate([v, sv[keep]])
        b = np.concatenate([b, speak[keep]])
        width = np.concatenate([width, swidth[keep]])
        order = np.lexsort((u, v))
        u, v, b, width = u[order], v[order], b[order], width[order]
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
        u, v, b, width = u[keep], v[keep], b[keep], width[keep]
    return StripeCentres(u, v, b, width)


# --------------------------------------------------------------------------- linking
def link_segments(
    u: ArrayLike,
    v: ArrayLike,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
) -> I64:
    """Chain centre points of consecutive rows into segments continuous along v.

    A point p in row v is linked to a point q in the first row v + g (g = 1 .. max_gap + 1)
    that has any point within ``max_du * g`` px of p's column, if q is the only such point
    there and p is likewise the only candidate in q's first non-empty row above. Ambiguities
    (two candidates), jumps and longer gaps break the chain. Vectorised with ``searchsorted``.

    Parameters
    ----------
    u, v : (K,) centre columns and rows (px); v is rounded to integer rows
    max_du : largest column change per row (px) within a segment
    max_gap : largest number of missing rows bridged
    min_length : segments with fewer points get label -1

    Returns
    -------
    labels : (K,) int64, segment id per point (0..S-1, ordered by the segments' mean u), -1 for
        points of too-short segments
    """
    uu = np.asarray(u, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    if uu.ndim != 1 or vv.shape != uu.shape:
        raise SlitExtractionError(
            f"u and v must be 1-D arrays of the same length, got {uu.shape} and {vv.shape}"
        )
    if not (np.isfinite(uu).all() and np.isfinite(vv).all()):
        raise SlitExtractionError("u and v must be finite")
    if not math.isfinite(max_du) or max_du < 0:
        raise SlitExtractionError(f"max_du must be >= 0, got {max_du}")
    if int(max_gap) != max_gap or max_gap < 0:
        raise SlitExtractionError(f"max_gap must be an integer >= 0, got {max_gap}")
    if int(min_length) != min_length or min_length < 1:
        raise SlitExtractionError(f"min_length must be an integer >= 1, got {min_length}")
    n = uu.size
    if n == 0:
        return np.empty(0, np.int64)
    rows = np.rint(vv)
    order = np.lexsort((uu, rows))
    us = uu[order] - uu.min()
    rs = rows[order] - rows.min()
    max_g = int(max_gap) + 1
    # key = row * span + u is sorted; span exceeds the u range plus the search tolerance, so a
    # search window never spills into another row
    span = float(us.max()) + 2 * max_du * max_g + 2.0
    key = rs * span + us
    idx = np.arange(n)

    def first_neighbour(sign: int) -> tuple[I64, I64]:
        """Per point: index of the unique candidate in the first non-empty row (-1 if none,
        -2 if ambiguous) and that row distance."""
        found = np.full(n, -1, np.int64)
        dist = np.zeros(n, np.int64)
        done = np.zeros(n, bool)
        for g in range(1, max_g + 1):
            tol = max_du * g
            centre = key + sign * g * span
            lo = np.searchsorted(key, centre - tol, "left")
            hi = np.searchsorted(key, centre + tol, "right")
            cnt = hi - lo
            new = ~done & (cnt > 0)
            found[new] = np.where(cnt[new] == 1, lo[new], -2)
            dist[new] = g
            done |= new
        return found, dist

    nxt, _ = first_neighbour(+1)
    prv, _ = first_neighbour(-1)
    has = nxt >= 0
    src = idx[has]
    dst = nxt[has]
    mutual = prv[dst] == src
    src, dst = src[mutual], dst[mutual]
    graph = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(n, n))
    _, comp = connected_components(graph, directed=True, connection="weak")
    size = np.bincount(comp)
    keep = size >= min_length
    mean_u = np.bincount(comp, weights=us) / size
    kept = np.flatnonzero(keep)
    new_id = np.full(size.size, -1, np.int64)
    new_id[kept[np.argsort(mean_u[kept], kind="stable")]] = np.arange(kept.size)
    labels = np.empty(n, np.int64)
    labels[order] = new_id[comp]
    return labels


# --------------------------------------------------------------------------- pipeline
def _empty_extraction(shape: tuple[int, int], noise: float, sw: float, ds: float) -> SlitExtraction:
    e = np.empty(0)
    return SlitExtraction(
        u=e,
        v=e.copy(),
        peak=e.copy(),
        width=e.copy(),
        segment=np.empty(0, np.int64),
        dots=np.zeros(shape, np.float32),
        noise_sigma=noise,
        stripe_width_px=sw,
        dot_size_px=ds,
    )


def extract_slits(
    image: ArrayLike,
    stripe_width_px: float | None = None,
    dot_size_px: float | None = None,
    *,
    method: str = "gaussian",
    k_sigma: float = DEFAULT_K_SIGMA,
    saturation_level: float | None = None,
    v_smooth: int = DEFAULT_V_SMOOTH,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
) -> SlitExtraction:
    """Stripe centre points, their segments and the dot image of one camera image.

    :func:`separate` -> :func:`find_stripe_centres` (threshold ``k_sigma`` times the highpass
    noise, saturated runs from the image) -> :func:`link_segments`; the dot image is cleaned of
    streaks by :func:`remove_streaks`. An image without slits
    gives an empty result (zero-length arrays), not an error.

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float grayscale
    stripe_width_px, dot_size_px : FWHMs (px); estimated from the image if None
    method : sub-pixel method, one of :data:`CENTRE_METHODS`
    k_sigma : detection threshold in noise sigmas
    saturation_level : camera saturation value (default dtype max for integer images)
    max_du, max_gap, min_length : see :func:`link_segments`

    Returns
    -------
    SlitExtraction

    Raises
    ------
    SlitExtractionError
        invalid image (not 2-D, empty, NaN/inf, bad dtype) or parameters.
    """
    img = _as_image(image)
    if method not in CENTRE_METHODS:
        raise SlitExtractionError(f"method must be one of {CENTRE_METHODS}, got {method!r}")
    if not math.isfinite(k_sigma) or k_sigma < 0:
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma}")
    sw = _positive(stripe_width_px, "stripe_width_px")
    ds = _positive(dot_size_px, "dot_size_px")
    if sw is None:
        try:
            est = estimate_stripe_width(img)
        except SlitExtractionError:
            est = None
        if est is None:  # nothing stripe-like: no slits
            return _empty_extraction(
                img.shape, estimate_noise(img), math.nan, ds if ds is not None else math.nan
            )
        sw = est
    if ds is None:
        hp0 = cv2.subtract(img, row_median_background(img, median_stride(sw)))
        ds = estimate_dot_size(hp0) or sw  # dots from the same optics: fall back to the stripe
    hp, slits, sat, noise = _separate(img, sw, ds, saturation_level)
    dots = remove_streaks(cv2.subtract(hp, slits), opening_length(ds)).astype(np.float32)
    centres = _find_centres(slits, k_sigma * noise, method, sat, sw, _taps(v_smooth))
    segment = link_segments(
        centres.u, centres.v, max_du=max_du, max_gap=max_gap, min_length=min_length
    )
    return SlitExtraction(
        u=centres.u,
        v=centres.v,
        peak=centres.peak,
        width=centres.width,
        segment=segment,
        dots=dots,
        noise_sigma=noise,
        stripe_width_px=sw,
        dot_size_px=ds,
    )


# --------------------------------------------------------------------------- refinement
#: Steger's smoothing sigma in :func:`refine_centres`, in units of the stripe's own sigma.
REFINE_STEGER_SCALE = 1.25


def _int_param(x: object, name: str, lo: int) -> int:
    if isinstance(x, bool) or not isinstance(x, int | np.integer) or int(x) < lo:
        raise SlitExtractionError(f"{name} must be an integer >= {lo}, got {x!r}")
    return int(x)


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
    noise = _noise_from_difference(img, bg)
    length = opening_length(dot_size_px)
    slope = stripe_slope(hp, slope_sigma(length))
    return _fill_dots(hp, vertical_opening(hp, length), 3.0 * noise, length, slope)


def refine_half_rows(stripe_width_px: float) -> int:
    """Default half window (rows) of :func:`refine_centres`: round(2.5 FWHM), at least 1.

    On the simulated rig (FWHM 3.4 px, half size, plane / steps / spheres) the 3D error falls
    from 3 to 9 rows a side and flattens beyond (12 rows: plane better, spheres worse).
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
    this dot refill mix the stripe with what lies beyond the end); fewer than ``degree + 2`` rows in
    the window; another stripe point in its row within the Steger kernel's reach
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
    degree : 0, 1 or 2, degree of the along-stripe polynomial
    max_shift_px : largest accepted move of a centre (px)
    steger_scale : Steger's smoothing sigma in stripe sigmas (FWHM / 2.355)
    end_rows : rows at each segment end left out; default :func:`opening_length` of the dot
        size (7 px for 1.9 px dots). 0 refines more points (simulated scenes at half size:
        plane 0.158 -> 0.152 mm, steps 0.224 -> 0.210 mm) but lets a 4 px stripe jump pull
        refined centres up to 0.54 px (0.03 px with the default)

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
    img = _as_image(image)
    h, w = img.shape
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
    sw = _positive(stripe_width_px, "stripe_width_px")
    if sw is None:
        raise SlitExtractionError("stripe_width_px must be given (a positive number of pixels)")
    ds = _positive(dot_size_px, "dot_size_px") or sw
    if not math.isfinite(max_shift_px) or max_shift_px <= 0:
        raise SlitExtractionError(f"max_shift_px must be > 0, got {max_shift_px}")
    if not math.isfinite(steger_scale) or steger_scale <= 0:
        raise SlitExtractionError(f"steger_scale must be > 0, got {steger_scale}")
    deg = _int_param(degree, "degree", 0)
    if deg > 2:
        raise SlitExtractionError(f"degree must be 0, 1 or 2, got {degree}")
    R = refine_half_rows(sw) if half_rows is None else _int_param(half_rows, "half_rows", 0)
    K = uu.size
    out = uu.copy()
    if K == 0:
        return out, np.zeros(0, bool)

    sigma = sw / FWHM_PER_SIGMA
    ss = max(steger_scale * sigma, 0.7)
    slit = refine_slit_image(img, sw, ds, 2 * R + 1, 2 * median_stride(sw) + 1)
    r = rows.astype(np.intp)
    # 1. Steger's centre in each row
    m = uu.copy()
    for _ in range(2):  # Newton steps
        d1, d2 = _steger_at(slit, np.clip(m, 0, w - 1), r, ss)
        good = d2 < 0
        m = m + np.clip(np.where(good, -d1 / np.where(good, d2, -1.0), 0.0), -1.0, 1.0)
    row_ok = good & (np.abs(m - uu) <= max_shift_px)

    # 2. along the stripe: rows of the same segment by a sorted (segment, row) key
    has = seg >= 0
    span = h + 2 * R + 2  # > row range + window: keys of two segments never meet
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
    # rows near a segment's end mix two stripes (and the dot refill acts across the end):
    # they neither get refined nor take part in other rows' fits
    end = opening_length(ds) if end_rows is None else _int_param(end_rows, "end_rows", 0)
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
        rhs += (wt * (m[nb] - uu))[:, None] * p[None, :n]
        count += found
    ok = has & (reach >= R // 2) & (inner >= 0) & (count >= min(deg + 2, 2 * R + 1))
    idx = np.arange(n)
    A = mom[:, idx[:, None] + idx[None, :]]  # (K, n, n) normal equations (Hankel)
    ok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(mom[:, 0], 1.0) ** n
    A[~ok] = np.eye(n)
    delta = np.linalg.solve(A, np.where(ok[:, None], rhs, 0.0)[..., None])[:, 0, 0]
    # another stripe within the kernel's reach in the same row: its flank biases the centre
    o = np.lexsort((uu, r))
    du = np.where(r[o][1:] == r[o][:-1], np.diff(uu[o]), np.inf)
    gap = np.full(K, np.inf)
    gap[o[:-1]] = du
    gap[o[1:]] = np.minimum(gap[o[1:]], du)
    ok &= gap >= 3.0 * ss + 2.5 * sigma
    ok &= np.abs(delta) <= max_shift_px
    out[ok] = uu[ok] + delta[ok]
    return out, ok

"""Separate the stripes (slits) from the dots on a flat background (paper, Fig. 11 c-e)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import trailing_zeros
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtri

from multislit.stripes.openings import stripe_opening, vertical_opening
from multislit.stripes.sizes import (
    estimate_dot_size,
    estimate_stripe_width,
    median_stride,
    opening_length,
)
from multislit.stripes.slope import LEAN_DECIMATION, _slopes_at, reflect101, slope_sigma
from multislit.stripes.validation import SlitExtractionError, as_image, positive_px
from multislit.summaries import Summarised

F32 = NDArray[np.float32]


@dataclass(frozen=True, eq=False, repr=False)
class Separation(Summarised):
    """Result of :func:`separate` (Fig. 11 c, d, e); all images (H, W) float32, intensity units.

    Attributes
    ----------
    highpass : image minus its row background, clipped at 0: stripes + dots (c)
    slits : ``highpass`` with the dots found by a vertical opening refilled along the stripe:
        the stripes only (d)
    dots : ``highpass - slits``: the dots only (e), >= 0
    saturated : (H, W) bool, pixels of saturated stripes (image >= saturation level, in vertical
        runs at least as long as the opening line); all False for float images that do not
        clip
    stripe_width_px : stripe FWHM (px) used to size the row background
    dot_size_px : dot FWHM (px) used to size the opening
    """

    highpass: F32
    slits: F32
    dots: F32
    saturated: NDArray[np.bool_]
    stripe_width_px: float
    dot_size_px: float

    def summary(self) -> str:
        """One line: image size, sizes used, saturated pixels."""
        h, w = self.slits.shape
        return (
            f"{w}x{h} px: stripes {self.stripe_width_px:.2f} px wide, dots "
            f"{self.dot_size_px:.2f} px, {int(np.count_nonzero(self.saturated))} saturated pixels"
        )


# Median of 9 by Devillard's 19 compare-exchange network ("Fast median search", 1998), pruned to
# the 30 min/max operations whose results are used: (i, j, keep_min, keep_max).
@njit(cache=True)
def _row_median(img: NDArray, stride: int) -> NDArray:
    """:func:`row_median_background`, row by row in one compiled pass."""
    h, w = img.shape
    pad = 4 * stride
    idx = np.empty(w + 2 * pad, np.intp)
    for k in range(w + 2 * pad):
        idx[k] = reflect101(k - pad, w) if pad < w else min(max(k - pad, 0), w - 1)
    out = np.empty_like(img)
    buf = np.empty(w + 2 * pad, img.dtype)
    for r in range(h):
        row = img[r]
        for k in range(w + 2 * pad):
            buf[k] = row[idx[k]]
        o = out[r]
        # 1-D views of the nine samples: the loop below vectorises
        b0, b1, b2 = buf[0:w], buf[stride : stride + w], buf[2 * stride : 2 * stride + w]
        b3, b4 = buf[3 * stride : 3 * stride + w], buf[4 * stride : 4 * stride + w]
        b5, b6 = buf[5 * stride : 5 * stride + w], buf[6 * stride : 6 * stride + w]
        b7, b8 = buf[7 * stride : 7 * stride + w], buf[8 * stride : 8 * stride + w]
        for c in range(w):
            p0, p1, p2, p3, p4 = b0[c], b1[c], b2[c], b3[c], b4[c]
            p5, p6, p7, p8 = b5[c], b6[c], b7[c], b8[c]
            # Devillard's median-of-9 network
            p1, p2 = min(p1, p2), max(p1, p2)
            p4, p5 = min(p4, p5), max(p4, p5)
            p7, p8 = min(p7, p8), max(p7, p8)
            p0, p1 = min(p0, p1), max(p0, p1)
            p3, p4 = min(p3, p4), max(p3, p4)
            p6, p7 = min(p6, p7), max(p6, p7)
            p1, p2 = min(p1, p2), max(p1, p2)
            p4, p5 = min(p4, p5), max(p4, p5)
            p7, p8 = min(p7, p8), max(p7, p8)
            p3 = max(p0, p3)
            p5 = min(p5, p8)
            p4, p7 = min(p4, p7), max(p4, p7)
            p6 = max(p3, p6)
            p4 = max(p1, p4)
            p2 = min(p2, p5)
            p4 = min(p4, p7)
            p4, p2 = min(p4, p2), max(p4, p2)
            p4 = max(p6, p4)
            o[c] = min(p4, p2)
    return out


def row_median_background(image: NDArray, stride: int) -> NDArray:
    """Row-wise sparse median background, same dtype as ``image`` (H, W).

    Median of the 9 pixels at u + stride * j (j = -4..4) of each row, by a sorting network in
    one compiled pass. Like any median it keeps steps (albedo edges) sharp; the image border
    is reflected (replicated where the samples reach past a narrow image).

    Parameters
    ----------
    image : (H, W) uint8, uint16 or float32
    stride : sample spacing (px), e.g. :func:`~multislit.stripes.sizes.median_stride`
    """
    return _row_median(np.ascontiguousarray(image), int(stride))


#: A float image is taken to resolve at most this many levels over its range (12 bits): the
#: quantisation step of float data whose values do not show one.
_FLOAT_LEVELS = 4096.0
#: Rows sampled (every n-th) to find the quantisation step of float data.
_STEP_SAMPLE = 4
#: Clip detection: the top of the histogram is read in ``_CLIP_BINS`` quantisation steps; the
#: bins from ``_CLIP_TAIL`` on are the tail below any clip. A clip is a top bin with at least
#: ``_MIN_CLIP_PIXELS`` pixels and ``_CLIP_EXCESS`` times the tail's median count; a spread
#: clip (JPEG rings around its flat tops, 250-255 for 255) extends down over at most
#: ``_MAX_CLIP_SPREAD`` bins that each hold clearly more than the tail (twice, plus 3 sigma).
_CLIP_BINS = 64
_CLIP_TAIL = 16
_MIN_CLIP_PIXELS = 20
_CLIP_EXCESS = 4.0
_MAX_CLIP_SPREAD = 12


def quantisation_step(img: NDArray) -> float:
    """The data's quantisation step (intensity units).

    For integer data the lowest bit any pixel uses: 1 for ordinary 8- and 16-bit data, 16 for
    12-bit data stored in the top bits of uint16. For float data the smallest step between
    the values of every ``_STEP_SAMPLE``-th row (1/255 for 8-bit data scaled to [0, 1]), but
    at least 1/4096 of their range.

    Parameters
    ----------
    img : (H, W) validated image (uint8, uint16 or float32)
    """
    if np.issubdtype(img.dtype, np.integer):
        bits = int(np.bitwise_or.reduce(img, axis=None))
        return float(bits & -bits) if bits else 1.0
    vals = np.unique(img[::_STEP_SAMPLE])
    span = float(vals[-1] - vals[0])
    floor = (span if span > 0 else max(abs(float(vals[0])), 1.0)) / _FLOAT_LEVELS
    if vals.size < 2:
        return floor
    return max(float(np.min(np.diff(vals.astype(np.float64)))), floor)


@njit(cache=True)
def _top_counts(img, first, top, step, bins):
    """Histogram (``bins``,) int64 of the pixels of ``img`` (H, W) from ``first`` (in the
    image's type: the least value within ``bins`` - 0.5 quantisation ``step``s of ``top``) up,
    by steps below ``top`` (rounded; the last bin takes the rest): one pass, no copies."""
    counts = np.zeros(bins, np.int64)
    h, w = img.shape
    for r in range(h):
        row = img[r]
        for c in range(w):
            if row[c] >= first:
                k = int(np.rint((top - float(row[c])) / step))
                counts[min(k, bins - 1)] += 1
    return counts


def clip_level(img: NDArray, step: float) -> float | None:
    """The level at which ``img`` clips, read from the data; None if nothing clips.

    A clip piles pixels up at the top of the histogram (flat tops of saturated stripes). A
    clean clip puts them all on the maximum; a JPEG rings around it, spreading them over the
    few values below (250-255 for 255), so the level is the lowest value of the pile-up.

    Parameters
    ----------
    img : (H, W) validated image
    step : quantisation step of ``img`` (:func:`quantisation_step`)
    """
    top = float(img.max())
    lo = top - (_CLIP_BINS - 0.5) * step
    if np.issubdtype(img.dtype, np.integer):
        first = img.dtype.type(max(math.ceil(lo), 0))  # <= top
    elif img.dtype == np.float32:  # the least float32 >= lo
        first = np.float32(lo)
        if float(first) < lo:
            first = np.nextafter(first, np.float32(np.inf))
    else:
        first = img.dtype.type(lo)
    counts = _top_counts(img, first, top, float(step), _CLIP_BINS)
    tail = float(np.median(counts[_CLIP_TAIL:]))
    if counts[0] < max(_MIN_CLIP_PIXELS, _CLIP_EXCESS * tail):
        return None
    excess = 2.0 * tail + 3.0 * math.sqrt(tail) + 2.0
    j = 0
    while j + 1 < _MAX_CLIP_SPREAD and counts[j + 1] > excess:
        j += 1
    return top - j * step


def saturation_level_of(img: NDArray) -> float | None:
    """The level at which ``img`` (H, W, validated) saturates, read from the data
    (:func:`clip_level`), else the dtype maximum for integer images; None for float data
    that does not clip."""
    return _saturation_level(img, None)


def _saturation_level(img: NDArray, saturation_level: float | None) -> float | None:
    """The saturation level: the given one, else the data's clip level (:func:`clip_level`),
    else the dtype maximum for integer images; None (no saturation) for float data that does
    not clip."""
    if saturation_level is not None:
        return float(saturation_level)
    level = clip_level(img, quantisation_step(img))
    if np.issubdtype(img.dtype, np.integer):
        top = float(np.iinfo(img.dtype).max)
        return top if level is None else min(level, top)
    return level


def mask_runs(d: NDArray[np.int8]) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Runs of ones along the rows of a 0/1 mask from ``d = np.diff(padded mask, axis=1)``.

    Returns row, start (first index in the padded-minus-one frame, i.e. the original column)
    and stop (one past the last) of every run, row-major. Starts (+1) and stops (-1) alternate
    in a row-major scan, so one flatnonzero finds both.
    """
    flat = np.flatnonzero(d)
    row, col = np.divmod(flat, d.shape[1])
    return row[0::2], col[0::2], col[1::2]


@njit(cache=True, inline="always")
def _row_interp(img: NDArray, r: int, u: float) -> np.float32:
    """Row ``r`` of ``img`` (H, W) interpolated linearly at column ``u`` (clamped to the
    row), in float32."""
    w = img.shape[1]
    u = min(max(u, 0.0), w - 1.0)
    u0 = min(int(u), w - 2) if w > 1 else 0  # u >= 0: int() is the floor
    return _row_lerp(img, r, u0, min(u0 + 1, w - 1), u)


@njit(cache=True, inline="always")
def _row_interp_inside(img: NDArray, r: int, u: float) -> np.float32:
    """:func:`_row_interp` at a column ``u`` in 0 .. W - 2 (the clamps change nothing)."""
    u0 = int(u)
    return _row_lerp(img, r, u0, u0 + 1, u)


@njit(cache=True, inline="always")
def _row_lerp(img: NDArray, r: int, u0: int, u1: int, u: float) -> np.float32:
    """Row ``r`` of ``img`` between columns ``u0`` and ``u1`` at column ``u``, in float32."""
    f = np.float32(u - u0)
    a = np.float32(img[r, u0])
    b = np.float32(img[r, u1])
    return np.float32(a + np.float32(np.float32(b - a) * f))


@njit(cache=True)
def _mask_runs_v(mask, words, cap):
    """The vertical runs of ``mask`` (H, W) pixels: column, start and stop (one past the
    last row) (K,) intp each, in the order of a row-major scan of their ends. ``words``
    (H, W / 8) uint64 is ``mask`` read 8 pixels at a time ((H, 0) if W is not a multiple of
    8): the bytes where a row's word differs from the one above are found by counting
    trailing zeros, the others are not looked at. ``cap``: at least the number of runs
    (e.g. the number of mask pixels)."""
    h, w = mask.shape
    nw = words.shape[1]
    # one spare slot: a changed byte writes run k whether or not it ends one
    cols = np.empty(cap + 1, np.intp)
    starts = np.empty(cap + 1, np.intp)
    stops = np.empty(cap + 1, np.intp)
    start = np.full(w, -1, np.intp)
    zero = np.uint64(0)
    byte = np.uint64(0xFF)
    k = 0
    for r in range(h + 1):
        for blk in range(nw):
            above = words[r - 1, blk] if r > 0 else zero
            here = words[r, blk] if r < h else zero
            x = above ^ here
            while x != zero:
                bit = trailing_zeros(x) & 56  # the changed byte's first bit
                x &= ~(byte << np.uint64(bit))
                cur = (here >> np.uint64(bit)) & byte != zero
                prev = (above >> np.uint64(bit)) & byte != zero
                # :func:`_run_edge` without branches (starts and ends come in no predictable
                # order): the run is written as run k always and kept only where it ends
                c = blk * 8 + bit // 8
                s0 = start[c]
                start[c] = r if cur and not prev else s0
                cols[k] = c
                starts[k] = s0
                stops[k] = r
                k += prev and not cur
        for c in range(8 * nw, w):  # no words: pixel by pixel
            cur = r < h and mask[r, c] != 0
            prev = r > 0 and mask[r - 1, c] != 0
            k = _run_edge(c, r, cur, prev, start, cols, starts, stops, k)
    return cols[:k], starts[:k], stops[:k]


@njit(cache=True, inline="always")
def _run_edge(c, r, cur, prev, start, cols, starts, stops, k):
    """One column ``c`` of :func:`_mask_runs_v` at row ``r``: a run starts where the pixel is
    set (``cur``) and the one above not (``prev``); it ends, and is written as run ``k``, where
    the one above is set and the pixel not. Returns the number of runs written."""
    if cur and not prev:
        start[c] = r
    elif prev and not cur:
        cols[k] = c
        starts[k] = start[c]
        stops[k] = r
        k += 1
    return k


@njit(cache=True)
def _fill_runs(hp, opened, cols, starts, stops, slopes, rint, out, lim, end_rows):
    """:func:`fill_dots`'s refill of the vertical runs of dot pixels (``cols``, ``starts``,
    ``stops`` (K,) of :func:`_mask_runs_v`) in ``out`` (a copy of ``hp``): a run touching the
    image border or longer than ``lim`` rows takes the opening ``opened``; the others are
    interpolated between the clean pixels t rows above and n + 1 - t rows below, shifted
    sideways along the stripe by the run's slope (``slopes`` (K,) float32 px per row; (0,) for
    straight above and below) and read by linear interpolation along their rows, no lower
    than the opening within ``end_rows`` of a stripe's end and over a run that is a whole
    stripe piece (:func:`_blend`); ``rint``: round, for integer images."""
    h, w = hp.shape
    for i in range(cols.size):
        c = cols[i]
        start = starts[i]
        stop = stops[i]
        n = stop - start
        if start == 0 or stop == h or n > lim:  # the opening, as the fallback
            for q in range(start, stop):
                out[q, c] = opened[q, c]
            continue
        den = float(np.float32(n + 1))
        # a run at least a line long whose opening keeps at least half its brightest pixel is
        # a stripe piece (speckle flagged on all of it), not dots on a faint string of their
        # own tails (a shorter run holds no line, so its opening keeps nothing of a piece);
        # only the stripes' ends kept (``end_rows``) read it
        whole = False
        if end_rows > 0 and 2 * n >= lim:
            fmax = 0.0
            hmax = 0.0
            for q in range(start, stop):
                fmax = max(fmax, float(opened[q, c]))
                hmax = max(hmax, float(hp[q, c]))
            whole = 2.0 * fmax >= hmax
        if slopes.size == 0:  # straight above and below
            above = np.float32(hp[start - 1, c])
            below = np.float32(hp[stop, c])
            for t in range(1, n + 1):
                out[start + t - 1, c] = _blend(
                    above,
                    below,
                    t / den,
                    rint,
                    hp[start + t - 1, c],
                    opened[start + t - 1, c],
                    t,
                    n + 1,
                    end_rows,
                    whole,
                )
            continue
        s = float(slopes[i])
        reach = abs(s) * (n + 1)  # no sample lies further from column c (NaN: none inside)
        if float(c) - reach >= 0.0 and float(c) + reach <= w - 2.0:
            # every sample inside the row: no clamping, the same values
            for t in range(1, n + 1):
                above = _row_interp_inside(hp, start - 1, float(c) - s * t)
                below = _row_interp_inside(hp, stop, float(c) + s * (n + 1 - t))
                out[start + t - 1, c] = _blend(
                    above,
                    below,
                    t / den,
                    rint,
                    hp[start + t - 1, c],
                    opened[start + t - 1, c],
                    t,
                    n + 1,
                    end_rows,
                    whole,
                )
            continue
        for t in range(1, n + 1):
            above = _row_interp(hp, start - 1, float(c) - s * t)
            below = _row_interp(hp, stop, float(c) + s * (n + 1 - t))
            out[start + t - 1, c] = _blend(
                above,
                below,
                t / den,
                rint,
                hp[start + t - 1, c],
                opened[start + t - 1, c],
                t,
                n + 1,
                end_rows,
                whole,
            )


@njit(cache=True, inline="always")
def _blend(above, below, frac, rint, here, floor, t, n1, end_rows, whole):
    """A refilled dot pixel of :func:`_fill_runs`, ``t`` rows below the sample ``above`` and
    ``n1`` - ``t`` above ``below``: ``above`` + (``below`` - ``above``) (in float32) times
    ``frac``, rounded where ``rint``, no darker than the opening ``floor`` where one sample
    reaches half of it and the other does not (a stripe's end) and the pixel is at most
    ``end_rows`` from the one that does, or where neither does and the run is ``whole`` (a
    stripe piece whose every pixel the speckle flagged), and no brighter than the pixel
    ``here``."""
    val = float(above) + float(np.float32(below - above)) * frac
    if rint:
        val = np.rint(val)
    if end_rows > 0:
        a, b, f = float(above), float(below), float(floor)
        if (
            (2.0 * a >= f > 2.0 * b and t <= end_rows)
            or (2.0 * b >= f > 2.0 * a and n1 - t <= end_rows)
            or (whole and f > 2.0 * a and f > 2.0 * b)
        ):
            val = max(val, f)
    return min(val, float(here))


#: A dot pixel lies above the opening by more than the dot threshold plus this fraction of
#: the opening (:func:`dot_mask`).
_DOT_OPENING_FRACTION = 0.05


def dot_mask(hp: NDArray, opened: NDArray, tau: float) -> NDArray[np.uint8]:
    """(H, W) uint8, 255 on the dot pixels :func:`fill_dots` refills: where ``opened`` lies
    below ``hp`` by more than ``tau`` plus 5 % of itself, widened by 1 px for the dots' tails.

    Float32 images in one compiled pass (:func:`_above_opening`, no float temporaries), the
    integer ones by OpenCV in their own type (saturating, as the comparison of integers needs).
    """
    # + 5 % of the opening: the opening flattens the top of a tilted stripe by
    # A (1 - exp(-(s (L - 1) / 2)^2 / (2 sigma^2))), ~2.5 % of its peak A at slope s = 0.1; that
    # is not a dot, and flagging whole stripe tops would make runs too long to interpolate
    if hp.dtype == np.float32 and opened.dtype == np.float32:
        mask = np.empty(hp.shape, np.uint8)
        _above_opening(hp, opened, np.float32(_DOT_OPENING_FRACTION), np.float32(tau), mask)
    else:
        diff = cv2.subtract(hp, opened)
        thr = cv2.addWeighted(opened, _DOT_OPENING_FRACTION, opened, 0.0, tau)
        mask = cv2.compare(diff, thr, cv2.CMP_GT, dst=diff if diff.dtype == np.uint8 else None)
    return cv2.dilate(mask, np.ones((3, 3), np.uint8))


@njit(cache=True)
def _above_opening(hp, opened, frac, tau, mask):
    """``mask`` (H, W) uint8: 255 where ``hp`` - ``opened`` > ``frac`` ``opened`` + ``tau``
    (float32 arithmetic; ``hp``, ``opened`` (H, W) float32), else 0."""
    h, w = hp.shape
    for r in range(h):
        x = hp[r]
        o = opened[r]
        m = mask[r]
        for c in range(w):
            m[c] = 255 if x[c] - o[c] > o[c] * frac + tau else 0


def _fill(
    hp: NDArray,
    opened: NDArray,
    tau: float,
    length: int,
    slope: NDArray | float | None,
    keep_ends: bool = False,
) -> NDArray:
    """:func:`fill_dots`; ``slope`` the slope image, None (straight above and below) or the
    integration scale (px, float) of the structure tensor that gives the slope where a run
    needs it (:func:`_slopes_at`)."""
    out = hp.copy()
    mask = dot_mask(hp, opened, tau)
    h, w = mask.shape
    words = mask.view(np.uint64) if w % 8 == 0 else np.zeros((h, 0), np.uint64)
    cols, starts, stops = _mask_runs_v(mask, words, max(cv2.countNonZero(mask), 1))
    lim = 2 * int(length)
    if slope is None:
        slopes = np.empty(0, np.float32)
    else:
        # the slope at the middle row of each run that is interpolated
        n = stops - starts
        inner = np.flatnonzero((starts > 0) & (stops < h) & (n <= lim))
        mids = starts[inner] + n[inner] // 2
        slopes = np.zeros(cols.size, np.float32)
        if isinstance(slope, np.ndarray):
            slopes[inner] = slope[mids, cols[inner]]
        else:
            slopes[inner] = _slopes_at(hp, slope, mids, cols[inner])
    rint = bool(np.issubdtype(hp.dtype, np.integer))
    end_rows = int(length) // 2 if keep_ends else 0
    _fill_runs(hp, opened, cols, starts, stops, slopes, rint, out, lim, end_rows)
    return out


def fill_dots(
    hp: NDArray,
    opened: NDArray,
    tau: float,
    length: int,
    slope: NDArray | None = None,
    keep_ends: bool = False,
) -> NDArray:
    """Slit image: ``hp`` with the dot pixels refilled by interpolation along the stripe.

    The opening alone distorts a tilted stripe's profile near a dot (the line windows that
    avoid the dot are off-centre, so they sample the stripe at a shifted position, ~0.1 px
    centre bias). Instead the opening only *finds* the dots (``hp - opened > tau + 5 %``, dilated by
    1 px for their tails); each vertical run of dot pixels in a column is replaced by linear
    interpolation between the clean rows just above and below it. With ``slope`` (px per row,
    :func:`~multislit.stripes.slope.stripe_slope`) those two samples are taken along the stripe (shifted sideways by the
    slope, interpolated along their rows), exact for a straight stripe of any lean; without it
    they are the pixels straight above and below, exact only for a vertical stripe (on a
    leaning stripe the speckle peaks along it are flagged too, and vertical interpolation would
    cut its core out).
    Runs longer than 2 ``length`` or touching the image border keep the opened value.
    With ``keep_ends``, where one of the two samples lies on a stripe (at least half the
    opening at the pixel) and the other does not, the interpolation is taken no lower than
    the opening over half the line's length from the stripe's side: near a stripe's end the
    sample beyond it is background, and the ramp down to it would cut the stripe's last rows
    out (the opening, a line of ``length`` px inside the stripe, keeps them; a dot is shorter
    than the line); and no further (where the stripe meets another one at an occlusion, its
    end kept whole would bridge the gap between them). Between two background samples it is
    taken no lower than the opening only where the run is a whole stripe piece: the opening
    keeps at least half of the run's brightest pixel. On a stripe piece shorter than two lines
    the laser speckle flags nearly every pixel (the test allows for noise, not for speckle),
    and the interpolation between the background above and below it would erase the piece;
    dots one above another off the stripes, whose opening is the faint string of their own
    tails, stay interpolated.
    The result is clipped to ``hp`` so that ``hp - slits >= 0``. One compiled pass over the
    dot mask.

    Parameters
    ----------
    hp : (H, W) highpass image, uint8, uint16 or float32
    opened : (H, W) its vertical opening (:func:`~multislit.stripes.openings.vertical_opening`), same dtype
    tau : dot threshold above the opening (intensity units)
    length : the opening's line length (px)
    slope : (H, W) stripe slope (px per row, :func:`~multislit.stripes.slope.stripe_slope`) or None

    Returns
    -------
    (H, W) slit image, dtype of ``hp``
    """
    sl = None if slope is None else np.asarray(slope, np.float32)
    return _fill(hp, opened, tau, length, sl, keep_ends)


#: Background estimators of :func:`separate`; the first is the default.
BACKGROUNDS = ("opening", "median")
#: Length of the row opening (``background="opening"``), in stripe widths (FWHMs): it passes
#: under a stripe up to 1.4 times as wide (a Gaussian falls to 1.3 % of its peak 1.25 of its
#: FWHMs from its centre), and a stripe twice as wide (a surface the projector grazes) loses
#: the lowest 12 % of its height; where stripes lie closer than the line, it rests in the
#: troughs between them, as a median does not.
OPENING_WIDTHS = 3.5
#: The photo mode's row opening (``extract_slits(..., reject_texture=True)``), in stripe
#: widths: shorter, to follow the squares of a checkerboard (measured on the photos of
#: ``tests/test_real_images.py``: a line over the squares found in 88 and 98 % of its rows
#: with 2.5 widths, 55 and 44 % with 3.5).
PHOTO_OPENING_WIDTHS = 2.5
#: The scans' row opening is lifted by the median of the image less it over the pixels within
#: this many noise sigmas above it: the background's own level, where the opening follows the
#: noise's minima.
LIFT_SIGMAS = 3.0
#: Every n-th row and column is read for that median.
_LIFT_STRIDE = 4


def row_opening_background(
    image: NDArray, stripe_width_px: float, widths: float = OPENING_WIDTHS
) -> NDArray:
    """Row-wise grey opening with a horizontal line of ``widths`` stripe widths (odd, px;
    default :data:`OPENING_WIDTHS`), same dtype as ``image`` (H, W).

    The opening is the largest image below ``image`` that is made of flat pieces at least
    that long: it passes under every narrower bright feature (a stripe) and follows wider ones
    (checker squares, a board's margin) and every edge exactly, so ``image`` minus it (a white
    top-hat) keeps the stripes and leaves no step, plateau or ripple.
    """
    length = 2 * math.ceil(widths * stripe_width_px / 2.0) + 1
    return cv2.morphologyEx(image, cv2.MORPH_OPEN, np.ones((1, length), np.uint8))


def lifted_opening_background(
    image: NDArray, stripe_width_px: float, noise: float | None = None
) -> NDArray:
    """The row opening (:func:`row_opening_background`) raised to the background's level,
    same dtype as ``image`` (H, W).

    The opening's flat pieces rest on the lowest pixels of the noise, about a noise sigma
    below its mean: ``image`` less it keeps that sigma everywhere, which single pixels then
    exceed on noise and on the rounded top of an albedo step. It is raised by the median of
    ``image`` less it over the pixels less than :data:`LIFT_SIGMAS` noise sigmas above it
    (:func:`noise_from_difference`; every :data:`_LIFT_STRIDE`-th row and column), rounded to
    the data's step for integer images. ``noise``: :func:`noise_from_difference` of
    ``image`` if already known.
    """
    if noise is None:
        noise = noise_from_difference(image)
    bg = row_opening_background(image, stripe_width_px)
    d = cv2.subtract(image[::_LIFT_STRIDE, ::_LIFT_STRIDE], bg[::_LIFT_STRIDE, ::_LIFT_STRIDE])
    low = d[d < LIFT_SIGMAS * noise]
    if not low.size:
        lift = 0.0
    elif np.issubdtype(low.dtype, np.integer):  # from the values' counts: no sort
        lift = _median_of_counts(np.bincount(low))
    else:
        lift = float(np.median(low))
    if np.issubdtype(bg.dtype, np.integer):
        lift = round(lift)
    return cv2.add(bg, np.full_like(bg, lift)) if lift > 0 else bg


def background_validated(
    img: NDArray,
    stripe_width_px: float,
    background: str,
    widths: float | None = None,
    noise: float | None = None,
) -> NDArray:
    """The row background of :func:`separate`'s ``background`` method (validated arguments):
    for ``"opening"`` the lifted opening (:func:`lifted_opening_background`; ``noise`` its
    noise sigma if already known), or with ``widths`` given the plain opening with a line of
    that many stripe widths (the photo mode's)."""
    if background == "opening":
        if widths is not None:
            return row_opening_background(img, stripe_width_px, widths)
        return lifted_opening_background(img, stripe_width_px, noise)
    return row_median_background(img, median_stride(stripe_width_px))


def dot_size_validated(img: NDArray, stripe_width_px: float, bg: NDArray | None = None) -> float:
    """The dots' FWHM (px) of :func:`~multislit.stripes.sizes.estimate_dot_size`, read on the
    image less ``bg``; the stripe width (dots from the same optics) where no dot is found.

    ``bg`` None (default): the row median. Clipped at 0, it leaves the troughs between the
    stripes at 0 and the dots alone on them; less the row opening, the troughs keep their
    noise, which the dots' scale selection along the columns takes for wider dots (measured on
    the reference boards of tuning rigs 0, 1, 10, 11, 13, over the opening not lifted:
    1.7-2.1 px read as 1.9-2.9 px).
    """
    if bg is None:
        bg = background_validated(img, stripe_width_px, "median")
    return estimate_dot_size(cv2.subtract(img, bg)) or stripe_width_px


def _at_least(img: NDArray, level: float) -> NDArray[np.bool_]:
    """``img >= level`` (H, W) bool; an integer image is compared in its own type (the same
    pixels, without a float copy)."""
    if np.issubdtype(img.dtype, np.integer) and math.isfinite(level):
        info = np.iinfo(img.dtype)
        first = math.ceil(level)
        if first > info.max:
            return np.zeros(img.shape, bool)
        return img >= img.dtype.type(max(first, info.min))
    return img >= level


def separate_validated(
    img: NDArray,
    stripe_width_px: float,
    dot_size_px: float,
    saturation_level: float | None,
    background: str = "opening",
    bg: NDArray | None = None,
    lean_decimation: int = LEAN_DECIMATION,
    keep_ends: bool = False,
    noise: float | None = None,
) -> tuple[NDArray, NDArray, NDArray, float]:
    """Core of :func:`separate` on a validated image, native dtype (exact integer arithmetic).

    ``bg``: the row background (:func:`background_validated`) if already made; ``noise``:
    :func:`noise_from_difference` of ``img`` if already known;
    ``lean_decimation``: the cell (px) of the lean map the opening follows the stripes by
    (:func:`~multislit.stripes.openings.stripe_opening`); ``keep_ends``: the refill keeps the
    stripes' ends (:func:`fill_dots`).
    Returns highpass, slits, saturated mask, noise sigma of the highpass.
    """
    if bg is None:
        bg = background_validated(img, stripe_width_px, background)
    hp = cv2.subtract(img, bg)  # saturates at 0 for integer images
    if hp.dtype == np.float32:
        np.maximum(hp, 0, out=hp)
    if noise is None:
        noise = noise_from_difference(img)
    length = opening_length(dot_size_px)
    # vertical, and along the stripe where it leans too far for the vertical line
    opened = stripe_opening(hp, length, 3.0 * noise, decimation=lean_decimation)
    # dot pixels: more than 3 noise sigmas above the opening (0.1 % false alarms on background;
    # false alarms on stripes are harmless, they are interpolated from their neighbours along
    # the stripe's local slope)
    slits = _fill(hp, opened, 3.0 * noise, length, slope_sigma(length), keep_ends)
    level = _saturation_level(img, saturation_level)
    if level is None:
        sat = np.zeros(img.shape, bool)
    else:
        sat = _at_least(img, level).view(np.uint8)
        # keep saturated runs that are stripes (vertically long), not saturated dots
        sat = vertical_opening(sat, length).view(bool)
    return hp, slits, sat, noise


@njit(cache=True)
def _pair_diff_histogram(img, levels):
    """Histogram (``levels``,) int64 of |img[2 i + 1] - img[2 i]| over rows pairs (i) and
    columns of an integer image. Four partial histograms, one per column mod 4, summed at
    the end: consecutive pixels do not wait on each other's counts."""
    h, w = img.shape
    part = np.zeros((4, levels), np.int64)
    for i in range(h // 2):
        a = img[2 * i]
        b = img[2 * i + 1]
        c = 0
        while c + 4 <= w:
            for j in range(4):
                x = int(a[c + j])
                y = int(b[c + j])
                part[j, x - y if x >= y else y - x] += 1
            c += 4
        while c < w:
            x = int(a[c])
            y = int(b[c])
            part[0, x - y if x >= y else y - x] += 1
            c += 1
    return part[0] + part[1] + part[2] + part[3]


def _median_of_counts(counts: NDArray[np.int64]) -> float:
    """The median (as :func:`numpy.median` gives it) of the whole numbers 0, 1, ... counted
    ``counts[k]`` times each (at least one)."""
    cum = np.cumsum(counts)
    n = int(cum[-1])
    hi = int(np.searchsorted(cum, n // 2 + 1))  # the (n // 2)-th smallest (0-based)
    return float(hi) if n % 2 else 0.5 * (int(np.searchsorted(cum, n // 2)) + hi)


def noise_from_difference(img: NDArray) -> float:
    """Pixel noise sigma from differences of vertical neighbours (intensity units).

    The stripes run along v, so a pixel minus the one below cancels them (and the background);
    what is left is noise, plus dots and stripe bends, which are a minority that the median
    ignores. Unlike the spread of ``img - bg`` this does not depend on how well the background
    was estimated (a row median lifted by dense stripes).

    The result is at least one quantisation step of the data (:func:`quantisation_step`): a
    JPEG smooths the noise away but leaves errors of about a step (block edges, ringing), and
    the median of quantised differences collapses to 0 where most neighbours are equal.
    """
    if img.dtype in (np.uint8, np.uint16) and img.shape[0] >= 2:
        # integer data: the median from the histogram of the differences (no sort)
        med = _median_of_counts(_pair_diff_histogram(img, int(np.iinfo(img.dtype).max) + 1))
    else:
        d = img[1::2].astype(np.float32) - img[:-1:2].astype(np.float32)
        med = float(np.median(np.abs(d)))
    sigma = 1.4826 * med / math.sqrt(2.0)
    return max(sigma, quantisation_step(img))


#: The noise by background level (:func:`noise_by_level`) is measured in this many bins, even
#: in the square root of the level ...
_LEVEL_BINS = 24
#: ... a bin of fewer than this many samples saying nothing ...
_LEVEL_MIN_COUNT = 500
#: ... on every this-many-th column of every this-many-th pair of rows.
_LEVEL_STRIDE = 2
#: The differences are counted up to this many quantisation steps (the last count holds the
#: rest).
_LEVEL_STEPS = 64
#: A level's noise is taken as no less than this share of the frame's.
LEVEL_NOISE_FLOOR = 0.35


#: An image whose differences across the rows of JPEG's 8 x 8 blocks exceed those within them
#: by more than this factor (the median over the bands of blocks, :func:`shows_jpeg_blocks`)
#: was compressed ...
_BLOCK_RATIO = 1.05
#: ... read on every this-many-th column.
_BLOCK_STRIDE = 4


def shows_jpeg_blocks(img: NDArray) -> bool:
    """Whether the image shows the 8 x 8 blocks of a JPEG (or another block transform): per
    band of 8 rows, the mean absolute difference between its last row and the next band's
    first over that of its own neighbouring rows; the median over the bands exceeds
    :data:`_BLOCK_RATIO` (on the simulator's frames 0.97-1.02 raw, 0.97-1.17 at JPEG quality
    98, 1.09-1.32 at 95, 1.19-1.52 at 90; a scene's edge moves a band or two, not the median).
    A compressed image's errors (a step or so, shaped like the image) do not show in its
    differences: its noise is not measured there.
    """
    nb = (img.shape[0] - 1) // 8
    if nb < 2:
        return False
    a = img[: 8 * nb + 1, ::_BLOCK_STRIDE].astype(np.float32)
    m = np.abs(np.diff(a, axis=0)).mean(axis=1).reshape(nb, 8)  # row 8 j + i to 8 j + i + 1
    inside = m[:, :7].mean(axis=1)
    ratio = m[:, 7] / np.maximum(inside, 1e-12)
    return bool(np.median(ratio[inside > 0]) > _BLOCK_RATIO) if np.any(inside > 0) else False


def _robust_sigma(hist: NDArray) -> float:
    """The sigma (in units) of a normal whose absolute values, rounded to whole units, have
    the histogram ``hist`` (0, 1, ... units): from the share P of them up to the first whole j
    that holds half, sigma = (j + 1/2) / Phi^-1((1 + P) / 2) (the median absolute deviation,
    read on rounded values, as integer data gives them); dots and stripe edges, a minority,
    move it little."""
    cum = np.cumsum(hist) / max(float(hist.sum()), 1.0)
    j = int(np.searchsorted(cum, 0.5))
    p = min(float(cum[min(j, cum.size - 1)]), 1.0 - 1e-9)
    return (j + 0.5) / float(ndtri(0.5 * (1.0 + p)))


@njit(cache=True)
def _level_histograms(img, bg, stride, nbins, top, unit):
    """:func:`noise_by_level`'s samples: the pairs of rows (r, r + 1) for every
    ``2 stride``-th r, every ``stride``-th column, binned by the square root of their mean
    background (``nbins`` even bins up to ``top``): per bin the histogram of their absolute
    difference in whole ``unit``s (:data:`_LEVEL_STEPS` columns, the last taking the rest),
    and the sum of their levels."""
    hist = np.zeros((nbins, _LEVEL_STEPS), np.int64)
    lsum = np.zeros(nbins)
    h, w = img.shape
    scale = nbins / top if top > 0.0 else 0.0
    for r in range(0, h - 1, 2 * stride):
        for c in range(0, w, stride):
            lv = 0.5 * (float(bg[r, c]) + float(bg[r + 1, c]))
            b = int(math.sqrt(max(lv, 0.0)) * scale)
            b = min(max(b, 0), nbins - 1)
            q = int(abs(float(img[r + 1, c]) - float(img[r, c])) / unit + 0.5)
            hist[b, min(q, _LEVEL_STEPS - 1)] += 1
            lsum[b] += lv
    return hist, lsum


def noise_by_level(
    img: NDArray, background: NDArray, noise: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The pixel noise as it grows with the background's level (shot noise), relative to the
    frame's (:func:`noise_from_difference`).

    The differences of vertical neighbours (as :func:`noise_from_difference` takes them, on
    every :data:`_LEVEL_STRIDE`-th column of every :data:`_LEVEL_STRIDE`-th pair of rows) are
    binned by the row background's level at them (:data:`_LEVEL_BINS` bins even in the square
    root of the level, as the shot noise's sigma grows). Per bin the noise is the robust sigma
    of the differences read on whole units (:func:`_robust_sigma`; a unit is the quantisation
    step, or an eighth of the frame's noise where that is more), over the square root of 2:
    the noise before the pixels' rounding, which is then added back (a step over the square
    root of 12). The frame's median of differences is a whole step or
    more on integer data; on a dark surface of an 8-bit image the noise is about half a grey
    level.

    Parameters
    ----------
    img : (H, W) validated image
    background : (H, W) its row background (intensity units)
    noise : the frame's pixel noise sigma (intensity units)

    Returns
    -------
    levels : (B,) float64, intensity units, the bins' mean background levels (increasing)
    scale : (B,) float64, each level's noise over ``noise``, between
        :data:`LEVEL_NOISE_FLOOR` and 1 (a level is never taken as noisier than the frame)
    """
    if img.shape[0] < 2 or not noise > 0:
        return np.zeros(1), np.ones(1)
    step = quantisation_step(img)
    unit = max(step, noise / 8.0)
    top = math.sqrt(max(float(background.max()), 0.0))
    hist, lsum = _level_histograms(img, background, _LEVEL_STRIDE, _LEVEL_BINS, top, unit)
    # bins even in the square root of the level; those of fewer than _LEVEL_MIN_COUNT samples
    # say nothing (the levels between the others are interpolated)
    counts = hist.sum(axis=1)
    keep = counts >= _LEVEL_MIN_COUNT
    if not keep.any():
        return np.zeros(1), np.ones(1)
    levels = lsum[keep] / counts[keep]
    sigma = np.array([_robust_sigma(x) for x in hist[keep]]) * unit / math.sqrt(2.0)
    scale = np.sqrt(sigma**2 + step**2 / 12.0) / noise
    # the noise does not fall as the level rises (read noise plus shot noise), and a level's
    # texture (an albedo's grain, edges) only adds to its spread: the lower envelope
    scale = np.minimum.accumulate(scale[::-1])[::-1]
    return levels, np.clip(scale, LEVEL_NOISE_FLOOR, 1.0)


def separate(
    image: ArrayLike,
    stripe_width_px: float | None = None,
    dot_size_px: float | None = None,
    *,
    saturation_level: float | None = None,
    channel: str = "red",
    background: str = "opening",
    order: str = "rgb",
) -> Separation:
    """Split an image into stripes (slits) and dots on a flat background (paper Fig. 11).

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB image, uint8, uint16 or float
    stripe_width_px : stripe FWHM along the row (px); estimated by
        :func:`estimate_stripe_width` if None. Sizes the row background.
    dot_size_px : dot FWHM (px); estimated by :func:`estimate_dot_size` if None (falling back
        to the stripe width). Sizes the opening (:func:`opening_length`).
    saturation_level : pixel value at which the camera saturates; default read from the data
        (:func:`clip_level`: the pile-up of flat tops at the top of the histogram, e.g. 250
        for a JPEG that rings around 255), else the dtype maximum for integer images and none
        for float images.
    channel : the plane of a colour image (:data:`~multislit.stripes.validation.CHANNELS`);
        default ``"red"``
    background : how the row background is estimated, one of :data:`BACKGROUNDS`:
        ``"opening"`` (default), the row opening lifted to the background's level
        (:func:`lifted_opening_background`), which passes under every stripe however close
        its neighbours lie and follows every edge and wider patch; or ``"median"``, the
        paper's sparse row median (:func:`row_median_background`), which sits on the
        stripes' flanks where they cover half its window (~8 stripe widths: many slits, or a
        face the slits cross at a slant)
    order : {'rgb', 'bgr'}
        The order of a colour image's planes (``"bgr"`` for ``cv2.imread``'s arrays); default
        ``"rgb"``

    Returns
    -------
    Separation
        highpass, slits, dots (H, W) float32, saturated (H, W) bool, sizes used.

    Raises
    ------
    SlitExtractionError
        bad image or sizes, or no stripe to estimate the width from.
    """
    # one contiguous plane: OpenCV and the compiled kernels read rows (a colour image's plane
    # is a strided view)
    img = np.ascontiguousarray(as_image(image, channel=channel, order=order))
    if background not in BACKGROUNDS:
        raise SlitExtractionError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    sw = positive_px(stripe_width_px, "stripe_width_px")
    ds = positive_px(dot_size_px, "dot_size_px")
    if sw is None:
        sw = estimate_stripe_width(img)
    bg = background_validated(img, sw, background)
    if ds is None:
        ds = dot_size_validated(img, sw, bg if background == "median" else None)
    hp, slits, sat, _ = separate_validated(img, sw, ds, saturation_level, background, bg)
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

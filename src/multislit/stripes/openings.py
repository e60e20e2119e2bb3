"""Grey openings with line structuring elements: the vertical opening that finds the dots on
upright stripes, the opening that follows a leaning stripe, and the streak removal of the dot
image (paper, section 4.1, Fig. 11)."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.stripes.slope import LEAN_DECIMATION, lean_map, slope_sigma


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
    """Grey opening with a vertical line of odd ``length`` px (erosion then dilation);
    out-of-image samples are ignored. OpenCV's opening with a (length, 1) rectangle for the
    types it takes (min and max are exact: the same values as :func:`_running_extreme`)."""
    if length <= 1:
        return x.copy()
    if x.dtype in (np.uint8, np.uint16, np.float32, np.float64):
        return cv2.morphologyEx(x, cv2.MORPH_OPEN, np.ones((int(length), 1), np.uint8))
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
    # (Python's round() rounds 1.5 and 2.5 both to 2: 15 and 30 deg would be one kernel)
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
        out = o if out is None else cv2.max(out, o, dst=out)
    return cv2.subtract(dots, out, dst=out)


#: Directions (deg from the vertical) the opening follows a leaning stripe in: a stripe leaning
#: more than half a step (7.5 deg) from upright is opened along the nearest of them.
FOLLOW_ANGLES_DEG = (-60.0, -45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0, 60.0)


def _follow_offsets(length: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The digital lines of :func:`line_kernel` at :data:`FOLLOW_ANGLES_DEG`: (A, n, 2) int64
    (row, column) offsets from the kernel's centre, and (A,) the number of pixels of each."""
    r = (length - 1) // 2
    lines = [np.argwhere(line_kernel(length, a)) - r for a in FOLLOW_ANGLES_DEG]
    offs = np.zeros((len(lines), max(len(p) for p in lines), 2), np.int64)
    for i, p in enumerate(lines):
        offs[i, : len(p)] = p
    return offs, np.array([len(p) for p in lines], np.int64)


@njit(cache=True)
def _follow_lines(angles):
    """The line each cell is opened along: ``angles`` (H // D, W // D) float32 or float64,
    deg, rounded (half to even) to the nearest of :data:`FOLLOW_ANGLES_DEG` (beyond them, the
    outermost); (H // D, W // D) int64 its index, -1 where that is upright or the angle is NaN;
    and whether any cell leans."""
    step = FOLLOW_ANGLES_DEG[1] - FOLLOW_ANGLES_DEG[0]
    last = len(FOLLOW_ANGLES_DEG) - 1
    mid = last // 2
    line = np.empty(angles.shape, np.int64)
    leaning = False
    for r in range(angles.shape[0]):
        for c in range(angles.shape[1]):
            a = np.float64(angles[r, c])
            k = mid
            if not np.isnan(a):
                q = np.rint(a / step) + mid
                k = 0 if q < 0 else (last if q > last else int(q))
            if k == mid:
                line[r, c] = -1
            else:
                line[r, c] = k
                leaning = True
    return line, leaning


@njit(cache=True)
def _follow_cells(hp, opened, line, f, offs, count, tau):
    """:func:`follow_stripe_opening` on the cells with a line (``line`` (H // f, W // f) int64,
    the index into ``offs``, -1: upright): at each of their pixels where ``opened`` lies below
    ``hp`` by more than ``tau`` plus 5 % of itself, ``opened`` is raised to the grey opening
    of ``hp`` with the cell's line: the largest, over the line's placements that cover the
    pixel, of the smallest sample under the placement (samples outside the image ignored, as
    OpenCV ignores its border), i.e. the erosion with the line, then the dilation with the line
    reflected (some digital lines are not symmetric about their centre)."""
    h, w = hp.shape
    nr, nc = line.shape
    for cr in range(nr):
        r1 = h if cr == nr - 1 else (cr + 1) * f
        for cc in range(nc):
            b = line[cr, cc]
            if b < 0:
                continue
            n = count[b]
            c1 = w if cc == nc - 1 else (cc + 1) * f
            for r in range(cr * f, r1):
                for c in range(cc * f, c1):
                    o = float(opened[r, c])
                    if float(hp[r, c]) - o <= tau + 0.05 * o:
                        continue
                    best = -np.inf
                    for j in range(n):
                        qr = r - offs[b, j, 0]
                        qc = c - offs[b, j, 1]
                        if qr < 0 or qr >= h or qc < 0 or qc >= w:
                            continue
                        low = np.inf
                        for k in range(n):
                            sr = qr + offs[b, k, 0]
                            sc = qc + offs[b, k, 1]
                            if 0 <= sr < h and 0 <= sc < w:
                                low = min(low, float(hp[sr, sc]))
                        best = max(best, low)
                    if best > o:
                        opened[r, c] = best


def follow_stripe_opening(
    hp: NDArray, opened: NDArray, length: int, angles: NDArray, decimation: int, tau: float
) -> None:
    """Where a stripe leans, open ``hp`` along it instead of vertically (in place).

    A vertical line of ``length`` px fits inside an upright stripe but not inside one leaning
    further than about a stripe width over the line: there the vertical opening cuts the
    stripe, and the stripe would be taken for dots. Where the stripes lean by more than 7.5 deg
    (``angles``), at the pixels where ``opened`` lies below ``hp`` by more than the dot
    threshold (``tau`` plus 5 % of the opening), ``opened`` is raised to the opening of ``hp``
    with a line of the same length along the nearest of :data:`FOLLOW_ANGLES_DEG`; a dot is
    shorter than the line in every direction, so it stays below the opening either way.

    Parameters
    ----------
    hp : (H, W) highpass image (uint8, uint16 or float32)
    opened : (H, W) its vertical opening (:func:`vertical_opening`), same dtype; updated
    length : int, px, the opening's line length
    angles : (H // D, W // D) float, deg from the vertical (positive leaning right going
        down), the stripes' direction per cell of D x D px
        (:func:`~multislit.stripes.slope.lean_map`; the last row and column of cells take
        the image's remainder); NaN where there is none (the vertical opening stays)
    decimation : int, D, px
    tau : float, intensity units, the dot threshold above the opening
    """
    ang = np.asarray(angles)
    if ang.dtype != np.float32:
        ang = ang.astype(np.float64)
    if length <= 1:
        return
    line, leaning = _follow_lines(np.ascontiguousarray(ang))
    if not leaning:
        return
    offs, count = _follow_offsets(int(length))
    _follow_cells(hp, opened, line, int(decimation), offs, count, float(tau))


def stripe_opening(
    hp: NDArray,
    length: int,
    tau: float,
    *,
    cells: NDArray[np.bool_] | None = None,
    decimation: int = LEAN_DECIMATION,
) -> NDArray:
    """The opening that finds the dots: ``hp``'s grey opening with a line of ``length`` px,
    vertical (:func:`vertical_opening`), along the stripe where it leans
    (:func:`follow_stripe_opening` at the pixels the vertical one lowers by more than the dot
    threshold ``tau``; the direction from :func:`~multislit.stripes.slope.lean_map`).

    Parameters
    ----------
    hp : (H, W) highpass image (uint8, uint16 or float32)
    length : int, px, the line's length
    tau : float, intensity units, the dot threshold above the opening
    cells : (H // D, W // D) bool, the cells of :func:`~multislit.stripes.slope.lean_map`
        (D = ``decimation``) where the opening follows
        leaning stripes; elsewhere it stays vertical. The opening along a line is made pixel by
        pixel, so inside the cells it equals the one made everywhere. Default None: every cell
    decimation : int, D, px, the lean map's cell (:func:`~multislit.stripes.slope.lean_map`);
        default :data:`~multislit.stripes.slope.LEAN_DECIMATION`

    Returns
    -------
    (H, W) the opening, dtype of ``hp``
    """
    opened = vertical_opening(hp, length)
    angles = lean_map(hp, slope_sigma(length), decimation)
    if cells is not None:
        if cells.shape != angles.shape:
            raise ValueError(f"cells must have the lean map's shape {angles.shape}")
        angles[~cells] = np.nan
    follow_stripe_opening(hp, opened, length, angles, decimation, tau)
    return opened

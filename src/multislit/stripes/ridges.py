"""Stripes at any angle: the column-wise pass for stripes that lean towards the horizontal.

The row-wise extraction (:func:`~multislit.stripes.separation.separate`,
:func:`~multislit.stripes.centres.find_stripe_centres`,
:func:`~multislit.stripes.linking.link_segments`) is made for stripes that run roughly along
the image's columns: a grey opening along each row estimates the background, a vertical
line opening finds the dots, each row's maxima are the centres, and the centres of
consecutive rows are linked. A stripe leaning far towards the horizontal (the top of a box on
a conveyor, seen by a rig whose baseline lies along the rows) defeats each of these steps:
along a row it is many stripe widths long, so the row background takes it in, the
vertical opening takes it for dots, and a row's maximum on it is anywhere along it. Turned by
90 degrees it is a stripe like any other.

:func:`column_pass` runs the same steps on the transposed image (the background along each
column is its grey opening, with a line of :data:`COLUMN_OPENING_WIDTHS` stripe widths), with
one change for the stripes it is for: the opening that finds the dots follows the stripes'
lean read on the image decimated :data:`_LEAN_DECIMATION` times, not 4 (:func:`~multislit.stripes.slope.
lean_map`: dense stripes read far too upright on the coarser grid). Its centres lie at whole
columns with a sub-pixel row. A stripe near the vertical is only a few columns wide: along a
column it is no narrow ridge, and what maxima it leaves link over fewer columns than a
segment needs. Where the pass runs is found by a quick look along the columns
(:func:`leaning_regions`: maxima down to :data:`WEAK_FRACTION` of the threshold, in runs that
cross no stripe of the row pass). In each
region its centres are the ridge response's, as in the row pass
(:func:`~multislit.stripes.centres.find_ridge_centres_validated`: a matched filter across the
stripe integrated along its lean, such stripes being dim); they are linked column to column
along the stripes' lean (``link_segments(v, u, slope=...)``), the pieces that continue one
another along the stripe are joined (:func:`join_collinear`), and the segments are kept that
are at least :data:`MIN_LENGTH_FACTOR` times as long as the row pass's, that a single pixel
shows above the threshold somewhere (:func:`strong_segments`) and through which no stripe of
the row pass runs (:func:`through_row_stripes`).

:func:`merge_passes` joins the two passes' points into one set in which each segment is one
stripe piece found by one pass. Where both found one stripe (a stripe leaning 35-55 degrees is
within reach of both linkings), its points go to the pass along whose direction the stripe
leans less: the row pass up to 45 degrees from the vertical, the column pass beyond. This is
decided per pair of segments over all the points they share, so a stripe close to 45 degrees
is not cut into short pieces that alternate between the passes. Every linked point carries
the stripe's direction there (:func:`chain_angles`: a line fitted to its segment's points
around it).

Units: px; angles in radians from the image's vertical, positive where the stripe leans to the
right going down (u grows with v), in (-pi/2, pi/2].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.stripes.centres import StripeCentres, find_ridge_centres_validated, row_maxima
from multislit.stripes.chains import drop_short, lex_order, link_segments, link_weak, run_end
from multislit.stripes.openings import remove_streaks
from multislit.stripes.response import ridge_threshold
from multislit.stripes.separation import (
    row_opening_background,
    saturation_level_of,
    separate_validated,
)
from multislit.stripes.sizes import opening_length

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Points on either side of a point in the line fitted along its segment for its direction.
ANGLE_HALF_WINDOW = 4
#: A row-pass and a column-pass centre closer than this along the row (px) are one stripe
#: found twice (a stripe leaning 56 degrees, the most the row linking follows, moves 1.5 px
#: along the row per row).
_SAME_STRIPE_PX = 1.5
#: The column pass's lean map reads the stripes' direction on the image decimated this many
#: times (the row pass's 4 reads stripes as dense as those on a box top far too upright).
_LEAN_DECIMATION = 2
#: Length of the columns' grey opening (the background along each column), in stripe widths:
#: shorter than the rows' (:data:`~multislit.stripes.separation.OPENING_WIDTHS`). Measured on
#: the half-size box tops (``tests/test_box_tops.py``): the tops' stripe pixels with the right
#: slit 75 % with 2.5 widths, 54 % with 3.5 (the same centres, fewer of them identified).
COLUMN_OPENING_WIDTHS = 2.5
#: The quick look of :func:`leaning_regions` takes maxima down to this fraction of the
#: detection threshold (the pass keeps the segments in which a single pixel reaches the whole
#: threshold, :func:`strong_segments`): a stripe leaning far is dim (its surface is lit at a grazing angle: a stripe leaning 80
#: degrees, seen by a rig whose camera and projector stand side by side, lies on a surface the
#: projector's light meets at 5 degrees or less), and its centres fade in and out around the
#: threshold. Texture and a smooth background that the column's opening leaves behind (a
#: ridge of a few noise sigmas along a row) reach the whole threshold nowhere.
WEAK_FRACTION = 0.4
#: A column-pass segment must be this many times as long as a row-pass one (``min_length``):
#: dots that happen to line up along a row (in a dense uniform pattern four to six of them)
#: make short column segments. On the references and scans of the zoo's tuning seeds 0-2,
#: 98 % of the column segments that lie on no stripe are shorter than 20 columns; the stripes
#: on box tops run over 20-100 columns.
MIN_LENGTH_FACTOR = 2
#: A column-pass segment is dropped where it passes through this many stripes of the row pass
#: (:func:`through_row_stripes`): the row-pass stripe has points this many rows above and below
#: the crossing. Stripes do not cross: a run of maxima along a row through upright stripes is
#: a horizontal edge or a row of dots, not a stripe (a leaning stripe meets upright ones where
#: a surface turns, but ends there).
_MAX_CROSSINGS = 1
_CROSS_ROWS = 3
#: The column pass runs on tiles of this many px where :func:`leaning_regions` finds a hint
#: of a leaning stripe, and on their neighbours.
_TILE = 32
#: The column pass joins pieces of one stripe across gaps of up to this many columns where the
#: line along each piece's end meets the other's within this many px.
_JOIN_GAP = 6
_JOIN_TOL_PX = 1.0
#: Around the column pass's centres, within this many stripe widths, the dot image is the
#: column pass's: there the row pass has taken the leaning stripes for dots, and its streak
#: removal leaves some of them behind.
_DOT_REACH_WIDTHS = 1.5


@dataclass(frozen=True, eq=False)
class ColumnCentres:
    """The column-wise pass of one image (:func:`column_pass`).

    Attributes
    ----------
    centres : StripeCentres
        In the image's frame, sorted by (u, v): ``u`` (K,) whole columns, ``v`` (K,) sub-pixel
        rows, ``peak`` the pass's slit image at the peak (intensity units), ``width`` the
        stripe's FWHM along the column (px, NaN where unknown)
    segment : (K,) int64, the centres' segments (:func:`link_columns`; -1: none)
    dots : (H, W) float32, the pass's dot image in its regions: the highpass less its slit
        image, less its streaks (:func:`~multislit.stripes.openings.remove_streaks`); 0
        elsewhere
    regions : int, the regions the pass ran on (:func:`leaning_regions`)
    strong : (K,) bool, the centres a single pixel shows above the threshold, not the ridge
        response alone (:func:`~multislit.stripes.centres.find_ridge_centres_validated`)
    slope : (K,) float64, the stripes' lean dv/du at the centres (rows per column; 0 where
        they lie along the rows)
    """

    centres: StripeCentres
    segment: I64
    dots: F32
    regions: int
    strong: NDArray[np.bool_]
    slope: F64


def leaning_regions(
    img: NDArray,
    stripe_width_px: float,
    threshold: float,
    link: dict,
    barrier: tuple[F64, F64] | None = None,
) -> tuple[NDArray[np.int32], list[tuple[int, int, int, int]]]:
    """Where stripes may lean towards the horizontal: a quick look along the columns.

    The transposed image less its row opening (:func:`~multislit.stripes.separation.
    row_opening_background`: along the columns, a stripe near the vertical is background), its
    maxima above ``threshold`` linked column to column over at least :data:`MIN_LENGTH_FACTOR`
    times ``min_length`` columns (dots not removed: they cut a stripe's run here and there, and
    make runs of their own). The tiles of :data:`_TILE` px that hold
    their points, and the tiles next to those, are the regions; each connected group of tiles
    is one region.

    Parameters
    ----------
    img : (H, W) validated image
    stripe_width_px : float, px
    threshold : float, intensity units
    link : the keyword arguments of :func:`~multislit.stripes.chains.link_segments`
    barrier : ((M,) float64, (M,) float64), px, the (v, u) of the row pass's linked centres:
        a run that crosses its stripes is no leaning stripe (:func:`off_row_stripes`, as
        :func:`link_columns` judges the column pass's segments), or None

    Returns
    -------
    tiles : (ceil(H / T), ceil(W / T)) int32, the region of each tile (0: none, 1 .. R)
    boxes : R tuples (r0, r1, c0, c1), px, the bounding box of each region's tiles
    """
    h, w = img.shape
    th, tw = -(-h // _TILE), -(-w // _TILE)
    t = cv2.transpose(img)
    hp = cv2.subtract(t, row_opening_background(t, stripe_width_px, COLUMN_OPENING_WIDTHS))
    if hp.dtype == np.float32:
        np.maximum(hp, 0, out=hp)
    # the maxima at whole pixels: only the tiles they fall in count
    r, c = row_maxima(hp, threshold)
    # the transposed image's rows are the columns: linked column to column
    seg = link_segments(
        c.astype(np.float64),
        r.astype(np.float64),
        link["max_du"],
        link["max_gap"],
        MIN_LENGTH_FACTOR * link["min_length"],
    )
    if barrier is not None and np.any(seg >= 0):
        on = np.flatnonzero(seg >= 0)
        e = np.empty(0)
        runs = StripeCentres(r[on].astype(np.float64), c[on].astype(np.float64), e, e)
        seg[on] = off_row_stripes(seg[on], runs, barrier)
    lk = seg >= 0
    mark = np.zeros((th, tw), np.uint8)
    mark[c[lk] // _TILE, r[lk] // _TILE] = 1
    mark = cv2.dilate(mark, np.ones((3, 3), np.uint8))
    n, tiles = cv2.connectedComponents(mark, connectivity=8)
    boxes = []
    for k in range(1, n):
        rr, cc = np.nonzero(tiles == k)
        boxes.append(
            (
                rr.min() * _TILE,
                min(h, (rr.max() + 1) * _TILE),
                cc.min() * _TILE,
                min(w, (cc.max() + 1) * _TILE),
            )
        )
    return tiles.astype(np.int32), boxes


def column_pass(
    img: NDArray,
    stripe_width_px: float,
    dot_size_px: float,
    threshold: float,
    method: str,
    saturation_level: float | None,
    taps: int,
    link: dict,
    barrier: tuple[F64, F64],
    levels: tuple[F64, F64] | None = None,
) -> ColumnCentres:
    """The centres of the stripes that lean towards the horizontal (see the module).

    In each region of :func:`leaning_regions` (with a margin: the filters' reach), the row
    pass's steps on the transposed crop: its maxima down to :data:`WEAK_FRACTION` of the
    threshold, linked along the columns (:func:`link_columns`).

    Parameters
    ----------
    img : (H, W) validated image (uint8, uint16 or float32)
    stripe_width_px, dot_size_px : float, px, the FWHMs the row pass used
    threshold : float, intensity units, the extraction's detection threshold
    method : the sub-pixel method (:data:`~multislit.stripes.centres.CENTRE_METHODS`)
    saturation_level : the camera's saturation level (None: read from the whole image)
    taps : int, pixels (odd) averaged along the stripe for the sub-pixel fit
    link : the keyword arguments of :func:`~multislit.stripes.chains.link_segments`
    barrier : ((M,) float64, (M,) float64), px, the (v, u) of the row pass's linked centres
    levels : ((B,) float64, (B,) float64) or None, the frame's noise by background level
        (:func:`~multislit.stripes.separation.noise_by_level`): the thresholds scale with it
        at each peak, by the crop's background there

    Returns
    -------
    ColumnCentres
    """
    h, w = img.shape
    tiles, boxes = leaning_regions(img, stripe_width_px, WEAK_FRACTION * threshold, link, barrier)
    dots = np.zeros((h, w), np.float32)
    if not boxes:
        e = np.empty(0)
        none = np.empty(0, np.int64)
        return ColumnCentres(StripeCentres(e, e, e, e), none, dots, 0, np.zeros(0, bool), e)
    ridge = ridge_threshold(threshold, stripe_width_px)
    level = saturation_level
    if level is None:  # the whole image's, not each crop's
        level = saturation_level_of(img)
    length = opening_length(dot_size_px)
    margin = _TILE + 2 * length
    parts, strong, lean = [], [], []
    for k, (r0, r1, c0, c1) in enumerate(boxes, start=1):
        # rows a multiple of 8: the transposed crop's rows are read 8 px at a time
        a0, a1 = _widen8(max(0, r0 - margin), min(h, r1 + margin), h)
        b0, b1 = max(0, c0 - margin), min(w, c1 + margin)
        t = cv2.transpose(np.ascontiguousarray(img[a0:a1, b0:b1]))
        bg = row_opening_background(t, stripe_width_px, COLUMN_OPENING_WIDTHS)
        hp, slits, sat, _ = separate_validated(
            t,
            stripe_width_px,
            dot_size_px,
            level,
            background="opening",
            bg=bg,
            lean_decimation=_LEAN_DECIMATION,
            keep_ends=True,
        )
        found, firm, slope = find_ridge_centres_validated(
            slits,
            threshold,
            ridge,
            method,
            sat,
            stripe_width_px,
            taps,
            levels=None if levels is None else (bg, *levels),
        )
        # the transposed crop's row is the column, its sub-pixel column the row
        u, v = found.v + b0, found.u + a0
        r = np.rint(v).astype(np.intp)
        inside = (r >= 0) & (r <= h - 1)
        inside[inside] = tiles[r[inside] // _TILE, u[inside].astype(np.intp) // _TILE] == k
        parts.append(StripeCentres(u[inside], v[inside], found.peak[inside], found.width[inside]))
        strong.append(firm[inside])
        lean.append(slope[inside])
        d = cv2.transpose(remove_streaks(cv2.subtract(hp, slits), length).astype(np.float32))
        own = _tile_mask(tiles, k, a0, a1, b0, b1)
        np.copyto(dots[a0:a1, b0:b1], d, where=own)
    centres = StripeCentres(*(np.concatenate(x) for x in zip(*parts, strict=True)))
    order = lex_order(centres.v, centres.u)
    centres = StripeCentres(*(x[order] for x in centres))
    firm, slope = np.concatenate(strong)[order], np.concatenate(lean)[order]
    segment = link_columns(centres, firm, slope, link, barrier)
    return ColumnCentres(centres, segment, dots, len(boxes), firm, slope)


def _tile_mask(
    tiles: NDArray[np.int32], k: int, a0: int, a1: int, b0: int, b1: int
) -> NDArray[np.bool_]:
    """(a1 - a0, b1 - b0) bool: the pixels of rows ``a0`` .. ``a1`` - 1 and columns ``b0`` ..
    ``b1`` - 1 whose tile of :data:`_TILE` px is in region ``k`` of ``tiles``."""
    t0, u0 = a0 // _TILE, b0 // _TILE
    sub = tiles[t0 : -(-a1 // _TILE), u0 : -(-b1 // _TILE)] == k
    big = sub.repeat(_TILE, axis=0).repeat(_TILE, axis=1)
    return big[a0 - t0 * _TILE : a1 - t0 * _TILE, b0 - u0 * _TILE : b1 - u0 * _TILE]


def _widen8(a0: int, a1: int, n: int) -> tuple[int, int]:
    """The range ``a0 .. a1`` of ``0 .. n`` widened to a multiple of 8 where ``n`` allows."""
    size = min(n, -(-(a1 - a0) // 8) * 8)
    a1 = min(n, a0 + size)
    return max(0, a1 - size), a1


def link_columns(
    c: StripeCentres,
    strong: NDArray[np.bool_],
    slope: F64 | None,
    link: dict,
    barrier: tuple[F64, F64],
) -> I64:
    """The column pass's segments: its centres ``c`` linked column to column
    (:func:`~multislit.stripes.chains.link_segments` with the row pass's ``link`` settings,
    along the stripes' lean ``slope`` (K,) dv/du, None: along the rows), the pieces that
    continue one another along the stripe joined (:func:`join_collinear`, across gaps of up to
    :data:`_JOIN_GAP` columns that no stripe of the row pass crosses: ``barrier``, their
    (v, u)), kept where :data:`MIN_LENGTH_FACTOR` times ``min_length`` long, where one of
    their centres is strong (``strong``: a single pixel shows it, not the ridge response
    alone; :func:`strong_segments`) and where no stripe of the row pass runs through them
    (:func:`through_row_stripes`).

    Returns
    -------
    (K,) int64, segment ids (-1: none)
    """
    seg = link_segments(c.v, c.u, link["max_du"], link["max_gap"], 1, slope)
    seg = join_collinear(c.v, c.u, seg, _JOIN_GAP, _JOIN_TOL_PX, barrier)
    seg = drop_short(seg, MIN_LENGTH_FACTOR * link["min_length"])
    seg = strong_segments(seg, strong)
    return off_row_stripes(seg, c, barrier)


def strong_segments(segment: I64, strong: NDArray[np.bool_], at_most: int | None = None) -> I64:
    """``segment`` (K,) int64 with -1 for the segments none of whose points is ``strong``
    (K,); with ``at_most``, for those with more than that many ``strong`` points instead."""
    lk = segment >= 0
    if not lk.any():
        return segment
    n = int(segment.max()) + 1
    count = np.bincount(segment[lk], strong[lk].astype(np.float64), n)
    ok = count > 0 if at_most is None else count <= at_most
    return np.where(lk & ok[np.maximum(segment, 0)], segment, -1)


def off_row_stripes(segment: I64, c: StripeCentres, barrier: tuple[F64, F64]) -> I64:
    """``segment`` (K,) int64 of the centres ``c`` (K,) with -1 for the segments that run
    through :data:`_MAX_CROSSINGS` or more stripes of the row pass (``barrier``: its linked
    (v, u), px; :func:`through_row_stripes`)."""
    return strong_segments(segment, through_row_stripes(c, barrier), at_most=_MAX_CROSSINGS - 1)


def through_row_stripes(c: StripeCentres, barrier: tuple[F64, F64]) -> NDArray[np.bool_]:
    """(K,) bool: which of the column pass's centres ``c`` (K,) a stripe of the row pass
    (``barrier``: its linked (v, u), px) runs through: it has points within
    :data:`_SAME_STRIPE_PX` along the row in the centre's row and :data:`_CROSS_ROWS` rows
    above and below."""
    bv, bu = (np.asarray(x, np.float64) for x in barrier)
    if c.u.size == 0 or bv.size == 0:
        return np.zeros(c.u.size, bool)
    lo_u = min(float(bu.min()), float(c.u.min()))
    span = max(float(bu.max()), float(c.u.max())) - lo_u + 4.0 * _SAME_STRIPE_PX + 2.0
    key = np.sort(np.rint(bv) * span + (bu - lo_u))
    rows, us = np.rint(c.v), c.u - lo_u
    through = np.ones(c.u.size, bool)
    for dr in (0, -_CROSS_ROWS, _CROSS_ROWS):
        k = (rows + dr) * span + us
        first = np.searchsorted(key, k - _SAME_STRIPE_PX, "left")
        last = np.searchsorted(key, k + _SAME_STRIPE_PX, "right")
        through &= last > first
    return through


def _end_lines(a: F64, b: F64, seg: I64, n: int, half: int) -> tuple:
    """Per segment 0..n-1 of the points (``a``, ``b``) sorted by (``seg``, ``b``): its first
    and last ``b``, and the lines a = p + q (b - b_end) fitted to its ``half`` points at each
    end (q = 0 for a single point): (b0, p0, q0, b1, p1, q1), each (n,) float64."""
    bounds = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1], True])
    lo, hi = bounds[:-1], bounds[1:]
    k = seg[lo]
    out = np.zeros((6, n))
    base = b[lo].repeat(np.diff(bounds))  # small numbers: exact sums
    x = b - base
    y = a - a[lo].repeat(np.diff(bounds))

    def sums(f: F64, i0: NDArray[np.intp], i1: NDArray[np.intp]) -> F64:
        c = np.r_[0.0, np.cumsum(f)]
        return c[i1] - c[i0]

    for j, (i0, i1) in enumerate(
        ((lo, np.minimum(hi, lo + half)), (np.maximum(lo, hi - half), hi))
    ):
        m = (i1 - i0).astype(np.float64)
        sx, sy = sums(x, i0, i1), sums(y, i0, i1)
        sxx, sxy = sums(x * x, i0, i1), sums(x * y, i0, i1)
        den = m * sxx - sx * sx
        q = np.where(den > 1e-9, (m * sxy - sx * sy) / np.where(den > 1e-9, den, 1.0), 0.0)
        end = b[lo] if j == 0 else b[hi - 1]
        # the line's value at the end: mean(y) + q (end - mean(x)), back in a
        p = a[lo] + sy / m + q * (end - b[lo] - sx / m)
        out[3 * j, k], out[3 * j + 1, k], out[3 * j + 2, k] = end, p, q
    return tuple(out)


def join_collinear(
    a: F64,
    b: F64,
    segment: I64,
    max_gap: int,
    tol_px: float,
    barrier: tuple[F64, F64] | None = None,
) -> I64:
    """Join segments that continue one another along the stripe's direction.

    The linking breaks a segment where a second maximum lies close to it (a dot beside the
    stripe) or where it fades for more than its gap. Segment S2 continues S1 where S2's first
    point lies 1 .. ``max_gap`` + 1 along ``b`` beyond S1's last, and the line fitted to
    :data:`ANGLE_HALF_WINDOW` points at each end, carried across the gap, meets the other end
    within ``tol_px``; each end joins at most one other, and only where that one is the only
    candidate of both. A gap that another stripe crosses (a ``barrier`` point within
    :data:`_SAME_STRIPE_PX` of the line in the gap) is not bridged: stripes do not cross, and
    two pieces on either side of one are no one stripe (dots that happen to line up on both
    sides of an upright stripe).

    Parameters
    ----------
    a : (K,) float64, px, the points' position across the chain (v for the column pass)
    b : (K,) float64, px, along the chain (whole columns for the column pass)
    segment : (K,) int64, segment id (-1: unlinked, left alone)
    max_gap : int, the most missing ``b`` bridged
    tol_px : float, px
    barrier : ((M,) float64, (M,) float64), px, the (a, b) of other stripes' points (the row
        pass's linked centres); default none

    Returns
    -------
    (K,) int64, segment ids (joined segments take one id; ids are not renumbered)
    """
    lk = np.flatnonzero(segment >= 0)
    if lk.size == 0:
        return segment
    lk = lk[np.lexsort((b[lk], segment[lk]))]
    ids, seg = np.unique(segment[lk], return_inverse=True)
    n = ids.size
    b0, p0, q0, b1, p1, q1 = _end_lines(a[lk], b[lk], seg, n, ANGLE_HALF_WINDOW)
    # candidates: the starts 1 .. max_gap + 1 beyond each end, within reach across (a
    # search per gap in the starts sorted by b, then a)
    lo_a = float(min(p0.min(), p1.min()))
    span = float(max(p0.max(), p1.max())) - lo_a + 4.0 * tol_px + 2.0 * (max_gap + 1) + 8.0
    key = b0 * span + (p0 - lo_a)
    by_start = np.argsort(key, kind="stable")
    key = key[by_start]
    ends, starts = [], []
    for g in range(1, int(max_gap) + 2):
        centre = (b1 + g) * span + (p1 + q1 * g - lo_a)
        first = np.searchsorted(key, centre - tol_px, "left")
        last = np.searchsorted(key, centre + tol_px, "right")
        cnt = last - first
        ends.append(np.repeat(np.arange(n), cnt))
        starts.append(by_start[np.repeat(first - np.cumsum(cnt) + cnt, cnt) + np.arange(cnt.sum())])
    i, j = np.concatenate(ends), np.concatenate(starts)
    gap = b0[j] - b1[i]
    # ... and the start's line carried back meets the end too
    ok = (gap >= 1) & (np.abs(p0[j] - q0[j] * gap - p1[i]) <= tol_px)
    i, j = i[ok], j[ok]
    if barrier is not None and i.size and barrier[0].size:
        i, j = _unbarred(i, j, b1, p1, q1, b0, barrier)
    # each end and each start in one candidate pair only
    single = (np.bincount(i, minlength=n)[i] == 1) & (np.bincount(j, minlength=n)[j] == 1)
    i, j = i[single], j[single]
    root = np.arange(n)
    for x, y in zip(i.tolist(), j.tolist(), strict=True):  # chains of joins: union-find
        rx, ry = x, y
        while root[rx] != rx:
            rx = root[rx]
        while root[ry] != ry:
            ry = root[ry]
        root[ry] = rx
    for x in range(n):
        r = x
        while root[r] != r:
            r = root[r]
        root[x] = r
    out = segment.copy()
    out[lk] = ids[root[seg]]
    return out


def _unbarred(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    b1: F64,
    p1: F64,
    q1: F64,
    b0: F64,
    barrier: tuple[F64, F64],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The pairs (end of i, start of j) of :func:`join_collinear` whose gap no barrier point
    crosses: none with b strictly between the ends and within :data:`_SAME_STRIPE_PX` of the
    line along i's end."""
    ba, bb = (np.asarray(x, np.float64) for x in barrier)
    # any order of equal b: a gap asks whether any point of its range lies near the line
    order = np.argsort(bb)
    ba, bb = ba[order], bb[order]
    lo = np.searchsorted(bb, b1[i], "right")
    hi = np.searchsorted(bb, b0[j], "left")
    keep = np.ones(i.size, bool)
    for n in np.flatnonzero(hi > lo):
        x, y = i[n], slice(lo[n], hi[n])
        line = p1[x] + q1[x] * (bb[y] - b1[x])
        keep[n] = not np.any(np.abs(ba[y] - line) <= _SAME_STRIPE_PX)
    return i[keep], j[keep]


def _local_slopes(a: F64, b: F64, segment: I64, half: int) -> F64:
    """(K,) float64: per linked point (``segment >= 0``), the slope da/db of the least-squares
    line through the points of its segment within ``half`` points of it along ``b``; NaN for
    unlinked points and where ``b`` does not vary in the window."""
    out = np.full(a.size, np.nan)
    lk = np.flatnonzero(segment >= 0)
    if lk.size == 0:
        return out
    lk = lk[np.lexsort((b[lk], segment[lk]))]
    out[lk] = _window_slopes(
        np.ascontiguousarray(a[lk], np.float64),
        np.ascontiguousarray(b[lk], np.float64),
        segment[lk].astype(np.int64),
        int(half),
    )
    return out


@njit(cache=True)
def _window_slopes(a, b, seg, half):
    """:func:`_local_slopes` of the points sorted by segment and ``b`` (``a``, ``b``, ``seg``
    (K,)): (K,) float64. The window sums are differences of running sums over all the points
    (each segment's a and b taken from its first point: small numbers, exact sums), added in
    order as np.cumsum adds."""
    n = a.size
    first = np.empty(n, np.int64)
    last = np.empty(n, np.int64)
    lo = 0
    while lo < n:
        hi = run_end(seg, lo)
        for q in range(lo, hi):
            first[q] = lo
            last[q] = hi - 1
        lo = hi
    ca = np.zeros(n + 1)
    cb = np.zeros(n + 1)
    cbb = np.zeros(n + 1)
    cab = np.zeros(n + 1)
    for q in range(n):
        bb = b[q] - b[first[q]]
        aa = a[q] - a[first[q]]
        ca[q + 1] = ca[q] + aa
        cb[q + 1] = cb[q] + bb
        cbb[q + 1] = cbb[q] + bb * bb
        cab[q + 1] = cab[q] + aa * bb
    out = np.empty(n)
    for q in range(n):
        w0 = max(q - half, first[q])
        w1 = min(q + half, last[q]) + 1
        m = float(w1 - w0)
        sb = cb[w1] - cb[w0]
        sa = ca[w1] - ca[w0]
        sbb = cbb[w1] - cbb[w0]
        sab = cab[w1] - cab[w0]
        den = m * sbb - sb * sb
        if den > 1e-9 * max(m * sbb, 1.0):
            out[q] = (m * sab - sb * sa) / den
        else:
            out[q] = np.nan
    return out


def chain_angles(u: F64, v: F64, segment: I64, by_column: NDArray[np.bool_]) -> F64:
    """The stripe's direction at every linked point, from its segment.

    A line fitted to the :data:`ANGLE_HALF_WINDOW` points on either side of the point along its
    segment: u as a function of v for a segment linked along the rows, v as a function of u
    for one linked along the columns.

    Parameters
    ----------
    u, v : (K,) float64, px, the centres
    segment : (K,) int64, segment id (-1: unlinked); a segment's points are all of one pass
    by_column : (K,) bool, the points of the column pass

    Returns
    -------
    (K,) float64, rad, from the image's vertical, positive leaning right going down, in
    (-pi/2, pi/2]; NaN for unlinked points
    """
    seg_r = np.where(by_column, -1, segment)
    seg_c = np.where(by_column, segment, -1)
    du_dv = _local_slopes(u, v, seg_r, ANGLE_HALF_WINDOW)
    dv_du = _local_slopes(v, u, seg_c, ANGLE_HALF_WINDOW)
    ang = np.arctan(du_dv)
    # along the columns: the direction (1, dv/du), from the vertical
    col = np.arctan2(1.0, dv_du)
    col = np.where(col > 0.5 * math.pi, col - math.pi, col)
    return np.where(by_column, col, ang)


@dataclass(frozen=True, eq=False)
class MergedCentres:
    """The two passes' points joined (:func:`merge_passes`).

    Attributes
    ----------
    centres : StripeCentres, sorted by (row, u) with row = rint(v)
    segment : (K,) int64, segment id (0..S-1 ordered by the segments' mean u; -1 unlinked)
    angle : (K,) float64, rad, the stripe's direction (:func:`chain_angles`; NaN unlinked)
    by_column : (K,) bool, the column pass's points
    """

    centres: StripeCentres
    segment: I64
    angle: F64
    by_column: NDArray[np.bool_]


def _shared(
    ur: F64, vr: F64, seg_r: I64, uc: F64, vc: F64
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pairs (i, j) of a column-pass point i and the linked row-pass point j nearest it in its
    row (rint(v)), within :data:`_SAME_STRIPE_PX`: one stripe found by both passes."""
    lk = np.flatnonzero(seg_r >= 0)
    e = np.zeros(0, np.intp)
    if lk.size == 0 or uc.size == 0:
        return e, e.copy()
    lo_u = min(float(ur[lk].min()), float(uc.min()))
    span = max(float(ur[lk].max()), float(uc.max())) - lo_u + 4.0 * _SAME_STRIPE_PX + 2.0
    key_r = np.rint(vr[lk]) * span + (ur[lk] - lo_u)
    o = np.argsort(key_r, kind="stable")
    key_r, lk = key_r[o], lk[o]
    key_c = np.rint(vc) * span + (uc - lo_u)
    p = np.searchsorted(key_r, key_c)
    best = np.full(uc.size, -1, np.intp)
    dist = np.full(uc.size, np.inf)
    for q in (p - 1, p):
        ok = (q >= 0) & (q < key_r.size)
        d = np.full(uc.size, np.inf)
        d[ok] = np.abs(key_r[q[ok]] - key_c[ok])
        better = d < dist
        best[better] = q[better]
        dist[better] = d[better]
    hit = dist <= _SAME_STRIPE_PX
    return np.flatnonzero(hit).astype(np.intp), lk[best[hit]].astype(np.intp)


def merge_passes(
    rows: StripeCentres,
    row_segment: I64,
    cols: StripeCentres,
    col_segment: I64,
    link: dict,
    threshold: float,
    barrier: tuple[F64, F64],
    row_weak: tuple[NDArray[np.bool_], F64] | None = None,
    col_weak: tuple[NDArray[np.bool_], F64] | None = None,
) -> MergedCentres:
    """Join the row pass's and the column pass's points (see the module).

    Parameters
    ----------
    rows : the row pass's centres (v whole rows); ``row_segment`` (K_r,) int64 their segments
        linked along the rows (-1: unlinked, kept as such)
    cols : the column pass's centres (u whole columns); ``col_segment`` (K_c,) int64 their
        segments linked along the columns (-1: unlinked, left out)
    link, threshold, barrier : the linking's settings (:func:`~multislit.stripes.chains.
        link_segments`), the detection threshold and the row pass's linked (v, u): where the
        merge takes points out of a segment, the rest of each pass is linked again (the
        columns by :func:`link_columns`)
    row_weak : ((K_r,) bool, (K_r,) float64), the row pass's strong centres and the stripes'
        lean at them (:func:`~multislit.stripes.centres.find_ridge_centres_validated`; the
        rows are linked again by :func:`~multislit.stripes.chains.link_weak`); default all
        strong, upright
    col_weak : ((K_c,) bool, (K_c,) float64), the same of the column pass
        (:attr:`ColumnCentres.strong`, :attr:`ColumnCentres.slope`); default all strong, along
        the rows

    Returns
    -------
    MergedCentres
    """
    keep_c = col_segment >= 0
    cols = StripeCentres(*(x[keep_c] for x in cols))
    col_segment = col_segment[keep_c]
    col_strong, col_slope = (
        (keep_c[keep_c], None) if col_weak is None else (col_weak[0][keep_c], col_weak[1][keep_c])
    )
    nr = rows.u.size
    u, v, by_col, seg, ang = _stacked(rows, row_segment, cols, col_segment)
    drop = np.zeros(u.size, bool)
    i, j = _shared(rows.u, rows.v, row_segment, cols.u, cols.v)
    if i.size:
        # per pair of segments: the lean over the points both passes found
        pair = row_segment[j] * (int(col_segment.max()) + 1) + col_segment[i]
        lean = 0.5 * (np.abs(ang[j]) + np.abs(ang[nr + i]))
        lean = np.where(np.isfinite(lean), lean, 0.25 * math.pi)
        keys, inv = np.unique(pair, return_inverse=True)
        mean = np.bincount(inv, lean, keys.size) / np.bincount(inv, minlength=keys.size)
        to_cols = mean[inv] > 0.25 * math.pi
        drop[j[to_cols]] = True
        drop[nr + i[~to_cols]] = True
    if drop.any():
        row_keep, col_keep = ~drop[:nr], ~drop[nr:]
        strong, slope = (
            (row_keep[row_keep], None)
            if row_weak is None
            else (row_weak[0][row_keep], row_weak[1][row_keep])
        )
        row_segment = link_weak(
            rows.u[row_keep], rows.v[row_keep], strong, slope, rows.peak[row_keep], **link
        )
        # a weak centre counts in a segment only
        row_keep[row_keep] = (row_segment >= 0) | strong
        row_segment = row_segment[(row_segment >= 0) | strong]
        rows = StripeCentres(*(x[row_keep] for x in rows))
        cols = StripeCentres(*(x[col_keep] for x in cols))
        col_segment = link_columns(
            cols,
            col_strong[col_keep],
            None if col_slope is None else col_slope[col_keep],
            link,
            barrier,
        )
        linked = col_segment >= 0
        cols = StripeCentres(*(x[linked] for x in cols))
        col_segment = col_segment[linked]
        u, v, by_col, seg, ang = _stacked(rows, row_segment, cols, col_segment)
    peak = np.r_[rows.peak, cols.peak]
    width = np.r_[rows.width, cols.width]
    # one numbering, by the segments' mean u (as the linking numbers them)
    if seg.size and seg.max() >= 0:
        lk = seg >= 0
        n = int(seg.max()) + 1
        mean_u = np.bincount(seg[lk], u[lk], n) / np.maximum(np.bincount(seg[lk], minlength=n), 1)
        present = np.bincount(seg[lk], minlength=n) > 0
        ids = np.flatnonzero(present)
        new_id = np.full(n, -1, np.int64)
        new_id[ids[np.argsort(mean_u[ids], kind="stable")]] = np.arange(ids.size)
        seg = np.where(lk, new_id[np.maximum(seg, 0)], -1)
    order = lex_order(u, np.rint(v))
    return MergedCentres(
        StripeCentres(u[order], v[order], peak[order], width[order]),
        seg[order],
        ang[order],
        by_col[order],
    )


def _stacked(
    rows: StripeCentres, row_segment: I64, cols: StripeCentres, col_segment: I64
) -> tuple[F64, F64, NDArray[np.bool_], I64, F64]:
    """The two passes' points in one list, the row pass's first: u, v (px), by_column, the
    segments (the column pass's numbered after the row pass's; -1: none) and the angles."""
    nr = rows.u.size
    u = np.r_[rows.u, cols.u]
    v = np.r_[rows.v, cols.v]
    by_col = np.r_[np.zeros(nr, bool), np.ones(cols.u.size, bool)]
    off = int(row_segment.max()) + 1 if nr else 0
    seg = np.r_[row_segment, np.where(col_segment >= 0, col_segment + off, -1)].astype(np.int64)
    return u, v, by_col, seg, chain_angles(u, v, seg, by_col)


def merge_dots(row_dots: F32, col_dots: F32, u: F64, v: F64, stripe_width_px: float) -> F32:
    """The dot image: the row pass's, but within :data:`_DOT_REACH_WIDTHS` stripe widths of the
    column pass's centres (``u``, ``v`` (K,) px) the column pass's (H, W) float32."""
    if u.size == 0:
        return row_dots
    h, w = row_dots.shape
    r = np.clip(np.rint(v).astype(np.intp), 0, h - 1)
    c = np.clip(u.astype(np.intp), 0, w - 1)
    rad = max(1, math.ceil(_DOT_REACH_WIDTHS * stripe_width_px))
    # only the centres' bounding box, widened by the reach, can be near one
    r0, r1 = max(int(r.min()) - rad, 0), min(int(r.max()) + rad + 1, h)
    c0, c1 = max(int(c.min()) - rad, 0), min(int(c.max()) + rad + 1, w)
    mark = np.zeros((r1 - r0, c1 - c0), np.uint8)
    mark[r - r0, c - c0] = 1
    near = cv2.dilate(mark, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1,) * 2))
    out = row_dots.copy()
    np.copyto(out[r0:r1, c0:c1], col_dots[r0:r1, c0:c1], where=near.view(bool))
    return out

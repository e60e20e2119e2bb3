"""Evidence from the dots' geometry: how well each slit explains the dots beside a stripe piece.

Under slit k, every stripe point of a piece is a 3D point (its line of sight meets plane k),
so the piece is a 3D curve. The dots that must land beside that curve are known rays of the
dot projector (:class:`~multislit.geometry.dots.DotProjector`): those whose angle across the slits
lies within the slit's band (``half_band``) and whose angle along the slits lies within the
curve's. Each lands where its ray meets the surface. Along the curve the surface is known;
across it, it is not: a surface turned away from the dot projector puts a dot at a range
``r_c (1 + g delta)``, ``r_c`` the curve's range at the dot's angle along the slits, ``delta``
its angle across from the curve, ``g`` the surface's slope across the stripe (tan of its
tilt). Each predicted dot is projected into the image for the slopes in ``[-G, G]``: a short
path, a parabola in ``g``. It is **found** at the slopes where an observed dot lies within
:data:`MATCH_TOL_PX` of the path (the dots found by :func:`~multislit.stripes.find_dots`,
speckle on the stripes left out).

One log-likelihood ratio per (window of a piece, slit, side of the stripe) against "the dots
there are background": each predicted dot found adds ``log(p_det / p_false)``, each missed
``log((1 - p_det) / (1 - p_false))``; ``p_false``, the chance that an observed dot lies that
close to a place by chance, is measured around it on the frame (:func:`false_match_map`),
``p_det`` is
:data:`P_DETECT`. The slope is marginalised over a uniform prior of the surface's tilt, so a
slope that finds a few dots by chance pays for its freedom. Dots predicted outside the image
count neither way. A slit that puts a window outside the measuring volume is ruled out (NaN).

Between two pieces side by side in the rows (:func:`gap_evidence`), slits k and k + 1 of one
surface leave no freedom: the surface between them is the one through both stripes, and every
dot between them has one predicted place.

Units: px, mm, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from multislit._groups import group_medians
from multislit.identify.launch import launch
from multislit.identify.result import DotMatches
from multislit.identify.rig import RigGeometry
from multislit.stripes.dots import (
    MIN_DOT_RATIO,
    STRIPE_CLEARANCE,
    DotCentres,
    DotResponse,
    dot_response,
    dots_off_stripes,
    find_dots,
    near_stripes,
    point_grid,
    z_many,
)
from multislit.stripes.separation import saturation_level_of

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

#: Largest slope across the stripe (tan of the surface's tilt) a window may take.
SLOPE_MAX = 3.0
#: A predicted dot is found when an observed dot lies within this many px of its place.
MATCH_TOL_PX = 1.5
#: Chance that a dot the rays predict on a lit surface is there to be seen (not hidden, its ray
#: right).
P_VISIBLE = 0.85
#: A dot's expected response is taken as this share of the frame's typical one: dots vary in
#: brightness, and a dimmer one than expected must still count.
ALPHA_SHARE = 0.6
#: Tilts of the surface across the stripe tried on either side of 0 (up to atan(SLOPE_MAX)).
_SLOPE_STEPS = 4
#: The frame's density of dots weighs in the local one as much as this many px of the place's
#: own neighbourhood (a place with few pixels of a zone around it takes the frame's density) ...
_PRIOR_AREA = 400.0
#: ... and a chance match is never taken as less likely than this.
_MIN_P_FALSE = 0.01
#: Per window, the slits scored with the slope marginalised: those within this (nats) of the
#: best at the slope 0 (the others are far from explaining the dots).
_KEEP = 15.0
#: A piece's 3D curve is worked out from every this many of its points (and its last).
_CURVE_STRIDE = 4
#: The chance of a false match is kept per block of this many px (a power of two) ...
BLOCK_PX = 4
#: ... which is 2 ** this.
_SHIFT = 2
#: The dots' brightness relative to the stripes is the median over at most about this many.
_BRIGHTNESS_SAMPLE = 1000
#: Levels of the chance of a dot by chance that the table of :func:`dot_llr` holds.
_CHANCE_LEVELS = 24
#: Cell of the observed dots' look-up grid, px.
_CELL = 4.0
#: The windows (and the gaps between them) are worked in this many runs of consecutive ones,
#: each with scratch of its own, spread over Numba's threads.
_CHUNKS = 64
#: Most records of found dots of one window and slit.
_MAX_CAND = 4096


@dataclass(frozen=True, eq=False)
class DotEvidence:
    """Per window of stripe points, per slit and per side of the stripe, how well the slit
    explains the dots.

    Attributes
    ----------
    llr : (W, N, 2) float32, log-likelihood ratio of slit k for the dots on the left (0) and
        right (1) of window w, against their being background, the slope across the stripe
        marginalised; NaN where slit k puts the window outside the measuring volume (or has no
        plane)
    found : (W, N, 2) int16, predicted dots found at the best slope
    usable : (W, N, 2) int16, predicted dots that could be seen (in the image)
    slope : (W, N, 2) float32, the best slope across the stripe
    kept : (W, N) bool, the slits scored with the slope marginalised (those not far below
        the window's best at the slope 0); the others' scores are a lower bound
    span : (W, N, 3) float32, where window w lies under slit k, seen from the dot source: the
        sines of its least and largest angle along the slits and its mean range (mm); NaN
        where slit k puts it outside the measuring volume
    means : (W, N, 4) float64, its mean place under slit k, seen from the dot source: cosine
        and sine of the angle across the slits, sine of the angle along them, range (mm)
    """

    llr: F32
    found: NDArray[np.int16]
    usable: NDArray[np.int16]
    slope: F32
    kept: NDArray[np.bool_]
    span: F32
    means: F64


@dataclass(frozen=True, eq=False)
class GapEvidence:
    """Per gap between two stripe pieces side by side in the rows (a on the left, b on the
    right) and per slit k of a (k + 1 of b), the dots between them.

    Attributes
    ----------
    fixed : (P, N) float32, log-likelihood ratio of the dots between the pieces when they are
        slits k and k + 1 of one surface: the surface between them is the one through both
        stripes, so every dot's place is predicted without a free slope; NaN where either
        piece leaves the measuring volume (and for k = N - 1)
    free_a, free_b : (P, N) float32, the same dots as :class:`DotEvidence` scores them: those
        nearer a with a free slope about a (slit k), those nearer b about b (slit k + 1)
    graze : (P, N) float32, |cos| of the angle between the surface through both stripes
        (midway along their shared rows) and the camera's or the dot source's line of sight,
        the larger: near 1 the "surface" is a step in depth
    """

    fixed: F32
    free_a: F32
    free_b: F32
    graze: F32

    @property
    def bonus(self) -> F32:
        """(P, N) float32: how much more the dots between the pieces say for (k, k + 1) on
        one surface than for each piece on its own (NaN: not a hypothesis)."""
        return self.fixed - self.free_a - self.free_b


def false_match_map(
    dots: DotCentres,
    near: NDArray[np.bool_],
    near_zone: NDArray[np.bool_],
    radius_px: float,
) -> F32:
    """(2, Hb, Wb) float32: per block of :data:`BLOCK_PX` x :data:`BLOCK_PX` px, the chance
    that an observed dot lies within :data:`MATCH_TOL_PX` of a place there by chance, clear of
    the stripes (0) and near one (1): from the density of the observed dots of that zone in
    the square of half side ``radius_px`` around the block, the frame's density of the zone
    weighing as much as :data:`_PRIOR_AREA` px of it; between :data:`_MIN_P_FALSE` and 0.5.

    Parameters
    ----------
    dots : the observed dots
    near : (M,) bool, the dots near a stripe
    near_zone : (H, W) bool, the places near a stripe
    radius_px : px
    """
    h, w = near_zone.shape
    out = np.empty((2, -(-h // BLOCK_PX), -(-w // BLOCK_PX)), np.float32)
    half = max(1, int(round(radius_px / BLOCK_PX)))
    _dot_densities(np.ascontiguousarray(near_zone).view(np.uint8), dots.u, dots.v,
                   np.asarray(near, bool), BLOCK_PX, half, out)  # fmt: skip
    # the chance of a dot within the tolerance at that density (numpy's exp: vectorised)
    np.exp(out * np.float32(-math.pi * MATCH_TOL_PX**2), out=out)
    np.subtract(np.float32(1.0), out, out=out)
    return np.clip(out, _MIN_P_FALSE, 0.5, out=out)


@njit(cache=True)
def _dot_densities(zone, u, v, near, block, half, out):
    """The observed dots' density (1 / px^2) of each zone around each block, into ``out`` (2,
    Hb, Wb): the dots (``u``, ``v``, ``near`` (M,)) and the pixels (``zone`` (H, W) uint8, 1
    near a stripe) of the zone in the (2 ``half`` + 1)-block square around the block (nothing
    beyond the image), the frame's density weighing as much as :data:`_PRIOR_AREA` px."""
    h, w = zone.shape
    hb, wb = out.shape[1], out.shape[2]
    # per block, side by side: the dots of each zone (0 clear, 1 near), the pixels of each
    x = np.zeros((hb, wb, 4), np.int32)
    n_near = 0
    for i in range(u.shape[0]):
        br = min(max(int(v[i]) // block, 0), hb - 1)
        bc = min(max(int(u[i]) // block, 0), wb - 1)
        x[br, bc, 1 if near[i] else 0] += 1
        n_near += 1 if near[i] else 0
    near_px = np.zeros((hb, wb), np.int32)
    _block_counts(zone, block, near_px)
    a_near = 0
    for br in range(hb):
        rows = min(h - br * block, block)
        for bc in range(wb):
            x[br, bc, 3] = near_px[br, bc]
            x[br, bc, 2] = rows * min(w - bc * block, block) - near_px[br, bc]
            a_near += near_px[br, bc]
    prior0 = _PRIOR_AREA * (u.shape[0] - n_near) / max(h * w - a_near, 1)
    prior1 = _PRIOR_AREA * n_near / max(a_near, 1)
    # the sums over the squares: running sums down the columns (whole rows at a time), then
    # differences of each row's prefix sums
    flat = x.reshape(hb, 4 * wb)
    col = np.zeros(4 * wb, np.int32)
    for r in range(min(half, hb)):
        col += flat[r]
    prefix = np.zeros((wb + 1, 4), np.int32)
    for br in range(hb):
        if br + half < hb:
            col += flat[br + half]
        if br - half - 1 >= 0:
            col -= flat[br - half - 1]
        for bc in range(wb):
            for k in range(4):
                prefix[bc + 1, k] = prefix[bc, k] + col[4 * bc + k]
        for bc in range(wb):
            hi, lo = min(bc + half + 1, wb), max(bc - half, 0)
            n0 = prefix[hi, 0] - prefix[lo, 0]
            n1 = prefix[hi, 1] - prefix[lo, 1]
            a0 = prefix[hi, 2] - prefix[lo, 2]
            a1 = prefix[hi, 3] - prefix[lo, 3]
            out[0, br, bc] = (n0 + prior0) / (a0 + _PRIOR_AREA)
            out[1, br, bc] = (n1 + prior1) / (a1 + _PRIOR_AREA)


@njit(cache=True)
def _block_counts(zone, block, out):
    """The pixels set in ``zone`` (H, W) uint8 (0 or 1, C order) per block of ``block`` x
    ``block`` px into ``out`` (ceil(H / block), ceil(W / block)): each block's rows summed
    first (whole rows at a time, which the compiler vectorises), then their columns. Blocks of
    4 px across an image a whole number of them wide sum a row's 4 bytes as one 32-bit word:
    the multiplication by 0x01010101 adds them into its top byte."""
    h, w = zone.shape
    if block == 4 and w % 4 == 0:
        words = zone.view(np.uint32)
        acc4 = np.zeros(w // 4, np.uint32)
        for br in range(out.shape[0]):
            acc4[:] = 0
            for r in range(br * 4, min(br * 4 + 4, h)):
                acc4 += words[r]  # each byte at most 4: no carry into the next
            for bc in range(w // 4):
                out[br, bc] = ((acc4[bc] * np.uint32(0x01010101)) >> np.uint32(24)) & np.uint32(
                    0xFF
                )
        return
    acc = np.zeros(w, np.int32)
    for br in range(out.shape[0]):
        acc[:] = 0
        for r in range(br * block, min((br + 1) * block, h)):
            row = zone[r]
            for c in range(w):
                acc[c] += row[c]
        for bc in range(out.shape[1]):
            t = 0
            for c in range(bc * block, min((bc + 1) * block, w)):
                t += acc[c]
            out[br, bc] = t


def dot_grid(
    dots: DotCentres, shape: tuple[int, int], cell: float = _CELL
) -> tuple[NDArray[np.intp], NDArray[np.intp], int, int]:
    """The observed dots in a grid of ``cell`` px: (order (M,), cell_start (C+1,), nx, ny):
    the dots of cell (cy, cx) are ``order[cell_start[cy*nx+cx]:cell_start[cy*nx+cx+1]]``."""
    return point_grid(dots.u, dots.v, shape, cell)


@dataclass(frozen=True, eq=False)
class FrameDots:
    """The frame's dots as the evidence kernels read them.

    The evidence reads the dots' response (:class:`~multislit.stripes.dots.DotResponse`) where
    each hypothesis puts a dot: a faint dot counts as far as it stands out of the noise there,
    and no threshold decides first. The dots found in the image (:func:`find_dots`) measure
    the chance that a dot lies at a place by chance, and are what the identified dots are
    paired with (:func:`dot_matches`).

    Attributes
    ----------
    dots : DotCentres, the dots found, speckle on the stripes left out
        (:func:`~multislit.stripes.dots.dots_off_stripes`)
    near : (M,) bool, the dots closer than ``clearance_px`` to a stripe centre
    clearance_px : px
    p_false : (2, Hb, Wb) float32, :func:`false_match_map`
    grid : the found dots' look-up grid (:func:`dot_grid`)
    near_zone : (H, W) uint8, 1 near a stripe
    response : the dots' response of the frame
    beta : the response of a dot per unit of the stripe's peak beside it (the frame's median
        over the dots found clear of the stripes): a dot on a surface is as bright, relative
        to the stripe on it, as on any other
    """

    dots: DotCentres
    near: NDArray[np.bool_]
    clearance_px: float
    p_false: F32
    grid: tuple
    near_zone: NDArray[np.uint8]
    response: DotResponse
    beta: float

    def kernel_args(self) -> tuple[tuple, tuple]:
        """What the kernels read (:func:`_llr_at`): the response (its
        :meth:`~multislit.stripes.dots.DotResponse.kernel_args`) and the chance of a dot by
        chance with the table of :func:`dot_llr`: (near zone (H, W) uint8, the chance's level
        per zone and block (2, Hb, Wb) uint8, logit of each level (Q,), the table (Q, T), its
        first ``y`` and its steps per unit of ``y``); made once per frame."""
        return self._kernel_args

    @cached_property
    def _kernel_args(self) -> tuple[tuple, tuple]:
        levels, table, lo, scale = _llr_table()
        q = _level_of(self.p_false, levels)
        chance = (self.near_zone, q, np.log(levels / (1.0 - levels)), table, lo, scale)
        return self.response.kernel_args(), chance


_TABLE: dict = {}


def _level_of(p: F32, levels: F64) -> NDArray[np.uint8]:
    """The nearest of the geometrically spaced ``levels`` (Q,) to each chance ``p`` (within
    their range), by the midpoints between them: ``np.searchsorted(midpoints, p)``, from
    the level below found by the logarithm."""
    mids = 0.5 * (levels[1:] + levels[:-1])
    step = math.log(levels[1] / levels[0])
    below = np.floor(np.log(p / np.float32(levels[0])) / np.float32(step)).astype(np.intp)
    below = np.clip(below, 0, len(mids) - 1)
    return (below + (mids[below] < p)).astype(np.uint8)


def _llr_table() -> tuple[F64, F64, float, float]:
    """The chance levels (Q,) and :func:`dot_llr` tabulated per level over ``y`` (Q, T),
    with ``y`` of entry i ``lo + i / scale``; made once."""
    if not _TABLE:
        levels = np.geomspace(_MIN_P_FALSE, 0.5, _CHANCE_LEVELS)
        lo, hi, scale = -40.0, 40.0, 20.0
        y = lo + np.arange(int((hi - lo) * scale) + 1) / scale
        pc = levels[:, None]
        p = P_VISIBLE
        table = np.log(1.0 - p + (p / pc) / (1.0 + np.exp(-y[None, :])))
        _TABLE["t"] = (levels, np.ascontiguousarray(table), lo, scale)
    return _TABLE["t"]


def _rig_args(rig: RigGeometry) -> tuple[tuple, tuple]:
    """The rig as the kernels read it: (camera centre, planes, half bands, their sines, the
    sign of phi from a slit to the next, dot source, dot frame, camera, R, t, distortion, near
    and far depth) and the dots (directions, cosines and sines of their angles across the
    slits, sines of their angles along them, their look-up order and bins)."""
    cam, R, t, dist = rig.camera_arrays()
    d_order, b_start, phi0, bw = rig.dot_index()
    dirs, cp, sp, ss = rig.dot_rays()
    hb = rig.half_band
    return (
        rig.camera.centre,
        np.ascontiguousarray(rig.planes),
        hb,
        np.where(np.isfinite(hb), np.sin(np.nan_to_num(hb)), 0.0),
        float(rig.phi_sign),
        rig.dots.source,
        np.ascontiguousarray(rig.dots.frame),
        cam,
        np.ascontiguousarray(R),
        t,
        dist,
        float(rig.depth_range[0]),
        float(rig.depth_range[1]),
    ), (dirs, cp, sp, ss, d_order, b_start, float(phi0), float(bw))


def _beta(rig: RigGeometry, frame: FrameDots) -> F64:
    """(D,) each dot's response per unit of the stripe's peak beside it: its own, calibrated
    on the reference boards (:attr:`~multislit.geometry.dots.DotProjector.brightness`), else
    the frame's (:attr:`FrameDots.beta`)."""
    own = np.asarray(rig.dots.brightness, np.float64)
    if own.shape != (rig.dots.num_dots,):
        return np.full(rig.dots.num_dots, frame.beta)
    return np.where(np.isfinite(own) & (own > 0), own, frame.beta)


def window_stripes(extraction, order: NDArray[np.intp], start: NDArray[np.intp]) -> tuple[F64, F64]:
    """Each window's stripe as the evidence reads it: its direction (rad from the image's
    vertical) and its peak (intensity units), the medians over its points
    ``order[start[w]:start[w+1]]`` of the extraction's ``angle`` and ``peak`` (W,) each."""
    n = np.diff(start)
    grp = np.repeat(np.arange(len(n)), n)
    direction = group_medians(np.asarray(extraction.angle, np.float64)[order], grp, len(n))
    peak = group_medians(np.asarray(extraction.peak, np.float64)[order], grp, len(n))
    return np.nan_to_num(direction), np.nan_to_num(peak)


def _window_args(direction: F64, peak: F64) -> tuple[F64, F64, F64]:
    """(sin, cos) of the stripes' directions (NaN: vertical) and their peaks, as the kernels
    read them."""
    a = np.nan_to_num(np.asarray(direction, np.float64))
    return np.sin(a), np.cos(a), np.ascontiguousarray(peak, np.float64)


def dot_evidence(
    rig: RigGeometry,
    rays: F64,
    order: NDArray[np.intp],
    win_start: NDArray[np.intp],
    frame: FrameDots,
    direction: F64,
    peak: F64,
    hypotheses: NDArray[np.bool_] | None = None,
) -> DotEvidence:
    """The dots' evidence for every window of stripe points, every slit and both sides.

    Parameters
    ----------
    rig : the prepared rig (:func:`~multislit.identify.rig.rig_geometry`)
    rays : (K, 3) float64, unit lines of sight of the stripe points (world frame)
    order : (P,) intp, stripe point indices, window after window
    win_start : (W+1,) intp, window w holds ``order[win_start[w]:win_start[w+1]]``
    frame : the frame's dots (:class:`FrameDots`)
    direction : (W,) float64, rad, each window's stripe direction from the image's vertical
    peak : (W,) float64, each window's stripe peak (intensity units): its dots are as bright
        as :attr:`FrameDots.beta` times it
    hypotheses : (W, N) bool, the slits to score per window; default all

    Returns
    -------
    DotEvidence
    """
    n = rig.num_slits
    nw = len(win_start) - 1
    if hypotheses is None:
        hypotheses = np.ones((nw, n), bool)
    llr = np.full((nw, n, 2), np.nan, np.float32)
    found = np.zeros((nw, n, 2), np.int16)
    used = np.zeros((nw, n, 2), np.int16)
    slope = np.zeros((nw, n, 2), np.float32)
    kept = np.zeros((nw, n), bool)
    span = np.full((nw, n, 3), np.nan, np.float32)
    means = np.full((nw, n, 4), np.nan, np.float64)
    if nw:
        rig_k, dots_k = _rig_args(rig)
        launch(
            _window_kernel,
            np.ascontiguousarray(rays, np.float64),
            order.astype(np.intp),
            win_start.astype(np.intp),
            np.ascontiguousarray(hypotheses),
            rig_k,
            dots_k,
            *_window_args(direction, peak),
            _beta(rig, frame),
            *frame.kernel_args(),
            SLOPE_MAX,
            _SLOPE_STEPS,
            _KEEP,
            llr,
            found,
            used,
            slope,
            kept,
            span,
            means,
        )
    return DotEvidence(llr, found, used, slope, kept, span, means)


def gap_evidence(
    rig: RigGeometry,
    rays: F64,
    a_order: NDArray[np.intp],
    a_start: NDArray[np.intp],
    b_order: NDArray[np.intp],
    b_start: NDArray[np.intp],
    frame: FrameDots,
    direction: F64,
    peak: F64,
    gap_a: NDArray[np.intp],
    gap_b: NDArray[np.intp],
    evidence: DotEvidence,
    pairs: NDArray[np.bool_] | None = None,
) -> GapEvidence:
    """The dots between pieces side by side in the rows, as one surface and apart.

    Parameters
    ----------
    rig : the prepared rig
    rays : (K, 3) float64, unit lines of sight of the stripe points
    a_order, a_start : gap p's left piece has the points ``a_order[a_start[p]:a_start[p+1]]``
        (those in the rows it shares with the right piece)
    b_order, b_start : the same for the right piece
    frame : the frame's dots
    direction : (P,) float64, rad, the stripes' direction at each gap (from the vertical)
    peak : (P,) float64, the stripes' peak at each gap (intensity units)
    gap_a, gap_b : (P,) intp, the windows of each gap (left, right)
    evidence : the windows' :class:`DotEvidence` (their mean places under each slit)
    pairs : (P, N) bool, the slits k of the left piece (k + 1 of the right) worth scoring;
        default all

    Returns
    -------
    GapEvidence (NaN for the pairs not scored)
    """
    n = rig.num_slits
    ng = len(a_start) - 1
    fixed = np.full((ng, n), np.nan, np.float32)
    free_a = np.full((ng, n), np.nan, np.float32)
    free_b = np.full((ng, n), np.nan, np.float32)
    graze = np.full((ng, n), np.nan, np.float32)
    if pairs is None:
        pairs = np.ones((ng, n), bool)
    if ng:
        rig_k, dots_k = _rig_args(rig)
        launch(
            _gap_kernel,
            np.ascontiguousarray(rays, np.float64),
            a_order.astype(np.intp),
            a_start.astype(np.intp),
            b_order.astype(np.intp),
            b_start.astype(np.intp),
            np.asarray(gap_a, np.intp),
            np.asarray(gap_b, np.intp),
            evidence.means,
            rig_k,
            dots_k,
            *_window_args(direction, peak),
            _beta(rig, frame),
            *frame.kernel_args(),
            SLOPE_MAX,
            _SLOPE_STEPS,
            np.ascontiguousarray(pairs),
            fixed,
            free_a,
            free_b,
            graze,
        )
    return GapEvidence(fixed, free_a, free_b, graze)


@njit(cache=True, inline="always")
def _project(x, y, z, cam, R, t, dist):
    """World point -> pixel (u, v) with OpenCV's distortion; (nan, nan) behind the camera.
    Without branches on the data, so that loops over points vectorise."""
    xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
    yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
    zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
    front = zc > 1e-9
    zc = zc if front else 1.0
    a = xc / zc
    b = yc / zc
    r2 = a * a + b * b
    rad = 1.0 + r2 * (dist[0] + r2 * (dist[1] + r2 * dist[4]))
    ad = a * rad + 2.0 * dist[2] * a * b + dist[3] * (r2 + 2.0 * a * a)
    bd = b * rad + dist[2] * (r2 + 2.0 * b * b) + 2.0 * dist[3] * a * b
    u = cam[0] * ad + cam[2]
    v = cam[1] * bd + cam[3]
    return (u if front else np.nan), (v if front else np.nan)


@njit(cache=True)
def _project_many(x, y, z, n, cam, R, t, dist, u, v):
    """The world points (``x[i]``, ``y[i]``, ``z[i]``), i < ``n``, -> pixels into ``u``,
    ``v`` (:func:`_project`)."""
    for i in range(n):
        u[i], v[i] = _project(x[i], y[i], z[i], cam, R, t, dist)


#: Rows of the curves' points (:func:`_curve_points`): the cosine and sine of the angle across
#: the slits seen from the dot source, the sine of the angle along them, the range, and the
#: tangent of the angle across.
_PTS = 5


@njit(cache=True)
def _plane_terms(planes, C):
    """The slit planes (N, 4) as :func:`_curve_points` reads them: their coefficients (4, N)
    and the numerators ``-(n . C + d)`` (N,) of the lines of sight from the camera centre
    ``C`` meeting them."""
    pl = np.ascontiguousarray(planes.T)
    num = np.empty(planes.shape[0])
    for k in range(planes.shape[0]):
        num[k] = -(planes[k, 0] * C[0] + planes[k, 1] * C[1] + planes[k, 2] * C[2] + planes[k, 3])
    return pl, num


@njit(cache=True, error_model="numpy")
def _curve_points(C, rays, order, a0, nt, pl, num, k0, k1, O, F, R, t, pts, zsum, bad):
    """The stripe points ``order[a0:a0+nt]`` (every :data:`_CURVE_STRIDE`-th and the last)
    under the slits ``k0 .. k1 - 1`` (their planes ``pl``, ``num``: :func:`_plane_terms`), seen
    from the dot source, into ``pts`` (:data:`_PTS`, T, N) per point and slit; the sum of
    their camera depths into ``zsum`` (N,), and into ``bad`` (N,) whether a line of sight
    misses a slit's plane or meets it behind the camera or the dot source. The slits are the
    inner loop, without branches, which the compiler vectorises. Returns the number of curve
    points."""
    m = (nt - 1) // _CURVE_STRIDE + 2 if nt > 1 else 1
    for k in range(k0, k1):
        zsum[k] = 0.0
        bad[k] = not np.isfinite(pl[0, k])
    for i in range(m):
        p = order[a0 + min(i * _CURVE_STRIDE, nt - 1)]
        rx, ry, rz = rays[p, 0], rays[p, 1], rays[p, 2]
        for k in range(k0, k1):
            den = pl[0, k] * rx + pl[1, k] * ry + pl[2, k] * rz
            s = num[k] / den
            X = C[0] + s * rx
            Y = C[1] + s * ry
            Z = C[2] + s * rz
            zsum[k] += R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
            qx, qy, qz = X - O[0], Y - O[1], Z - O[2]
            lx = F[0, 0] * qx + F[0, 1] * qy + F[0, 2] * qz
            ly = F[1, 0] * qx + F[1, 1] * qy + F[1, 2] * qz
            lz = F[2, 0] * qx + F[2, 1] * qy + F[2, 2] * qz
            hn = math.sqrt(lx * lx + lz * lz)
            rn = math.sqrt(hn * hn + ly * ly)
            bad[k] |= (abs(den) < 1e-12) | (s <= 0) | (lz <= 0.0)
            pts[0, i, k] = lz / hn
            pts[1, i, k] = lx / hn
            pts[2, i, k] = ly / rn
            pts[3, i, k] = rn
            pts[4, i, k] = lx / lz
    return m


@njit(cache=True)
def _curve_of(pts, m, k, zsum, bad, cp, sp, ss, rr, idx):
    """Slit ``k``'s curve of :func:`_curve_points`: the cosine ``cp`` and sine ``sp`` of its
    points' angle across the slits, the sine ``ss`` of their angle along them and their range
    ``rr``, with ``idx`` their order along the slits. Returns (ok, mean camera depth, the
    number of curve points, the least and the largest angle across the slits); not ok where a
    line of sight misses the plane or meets it behind the camera."""
    if bad[k]:
        return False, 0.0, 0, 0.0, 0.0
    tmin = np.inf
    tmax = -np.inf
    for i in range(m):
        cp[i] = pts[0, i, k]
        sp[i] = pts[1, i, k]
        ss[i] = pts[2, i, k]
        rr[i] = pts[3, i, k]
        idx[i] = i
        tmin = min(tmin, pts[4, i, k])
        tmax = max(tmax, pts[4, i, k])
    for i in range(1, m):  # along the slits (insertion sort: the points come nearly in order)
        j = i
        while j > 0 and ss[idx[j - 1]] > ss[idx[j]]:
            tmp = idx[j - 1]
            idx[j - 1] = idx[j]
            idx[j] = tmp
            j -= 1
    return True, zsum[k] / m, m, math.atan(tmin), math.atan(tmax)


@njit(cache=True)
def _curve(C, rays, order, a0, nt, pl, num, k, O, F, R, t, pts, zsum, bad, cp, sp, ss, rr, idx):
    """One slit's curve (:func:`_curve_points` of the slit ``k`` alone, then
    :func:`_curve_of`)."""
    m = _curve_points(C, rays, order, a0, nt, pl, num, k, k + 1, O, F, R, t, pts, zsum, bad)
    return _curve_of(pts, m, k, zsum, bad, cp, sp, ss, rr, idx)


@njit(cache=True, inline="always")
def _first_from(key, d_order, lo, hi, smin):
    """The first position q in ``lo .. hi`` of a bin of ``d_order`` (its dots along the
    slits) whose dot has ``key`` (the sine of its angle along the slits) >= ``smin`` (``hi``:
    none)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if key[d_order[mid]] < smin:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def _at(ss, cp, sp, rr, idx, nt, ssj, m):
    """The curve's cosine and sine across the slits and its range where the sine of its angle
    along them is ``ssj``, linear between its points, and the segment of the curve it lies
    on, searched from the segment ``m`` on (that of a ``ssj`` no larger, or 0)."""
    while m < nt - 2 and ss[idx[m + 1]] < ssj:
        m += 1
    i0 = idx[m]
    i1 = idx[min(m + 1, nt - 1)]
    span = ss[i1] - ss[i0]
    f = (ssj - ss[i0]) / span if span > 1e-15 else 0.0
    f = min(1.0, max(0.0, f))
    return (
        cp[i0] + f * (cp[i1] - cp[i0]),
        sp[i0] + f * (sp[i1] - sp[i0]),
        rr[i0] + f * (rr[i1] - rr[i0]),
        m,
    )


@njit(cache=True, inline="always")
def _range(rc, cpc, spc, cpj, spj, g):
    """The range of a dot at the angle (cosine ``cpj``, sine ``spj``) across the slits on the
    plane through the curve's point at the angle (``cpc``, ``spc``) and range ``rc`` (same angle
    along the slits), tilted about the slit axis by atan(g) from facing the dot source's axis:
    g = 0 is a plane at right angles to the dots' mean ray."""
    return rc * (cpc + g * spc) / (cpj + g * spj)


@njit(cache=True)
def _scratch(m):
    """Scratch for reading ``m`` places (:func:`_llr_at`): (su, sv, zone, z, inv, llr)."""
    return (
        np.empty(m),
        np.empty(m),
        np.empty(m, np.intp),
        np.empty(m),
        np.empty(m),
        np.empty(m),
    )


@njit(cache=True)
def _llr_at(u, v, amp, n, su, sv, resp, chance, work):
    """The log-likelihood ratios of dots predicted at the places (``u[i]``, ``v[i]``) px,
    i < ``n``, beside a stripe of direction (``su``, ``sv``) on which each dot's response is
    ``amp[i]`` (intensity units), into ``work[5]`` (``work``: :func:`_scratch` of at least
    ``n``): the frame's dots' response there in noise sigmas of its zone and level
    (:func:`~multislit.stripes.dots.z_many`), read through the frame's table of
    :func:`dot_llr` (``chance``, :meth:`FrameDots.kernel_args`); NaN where a dot cannot be
    read (outside the image, on saturated places). Loops without branches on the data, which
    the compiler vectorises."""
    sm, reach, lut_lo, lut_scale, lut_off, lut_inv = resp
    zone_m, pcl, logit_q, tab, tab_lo, tab_scale = chance
    psu, psv, zone, z, inv, out = work
    h, w = zone_m.shape
    for i in range(n):
        inside = (u[i] >= 1.0) & (u[i] <= w - 2.0) & (v[i] >= 1.0) & (v[i] <= h - 2.0)
        uu = u[i] if inside else 1.0
        vv = v[i] if inside else 1.0
        psu[i] = su
        psv[i] = sv
        zone[i] = zone_m[int(vv + 0.5), int(uu + 0.5)]
    z_many(sm, u, v, psu, psv, zone, n, reach, lut_lo, lut_scale, lut_off, lut_inv, z, inv)
    top = tab.shape[1] - 1.0
    for i in range(n):
        inside = (u[i] >= 1.0) & (u[i] <= w - 2.0) & (v[i] >= 1.0) & (v[i] <= h - 2.0)
        good = inside & np.isfinite(z[i])
        uu = u[i] if good else 1.0
        vv = v[i] if good else 1.0
        q = np.intp(pcl[zone[i], int(vv + 0.5) >> _SHIFT, int(uu + 0.5) >> _SHIFT])
        a = ALPHA_SHARE * amp[i] * inv[i]
        y = a * z[i] - 0.5 * a * a + logit_q[q]
        x = (y - tab_lo) * tab_scale + 0.5
        x = tab[q, int(min(max(x if good else 0.0, 0.0), top))]
        out[i] = x if good else np.nan


@njit(cache=True)
def _paths(u0, v0, um, vm, up, vp, amp, G, gvals, pu, pv, pa, m):
    """One predicted dot's places over the slope grid ``gvals`` (S,) into ``pu``, ``pv``
    (its response ``amp`` into ``pa``) from ``m`` on: the path ``p(g)``, the parabola through
    (um, vm), (u0, v0), (up, vp) at g = -G, 0, G. Returns the end."""
    bu = (up - um) / (2.0 * G)
    bv = (vp - vm) / (2.0 * G)
    cu = (up + um - 2.0 * u0) / (2.0 * G * G)
    cv = (vp + vm - 2.0 * v0) / (2.0 * G * G)
    for gi in range(len(gvals)):
        g = gvals[gi]
        pu[m] = u0 + bu * g + cu * g * g
        pv[m] = v0 + bv * g + cv * g * g
        pa[m] = amp
        m += 1
    return m


@njit(cache=True)
def _add_paths(x, sides, n, ns, score, count):
    """Add the log-likelihood ratios ``x`` of ``n`` dots' paths of ``ns`` places each (dot
    after dot), the dot i on the side ``sides[i]``, to ``score`` (2, S) per slope; ``count``
    (2, S) counts the places that favour a dot. Places that cannot be read count neither
    way."""
    m = 0
    for i in range(n):
        sd = sides[i]
        for gi in range(ns):
            if np.isfinite(x[m]):
                score[sd, gi] += x[m]
                if x[m] > 0.0:
                    count[sd, gi] += 1
            m += 1


@njit(cache=True)
def _log_mean_exp(x):
    """log(mean(exp(x))) of a 1-D array, and the index of its largest value."""
    best = 0
    for i in range(1, len(x)):
        if x[i] > x[best]:
            best = i
    acc = 0.0
    for i in range(len(x)):
        acc += math.exp(x[i] - x[best])
    return x[best] + math.log(acc / len(x)), best


#: Rows of the predicted dots' records (:func:`_in_image`), a column per dot in the image: side,
#: dot, the curve's range, cosine and sine across the slits at the dot's angle along them, its
#: place (u, v) at the slope 0 and its expected response.
_REC = 8


#: Rows of the candidate dots (:func:`_slope_zero`), a column per dot: side, dot, the curve's
#: range, cosine and sine across the slits at the dot's angle along them, its place (x, y, z)
#: in the world at the slope 0 and its expected response.
_CAND = 9


@njit(cache=True)
def _slope_zero(k, ssmin, ssmax, phmin, phmax, cp, sp, ss, rr, idx, nc, rig, dots, amp, beta,
                cand, n0):  # fmt: skip
    """The dots of a window's slit hypothesis ``k`` (its curve ``cp``, ``sp``, ``ss``, ``rr``
    sorted by ``idx``, its stripe's peak ``amp``) at the slope 0: each dot in the slit's band
    beside the curve recorded in ``cand`` (:data:`_CAND`, R) from column ``n0`` on. Returns
    the end of the records, or -1 when ``cand`` is too short."""
    C, planes, hb, shb, phi_sign, O, F, cam, R, t, dist, zmin, zmax = rig
    dirs, dcp, dsp, dss, d_order, b_start, phi0, bw = dots
    nb = len(b_start) - 1
    b0 = max(0, int(math.floor((phmin - hb[k] - phi0) / bw)))
    b1 = min(nb - 1, int(math.floor((phmax + hb[k] - phi0) / bw)))
    n = n0
    for b in range(b0, b1 + 1):
        lo = _first_from(dss, d_order, b_start[b], b_start[b + 1], ssmin)
        m = 0  # the dots of a bin come in the order along the slits
        for q in range(lo, b_start[b + 1]):
            j = d_order[q]
            ssj = dss[j]
            if ssj > ssmax:
                break
            cpc, spc, rc, m = _at(ss, cp, sp, rr, idx, nc, ssj, m)
            sd = dsp[j] * cpc - dcp[j] * spc  # the sine of the dot's angle from the curve
            if abs(sd) > shb[k]:
                continue
            if n >= cand.shape[1]:
                return -1
            r0 = _range(rc, cpc, spc, dcp[j], dsp[j], 0.0)
            cand[0, n] = 1 if sd * phi_sign > 0 else 0
            cand[1, n], cand[2, n], cand[3, n], cand[4, n] = j, rc, cpc, spc
            cand[5, n] = O[0] + r0 * dirs[j, 0]
            cand[6, n] = O[1] + r0 * dirs[j, 1]
            cand[7, n] = O[2] + r0 * dirs[j, 2]
            cand[8, n] = beta[j] * amp
            n += 1
    return n


@njit(cache=True)
def _in_image(cand, n, shape, cam, R, t, dist, pu, pv, rec, rec_start, rec_end, nuse):
    """The candidates ``cand[:, :n]`` (:func:`_slope_zero`) projected into the image (of
    ``shape`` (H, W); their places into ``pu``, ``pv``), those in it recorded in ``rec``
    (:data:`_REC`, at least n) in their order: each slit's range of candidates, ``rec_start``,
    ``rec_end`` (N,) (-1: none), becomes its range of records, and its records per side are
    counted in ``nuse`` (N, 2) (the slits without candidates keep theirs)."""
    h, w = shape
    _project_many(cand[5], cand[6], cand[7], n, cam, R, t, dist, pu, pv)
    m = 0
    for k in range(len(rec_start)):
        if rec_start[k] < 0:
            continue
        m0 = m
        nuse[k, 0] = nuse[k, 1] = 0
        for i in range(rec_start[k], rec_end[k]):
            u0, v0 = pu[i], pv[i]
            if not (u0 >= 1.0 and u0 <= w - 2.0 and v0 >= 1.0 and v0 <= h - 2.0):
                continue
            side = int(cand[0, i])
            nuse[k, side] += 1
            rec[0, m], rec[1, m], rec[2, m], rec[3, m] = side, cand[1, i], cand[2, i], cand[3, i]
            rec[4, m], rec[5, m], rec[6, m], rec[7, m] = cand[4, i], u0, v0, cand[8, i]
            m += 1
        rec_start[k], rec_end[k] = m0, m
    return m


@njit(cache=True)
def _slope_places(rec, n0, n1, rig, dots, G, gvals, pu, pv, pa, sides):
    """The places of the recorded dots ``rec[:, n0:n1]`` (:func:`_slope_zero`) over the
    slopes ``gvals`` (S,), dot after dot, into ``pu``, ``pv``, ``pa`` (at least (n1 - n0) S),
    and their sides into ``sides``."""
    C, planes, hb, shb, phi_sign, O, F, cam, R, t, dist, zmin, zmax = rig
    dirs, dcp, dsp, dss, d_order, b_start, phi0, bw = dots
    m = 0
    for n in range(n0, n1):
        j = int(rec[1, n])
        sides[n - n0] = int(rec[0, n])
        rc, cpc, spc, u0, v0, a = rec[2, n], rec[3, n], rec[4, n], rec[5, n], rec[6, n], rec[7, n]
        dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        rm = _range(rc, cpc, spc, dcp[j], dsp[j], -G)
        rp = _range(rc, cpc, spc, dcp[j], dsp[j], G)
        um, vm = _project(O[0] + rm * dx, O[1] + rm * dy, O[2] + rm * dz, cam, R, t, dist)
        up, vp = _project(O[0] + rp * dx, O[1] + rp * dy, O[2] + rp * dz, cam, R, t, dist)
        if not (np.isfinite(um) and np.isfinite(up)):
            um, vm, up, vp = u0, v0, u0, v0
        m = _paths(u0, v0, um, vm, up, vp, a, G, gvals, pu, pv, pa, m)


@njit(cache=True, parallel=True)
def _window_kernel(rays, order, win_start, hyp, rig, dots, wsu, wsv, wamp, beta, resp, chance,
                   G, steps, keep, llr, found, used, slope, kept, span, means):  # fmt: skip
    """:func:`dot_evidence`'s windows; per (window, slit, side) into ``llr``, ``found``,
    ``used`` and ``slope``, per (window, slit) into ``span`` and ``means``: every slit at the
    slope 0 first, then those within ``keep`` of the window's best with the slope
    marginalised, from the dots recorded at the slope 0 (the others keep the marginal's lower
    bound: their score at the slope 0 as if all other slopes found nothing).

    The windows are worked in :data:`_CHUNKS` runs spread over Numba's threads; each window
    writes its own rows only, so the result does not depend on the number of threads."""
    nw = len(win_start) - 1
    maxt = 2
    for wi in range(nw):
        maxt = max(maxt, (win_start[wi + 1] - win_start[wi] - 1) // _CURVE_STRIDE + 2)
    nchunk = min(nw, _CHUNKS)
    for c in prange(nchunk):
        _window_run(c * nw // nchunk, (c + 1) * nw // nchunk, maxt, rays, order, win_start,
                    hyp, rig, dots, wsu, wsv, wamp, beta, resp, chance, G, steps, keep, llr,
                    found, used, slope, kept, span, means)  # fmt: skip


@njit(cache=True)
def _window_run(w0, w1, maxt, rays, order, win_start, hyp, rig, dots, wsu, wsv, wamp, beta,
                resp, chance, G, steps, keep, llr, found, used, slope, kept, span, means):  # fmt: skip
    """:func:`_window_kernel` on the windows ``w0 .. w1 - 1``, with scratch of its own for
    curves of up to ``maxt`` points."""
    C, planes, hb, shb, phi_sign, O, F, cam, R, t, dist, zmin, zmax = rig
    nslit = planes.shape[0]
    shape = chance[0].shape
    gvals = _slope_grid(G, steps)
    ns = len(gvals)
    cp = np.empty(maxt)
    sp = np.empty(maxt)
    ss = np.empty(maxt)
    rr = np.empty(maxt)
    idx = np.empty(maxt, np.int64)
    pl, num = _plane_terms(planes, C)
    pts = np.empty((_PTS, maxt, nslit))
    zsum = np.empty(nslit)
    bad = np.empty(nslit, np.bool_)
    score = np.zeros((2, ns))
    count = np.zeros((2, ns), np.int64)
    quick = np.empty(nslit)
    cand = np.empty((_CAND, 1024))
    rec = np.empty((_REC, 1024))
    work = _scratch(1024)
    pu = np.empty(1024)
    pv = np.empty(1024)
    pa = np.empty(1024)
    sides = np.empty(1024, np.int64)
    rec_start = np.zeros(nslit, np.int64)
    rec_end = np.zeros(nslit, np.int64)
    for wi in range(w0, w1):
        a0 = win_start[wi]
        nt = win_start[wi + 1] - a0
        if nt <= 0:
            continue
        n = 0
        mc = _curve_points(C, rays, order, a0, nt, pl, num, 0, nslit, O, F, R, t, pts, zsum, bad)
        for k in range(nslit):  # every slit's dots at the slope 0
            quick[k] = -np.inf
            rec_start[k] = rec_end[k] = -1
            if not hyp[wi, k] or not np.isfinite(hb[k]):
                continue
            ok, zmean, nc, phmin, phmax = _curve_of(pts, mc, k, zsum, bad, cp, sp, ss, rr, idx)
            if not ok or zmean < zmin or zmean > zmax:
                continue
            span[wi, k, 0] = ss[idx[0]]
            span[wi, k, 1] = ss[idx[nc - 1]]
            m0 = m1 = m2 = m3 = 0.0
            for i in range(nc):
                m0 += cp[i]
                m1 += sp[i]
                m2 += ss[i]
                m3 += rr[i]
            span[wi, k, 2] = m3 / nc
            means[wi, k, 0] = m0 / nc
            means[wi, k, 1] = m1 / nc
            means[wi, k, 2] = m2 / nc
            means[wi, k, 3] = m3 / nc
            while True:
                end = _slope_zero(k, ss[idx[0]], ss[idx[nc - 1]], phmin, phmax, cp, sp, ss, rr,
                                  idx, nc, rig, dots, wamp[wi], beta, cand, n)  # fmt: skip
                if end >= 0:
                    break
                grown = np.empty((_CAND, 2 * cand.shape[1]))
                grown[:, :n] = cand[:, :n]
                cand = grown
            rec_start[k], rec_end[k] = n, end
            n = end
        if rec.shape[1] < n:
            rec = np.empty((_REC, cand.shape[1]))
        if work[0].shape[0] < n:
            work = _scratch(cand.shape[1])
        if pu.shape[0] < n:
            pu = np.empty(cand.shape[1])
            pv = np.empty(cand.shape[1])
            pa = np.empty(cand.shape[1])
        n = _in_image(cand, n, shape, cam, R, t, dist, pu, pv, rec, rec_start, rec_end, used[wi])
        _llr_at(rec[5], rec[6], rec[7], n, wsu[wi], wsv[wi], resp, chance, work)
        x = work[5]
        for k in range(nslit):  # the marginal's lower bound: the slope 0 alone
            if rec_start[k] < 0:
                continue
            score[:, 0] = 0.0
            count[:, 0] = 0
            for i in range(rec_start[k], rec_end[k]):
                if np.isfinite(x[i]):
                    sd = int(rec[0, i])
                    score[sd, 0] += x[i]
                    if x[i] > 0.0:
                        count[sd, 0] += 1
            for sd in range(2):
                llr[wi, k, sd] = score[sd, 0] - math.log(ns)
                found[wi, k, sd] = count[sd, 0]
                slope[wi, k, sd] = 0.0
            quick[k] = score[0, 0] + score[1, 0]
        best = -np.inf
        for k in range(nslit):
            best = max(best, quick[k])
        for k in range(nslit):  # the slits worth the slope: near the best at the slope 0
            if not (np.isfinite(quick[k]) and quick[k] >= best - keep):
                continue
            nd = rec_end[k] - rec_start[k]
            if pu.shape[0] < nd * ns:
                pu = np.empty(2 * nd * ns)
                pv = np.empty(2 * nd * ns)
                pa = np.empty(2 * nd * ns)
            if sides.shape[0] < nd:
                sides = np.empty(2 * nd, np.int64)
            if work[0].shape[0] < nd * ns:
                work = _scratch(2 * nd * ns)
            _slope_places(rec, rec_start[k], rec_end[k], rig, dots, G, gvals, pu, pv, pa, sides)
            _llr_at(pu, pv, pa, nd * ns, wsu[wi], wsv[wi], resp, chance, work)
            score[:] = 0.0
            count[:] = 0
            _add_paths(work[5], sides, nd, ns, score, count)
            for sd in range(2):
                lm, bi = _log_mean_exp(score[sd])
                llr[wi, k, sd] = lm
                found[wi, k, sd] = count[sd, bi]
                slope[wi, k, sd] = gvals[bi]
                kept[wi, k] = True


@njit(cache=True)
def _slope_grid(G, steps):
    """(2 steps + 1,) slopes: tan of tilts evenly spaced in [-atan G, atan G] (a uniform prior
    of the surface's tilt across the stripe)."""
    bmax = math.atan(G)
    out = np.empty(2 * steps + 1)
    for i in range(-steps, steps + 1):
        out[i + steps] = math.tan(i * bmax / steps)
    return out


@njit(cache=True, inline="always")
def _point(O, F, cp, sp, ss, r):
    """The world point at range ``r`` from the dot source in the direction of the angles
    (cosine ``cp``, sine ``sp`` across the slits; sine ``ss`` along them)."""
    cs = math.sqrt(max(0.0, 1.0 - ss * ss))
    lx, ly, lz = sp * cs, ss, cp * cs
    return (
        O[0] + r * (F[0, 0] * lx + F[1, 0] * ly + F[2, 0] * lz),
        O[1] + r * (F[0, 1] * lx + F[1, 1] * ly + F[2, 1] * lz),
        O[2] + r * (F[0, 2] * lx + F[1, 2] * ly + F[2, 2] * lz),
    )


#: Rows of the dots between two pieces (:func:`_gap_run`), a column per dot: side (the nearer
#: stripe's), expected response, and in the world its place on the surface through both stripes,
#: its place at the slope 0 about the nearer stripe and at the slopes -G and G (x, y, z each).
_GAP_PTS = 14


@njit(cache=True, inline="always")
def _on_ray(pts, row, i, O, d, r):
    """The point at range ``r`` on the ray from ``O`` along ``d`` (3,) into ``pts[row:row+3,
    i]``."""
    pts[row, i] = O[0] + r * d[0]
    pts[row + 1, i] = O[1] + r * d[1]
    pts[row + 2, i] = O[2] + r * d[2]


@njit(cache=True, parallel=True)
def _gap_kernel(rays, a_order, a_start, b_order, b_start_, ga, gb, means, rig, dots, gsu, gsv,
                gamp, beta, resp, chance, G, steps, pairs, fixed, free_a, free_b,
                graze):  # fmt: skip
    """:func:`gap_evidence`: per gap and slit k of its left piece (k + 1 of its right one);
    the gaps in :data:`_CHUNKS` runs spread over Numba's threads (each writes its own rows)."""
    ngap = len(a_start) - 1
    maxt = 2
    for p in range(ngap):
        na_ = (a_start[p + 1] - a_start[p] - 1) // _CURVE_STRIDE + 2
        nb_ = (b_start_[p + 1] - b_start_[p] - 1) // _CURVE_STRIDE + 2
        maxt = max(maxt, na_, nb_)
    nchunk = min(ngap, _CHUNKS)
    for c in prange(nchunk):
        _gap_run(c * ngap // nchunk, (c + 1) * ngap // nchunk, maxt, rays, a_order, a_start,
                 b_order, b_start_, ga, gb, means, rig, dots, gsu, gsv, gamp, beta, resp, chance,
                 G, steps, pairs, fixed, free_a, free_b, graze)  # fmt: skip


@njit(cache=True)
def _gap_run(p0, p1, maxt, rays, a_order, a_start, b_order, b_start_, ga, gb, means, rig, dots,
             gsu, gsv, gamp, beta, resp, chance, G, steps, pairs, fixed, free_a, free_b,
             graze):  # fmt: skip
    """:func:`_gap_kernel` on the gaps ``p0 .. p1 - 1``, with scratch of its own for curves of
    up to ``maxt`` points."""
    C, planes, hb, shb, phi_sign, O, F, cam, R, t, dist, zmin, zmax = rig
    dirs, dcp, dsp, dss, d_order, b_start, phi0, bw = dots
    nslit = planes.shape[0]
    h, w = chance[0].shape
    nb = len(b_start) - 1
    cpa = np.empty(maxt)
    spa = np.empty(maxt)
    ssa = np.empty(maxt)
    rra = np.empty(maxt)
    ia = np.empty(maxt, np.int64)
    cpb = np.empty(maxt)
    spb = np.empty(maxt)
    ssb = np.empty(maxt)
    rrb = np.empty(maxt)
    ib = np.empty(maxt, np.int64)
    pl, num = _plane_terms(planes, C)
    cpts = np.empty((_PTS, maxt, nslit))
    zsum = np.empty(nslit)
    bad = np.empty(nslit, np.bool_)
    gvals = _slope_grid(G, steps)
    ns = len(gvals)
    score = np.zeros((2, ns))
    count = np.zeros((2, ns), np.int64)
    pts = np.empty((_GAP_PTS, 256))  # the dots between the pieces, in the world
    uv = np.empty((8, 256))  # ... and in the image
    pu = np.empty(256 * ns)  # their paths with a free slope about the nearer stripe
    pv = np.empty(256 * ns)
    pa = np.empty(256 * ns)
    sides = np.empty(256, np.int64)
    work = _scratch(256 * ns)
    for p in range(p0, p1):
        a0, na0 = a_start[p], a_start[p + 1] - a_start[p]
        c0, nb0 = b_start_[p], b_start_[p + 1] - b_start_[p]
        if na0 < 2 or nb0 < 2:
            continue
        wa, wb = ga[p], gb[p]
        for k in range(nslit - 1):
            ma, mb = means[wa, k], means[wb, k + 1]
            if not (np.isfinite(ma[3]) and np.isfinite(mb[3])):
                continue  # a window outside the measuring volume (or a slit without a plane)
            # how nearly the surface through both stripes grazes the camera's or the dot
            # source's line of sight: from each window's mean place, across the slits only
            xa, ya, za = _point(O, F, ma[0], ma[1], ma[2], ma[3])
            xb, yb, zb = _point(O, F, mb[0], mb[1], mb[2], mb[3])
            sx, sy, sz = xb - xa, yb - ya, zb - za
            along = sx * F[1, 0] + sy * F[1, 1] + sz * F[1, 2]
            sx, sy, sz = sx - along * F[1, 0], sy - along * F[1, 1], sz - along * F[1, 2]
            sn = math.sqrt(sx * sx + sy * sy + sz * sz) + 1e-12
            mx, my, mz = 0.5 * (xa + xb), 0.5 * (ya + yb), 0.5 * (za + zb)
            cx_, cy_, cz_ = mx - C[0], my - C[1], mz - C[2]
            cn = math.sqrt(cx_ * cx_ + cy_ * cy_ + cz_ * cz_)
            qx_, qy_, qz_ = mx - O[0], my - O[1], mz - O[2]
            qn = math.sqrt(qx_ * qx_ + qy_ * qy_ + qz_ * qz_)
            g1 = abs(sx * cx_ + sy * cy_ + sz * cz_) / (sn * cn)
            g2 = abs(sx * qx_ + sy * qy_ + sz * qz_) / (sn * qn)
            graze[p, k] = max(g1, g2)
            if not pairs[p, k]:
                continue
            oka, _, na, pha0, pha1 = _curve(C, rays, a_order, a0, na0, pl, num, k, O, F, R, t,
                                            cpts, zsum, bad, cpa, spa, ssa, rra, ia)  # fmt: skip
            okb, _, nbp, phb0, phb1 = _curve(C, rays, b_order, c0, nb0, pl, num, k + 1, O, F, R,
                                             t, cpts, zsum, bad, cpb, spb, ssb, rrb, ib)  # fmt: skip
            if not (oka and okb):
                continue
            ssmin = max(ssa[ia[0]], ssb[ib[0]])
            ssmax = min(ssa[ia[na - 1]], ssb[ib[nbp - 1]])
            if ssmax <= ssmin:
                continue
            b0 = max(0, int(math.floor((min(pha0, phb0) - phi0) / bw)))
            b1 = min(nb - 1, int(math.floor((max(pha1, phb1) - phi0) / bw)))
            nf = 0
            for bb in range(b0, b1 + 1):
                lo = _first_from(dss, d_order, b_start[bb], b_start[bb + 1], ssmin)
                ma = mb = 0  # the dots of a bin come in the order along the slits
                for q in range(lo, b_start[bb + 1]):
                    j = d_order[q]
                    ssj = dss[j]
                    if ssj > ssmax:
                        break
                    cpa_, spa_, ra, ma = _at(ssa, cpa, spa, rra, ia, na, ssj, ma)
                    cpb_, spb_, rb, mb = _at(ssb, cpb, spb, rrb, ib, nbp, ssj, mb)
                    # the dot's place across, from a's stripe (0) to b's (1)
                    width = spb_ * cpa_ - cpb_ * spa_
                    if abs(width) < 1e-12:
                        continue
                    f = (dsp[j] * cpa_ - dcp[j] * spa_) / width
                    if f <= 0.0 or f >= 1.0:
                        continue
                    if nf >= pts.shape[1]:
                        grown = np.empty((_GAP_PTS, 2 * pts.shape[1]))
                        grown[:, :nf] = pts[:, :nf]
                        pts = grown
                    # on the surface between the two stripes (range linear across), and with a
                    # free slope about the nearer stripe
                    side = 0 if f <= 0.5 else 1
                    cpc, spc, rc = (cpa_, spa_, ra) if side == 0 else (cpb_, spb_, rb)
                    pts[0, nf] = side
                    pts[1, nf] = beta[j] * gamp[p]
                    _on_ray(pts, 2, nf, O, dirs[j], ra + f * (rb - ra))
                    _on_ray(pts, 5, nf, O, dirs[j], _range(rc, cpc, spc, dcp[j], dsp[j], 0.0))
                    _on_ray(pts, 8, nf, O, dirs[j], _range(rc, cpc, spc, dcp[j], dsp[j], -G))
                    _on_ray(pts, 11, nf, O, dirs[j], _range(rc, cpc, spc, dcp[j], dsp[j], G))
                    nf += 1
            if uv.shape[1] < nf:
                uv = np.empty((8, pts.shape[1]))
            if sides.shape[0] < nf:
                sides = np.empty(pts.shape[1], np.int64)
                pu = np.empty(pts.shape[1] * ns)
                pv = np.empty(pts.shape[1] * ns)
                pa = np.empty(pts.shape[1] * ns)
            if work[0].shape[0] < nf * ns:
                work = _scratch(pts.shape[1] * ns)
            for c in range(4):
                _project_many(pts[2 + 3 * c], pts[3 + 3 * c], pts[4 + 3 * c], nf, cam, R, t, dist,
                              uv[2 * c], uv[2 * c + 1])  # fmt: skip
            nd = 0
            for i in range(nf):
                u0, v0 = uv[2, i], uv[3, i]
                if not (u0 >= 1.0 and u0 <= w - 2.0 and v0 >= 1.0 and v0 <= h - 2.0):
                    continue
                um, vm, up, vp = uv[4, i], uv[5, i], uv[6, i], uv[7, i]
                if not (np.isfinite(um) and np.isfinite(up)):
                    um, vm, up, vp = u0, v0, u0, v0
                sides[nd] = int(pts[0, i])
                _paths(u0, v0, um, vm, up, vp, pts[1, i], G, gvals, pu, pv, pa, nd * ns)
                nd += 1
            _llr_at(uv[0], uv[1], pts[1], nf, gsu[p], gsv[p], resp, chance, work)
            fx = 0.0
            for i in range(nf):
                if np.isfinite(work[5][i]):
                    fx += work[5][i]
            _llr_at(pu, pv, pa, nd * ns, gsu[p], gsv[p], resp, chance, work)
            score[:] = 0.0
            count[:] = 0
            _add_paths(work[5], sides, nd, ns, score, count)
            fixed[p, k] = fx
            free_a[p, k] = _log_mean_exp(score[0])[0]
            free_b[p, k] = _log_mean_exp(score[1])[0]


def frame_dots(extraction, spacing_px: float) -> FrameDots:
    """The frame's dots of an extraction (:class:`~multislit.stripes.SlitExtraction`): its
    dots' response (:func:`~multislit.stripes.dots.dot_response`, its noise measured up to half
    the slits' spacing ``spacing_px`` across the stripes), the dots found in its dot image
    (:func:`~multislit.stripes.dots.find_dots`, speckle on the stripes left out) with the
    chance of a false match measured over squares of about ``spacing_px`` around each place,
    and the dots' brightness relative to the stripes beside them."""
    ex = extraction
    h, w = ex.dots.shape
    clearance = STRIPE_CLEARANCE * ex.stripe_width_px
    near_zone = near_stripes(ex.u, ex.v, (h, w), clearance)
    found = find_dots(ex.dots, ex.noise_sigma, ex.dot_size_px)
    dots, near = dots_off_stripes(found, near_zone, ex.u, ex.v, ex.peak, clearance, MIN_DOT_RATIO)
    response = dot_response(
        ex.plane,
        ex.dot_size_px,
        ex.u,
        ex.v,
        ex.angle,
        near_zone,
        0.5 * max(float(spacing_px), 2.0 * clearance),
        saturation_level_of(ex.plane),
    )
    pf = false_match_map(dots, near, near_zone, max(8.0, float(spacing_px)))
    return FrameDots(
        dots,
        near,
        float(clearance),
        pf,
        dot_grid(dots, (h, w)),
        near_zone.view(np.uint8),
        response,
        _dot_brightness(ex, dots.subset(~near), response, spacing_px),
    )


def _dot_brightness(ex, dots: DotCentres, response: DotResponse, spacing_px: float) -> float:
    """The dots' response per unit of the peak of the stripe nearest them: the median over
    (a sample of :data:`_BRIGHTNESS_SAMPLE` of) the dots found clear of the stripes within a
    slit spacing of a stripe centre (every fourth centre); 1 where there are none."""
    if len(dots) == 0 or len(ex.u) == 0:
        return 1.0
    step = max(1, len(dots) // _BRIGHTNESS_SAMPLE)
    u, v = dots.u[::step], dots.v[::step]
    centre = np.arange(0, len(ex.u), 4)
    cu, cv = ex.u[centre], ex.v[centre]
    tol = max(float(spacing_px), 1.0)
    g_order, g_start, gnx, gny = point_grid(cu, cv, ex.dots.shape, tol)
    i = np.empty(len(u), np.intp)
    _nearest_each(u, v, tol, cu, cv, g_order, g_start, gnx, gny, tol, i)
    ok = i >= 0
    if not ok.any():
        return 1.0
    i = centre[i[ok]]
    r, _ = response.at(u[ok], v[ok], np.nan_to_num(ex.angle[i]))
    ratio = r / np.maximum(ex.peak[i], 1e-9)
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    return float(np.median(ratio)) if ratio.size else 1.0


@njit(cache=True)
def _nearest_at(u0, v0, tol, ou, ov, g_order, g_start, gnx, gny, cell):
    """The observed dot nearest (u0, v0) within ``tol`` px (-1: none)."""
    cx0 = max(0, int((u0 - tol) / cell))
    cx1 = min(gnx - 1, int((u0 + tol) / cell))
    cy0 = max(0, int((v0 - tol) / cell))
    cy1 = min(gny - 1, int((v0 + tol) / cell))
    best = -1
    bd = tol * tol
    for cy in range(cy0, cy1 + 1):
        for cx in range(cx0, cx1 + 1):
            cidx = cy * gnx + cx
            for e in range(g_start[cidx], g_start[cidx + 1]):
                o = g_order[e]
                d = (ou[o] - u0) ** 2 + (ov[o] - v0) ** 2
                if d <= bd:
                    bd = d
                    best = o
    return best


@njit(cache=True)
def _nearest_each(u, v, tol, ou, ov, g_order, g_start, gnx, gny, cell, out):
    """:func:`_nearest_at` of every place (``u``, ``v``) (M,) into ``out`` (M,)."""
    for i in range(u.shape[0]):
        out[i] = _nearest_at(u[i], v[i], tol, ou, ov, g_order, g_start, gnx, gny, cell)


@njit(cache=True)
def _match_kernel(rays, order, win_start, windows, labels, slopes, rig, dots, ou, ov, g_order,
                  g_start, gnx, gny, cell, tol, out_obs, out_dot, out_win):  # fmt: skip
    """:func:`dot_matches`: per window of ``windows`` with slit ``labels`` and the slopes
    ``slopes`` (W', 2) per side, the observed dot nearest each predicted dot (within
    ``tol``); returns how many pairs were written."""
    C, planes, hb, shb, phi_sign, O, F, cam, R, t, dist, zmin, zmax = rig
    dirs, dcp, dsp, dss, d_order, b_start, phi0, bw = dots
    nb = len(b_start) - 1
    maxt = 2
    for wi in range(len(win_start) - 1):
        maxt = max(maxt, (win_start[wi + 1] - win_start[wi] - 1) // _CURVE_STRIDE + 2)
    cp = np.empty(maxt)
    sp = np.empty(maxt)
    ss = np.empty(maxt)
    rr = np.empty(maxt)
    idx = np.empty(maxt, np.int64)
    pl, num = _plane_terms(planes, C)
    pts = np.empty((_PTS, maxt, planes.shape[0]))
    zsum = np.empty(planes.shape[0])
    bad = np.empty(planes.shape[0], np.bool_)
    n = 0
    for i in range(len(windows)):
        wi = windows[i]
        k = labels[i]
        a0 = win_start[wi]
        nt = win_start[wi + 1] - a0
        ok, _, nc, phmin, phmax = _curve(
            C, rays, order, a0, nt, pl, num, k, O, F, R, t, pts, zsum, bad, cp, sp, ss, rr, idx
        )
        if not ok:
            continue
        ssmin, ssmax = ss[idx[0]], ss[idx[nc - 1]]
        b0 = max(0, int(math.floor((phmin - hb[k] - phi0) / bw)))
        b1 = min(nb - 1, int(math.floor((phmax + hb[k] - phi0) / bw)))
        for b in range(b0, b1 + 1):
            lo = _first_from(dss, d_order, b_start[b], b_start[b + 1], ssmin)
            m = 0  # the dots of a bin come in the order along the slits
            for q in range(lo, b_start[b + 1]):
                j = d_order[q]
                if dss[j] > ssmax:
                    break
                cpc, spc, rc, m = _at(ss, cp, sp, rr, idx, nc, dss[j], m)
                sd = dsp[j] * cpc - dcp[j] * spc
                if abs(sd) > shb[k]:
                    continue
                side = 1 if sd * phi_sign > 0 else 0
                r = _range(rc, cpc, spc, dcp[j], dsp[j], slopes[i, side])
                u0, v0 = _project(
                    O[0] + r * dirs[j, 0], O[1] + r * dirs[j, 1], O[2] + r * dirs[j, 2], cam, R,
                    t, dist,
                )  # fmt: skip
                if not np.isfinite(u0):
                    continue
                o = _nearest_at(u0, v0, tol, ou, ov, g_order, g_start, gnx, gny, cell)
                if o >= 0 and n < len(out_obs):
                    out_obs[n] = o
                    out_dot[n] = j
                    out_win[n] = wi
                    n += 1
    return n


def dot_matches(
    rig: RigGeometry,
    rays: F64,
    order: NDArray[np.intp],
    win_start: NDArray[np.intp],
    frame: FrameDots,
    windows: NDArray[np.intp],
    labels: NDArray[np.intp],
    slopes: F64,
    confidence: F64,
    direction: F64,
) -> DotMatches:
    """The observed dots the labelled windows' predictions found: each predicted dot of a
    window (under its slit and at its best slope on each side) paired with the observed dot
    nearest its place within :data:`MATCH_TOL_PX`; an observed dot that two predictions
    found is left out (ambiguous). The paired dots keep the centres they were found at; a scan
    that measures them centres them as spots (:func:`~multislit.stripes.dots.centre_dots`).

    Parameters
    ----------
    rig, rays, order, win_start, frame : as for :func:`dot_evidence`
    windows : (W',) intp, the labelled windows
    labels : (W',) intp, their slits
    slopes : (W', 2) float64, their best slope on each side
    confidence : (W',) float64, their confidence
    direction : (W,) float64, rad, every window's stripe direction (from the image's vertical)

    Returns
    -------
    DotMatches
    """
    cap = max(16, 64 * len(windows))
    out_obs = np.empty(cap, np.int64)
    out_dot = np.empty(cap, np.int64)
    out_win = np.empty(cap, np.int64)
    n = 0
    if len(windows):
        rig_k, dots_k = _rig_args(rig)
        g_order, g_start, gnx, gny = frame.grid
        n = _match_kernel(
            np.ascontiguousarray(rays, np.float64),
            order.astype(np.intp),
            win_start.astype(np.intp),
            np.asarray(windows, np.intp),
            np.asarray(labels, np.intp),
            np.ascontiguousarray(slopes, np.float64),
            rig_k,
            dots_k,
            frame.dots.u,
            frame.dots.v,
            g_order,
            g_start,
            gnx,
            gny,
            _CELL,
            MATCH_TOL_PX,
            out_obs,
            out_dot,
            out_win,
        )
    obs, dot, win = out_obs[:n], out_dot[:n], out_win[:n]
    # one ray per observed dot and one observed dot per ray
    once = (np.bincount(obs, minlength=len(frame.dots))[obs] == 1) & (
        np.bincount(dot, minlength=rig.dots.num_dots)[dot] == 1
    )
    obs, dot, win = obs[once], dot[once], win[once]
    slit = np.zeros(int(np.max(windows, initial=-1)) + 1, np.int64)
    slit[np.asarray(windows, np.intp)] = labels
    conf = np.zeros(len(slit))
    conf[np.asarray(windows, np.intp)] = confidence
    return DotMatches(
        frame.dots.u[obs], frame.dots.v[obs], dot, win, slit[win], conf[win], direction[win]
    )

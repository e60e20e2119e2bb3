"""Reference images: one curve per slit ("reference lines"), the dot images, and the epipole.

The paper records a flat board at a few distances with the lasers on and fits a line to each
slit. We fit a low-order polynomial u = p(v) per slit (a straight line bends slightly under lens
distortion) and number the slits 0..N-1 from left to right.

The epipolar geometry that identification needs is that of the camera and the *dot* projector:
as the depth of a surface point changes, the dots around it move in the image along a line
through the dot projector's epipole. With no calibration at all, the epipole is estimated from
the reference images themselves: the same dots, matched between two board distances, move along
lines that all pass through it.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from multislit.errors import ReferenceImageError
from multislit.identify.patches import (
    WINDOW_SUMS,
    normalise_patches,
    sample_patch_columns,
    sample_patches,
    window_sums,
)
from multislit.io import Capture, write_bytes_atomic
from multislit.stripes import SlitExtraction, extract_slits
from multislit.stripes.validation import SlitExtractionError, as_image

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
#: The row background (``extract_slits(background=...)``) of the reference boards and of the
#: frames the template method matches against them: the paper's row median. Over the scans'
#: default, the row opening, the template matching's confident mistakes on the half-size
#: spheres scene (``tests/test_identify.py``) rose from 0 to 0.46-0.51 %, the frames alone or
#: the frames and the boards extracted over it.
TEMPLATE_BACKGROUND = "median"
#: Degree of the polynomial u = p(v) fitted per slit: a line plus the bend of a few px that
#: lens distortion gives.
CURVE_DEGREE = 3
#: Dots a template holds on average when dots are matched between reference images.
_EPIPOLE_DOTS = 12.0
#: Pairs of dot tracks whose meeting points are tried as the epipole (:func:`_track_epipole`):
#: with half the tracks wrong, a quarter of the pairs are both right.
_EPIPOLE_PAIRS = 500
#: A track whose end is this close (px) to its line through the epipole is kept however
#: small the others' spread (the tracks' ends are sub-pixel matches).
_EPIPOLE_TOLERANCE = 0.5
#: Rounds of the least squares epipole over the tracks near the last one.
_EPIPOLE_ROUNDS = 5
#: Templates scored per matrix product in the epipole's dot search.
_SCORE_BLOCK = 8
#: Zeros after each row of :meth:`ReferenceSet.padded_dots` (px): more than a vector's lanes,
#: and rows not a multiple of the page size long.
_ROW_PAD = 32
#: A candidate patch whose values' norm about their mean is at most this is flat (score 0), as
#: in :func:`normalise_patches`.
_FLAT = 1e-6


# --------------------------------------------------------------------------- curves
def _fit_curves(
    ex: SlitExtraction, num_slits: int, name: str, image_height: int
) -> tuple[F64, F64]:
    """Group one reference image's centre points into ``num_slits`` slits; a curve per slit.

    On a flat board every row crosses all N slits in order. Rows that show exactly N linked
    stripe centres number them 0..N-1 from left to right; each linked segment takes the number
    its points got most often, so a slit broken into pieces, short ones included, is still one
    slit. A residue of dots lined up along v makes its rows show N + 1 centres: it gets no
    number, and its points are left out.
    """
    seg = ex.segment
    use = seg >= 0
    if not np.any(use):
        raise ReferenceImageError(
            f"reference image {name}: no slits found (is the board lit by the lasers?)"
        )
    u, v, sg = ex.u[use], ex.v[use], seg[use]
    row = np.round(v).astype(int)
    order = np.lexsort((u, row))
    u, v, sg, row = u[order], v[order], sg[order], row[order]
    rows, start, per_row = np.unique(row, return_index=True, return_counts=True)
    complete = per_row == num_slits
    if complete.sum() < max(10, 0.2 * rows.size):
        typical = int(np.bincount(per_row).argmax())
        raise ReferenceImageError(
            f"reference image {name}: found {typical} slits in most rows, expected {num_slits}; "
            f"every slit must cross the board in every reference image (check that the board "
            f"fills the field of view, the exposure, and rig.json's num_slits)"
        )
    rank = np.full(len(u), -1)
    rank[(start[complete][:, None] + np.arange(num_slits)).ravel()] = np.tile(
        np.arange(num_slits), int(complete.sum())
    )
    lab = _segment_ranks(sg, rank, num_slits)
    coeffs = np.zeros((num_slits, CURVE_DEGREE + 1))
    vrange = np.zeros((num_slits, 2))
    by_slit = np.argsort(lab, kind="stable")  # each slit's points in their order
    ends = np.searchsorted(lab[by_slit], np.arange(num_slits + 1))
    for k in range(num_slits):
        m = by_slit[ends[k] : ends[k + 1]]
        if m.size < max(20, 0.2 * image_height):
            raise ReferenceImageError(
                f"reference image {name}: slit {k} is seen over only {m.size} rows; every "
                f"slit must cross the board (is part of the board in shadow or outside the fan?)"
            )
        vk, uk = v[m], u[m]
        c = np.polyfit(vk, uk, CURVE_DEGREE)
        r = uk - np.polyval(c, vk)
        ok = np.abs(r) < max(1.0, 4 * 1.4826 * np.median(np.abs(r)))
        coeffs[k] = np.polyfit(vk[ok], uk[ok], CURVE_DEGREE)
        vrange[k] = vk[ok].min(), vk[ok].max()
    mid = np.array([np.polyval(c, image_height / 2.0) for c in coeffs])
    if np.any(np.diff(mid) <= 0):
        raise ReferenceImageError(
            f"reference image {name}: slit curves cross each other; is this a flat board?"
        )
    return coeffs, vrange


def _segment_ranks(sg: NDArray[np.intp], rank: NDArray[np.intp], num_slits: int) -> NDArray:
    """The slit number of each point's segment: the rank (0..N-1, -1 unknown) that most of the
    segment's ranked points got (the smallest such rank on a tie), if at least 90% of them got
    it (a segment that changes rank is two slits joined), else -1."""
    seg_ids, inv = np.unique(sg, return_inverse=True)
    ranked = rank >= 0
    pair, count = np.unique(inv[ranked] * num_slits + rank[ranked], return_counts=True)
    p_seg, p_rank = pair // num_slits, pair % num_slits
    total = np.bincount(p_seg, weights=count, minlength=len(seg_ids))
    # per segment the pair with the most points, the smallest rank first among equals
    order = np.lexsort((p_rank, -count, p_seg))
    first = order[np.r_[True, p_seg[order][1:] != p_seg[order][:-1]]]
    keep = count[first] >= 0.9 * total[p_seg[first]]
    seg_rank = np.full(len(seg_ids), -1)
    seg_rank[p_seg[first][keep]] = p_rank[first][keep]
    return seg_rank[inv]


def curve_u(coeffs: F64, v: F64) -> F64:
    """Evaluate curves: coeffs (..., D+1) highest power first, v broadcastable -> u."""
    u = np.zeros(np.broadcast_shapes(coeffs.shape[:-1], np.shape(v)))
    for i in range(coeffs.shape[-1]):
        u = u * v + coeffs[..., i]
    return u


def curve_du(coeffs: F64, v: F64) -> F64:
    """Derivative du/dv of the curves."""
    d = coeffs.shape[-1] - 1
    out = np.zeros(np.broadcast_shapes(coeffs.shape[:-1], np.shape(v)))
    for i in range(d):
        out = out * v + coeffs[..., i] * (d - i)
    return out


@njit(cache=True)
def _newton_kernel(lines, coeffs_t, v, iterations, tol, block):
    """Newton steps of :func:`intersect_line_curves` on a grid: line ``lines[p, q]`` (P, Q, 3)
    with curve ``coeffs_t[p, :, s]`` (P, D+1, S), from and into ``v`` (P, Q, S).

    The same float64 operations in the same order as :func:`curve_u` and :func:`curve_du` (no
    fused multiply-adds), so the same numbers; the loops along S vectorise. Blocks of
    ``block`` lines along Q each stop on their own.
    """
    P, Q, S = v.shape
    d = coeffs_t.shape[1] - 1
    u = np.empty(S)
    du = np.empty(S)
    for q0 in range(0, Q, block):
        _newton_block(lines, coeffs_t, v, iterations, tol, q0, min(q0 + block, Q), d, u, du)


@njit(cache=True)
def _newton_block(lines, coeffs_t, v, iterations, tol, q0, q1, d, u, du):
    """:func:`_newton_kernel` on the lines ``q0:q1``."""
    P, S = v.shape[0], v.shape[2]
    for _ in range(iterations):
        moved = False
        for p in range(P):
            cf = coeffs_t[p]
            for q in range(q0, q1):
                x = v[p, q]
                u[:] = 0.0
                du[:] = 0.0
                for e in range(d + 1):
                    for s in range(S):
                        u[s] = u[s] * x[s] + cf[e, s]
                for e in range(d):
                    for s in range(S):
                        du[s] = du[s] * x[s] + cf[e, s] * (d - e)
                a, b, c = lines[p, q, 0], lines[p, q, 1], lines[p, q, 2]
                for s in range(S):
                    f = a * u[s] + b * x[s] + c
                    df = a * du[s] + b
                    dv = f / df if abs(df) > 1e-12 else np.nan
                    x[s] = x[s] - dv
                    moved |= abs(dv) > tol  # (NaN compares False: no intersection)
        if not moved:
            break


def intersect_line_curves(
    lines: F64,
    coeffs: F64,
    v0: F64,
    iterations: int = 6,
    tol: float = 1e-6,
    *,
    block: int | None = None,
) -> F64:
    """Rows v where lines a u + b v + c = 0 meet curves u = p(v) (Newton from v0), broadcast.

    At most ``iterations`` Newton steps, all points together; stops early once no step
    exceeds ``tol`` px. Compiled; fastest when the lines vary along other axes than the curves
    do (every line with every curve, as :func:`~multislit.identify.matching.score_candidates`
    asks: lines (1, M, 1, 3) with curves (R, 1, N, D+1)).

    Parameters
    ----------
    lines : (..., 3) float64, (a, b, c) per line
    coeffs : (..., D+1) float64, u = p(v), highest power first (:func:`curve_u`)
    v0 : (...) float64, px, the start rows
    iterations : most Newton steps
    tol : px, the step size below which a point has converged
    block : the points are taken in blocks of this many lines (of the axes where only the
        lines vary), each stopping on its own (same numbers as one call per block); default
        all at once

    Returns
    -------
    v : float64, px, broadcast shape of the three (a view of the grid's memory, laid out in
        its order); NaN where there is no intersection
    """
    lines = np.asarray(lines, dtype=np.float64)
    coeffs = np.asarray(coeffs, dtype=np.float64)
    shape = np.broadcast_shapes(lines.shape[:-1], coeffs.shape[:-1], np.shape(v0))
    if 0 in shape:
        return np.zeros(shape)
    # the grid (P, Q, S): the axes where only the curves vary (S) go last, where only the
    # lines vary (Q) next, the rest (P) first; lines and curves are made (P, Q) and (P, S)
    nd = len(shape)
    ls = (1,) * (nd - lines.ndim + 1) + lines.shape[:-1]
    cs = (1,) * (nd - coeffs.ndim + 1) + coeffs.shape[:-1]
    only_c = [i for i in range(nd) if ls[i] == 1 and shape[i] > 1]
    only_l = [i for i in range(nd) if cs[i] == 1 and shape[i] > 1 and i not in only_c]
    rest = [i for i in range(nd) if i not in only_c and i not in only_l]
    order = rest + only_l + only_c
    P = int(np.prod([shape[i] for i in rest]))
    Q = int(np.prod([shape[i] for i in only_l]))
    S = int(np.prod([shape[i] for i in only_c]))
    lb = np.broadcast_to(lines.reshape(ls + (3,)), shape + (3,)).transpose(order + [nd])
    cb = np.broadcast_to(coeffs.reshape(cs + coeffs.shape[-1:]), shape + coeffs.shape[-1:])
    cb = cb.transpose(order + [nd])
    ln = np.ascontiguousarray(lb[(Ellipsis,) + (0,) * len(only_c) + (slice(None),)]).reshape(
        P, Q, 3
    )
    idx = tuple([slice(None)] * len(rest) + [0] * len(only_l))
    ct = np.ascontiguousarray(np.moveaxis(cb[idx].reshape(P, S, -1), 2, 1))
    # the start rows, copied into the grid's order (and updated there in place)
    vg = np.array(np.broadcast_to(v0, shape).transpose(order), np.float64, order="C")
    vg = vg.reshape(P, Q, S)
    _newton_kernel(ln, ct, vg, int(iterations), float(tol), max(1, int(block or Q)))
    return vg.reshape([shape[i] for i in order]).transpose(np.argsort(order))


# --------------------------------------------------------------------------- reference set
@dataclass(frozen=True, eq=False)
class ReferenceSet:
    """Everything identification needs from the reference images, prepared once.

    Attributes
    ----------
    image_size : (W, H) px
    num_slits : N
    names : (R,) reference image names
    curves : (R, N, D+1) float64, u = p(v) per image and slit (highest power first)
    vrange : (R, N, 2) float64, px, rows where each curve was seen
    dots : (R, H, W) float32, the dot images (slits removed)
    epipole : (3,) float64, homogeneous image point of the dot projector
    spacing_px : float, median slit spacing in the references
    dot_density : float, dots per px^2 within the slit field (sizes the templates)
    stripe_width_px, dot_size_px : float, measured in the references
    epipole_residual_px : float, RMS distance of the matched dot tracks to the epipole's lines
    epipole_problem : why the epipole could not be estimated ('' when it was; then
        ``epipole`` is NaN and only identification by the dots' geometry can be used)

    Derived data that depends only on the references (e.g. :meth:`window_sums`) is computed on
    first use and kept with the set, so it is paid once per rig, not per scan.
    """

    image_size: tuple[int, int]
    num_slits: int
    names: tuple[str, ...]
    curves: F64
    vrange: F64
    dots: F32
    epipole: F64
    spacing_px: float
    stripe_width_px: float
    dot_size_px: float
    epipole_residual_px: float
    dot_density: float = 0.02  # dots per px^2 in the slit field of the references
    epipole_problem: str = ""
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def window_sums(self, half_w: int, half_h: int) -> F32:
        """:func:`window_sums` of every dot image, computed once per template size and kept.

        Returns
        -------
        sums : (R, W - 2*half_w, H - 2*half_h, 6) float32, read-only, x-major (the image axes
            swapped, see :func:`bilinear_patch_moments`): the sums along a slit, which runs
            down the image, lie close together in memory
        """
        hw, hh = int(half_w), int(half_h)
        return self._cached(
            ("window_sums", hw, hh),
            lambda: self._stacked_sums(hw, hh),
        )

    def _stacked_sums(self, hw: int, hh: int) -> F32:
        """The x-major window sums of every dot image, written into one array."""
        r, h, w = self.dots.shape
        out = np.empty((r, w - 2 * hw, h - 2 * hh, len(WINDOW_SUMS)), np.float32)
        for d, o in zip(self.dots, out, strict=True):
            window_sums(d, hw, hh, x_major=True, out=o)
        return out

    def padded_dots(self, transposed: bool = False) -> F32:
        """The dot images with ``_ROW_PAD`` zeros after each row, (R, H, W + pad) float32
        C-contiguous, or transposed (R, W, H + pad) (read-only, kept).

        :func:`~multislit.identify.patches.bilinear_ncc` reads patches row by row from it: rows
        a page long (a 1024 px high image transposed) would all fall in the same cache sets,
        and a patch may read whole vector lanes past the end of its row.
        """

        def make() -> F32:
            d = self.dots.transpose(0, 2, 1) if transposed else self.dots
            out = np.zeros(d.shape[:2] + (d.shape[2] + _ROW_PAD,), np.float32)
            out[:, :, : d.shape[2]] = d
            return out

        return self._cached(("padded_dots", bool(transposed)), make)

    def _cached(self, key: tuple, make: Callable[[], NDArray]) -> NDArray:
        """``make()``, computed once per key and kept read-only with the set."""
        cache = self.__dict__.setdefault("_cache", {})  # (also on sets unpickled without one)
        out = cache.get(key)
        if out is None:
            out = make()
            out.flags.writeable = False
            cache[key] = out
        return out

    def epipolar_lines(self, uv: F64) -> F64:
        """Lines (M, 3) through the points (M, 2) px and the dot projector's epipole."""
        h = np.concatenate([uv, np.ones((len(uv), 1))], axis=1)
        ln = np.cross(h, self.epipole[None, :])
        return ln / np.linalg.norm(ln[:, :2], axis=1, keepdims=True)

    def save(self, path: str | Path) -> None:
        """Write the set to ``path`` (a compressed ``.npz``, the suffix added if missing; the dot
        images as float16), whole or not at all."""
        p = Path(path)
        if p.suffix != ".npz":
            p = p.with_name(p.name + ".npz")
        buf = io.BytesIO()
        np.savez_compressed(
            buf,
            image_size=np.array(self.image_size),
            num_slits=self.num_slits,
            names=np.array(self.names),
            curves=self.curves,
            vrange=self.vrange,
            dots=self.dots.astype(np.float16),
            epipole=self.epipole,
            spacing_px=self.spacing_px,
            stripe_width_px=self.stripe_width_px,
            dot_size_px=self.dot_size_px,
            epipole_residual_px=self.epipole_residual_px,
            dot_density=self.dot_density,
            epipole_problem=self.epipole_problem,
            schema="multislit-reference/1",
        )
        write_bytes_atomic(p, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> ReferenceSet:
        """Read a set written by :meth:`save`.

        Raises
        ------
        ReferenceImageError
            if ``path`` is not a file or not a multislit reference file.
        """
        p = Path(path)
        if not p.is_file():
            raise ReferenceImageError(f"prepared reference not found: {p}")
        z = np.load(p, allow_pickle=False)
        if str(z.get("schema", "")) != "multislit-reference/1":
            raise ReferenceImageError(
                f"{p} is not a multislit reference file (schema multislit-reference/1)"
            )
        return cls(
            tuple(int(x) for x in z["image_size"]),
            int(z["num_slits"]),
            tuple(str(x) for x in z["names"]),
            z["curves"],
            z["vrange"],
            z["dots"].astype(np.float32),
            z["epipole"],
            float(z["spacing_px"]),
            float(z["stripe_width_px"]),
            float(z["dot_size_px"]),
            float(z["epipole_residual_px"]),
            float(z["dot_density"]),
            str(z["epipole_problem"]) if "epipole_problem" in z else "",
        )


def _dot_tracks(
    curves: F64, vrange: F64, dots: F32, spacing_px: float, dot_density: float | None = None
) -> F64:
    """The dots' tracks between reference images that :func:`estimate_epipole` meets.

    For each pair of images (a, b), a < b, and each slit, templates beside the slit in image a,
    every ``max(hh, 8)`` rows, are searched for along the slit's curve in image b, at every
    whole-row offset within 2.5 slit spacings (normalised cross-correlation of bilinear
    patches); a clear best match (score > 0.5, 0.15 above the third best, not at the end of the
    search) gives a track, its end refined by a parabola through the neighbouring scores.

    Parameters
    ----------
    curves : (R, N, D+1) float64, u = p(v) per image and slit
    vrange : (R, N, 2) float64, px, rows where each curve was seen
    dots : (R, H, W) float32, the dot images
    spacing_px : float, px, slit spacing (sizes the templates and the search)
    dot_density : float, dots per px^2 in the slit field; a template is made tall enough to
        hold ``_EPIPOLE_DOTS`` dots on average (up to 4 slit spacings): with only a few dots,
        chance matches outnumber true ones. Default None: 0.6 slit spacings tall

    Returns
    -------
    tracks : (T, 4) float64, px, (u, v) in image a and (u, v) in image b per track, in the
        order of the pairs, the slits and the rows
    """
    R, N = curves.shape[:2]
    hw = max(3, int(round(0.35 * spacing_px)))
    hh = max(6, int(round(0.6 * spacing_px)))
    if dot_density is not None and dot_density > 0:
        want = _EPIPOLE_DOTS / dot_density / (2 * hw + 1) / 2
        hh = max(hh, int(round(min(want, 4.0 * spacing_px))))
    search = int(round(2.5 * spacing_px))
    step = max(hh, 8)  # px between templates: whole, so the searches share candidate rows
    offs = np.arange(-search, search + 1, 1.0)
    dots_t = [cv2.transpose(np.ascontiguousarray(d, dtype=np.float32)) for d in dots]
    tracks = []
    for a in range(R):
        for b in range(a + 1, R):
            for k in range(N):
                lo = max(vrange[a, k, 0], vrange[b, k, 0]) + hh + search
                hi = min(vrange[a, k, 1], vrange[b, k, 1]) - hh - search
                if hi <= lo:
                    continue
                vs = np.arange(lo, hi, float(step))
                ua = curve_u(curves[a, k], vs)
                tmpl = normalise_patches(sample_patches(dots[a], np.c_[ua, vs], hw, hh))
                # template i searches rows vs[i] + offs: candidate row i*step + j of the
                # candidates at vs[0] - search + 0, 1, 2, ... (each made once)
                n_rows = (len(vs) - 1) * step + len(offs)
                first = np.minimum(np.arange(n_rows) // step, len(vs) - 1)
                vb = vs[first] + offs[np.minimum(np.arange(n_rows) - first * step, len(offs) - 1)]
                ub = curve_u(curves[b, k], vb)
                cols, m1, m2 = sample_patch_columns(
                    dots[b], np.c_[ub, vb], hw, hh, image_t=dots_t[b]
                )
                score = _search_scores(tmpl, hw, hh, cols, m1, m2, step, len(offs))
                j = np.argmax(score, axis=1)
                best = score[np.arange(len(vs)), j]
                third = np.partition(score, len(offs) - 3, axis=1)[:, -3]
                ok = (best > 0.5) & (best - third > 0.15) & (j > 0) & (j < len(offs) - 1)
                i = np.flatnonzero(ok)
                ji = j[i]
                # sub-step peak by a parabola through the neighbours
                s0, s1, s2 = score[i, ji - 1], score[i, ji], score[i, ji + 1]
                den = s0 - 2 * s1 + s2
                with np.errstate(divide="ignore", invalid="ignore"):
                    d = np.where(den < 0, 0.5 * (s0 - s2) / den, np.float32(0.0))
                v2 = vs[i] + offs[ji] + d
                tracks.append(np.c_[ua[i], vs[i], curve_u(curves[b, k], v2), v2])
    return np.concatenate(tracks) if tracks else np.zeros((0, 4))


def estimate_epipole(
    curves: F64,
    vrange: F64,
    dots: F32,
    spacing_px: float,
    image_height: int,
    dot_density: float | None = None,
) -> tuple[F64, float]:
    """The dot projector's epipole from dots matched between reference images.

    For each pair of reference images and each slit, dot templates beside the slit in the first
    image are found beside the same slit in the second (a 1-D search along its curve); each
    match is a short track whose line passes through the epipole. The epipole is the meeting
    point of the tracks' lines, robust to wrong matches (:func:`_track_epipole`).

    Parameters
    ----------
    curves : (R, N, D+1) float64, u = p(v) per reference image and slit
    vrange : (R, N, 2) float64, px, rows where each curve was seen
    dots : (R, H, W) float32, the dot images
    spacing_px : float, px, slit spacing
    image_height : int, px
    dot_density : float, dots per px^2 in the slit field: the templates are made to hold about
        a dozen dots (see :func:`_dot_tracks`); default None: 0.6 slit spacings tall

    Returns
    -------
    epipole : (3,) homogeneous, unit norm
    rms : float, px, RMS distance of the track lines' far ends to the fitted epipole line
    """
    T = _dot_tracks(curves, vrange, dots, spacing_px, dot_density)
    if len(T) < 4:
        raise ReferenceImageError(
            f"could not match the dots between reference images ({len(T)} matches): the "
            "reference boards must show the same dot pattern at different distances"
        )
    moving = np.linalg.norm(T[:, 2:] - T[:, :2], axis=1) > 0.5  # a measurable motion
    if moving.sum() < 4:
        raise ReferenceImageError(
            "the dots do not move between the reference images: are the boards at different distances?"
        )
    return _track_epipole(T[moving])


def _track_residuals(tracks: F64, e: F64) -> F64:
    """(C, T) float64, px: the distance of each track's end from the line through its start and
    each candidate epipole ``e`` (C, 3) (homogeneous); ``tracks`` (T, 4) as in
    :func:`_track_epipole`. inf where that line is undefined (the start on the epipole)."""
    u, v = tracks[:, 0], tracks[:, 1]
    # the line p1 x e is ((v z - y), (x - u z), (u y - v x)); its value at p2 is -e . (p1 x p2)
    p1 = np.c_[tracks[:, :2], np.ones(len(tracks))]
    p2 = np.c_[tracks[:, 2:], np.ones(len(tracks))]
    num = np.abs(e @ np.cross(p1, p2).T)
    x, y, z = e[:, 0:1], e[:, 1:2], e[:, 2:3]
    den = np.hypot(v[None, :] * z - y, x - u[None, :] * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)


def _track_epipole(tracks: F64) -> tuple[F64, float]:
    """The point that the lines of dot tracks meet at, robust to wrong tracks.

    The start is the least median of squares (Rousseeuw) over the meeting points of pairs of
    tracks (all pairs, or :data:`_EPIPOLE_PAIRS` drawn with a fixed seed when there are more):
    the candidate whose median distance of the tracks' ends to its lines is least. It holds
    while fewer than half of the tracks are wrong, however wrong they are. From the tracks
    within 2.5 of its robust scale (at least ``_EPIPOLE_TOLERANCE``), the least squares point of
    the tracks' lines (homogeneous, so it may lie far outside the image or at infinity), again
    from the tracks within 3 robust sigmas of it, until the set no longer changes.

    Parameters
    ----------
    tracks : (T, 4) float64, px, (u, v) at the start and (u, v) at the end of each track,
        T >= 2, each moving

    Returns
    -------
    epipole : (3,) homogeneous, unit norm
    rms : float, px, RMS distance of the kept tracks' ends to the lines through their starts
        and the epipole
    """
    tracks = np.asarray(tracks, np.float64)
    m = len(tracks)
    p1 = np.c_[tracks[:, :2], np.ones(m)]
    p2 = np.c_[tracks[:, 2:], np.ones(m)]
    lines = np.cross(p1, p2)
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    i, j = np.triu_indices(m, 1)
    if len(i) > _EPIPOLE_PAIRS:
        pick = np.random.default_rng(0).choice(len(i), _EPIPOLE_PAIRS, replace=False)
        i, j = i[pick], j[pick]
    cand = np.cross(lines[i], lines[j])
    norm = np.linalg.norm(cand, axis=1)
    cand = cand[norm > 1e-12] / norm[norm > 1e-12, None]  # not one line twice
    if len(cand) == 0:
        cand = np.linalg.svd(lines, full_matrices=False)[2][-1:]
    med = np.median(_track_residuals(tracks, cand) ** 2, axis=1)
    best = int(np.argmin(med))
    res = _track_residuals(tracks, cand[best : best + 1])[0]
    # the least median of squares' scale (Rousseeuw and Leroy 1987, with its small-sample factor)
    scale = 1.4826 * (1.0 + 5.0 / max(m - 2, 1)) * np.sqrt(med[best])
    keep = res < max(_EPIPOLE_TOLERANCE, 2.5 * scale)
    e = cand[best]
    for _ in range(_EPIPOLE_ROUNDS):
        if keep.sum() < 2:
            break
        e = np.linalg.svd(lines[keep], full_matrices=False)[2][-1]
        res = _track_residuals(tracks, e[None, :])[0]
        new = res < max(_EPIPOLE_TOLERANCE, 3 * 1.4826 * np.median(res[keep]))
        if np.array_equal(new, keep):
            break
        keep = new
    rms = float(np.sqrt(np.mean(res[keep] ** 2))) if keep.any() else float("inf")
    return e / np.linalg.norm(e), rms


def _search_scores(
    tmpl: F32, half_w: int, half_h: int, cols: F32, s1: F64, s2: F64, step: int, n_offs: int
) -> F32:
    """Normalised cross-correlations of templates with the candidates of a 1-D search.

    Template i is compared with candidates ``i*step .. i*step + n_offs - 1``; the result is
    ``normalise_patches`` of the candidates dotted with the templates (to float32 rounding),
    taken from the raw candidates, their sums ``s1`` and sums of squares ``s2`` (a zero-mean
    template's dot product with a patch does not depend on the patch's mean).

    Parameters
    ----------
    tmpl : (M, K) float32, :func:`normalise_patches` of (2*half_h+1, 2*half_w+1) patches
    cols : (C, 2*half_w+1, 2*half_h+1) float32, the candidates transposed
        (:func:`sample_patch_columns`), C = (M-1)*step + n_offs
    s1, s2 : (C,) float64, their sums and sums of squares

    Returns
    -------
    score : (M, n_offs) float32, zero for flat candidates
    """
    m = len(tmpl)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    t = np.ascontiguousarray(tmpl.reshape(m, ph, pw).transpose(0, 2, 1)).reshape(m, -1)
    c = cols.reshape(len(cols), -1)
    dot = np.empty((m, n_offs), np.float32)
    for g0 in range(0, m, _SCORE_BLOCK):
        g1 = min(g0 + _SCORE_BLOCK, m)
        r0, r1 = g0 * step, (g1 - 1) * step + n_offs
        full = t[g0:g1] @ c[r0:r1].T  # (g, r1 - r0): template g0 + q's band starts at q*step
        dot[g0:g1] = np.lib.stride_tricks.as_strided(
            full,
            shape=(g1 - g0, n_offs),
            strides=(full.strides[0] + step * full.strides[1], full.strides[1]),
            writeable=False,
        )
    k = c.shape[1]
    mean = s1 / k
    norm = np.sqrt(np.maximum(s2 - s1 * mean, 0.0))
    row = np.arange(m)[:, None] * step + np.arange(n_offs)[None, :]
    t_sum = tmpl.sum(axis=1, dtype=np.float64)[:, None]
    nr = norm[row]
    with np.errstate(divide="ignore", invalid="ignore"):
        score = (dot - mean[row] * t_sum) / nr
    return np.where(nr > _FLAT, score, 0.0).astype(np.float32)


def _dot_density(dots: F32, curves: F64, vrange: F64) -> float:
    """Dots per px^2 between the first and the last slit of a reference image."""
    h, w = dots.shape
    d = cv2.GaussianBlur(dots, (0, 0), 0.8)
    local_max = d == cv2.dilate(d, np.ones((3, 3), np.uint8))
    thr = 4.0 * 1.4826 * float(np.median(np.abs(d[d > 0]))) if np.any(d > 0) else 0.0
    peaks = local_max & (d > max(thr, 1e-6))
    vv = np.arange(h, dtype=float)
    u0 = curve_u(curves[0], vv)
    u1 = curve_u(curves[-1], vv)
    uu = np.arange(w, dtype=float)[None, :]
    field = (uu >= u0[:, None]) & (uu <= u1[:, None])
    rows_ok = (vv >= vrange[:, 0].max()) & (vv <= vrange[:, 1].min())
    field &= rows_ok[:, None]
    area = float(field.sum())
    return float((peaks & field).sum()) / area if area > 0 else 0.0


def prepare_reference(
    images: Sequence[NDArray],
    num_slits: int,
    names: Sequence[str] | None = None,
    stripe_width_px: float | None = None,
    dot_size_px: float | None = None,
) -> ReferenceSet:
    """Prepare the reference set from >= 2 images of a flat board at different distances.

    Parameters
    ----------
    images : sequence of (H, W) uint8/uint16, the reference images (lasers on)
    num_slits : int, N; every image must show all N slits
    names : names of the images for messages (default ref0, ref1, ...)
    stripe_width_px, dot_size_px : optional, else measured from the images

    Returns
    -------
    ReferenceSet, reused for every scan.
    """
    if isinstance(images, str | bytes | Path) or not hasattr(images, "__len__"):
        raise ReferenceImageError(
            f"images must be a sequence of (H, W) arrays (the reference images), got "
            f"{type(images).__name__}"
        )
    if isinstance(images, np.ndarray) and images.ndim < 3:
        raise ReferenceImageError(
            "images must be a sequence of (H, W) arrays (the reference images), got an "
            f"array of shape {images.shape}"
        )
    if len(images) < 2:
        raise ReferenceImageError(
            f"need >= 2 reference images at different distances, got {len(images)}"
        )
    if isinstance(num_slits, bool) or not isinstance(num_slits, int | np.integer) or num_slits < 1:
        raise ReferenceImageError(f"num_slits must be a positive integer, got {num_slits!r}")
    names = tuple(names) if names is not None else tuple(f"ref{i}" for i in range(len(images)))
    if len(names) != len(images):
        raise ReferenceImageError(f"names has {len(names)} names for {len(images)} images")
    try:
        for im, nm in zip(images, names, strict=True):
            as_image(im, name=f"reference image {nm!r}")
    except SlitExtractionError as exc:
        raise ReferenceImageError(str(exc)) from None
    shapes = {np.shape(im) for im in images}
    if len(shapes) != 1:
        raise ReferenceImageError(f"reference images differ in size: {sorted(shapes)}")
    h, w = np.shape(images[0])[:2]
    curves, vranges, dots, widths, dsz, spacing = [], [], [], [], [], []
    for im, nm in zip(images, names, strict=True):
        ex = extract_slits(
            im,
            stripe_width_px=stripe_width_px,
            dot_size_px=dot_size_px,
            leaning=False,
            background=TEMPLATE_BACKGROUND,
        )
        c, vr = _fit_curves(ex, num_slits, nm, h)
        curves.append(c)
        vranges.append(vr)
        dots.append(ex.dots.astype(np.float32))
        widths.append(ex.stripe_width_px)
        dsz.append(ex.dot_size_px)
        mid = curve_u(c, np.full(num_slits, h / 2.0))
        if num_slits > 1:
            spacing.append(float(np.median(np.diff(mid))))
    curves_a = np.array(curves)
    vr_a = np.array(vranges)
    dots_a = np.array(dots)
    sp = float(np.median(spacing)) if spacing else float(w) / 4
    density = float(
        np.median([_dot_density(d, c, vr) for d, c, vr in zip(dots_a, curves_a, vr_a, strict=True)])
    )
    try:
        epi, rms = estimate_epipole(curves_a, vr_a, dots_a, sp, h, density)
        problem = ""
    except ReferenceImageError as exc:  # only the template method needs it
        epi, rms, problem = np.full(3, np.nan), float("nan"), str(exc)
    return ReferenceSet(
        (int(w), int(h)),
        int(num_slits),
        names,
        curves_a,
        vr_a,
        dots_a,
        epi,
        sp,
        float(np.median(widths)),
        float(np.median(dsz)),
        rms,
        density,
        problem,
    )


def capture_reference(capture: Capture) -> ReferenceSet:
    """:func:`prepare_reference` of a capture folder's reference images (named by file stem)."""
    imgs = [capture.image(p) for p in capture.references]
    return prepare_reference(imgs, capture.num_slits, [p.stem for p in capture.references])


def reference_curves(image: NDArray, num_slits: int, name: str = "ref") -> tuple[F64, F64, float]:
    """The slit curves of one reference image, numbered 0..N-1 left to right, without the
    other images or the epipole (as :func:`prepare_reference` fits them).

    Parameters
    ----------
    image : (H, W) a reference image (a flat board, lasers on)
    num_slits : int, N
    name : the image's name for messages

    Returns
    -------
    curves : (N, CURVE_DEGREE + 1) float64, u = p(v) per slit (:func:`curve_u`)
    vrange : (N, 2) float64, px, the rows each curve was fitted over
    spacing_px : float, px, the median distance between neighbouring curves mid-height

    Raises
    ------
    ReferenceImageError
        Not every slit crosses the board, or the curves cross.
    """
    try:
        as_image(image, name=f"reference image {name!r}")
    except SlitExtractionError as exc:
        raise ReferenceImageError(str(exc)) from None
    h = np.shape(image)[0]
    ex = extract_slits(image, leaning=False, background=TEMPLATE_BACKGROUND)
    curves, vrange = _fit_curves(ex, num_slits, name, h)
    mid = curve_u(curves, np.full(num_slits, h / 2.0))
    spacing = float(np.median(np.diff(mid))) if num_slits > 1 else float(np.shape(image)[1]) / 4
    return curves, vrange, spacing

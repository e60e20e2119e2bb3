"""Slit address identification (paper section 4.2, Fig. 12-13).

For sample points on each slit segment of a scan, a template of the dot image around the point
is compared (normalised cross-correlation) with the reference dot images only where the point's
epipolar line meets each slit's reference curve: N candidates per reference image instead of a
search over the image. The samples of a segment vote; the margin between the best and the
second-best slit gives a confidence; the left-to-right order of neighbouring segments is checked;
a segment that cannot be identified with confidence is dropped and counted, never guessed.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import IdentificationError
from multislit.identify.order import OrderParams, _apply, _run_offsets, _runs
from multislit.identify.reference import (
    ReferenceSet,
    bilinear_patch_moments,
    curve_du,
    curve_u,
    intersect_line_curves,
    normalise_patches,
    sample_patches,
    sample_sheared_patches,
)
from multislit.stripes import SlitExtraction, extract_slits

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class IdentifyParams:
    """Tuning of the identification; sizes in units of the reference slit spacing unless px.

    template_half_width : template half width across the slit (x spacing)
    template_dots : the template's height is chosen to hold about this many dots (from the
        dot density measured in the references), between 0.5 and 4 slit spacings
    coarse_every, keep_hypotheses : coarse to fine: every slit is scored on every
        ``coarse_every``-th sample of a segment, then only the segment's ``keep_hypotheses`` best
        slits on all its samples (1, the default = score every slit everywhere). Measured with
        benchmarks/bench_identify.py before the scoring was vectorised: coarse_every=3, keep 3
        halved the time at 25 slits (~2.5x at 49) but cost coverage and correctness on curved
        and occluded scenes; with the present scoring it saves little (none at 25 slits, ~1.2x
        at 49, half-size scenes) and gives the same slits as before
    order_fill : give segments the dots left unidentified the slit number their place in the
        row implies, when the dot-identified stripes around them agree (confidence <= 0.6),
        or when the dots' own weak vote agrees (see :func:`_fill_by_order` for the rules)
    min_confirm, confirm_share : a segment dropped for low confidence takes the dots' best
        slit if their confidence reaches ``min_confirm`` and >= ``confirm_share`` of its
        order labels (also beyond the run's last dot-identified stripe) agree. Measured with
        benchmarks/bench_identify.py (half size, seed 11): 49-slit free-form coverage 79.1 ->
        81.9 %, no scene's correct share lower; min_confirm 0 instead of 0.05 took a
        25-slit holes segment with confidence 0.00 for the wrong slit (0.19 % of points)
    extrapolate_top : an unidentified segment takes its run's order label beyond the run's
        last dot-identified stripe only if that slit is among the dots' ``extrapolate_top``
        best for it with a mean score >= ``min_score`` (0: never). Measured as above: 49-slit
        free-form coverage 83.9 -> 86.9 %, spheres 88.4 -> 88.7 %, every correct share within
        0.03 points; without the dots' check the 49-slit spheres' correct share fell from
        99.55 to 99.33 % (extrapolation across an occlusion, labels 11-13 slits off)
    end_order : rows left out at a segment's ends (``trim_rows``, ``junction_template``) or
        far from its samples are labelled after all where their place in the row gives the
        segment's slit (the order label between agreeing dot-identified stripes). Measured as
        above: coverage +0.4..+3.4 points at 25 and 49 slits (49-slit spheres 85.8 -> 88.4 %),
        confidently wrong points +0.01 points at most
    neighbour_share : a segment the dots were too unsure of (dropped for low confidence) takes
        their best slit where its neighbours in the rows confirm it on >= this share of its
        points (:func:`_confirm_by_neighbours`; > 1: never). Measured as above: 49-slit
        spheres coverage 88.0 -> 90.0 %, free-form 86.9 -> 87.3 %, correct shares unchanged
        (within 0.01 points); 0.8 instead of 0.5 gained 0.2 points less
    order_check : a point whose run label within the span of the run's dot-identified stripes
        (its place in its row) is another slit than its own label is left out. Measured as
        above, 49 slits: free-form correct 99.51 -> 99.87 %, confidently wrong 0.24 -> 0.05 %,
        coverage unchanged; spheres 99.56 -> 99.71 %, 0.09 -> 0.06 %, coverage 90.9 -> 90.0 %;
        at 25 slits coverage -0.5 points at most. Using the run label also beyond the span
        removed no more wrong points and cost the 49-slit spheres 2 points of coverage; only
        the order fill's labels, or only labels with confidence < 0.9, removed fewer wrong ones
    min_score : a segment's best mean NCC must reach this
    min_confidence : segments below this confidence are dropped
    border_cut : samples are taken only where the template is cut by the image's top or bottom
        by at most this fraction of its half height (1: never cut; :func:`_band_samples`).
        Measured on the full-size 49-slit holes scene (seeds 5 / 7 / 13): 0.5 instead of 1 let
        short segments at the image's bottom edge, where the board ends in front of the far
        wall, take wrong slits from templates lying mostly on the board above them: confidently
        wrong 0.22 / 0.10 / 0.02 % of points (1: 0.06 / 0.05 / 0.02 %), coverage unchanged at
        full size (25 and 49 slits); at half size -0.7 points at most (49-slit steps)
    min_samples : segments with fewer sample points are dropped (too short to vote). 3, not
        2: on the half-size free-form scene a 6-row piece with 2 samples took slit 0 for 17
        with confidence 0.76; with 3 (benchmarks/bench_identify.py) no scene lost coverage
    chunk : most sample points scored in one block (with a ~4 MB bound on the reference
        windows gathered at once; bounds memory, not results)
    """

    template_half_width: float = 0.40
    template_dots: float = 12.0
    sample_step: float = 0.30
    search_px: int = 0
    depth_margin: float = math.inf
    references: str = "nearest"
    coarse_every: int = 1
    keep_hypotheses: int = 3
    trim_rows: int = 2
    junction_template: float = 0.4
    order_fill: bool = True
    follow_stripe: str = "line"
    min_score: float = 0.15
    min_confidence: float = 0.30
    min_samples: int = 3
    border_cut: float = 1.0
    min_confirm: float = 0.05
    confirm_share: float = 0.8
    extrapolate_top: int = 5
    neighbour_share: float = 0.5
    end_order: bool = True
    order_check: bool = True
    chunk: int = 400

    def junction_rows(self, half_height_px: int) -> int:
        """Rows left out next to a junction of two segments, for a template half height (px)."""
        return max(self.trim_rows, int(math.ceil(self.junction_template * half_height_px)))


@dataclass(frozen=True, eq=False)
class Identification:
    """Result of identifying the slits of one image. Arrays are per stripe-centre point.

    u, v : (K,) float64, px, stripe centres
    slit : (K,) int64, slit number 0..N-1, -1 where not identified
    confidence : (K,) float64, 0..1 (0 where not identified)
    segment : (K,) int64, segment id from the extraction (-1 for unlinked points)
    peak, width : (K,) float64, stripe peak height (DN above background) and width (px)
    """

    u: F64
    v: F64
    slit: I64
    confidence: F64
    segment: I64
    peak: F64
    width: F64
    num_segments: int
    num_identified: int
    dropped: dict[str, int] = field(default_factory=dict)
    message: str = ""
    extraction: SlitExtraction | None = None

    @property
    def identified(self) -> NDArray[np.bool_]:
        return self.slit >= 0

    @property
    def num_dropped(self) -> int:
        return int(sum(self.dropped.values()))


def _segment_runs(seg: I64, v: F64) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The linked points ordered by (segment, v), and for each of them the positions (in that
    order) of its segment's first and last point: ``order, first, last``, each (K',)."""
    idx = np.flatnonzero(seg >= 0)
    order = idx[np.lexsort((v[idx], seg[idx]))]
    pos = np.arange(len(order))
    if order.size == 0:
        return order, pos, pos
    s = seg[order]
    starts = np.r_[True, s[1:] != s[:-1]]
    ends = np.r_[s[1:] != s[:-1], True]
    first = np.maximum.accumulate(np.where(starts, pos, 0))
    # the last point of each run, propagated backwards
    last = np.minimum.accumulate(np.where(ends, pos, len(order))[::-1])[::-1]
    return order, first, last


def _sample_points(seg: I64, v: F64, step_px: float) -> NDArray[np.intp]:
    """Indices of points spaced about ``step_px`` rows apart along each segment."""
    order, start_v, _ = _segment_runs(seg, v)
    if order.size == 0:
        return order
    s = seg[order]
    rel = v[order] - v[order][start_v]
    bucket = np.floor(rel / step_px + 0.5).astype(np.int64)
    # keep the first point of each (segment, bucket)
    key = s.astype(np.int64) * 1_000_000 + bucket
    keep = np.r_[True, key[1:] != key[:-1]]
    return order[keep]


def _band_samples(seg: I64, v: F64, step_px: float, lo: float, hi: float) -> NDArray[np.intp]:
    """Sample points (:func:`_sample_points`) only in the rows ``lo <= v <= hi``.

    A template centred outside the band would be cut by the image's top or bottom: partly
    empty rows, which say little. Each segment's sampling starts at its first row in the band,
    and a segment that runs on below the band also gets its last row in the band, so the rows
    between the band and the image edge lie within a template's half height of a sample.
    """
    inside = (v >= lo) & (v <= hi)
    seg_in = np.where(inside, seg, -1)
    si = _sample_points(seg_in, v, step_px)
    below = np.unique(seg[(seg >= 0) & (v > hi)])
    if below.size == 0 or si.size == 0:
        return si
    # the last row in the band of each segment that runs on below it
    m = np.flatnonzero(inside & np.isin(seg, below))
    o = m[np.lexsort((v[m], seg[m]))]
    ends = o[np.r_[seg[o][1:] != seg[o][:-1], True]] if o.size else o
    si = np.unique(np.r_[si, ends])
    return si[np.lexsort((v[si], seg[si]))]  # by segment, then row, as _sample_points


def template_size(ref: ReferenceSet, p: IdentifyParams) -> tuple[int, int]:
    """Template half width and half height (px): as wide as a dot band, tall enough for dots."""
    hw = max(3, int(round(p.template_half_width * ref.spacing_px)))
    want = p.template_dots / max(ref.dot_density, 1e-6) / (2 * hw + 1)
    hh = int(round(np.clip(want / 2, 0.5 * ref.spacing_px, 4.0 * ref.spacing_px)))
    return hw, max(4, hh)


def _template_row_shift(
    u: F64, v: F64, seg: I64, si: NDArray[np.intp], ref: ReferenceSet, hh: int, mode: str
) -> F64 | None:
    """(M, 2*hh+1) px: sideways shift of each template row so that the template follows its
    stripe (see ``IdentifyParams.follow_stripe``); None for ``mode`` "off".

    A line u = a + s dv is fitted (least squares, all samples at once) to the centres of the
    sample's segment within +-hh rows; a sample with fewer than 3 such centres, or spanning
    fewer than 4 rows, keeps an upright template. The reference curves' own slant at the sample
    (the curve nearest it in the middle reference) is kept in the template.
    """
    if mode == "off" or len(si) == 0:
        return None
    dy = np.arange(-hh, hh + 1, dtype=np.float64)
    # the segment's centre in every template row (absent where the segment has no point there)
    order = _segment_runs(seg, v)[0]
    span = float(np.ceil(v.max()) + 2 * hh + 2)
    keys = seg[order] * span + np.rint(v[order])
    want = (seg[si] * span + np.rint(v[si]))[:, None] + dy[None, :]
    pos = np.clip(np.searchsorted(keys, want), 0, len(keys) - 1)
    found = keys[pos] == want
    w = found.astype(np.float64)
    uu = np.where(found, u[order[pos]] - u[si][:, None], 0.0)
    n = w.sum(axis=1)
    sy, syy = w @ dy, w @ (dy * dy)
    su, suy = uu.sum(axis=1), uu @ dy
    det = n * syy - sy * sy
    lo = np.where(found, dy, np.inf).min(axis=1)
    hi = np.where(found, dy, -np.inf).max(axis=1)
    use = (n >= 3) & (hi - lo >= min(4.0, hh)) & (det > 0)
    slope = np.where(use, (n * suy - sy * su) / np.where(use, det, 1.0), 0.0)
    # the reference curves' slant around the point stays in the template
    r = ref.curves.shape[0] // 2
    U = curve_u(ref.curves[r][None, :, :], v[si][:, None])  # (M, N)
    k = np.argmin(np.abs(U - u[si][:, None]), axis=1)
    s_ref = np.where(use, curve_du(ref.curves[r, k], v[si]), 0.0)
    return (slope - s_ref)[:, None] * dy[None, :]


def _near_segment_ends(
    u: F64, v: F64, seg: I64, label: I64, trim: int, junction: int
) -> NDArray[np.bool_]:
    """(K,) bool: points within ``trim`` rows of their segment's first or last row, or within
    ``junction`` rows of an end that meets the end of a segment of another slit (within 3 rows
    and 3 px; ``label`` (S,) is each segment's slit, -1 if none).

    Where a stripe runs into another slit's stripe on another surface (an occlusion edge), the
    split between the two segments is placed from sampled evidence (brightness medians, sample
    winners) and can be off by a few samples: the rows next to such a junction may belong to
    the other stripe, so more of them are left out than at a free end.
    """
    out = np.zeros(len(seg), bool)
    o, fi, li = _segment_runs(seg, v)
    if o.size == 0:
        return out
    sg = seg[o]
    pos = np.arange(len(o))
    ends = np.r_[pos[fi == pos], pos[li == pos]]  # positions in o of first and last points
    pts = np.c_[u[o[ends]], v[o[ends]]]
    joined = np.zeros(len(o), bool)  # per position in o: is this end a junction
    if len(ends) > 1:
        from scipy.spatial import cKDTree

        pairs = cKDTree(pts).query_pairs(3.0 * math.sqrt(2.0), output_type="ndarray")
        if len(pairs):
            a, b = ends[pairs[:, 0]], ends[pairs[:, 1]]
            la, lb = label[sg[a]], label[sg[b]]
            close = (la >= 0) & (lb >= 0) & (la != lb)
            close &= (np.abs(pts[pairs[:, 0]] - pts[pairs[:, 1]]) <= 3.0).all(1)
            joined[a[close]] = True
            joined[b[close]] = True
    rows_first = np.where(joined[fi], junction, trim)
    rows_last = np.where(joined[li], junction, trim)
    vv = v[o]
    out[o] = (vv - vv[fi] < rows_first) | (vv[li] - vv < rows_last)
    return out


def _in_volume(ref: ReferenceSet, uv: F64, margin: float) -> NDArray[np.bool_]:
    """(M, N) bool: could slit n light sample m at a depth inside the measuring volume?

    In the sample's row, slit n's reference curves span [lo, hi] over the boards' depths; the
    sample must lie within [lo - margin (hi - lo), hi + margin (hi - lo)].
    """
    U = curve_u(ref.curves[:, None, :, :], uv[None, :, 1:2])  # (R, M, N)
    lo, hi = U.min(axis=0), U.max(axis=0)
    pad = margin * (hi - lo)
    u = uv[:, 0:1]
    return (u >= lo - pad) & (u <= hi + pad)


def _candidates(
    ref: ReferenceSet, uv: F64, lines: F64, hw: int, hh: int, depth_margin: float = np.inf
) -> tuple[F64, F64]:
    """Where each sample's epipolar line meets each slit's curve in each reference image.

    Parameters
    ----------
    uv : (M, 2) float64, px, sample points
    lines : (M, 3) float64, their epipolar lines (unit normal)
    hw, hh : template half sizes, px
    depth_margin : see :class:`IdentifyParams` (inf: no depth limit)

    Returns
    -------
    uu, vv : (R, M, N) float64, px, the intersections; NaN where there is none, where it lies
        beyond the rows the curve was seen in (+- ``hh``), where the template would leave
        the image, or where the slit would put the sample outside the measuring volume
    """
    w, h = ref.image_size
    R, N = ref.curves.shape[:2]
    M = len(uv)
    vv = np.empty((R, M, N))
    uu = np.empty((R, M, N))
    step = max(1, 2**16 // (R * N))  # samples per block: the Newton steps' arrays stay in cache
    for a in range(0, M, step):
        sl = slice(a, a + step)
        vv[:, sl] = intersect_line_curves(
            lines[None, sl, None, :],
            ref.curves[:, None, :, :],
            np.broadcast_to(uv[None, sl, 1:2], (R, len(uv[sl]), N)),
        )
        uu[:, sl] = curve_u(ref.curves[:, None, :, :], vv[:, sl])
    lo = ref.vrange[:, None, :, 0]
    hi = ref.vrange[:, None, :, 1]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(vv) & (vv >= lo - hh) & (vv <= hi + hh)
        ok &= (uu >= hw) & (uu <= w - 1 - hw) & (vv >= hh) & (vv <= h - 1 - hh)
    if np.isfinite(depth_margin):
        ok &= _in_volume(ref, uv, depth_margin)[None]
    return np.where(ok, uu, np.nan), np.where(ok, vv, np.nan)


#: Bytes of reference windows gathered at once when scoring (bounds memory, stays in cache).
_GATHER_BYTES = 4 << 20


def _ncc_at(
    ref: ReferenceSet,
    sums: NDArray[np.float32],
    tmpl: NDArray[np.float32],
    r: NDArray[np.intp],
    uu: F64,
    vv: F64,
    hw: int,
    hh: int,
    max_block: int = 400,
) -> F64:
    """NCC of each sample's template with bilinear reference patches at given centres.

    Equal to ``normalise_patches(sample_patches(ref.dots[r], (uu, vv), hw, hh))`` dotted with
    the template, without sampling the patches: the bilinear patch blends the four integer
    windows at the corners of its pixel cell, so its dot product with the template is the same
    blend of the template's dot products with those windows (one matrix product over one
    gathered window a pixel larger), and its mean and norm follow from the reference's window
    sums (:func:`~multislit.reference.bilinear_patch_moments`).

    Parameters
    ----------
    sums : (R, W', H', 6) float32, ``ref.window_sums(hw, hh)`` (x-major)
    tmpl : (m, K) float32, normalised templates (:func:`~multislit.reference.normalise_patches`)
    r : (m, C) intp, reference image of each candidate
    uu, vv : (m, C) float64, px, patch centres, with the patch inside the image
    hw, hh : patch half sizes, px
    max_block : most samples whose windows are gathered at once

    Returns
    -------
    ncc : (m, C) float64, 0 for a flat (all equal) reference patch
    """
    m, C = r.shape
    ph, pw = 2 * hh + 1, 2 * hw + 1
    K = ph * pw
    if m == 0 or C == 0:
        return np.zeros((m, C))
    x, y = uu - hw, vv - hh
    ws, hs = sums.shape[1:3]  # x-major
    x0 = np.minimum(np.floor(x), ws - 2).astype(np.intp)
    y0 = np.minimum(np.floor(y), hs - 2).astype(np.intp)
    fx, fy = x - x0, y - y0
    # the template at the four corners of the cell, in a window one pixel larger; a tall patch
    # is gathered from the transposed images (fewer, longer rows to copy)
    tall = ph > pw
    t2 = tmpl.reshape(m, ph, pw)
    if tall:
        t2 = t2.transpose(0, 2, 1)
        src, idx = ref.dots_transposed(), (x0, y0)
    else:
        src, idx = ref.dots, (y0, x0)
    n0, n1 = t2.shape[1:]
    # corners in the order 00, 10, 01, 11 (x offset, y offset) -> offsets in the window layout
    corners = [(ox, oy) if not tall else (oy, ox) for ox, oy in ((0, 0), (1, 0), (0, 1), (1, 1))]
    win = np.lib.stride_tricks.sliding_window_view(src, (n0 + 1, n1 + 1), axis=(1, 2))
    dots4 = np.empty((m, C, 4), np.float32)
    step = max(1, min(max_block, _GATHER_BYTES // (C * (n0 + 1) * (n1 + 1) * 4)))
    t4 = np.zeros((min(step, m), 4, n0 + 1, n1 + 1), np.float32)
    for a in range(0, m, step):
        sl = slice(a, a + step)
        s_ = len(t2[sl])
        for j, (d1, d0) in enumerate(corners):
            t4[:s_, j, d0 : d0 + n0, d1 : d1 + n1] = t2[sl]  # (its other cells stay 0)
        # slit by slit (consecutive samples' windows overlap in memory): (C, s, n0+1, n1+1)
        g = win[r[sl].T, idx[0][sl].T, idx[1][sl].T]
        np.matmul(
            g.reshape(C, s_, -1).transpose(1, 0, 2),
            t4[:s_].reshape(s_, 4, -1).transpose(0, 2, 1),
            out=dots4[sl],
        )
    num = (1 - fy) * ((1 - fx) * dots4[..., 0] + fx * dots4[..., 1]) + fy * (
        (1 - fx) * dots4[..., 2] + fx * dots4[..., 3]
    )
    # slit by slit: consecutive samples' patches lie close together in the x-major sums
    s1, s2 = bilinear_patch_moments(sums, x.T.copy(), y.T.copy(), r.T.copy(), x_major=True)
    s1, s2 = s1.T, s2.T
    var = s2 - s1 * s1 / K
    flat = var <= 1e-6 * np.maximum(s2, 1e-12)
    return np.where(flat, 0.0, num / np.sqrt(np.where(flat, 1.0, var)))


def _score_candidates(
    ref: ReferenceSet,
    scan_dots: NDArray,
    pu: F64,
    pv: F64,
    p: IdentifyParams,
    allowed: NDArray[np.bool_] | None = None,
    row_shift: F64 | None = None,
) -> F64:
    """NCC of each sample's template at each slit's epipolar intersection: (M, N), NaN = none.

    ``allowed`` (M, N) bool limits the hypotheses scored per sample (others stay NaN);
    ``row_shift`` (M, 2*hh+1) px shifts the scan template's rows (:func:`_template_row_shift`).
    """
    R, N = ref.curves.shape[:2]
    w, h = ref.image_size
    hw, hh = template_size(ref, p)
    M = len(pu)
    scores = np.full((M, N), np.nan)
    if M == 0:
        return scores
    sums = ref.window_sums(hw, hh)
    offs = np.arange(-p.search_px, p.search_px + 1, dtype=float)
    uv = np.c_[pu, pv]
    lines = ref.epipolar_lines(uv)  # (M, 3), unit normal (a, b)
    direction = np.c_[lines[:, 1], -lines[:, 0]]  # along the line
    uu_all, vv_all = _candidates(ref, uv, lines, hw, hh, p.depth_margin)  # (R, M, N)
    valid_any = np.isfinite(vv_all).any(axis=0)
    if allowed is not None:
        valid_any &= allowed
    if p.references == "nearest":
        # compare each hypothesis in the reference where its candidate lies nearest the
        # scan point: the board depth closest to the surface's, the least deformed dots
        disp = np.hypot(uu_all - uv[None, :, 0:1], vv_all - uv[None, :, 1:2])
        r_sel = np.argmin(np.where(np.isfinite(disp), disp, np.inf), axis=0)[:, :, None]
    else:
        r_sel = np.broadcast_to(np.arange(R)[None, None, :], (M, N, R))
    ii = np.arange(M)[:, None, None]
    kk = np.arange(N)[None, :, None]
    cu = uu_all[r_sel, ii, kk]  # (M, N, R') candidate centres
    cv = vv_all[r_sel, ii, kk]
    ok = np.isfinite(cv) & valid_any[:, :, None]
    # search along the epipolar line: (M, N, R', O)
    cu = cu[..., None] + offs * direction[:, None, None, 0:1]
    cv = cv[..., None] + offs * direction[:, None, None, 1:2]
    rr = np.broadcast_to(r_sel[..., None], cu.shape)
    ok = np.broadcast_to(ok[..., None], cu.shape)
    # a patch shifted off the image is zero-padded: sample it directly (rare)
    with np.errstate(invalid="ignore"):
        inside = (cu >= hw) & (cu <= w - 1 - hw) & (cv >= hh) & (cv <= h - 1 - hh)
    direct = ok & ~inside
    fast = ok & inside
    shape = cu.shape
    if row_shift is None:
        patches = sample_patches(scan_dots, uv, hw, hh)
    else:
        patches = sample_sheared_patches(scan_dots, uv, hw, hh, row_shift)
    tmpl = normalise_patches(patches)  # (M, K)
    rr_f = np.where(fast, rr, 0).reshape(M, -1)
    cu_f = np.where(fast, cu, hw).reshape(M, -1)
    cv_f = np.where(fast, cv, hh).reshape(M, -1)
    sc = np.full(shape, -np.inf)
    sc_flat = sc.reshape(M, -1)
    fast_flat = fast.reshape(M, -1)
    n_max = int(fast_flat.sum(axis=1).max())
    if n_max == fast_flat.shape[1]:
        sc_flat[:] = _ncc_at(ref, sums, tmpl, rr_f, cu_f, cv_f, hw, hh, p.chunk)
    elif n_max > 0:
        # few hypotheses per sample (coarse to fine, missing candidates): score only those,
        # packed to the front of each sample's row
        cols = np.argsort(~fast_flat, axis=1, kind="stable")[:, :n_max]
        packed = [np.take_along_axis(a, cols, axis=1) for a in (rr_f, cu_f, cv_f)]
        scored = _ncc_at(ref, sums, tmpl, *packed, hw, hh, p.chunk)
        np.put_along_axis(sc_flat, cols, scored, axis=1)
    sc_flat[~fast_flat] = -np.inf
    if direct.any():
        di = np.nonzero(direct)
        for r in np.unique(rr[di]):
            sel = tuple(q[rr[di] == r] for q in di)
            pat = normalise_patches(sample_patches(ref.dots[r], np.c_[cu[sel], cv[sel]], hw, hh))
            sc[sel] = np.einsum("ij,ij->i", pat, tmpl[sel[0]])
    best = sc.reshape(M, N, -1).max(axis=2)
    blk = np.where(valid_any & np.isfinite(best), best, np.nan)
    # a flat template (no dots around the point) says nothing
    flat = ~np.any(tmpl != 0, axis=1)
    blk[flat] = np.nan
    scores[:] = blk
    return scores


def split_at_brightness_steps(
    seg: I64, v: F64, peak: F64, ratio: float = 1.6, window: int = 6
) -> I64:
    """Split segments where the stripe's brightness steps abruptly along v.

    Where a stripe on one surface runs into another slit's stripe on a surface at another depth
    (or albedo), linking can join them; the peak brightness then changes by a large factor from
    one side of the junction to the other, while along one surface it changes slowly. The split
    is placed where the median brightness of the ``window`` rows before and after differ most,
    if they differ by more than ``ratio``.
    """
    from numpy.lib.stride_tricks import sliding_window_view

    seg = seg.copy()
    next_id = int(seg.max()) + 1 if seg.size else 0
    idx = np.flatnonzero(seg >= 0)
    if idx.size < 2 * window + 2:
        return seg
    # all segments at once: points by (segment, v); rolling medians of log brightness
    order = idx[np.lexsort((v[idx], seg[idx]))]
    s_o = seg[order]
    bounds = np.flatnonzero(np.r_[True, s_o[1:] != s_o[:-1], True])
    start = np.repeat(bounds[:-1], np.diff(bounds))  # first point of each point's segment
    end = np.repeat(bounds[1:], np.diff(bounds))
    logp = np.log(np.maximum(peak[order], 1e-3))
    med = np.median(sliding_window_view(logp, window), axis=1)  # med[i] = points i..i+w-1
    g = np.arange(len(med) - window)  # before: g..g+w-1, after: g+w..g+2w-1
    inside = (g + 2 * window <= end[g]) & (end[g] - start[g] >= 2 * window + 2)
    step_all = np.where(inside, np.abs(med[g + window] - med[g]), 0.0)
    candidates = np.unique(s_o[g[step_all > np.log(ratio)]])
    for sid in candidates:
        a = int(np.searchsorted(s_o, sid, side="left"))
        b = int(np.searchsorted(s_o, sid, side="right"))
        pts = order[a:b]
        step = step_all[a : b - 2 * window + 1].copy()  # same as this segment's own medians
        cut_at = []
        while step.size and step.max() > np.log(ratio):
            j = int(np.argmax(step))
            cut_at.append(j + window)  # first point of the new piece
            lo, hi = max(0, j - window), min(len(step), j + window + 1)
            step[lo:hi] = 0
        for c in sorted(cut_at):
            seg[pts[c:]] = np.where(seg[pts[c:]] == seg[pts[c]], next_id, seg[pts[c:]])
            next_id += 1
    return seg


def _split_segments(seg: I64, v: F64, si: NDArray[np.intp], scores: F64, p: IdentifyParams) -> I64:
    """Split segments whose samples clearly change winner along v (two slits linked by chance).

    A stripe on a near surface can run into another slit's stripe on a far surface at the same
    image column; linking then joins them. Along such a segment the per-sample best slit changes
    from one run of samples to another: each run of >= 2 confident samples becomes a segment.
    """
    seg = seg.copy()
    if len(si) == 0:
        return seg
    S = np.where(np.isfinite(scores), scores, -1.0)
    top2 = np.sort(S, axis=1)[:, -2:] if S.shape[1] > 1 else np.c_[np.full(len(S), -1.0), S]
    win = np.argmax(S, axis=1)
    strong = (top2[:, 1] >= p.min_score) & (top2[:, 1] - top2[:, 0] >= 0.1)
    next_id = int(seg.max()) + 1
    ss = seg[si]
    # only segments with >= 4 strong samples whose winner changes can split
    st = np.flatnonzero(strong)
    st = st[np.lexsort((v[si[st]], ss[st]))]
    same = ss[st][1:] == ss[st][:-1]
    changing = np.unique(ss[st][1:][same & (win[st][1:] != win[st][:-1])])
    for sid in changing:
        rows = np.flatnonzero((ss == sid) & strong)
        if rows.size < 4:
            continue
        rows = rows[np.argsort(v[si[rows]])]
        w_ = win[rows]
        change = np.flatnonzero(w_[1:] != w_[:-1])
        if change.size == 0:
            continue
        # runs of equal winners; only runs of >= 2 samples count, single outliers are noise
        starts = np.r_[0, change + 1]
        ends = np.r_[change + 1, len(w_)]
        runs = [(a, b) for a, b in zip(starts, ends, strict=True) if b - a >= 2]
        if len(runs) < 2:
            continue
        # merge neighbouring runs with the same winner
        merged = [runs[0]]
        for a, b in runs[1:]:
            if w_[a] == w_[merged[-1][0]]:
                merged[-1] = (merged[-1][0], b)
            else:
                merged.append((a, b))
        if len(merged) < 2:
            continue
        pts = np.flatnonzero(seg == sid)
        for (_, b_prev), (a_next, _) in zip(merged[:-1], merged[1:], strict=True):
            cut = 0.5 * (v[si[rows[b_prev - 1]]] + v[si[rows[a_next]]])
            seg[pts[v[pts] > cut]] = next_id
            next_id += 1
    return seg


def _segment_votes(
    seg_of_sample: I64, scores: F64, p: IdentifyParams, means: dict | None = None
) -> dict[int, tuple[int, float, float, int]]:
    """Per segment: (best slit, confidence, best mean score, number of samples).

    ``means``, if given, receives per segment with samples its (N,) mean score per slit (a
    hypothesis without a candidate counting -0.2).
    """
    out: dict[int, tuple[int, float, float, int]] = {}
    if len(scores) == 0:
        return out
    N = scores.shape[1]
    good = np.isfinite(scores).any(axis=1)
    sids = np.unique(seg_of_sample)
    for sid in np.setdiff1d(sids, seg_of_sample[good]):
        out[int(sid)] = (-1, 0.0, np.nan, 0)
    rows = np.flatnonzero(good)
    if rows.size == 0:
        return out
    rows = rows[np.argsort(seg_of_sample[rows], kind="stable")]
    s_sorted = seg_of_sample[rows]
    starts = np.flatnonzero(np.r_[True, s_sorted[1:] != s_sorted[:-1]])
    n = np.diff(np.r_[starts, len(rows)])
    S = scores[rows]
    # a hypothesis without a candidate counts as a bad match
    Sz = np.where(np.isfinite(S), S, -0.2)
    mean = np.add.reduceat(Sz, starts, axis=0) / n[:, None]  # (G, N)
    k1 = np.argmax(mean, axis=1)
    g = np.arange(len(starts))
    m1 = mean[g, k1]
    if N > 1:
        rest = mean.copy()
        rest[g, k1] = -np.inf
        k2 = np.argmax(rest, axis=1)
        m2 = rest[g, k2]
        grp = np.repeat(g, n)
        d = Sz[np.arange(len(rows)), k1[grp]] - Sz[np.arange(len(rows)), k2[grp]]
    else:
        m2 = np.full(len(starts), -1.0)
        grp = np.repeat(g, n)
        d = Sz[:, 0] + 1.0
    # margin, discounted by its uncertainty (few or disagreeing samples)
    dm = np.add.reduceat(d, starts) / n
    ss = np.add.reduceat((d - dm[grp]) ** 2, starts)
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.where(n > 1, np.sqrt(ss / np.maximum(n - 1, 1)) / np.sqrt(n), 0.3)
    margin = np.maximum(0.0, m1 - m2 - se)
    conf = np.clip(margin / 0.3, 0.0, 1.0)
    for j, sid in enumerate(s_sorted[starts]):
        out[int(sid)] = (int(k1[j]), float(conf[j]), float(m1[j]), int(n[j]))
    if means is not None:
        means.update({int(sid): mean[j] for j, sid in enumerate(s_sorted[starts])})
    return out


def _order_violations(
    u: F64, v: F64, slit: I64, seg: I64, max_gap_px: float
) -> set[tuple[int, int]]:
    """Pairs of segments side by side in a row (closer than ``max_gap_px``) out of slit order.

    Across an occlusion or a shadow the order of slits can legitimately change, but two stripes
    directly next to each other on one surface keep the projector's left-to-right order.
    """
    m = slit >= 0
    if m.sum() < 2:
        return set()
    row = np.round(v[m]).astype(np.int64)
    uu, ss, gg = u[m], slit[m], seg[m]
    o = np.lexsort((uu, row))
    row, uu, ss, gg = row[o], uu[o], ss[o], gg[o]
    same = row[1:] == row[:-1]
    near = (uu[1:] - uu[:-1]) < max_gap_px
    bad = same & near & (ss[1:] <= ss[:-1]) & (gg[1:] != gg[:-1])
    return {(int(gg[i]), int(gg[i + 1])) for i in np.flatnonzero(bad)}


def _between_agreeing(
    run: NDArray[np.intp],
    rank: NDArray[np.intp],
    vote: NDArray[np.intp],
    voted: NDArray[np.bool_],
    lab: NDArray[np.intp],
) -> NDArray[np.bool_]:
    """For each point: do the nearest dot-identified stripes left and right of it in its run
    agree with each other and with its order label ``lab``? (their slits differ by their rank
    difference, and ``lab`` is the left one's slit plus the rank step). A run's majority offset
    can disagree with the stripes right beside a point where a hidden slit leaves no gap wide
    enough to cut the run (measured: on the half-size free-form scene two segments next to an
    occluded pair of slits took slit 20 for 18)."""
    out = np.zeros(len(run), bool)
    vi = np.flatnonzero(voted)
    if vi.size == 0:
        return out
    big = np.int64(rank.max()) + 2
    key_v = run[vi].astype(np.int64) * big + rank[vi]
    o = np.argsort(key_v, kind="stable")
    vi, key_v = vi[o], key_v[o]
    q = np.flatnonzero((run >= 0) & (lab >= 0))
    if q.size == 0:
        return out
    key_q = run[q].astype(np.int64) * big + rank[q]
    j = np.searchsorted(key_v, key_q)  # first voted at or after the point
    has_l = j > 0
    has_r = j < len(vi)
    jl = np.clip(j - 1, 0, len(vi) - 1)
    jr = np.clip(j, 0, len(vi) - 1)
    left, right = vi[jl], vi[jr]
    ok = has_l & has_r & (run[left] == run[q]) & (run[right] == run[q])
    ok &= (vote[right] - vote[left]) == (rank[right] - rank[left])
    ok &= lab[q] == vote[left] + (rank[q] - rank[left])
    out[q] = ok
    return out


class _RowOrder(NamedTuple):
    """Order labels of every point (:func:`_order_labels`); -1 where the order says nothing.

    run, rank : (K,) the point's row-run and its rank in it (-1: in no run)
    extended : (K,) run label wherever the run has an agreed offset (also beyond the run's
        first or last dot-identified stripe)
    inside : (K,) run label from the run's first to its last dot-identified stripe
    between : (K,) run label strictly between the run's first and last dot-identified
        stripes, where the nearest ones on either side agree with it (:func:`_between_agreeing`)
    """

    run: NDArray[np.intp]
    rank: NDArray[np.intp]
    extended: NDArray[np.intp]
    inside: NDArray[np.intp]
    between: NDArray[np.intp]


def _order_labels(u: F64, v: F64, seg: I64, slit: I64, conf: F64, num_slits: int) -> _RowOrder:
    """Per point, the slit its place in its row implies (-1 where the order says nothing).

    Along a row, stripes closer than ~1.6 local spacings belong to consecutive slits (a larger
    gap or a double detection cuts the run); each run's offset ``slit - rank`` must be agreed by
    its dot-identified points (>= 80 %, >= 3 votes, from >= 2 different stripes;
    :mod:`multislit.order`).

    Returns
    -------
    :class:`_RowOrder`
    """
    op = OrderParams()
    ok = seg >= 0
    run, rank = _runs(u, v, ok, op)
    n_runs = int(run.max()) + 1 if (run >= 0).any() else 0
    if n_runs == 0:
        none = np.full(len(u), -1, np.intp)
        return _RowOrder(run, rank, none, none, none)
    vote = np.where(slit >= 0, slit, -1).astype(np.intp)
    offset = _run_offsets(run, rank, vote, np.where(slit >= 0, conf, 0.0), n_runs, op)
    # an offset must be confirmed by the dots of >= 2 different stripes (segments) of the run
    voted = (vote >= 0) & (run >= 0)
    span = int(seg.max()) + 2
    pairs = np.unique(run[voted].astype(np.int64) * span + (seg[voted] + 1))
    n_seg_votes = np.bincount(pairs // span, minlength=n_runs)
    offset = np.where(n_seg_votes >= 2, offset, np.iinfo(np.intp).min)
    run_label = _apply(run, rank, offset, num_slits)
    # interpolate only: a point is labelled only between dot-identified stripes of its run
    big = np.iinfo(np.intp).max
    lo = np.full(n_runs, big, np.intp)
    hi = np.full(n_runs, -1, np.intp)
    np.minimum.at(lo, run[voted], rank[voted])
    np.maximum.at(hi, run[voted], rank[voted])
    r = np.maximum(run, 0)
    span_ = (run >= 0) & (rank >= lo[r]) & (rank <= hi[r])
    lab = np.where(span_ & (rank > lo[r]) & (rank < hi[r]), run_label, -1)
    between = np.where(_between_agreeing(run, rank, vote, voted, lab), lab, -1)
    return _RowOrder(run, rank, run_label, np.where(span_, run_label, -1), between)


def _fill_by_order(
    seg: I64,
    slit: I64,
    usable: NDArray[np.bool_],
    order: _RowOrder,
    num_slits: int,
    dots: dict[int, tuple[int, float, F64]] | None = None,
    p: IdentifyParams | None = None,
) -> dict[int, tuple[int, float]]:
    """Slit numbers for segments the dots left unidentified, from the order along the rows.

    ``order`` holds the order labels (:func:`_order_labels`); ``dots`` holds,
    per segment the dots left unidentified, their vote: (best slit, confidence, (N,) mean score
    per slit). A free segment takes, by the first rule that holds:

    1. the ``order.between`` label, if it covers >= 50 % (>= 5) of the segment's points and >= 95 %
       of those agree; confidence 0.6 x agreement (order-inferred labels never count as
       certain);
    2. the dots' best slit, if their confidence reaches ``p.min_confirm`` and the run label
       (``order.extended``, also beyond the run's last dot-identified stripe) covers >= 30 % (>= 5) of the
       points and >= ``p.confirm_share`` of those agree with it: two independent sources
       agreeing on one of N slits; confidence 0.6 x agreement;
    3. the run label, if it covers >= 50 % (>= 5) of the points, >= 95 % of those agree, and
       the dots do not contradict it: it is among their ``p.extrapolate_top`` best slits with a
       mean score >= ``p.min_score``; confidence 0.4 x agreement (extrapolated order, weak dots).
    """
    p = p or IdentifyParams()
    dots = dots or {}
    out: dict[int, tuple[int, float]] = {}
    ok = seg >= 0
    free = np.unique(seg[ok & (slit < 0) & usable])
    if free.size == 0:
        return out
    span = int(seg.max()) + 2
    n_pts = np.bincount(seg[ok], minlength=span)

    def majority(lab: NDArray[np.intp]) -> tuple[NDArray[np.int64], F64, F64]:
        """Per segment: most frequent label (the smallest of equally frequent ones), its count,
        and the number of labelled points."""
        lm = ok & (lab >= 0)
        L = num_slits + 1
        keys, cnt = np.unique(seg[lm].astype(np.int64) * L + lab[lm], return_counts=True)
        ks, kl = keys // L, keys % L
        n_lab = np.bincount(ks, weights=cnt, minlength=span)
        o = np.lexsort((kl, -cnt, ks))
        first = o[np.r_[True, ks[o][1:] != ks[o][:-1]]] if len(o) else o
        best = np.full(span, -1, np.int64)
        best_cnt = np.zeros(span)
        best[ks[first]] = kl[first]
        best_cnt[ks[first]] = cnt[first]
        return best, best_cnt, n_lab

    b_lab, b_cnt, b_n = majority(order.between)
    r_lab, r_cnt, r_n = majority(order.extended)
    # per segment: how many of its run labels name the dots' best slit (rule 2)
    dot_k = np.full(span, -1, np.int64)
    for sid, (k, _, _) in dots.items():
        dot_k[sid] = k
    named = ok & (order.extended >= 0) & (order.extended == dot_k[np.maximum(seg, 0)])
    n_named = np.bincount(seg[named], minlength=span)
    for sid in free:
        nb, nr = b_n[sid], r_n[sid]
        if nb >= 5 and nb >= 0.5 * n_pts[sid] and b_cnt[sid] >= 0.95 * nb:
            out[int(sid)] = (int(b_lab[sid]), float(0.6 * b_cnt[sid] / nb))
            continue
        if int(sid) not in dots or nr < 5:
            continue
        k, c, mean = dots[int(sid)]
        agree = float(n_named[sid] / nr)
        if k >= 0 and c >= p.min_confirm and nr >= 0.3 * n_pts[sid] and agree >= p.confirm_share:
            out[int(sid)] = (int(k), 0.6 * agree)
            continue
        kr = int(r_lab[sid])
        if nr >= 0.5 * n_pts[sid] and r_cnt[sid] >= 0.95 * nr and mean[kr] >= p.min_score:
            if np.sum(mean > mean[kr]) < p.extrapolate_top:
                out[int(sid)] = (kr, float(0.4 * r_cnt[sid] / nr))
    return out


def _confirm_by_neighbours(
    order: _RowOrder,
    seg: I64,
    slit: I64,
    weak: I64,
    usable: NDArray[np.bool_],
    min_share: float,
) -> dict[int, int]:
    """Weak dot votes that their neighbours in the rows confirm.

    ``weak`` (S,) is, per segment, the dots' best slit where they were too unsure to label it
    (-1 elsewhere). A point is supported where the next stripe to its left in its row-run
    (another segment) carries its slit - 1, or the next one to its right its slit + 1, counting
    labels and weak votes alike. A segment whose weak vote is supported on >= ``min_share`` of
    its usable points (>= 5) takes it: two neighbouring stripes whose dots each point to
    consecutive slits (on the half-size 49-slit spheres, 5 stripes side by side with dot
    confidence 0.02-0.26 each named its true slit).

    Returns
    -------
    dict segment -> slit, for the segments confirmed
    """
    lab = np.where(slit >= 0, slit, np.where(seg >= 0, weak[np.maximum(seg, 0)], -1))
    o = np.lexsort((order.rank, order.run))
    o = o[order.run[o] >= 0]
    nxt = (order.run[o][1:] == order.run[o][:-1]) & (order.rank[o][1:] == order.rank[o][:-1] + 1)
    a, b = o[:-1][nxt], o[1:][nxt]
    pair = (lab[a] >= 0) & (lab[b] == lab[a] + 1) & (seg[a] != seg[b])
    support = np.zeros(len(seg), bool)
    support[a[pair]] = True
    support[b[pair]] = True
    out: dict[int, int] = {}
    m = usable & (seg >= 0)
    m &= weak[np.maximum(seg, 0)] >= 0
    m &= slit < 0
    if not m.any():
        return out
    n = np.bincount(seg[m], minlength=len(weak))
    n_sup = np.bincount(seg[m], weights=support[m], minlength=len(weak))
    for sid in np.flatnonzero((n >= 5) & (n_sup >= min_share * np.maximum(n, 1))):
        out[int(sid)] = int(weak[sid])
    return out


def identify(
    image: ArrayLike,
    reference: ReferenceSet,
    params: IdentifyParams | None = None,
    extraction: SlitExtraction | None = None,
) -> Identification:
    """Find the slits in one image and give each stripe-centre point its slit number.

    Parameters
    ----------
    image : (H, W) uint8/uint16, a scan (lasers on); must have the reference's image size
    reference : the prepared :class:`ReferenceSet` (see ``prepare_reference``), reused per scan
    params : tuning (defaults work for the simulated and paper-like rigs)
    extraction : an extraction of ``image`` already made (skips extracting again)

    Returns
    -------
    Identification with per-point u, v, slit (-1 = not identified) and confidence. An image
    with no slits gives empty arrays and a message, not an exception.
    """
    p = params or IdentifyParams()
    if p.follow_stripe not in ("line", "off"):
        raise IdentificationError(
            f"params.follow_stripe must be 'line' or 'off', got {p.follow_stripe!r}"
        )
    if not p.junction_template >= 0:  # also catches NaN
        raise IdentificationError(
            "params.junction_template must be >= 0 (a fraction of the template's half height), "
            f"got {p.junction_template}"
        )
    if not p.depth_margin >= 0:  # also catches NaN
        raise IdentificationError(
            f"params.depth_margin must be >= 0 (or inf for no depth limit), got {p.depth_margin}"
        )
    for name in ("min_confirm", "confirm_share", "neighbour_share", "border_cut"):
        if not getattr(p, name) >= 0:  # also catches NaN
            raise IdentificationError(f"params.{name} must be >= 0, got {getattr(p, name)}")
    if not (isinstance(p.extrapolate_top, int) and p.extrapolate_top >= 0):
        raise IdentificationError(
            f"params.extrapolate_top must be an integer >= 0 (0: never), got {p.extrapolate_top!r}"
        )
    img = np.asarray(image)
    if img.ndim != 2:
        raise IdentificationError(f"image must be a 2-D grayscale array, got shape {img.shape}")
    w, h = reference.image_size
    if img.shape != (h, w):
        raise IdentificationError(
            f"image is {img.shape[1]}x{img.shape[0]} px but the reference was prepared for {w}x{h} px"
        )
    ex = extraction or extract_slits(
        img, stripe_width_px=reference.stripe_width_px, dot_size_px=reference.dot_size_px
    )
    K = len(ex.u)
    slit = np.full(K, -1, np.int64)
    conf = np.zeros(K)
    seg = ex.segment.astype(np.int64)
    n_seg = int(len(np.unique(seg[seg >= 0])))
    if K == 0 or n_seg == 0:
        return Identification(
            ex.u,
            ex.v,
            slit,
            conf,
            seg,
            ex.peak,
            ex.width,
            0,
            0,
            {},
            "no slits found in the image",
            ex,
        )
    seg = split_at_brightness_steps(seg, ex.v, ex.peak)
    step = max(2.0, p.sample_step * reference.spacing_px)
    hh = template_size(reference, p)[1]
    si = _band_samples(seg, ex.v, step, p.border_cut * hh, h - 1 - p.border_cut * hh)
    dots = ex.dots.astype(np.float32)
    shift = _template_row_shift(ex.u, ex.v, seg, si, reference, hh, p.follow_stripe)
    if p.coarse_every > 1 and reference.num_slits > p.keep_hypotheses:
        # coarse to fine: every slit on a few samples of each segment, then on every sample only
        # the few slits each segment's coarse samples liked best
        rank = np.zeros(len(si), np.int64)
        ss = seg[si]
        first = np.r_[True, ss[1:] != ss[:-1]]
        start = np.maximum.accumulate(np.where(first, np.arange(len(si)), 0))
        rank = np.arange(len(si)) - start
        coarse = rank % p.coarse_every == 0
        sc = _score_candidates(
            reference,
            dots,
            ex.u[si[coarse]],
            ex.v[si[coarse]],
            p,
            row_shift=None if shift is None else shift[coarse],
        )
        allowed = np.zeros((len(si), reference.num_slits), bool)
        coarse_mean = np.full((len(si), reference.num_slits), np.nan)
        sc_seg = ss[coarse]
        for sid in np.unique(sc_seg):
            rows = sc_seg == sid
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a slit without candidates
                mean = np.nanmean(sc[rows], axis=0)
            ranked = np.where(np.isfinite(mean), mean, -np.inf)
            top = np.argsort(ranked)[::-1][: p.keep_hypotheses]
            members = np.flatnonzero(ss == sid)
            allowed[np.ix_(members, top)] = True
            coarse_mean[members] = mean
        scores = _score_candidates(reference, dots, ex.u[si], ex.v[si], p, allowed, shift)
        # the slits not kept still count in the vote, with their coarse mean score: the margin
        # to the runner-up must not grow just because the runner-up was not scored again
        fill = ~allowed & np.isfinite(coarse_mean)
        scores[fill] = coarse_mean[fill]
    else:
        scores = _score_candidates(reference, dots, ex.u[si], ex.v[si], p, row_shift=shift)
    seg = _split_segments(seg, ex.v, si, scores, p)
    means: dict[int, F64] = {}
    votes = _segment_votes(seg[si], scores, p, means)
    dropped = {"too_short": 0, "no_candidate": 0, "weak_match": 0, "low_confidence": 0, "order": 0}
    accepted: dict[int, tuple[int, float]] = {}
    dot_votes: dict[int, tuple[int, float, F64]] = {}  # of the segments dropped
    for sid in np.unique(seg[seg >= 0]):
        k, c, m1, n = votes.get(int(sid), (-1, 0.0, np.nan, 0))
        low_confidence = False
        if n < p.min_samples:
            dropped["too_short" if n > 0 or int(sid) not in votes else "no_candidate"] += 1
        elif k < 0:
            dropped["no_candidate"] += 1
        elif m1 < p.min_score:
            dropped["weak_match"] += 1
        elif c < p.min_confidence:
            dropped["low_confidence"] += 1
            low_confidence = True
        else:
            accepted[int(sid)] = (k, c)
            continue
        if int(sid) in means:
            # not enough alone; the order along the rows may confirm it (_fill_by_order)
            dot_votes[int(sid)] = (k if low_confidence else -1, c, means[int(sid)])
    lut_k = np.full(int(seg.max()) + 1, -1, np.int64)
    lut_c = np.zeros(int(seg.max()) + 1)
    for sid, (k, c) in accepted.items():
        lut_k[sid], lut_c[sid] = k, c
    has = seg >= 0
    # a point far from every usable sample of its segment is not vouched for by the dots
    usable = np.isfinite(scores).any(axis=1)
    reach = np.full(len(seg), np.inf)
    if usable.any():
        us = si[usable]
        o = np.lexsort((ex.v[us], seg[us]))
        us = us[o]
        key_s = seg[us].astype(float) * 1e6 + ex.v[us]
        key_p = seg.astype(float) * 1e6 + ex.v
        j = np.clip(np.searchsorted(key_s, key_p), 1, len(us) - 1)
        for jj in (j - 1, j):
            same = seg[us[jj]] == seg
            reach = np.where(same, np.minimum(reach, np.abs(ex.v[us[jj]] - ex.v)), reach)
    has &= reach <= max(step, hh)
    # the rows at a segment's ends are where it meets another surface or slit: the centre there
    # mixes two stripes, so they are not vouched for
    if p.trim_rows > 0 and has.any():
        has &= ~_near_segment_ends(ex.u, ex.v, seg, lut_k, p.trim_rows, p.junction_rows(hh))
    slit[has] = lut_k[seg[has]]
    conf[has] = lut_c[seg[has]]
    # left-to-right order: drop the less confident of each out-of-order pair
    for _ in range(10):
        bad = _order_violations(ex.u, ex.v, slit, seg, 1.5 * reference.spacing_px)
        if not bad:
            break
        drop = {a if lut_c[a] < lut_c[b] else b for a, b in bad}
        for sid in drop:
            lut_k[sid] = -1
            lut_c[sid] = 0.0
            dropped["order"] += 1
        slit[has] = lut_k[seg[has]]
        conf[has] = lut_c[seg[has]]
    if p.order_fill:
        order = _order_labels(ex.u, ex.v, seg, slit, conf, reference.num_slits)
        filled = _fill_by_order(seg, slit, has, order, reference.num_slits, dot_votes, p)
        for sid, (k, c) in filled.items():
            lut_k[sid], lut_c[sid] = k, c
        if p.neighbour_share <= 1:
            weak = np.full(len(lut_k), -1, np.int64)
            for sid, (k, _, _) in dot_votes.items():
                if lut_k[sid] < 0:
                    weak[sid] = k
            slit[has] = lut_k[seg[has]]
            agreed = _confirm_by_neighbours(order, seg, slit, weak, has, p.neighbour_share)
            for sid, k in agreed.items():
                lut_k[sid], lut_c[sid] = k, 0.4
        slit[has] = lut_k[seg[has]]
        conf[has] = lut_c[seg[has]]
        if p.end_order:
            # rows left out at a segment's ends (or far from its samples) come back where
            # their place in the row says the segment's slit too
            back = (seg >= 0) & ~has & (order.between >= 0)
            back &= order.between == lut_k[np.maximum(seg, 0)]
            slit[back] = lut_k[seg[back]]
            conf[back] = lut_c[seg[back]]
        if p.order_check:
            # a point whose place in its row, within the span of the run's dot-identified
            # stripes, gives another slit than its label is left out
            left_out = (slit >= 0) & (order.inside >= 0) & (order.inside != slit)
            slit[left_out] = -1
    conf[slit < 0] = 0.0
    n_id = int(np.sum(lut_k >= 0))
    return Identification(
        ex.u, ex.v, slit, conf, seg, ex.peak, ex.width, n_seg, n_id, dropped, "", ex
    )

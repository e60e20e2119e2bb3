"""Slit address identification by template matching (paper section 4.2, Fig. 12-13).

The dot templates of sample points on each slit segment of a scan are matched with the
reference dot images where the sample's epipolar line meets each slit's reference curve
(:mod:`~multislit.identify.matching`). The samples of a segment vote: the slit with the best
mean NCC wins, and the margin to the second-best slit, less its standard error, gives the
confidence. A segment whose vote is too short, too weak or too unsure is dropped and counted,
never guessed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.errors import IdentificationError
from multislit.identify.matching import score_candidates, template_geometry, template_size
from multislit.identify.patches import compile_kernels as compile_patch_kernels
from multislit.identify.prior import check_previous, scores_with_prior
from multislit.identify.reference import TEMPLATE_BACKGROUND, ReferenceSet
from multislit.identify.result import Identification
from multislit.identify.segments import (
    band_samples,
    by_segment,
    near_segment_ends,
    split_at_brightness_steps,
    split_at_winner_changes,
)
from multislit.identify.votes import MIN_SAMPLES, MIN_SCORE, scored_rows, segment_votes
from multislit.stripes import SlitExtraction, as_image, extract_slits

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Spacing of the sample points along a segment, in reference slit spacings (at least 2 px).
_SAMPLE_STEP = 0.30
#: Samples are taken only where the template is cut by the image's top or bottom by at most
#: this fraction of its half height (1: never cut).
_BORDER_CUT = 1.0
#: Rows left out at each end of a segment: the centre there mixes two stripes.
_TRIM_ROWS = 2
#: Rows left out next to a junction of two segments of different slits, as a fraction of the
#: template's half height (at least ``_TRIM_ROWS``).
_JUNCTION_TEMPLATE = 0.4


def _junction_rows(half_height_px: int) -> int:
    """Rows left out next to a junction of two segments, for a template half height (px)."""
    return max(_TRIM_ROWS, int(math.ceil(_JUNCTION_TEMPLATE * half_height_px)))


def identify_template(
    image: ArrayLike,
    reference: ReferenceSet,
    *,
    min_confidence: float = 0.30,
    extraction: SlitExtraction | None = None,
    previous: Identification | None = None,
) -> Identification:
    """Find the slits in one image by the paper's template matching (:func:`identify`'s
    ``method="template"``) and give each stripe-centre point its slit number.

    Parameters
    ----------
    image : (H, W) uint8/uint16, a scan (lasers on); must have the reference's image size
    reference : the prepared :class:`~multislit.identify.reference.ReferenceSet` (see
        :func:`~multislit.identify.reference.prepare_reference`), reused for every scan
    min_confidence : a segment whose samples' vote gives its best slit a confidence (0..1)
        below this is left out; default 0.30
    extraction : an extraction of ``image`` already made (skips extracting again); default
        None: extract with the reference's stripe width and dot size
    previous : the :class:`Identification` of the previous frame of a sequence (the same
        camera and reference), used as a prior: a segment lying on a piece ``previous``
        labelled with slit k is checked against slits k-1..k+1 only, on about one sample per
        template height (a sample slit k explains poorly is searched over all slits), and
        keeps k where k wins with the confidence this vote requires and no sample prefers
        another slit; a segment failing the check, or without such a piece, is searched over
        all slits (:mod:`~multislit.identify.prior`). Default None: every segment is searched
        (single images)

    Returns
    -------
    Identification with per-point u, v, slit (-1 = not identified) and confidence. An image
    with no slits gives empty arrays and a message, not an exception.

    Raises
    ------
    IdentificationError
        (a ``ValueError``) if ``image`` is not a grayscale image of the reference's size, or
        ``min_confidence`` is not in [0, 1], or ``previous`` is not an Identification of an
        image of the reference's size.
    """
    if not 0.0 <= min_confidence <= 1.0:  # also catches NaN
        raise IdentificationError(f"min_confidence must be in [0, 1], got {min_confidence}")
    if reference.epipole_problem:
        raise IdentificationError(
            "the template identification needs the dot projector's epipole, which the "
            f"reference images did not give ({reference.epipole_problem}); identify by the "
            "dots' geometry instead"
        )
    if previous is not None:
        check_previous(previous, reference)
    img = as_image(image)
    w, h = reference.image_size
    if img.shape != (h, w):
        raise IdentificationError(
            f"image is {img.shape[1]}x{img.shape[0]} px but the reference was prepared for {w}x{h} px"
        )
    ex = extraction or extract_slits(
        img,
        stripe_width_px=reference.stripe_width_px,
        dot_size_px=reference.dot_size_px,
        background=TEMPLATE_BACKGROUND,
    )
    K = len(ex.u)
    slit = np.full(K, -1, np.int64)
    conf = np.zeros(K)
    seg = ex.segment.astype(np.int64)
    n_seg = int(np.count_nonzero(np.bincount(seg[seg >= 0])))
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
    seg, si, step, hh = _sampled_segments(ex, reference)
    reach = max(step, hh)
    if previous is None:
        scores = _sample_scores(ex, seg, si, reference, hh)
    else:  # the previous frame's labels: checked, not searched
        si, scores = scores_with_prior(
            ex, seg, si, reference, hh, reach, min_confidence, previous, _sample_scores
        )
    seg = split_at_winner_changes(seg, ex.v, si, scores, MIN_SCORE)
    lut_k, lut_c, dropped = _segment_decisions(seg, si, scores, min_confidence)
    has = _vouched_points(ex, seg, si, scores, reach, lut_k, hh)
    slit[has] = lut_k[seg[has]]
    conf[has] = lut_c[seg[has]]
    n_id = int(np.sum(lut_k >= 0))
    return Identification(
        ex.u, ex.v, slit, conf, seg, ex.peak, ex.width, n_seg, n_id, dropped, "", ex
    )


def _sampled_segments(
    ex: SlitExtraction, reference: ReferenceSet
) -> tuple[I64, NDArray[np.intp], float, int]:
    """The extraction's segments split at brightness steps, and where they are sampled.

    Returns
    -------
    seg : (K,) int64, segment id per point (-1: none)
    si : (M,) intp, the sample points (every ``step`` rows of a segment, with templates
        inside the image)
    step : float, px, the sample spacing
    hh : int, px, the template's half height
    """
    seg = split_at_brightness_steps(ex.segment.astype(np.int64), ex.v, ex.peak)
    step = max(2.0, _SAMPLE_STEP * reference.spacing_px)
    hh = template_size(reference)[1]
    h = reference.image_size[1]
    si = band_samples(seg, ex.v, step, _BORDER_CUT * hh, h - 1 - _BORDER_CUT * hh)
    return seg, si, step, hh


def _sample_scores(
    ex: SlitExtraction, seg: I64, si: NDArray[np.intp], reference: ReferenceSet, hh: int
) -> F64:
    """(M, N) NCC of the templates at the sample points ``si`` with each slit's candidates
    (:func:`~.matching.score_candidates`; NaN: no candidate), the templates following their
    stripes' lean and spacing (:func:`~.matching.template_geometry`)."""
    shift, scale = template_geometry(ex.u, ex.v, seg, si, reference, hh)
    dots = ex.dots.astype(np.float32)
    return score_candidates(reference, dots, ex.u[si], ex.v[si], shift, scale)


def _segment_decisions(
    seg: I64, si: NDArray[np.intp], scores: F64, min_confidence: float
) -> tuple[I64, F64, dict[str, int]]:
    """Accept or drop each segment by its samples' vote (:func:`~.votes.segment_votes`).

    Returns
    -------
    lut_k, lut_c : (S,) int64 and float64, per segment id its slit (-1: not accepted) and
        confidence
    dropped : counts of the dropped segments by reason
    """
    votes = segment_votes(seg[si], scores)
    dropped = {"too_short": 0, "no_candidate": 0, "weak_match": 0, "low_confidence": 0}
    lut_k = np.full(int(seg.max()) + 1, -1, np.int64)
    lut_c = np.zeros(int(seg.max()) + 1)
    for sid in np.flatnonzero(np.bincount(seg[seg >= 0])):
        k, c, m1, n = votes.get(int(sid), (-1, 0.0, np.nan, 0))
        if n < MIN_SAMPLES:
            dropped["too_short" if n > 0 or int(sid) not in votes else "no_candidate"] += 1
        elif k < 0:
            dropped["no_candidate"] += 1
        elif m1 < MIN_SCORE:
            dropped["weak_match"] += 1
        elif c < min_confidence:
            dropped["low_confidence"] += 1
        else:
            lut_k[sid], lut_c[sid] = k, c
    return lut_k, lut_c, dropped


@njit(cache=True)
def _rows_to_sample(order, seg, v, sample):
    """(K,) float64: per point, the rows (``|dv|``, px) to the nearest point of its segment
    flagged in ``sample`` (K,) bool (inf: none); ``order`` holds the linked points by
    (segment, v) (:func:`~.segments.by_segment`)."""
    out = np.full(len(seg), np.inf)
    n = len(order)
    for backward in (False, True):  # the nearest sample at or before, then at or after
        last = -1
        for s in range(n):
            i = order[n - 1 - s if backward else s]
            if last >= 0 and seg[last] != seg[i]:
                last = -1
            if sample[i]:
                last = i
            if last >= 0:
                out[i] = min(out[i], abs(v[last] - v[i]))
    return out


def _vouched_points(
    ex: SlitExtraction,
    seg: I64,
    si: NDArray[np.intp],
    scores: F64,
    max_reach: float,
    lut_k: I64,
    hh: int,
) -> NDArray[np.bool_]:
    """(K,) bool: the linked points the dots vouch for: within ``max_reach`` rows of a usable
    sample of their segment, and not in the rows at the segment's ends (where it meets another
    surface or slit, the centre mixes two stripes; :func:`~.segments.near_segment_ends`)."""
    has = seg >= 0
    usable = np.zeros(len(seg), bool)
    usable[si[scored_rows(scores)]] = True
    reach = _rows_to_sample(by_segment(seg, ex.v), seg, ex.v.astype(np.float64), usable)
    has &= reach <= max_reach
    if has.any():
        has &= ~near_segment_ends(ex.u, ex.v, seg, lut_k, _TRIM_ROWS, _junction_rows(hh))
    return has


#: The synthetic frame of :func:`synthetic_frame`: image size (px), slits, their spacing (px)
#: and the first stripe's column (px), and the dots' shift between the two references (px).
_SYNTH_W, _SYNTH_H, _SYNTH_SLITS, _SYNTH_SPACING, _SYNTH_U0, _SYNTH_SHIFT = (
    160,
    120,
    5,
    25.0,
    31.0,
    3,
)


def synthetic_frame() -> tuple[ReferenceSet, list[NDArray[np.uint8]], F64, F64]:
    """A small synthetic frame for compiling the kernels: five vertical slits (stripes at
    columns 31, 56, ... px) over 400 dots of 2x2 px on a 160x120 image, and two flat
    references whose dots move along the rows.

    Returns
    -------
    reference : the ReferenceSet of the two references
    images : two uint8 images: dots beside every stripe, and one stripe's dots missing
    dot_uv : (D, 2) float64, px, the dots' centres
    stripe_u : (5,) float64, px, the stripes' columns
    """
    w, h, n, spacing, shift = _SYNTH_W, _SYNTH_H, _SYNTH_SLITS, _SYNTH_SPACING, _SYNTH_SHIFT
    rng = np.random.default_rng(0)
    dots = np.zeros((h, w), np.float32)
    yx = np.stack([rng.integers(0, h - 2, 400), rng.integers(0, w - 2, 400)], axis=1)
    for y, x in yx:
        dots[y : y + 2, x : x + 2] = 100.0
    us = _SYNTH_U0 - 1.0 + spacing * np.arange(n)
    curves = np.zeros((2, n, 4))
    curves[0, :, -1] = us
    curves[1, :, -1] = us + shift
    reference = ReferenceSet(
        (w, h),
        n,
        ("near", "far"),
        curves,
        np.tile([0.0, h - 1.0], (2, n, 1)),
        np.stack([dots, np.roll(dots, shift, axis=1)]),
        np.array([1e5, h / 2, 1.0]),  # the dots move along the rows
        spacing,
        3.0,
        2.0,
        0.1,
        0.02,
    )
    stripes = 200.0 * np.exp(-0.5 * ((np.arange(w) - us[:, None] - 1) / 1.3) ** 2).sum(axis=0)
    images = [
        np.clip(10.0 + 1.2 * scan_dots + stripes, 0, 255).astype(np.uint8)
        for scan_dots in (dots, np.where(np.abs(np.arange(w) - us[2]) < 12, 0, dots))
    ]
    return reference, images, yx[:, ::-1] + 0.5, us + 1.0


def compile_kernels() -> None:
    """Compile the template identification's Numba kernels now.

    Numba compiles each kernel on first use (seconds) and caches the machine code on disk
    beside the package, so only the first run after an install pays it. It runs
    :func:`identify_template` on the frame of :func:`synthetic_frame`, once with dots beside
    every stripe and once with one stripe's dots missing (its templates flat: left out), after
    the reference preparation's patch sampler
    (:func:`~multislit.identify.patches.compile_kernels`).
    """
    compile_patch_kernels()
    reference, images, _, _ = synthetic_frame()
    for image in images:
        identify_template(image, reference)

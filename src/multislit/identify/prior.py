"""The previous frame's slit labels as a prior for the next frame of a sequence.

Between two frames of a camera running at its frame rate, a stripe moves little: a segment
of the new frame that lies on a piece the previous frame labelled with slit k (in the same
rows, within a quarter of the slit spacing) is most likely slit k again. Such a segment is
checked, not searched: its dot templates are matched only with slits k-1, k and k+1, on about
one sample per template height (all samples in its first and last template height). A sample
that slit k explains poorly (NCC below ``_CONFIRM``: another surface's stripe may have moved
onto the place of slit k's) is matched with every slit. Slit k is kept when it wins the
segment's vote with the tests the full identification applies (enough samples, a best mean
NCC of at least the minimum score, the confidence the caller asked for) and no sample clearly
prefers another slit. Otherwise, and for every segment without a prior, the segment goes
through the full search over all slits on all its samples: a prior never labels a segment by
itself, and a failed check guesses nothing.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from multislit.errors import IdentificationError
from multislit.identify.matching import score_candidates, template_geometry
from multislit.identify.reference import ReferenceSet
from multislit.identify.result import Identification
from multislit.identify.segments import clear_winners
from multislit.identify.votes import MIN_SAMPLES, MIN_SCORE, segment_votes
from multislit.stripes import SlitExtraction

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: A new point takes the slit of the previous frame's labelled point nearest it in the same
#: row within this many slit spacings.
_REACH = 0.25
#: A segment has a prior slit k when at least this share of its points take k ...
_SHARE = 0.6
#: ... and at most this share take any other slit.
_OTHER = 0.05
#: A checked sample whose NCC with the prior slit is below this is searched over all slits
#: (the dots of a stripe on the backdrop match their slit at 0.7-0.9; on a moving object's
#: curved faces often less, and another surface's stripe that has moved onto the prior's
#: place matches the prior slit at most ~0.3).
_CONFIRM = 0.5
#: Hypotheses checked either side of the prior slit.
_NEIGHBOURS = 1


def check_previous(previous: object, reference: ReferenceSet) -> None:
    """Raise :class:`IdentificationError` naming ``previous`` unless it is an
    :class:`~multislit.identify.Identification` of an image of the reference's size whose
    slit numbers are the reference's."""
    if not isinstance(previous, Identification):
        raise IdentificationError(
            "previous must be the Identification identify() returned for the previous frame "
            f"(or None), got {type(previous).__name__}"
        )
    w, h = reference.image_size
    ex = previous.extraction
    if ex is not None and np.shape(ex.dots) != (h, w):
        hh, ww = np.shape(ex.dots)[:2]
        raise IdentificationError(
            f"previous is an identification of a {ww}x{hh} px image but the reference was "
            f"prepared for {w}x{h} px; pass the previous frame of the same camera"
        )
    n = len(previous.slit)
    if len(previous.u) != n or len(previous.v) != n:
        raise IdentificationError("previous has arrays of different lengths (u, v, slit)")
    lab = previous.slit >= 0
    if np.any(previous.slit[lab] >= reference.num_slits) or not (
        np.all(np.isfinite(previous.u[lab])) and np.all(np.isfinite(previous.v[lab]))
    ):
        raise IdentificationError(
            f"previous has slit numbers beyond this reference's {reference.num_slits} slits or "
            "points that are not finite; pass the previous frame identified with this reference"
        )
    inside = (previous.u[lab] > -1) & (previous.u[lab] < w) & (previous.v[lab] > -1)
    if not np.all(inside & (previous.v[lab] < h)):
        raise IdentificationError(
            f"previous has points outside the reference's {w}x{h} px image; pass the previous "
            "frame of the same camera"
        )


def prior_slits(u: F64, v: F64, seg: I64, previous: Identification, spacing_px: float) -> I64:
    """Per segment id, the slit the previous frame gives it (-1: none).

    Each linked point takes the slit of the previous frame's labelled point nearest it in the
    same row (within ``_REACH`` slit spacings); a segment whose points take one slit k on at
    least ``_SHARE`` of them, and any other slit on at most ``_OTHER``, has prior k.

    Parameters
    ----------
    u, v : (K,) float64, px, the new frame's stripe centres
    seg : (K,) int64, their segment ids (-1: not linked)
    previous : the previous frame's identification
    spacing_px : the reference's slit spacing, px

    Returns
    -------
    (S,) int64, S = ``seg.max() + 1``
    """
    n_seg = int(seg.max()) + 1 if len(seg) else 0
    out = np.full(n_seg, -1, np.int64)
    lab = np.flatnonzero(previous.slit >= 0)
    pts = np.flatnonzero(seg >= 0)
    if n_seg == 0 or lab.size == 0 or pts.size == 0:
        return out
    # previous labelled points keyed by (row, u); rows far enough apart that keys never mix
    span = float(max(np.max(previous.u[lab]), np.max(u)) + 4 * spacing_px + 4)
    pkey = np.rint(previous.v[lab]) * span + previous.u[lab]
    o = np.argsort(pkey, kind="stable")
    pkey, pk = pkey[o], previous.slit[lab][o]
    key = np.rint(v[pts]) * span + u[pts]
    j = np.searchsorted(pkey, key)
    best = np.full(len(pts), np.inf)
    got = np.full(len(pts), -1, np.int64)
    for jj in (j - 1, j):
        ok = (jj >= 0) & (jj < len(pkey))
        d = np.where(ok, np.abs(pkey[np.clip(jj, 0, len(pkey) - 1)] - key), np.inf)
        closer = d < best
        best = np.where(closer, d, best)
        got = np.where(closer, pk[np.clip(jj, 0, len(pkey) - 1)], got)
    got[best > _REACH * spacing_px] = -1
    # points per (segment, slit)
    N = int(max(pk.max(), 0)) + 1
    m = got >= 0
    count = np.bincount(seg[pts][m] * N + got[m], minlength=n_seg * N).reshape(n_seg, N)
    n_pts = np.maximum(np.bincount(seg[pts], minlength=n_seg), 1)
    top_k = np.argmax(count, axis=1)
    top = count[np.arange(n_seg), top_k]
    good = (top >= _SHARE * n_pts) & (count.sum(axis=1) - top <= _OTHER * n_pts) & (top > 0)
    out[good] = top_k[good]
    return out


def _thinned(seg: I64, v: F64, si: NDArray[np.intp], rows: float) -> NDArray[np.bool_]:
    """(M,) bool: of the samples ``si`` (ordered by segment, then row), the first of each
    segment's ``rows``-high bins along v, and all in its first and last ``rows`` rows (near
    the image's top and bottom a template may find no candidate for the prior's slits): every
    point of the segment lies within ``rows`` rows of one of them."""
    if len(si) == 0:
        return np.zeros(0, bool)
    s = seg[si]
    first = np.r_[True, s[1:] != s[:-1]]
    last = np.r_[s[1:] != s[:-1], True]
    pos = np.arange(len(si))
    start = np.maximum.accumulate(np.where(first, pos, 0))
    end = np.minimum.accumulate(np.where(last, pos, len(si))[::-1])[::-1]
    vs = v[si]
    b = np.floor((vs - vs[start]) / rows).astype(np.int64)
    ends = (vs - vs[start] < rows) | (vs[end] - vs < rows)
    return ends | np.r_[True, b[1:] != b[:-1]]


def _strays(ss: I64, vs: F64, scores: F64, k: I64, reach: float) -> set[int]:
    """The segments some of whose checked samples clearly prefer another slit than their prior.

    A sample clearly prefers slit j when its best NCC (j's) reaches ``MIN_SCORE`` and leads
    the second best (:func:`~.segments.clear_winners`, as the full identification's split). A
    segment is sent back when two such samples in a row (of its clear samples, by row) prefer
    the same other slit (where the full identification would split the segment), or one does
    where the samples are thinned (``reach`` rows or more from a neighbouring sample: it may
    stand for several). One such sample among dense samples (where a template reaches past
    the segment's end) is left to the vote, as in the full identification.

    Parameters
    ----------
    ss, vs : (M,) segment id and row (px) of the checked samples, ordered by segment, then row
    scores : (M, N) float64, their NCC (NaN: not scored)
    k : (M,) int64, their segment's prior slit
    reach : px, the thinned samples' spacing
    """
    win, clear = clear_winners(scores, MIN_SCORE)
    stray = clear & (win != k)
    out: set[int] = set()
    same = np.r_[ss[1:] == ss[:-1], False]  # the next sample is of the same segment
    gap_next = np.where(same, np.r_[vs[1:] - vs[:-1], 0.0], 0.0)
    gap_prev = np.r_[0.0, gap_next[:-1]]
    for sid in np.unique(ss[stray]):
        rows = np.flatnonzero((ss == sid) & clear)
        w = win[rows]
        bad = w != k[rows]
        pair = bad[1:] & bad[:-1] & (w[1:] == w[:-1])
        lone = rows[bad]
        if pair.any() or np.any(np.maximum(gap_next[lone], gap_prev[lone]) >= reach):
            out.add(int(sid))
    return out


def scores_with_prior(
    ex: SlitExtraction,
    seg: I64,
    si: NDArray[np.intp],
    reference: ReferenceSet,
    hh: int,
    reach: float,
    min_confidence: float,
    previous: Identification,
    full_scores: Callable[..., F64],
) -> tuple[NDArray[np.intp], F64]:
    """The samples and their scores for the identification, with the previous frame's prior.

    Parameters
    ----------
    ex : the frame's extraction
    seg : (K,) int64, the segment ids (after the brightness-step splits)
    si : (M,) intp, the full identification's sample points, ordered by segment, then row
    reference : the prepared references
    hh : template half height, px
    reach : px, the farthest a point may lie (in rows) from a scored sample of its segment to
        be vouched for; the checked segments keep a sample within it of each of their points
    min_confidence : the confidence the check's vote must reach (the identification's)
    previous : the previous frame's identification (checked by :func:`check_previous`)
    full_scores : ``full_scores(ex, seg, si, reference, hh)`` -> (M', N) scores of the
        full search over all slits, for the segments without a prior or failing the check

    Returns
    -------
    si : (M',) intp, the samples kept (a checked segment's thinned ones, every other segment's
        all), ordered by segment, then row
    scores : (M', N) float64, NCC per sample and slit: on a checked segment only slits
        k-1..k+1 are scored (NaN elsewhere)
    """
    N = reference.num_slits
    prior = prior_slits(ex.u, ex.v, seg, previous, reference.spacing_px)
    k_s = prior[seg[si]] if len(si) else np.zeros(0, np.int64)
    cand = (k_s >= 0) & _thinned(seg, ex.v, si, max(reach, 1.0))
    accepted = np.zeros(len(prior), bool)
    ci = si[cand]
    sc_c = np.zeros((0, N))
    if ci.size:
        kk = k_s[cand]
        allowed = np.abs(np.arange(N)[None, :] - kk[:, None]) <= _NEIGHBOURS
        shift, scale = template_geometry(ex.u, ex.v, seg, ci, reference, hh)
        sc_c = score_candidates(
            reference, ex.dots.astype(np.float32), ex.u[ci], ex.v[ci], shift, scale, allowed
        )
        # samples the prior slit does not explain well are searched over all slits
        own = sc_c[np.arange(len(ci)), kk]
        unsure = ~(own >= _CONFIRM)
        if unsure.any():
            sc_c[unsure] = full_scores(ex, seg, ci[unsure], reference, hh)
        votes = segment_votes(seg[ci], sc_c)
        stray_seg = _strays(seg[ci], ex.v[ci], sc_c, kk, reach)
        for sid, (k, c, m1, n) in votes.items():
            accepted[sid] = (
                k == prior[sid]
                and n >= MIN_SAMPLES
                and m1 >= MIN_SCORE
                and c >= min_confidence
                and sid not in stray_seg
            )
        keep = accepted[seg[ci]]
        ci, sc_c = ci[keep], sc_c[keep]
    rest = si[~accepted[seg[si]]] if len(si) else si
    sc_r = full_scores(ex, seg, rest, reference, hh)
    out_si = np.r_[ci, rest].astype(si.dtype)
    out_sc = np.concatenate([sc_c.reshape(-1, N), sc_r.reshape(-1, N)])
    o = np.lexsort((ex.v[out_si], seg[out_si]))
    return out_si[o], out_sc[o]
